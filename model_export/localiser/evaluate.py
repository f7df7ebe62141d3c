"""Measured figures of a localiser: Dice, pose agreement without masks, latency.

* **Generated whole-uterus validation set**: shards of the ``heldout`` style
  (:mod:`model_export.localiser.scenes`; surroundings unlike the training ones) around the
  validation atlas volumes, kept with their stacks; Dice on each stack's own grid.
* **Real scans** (``../shared/data/real_scans``): Dice against the manual masks where there are
  some; volume and confidence elsewhere.
* **Poses without masks**: ``/v1/predict``'s pipeline run on the same stacks with the reference
  masks and with the localiser's; the median anchor-point distance (E.D.) between the two sets of
  poses, and the ratio of their wall times.

Example:
    >>> import numpy as np
    >>> a = np.zeros((4, 4, 4), bool); a[:2] = True; b = np.zeros_like(a); b[1:3] = True
    >>> dice(a, b)
    0.5
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from service.core.settings import Settings
from service.core.threads import limit_blas_threads
from service.geometry import anchors
from service.pipeline.documents import stack_objects
from model_export.atlas import SHARED_DATA
from model_export.localiser.pose_accuracy import pose_accuracy, pose_estimator, slice_poses, validation_scenes
from service.pipeline.predict import predict
from service.pipeline.prepare import StackUpload, prepare_stacks
from service.io.volume import Volume, read_volume
from service.preprocess.localise import Localiser

REAL_SCANS = SHARED_DATA / "real_scans"


def dice(a: NDArray, b: NDArray) -> float:
    """Dice overlap of two boolean masks (1 when both are empty)."""
    a, b = np.asarray(a, bool), np.asarray(b, bool)
    total = a.sum() + b.sum()
    return 1.0 if total == 0 else float(2 * np.logical_and(a, b).sum() / total)


def heldout_dice(localiser: Localiser, folder: Path) -> list[dict]:
    """Dice, volumes, confidence and time on every kept-stack shard of ``folder``."""
    rows = []
    for path in sorted(Path(folder).glob("*.npz")):
        with np.load(path) as z:
            volume, truth = Volume(z["stack"].astype(np.float32), z["affine"]), z["mask"]
            t2_like = bool(z["t2_like"]) if "t2_like" in z else None
        t = time.perf_counter()
        found = localiser.localise(volume)
        rows.append({"stack": path.stem, "dice": dice(found.mask, truth), "confidence": found.confidence,
                     "ml": found.brain_volume_ml, "true_ml": float(truth.sum() * np.prod(volume.spacing) / 1e3),
                     "ms": (time.perf_counter() - t) * 1e3, "shape": list(volume.array.shape), "t2_like": t2_like})
    return rows


def real_scan_rows(localiser: Localiser, root: Path = REAL_SCANS) -> list[dict]:
    """Per real stack: Dice against its manual mask (None without one), volume, confidence, time."""
    rows = []
    for path in sorted(Path(root).glob("*/*.nii.gz")):
        if "mask" in path.name:
            continue
        volume = read_volume(path)
        manual = path.with_name(path.name.replace(".nii.gz", MASK_SUFFIX))
        t = time.perf_counter()
        found = localiser.localise(volume)
        ms = (time.perf_counter() - t) * 1e3
        truth = read_volume(manual).array > 0 if manual.exists() else None
        rows.append({"stack": f"{path.parent.name}/{path.name}", "dice": None if truth is None else dice(found.mask, truth),
                     "confidence": found.confidence, "ml": found.brain_volume_ml, "ms": ms,
                     "shape": list(volume.array.shape)})
    return rows


MASK_SUFFIX = "_brain_mask.nii.gz"
"""A real scan's manual mask of stack ``NAME.nii.gz`` is ``NAME_brain_mask.nii.gz`` beside it."""


