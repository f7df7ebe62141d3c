"""Synthetic whole-uterus stacks: reproducible, with a brain of the head's size where it was put,
and surroundings that differ between the two styles."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import ndimage

from model_export.localiser import surroundings
from model_export.localiser.scenes import HeadModel, StackGeometry, synth_scene, synth_stack
from tests.support.phantoms import phantom_brain


@pytest.fixture
def small_fields(monkeypatch: pytest.MonkeyPatch) -> None:
    """Stacks of at most 200 mm fields of view and pixels of at least 1.4 mm (each geometry drawn as
    usual, then cut down): for the tests whose checks hold on any field of view that holds the head,
    a third to a sixth of the pixels."""
    drawn = StackGeometry.draw.__func__

    def smaller(cls: type, rng: np.random.Generator) -> StackGeometry:
        geo = drawn(cls, rng)
        pixel = max(geo.pixel_mm, 1.4)
        return StackGeometry(pixel, int(min(geo.size * geo.pixel_mm, 200.0) / pixel), geo.thickness_mm, geo.gap_mm,
                             geo.slices)

    monkeypatch.setattr(StackGeometry, "draw", classmethod(smaller))


@pytest.fixture(scope="module")
def head() -> HeadModel:
    image, mask, affine = phantom_brain(3)
    return HeadModel.from_arrays(image, mask, affine)


def test_the_head_model_knows_the_brain_inside_and_out(head: HeadModel) -> None:
    assert head.sdf.min() < -20 and head.sdf.max() > 5            # mm: deep inside, well outside
    assert 30 < head.radius_mm < 45                                 # the phantom's largest radius is 38 mm +- 5 %
    assert float(head.t2.max()) <= 1.5 and float(head.t2.min()) >= 0


def test_a_seed_gives_the_same_stack(head: HeadModel, small_fields: None) -> None:
    a, ma = synth_stack(head, np.random.default_rng(4))
    b, mb = synth_stack(head, np.random.default_rng(4))
    assert np.array_equal(a.array, b.array) and np.array_equal(ma, mb)
    c, _ = synth_stack(head, np.random.default_rng(5))
    assert c.array.shape != a.array.shape or not np.allclose(c.array, a.array)


@pytest.mark.parametrize("style", ["train", "heldout"])
def test_the_stack_is_whole_uterus_with_a_brain_of_plausible_volume(head: HeadModel, style: str) -> None:
    for seed in range(3):
        rng = np.random.default_rng(seed)
        vol, mask = synth_stack(head, rng, style)
        fov = vol.array.shape[0] * vol.spacing[0]
        assert 125 <= fov <= 405 and vol.array.shape[0] == vol.array.shape[1]
        assert 0.85 <= vol.spacing[0] <= 1.65 and 1.6 <= vol.spacing[2] <= 5.2
        ml = mask.sum() * np.prod(vol.spacing) / 1e3
        brain_ml = (head.sdf <= 0).sum() * 1.6 ** 3 / 1e3
        # the mask is the skull's inside: the brain plus 1-3.5 mm of CSF, scaled by 0.9-1.1, cut by the slab
        assert 0.1 * brain_ml < ml < 2.0 * brain_ml, (ml, brain_ml)
        assert mask.mean() < 0.1                                        # most of the field of view is not brain
        inside, outside = vol.array[mask].mean(), vol.array[~mask].mean()
        assert np.isfinite(inside) and np.isfinite(outside) and vol.array.min() >= 0


def test_the_styles_differ_around_the_same_head(head: HeadModel, small_fields: None) -> None:
    a, _ = synth_stack(head, np.random.default_rng(7), "train")
    b, _ = synth_stack(head, np.random.default_rng(7), "heldout")
    assert a.array.shape == b.array.shape                       # the same geometry draw ...
    assert not np.allclose(a.array / a.array.max(), b.array / b.array.max(), atol=0.05)   # ... other scenes
    with pytest.raises(ValueError, match="style"):
        synth_stack(head, np.random.default_rng(0), "other")


def test_geometry_draws_cover_the_scanners_ranges() -> None:
    draws = [StackGeometry.draw(np.random.default_rng(s)) for s in range(200)]
    pixels = np.array([g.pixel_mm for g in draws])
    fovs = np.array([g.size * g.pixel_mm for g in draws])
    assert pixels.min() < 1.0 and pixels.max() > 1.5
    assert fovs.min() < 160 and fovs.max() > 380 and np.mean(fovs >= 250) > 0.8
    assert min(g.thickness_mm for g in draws) < 2.3 and max(g.thickness_mm for g in draws) > 4.2


def test_some_heads_sit_at_the_uterine_wall_without_a_fluid_rim(monkeypatch: pytest.MonkeyPatch) -> None:
    """Around where the head goes (a shell 5-15 mm outside it), amniotic fluid is the rule when no
    head is engaged and the exception when every head is."""
    tissue = {"fluid": 1.0, "csf": 1.0, "skull": 0.05, "scalp": 0.3, "body": 0.3, "wall": 0.3, "placenta": 0.4,
              "fat": 0.6, "air": 0.0}

    def fluid_share(engaged: float) -> float:
        monkeypatch.setitem(surroundings.ENGAGED_SHARE, "train", engaged)
        shares = []
        for seed in range(6):
            rng = np.random.default_rng(seed)
            geo = StackGeometry(1.2, 250, 3.0, 3.0, 30)
            image = surroundings.draw_surroundings(rng, geo, np.zeros(3), 40.0, tissue, "train")
            r = np.linalg.norm(geo.coordinates(step=2), axis=-1)
            shell = (r > 45.0) & (r < 55.0)
            shares.append(float((np.abs(image[shell] - 1.0) < 0.15).mean()))
        return float(np.mean(shares))

    assert fluid_share(0.0) > 0.5 and fluid_share(1.0) < 0.6 * fluid_share(0.0)


@pytest.mark.parametrize(("motion", "planned"), [(None, False), ("independent", False), ("mild", True)])
def test_a_rigid_scene_knows_each_slice_pose_in_the_atlas(small_fields: None, motion: str | None, planned: bool) -> None:
    """The atlas brain mask sampled at each slice's true pose is the scene's brain in that slice; the
    skull-inside mask holds the brain; and the head moved between slices (by the generator's drift,
    or as the pose benchmarks' independent motion moves it); the same for a stack planned coronal to
    the head (``orientation``)."""
    from model_export.acquisitions import stack_axes

    from scipy import ndimage

    from model_export.localiser.scenes import synth_scene

    image, mask, affine = phantom_brain(3)
    affine = affine.copy()
    affine[:3, 3] = [-40.0, 25.0, 7.0]                   # an atlas whose world origin is not its corner
    head = HeadModel.from_arrays(image, mask, affine)
    orientation = stack_axes("coronal", np.random.default_rng(2)).T if planned else None
    scene = synth_scene(head, np.random.default_rng(11), "heldout", rigid=True, motion=motion, orientation=orientation)
    assert scene.atlas_from_voxel is not None and len(scene.atlas_from_voxel) == scene.volume.array.shape[2]
    assert np.allclose(np.linalg.det(scene.atlas_from_voxel[:, :3, :3]), np.prod(scene.volume.spacing))   # rigid
    assert (scene.brain <= scene.mask).all() and scene.mask.sum() > scene.brain.sum() > 0
    nx, ny, n = scene.volume.array.shape
    i, j = np.meshgrid(np.arange(nx), np.arange(ny), indexing="ij")
    found = []
    for k in np.flatnonzero(scene.brain.any((0, 1))):
        voxel = np.stack([i.ravel(), j.ravel(), np.full(i.size, k), np.ones(i.size)])
        atlas_voxel = np.linalg.solve(affine, scene.atlas_from_voxel[k] @ voxel)[:3]
        sampled = ndimage.map_coordinates(mask.astype(np.float32), atlas_voxel, order=1).reshape(nx, ny) >= 0.5
        found.append((sampled & scene.brain[:, :, k]).sum() * 2 / (sampled.sum() + scene.brain[:, :, k].sum()))
    assert np.median(found) > 0.9, found
    moved = np.abs(np.diff(scene.atlas_from_voxel[:, :3, 3], axis=0)).max()
    assert moved > 0.1
    assert synth_scene(head, np.random.default_rng(11), "heldout").atlas_from_voxel is None   # scaled: no pose


def test_camouflaged_heads_sit_in_tissue_as_bright_as_the_brain(head: HeadModel, monkeypatch: pytest.MonkeyPatch, small_fields: None) -> None:
    """With every head camouflaged, the tissue 11-15 mm outside the skull's inside is about as bright as
    the brain; without, it is mostly amniotic fluid (T2-like contrast, no engaged heads)."""
    from scipy import ndimage

    from model_export.localiser import scenes

    monkeypatch.setitem(surroundings.ENGAGED_SHARE, "train", 0.0)

    def ring_over_brain(share: float) -> float:
        monkeypatch.setitem(scenes.CAMOUFLAGE_SHARE, "train", share)
        ratios = []
        for seed in range(4):                   # medians 0.11 and 0.89 in small fields (0.11 and 0.90 in whole ones)
            scene = scenes.synth_scene(head, np.random.default_rng(seed), "train", random_contrast=False)
            px = float(scene.volume.spacing[0])
            plane = np.zeros((3, 3, 3), bool)
            plane[:, :, 1] = ndimage.generate_binary_structure(2, 1)
            near = ndimage.binary_dilation(scene.mask, plane, iterations=int(11 / px))
            ring = ndimage.binary_dilation(scene.mask, plane, iterations=int(15 / px)) & ~near
            image = scene.volume.array
            ratios.append(abs(np.log(np.median(image[ring]) / np.median(image[scene.brain]))))
        return float(np.median(ratios))

    assert ring_over_brain(1.0) < 0.35 < ring_over_brain(0.0)


def test_a_face_lies_in_front_of_and_below_the_brain_outside_the_skull(head: HeadModel) -> None:
    """The eyes: a left-right pair in front of and below the brain's centre, outside the skull's
    outer surface, rendered at the fluid-bright eye level inside the face."""
    from scipy import ndimage

    from model_export.localiser import scenes

    for seed in range(4):
        rng = np.random.default_rng(seed)
        tissue = surroundings.intensities(rng, False)
        face = scenes.Face.draw(rng, head, tissue, 0.5, 5.0, "train")
        assert (face.eyes[:, 1] > 0).all() and (face.eyes[:, 2] < 0).all()
        assert np.isclose(face.eyes[0, 0], -face.eyes[1, 0]) and face.eyes[1, 0] > 0
        vox = face.eyes @ head.voxel_from_mm[:3, :3].T + head.voxel_from_mm[:3, 3]
        assert (ndimage.map_coordinates(head.sdf, vox.T, order=1) >= 5.0 + 0.6 * face.eye_radius - 1e-3).all()
        values, where = face.render(face.eyes)
        assert where.all() and np.allclose(values, face.eye_level) and face.eye_level > 0.5
        assert face.reach_mm > head.radius_mm * 0.8


def test_training_faces_are_as_bright_as_the_body_and_held_out_ones_also_as_the_brain(head: HeadModel) -> None:
    """Training faces take the fetal body's tissue level (so that brain-like tissue beside a head is
    never taught to be a face); held-out faces also take the brain's, half of the time."""
    from model_export.localiser import scenes

    def brain_like(style: str) -> list[bool]:
        out = []
        for seed in range(40):
            rng = np.random.default_rng(seed)
            tissue = surroundings.intensities(rng, False)
            tissue["body"] = 0.2                                       # far below the brain's level
            face = scenes.Face.draw(rng, head, tissue, 0.8, 5.0, style)
            assert 0.2 * 0.8 <= face.tissue_level <= 0.8 * 1.2
            out.append(face.tissue_level > 0.2 * 1.5)
        return out

    assert not any(brain_like("train"))
    assert 0.25 < np.mean(brain_like("heldout")) < 0.75


