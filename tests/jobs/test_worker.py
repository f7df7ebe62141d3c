"""What a job's run makes of its inputs: the reason it fails with, the masks and model a job given
poses uses, what its own prediction says of stacks without a brain."""

from __future__ import annotations

import numpy as np
import pytest

from service.core.errors import UnusableImage
from service.io.volume import Volume
from service.jobs.worker import job_estimator, predicted_body
from service.pipeline.prepare import StackUpload
from service.preprocess.localise import default_localiser
from tests.api.conftest import tiny_model_path  # noqa: F401 - fixture


def test_the_queues_time_limit_says_so_even_where_a_reader_turned_it_into_its_own_error() -> None:
    from service.core.errors import UnsupportedFile
    from service.jobs.worker import TIMED_OUT, failure_reason

    class JobTimeoutException(Exception):              # RQ's, raised by its alarm wherever the job is
        pass

    try:
        try:
            raise JobTimeoutException("Task exceeded maximum timeout value (1 seconds)")
        except Exception as exc:
            raise UnsupportedFile("stack0.nii.gz: could not be read (corrupt, truncated or inconsistent file)") from exc
    except UnsupportedFile as err:
        assert failure_reason(err) == TIMED_OUT
    assert failure_reason(UnsupportedFile("stack0.nii.gz: could not be read")) == "stack0.nii.gz: could not be read"


def test_a_job_given_poses_reconstructs_the_pixels_a_job_that_predicts_them_does() -> None:
    """With an uploaded mask that holds the CSF, the pixels a job reconstructs from are the pose
    network's (the rim inset), whether it predicts the poses or is given them."""
    from service.inference.model_file import ModelInfo
    from service.io.volume import Volume
    from service.jobs.worker import uploaded_pose_masks
    from service.pipeline.prepare import StackUpload, prepare_stacks
    from tests.support.phantoms import acquire_stack, phantom_brain, stack_affine

    img, msk, aff = phantom_brain(2)
    shape = (64, 64, 20)
    a = stack_affine(2, np.eye(3), 1.2, 3.0, shape)
    stack, mask = acquire_stack(img, msk, aff, a, shape, 2, np.stack([np.eye(4)] * shape[2]))
    up = StackUpload("s.nii.gz", Volume(stack.astype(np.float32), a), Volume((mask > 0.5).astype(np.uint8), a),
                     "m.nii.gz", mask_holds_csf=True)
    info = ModelInfo(name="m", version="0", backbone="b", label_type="anchor", input_size=32, pixel_spacing_mm=2.0,
                     variance_threshold=1.0, dropout_p=0.1, atlas_id="a", trained_on="-", sha256="0" * 64)
    [prepared] = prepare_stacks([up], info, False)
    predicted = prepared.slices.to_stack(prepared.slices.masks) > 0
    [given] = uploaded_pose_masks([up])
    assert predicted.sum() < (mask > 0.5).sum()                       # the rim is inset ...
    np.testing.assert_array_equal(given > 0, predicted)               # ... in both paths alike


def test_a_job_localises_with_the_servers_localiser_where_a_stack_has_no_mask(tmp_path) -> None:  # noqa: ANN001
    """The localiser of ``SVRNET_LOCALISERS_DIR``, as ``/v1/predict`` runs it; none where every stack has a mask."""
    import shutil
    from pathlib import Path

    from service.io.volume import Volume
    from service.jobs.worker import job_localiser
    from service.pipeline.prepare import StackUpload

    shipped = Path(__file__).resolve().parents[2] / "service" / "localisers" / "default" / "model.onnx"
    (tmp_path / "default").mkdir()
    shutil.copy(shipped, tmp_path / "default" / "model.onnx")
    vol = Volume(np.zeros((8, 8, 4), np.float32), np.diag([1.0, 1.0, 3.0, 1.0]))
    masked, bare = StackUpload("a", vol, vol), StackUpload("b", vol)
    assert job_localiser(tmp_path, [masked]) is None and job_localiser(None, [bare]) is None
    assert job_localiser(tmp_path, [masked, bare]).path == tmp_path / "default" / "model.onnx"


