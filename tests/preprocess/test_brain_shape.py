"""The brain's geometry in a localiser's probability maps (service.preprocess.brain_shape), on
generated maps: one component, waists, holes, the volume's plausibility."""

from __future__ import annotations

import numpy as np
from scipy import ndimage

from service.preprocess.brain_shape import brain_from_probabilities, cut_at_waists, fill_holes_in_plane, plausibility
from tests.support.phantoms import ellipsoid_brain_maps


def test_the_geometry_keeps_one_connected_brain_with_its_holes_filled() -> None:
    p = np.zeros((8, 40, 40), np.float32)
    disc = np.hypot(*np.mgrid[-15:25, -15:25]) <= 11
    p[1:7, disc] = 0.9
    p[3, 12:16, 12:16] = 0.1                                       # a hole (a dark ventricle, say)
    p[2:4, 30:36, 30:36] = 0.8                                     # a smaller, separate blob
    brain, confidence = brain_from_probabilities(p, voxel_ml=0.1)             # 230 ml: plausible
    assert brain[3, 13, 13] and not brain[2, 32, 32]
    assert brain.sum() == 6 * disc.sum() and 0.8 < confidence < 0.9       # 0.9 sure, 97 % of the mass


def test_a_brain_leaking_through_a_thin_bridge_loses_what_lies_beyond_it() -> None:
    p = ellipsoid_brain_maps(24)
    p[16:] = 0.0                                                    # the brain ends at slice 15
    p[16, 32:35, 32:35] = 0.8                                       # a bridge of one slice, then a blob beside it
    p[17:22, 33:46, 33:46] = 0.8                                    # (the fetal neck and body, say)
    brain, _ = brain_from_probabilities(p, voxel_ml=0.1)
    assert brain[:16].sum() == (p[:16] >= 0.5).sum() and not brain[16:].any()
    whole = brain_from_probabilities(p, voxel_ml=0.1)[0] | (p >= 0.5)
    assert cut_at_waists(whole, p).sum() == brain.sum()


def test_a_poor_slice_through_the_middle_of_a_brain_cuts_nothing() -> None:
    p = ellipsoid_brain_maps(24)
    p[6] = np.where(p[6] > 0, 0.0, 0.0)                             # a slice the network barely sees
    p[6, 18:21, 18:21] = 0.9
    component = p >= 0.5
    assert np.array_equal(cut_at_waists(component, p), component)  # its neighbours overlap: one brain


def test_no_brain_or_an_implausible_one_gives_a_low_confidence() -> None:
    brain, confidence = brain_from_probabilities(np.full((5, 20, 20), 0.2, np.float32), voxel_ml=1.0)
    assert not brain.any() and confidence == 0.0
    everything = np.full((20, 60, 60), 0.95, np.float32)          # 72 l: no fetal brain is that large
    _, confidence = brain_from_probabilities(everything, voxel_ml=1.0)
    assert confidence == 0.0
    tiny = np.zeros((5, 20, 20), np.float32)
    tiny[2, 5:7, 5:7] = 0.99                                       # 4 ml
    assert brain_from_probabilities(tiny, voxel_ml=1.0)[0].sum() == 0


def test_plausible_volumes_span_the_second_and_third_trimester() -> None:
    assert plausibility(60.0) == plausibility(450.0) == 1.0
    assert 0 < plausibility(20.0) < 1 and 0 < plausibility(1200.0) < 1
    assert plausibility(5.0) == plausibility(5000.0) == 0.0