def test_a_scene_with_a_face_has_it_outside_the_mask_and_the_same_mask(head: HeadModel, monkeypatch: pytest.MonkeyPatch, small_fields: None) -> None:
    """The face changes the image outside the skull only: the same seed with and without faces gives
    the same skull-inside mask, and images that differ outside it."""
    from model_export.localiser import scenes

    for seed in range(3):
        monkeypatch.setitem(scenes.FACE_SHARE, "train", 1.0)
        with_face = scenes.synth_scene(head, np.random.default_rng(seed), "train", random_contrast=False)
        monkeypatch.setitem(scenes.FACE_SHARE, "train", 0.0)
        without = scenes.synth_scene(head, np.random.default_rng(seed), "train", random_contrast=False)
        assert with_face.mask.shape == without.mask.shape
        assert np.array_equal(with_face.mask, without.mask)
        assert not np.allclose(with_face.volume.array[~with_face.mask], without.volume.array[~without.mask])


def test_a_rigid_scene_shows_its_eyes_where_its_true_poses_put_them(monkeypatch: pytest.MonkeyPatch, small_fields: None) -> None:
    """The face's eye centres (head frame) carried through the atlas and a rigid scene's true slice
    poses into the stack land on fluid-bright eyes: brighter than the face between them. This checks
    the face's frame (the head model's) against the frame the scene's truth is written in."""
    from model_export.localiser import scenes

    image, mask, affine = phantom_brain(3)
    head = HeadModel.from_arrays(image, mask, affine)
    monkeypatch.setitem(scenes.FACE_SHARE, "train", 1.0)
    monkeypatch.setitem(surroundings.ENGAGED_SHARE, "train", 0.0)
    monkeypatch.setitem(scenes.CAMOUFLAGE_SHARE, "train", 0.0)
    drawn = []
    original = scenes.Face.draw.__func__
    monkeypatch.setattr(scenes.Face, "draw", classmethod(lambda cls, *a: drawn.append(original(cls, *a)) or drawn[-1]))
    atlas_from_head = head.atlas_from_voxel @ head.voxel_from_mm

    def value(scene: scenes.Scene, head_point: np.ndarray) -> float:
        """The stack's intensity at a head-frame point, in the slice whose true pose holds it (NaN: none)."""
        vox = np.einsum("kij,j->ki", np.linalg.inv(scene.atlas_from_voxel), atlas_from_head @ np.r_[head_point, 1.0])
        k = int(np.argmin(np.abs(vox[:, 2] - np.arange(len(vox)))))
        i, j = np.round(vox[k, :2]).astype(int)
        shape = scene.volume.array.shape
        return float(scene.volume.array[i, j, k]) if abs(vox[k, 2] - k) < 0.5 and 0 <= i < shape[0] \
            and 0 <= j < shape[1] else np.nan

    brighter = []
    for seed in range(6):
        scene = synth_scene(head, np.random.default_rng(seed), "train", random_contrast=False, rigid=True)
        face = drawn[-1]
        between = value(scene, face.eyes.mean(axis=0))
        brighter += [value(scene, eye) > between for eye in face.eyes if np.isfinite(value(scene, eye) - between)]
    assert len(brighter) >= 4 and np.mean(brighter) >= 0.8, brighter


