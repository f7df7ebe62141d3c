"""Simulated 3-stack acquisitions through the very pipeline the server runs, scored per motion level.

For each motion level (:data:`model_export.acquisitions.MOTION_LEVELS`) and each volume, an
acquisition is simulated with exact per-slice truth, prepared by the service's own
:func:`~service.pipeline.prepare.prepare_stacks` (uploaded masks, N4 as the server does) and
predicted by :func:`~service.pipeline.predict.predict` with stack consistency on. Every pose is
scored twice: against the truth and twin-min (the nearer of the truth and its left-right twin),
for the network's own poses and for the stack-consistent ones.

:class:`NoisyTwinEstimator` stands in for a network: per slice it returns the truth or its twin at
random plus 10 mm / 10 deg of noise, with MC samples spread like that noise (a calibrated
network) and a fifth of them on the other twin; it tests the service's half of the symmetry
independently of any model.
"""

from __future__ import annotations

import time
from collections import defaultdict
from collections.abc import Callable
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike, NDArray

from model_export.acquisitions import MOTION_LEVELS, SimulatedStack, simulate_acquisition
from model_export.pose_metrics import auroc, error_components
from service.geometry import anchors, se3, twin
from service.geometry.anchors import ed
from service.inference.estimator import PoseEstimate, shown, statistics
from service.inference.model_file import ModelInfo
from service.consistency.slice_order import SliceOrder
from service.pipeline.documents import stack_objects
from service.pipeline.predict import StackPrediction, predict
from service.pipeline.prepare import PreparedStack, StackUpload, prepare_stacks

ERROR_MM = 10.0
DISTINGUISHABLE_MM = 20.0
"""A slice whose truth and twin are nearer than this is its own twin within the error: both branches count as right."""
MIN_MASK_PIXELS = 20


class NoisyTwinEstimator:
    """Truth or twin (50 %) plus noise, per slice; set :attr:`truth` before each call."""

    def __init__(self, info: ModelInfo, rng: np.random.Generator, noise_deg: float = 10.0, noise_mm: float = 10.0,
                 other_twin_fraction: float = 0.2) -> None:
        self.info, self.rng = info, rng
        self.sigma = np.array([np.radians(noise_deg)] * 3 + [noise_mm] * 3) / np.sqrt(3.0)
        self.other = other_twin_fraction
        self.truth: NDArray | None = None
        self.chose_twin: NDArray | None = None

    def estimate(self, inputs: NDArray, mc_samples: int) -> PoseEstimate:
        assert self.truth is not None and len(self.truth) == len(inputs), "truth and slices out of step"
        n, plane = len(inputs), self.info.symmetry_plane_x_mm
        self.chose_twin = self.rng.random(n) < 0.5
        centre = np.where(self.chose_twin[:, None, None], twin.twin(self.truth, plane), self.truth)
        centre = centre @ se3.exp(self.rng.normal(0, 1, (n, 6)) * self.sigma)
        samples = centre[:, None] @ se3.exp(self.rng.normal(0, 1, (n, mc_samples, 6)) * self.sigma)
        flip = self.rng.random((n, mc_samples)) < self.other
        samples = np.where(flip[..., None, None], twin.twin(samples, plane), samples)
        est = statistics(anchors.encode(samples), "anchor", plane)
        seen = shown(inputs)                                      # as the network: an empty slice gets no pose
        return est if seen.all() else PoseEstimate.scattered(est.part(seen), seen)


class Scored:
    """Per-slice columns of one motion level, gathered over acquisitions."""

    def __init__(self) -> None:
        self.columns: dict[str, list[NDArray]] = defaultdict(list)

    def add(self, **columns: ArrayLike) -> None:
        for key, values in columns.items():
            self.columns[key].append(np.asarray(values))

    def array(self, key: str) -> NDArray:
        return np.concatenate(self.columns[key]) if self.columns[key] else np.zeros(0)


class _Reused:
    """An estimator's one answer, given again to each call with the same inputs (the stage's variants
    are compared on the same network poses)."""

    def __init__(self, estimator) -> None:  # noqa: ANN001
        self.estimator, self.info, self.last = estimator, estimator.info, None

    def estimate(self, inputs: NDArray, mc_samples: int) -> PoseEstimate:
        if self.last is None or not np.array_equal(self.last[0], inputs):
            self.last = (inputs, self.estimator.estimate(inputs, mc_samples))
        return self.last[1]