def masked_files(scan: Path) -> list[tuple[str, Path, Path]]:
    """``(name, stack file, manual mask file)`` of every stack of a real ``scan`` folder that has a
    manual mask, by name (none when the folder is absent)."""
    masks = sorted(Path(scan).glob(f"*{MASK_SUFFIX}"))
    return [(m.name[:-len(MASK_SUFFIX)], m.with_name(m.name.replace(MASK_SUFFIX, ".nii.gz")), m) for m in masks]


def masked_stacks(scan: Path, localiser: Localiser) -> tuple[list[str], list[Volume], list[NDArray], list[NDArray]]:
    """The stacks of a real ``scan`` folder that have a manual mask (``*_brain_mask.nii.gz``): their
    names, volumes, manual masks and the localiser's masks (boolean, on each stack's grid)."""
    files = masked_files(scan)
    volumes = [read_volume(stack) for _, stack, _ in files]
    return ([n for n, _, _ in files], volumes, [read_volume(m).array > 0 for _, _, m in files],
            [localiser.localise(v).mask for v in volumes])


def csf_mask_upload(name: str, volume: Volume, mask: NDArray) -> StackUpload:
    """A stack with a skull-inside mask, as ``/v1/predict`` gets it with ``masks_hold_csf``."""
    return StackUpload(name, volume, Volume(np.asarray(mask).astype(np.uint8), volume.affine), mask_holds_csf=True)


def median_ed(a: list[dict], b: list[dict], prepared: list) -> tuple[float | None, int]:
    """Median E.D. (mm) between the slice poses of two answers for the same stacks, over the slices
    neither calls ``empty``."""
    distances = []
    for sa, sb, p in zip(a, b, prepared):
        (pa, ka), (pb, kb) = slice_poses(sa, p), slice_poses(sb, p)
        distances += list(anchors.ed(pa[ka & kb], pb[ka & kb]))
    return (float(np.median(distances)) if distances else None), len(distances)


def pose_agreement(uploads_with_masks: list[StackUpload], localiser: Localiser, estimator, mc_samples: int = 100,  # noqa: ANN001
                   rounds: int = 4) -> dict:
    """Median E.D. (mm) between the poses predicted with the given masks and with the localiser's, and
    between two runs with the given masks (0 with the model's fixed MC draws: a request gets one
    answer; a model that draws afresh shows its draws' spread there); the ratio of the
    requests' wall times without and with masks (each the quickest of ``rounds`` runs, alternating,
    with the BLAS threads the server runs with: ``SVRNET_BLAS_THREADS``)."""
    def run(uploads: list[StackUpload]) -> tuple[list[dict], list, float]:
        t = time.perf_counter()
        prepared = prepare_stacks(uploads, estimator.info, True, workers=2, localiser=localiser)
        predictions, _ = predict(prepared, estimator, mc_samples, estimator.info.variance_threshold)
        return stack_objects(predictions), prepared, time.perf_counter() - t

    bare = [StackUpload(u.filename, u.volume) for u in uploads_with_masks]
    limiter = limit_blas_threads(Settings().blas_threads)
    try:
        with_masks, prepared, t_masks = run(uploads_with_masks)
        without, _, t_without = run(bare)
        again, _, t_again = run(uploads_with_masks)
        t_without = min(t_without, run(bare)[2])
        for _ in range(rounds - 2):
            t_again = min(t_again, run(uploads_with_masks)[2])
            t_without = min(t_without, run(bare)[2])
    finally:
        if limiter is not None:
            limiter.restore_original_limits()
    ed, n = median_ed(with_masks, without, prepared)
    floor, _ = median_ed(with_masks, again, prepared)
    t_masks = min(t_masks, t_again)
    return {"median_ed_mm": ed, "repeat_median_ed_mm": floor, "slices": n, "latency_ratio": t_without / t_masks,
            "seconds_with_masks": t_masks, "seconds_without": t_without}