def test_a_wider_csf_layer_widens_the_skull_inside_and_changes_nothing_else(head: HeadModel, small_fields: None) -> None:
    """The same seed with the CSF layer set to 1 and to 6 mm: the same brain, a larger skull-inside mask."""
    thin = synth_scene(head, np.random.default_rng(7), "heldout", random_contrast=False, csf_mm=1.0)
    wide = synth_scene(head, np.random.default_rng(7), "heldout", random_contrast=False, csf_mm=6.0)
    assert np.array_equal(thin.brain, wide.brain)
    assert wide.mask.sum() > 1.2 * thin.mask.sum() and np.all(wide.mask[thin.mask])


def test_csf_patches_widen_the_skull_inside_in_places_and_keep_the_brain(head: HeadModel, small_fields: None) -> None:
    """The same seed with and without CSF patches of up to 8 mm: the same brain, a skull-inside mask
    that holds the even layer's and more, by less than the 8 mm all round would add."""
    even = synth_scene(head, np.random.default_rng(7), "heldout", random_contrast=False, csf_mm=2.0)
    patchy = synth_scene(head, np.random.default_rng(7), "heldout", random_contrast=False, csf_mm=2.0, csf_patches_mm=8.0)
    wide = synth_scene(head, np.random.default_rng(7), "heldout", random_contrast=False, csf_mm=10.0)
    assert np.array_equal(even.brain, patchy.brain)
    assert np.all(patchy.mask[even.mask]) and np.all(wide.mask[patchy.mask])
    grown, all_round = patchy.mask.sum() - even.mask.sum(), wide.mask.sum() - even.mask.sum()
    assert 0.1 * all_round < grown < 0.7 * all_round