def prepare_acquisition(stacks: list[SimulatedStack], info: ModelInfo, bias_correction: bool = True,
                        ) -> tuple[list[PreparedStack], list[NDArray]]:
    """One simulated acquisition prepared as the server prepares uploads, and each stack's true
    network-frame poses ``[n, 4, 4]`` (the simulation's ``atlas_from_voxel`` through the service's
    own crop/centre)."""
    uploads = [StackUpload(f"{s.orientation}.nii.gz", s.volume, s.mask, f"{s.orientation}_mask.nii.gz") for s in stacks]
    prepared = prepare_stacks(uploads, info, bias_correction, workers=2)
    return prepared, [p.in_network_frame(s.atlas_from_voxel) for s, p in zip(stacks, prepared)]


def run_acquisition(stacks: list[SimulatedStack], estimator, mc_samples: int = 100,  # noqa: ANN001
                    bias_correction: bool = True, orders: tuple[str | None, ...] = (None,),
                    ) -> tuple[list[list[StackPrediction]], list[PreparedStack], list[NDArray]]:
    """Predict one acquisition as the server would, once per ``orders`` (``slice_order`` values;
    ``None``: not given) from one network pass; returns the stacks' predictions per order
    (:func:`~service.pipeline.documents.stack_objects` writes their answers), the prepared stacks and each
    stack's true network-frame poses."""
    prepared, truth = prepare_acquisition(stacks, estimator.info, bias_correction)
    if hasattr(estimator, "truth"):
        estimator.truth = np.concatenate(truth)
    once = _Reused(estimator)
    predictions = [predict(prepared, once, mc_samples, estimator.info.variance_threshold,
                           orders=None if order is None else [SliceOrder.parse(order)])[0] for order in orders]
    return predictions, prepared, truth


def acceptance_columns(final: NDArray, true: NDArray, expected: ArrayLike, variance: ArrayLike,
                       reasons: list[str | None], mask_pixels: NDArray, decidable: bool,
                       plane_x_mm: float) -> dict[str, NDArray]:
    """The per-slice columns of one stack's answer that the accept flags are calibrated on
    (:func:`~model_export.calibrate_acceptance.level_columns` reads them): E.D. of the returned poses
    ``final [n, 4, 4]`` against the truth and twin-min, their distance to their twin, the expected
    error and geodesic variance (a missing one, NaN or None, as inf), the reason a slice is not
    accepted ("" when it is), its mask pixels and whether its stack was decidable.

    Example (a slice 2 mm from its truth, 30 mm off the mid-sagittal plane; no expected error):
        >>> true = np.eye(4)[None].copy(); true[0, 0, 3] = 30.0
        >>> final = true.copy(); final[0, 1, 3] += 2.0
        >>> cols = acceptance_columns(final, true, [None], [1.0], [None], np.array([50]), True, 0.0)
        >>> cols["ed"].round(6).tolist(), cols["expected"].tolist(), cols["reason"].tolist()
        ([2.0], [inf], [''])
    """
    e = ed(final, true)
    n = len(e)
    missing = lambda values: np.array([np.nan if v is None else v for v in values], np.float64)  # noqa: E731
    expected, variance = missing(expected), missing(variance)
    return {"ed": e, "ed_min": np.minimum(e, ed(final, twin.twin(true, plane_x_mm))),
            "twin_mm": twin.twin_distance_mm(final, plane_x_mm),
            "expected": np.where(np.isfinite(expected), expected, np.inf),
            "variance": np.where(np.isfinite(variance), variance, np.inf),
            "reason": np.array([r or "" for r in reasons]), "mask_pixels": np.asarray(mask_pixels),
            "decidable": np.full(n, bool(decidable))}


