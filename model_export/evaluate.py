"""Evaluation with the paper's metrics, written as a markdown report with figures.

On the validation volumes (3 mm thick, 1 mm pixels, noisy, bias-shaded slices; see
:meth:`SimulationConfig.validation`), the exported model runs through the service's estimator
(onnxruntime, MC dropout, Fréchet mean). Per slice:

* image similarity between the slice rendered at the TRUE pose and at the PREDICTED pose (same
  volume, same thick-slice PSF, same preprocessing): CC, MSE, PSNR, SSIM -- the paper compares the
  input with the slice re-sampled at the prediction; our inputs are noisy, so both sides are
  rendered noise-free to measure the pose and not the noise;
* mean anchor-point Euclidean distance (E.D., mm) to the truth and the twin-min E.D. (to whichever
  of the truth and its left-right twin is nearer: a single slice cannot tell them apart, the stack
  decides), and the geodesic distance (G.D.); MC samples are put on one branch first
  (the service's twin-aware :func:`~service.inference.estimator.statistics`);
* where the error lies, against the nearer twin: tilt of the plane, in-plane twist, centre, and the
  branch (the share of slices nearer the twin);
* the paper's outlier rule: G.D. more than 3 scaled MADs from the median; tables give all slices and
  inliers.
"""

from __future__ import annotations

import inspect
from pathlib import Path

import numpy as np
from scipy import ndimage

from model_export.atlas import DEFAULT_ATLAS_ROOT, load_volumes, split, validation_volumes
from model_export.calibrate import ERROR_MM
from model_export.pose_metrics import auroc, by_orientation, error_components
from model_export.simulate import SimulationConfig
from model_export.train import pose_errors, validation_set
from service.geometry import sampling, se3
from service.geometry.twin import twin
from service.inference.estimator import OnnxPoseEstimator, statistics
from service.inference.model_file import load_model
from service.preprocess.intensity import rescale_0_255


def ssim(a: np.ndarray, b: np.ndarray, data_range: float = 255.0, sigma: float = 1.5) -> np.ndarray:
    """Mean SSIM (Wang et al. 2004, Gaussian window) per image of ``[B, H, W]`` pairs."""
    f = lambda x: ndimage.gaussian_filter(x, (0, sigma, sigma))  # noqa: E731
    a, b = a.astype(np.float64), b.astype(np.float64)
    c1, c2 = (0.01 * data_range) ** 2, (0.03 * data_range) ** 2
    ma, mb = f(a), f(b)
    va, vb, cov = f(a * a) - ma * ma, f(b * b) - mb * mb, f(a * b) - ma * mb
    s = ((2 * ma * mb + c1) * (2 * cov + c2)) / ((ma * ma + mb * mb + c1) * (va + vb + c2))
    return s.mean(axis=(1, 2))


def image_metrics(ref: np.ndarray, pred: np.ndarray) -> dict[str, np.ndarray]:
    """CC, MSE, PSNR (dB, peak 255) and SSIM per slice."""
    r = ref.reshape(len(ref), -1).astype(np.float64)
    p = pred.reshape(len(pred), -1).astype(np.float64)
    rc, pc = r - r.mean(1, keepdims=True), p - p.mean(1, keepdims=True)
    cc = (rc * pc).sum(1) / np.sqrt((rc**2).sum(1) * (pc**2).sum(1) + 1e-12)
    mse = ((r - p) ** 2).mean(1)
    psnr = 10 * np.log10(255.0**2 / np.maximum(mse, 1e-12))
    return {"cc": cc, "mse": mse, "psnr": psnr, "ssim": ssim(ref, pred)}


def render(vol, poses: np.ndarray, size: int, pixel_mm: float, thickness_mm: float) -> np.ndarray:  # noqa: ANN001
    """Noise-free preprocessed slices of ``vol`` at ``poses`` on the network grid."""
    img = sampling.sample_slices(vol.image, vol.affine, poses, size, pixel_mm, thickness_mm=thickness_mm)
    mask = sampling.sample_slices(vol.mask, vol.affine, poses, size, pixel_mm) > 0.5
    return rescale_0_255(img, mask)