def test_a_faint_skull_brightens_the_skull_and_keeps_the_scene(head: HeadModel, small_fields: None) -> None:
    """The same seed with every skull faint: the same brain and skull-inside mask, the same picture
    inside it; just outside it (where the skull is), brighter."""
    plain = synth_scene(head, np.random.default_rng(7), "heldout", random_contrast=False)
    faint = synth_scene(head, np.random.default_rng(7), "heldout", random_contrast=False, faint_skull_share=1.0)
    assert np.array_equal(plain.brain, faint.brain) and np.array_equal(plain.mask, faint.mask)
    deep = ndimage.binary_erosion(plain.mask, np.ones((5, 5, 1), bool))
    np.testing.assert_allclose(faint.volume.array[deep], plain.volume.array[deep], rtol=0.05)
    rim = ndimage.binary_dilation(plain.mask, np.ones((3, 3, 1), bool)) & ~plain.mask
    assert np.median(faint.volume.array[rim]) > 1.5 * np.median(plain.volume.array[rim])


def test_a_shaded_scene_darkens_its_head_and_keeps_its_masks(head: HeadModel, small_fields: None) -> None:
    """With ``shading_share`` 1 every scene has a dark region over its head: the same head and masks
    as the same seed without it (every draw of the scene comes before the shading's), and inside the
    skull a lower median intensity relative to the stack's, for each seed; at share 0 a seed gives
    the stack it gave before the option existed (nothing drawn for it)."""
    darker, plain_of = [], {}
    for seed in range(2):
        plain = plain_of[seed] = synth_scene(head, np.random.default_rng(seed), "train")
        shaded = synth_scene(head, np.random.default_rng(seed), "train", shading_share=1.0)
        assert np.array_equal(plain.mask, shaded.mask) and np.array_equal(plain.brain, shaded.brain)

        def head_level(scene) -> float:  # noqa: ANN001
            return float(np.median(scene.volume.array[scene.mask]) / np.median(scene.volume.array))

        darker.append(head_level(shaded) < head_level(plain))
    assert all(darker)
    again = synth_scene(head, np.random.default_rng(0), "train", shading_share=0.0)
    np.testing.assert_array_equal(again.volume.array, plain_of[0].volume.array)


