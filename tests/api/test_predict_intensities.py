"""``/v1/predict`` on stacks stored in unusual units: the network sees what the same stack in ordinary
units shows it."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from fastapi.testclient import TestClient

from service.io.volume import Volume, write_volume
from tests.api.conftest import OracleEstimator
from tests.support.phantoms import acquire_stack, phantom_brain, stack_affine


@pytest.mark.parametrize("bias_correction", ["false", "true"])
def test_a_stack_stored_in_very_small_units_shows_the_network_the_same_slices(
        oracle: OracleEstimator, oracle_client: TestClient, tmp_path: Path, bias_correction: str) -> None:
    """Brain values of about 1e-7 (a float export in other units): the network's inputs are the
    same as for the stack in ordinary units (they were nearly black: a fixed 1e-6 took the slices'
    whole range for none)."""
    shape = (40, 40, 12)
    aff = stack_affine(2, np.eye(3), 1.6, 3.5, shape)
    img, msk = acquire_stack(*phantom_brain(2), aff, shape, 2, np.broadcast_to(np.eye(4), (12, 4, 4)))
    oracle.truth = np.broadcast_to(np.eye(4), (12, 4, 4)).copy()
    write_volume(Volume(msk.astype(np.uint8), aff), tmp_path / "m.nii.gz")
    seen = {}
    for scale in (1.0, 1e-9):
        write_volume(Volume((img * 3 + 20) * np.float32(scale), aff), tmp_path / "s.nii.gz")
        files = [("stacks", ("s.nii.gz", (tmp_path / "s.nii.gz").read_bytes())),
                 ("masks", ("m.nii.gz", (tmp_path / "m.nii.gz").read_bytes()))]
        r = oracle_client.post("/v1/predict", files=files, data={"bias_correction": bias_correction, "mc_samples": "2",
                                                                 "stack_consistency": "false"})
        assert r.status_code == 200, r.text
        seen[scale] = oracle.seen.copy()
    assert seen[1.0].max() == pytest.approx(255.0)
    np.testing.assert_allclose(seen[1e-9], seen[1.0], atol=0.5)


def test_stacks_stored_in_very_small_units_get_the_poses_of_ordinary_units(oracle: OracleEstimator,
                                                                            oracle_client: TestClient,
                                                                            tmp_path: Path) -> None:
    """Two crossing stacks, every stage on (the image stage refines them where they cross): stored
    with brain values of about 1e-9, each slice gets the pose the same stacks in ordinary units get
    (the image stage's slices were scaled by 1e-6 in place of their brain's median, and it moved
    slices by a millimetre and more)."""
    from tests.api.test_predict_geometry import answered, rewritten, stacks_apart, two_still_stacks

    files, truths = two_still_stacks(tmp_path)
    small = rewritten(files, tmp_path, "stacks",
                      lambda v: Volume(v.array.astype(np.float32) * np.float32(1e-9), v.affine))
    poses = []
    for upload in (files, small):
        oracle.truth = stacks_apart(truths, np.random.default_rng(5), 2.5, 0.5)
        oracle.spread_mm = 4.0
        [stacks] = answered(oracle_client, [upload], bias_correction="false", mc_samples="5")
        assert all(st["consistency"]["image_consistency"]["slices_refined"] > 5 for st in stacks)
        poses.append(np.array([s["atlas_from_voxel"] for st in stacks for s in st["slices"]]))
    np.testing.assert_allclose(poses[1], poses[0], atol=1e-3)