def latency_ms(localiser: Localiser, shape: tuple[int, int, int] = (320, 320, 22), pixel_mm: float = 1.125,
               repeats: int = 5) -> float:
    """Median wall time (ms) of :meth:`Localiser.localise` on a random stack of ``shape``."""
    rng = np.random.default_rng(0)
    volume = Volume(rng.random(shape, np.float32) * 100, np.diag([pixel_mm, pixel_mm, 3.3, 1.0]))
    times = []
    for _ in range(repeats + 1):
        t = time.perf_counter()
        localiser.localise(volume)
        times.append((time.perf_counter() - t) * 1e3)
    return float(np.median(times[1:]))


def measure(localiser: Localiser, heldout: Path, pose_stacks: int = 8, root: Path = REAL_SCANS,
            pose_scenes: int = 10) -> dict:
    """Every figure of the model card (see the module docstring); ``pose_scenes`` whole-uterus scenes
    of known slice poses give the poses' accuracy with and without masks
    (:func:`~model_export.localiser.pose_accuracy.pose_accuracy`)."""
    held = heldout_dice(localiser, heldout)
    real = real_scan_rows(localiser, root) if Path(root).exists() else []
    estimator = pose_estimator()
    poses_heldout = []
    def is_t2_like(path: Path) -> bool:
        with np.load(path) as z:
            return bool(z["t2_like"])

    t2_like = [p for p in sorted(Path(heldout).glob("*.npz")) if is_t2_like(p)]
    for path in t2_like[:pose_stacks]:                 # the pose network knows T2 contrast only
        with np.load(path) as z:
            volume = Volume(z["stack"].astype(np.float32), z["affine"])
            poses_heldout.append(pose_agreement(
                [StackUpload(path.stem, volume, Volume(z["mask"].astype(np.uint8), z["affine"]))], localiser, estimator))
    manual = [f for scan in sorted(Path(root).glob("*/")) for f in masked_files(scan)]
    uploads = [StackUpload(name, read_volume(stack), read_volume(m)) for name, stack, m in manual]
    poses_real = pose_agreement(uploads, localiser, estimator) if uploads else None
    held_dice = [r["dice"] for r in held]
    real_dice = [r["dice"] for r in real if r["dice"] is not None]
    summary = {
        "heldout_median_dice": float(np.median(held_dice)), "heldout_min_dice": float(np.min(held_dice)),
        "heldout_stacks": len(held), "real_dice": real_dice,
        "heldout_t2_like_median_dice": float(np.median([r["dice"] for r in held if r["t2_like"]] or [np.nan])),
        "heldout_random_contrast_median_dice": float(np.median([r["dice"] for r in held if r["t2_like"] is False]
                                                               or [np.nan])),
        "real_without_mask": [r["stack"] for r in real if r["ml"] == 0],
        "poses_real_median_ed_mm": poses_real and poses_real["median_ed_mm"],
        "poses_real_latency_ratio": poses_real and poses_real["latency_ratio"],
        "poses_heldout_median_ed_mm": float(np.median([p["median_ed_mm"] for p in poses_heldout
                                                       if p["median_ed_mm"] is not None])) if poses_heldout else None,
        "poses_heldout_repeat_median_ed_mm": float(np.median([p["repeat_median_ed_mm"] for p in poses_heldout
                                                              if p["repeat_median_ed_mm"] is not None]))
        if poses_heldout else None,
        "latency_ms_320x320x22": latency_ms(localiser),
        "onnx_mb": localiser.path.stat().st_size / 2**20,
    }
    truth = pose_accuracy(validation_scenes(pose_scenes), estimator, localiser) if pose_scenes else {}
    summary["pose_scenes"] = pose_scenes
    summary["poses_truth_median_ed_mm"] = {k: v["median_ed_mm"] for k, v in truth.items()}
    return {"summary": summary, "heldout": held, "real": real, "poses_real": poses_real, "poses_heldout": poses_heldout,
            "poses_truth": truth}
