"""A model's metadata: the twin risk's coefficients are read, or refused with the reason."""

from __future__ import annotations

import pytest

from service.inference.model_file import ModelInfo

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