def evaluate(model_path: Path, report: Path, root: Path = DEFAULT_ATLAS_ROOT, *, per_volume: int = 100,
             mc_samples: int = 100, seed: int = 12345) -> dict:
    """Run the evaluation; writes ``report`` (markdown) and PNG figures beside it; returns the summary."""
    model = load_model(model_path)
    info = model.info
    _, val_names = split(root, validation_volumes(info.metadata))
    cfg = SimulationConfig.validation(size=info.input_size, pixel_mm=info.pixel_spacing_mm)
    val = validation_set(val_names, root, per_volume, seed=seed, config=cfg)
    plane = info.symmetry_plane_x_mm
    est = statistics(OnnxPoseEstimator(model).sample_labels(val.inputs, mc_samples), info.label_type, plane)
    err = pose_errors(est.mean, val.poses, plane)
    vols = {v.name: v for v in load_volumes(val_names, root)}
    names = np.array(val.volume)
    ref = np.zeros_like(val.inputs)
    pred = np.zeros_like(val.inputs)
    for name, vol in vols.items():
        sel = names == name
        ref[sel] = render(vol, val.poses[sel], info.input_size, info.pixel_spacing_mm, 3.0)
        pred[sel] = render(vol, est.mean[sel], info.input_size, info.pixel_spacing_mm, 3.0)
    metrics = {**image_metrics(ref, pred), "ed_mm": err["ed_mm"], "ed_twin_mm": err["ed_twin_mm"], "gd": err["gd"],
               "gd_twin": err["gd_twin"], "variance": est.variance}
    outlier = {"truth": se3.mad_outliers(err["gd"]), "twin_min": se3.mad_outliers(err["gd_twin"])}
    accepted = est.variance <= info.variance_threshold
    summary = _summary(metrics, outlier, accepted, names, info)
    summary["on_twin_fraction"] = float(err["on_twin"].mean())
    summary["mc_other_branch_fraction"] = float(est.twin_mass.mean())
    nearer = np.where(err["on_twin"][:, None, None], twin(val.poses, plane), val.poses)
    summary["components"] = _quartiles(error_components(est.mean, nearer))
    summary["by_orientation"] = by_orientation(err["ed_twin_mm"], val.poses)
    report.parent.mkdir(parents=True, exist_ok=True)
    _figures(report, metrics, val.inputs, pred, info.variance_threshold)
    defaults = inspect.signature(evaluate).parameters            # the command's own: left out of the report's
    options = "".join(f" --{k.replace('_', '-')} {v}" for k, v in
                      (("per_volume", per_volume), ("mc_samples", mc_samples), ("seed", seed)) if v != defaults[k].default)
    options += "" if Path(root).resolve() == DEFAULT_ATLAS_ROOT.resolve() else f" --root {root}"
    report.write_text(_markdown(model_path, info, summary, mc_samples, len(names), report, options))
    return ({k: v for k, v in summary.items() if not isinstance(v, dict)}
            | {k: summary[k] for k in ("per_volume", "per_volume_twin", "components", "by_orientation")})






def _stats(metrics: dict[str, np.ndarray], sel: np.ndarray) -> dict[str, float]:
    return {k: float(np.mean(v[sel])) for k, v in metrics.items() if k != "variance"}