def score(predictions: list[StackPrediction], prepared: list[PreparedStack], truth: list[NDArray],
          stacks: list[SimulatedStack], plane_x_mm: float, into: Scored) -> None:
    """Add one acquisition's per-slice errors to ``into``, with where each lies: its components
    against the nearer of the truth and twin (tilt, twist, centre, along the normal), its distance
    to its own twin, its depth in the stack (0 centre, 1 the outermost slice with >=
    :data:`MIN_MASK_PIXELS`) and its place in the acquisition (0 first, 1 last); and what the
    service knows of each slice besides its answer (:func:`slice_evidence`)."""
    for res, pred, p, true, sim in zip(stack_objects(predictions), predictions, prepared, truth, stacks):
        final = p.in_network_frame([s["atlas_from_voxel"] for s in res["slices"]])
        unseen = np.full((4, 4), np.nan)                # an empty slice is not shown to the network
        network = p.in_network_frame([unseen if s["network_atlas_from_voxel"] is None else s["network_atlas_from_voxel"]
                                      for s in res["slices"]])
        tw = twin.twin(true, plane_x_mm)
        e, e_tw = ed(final, true), ed(final, tw)
        stage = res["consistency"] or {}
        n = len(e)
        parts = error_components(final, np.where((e <= e_tw)[:, None, None], true, tw))
        k = np.arange(n)
        inside = k[p.prepared.mask_pixels >= MIN_MASK_PIXELS]
        mid, half = ((inside.min() + inside.max()) / 2.0, max((inside.max() - inside.min()) / 2.0, 1.0)) if len(inside) \
            else ((n - 1) / 2.0, max((n - 1) / 2.0, 1.0))
        times = np.asarray(sim.times, dtype=np.float64)
        # The motion the stage fitted: how far it put each slice from its rigid stack pose.
        rigid = rigid_poses(stage, sim.volume.affine, np.linalg.inv(p.network_from_voxel()))
        fitted = ed(final, rigid) if rigid is not None else np.full(n, np.nan)
        into.add(**acceptance_columns(final, true, [s.get("expected_error_mm") for s in res["slices"]],
                                      [s["geodesic_variance"] for s in res["slices"]],
                                      [s["reason"] for s in res["slices"]], p.prepared.mask_pixels,
                                      stage.get("decidable"), plane_x_mm),
                 ed_network=ed(network, true), moved_mm=ed(final, network),
                 motion_mm=true_motion_mm(sim.atlas_from_voxel, sim.volume.affine, true), fitted_motion_mm=fitted,
                 stack=np.full(n, len(into.columns["ed"])),
                 ed_network_min=twin.twin_min_ed(network, true, plane_x_mm),
                 right_branch=(e <= e_tw) | (ed(true, tw) < DISTINGUISHABLE_MM),
                 accepted=[s["accepted"] for s in res["slices"]],
                 orientation=[sim.orientation] * n,
                 branch_decided=np.full(n, bool(stage.get("branch_decided"))),
                 tilt_deg=parts["tilt_deg"], twist_deg=parts["twist_deg"], centre_mm=parts["centre_mm"],
                 off_plane_mm=parts["off_plane_mm"], depth=np.abs(k - mid) / half,
                 time=(times - times.min()) / max(float(np.ptp(times)), 1.0), input_noise=np.full(n, p.input_noise),
                 **slice_evidence(pred))


def slice_evidence(prediction: StackPrediction) -> dict[str, NDArray]:
    """Per slice of one stack, what the service knows besides its answer (NaN where a stage did not
    run): the network's MC mass on the other twin, the stage's expected E.D. before the image
    refinement, the image mismatch left after it over the request's median, and the refined pose's
    Laplace spread."""
    n = len(prediction.poses.poses)
    ic = prediction.poses.image_consistency
    nan = np.full(n, np.nan)
    return {"twin_mass": np.asarray(prediction.poses.twin_mass, np.float64),
            "expected_stage": nan if ic is None or ic.expected_before_mm is None else ic.expected_before_mm,
            "mismatch": nan if ic is None or ic.slice_mismatch is None else ic.slice_mismatch,
            "spread": nan if ic is None or ic.slice_spread_mm is None else ic.slice_spread_mm}


def rigid_poses(report: dict, scanner_from_voxel: NDArray, voxel_from_network: NDArray) -> NDArray | None:
    """Each slice's pose ``[n, 4, 4]`` (network frame -> atlas) under the rigid placement the stage
    reported for its stack (pooled across stacks when it was); None where the stack was undecidable."""
    rigid = report.get("pooled_atlas_from_scanner") or report.get("atlas_from_scanner")
    return None if rigid is None else np.asarray(rigid) @ scanner_from_voxel @ voxel_from_network


def true_motion_mm(atlas_from_voxel: NDArray, scanner_from_voxel: NDArray, poses: NDArray) -> NDArray:
    """Each slice's true motion: the E.D. between its pose ``poses[k]`` (network frame -> atlas) and
    where the stack's mean rigid placement (the Frechet mean of the slices' atlas_from_scanner) would
    put it.

    Example:
        >>> a = np.stack([np.eye(4)] * 4); a[0, 0, 3] = 8.0          # slice 0 moved 8 mm along x
        >>> true_motion_mm(a, np.eye(4), a).round(1).tolist()
        [6.0, 2.0, 2.0, 2.0]
    """
    atlas_from_scanner = atlas_from_voxel @ np.linalg.inv(scanner_from_voxel)
    still = se3.frechet_mean(atlas_from_scanner) @ np.linalg.inv(atlas_from_scanner) @ poses
    return ed(poses, still)