def test_a_job_given_poses_works_in_the_plane_of_the_model_it_names(tiny_model_path, tmp_path) -> None:  # noqa: ANN001
    """Given poses come from the named model's ``/v1/predict``: the job's twin branches and frame steps
    use that model's mid-sagittal plane, not the default; a server without the file still runs the
    job in the default plane, and a job that must predict says the model is missing."""
    import onnx
    import pytest

    from model_export.export import metadata_of, set_metadata
    from service.geometry.twin import DEFAULT_PLANE_X_MM
    from service.jobs.worker import job_estimator

    proto = onnx.load(str(tiny_model_path))
    set_metadata(proto, {**metadata_of(proto), "symmetry_plane_x_mm": "1.5"})
    onnx.save(proto, str(tmp_path / "model.onnx"))
    estimator, plane = job_estimator(tmp_path / "model.onnx", required=False)
    assert plane == 1.5 != DEFAULT_PLANE_X_MM and estimator.info.symmetry_plane_x_mm == 1.5
    assert job_estimator(tmp_path / "absent.onnx", required=False) == (None, DEFAULT_PLANE_X_MM)
    with pytest.raises(ValueError, match="model: .*'s file is no longer in the models folder or does not load"):
        job_estimator(tmp_path / "absent.onnx")


def test_a_job_whose_model_file_changed_since_it_was_submitted_fails_saying_so(tiny_model_path) -> None:  # noqa: ANN001
    """The server serves the models it loaded at start; a job loads its model's file when it runs: a
    file replaced meanwhile (another sha256 than the one the submission recorded) fails the job naming
    ``model`` rather than running on the new file under the old name."""
    from service.inference.model_file import load_model

    estimator, _ = job_estimator(tiny_model_path, sha256=load_model(tiny_model_path).info.sha256)
    assert estimator is not None
    with pytest.raises(ValueError, match="model: .*'s file changed on disk since the job was submitted"):
        job_estimator(tiny_model_path, sha256="0" * 64)


def test_a_job_whose_stacks_hold_no_brain_the_localiser_finds_says_so(tiny_model_path) -> None:  # noqa: ANN001
    """Stacks sent without masks in which the localiser finds no brain (noise): the job fails with
    what `/v1/predict`'s answer says of them (send a mask), not with the reconstruction's "no pixel
    inside its mask" of masks the user never sent."""
    noise = np.random.default_rng(0).random((128, 128, 12), np.float32) * 500
    upload = StackUpload("noise.nii.gz", Volume(noise, np.diag([1.5, 1.5, 3.0, 1.0])))
    estimator, _ = job_estimator(tiny_model_path)
    with pytest.raises(UnusableImage, match="the localiser found no brain in any stack.*upload a brain mask"):
        predicted_body([upload], estimator, mc_samples=5, localiser=default_localiser())


def test_a_job_names_its_model_by_the_name_it_was_served_under(tiny_model_path) -> None:  # noqa: ANN001
    """A model copied into another folder (a researcher's ``next``) is served under the folder's name:
    the job's prediction names it so, as ``/v1/predict`` does, not by its file's own metadata name."""
    from tests.support.phantoms import acquire_stack, phantom_brain, stack_affine

    img, msk, aff = phantom_brain(2)
    shape = (48, 48, 12)
    a = stack_affine(2, np.eye(3), 1.5, 3.0, shape)
    stack, mask = acquire_stack(img, msk, aff, a, shape, 2, np.stack([np.eye(4)] * shape[2]))
    upload = StackUpload("s.nii.gz", Volume(stack.astype(np.float32), a), Volume((mask > 0.5).astype(np.uint8), a),
                         "m.nii.gz")
    estimator, _ = job_estimator(tiny_model_path)
    body, _ = predicted_body([upload], estimator, mc_samples=2, model_name="next")
    assert body["model"]["name"] == "next" != estimator.info.name
    assert body["model"]["sha256"] == estimator.info.sha256