def test_the_shading_field_is_darkest_near_the_head_and_one_far_from_it() -> None:
    geo = StackGeometry(2.0, 150, 3.0, 3.0, 30)
    head_centre = np.array([20.0, -10.0, 0.0])
    for seed in range(5):
        gain = surroundings.shading(np.random.default_rng(seed), geo, head_centre, 40.0)
        pts = geo.coordinates()
        near = np.linalg.norm(pts - head_centre, axis=-1) < 40.0
        assert 0.19 < gain.min() < 0.75 and gain.max() <= 1.0
        assert gain[near].min() == pytest.approx(gain.min())                # the darkest point lies on the head
        assert gain[np.linalg.norm(pts - head_centre, axis=-1) > 220.0].min() > 0.95


def test_a_scene_can_move_its_head_as_the_pose_benchmarks_levels_do(small_fields: None) -> None:
    """``motion`` changes only the head's motion: the same seed gives the same surroundings; with
    independent motion neighbouring slices turn against each other by a median of over 8 deg
    (uniform up to 20 deg each), with mild motion by at most twice its 5 deg, where the generator's
    own drift turns them by a few; an unknown level is refused."""
    image, mask, affine = phantom_brain(3)
    head = HeadModel.from_arrays(image, mask, affine)

    def scene(motion: str | None):  # noqa: ANN202
        return synth_scene(head, np.random.default_rng(12), "heldout", rigid=True, motion=motion)

    def neighbours_turn_deg(moving) -> np.ndarray:  # noqa: ANN001
        a = moving.atlas_from_voxel[:, :3, :3]
        rot = a / np.linalg.norm(a, axis=1)[:, None, :]
        rel = np.einsum("nji,njk->nik", rot[:-1], rot[1:])
        return np.degrees(np.arccos(np.clip((np.trace(rel, axis1=1, axis2=2) - 1) / 2, -1, 1)))

    own, mild, independent = scene(None), scene("mild"), scene("independent")
    changed = own.volume.array != independent.volume.array
    to_heads = ndimage.distance_transform_edt(~(own.mask | independent.mask), sampling=own.volume.spacing)
    assert changed.any() and to_heads[changed].max() < 30.0         # the head (and its scalp) alone moved
    assert np.median(neighbours_turn_deg(independent)) > 8.0 > np.median(neighbours_turn_deg(own))
    assert neighbours_turn_deg(mild).max() <= 10.0 + 1e-6
    with pytest.raises(ValueError, match="motion"):
        synth_scene(head, np.random.default_rng(12), "heldout", motion="extreme")