def test_holes_are_filled_slice_by_slice_not_through_the_stack() -> None:
    m = np.zeros((5, 20, 20), bool)
    m[1:4, 3:15, 3:15] = True
    m[1:4, 7:10, 7:10] = False                      # a tube through three slices: a hole in each of them
    m[0, 2:6, 2:6] = True
    m[0, 3:5, 3:5] = False                          # a hole in the first slice, at the array's face
    m[4, 10:18, 10:18] = True
    m[4, 12:16, 18 - 1] = False                     # a notch open to the side: no hole
    out = fill_holes_in_plane(m)
    assert out[1:4, 7:10, 7:10].all() and out[0, 3:5, 3:5].all()
    assert not out[4, 12:16, 17].any()
    assert np.array_equal(out | m, out) and int(out.sum() - m.sum()) == 3 * 9 + 4
    assert np.array_equal(out, np.stack([ndimage.binary_fill_holes(s) for s in m]))
    assert not fill_holes_in_plane(np.zeros((3, 4, 4), bool)).any()


def test_a_bridge_of_several_small_slices_is_a_waist_though_they_overlap() -> None:
    """The face below a brain, joined to it through four small slices that overlap one another (and
    the large slices on either side): each bridge slice's neighbours overlap, the run of them is
    still a bridge, cut at its narrowest slice (all alike: the first)."""
    p = np.zeros((28, 48, 48), np.float32)
    p[12:] = ellipsoid_brain_maps(18)[:16]                              # the brain from slice 13 on
    p[9:13, 20:24, 18:22] = 0.8                                     # slices 9-12: a narrow bridge
    p[2:9, 12:30, 10:28] = 0.8                                      # slices 2-8: the face, as wide as the brain
    whole = (p >= 0.5) & (ndimage.label(p >= 0.5, structure=np.ones((3, 3, 3)))[0] == 1)
    assert whole[2:9].any() and whole[13:].any()                    # one component
    kept = cut_at_waists(whole, p)
    assert not kept[:10].any() and np.array_equal(kept[10:], whole[10:])   # cut at the bridge's first slice


def test_bits_of_a_body_beyond_a_brains_last_slice_are_cut_and_a_narrowing_cap_is_not() -> None:
    """A brain whose component runs on, past a slice of a few pixels, through small bits of a fetal
    body that do not narrow towards the stack's end: cut at the dip. The brain alone, whose caps
    narrow to their last slices, keeps every slice."""
    brain = ellipsoid_brain_maps(24)
    assert np.array_equal(cut_at_waists(brain >= 0.5, brain), brain >= 0.5)
    p = np.zeros((30, 48, 48), np.float32)
    p[:24] = brain
    last = int(np.flatnonzero((brain >= 0.5).any(axis=(1, 2)))[-1])
    p[last + 1, 22:24, 22:24] = 0.7                                 # a dip of 4 pixels
    for k, (r, c) in enumerate([(20, 20), (21, 23), (23, 21), (22, 24)]):
        p[last + 2 + k, r:r + 4, c:c + 4] = 0.7                     # bits of 16 pixels, wandering
    component = (p >= 0.5) & (ndimage.label(p >= 0.5, structure=np.ones((3, 3, 3)))[0] == 1)
    assert component[last + 5].any()                                # one component
    kept = cut_at_waists(component, p)
    assert np.array_equal(kept[:last + 1], component[:last + 1]) and not kept[last + 1:].any()


def test_a_face_past_the_skull_base_is_cut_though_the_slices_beside_the_thin_one_overlap() -> None:
    """A face of three slices as wide as the brain's middle, past a thin slice, then a narrow skull
    base that lies inside the face's outline (so the slices beside the thin one overlap): the
    component widens again past the thin slice, which no cap does: cut there."""
    p = np.zeros((26, 48, 48), np.float32)
    p[8:] = ellipsoid_brain_maps(20)[1:19]                          # the brain from slice 8 on
    p[4:7, 10:30, 8:28] = 0.8                                       # slices 4-6: the face
    p[7, 18:21, 16:19] = 0.8                                        # slice 7: thin, inside both
    component = (p >= 0.5) & (ndimage.label(p >= 0.5, structure=np.ones((3, 3, 3)))[0] == 1)
    assert component[4].any() and (component[6] & component[8]).sum() == component[8].sum()
    kept = cut_at_waists(component, p)
    assert not kept[:8].any() and np.array_equal(kept[8:], component[8:])


