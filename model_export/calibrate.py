"""Calibration of the acceptance threshold on geodesic variance.

On whole held-out volumes, slices are simulated with the full training corruptions (thick, noisy,
bias, voids, imperfect masks), the MC-dropout statistics are computed as the service does (same
head sampling, same Fréchet mean and variance) after the samples of each slice are put on one
branch of the left-right twin (the service's twin-aware statistics), and the variance is compared to the twin-min
anchor-point error of the mean pose: a single slice cannot tell a pose from its twin (the stack
decides the branch), so the variance is asked to flag slices that are wrong on either branch. The threshold maximises Youden's J (TPR - FPR) for flagging
slices with error > ``error_mm``; the AUROC says how well variance ranks bad slices.

The statistics are those of the file the service runs when one is given (``model_file``: the
exported, perhaps int8, ONNX file through the service's own estimator, with its test-time views and
fixed draws), else those of the checkpoint's float network in torch.

When fewer than ``MIN_CLASS_FRACTION`` of the slices fall on one side of ``error_mm`` (a weak model:
nearly every slice is off by more than 10 mm), Youden's J on a handful of slices is noise; the
threshold is then chosen for the median error instead (flag the worse half), and both AUROCs are
reported.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
from scipy import stats

from model_export.atlas import DEFAULT_ATLAS_ROOT, validation_volumes
from model_export.packaging import load_checkpoint
from model_export.simulate import SimulationConfig
from model_export.pose_metrics import auroc, youden_threshold
from model_export.train import pose_errors, validation_set
from service.inference.estimator import statistics
from service.inference.views import sample_views

ERROR_MM = 10.0
MIN_CLASS_FRACTION = 0.1






@torch.no_grad()
def mc_statistics(model, inputs: np.ndarray, mc_samples: int, batch: int = 64,  # noqa: ANN001
                  plane_x_mm: float = 0.0, views: int = 1):
    """Torch MC sampling through the export path (``mc_forward``) over the service's test-time
    ``views``, on one branch, reduced like the service."""

    def run(x: np.ndarray, n: int) -> np.ndarray:
        passes = torch.ones(n) if n > 0 else torch.zeros(1)
        return np.concatenate([model.mc_forward(torch.from_numpy(x[i:i + batch, None]), passes).double().numpy()
                               for i in range(0, len(x), batch)])

    return statistics(sample_views(run, inputs, mc_samples, model.label_type, plane_x_mm, views),
                      model.label_type, plane_x_mm)


def calibrate(checkpoint: Path, root: Path = DEFAULT_ATLAS_ROOT, *, mc_samples: int = 100,
              per_volume: int = 120, error_mm: float = ERROR_MM, seed: int = 777, views: int = 1,
              model_file: Path | None = None) -> dict:
    """Choose the variance threshold on the checkpoint's validation volumes, simulated as it trained;
    returns it with the AUROC and the data behind them.

    Args:
        checkpoint: the training checkpoint (its validation volumes, simulation and symmetry plane).
        views: test-time views of the float network (a ``model_file`` runs its own).
        model_file: the exported ONNX file to measure, as the service runs it (the file shipped:
            int8 where its convolutions are); None measures the checkpoint's float network.
    """
    model, ck = load_checkpoint(checkpoint)
    torch.manual_seed(seed)
    plane = float(ck["config"].get("plane_x_mm", 0.0))
    sim = SimulationConfig(**{k: v for k, v in ck["simulation"].items() if k in SimulationConfig.__dataclass_fields__})
    val = validation_set(validation_volumes(ck), root, per_volume, seed=seed, config=sim)
    if model_file is None:
        est = mc_statistics(model, val.inputs, mc_samples, plane_x_mm=plane, views=views)
    else:
        from service.inference.estimator import OnnxPoseEstimator
        from service.inference.model_file import load_model

        served = OnnxPoseEstimator(load_model(model_file))
        views = served.info.tta_views
        est = statistics(served.sample_labels(val.inputs, mc_samples), served.info.label_type, plane)
    errors = pose_errors(est.mean, val.poses, plane)
    err = errors["ed_twin_mm"]
    bad = err > error_mm
    criterion = error_mm
    if min(bad.mean(), 1 - bad.mean()) < MIN_CLASS_FRACTION:
        criterion = float(np.median(err))
    thr = youden_threshold(est.variance, err > criterion)
    accepted = est.variance <= thr
    return {
        "threshold": thr, "auroc": auroc(est.variance, bad), "error_mm": error_mm, "errors": "twin-min", "views": views,
        "measured_on": "checkpoint (float, torch)" if model_file is None else Path(model_file).name,
        "auroc_truth": auroc(est.variance, errors["ed_mm"] > error_mm),
        "criterion_mm": criterion, "auroc_criterion": auroc(est.variance, err > criterion),
        "n_slices": int(len(err)),
        "bad_fraction": float(bad.mean()), "accepted_fraction": float(accepted.mean()),
        "ed_accepted_mean_mm": float(err[accepted].mean()) if accepted.any() else float("nan"),
        "ed_rejected_mean_mm": float(err[~accepted].mean()) if (~accepted).any() else float("nan"),
        "spearman_variance_error": float(stats.spearmanr(est.variance, err).statistic),
        "variance": est.variance.tolist(), "ed_mm": err.tolist(),
    }
