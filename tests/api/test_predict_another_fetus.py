"""A stack of another fetus among a request's stacks: left out of what the request decides together."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from service.geometry.pose import translate
from service.io.volume import Volume
from tests.api.test_predict_geometry import answered, rewritten, stacks_apart, two_still_stacks


def _atlas_from_voxel(stack: dict) -> np.ndarray:
    return np.array([s["atlas_from_voxel"] for s in stack["slices"]])


def test_a_stack_whose_brain_lies_100_mm_away_is_apart_and_changes_nothing_of_the_others(
        oracle, oracle_client, tmp_path: Path) -> None:  # noqa: ANN001
    """Two stacks of a fetus (the network 2-4 deg / mm off per stack, 1 deg / 1 mm per slice) and a
    third whose file places its brain 100 mm from theirs in the scanner (a twin's stack, with its
    mask), the network placing its slices as well as theirs: the third is ``apart_from_request``
    (100 mm), none of its slices accepted; the first two are pooled and refined with each other
    alone, and get the poses they get without it (before, all three were pooled and refined
    together, and the third pulled the others its way)."""
    files, truths = two_still_stacks(tmp_path)
    given = stacks_apart(truths, np.random.default_rng(8), 4.0, 1.0)
    shift = np.array([100.0, 0.0, 0.0])
    twin_files = rewritten(files[2:], tmp_path, "stacks", lambda v: Volume(v.array, translate(shift) @ v.affine))
    twin_files = rewritten(twin_files, tmp_path, "masks", lambda v: Volume(v.array, translate(shift) @ v.affine))
    twin_files = [(field, (f"twin-{name}", data)) for field, (name, data) in twin_files]
    oracle.spread_mm = 3.0
    oracle.truth = given
    (alone,) = answered(oracle_client, [files], bias_correction="false", mc_samples="5")
    oracle.truth = np.concatenate([given, given[len(truths[0]):]])
    (beside,) = answered(oracle_client, [files + twin_files], bias_correction="false", mc_samples="5")
    apart = beside[2]["consistency"]
    assert apart["apart_from_request"] and abs(apart["apart_mm"] - 100.0) < 1.0
    assert apart["stacks_pooled"] is None and apart["image_consistency"] is None
    assert not any(s["accepted"] for s in beside[2]["slices"])
    assert {s["reason"] for s in beside[2]["slices"]} <= {"inconsistent_with_stack", "empty"}
    for here, there in zip(alone, beside[:2]):
        assert not there["consistency"]["apart_from_request"] and there["consistency"]["apart_mm"] is None
        assert there["consistency"]["stacks_pooled"] == 2 and there["consistency"]["image_consistency"]["stacks"] == 2
        np.testing.assert_allclose(_atlas_from_voxel(there), _atlas_from_voxel(here), atol=1e-6)
        assert [s["accepted"] for s in there["slices"]] == [s["accepted"] for s in here["slices"]]


def test_the_uploaded_masks_decide_the_requests_fetus() -> None:
    """A stack sent with its mask of one fetus and two without, in which the localiser kept a brain
    100 mm away (it saw none near the mask's): the user's mask decides, and the two are apart,
    though their confidences together outweigh the mask's (before, the masked stack was)."""
    from types import SimpleNamespace

    from service.pipeline.predict import apart_distances, set_apart

    def stack(x_mm: float, method: str, confidence: float) -> SimpleNamespace:
        mask = np.zeros((10, 10, 4), bool)
        mask[4:6, 4:6, 1:3] = True
        volume = SimpleNamespace(affine=translate(np.array([x_mm, 0.0, 0.0])))
        return SimpleNamespace(localisation=SimpleNamespace(mask=mask, method=method, confidence=confidence),
                               upload=SimpleNamespace(volume=volume))

    prepared = [stack(0.0, "mask", 1.0), stack(100.0, "network", 0.8), stack(100.0, "network", 0.8)]
    outs = [SimpleNamespace(poses=np.zeros((4, 4, 4)), inconsistent=np.zeros(4, bool), apart_mm=np.nan) for _ in prepared]
    set_apart(outs, apart_distances(prepared))
    assert np.isnan(outs[0].apart_mm) and not outs[0].inconsistent.any()
    assert [round(o.apart_mm) for o in outs[1:]] == [100, 100] and all(o.inconsistent.all() for o in outs[1:])