def test_a_poor_slice_beside_a_partly_seen_one_keeps_its_cap() -> None:
    """A poor slice, and the slice after it seen in part: the cap before them narrows away from
    them, as caps do, and is kept, as is a cap past a poor slice second from the end."""
    for k in (5, 8):
        p = ellipsoid_brain_maps(24)
        p[k] = 0.0
        p[k, 18:21, 18:21] = 0.9
        inside = np.argwhere(p[k + 1] > 0)
        p[k + 1] = 0.0
        p[k + 1][tuple(inside[: int(0.6 * len(inside))].T)] = 0.9
        component = p >= 0.5
        assert np.array_equal(cut_at_waists(component, p), component), k
    p = ellipsoid_brain_maps(24)
    p[21] = 0.0
    p[21, 20, 20] = 0.9                                             # second from the last slice (22)
    component = (p >= 0.5) & (ndimage.label(p >= 0.5, structure=np.ones((3, 3, 3)))[0] == 1)
    assert np.array_equal(cut_at_waists(component, p), component)


def test_two_poor_slices_through_the_middle_of_a_brain_cut_nothing() -> None:
    p = ellipsoid_brain_maps(24)
    p[10:12] = 0.0
    p[10:12, 18:21, 18:21] = 0.9                                    # two slices the network barely sees
    component = p >= 0.5
    assert np.array_equal(cut_at_waists(component, p), component)  # both sides hold most of the brain


def test_a_slice_the_network_sees_no_brain_in_does_not_cut_the_brain_in_two() -> None:
    """A slice a signal void darkened over the brain holds no brain for the network: both halves stay
    one brain (the slice without a mask), where a blob past the brain's end beyond an empty slice, or
    a small one over it, does not join it."""
    p = ellipsoid_brain_maps(24)
    rows = np.flatnonzero(p.reshape(len(p), -1).max(1) >= 0.5)
    middle = (rows[0] + rows[-1]) // 2
    seen = p >= 0.5
    p[middle] = 0.0
    brain, _ = brain_from_probabilities(p, voxel_ml=0.1)
    assert not brain[middle].any()
    assert brain.sum() == seen.sum() - seen[middle].sum()              # both halves, every pixel they hold
    q = ellipsoid_brain_maps(24)
    q[16:] = 0.0                                                          # the brain ends at slice 15; slice 16
    q[17:19] = np.where(q[15] >= 0.5, 0.8, 0.0)                           # empty, then a blob over its last slice
    brain, _ = brain_from_probabilities(q, voxel_ml=0.1)
    assert brain[15].any() and not brain[16:].any()


def test_two_slices_the_network_sees_no_brain_in_do_not_cut_the_brain_in_two() -> None:
    """Neighbouring slices of an interleaved stack are acquired apart in time, and two of them can be
    darkened: both halves stay one brain, the two slices without a mask (before, a run of two kept
    the larger half alone)."""
    p = ellipsoid_brain_maps(24)
    seen = p >= 0.5
    p[10:12] = 0.0
    brain, _ = brain_from_probabilities(p, voxel_ml=0.1)
    assert not brain[10:12].any()
    assert brain.sum() == seen.sum() - seen[10:12].sum()


def test_a_lateral_part_past_a_poor_and_an_unseen_slice_stays_with_its_brain() -> None:
    """The brain's component ends in a slice the network barely sees, the next it does not see, and
    the four slices beyond (under a third of the brain, on the wide slice's place) are the brain's
    side: a sagittal stack whose head lies turned in the picture (the shared scan's, at 30 deg:
    Dice 0.777 -> 0.853). A blob of one or two slices there is still no part of it (the test above)."""
    p = ellipsoid_brain_maps(24)
    seen = p >= 0.5
    p[17] = 0.0
    p[17, 20:22, 20:22] = 0.9                                       # barely seen
    p[18] = 0.0                                                     # not seen
    brain, _ = brain_from_probabilities(p, voxel_ml=0.1)
    assert brain[19:].sum() == seen[19:].sum() > 0
    assert not brain[17:19].any()
