"""Pose-error metrics the calibration, the evaluation report and the benchmarks share: how well a
score ranks bad slices (AUROC, Youden's threshold), what a pose error is made of (tilt, twist,
centre, along the normal) and the error per class of slice normal.

They depend on numpy and scipy alone, so that every report and experiment imports them without
importing each other.

Example:
    >>> import numpy as np
    >>> auroc(np.array([0.1, 0.2, 0.8, 0.9]), np.array([False, False, True, True]))
    1.0
"""

from __future__ import annotations

import numpy as np
from scipy import stats
from scipy.spatial.transform import Rotation


def auroc(scores: np.ndarray, positive: np.ndarray) -> float:
    """Area under the ROC curve of ``scores`` for ``positive`` (Mann-Whitney U / (n+ n-))."""
    pos, neg = scores[positive], scores[~positive]
    if len(pos) == 0 or len(neg) == 0:
        return float("nan")
    u = stats.mannwhitneyu(pos, neg, alternative="two-sided").statistic
    return float(u / (len(pos) * len(neg)))


def youden_threshold(scores: np.ndarray, positive: np.ndarray) -> float:
    """The score threshold (flag if above) that maximises TPR - FPR."""
    cand = np.unique(scores)
    tpr = (scores[None, positive] > cand[:, None]).mean(1) if positive.any() else np.zeros(len(cand))
    fpr = (scores[None, ~positive] > cand[:, None]).mean(1) if (~positive).any() else np.zeros(len(cand))
    return float(cand[np.argmax(tpr - fpr)])


def error_components(pred: np.ndarray, true: np.ndarray) -> dict[str, np.ndarray]:
    """Where a pose error comes from, per slice (poses ``[n, 4, 4]`` in atlas mm).

    The relative rotation ``R = R_true^T R_pred`` (in the true slice frame) is split into a swing,
    which tilts the slice normal, and a twist about the normal (swing-twist decomposition):

    * ``tilt_deg``: angle between the two planes (0-90, whichever side each faces);
    * ``flipped``: the predicted normal points the other way (tilt beyond 90 degrees before folding);
    * ``twist_deg``: in-plane rotation about the normal (0-180);
    * ``centre_mm``: distance between the plane centres; ``off_plane_mm``: its part along the true normal.

    Example:
        >>> from scipy.spatial.transform import Rotation
        >>> true, pred = np.eye(4)[None], np.eye(4)[None].copy()
        >>> pred[0, :3, :3] = Rotation.from_euler("xz", [40, 30], degrees=True).as_matrix()
        >>> c = error_components(pred, true)
        >>> round(float(c["tilt_deg"][0]), 6), round(float(c["twist_deg"][0]), 6)
        (40.0, 30.0)
    """
    rel = np.einsum("nji,njk->nik", true[:, :3, :3], pred[:, :3, :3])
    cos_tilt = np.clip(rel[:, 2, 2], -1.0, 1.0)
    x, y, z, w = Rotation.from_matrix(rel).as_quat().T
    twist = 2.0 * np.arctan2(np.abs(z), np.abs(w))
    shift = pred[:, :3, 3] - true[:, :3, 3]
    return {"tilt_deg": np.degrees(np.arccos(np.abs(cos_tilt))), "flipped": cos_tilt < 0,
            "twist_deg": np.degrees(twist), "centre_mm": np.linalg.norm(shift, axis=1),
            "off_plane_mm": np.abs(np.einsum("ni,ni->n", shift, true[:, :3, 2]))}


def by_orientation(errors: np.ndarray, poses: np.ndarray) -> dict[str, float]:
    """Mean error per class of slice normal: the atlas axis the normal is nearest (axial, coronal, sagittal).

    Example:
        >>> by_orientation(np.array([1.0, 3.0]), np.stack([np.eye(4)] * 2))
        {'sagittal': nan, 'coronal': nan, 'axial': 2.0}
    """
    axis = np.argmax(np.abs(poses[:, :3, 2]), axis=1)
    names = ("sagittal", "coronal", "axial")                   # normal along x, y, z (RAS)
    return {n: float(errors[axis == i].mean()) if (axis == i).any() else float("nan") for i, n in enumerate(names)}
