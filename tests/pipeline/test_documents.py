"""A prediction's JSON documents state each slice's pose in every form the contract names, and they
agree with one another and with the pose the pipeline holds; a stack's geometry is its file's."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from service.geometry import anchors
from service.inference.estimator import PoseEstimate
from service.io.volume import Volume
from service.pipeline import predict
from service.pipeline.documents import stack_objects
from service.pipeline.prepare import StackUpload, prepare_stack
from tests.api.conftest import INFO
from tests.support.phantoms import acquire_stack, phantom_brain, stack_affine


def _answer(seed: int = 5) -> tuple[dict, np.ndarray, object, np.ndarray]:
    """The stack object of a phantom stack whose slices get random poses (their truth), the stack
    consistency stage off so that the answer keeps them; the truth, the prediction and the affine."""
    image, mask, affine = phantom_brain(seed)
    shape = (40, 44, 12)
    tilt = Rotation.from_euler("xy", [25, -30], degrees=True).as_matrix()
    aff = stack_affine(2, tilt, 1.5, 3.0, shape)
    img, msk = acquire_stack(image, mask, affine, aff, shape, 2, np.broadcast_to(np.eye(4), (12, 4, 4)))
    upload = StackUpload("oblique.nii.gz", Volume((img * 3 + 20).astype(np.float32), aff),
                         Volume(msk.astype(np.uint8), aff), "mask.nii.gz")
    stack = prepare_stack(upload, INFO, bias_correction=False)
    n = len(stack.prepared.inputs)
    rng = np.random.default_rng(seed)
    truth = np.repeat(np.eye(4)[None], n, 0)
    truth[:, :3, :3] = Rotation.random(n, random_state=seed).as_matrix()
    truth[:, :3, 3] = rng.uniform(-30, 30, (n, 3))
    estimate = PoseEstimate(truth, np.full(n, 5.0), np.zeros(n, bool), np.zeros(n), np.full(n, 1.0))
    predictions, _ = predict.predict_from_estimates([stack], [estimate], INFO, INFO.variance_threshold,
                                                    stack_consistency=False)
    return stack_objects(predictions)[0], truth, predictions[0], aff


def test_every_form_of_a_slice_pose_is_the_same_pose() -> None:
    body, truth, prediction, _ = _answer()
    assert [s["index"] for s in body["slices"]] == list(range(len(truth)))
    for s, true, frame in zip(body["slices"], truth, prediction.network_from_voxel):
        rotation = np.array(s["rotation"])
        np.testing.assert_allclose(rotation, true[:3, :3], atol=1e-9)
        np.testing.assert_allclose(s["translation_mm"], true[:3, 3], atol=1e-9)
        w, x, y, z = s["quaternion_wxyz"]
        assert w >= 0                                                        # the canonical sign
        np.testing.assert_allclose(Rotation.from_quat([x, y, z, w]).as_matrix(), rotation, atol=1e-9)
        np.testing.assert_allclose(Rotation.from_rotvec(s["rotation_vector"]).as_matrix(), rotation, atol=1e-9)
        np.testing.assert_allclose(anchors.decode(np.array(s["anchor_points_mm"]).ravel()), true, atol=1e-6)
        np.testing.assert_allclose(s["atlas_from_voxel"], true @ frame, atol=1e-9)
        assert s["branch"] == "network" and s["twin_mass"] == 0.0


def test_a_stack_object_states_the_geometry_its_file_gave() -> None:
    body, _, _, aff = _answer()
    assert body["index"] == 0 and body["filename"] == "oblique.nii.gz"
    assert body["shape"] == [40, 44, 12] and body["slice_axis"] == 2
    np.testing.assert_allclose(body["scanner_from_voxel"], aff)
    np.testing.assert_allclose(body["spacing_mm"], [1.5, 1.5, 3.0])
    assert body["consistency"] is None                                      # the stage was off
    assert body["localisation"]["method"] == "mask"