def _summary(metrics, outlier, accepted, names, info) -> dict:  # noqa: ANN001
    ed, tw = metrics["ed_mm"], metrics["ed_twin_mm"]
    bad = tw > ERROR_MM
    return {
        "n": int(len(ed)), "ed_mean_mm": float(ed.mean()), "ed_median_mm": float(np.median(ed)),
        "ed_p90_mm": float(np.percentile(ed, 90)), "ed_under_10mm": float((ed < ERROR_MM).mean()),
        "ed_twin_mean_mm": float(tw.mean()), "ed_twin_median_mm": float(np.median(tw)),
        "ed_twin_p90_mm": float(np.percentile(tw, 90)), "ed_twin_under_10mm": float((tw < ERROR_MM).mean()),
        "gd_mean": float(metrics["gd"].mean()), "gd_twin_mean": float(metrics["gd_twin"].mean()),
        "outlier_fraction": float(outlier["truth"].mean()), "outlier_twin_fraction": float(outlier["twin_min"].mean()),
        "auroc_variance_error_gt_10mm": auroc(metrics["variance"], bad),
        "auroc_variance_truth_error_gt_10mm": auroc(metrics["variance"], ed > ERROR_MM),
        "accepted_fraction": float(accepted.mean()),
        "ed_accepted_mean_mm": float(ed[accepted].mean()) if accepted.any() else float("nan"),
        "ed_twin_accepted_mean_mm": float(tw[accepted].mean()) if accepted.any() else float("nan"),
        "all": _stats(metrics, np.ones_like(outlier["truth"])), "inliers": _stats(metrics, ~outlier["truth"]),
        "inliers_twin": _stats(metrics, ~outlier["twin_min"]),
        "per_volume": {n: float(ed[names == n].mean()) for n in dict.fromkeys(names)},
        "per_volume_twin": {n: float(tw[names == n].mean()) for n in dict.fromkeys(names)},
    }


def _quartiles(components: dict[str, np.ndarray]) -> dict[str, list[float] | float]:
    out: dict[str, list[float] | float] = {k: np.percentile(v, [25, 50, 75]).tolist()
                                           for k, v in components.items() if k != "flipped"}
    out["flipped_fraction"] = float(components["flipped"].mean())
    return out


def _figures(report: Path, metrics, inputs, pred, threshold) -> None:  # noqa: ANN001
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    stem = report.with_suffix("")
    fig, ax = plt.subplots(1, 2, figsize=(10, 3.5))
    ax[0].hist([metrics["ed_mm"], metrics["ed_twin_mm"]], bins=40, label=["against the truth", "twin-min"])
    ax[0].set(xlabel="mean anchor-point E.D. (mm)", ylabel="slices", title="error distribution")
    ax[0].legend()
    ax[1].scatter(metrics["variance"], metrics["ed_twin_mm"], s=6, alpha=0.5)
    ax[1].axvline(threshold, color="r", ls="--", label=f"threshold {threshold:.3g}")
    ax[1].set(xscale="log", yscale="log", xlabel="geodesic variance", ylabel="twin-min E.D. (mm)",
              title="confidence vs error")
    ax[1].legend()
    fig.tight_layout()
    fig.savefig(f"{stem}_errors.png", dpi=90)
    plt.close(fig)
    order = np.argsort(metrics["ed_twin_mm"])
    picks = order[np.linspace(0, len(order) - 1, 8).astype(int)]
    fig, ax = plt.subplots(2, 8, figsize=(16, 4.4))
    for j, i in enumerate(picks):
        ax[0, j].imshow(inputs[i], cmap="gray", vmin=0, vmax=255)
        ax[0, j].set_title(f"E.D. {metrics['ed_mm'][i]:.1f} / twin-min {metrics['ed_twin_mm'][i]:.1f} mm", fontsize=7)
        ax[1, j].imshow(pred[i], cmap="gray", vmin=0, vmax=255)
    for a in ax.ravel():
        a.axis("off")
    ax[0, 0].text(-10, 48, "input", rotation=90, va="center")
    ax[1, 0].text(-10, 48, "at prediction", rotation=90, va="center")
    fig.tight_layout()
    fig.savefig(f"{stem}_examples.png", dpi=80)
    plt.close(fig)


