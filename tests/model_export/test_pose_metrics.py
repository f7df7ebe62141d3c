"""The pose-error metrics of the reports: AUROC and Youden's threshold on synthetic scores, the
decomposition of pose errors on constructed poses."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from model_export.pose_metrics import auroc, error_components, youden_threshold
from service.geometry.pose import make_pose

RNG = np.random.default_rng(0)


def test_auroc_and_youden_on_separable_and_random_scores() -> None:
    bad = np.r_[np.zeros(50, bool), np.ones(50, bool)]
    scores = np.r_[RNG.uniform(0, 1, 50), RNG.uniform(2, 3, 50)]
    assert auroc(scores, bad) == 1.0 and auroc(-scores, bad) == 0.0
    thr = youden_threshold(scores, bad)
    assert scores[:50].max() <= thr < scores[50:].min() and ((scores > thr) == bad).all()
    noise = RNG.uniform(size=4000)
    assert abs(auroc(noise, RNG.uniform(size=4000) > 0.5) - 0.5) < 0.05
    assert np.isnan(auroc(scores, np.zeros(100, bool)))


def test_tilt_twist_flip_and_shift_are_told_apart() -> None:
    rng = np.random.default_rng(3)
    true = make_pose(Rotation.random(4, random_state=rng).as_matrix(), rng.normal(0, 20, (4, 3)))
    local = (Rotation.from_euler("z", np.array([[25], [0], [0], [0]]), degrees=True)
             * Rotation.from_euler("x", np.array([[0], [35], [180], [0]]), degrees=True))
    pred = true @ make_pose(local.as_matrix(), np.zeros(3))              # errors in the true slice frame
    pred[3, :3, 3] += 6.0 * true[3, :3, 2] + 8.0 * true[3, :3, 0]         # 6 mm off the plane, 8 in it
    c = error_components(pred, true)
    np.testing.assert_allclose(c["tilt_deg"], [0, 35, 0, 0], atol=1e-6)
    np.testing.assert_allclose(c["twist_deg"][[0, 1, 3]], [25, 0, 0], atol=1e-6)
    assert c["flipped"].tolist() == [False, False, True, False]
    np.testing.assert_allclose(c["centre_mm"], [0, 0, 0, 10.0], atol=1e-9)
    np.testing.assert_allclose(c["off_plane_mm"], [0, 0, 0, 6.0], atol=1e-9)


def test_ranges_on_random_errors() -> None:
    rng = np.random.default_rng(4)
    true = make_pose(Rotation.random(200, random_state=rng).as_matrix(), np.zeros((200, 3)))
    pred = make_pose(Rotation.random(200, random_state=rng).as_matrix(), np.zeros((200, 3)))
    c = error_components(pred, true)
    assert (c["tilt_deg"] >= 0).all() and (c["tilt_deg"] <= 90 + 1e-9).all()
    assert (c["twist_deg"] >= 0).all() and (c["twist_deg"] <= 180 + 1e-9).all()
    assert 0.3 < c["flipped"].mean() < 0.7