def test_a_stack_planned_about_the_head_cuts_it_in_that_plane_and_keeps_the_scene(small_fields: None) -> None:
    """``orientation`` sets the head's axes in the stack: a stack planned sagittal to the head has its
    slice normal along the atlas's left-right axis in every slice's true pose (within the planning's
    tilt and the head's mild motion), an axial one along inferior-superior; every other draw stays
    the seed's (the same field of view, slices and look; the fetal body follows the head's neck)."""
    from model_export.acquisitions import stack_axes

    image, mask, affine = phantom_brain(3)
    head = HeadModel.from_arrays(image, mask, affine)

    def normals(scene) -> np.ndarray:  # noqa: ANN001
        n = scene.atlas_from_voxel[:, :3, 2]
        return np.abs(n / np.linalg.norm(n, axis=1, keepdims=True))

    drawn = synth_scene(head, np.random.default_rng(13), "heldout", rigid=True, motion="mild")
    for plane, axis in (("sagittal", 0), ("axial", 2)):
        axes = stack_axes(plane, np.random.default_rng(1))
        planned = synth_scene(head, np.random.default_rng(13), "heldout", rigid=True, motion="mild",
                              orientation=axes.T)
        assert np.all(normals(planned)[:, axis] > np.cos(np.radians(35.0))), normals(planned)
        assert planned.volume.array.shape == drawn.volume.array.shape and planned.look == drawn.look
        assert np.allclose(planned.volume.affine, drawn.volume.affine)
        assert not np.all(normals(drawn)[:, axis] > np.cos(np.radians(35.0)))        # drawn: another plane