def _markdown(model_path, info, s, mc, n, report, options="") -> str:  # noqa: ANN001
    stem = report.with_suffix("").name
    row = lambda k, d: (f"| {k} | {d['cc']:.3f} | {d['mse']:.1f} | {d['psnr']:.2f} | {d['ssim']:.3f} | "  # noqa: E731
                        f"{d['ed_mm']:.2f} / {d['ed_twin_mm']:.2f} | {d['gd']:.2f} / {d['gd_twin']:.2f} |")
    vols = "\n".join(f"| {k} | {v:.2f} | {s['per_volume_twin'][k]:.2f} |" for k, v in s["per_volume"].items())
    orient = " / ".join(f"{k} {v:.1f}" for k, v in s["by_orientation"].items())
    c = s["components"]
    labels = {"tilt_deg": "tilt of the plane (deg)", "twist_deg": "in-plane twist (deg)",
              "centre_mm": "distance of the centres (mm)", "off_plane_mm": "  of which along the normal (mm)"}
    parts = "\n".join(f"| {label} | " + " | ".join(f"{q:.1f}" for q in c[k]) + " |" for k, label in labels.items())
    return f"""# Evaluation of `{model_path.name}` ({info.name} {info.version}, {info.backbone}, {info.label_type})

Validation volumes held out by whole volume; {n} slices, 3 mm thick (Gaussian PSF), 1.0 mm pixels,
Rician noise 3 %, bias field, random orientation (full sphere, any in-plane angle), Tz in the central
70 % of the brain. {mc} MC-dropout passes per slice, Fréchet mean pose. Regenerate with
`svrnet-train evaluate {model_path} --report {report}{options}`.

| slices | CC | MSE | PSNR (dB) | SSIM | E.D. (mm), truth / twin-min | G.D., truth / twin-min |
|---|---|---|---|---|---|---|
{row("all", s["all"])}
{row("inliers (3-MAD on G.D. against the truth, as the paper)", s["inliers"])}
{row("inliers (3-MAD on twin-min G.D.)", s["inliers_twin"])}

| mean anchor-point E.D. (mm) | mean | median | p90 | under 10 mm |
|---|---|---|---|---|
| against the truth | **{s['ed_mean_mm']:.2f}** | {s['ed_median_mm']:.2f} | {s['ed_p90_mm']:.2f} | {100 * s['ed_under_10mm']:.1f} % |
| twin-min (nearer of truth and twin) | **{s['ed_twin_mean_mm']:.2f}** | {s['ed_twin_median_mm']:.2f} | {s['ed_twin_p90_mm']:.2f} | {100 * s['ed_twin_under_10mm']:.1f} % |

- G.D. {s['gd_mean']:.2f} against the truth, {s['gd_twin_mean']:.2f} twin-min; 3-MAD outliers: {100 * s['outlier_fraction']:.1f} %
  of slices on G.D. against the truth (most of them on the twin: a single slice cannot tell), {100 * s['outlier_twin_fraction']:.1f} % on twin-min G.D.
- branch: {100 * s['on_twin_fraction']:.1f} % of the slices are nearer the twin than the truth (a single slice
  cannot tell; the stack decides); {100 * s['mc_other_branch_fraction']:.1f} % of the MC samples fell on the other
  twin of their slice and were mirrored back before the Fréchet mean
- twin-min E.D. by slice orientation (normal nearest x / y / z): {orient} mm
- AUROC of geodesic variance for twin-min E.D. > 10 mm: {s['auroc_variance_error_gt_10mm']:.3f} (for E.D. against
  the truth > 10 mm: {s['auroc_variance_truth_error_gt_10mm']:.3f})
- accepted at the model's threshold {info.variance_threshold:.3g}: {100 * s['accepted_fraction']:.1f} %, their mean E.D.
  {s['ed_accepted_mean_mm']:.2f} mm, twin-min {s['ed_twin_accepted_mean_mm']:.2f} mm

Where the error comes from, against the nearer twin (quartiles 25 / 50 / 75 %; the relative
rotation split into the tilt of the slice plane and the twist about its normal):

| component | 25 % | median | 75 % |
|---|---|---|---|
{parts}

The predicted normal faces the other way for {100 * c['flipped_fraction']:.1f} % of the slices (the same
plane seen from behind, a mirrored image).

| validation volume | mean E.D. (mm) | twin-min (mm) |
|---|---|---|
{vols}

![errors]({stem}_errors.png)

![examples]({stem}_examples.png)
"""