def summarise(sc: Scored) -> dict:
    """Per motion level: E.D. (mean, median, p90) against the truth and twin-min, before and after
    the stack stage, the right-branch fraction, the AUROC of the variance and acceptance."""
    keep = sc.array("mask_pixels") >= MIN_MASK_PIXELS
    out: dict = {"slices": int(keep.sum())}
    for key in ("ed", "ed_min", "ed_network", "ed_network_min"):
        v = sc.array(key)[keep]
        out[key] = {"mean": float(v.mean()), "median": float(np.median(v)), "p90": float(np.percentile(v, 90))}
    e, e_min, right = sc.array("ed")[keep], sc.array("ed_min")[keep], sc.array("right_branch")[keep].astype(bool)
    out["right_branch"] = float(right.mean())
    good = e_min < 15.0
    out["right_branch_twin_min_under_15mm"] = float(right[good].mean()) if good.any() else float("nan")
    var = sc.array("variance")[keep]
    out["auroc_variance_ed_over_10mm"] = auroc(np.nan_to_num(var, posinf=1e12), e > ERROR_MM)
    expected = sc.array("expected")[keep]
    out["auroc_expected_error_ed_over_10mm"] = auroc(np.nan_to_num(expected, posinf=1e12), e > ERROR_MM)
    out["auroc_expected_error_ed_min_over_10mm"] = auroc(np.nan_to_num(expected, posinf=1e12), e_min > ERROR_MM)
    out["expected_error_mm_rms"] = float(np.sqrt(np.mean(expected[np.isfinite(expected)] ** 2)))
    out["ed_rms"] = float(np.sqrt(np.mean(e ** 2)))
    acc = sc.array("accepted")[keep].astype(bool)
    out["accepted"] = float(acc.mean())
    out["accepted_ed_mean"] = float(e[acc].mean()) if acc.any() else float("nan")
    out["accepted_ed_min_mean"] = float(e_min[acc].mean()) if acc.any() else float("nan")
    out["decidable_stacks"] = float(sc.array("decidable")[keep].mean())
    decided = sc.array("branch_decided")[keep].astype(bool)
    out["branch_decided_slices"] = float(decided.mean())
    out["right_branch_where_decided"] = float(right[decided].mean()) if decided.any() else float("nan")
    both = decided & good
    out["right_branch_where_decided_twin_min_under_15mm"] = float(right[both].mean()) if both.any() else float("nan")
    out["components"] = {key: float(sc.array(key)[keep].mean())
                         for key in ("tilt_deg", "twist_deg", "centre_mm", "off_plane_mm")}
    thirds = lambda x: np.minimum((x * 3).astype(int), 2)  # noqa: E731
    for key, names in (("depth", ("centre", "middle", "outer")), ("time", ("start", "middle", "end"))):
        which = thirds(np.clip(sc.array(key)[keep], 0.0, 1.0))
        out[f"ed_by_{key}"] = {name: float(e[which == i].mean()) if (which == i).any() else float("nan")
                               for i, name in enumerate(names)}
        out[f"ed_min_by_{key}"] = {name: float(e_min[which == i].mean()) if (which == i).any() else float("nan")
                                   for i, name in enumerate(names)}
    orientation = sc.array("orientation")[keep]
    out["by_orientation"] = {o: {"ed_mean": float(e[orientation == o].mean()),
                                 "ed_min_mean": float(e_min[orientation == o].mean()),
                                 "right_branch": float(right[orientation == o].mean())}
                             for o in np.unique(orientation)}
    return out


def evaluate_acquisitions(volumes: list, estimator, rng: np.random.Generator, levels: tuple[str, ...] = tuple(MOTION_LEVELS),  # noqa: ANN001
                          per_volume: int = 1, mc_samples: int = 100, bias_correction: bool = True,
                          told: tuple[str, ...] = (), slices: Path | None = None,
                          progress: Callable[[str], object] | None = None, **sim: float) -> dict[str, dict]:
    """Score ``per_volume`` acquisitions of each of ``volumes`` (objects with ``image``, ``mask``,
    ``affine``) at each motion level; returns :func:`summarise` per level. Each of ``told``
    (``slice_order`` values, e.g. ``interleaved``: what the simulation acquires) adds a row per
    level, ``"<level>, told <order>"``, scored on the same network poses. ``slices``: also write every
    per-slice column of every row to this ``.npz`` (keys ``"<row>/<column>"``; ``stack`` numbers the
    stacks of a row), for analyses the summary does not make. ``progress``: told a line after each
    acquisition (its level, count and the seconds so far: N4 and every stage run on each stack)."""
    plane = estimator.info.symmetry_plane_x_mm
    out, columns = {}, {}
    orders = (None, *told)
    start, done, total = time.perf_counter(), 0, len(levels) * len(volumes) * per_volume
    for level in levels:
        scored = [Scored() for _ in orders]
        for vol in volumes:
            for _ in range(per_volume):
                stacks = simulate_acquisition(vol.image, vol.mask, vol.affine, rng, level, **sim)
                predictions, prepared, truth = run_acquisition(stacks, estimator, mc_samples, bias_correction, orders)
                for res, sc in zip(predictions, scored):
                    score(res, prepared, truth, stacks, plane, sc)
                done += 1
                if progress is not None:
                    progress(f"{level}: acquisition {done} of {total} ({time.perf_counter() - start:.0f} s)")
        for order, sc in zip(orders, scored):
            row = level if order is None else f"{level}, told {order}"
            out[row] = summarise(sc)
            columns.update({f"{row}/{key}": sc.array(key) for key in sc.columns})
    if slices is not None:
        np.savez_compressed(slices, **columns)
    return out


