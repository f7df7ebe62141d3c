"""A model's metadata: the twin risk's coefficients and the test-time views are read, or refused with
the reason; every shipped pose model states the test-time views its calibrations were made with."""

from __future__ import annotations

from pathlib import Path

import pytest

from service.inference.model_file import ModelInfo, load_model
from service.inference.views import SHIPPED_VIEWS

MODELS = Path(__file__).resolve().parents[2] / "service" / "models"

META = {"name": "m", "version": "1", "backbone": "compact", "label_type": "grid", "input_size": "96",
        "pixel_spacing_mm": "1.25", "variance_threshold": "492.3"}


def test_the_twin_risk_is_read_and_absent_or_empty_means_none() -> None:
    assert ModelInfo.from_metadata({**META, "twin_risk_logit": "-0.58,-0.186"}, "s").twin_risk_logit == (-0.58, -0.186)
    assert ModelInfo.from_metadata(META, "s").twin_risk_logit is None
    assert ModelInfo.from_metadata({**META, "twin_risk_logit": ""}, "s").twin_risk_logit is None


@pytest.mark.parametrize("text", ["-0.5,0.1", "-0.5,0", "-0.5", "a,b", "nan,-0.1"])
def test_a_twin_risk_that_does_not_fall_with_the_distance_or_is_not_two_numbers_is_refused(text: str) -> None:
    with pytest.raises(ValueError, match="metadata"):
        ModelInfo.from_metadata({**META, "twin_risk_logit": text}, "s")


def test_the_noise_error_is_read_and_absent_or_empty_means_none() -> None:
    assert ModelInfo.from_metadata({**META, "noise_error": "0.09,52.5"}, "s").noise_error == (0.09, 52.5)
    assert ModelInfo.from_metadata(META, "s").noise_error is None
    assert ModelInfo.from_metadata({**META, "noise_error": ""}, "s").noise_error is None


@pytest.mark.parametrize("text", ["0.1,-5", "1.5,40", "-0.1,40", "0.1", "0.1,inf", "0.1,nan", "a,b"])
def test_a_noise_error_that_is_not_an_onset_and_a_non_negative_slope_is_refused(text: str) -> None:
    with pytest.raises(ValueError, match="noise_error"):
        ModelInfo.from_metadata({**META, "noise_error": text}, "s")


def test_the_frame_error_is_read_and_absent_or_empty_means_none() -> None:
    assert ModelInfo.from_metadata({**META, "frame_error": "13,0.5"}, "s").frame_error == (13.0, 0.5)
    assert ModelInfo.from_metadata(META, "s").frame_error is None
    assert ModelInfo.from_metadata({**META, "frame_error": ""}, "s").frame_error is None


@pytest.mark.parametrize("text", ["13,-0.5", "-1,0.5", "13", "13,inf", "nan,0.5", "a,b", "1,2,3"])
def test_a_frame_error_that_is_not_an_onset_and_a_non_negative_slope_is_refused(text: str) -> None:
    with pytest.raises(ValueError, match="frame_error"):
        ModelInfo.from_metadata({**META, "frame_error": text}, "s")


@pytest.mark.parametrize("text", ["2", "0", "16"])
def test_a_view_count_the_estimator_cannot_run_is_refused_when_the_file_is_read(text: str) -> None:
    """A file with another count of test-time views would load and then fail every request."""
    assert ModelInfo.from_metadata({**META, "tta_views": "4"}, "s").tta_views == 4
    with pytest.raises(ValueError, match="tta_views"):
        ModelInfo.from_metadata({**META, "tta_views": text}, "s")


@pytest.mark.parametrize("folder", sorted(p.name for p in MODELS.iterdir() if (p / "model.onnx").exists()))
def test_every_shipped_pose_model_states_the_views_it_was_calibrated_with(folder: str) -> None:
    """Without ``tta_views`` the service runs one view, where the calibrations and the card's figures
    were measured with :data:`SHIPPED_VIEWS` (docs/training.md measures what one view costs)."""
    assert load_model(MODELS / folder / "model.onnx").info.metadata.get("tta_views") == str(SHIPPED_VIEWS)


@pytest.mark.parametrize(("updates", "said"), [({"input_size": "128"}, "does not run on slices of 128 x 128 px"),
                                                ({"label_type": "euler"}, "label_type 'euler' needs [1, 1, 6]")])
def test_a_graph_that_is_not_what_its_metadata_says_is_refused_where_it_is_loaded(
        updates: dict, said: str, tiny_model_path: Path, tmp_path: Path) -> None:
    """A model whose metadata names another input size or label than its graph has (a file edited by
    hand, a copy of another model's metadata) fails at load, naming the field, where it had been
    served and answered every request with a 500."""
    import shutil

    from model_export.spread import write_metadata

    copy = tmp_path / "model.onnx"
    shutil.copyfile(tiny_model_path, copy)
    load_model(copy)
    write_metadata(copy, updates)
    with pytest.raises(ValueError, match=said.replace("[", r"\[").replace("]", r"\]")):
        load_model(copy)