def _auc(value: float) -> str:
    """An AUROC for the report; none where no slice is over the error it ranks for.

    Example:
        >>> _auc(0.8612), _auc(float("nan"))
        ('0.86', 'none > 10 mm')
    """
    return f"{value:.2f}" if np.isfinite(value) else "none > 10 mm"


def markdown(summary: dict[str, dict], title: str) -> str:
    """A report table: one row per motion level."""
    rows = [f"# {title}", "",
            "E.D. in mm over slices with >= 20 mask pixels; 'network' = the network's own per-slice poses, "
            "'consistent' = after the stack-consistency stage; twin-min = the nearer of the truth and its "
            "left-right twin.", "",
            "| motion | slices | network E.D. mean / median / p90 | network twin-min mean | consistent E.D. mean / "
            "median / p90 | consistent twin-min mean | right branch | right branch (twin-min < 15 mm) | "
            "AUROC var > 10 mm | AUROC expected_error_mm > 10 mm (truth / twin-min) | RMS E.D. / RMS expected_error_mm | "
            "accepted (their E.D. mean, truth / twin-min) | "
            "decidable stacks | branch decided | right branch where decided (all / twin-min < 15 mm) |",
            "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for level, s in summary.items():
        f = lambda d: f"{d['mean']:.1f} / {d['median']:.1f} / {d['p90']:.1f}"  # noqa: E731
        rows.append(f"| {level} | {s['slices']} | {f(s['ed_network'])} | {s['ed_network_min']['mean']:.1f} | "
                    f"{f(s['ed'])} | {s['ed_min']['mean']:.1f} | {100 * s['right_branch']:.1f} % | "
                    f"{100 * s['right_branch_twin_min_under_15mm']:.1f} % | {_auc(s['auroc_variance_ed_over_10mm'])} | "
                    f"{_auc(s['auroc_expected_error_ed_over_10mm'])} / {_auc(s['auroc_expected_error_ed_min_over_10mm'])} | "
                    f"{s['ed_rms']:.1f} / {s['expected_error_mm_rms']:.1f} | "
                    f"{100 * s['accepted']:.0f} % ({s['accepted_ed_mean']:.1f} / {s['accepted_ed_min_mean']:.1f}) | "
                    f"{100 * s['decidable_stacks']:.0f} % | "
                    f"{100 * s['branch_decided_slices']:.0f} % | {100 * s['right_branch_where_decided']:.1f} % / "
                    f"{100 * s['right_branch_where_decided_twin_min_under_15mm']:.1f} % |")
    rows += ["", "Where the consistent poses' error lies (means; against the nearer of the truth and its twin; "
             "depth: thirds from the stack's centre to its outermost slice; time: thirds of the acquisition):", "",
             "| motion | tilt (deg) | twist (deg) | centre (mm) | along the normal (mm) | E.D. by depth: centre / "
             "middle / outer | E.D. by time: start / middle / end |", "|---|---|---|---|---|---|---|"]
    for level, s in summary.items():
        c, d, t = s["components"], s["ed_min_by_depth"], s["ed_min_by_time"]
        rows.append(f"| {level} | {c['tilt_deg']:.1f} | {c['twist_deg']:.1f} | {c['centre_mm']:.1f} | "
                    f"{c['off_plane_mm']:.1f} | {d['centre']:.1f} / {d['middle']:.1f} / {d['outer']:.1f} | "
                    f"{t['start']:.1f} / {t['middle']:.1f} / {t['end']:.1f} |")
    return "\n".join(rows) + "\n"
