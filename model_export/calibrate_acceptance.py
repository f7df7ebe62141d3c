"""Calibrate a model's accept flags on the pipeline's final poses.

Simulated 3-stack acquisitions of the validation volumes at every motion level
(:data:`model_export.acquisitions.MOTION_LEVELS` but ``extreme``) go through the very pipeline the
server runs (:func:`~model_export.evaluate_acquisitions.evaluate_acquisitions`), with the model's
expected-error floor at 0 and no expected-error limit. From every slice's final E.D. (against the
truth), its expected error, its variance and the other reasons it may be rejected for:

1. ``twin_risk_logit``: the chance that a slice of a stack the stage found consistent sits
   on its mirror twin (nearer the twin than the truth), as a logistic in its distance to the twin
   (:func:`fit_twin_risk`, over the :data:`TARGET_LEVELS`); each such slice's expected error then
   grows by that chance times its squared distance to the twin, as the service adds it
   (:func:`~service.pipeline.predict.add_unseen_errors`);
2. ``expected_error_floor_mm``: the error no stage sees (the request's placement in the atlas
   frame), added in quadrature to every slice's expected error; chosen so that RMS E.D. / RMS
   expected error is nearest 1 at every level (the largest ``|log ratio|`` smallest);
3. ``variance_threshold``: the :data:`GOOD_VARIANCE_QUANTILE` quantile of the variance of the slices
   whose E.D. is under :data:`GOOD_MM`: the network's spread for one slice alone does not reject a
   good fused pose;
4. ``max_expected_error_mm``: the largest limit under which at most :data:`MAX_BAD_ACCEPTED` of the
   slices whose E.D. exceeds :data:`BAD_MM` are accepted at every level of :data:`TARGET_LEVELS` that
   has :data:`MIN_BAD_SLICES` such slices or more (every other reason applied too); where no limit
   does that, the one that accepts the fewest.

Example:
    >>> ed = {"a": np.array([1.0, 2.0, 3.0]), "b": np.array([4.0, 6.0, 8.0])}
    >>> expected = {"a": np.array([0.5, 0.5, 0.5]), "b": np.array([5.0, 6.0, 7.0])}
    >>> round(choose_floor(ed, expected), 1)           # a's RMS E.D. 2.2 mm, its expected error 0.5 mm
    2.1
"""

from __future__ import annotations

import tempfile
from copy import copy
from dataclasses import replace
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from model_export.evaluate_acquisitions import MIN_MASK_PIXELS, evaluate_acquisitions
from service.geometry import twin
from service.inference import acceptance
from service.inference.model_file import ModelInfo

LEVELS = ("mild", "moderate", "jumps", "independent")
TARGET_LEVELS = ("mild", "moderate", "jumps")
"""The levels the limit must hold at (``independent`` is reported beside them)."""
GOOD_MM, BAD_MM = 5.0, 10.0
MAX_BAD_ACCEPTED = 0.10
MIN_BAD_SLICES = 20
"""A level's share of slices over :data:`BAD_MM` accepted judges a limit only where it has this many:
mild motion has only a few such slices, and one of them accepted would decide the limit by one
slice (the counts: docs/reports/accuracy-analyses.md, "Accept flags: the calibration's sample
sizes")."""
GOOD_VARIANCE_QUANTILE = 99.5
PER_VOLUME = 8
"""Acquisitions per validation volume and motion level: enough slices over :data:`BAD_MM` at jumping
motion that one slice moves the accepted share little, and the limit holds between runs of the
same acquisitions with other MC draws (the counts: docs/reports/accuracy-analyses.md, "Accept
flags: the calibration's sample sizes")."""
FLOORS_MM = np.arange(0.0, 4.01, 0.1)
LIMITS_MM = np.arange(2.0, 12.001, 0.1)
MIN_TWIN_SLICES = 10
"""Slices on their twin needed to fit :func:`fit_twin_risk` (fewer: no twin risk)."""
OTHER_REASONS = (acceptance.EMPTY, acceptance.DEGENERATE, acceptance.OUTSIDE, acceptance.INCONSISTENT)


def rms(x: NDArray) -> float:
    x = np.asarray(x, dtype=np.float64)
    x = x[np.isfinite(x)]
    return float(np.sqrt(np.mean(x ** 2))) if len(x) else float("nan")


RIDGE = 1e-3
"""L2 penalty on the twin risk's two coefficients: keeps the fit finite where the slices on their
twin and the others are separable by distance."""


def fit_twin_risk(distance_mm: NDArray, on_twin: NDArray, iterations: int = 100) -> tuple[float, float] | None:
    """``(a, b)`` of the logistic ``P(on twin) = 1 / (1 + exp(-(a + b d)))`` by penalised maximum
    likelihood (Newton's method, :data:`RIDGE`; slices with a non-finite distance left out). None
    where the chance does not fall with the distance (``b >= 0``), the fit does not converge, or
    no slice sits on its twin.

    Example:
        >>> rng = np.random.default_rng(0)
        >>> d = rng.uniform(0.0, 60.0, 20000)
        >>> on = rng.random(20000) < twin.twin_risk(d, (-1.0, -0.1))
        >>> [round(v, 1) for v in fit_twin_risk(d, on)]
        [-1.0, -0.1]
        >>> fit_twin_risk(d, d > 30.0) is None                  # the chance grows with the distance
        True
    """
    d = np.asarray(distance_mm, np.float64)
    ok = np.isfinite(d)
    d, y = d[ok], np.asarray(on_twin, np.float64)[ok]
    x = np.stack([np.ones(len(d)), d], axis=1)
    if not 0.0 < y.sum() < len(y):
        return None
    w = np.array([np.log(y.mean() / (1.0 - y.mean())), 0.0])
    for _ in range(iterations):
        p = twin.twin_risk(d, (w[0], w[1]))
        hess = (x * (p * (1.0 - p))[:, None]).T @ x + RIDGE * np.eye(2)
        step = np.linalg.solve(hess, x.T @ (y - p) - RIDGE * w)
        w = w + step
        if np.abs(step).max() < 1e-9:
            break
    else:
        return None
    return (float(w[0]), float(w[1])) if w[1] < 0 and np.all(np.isfinite(w)) else None


def choose_twin_risk(by_level: dict[str, dict[str, NDArray]]) -> tuple[float, float] | None:
    """:func:`fit_twin_risk` over the :data:`TARGET_LEVELS`' slices of stacks the stage found
    consistent (``decidable``), those nearer their twin than their truth counted as on it (None
    without a ``twin_mm`` column or with fewer than :data:`MIN_TWIN_SLICES` slices on their twin).

    Example (one level, 40 slices 2-80 mm from their twins, the 12 nearest on it):
        >>> c = {"twin_mm": np.linspace(2.0, 80.0, 40), "decidable": np.ones(40, bool),
        ...      "ed": np.r_[np.full(12, 3.0), np.ones(28)], "ed_min": np.ones(40)}
        >>> a, b = choose_twin_risk({"mild": c}); b < 0
        True
        >>> choose_twin_risk({"mild": {**c, "decidable": np.arange(40) >= 5}}) is None   # 7 on it: too few
        True
    """
    cols = [c for k, c in by_level.items() if k in TARGET_LEVELS and "twin_mm" in c]
    if not cols:
        return None
    decided = np.concatenate([c["decidable"].astype(bool) for c in cols])
    d = np.concatenate([c["twin_mm"] for c in cols])[decided]
    on_twin = np.concatenate([c["ed"] > c["ed_min"] for c in cols])[decided]
    return fit_twin_risk(d, on_twin) if on_twin.sum() >= MIN_TWIN_SLICES else None


def with_twin_risk(columns: dict[str, NDArray], logit: tuple[float, float] | None) -> dict[str, NDArray]:
    """``columns`` with the expected error of each slice of a consistent stack grown by what its twin
    adds (:func:`~service.geometry.twin.twin_variance`, as the service adds it).

    Example:
        >>> c = {"expected": np.array([3.0, 3.0]), "twin_mm": np.array([10.0, 10.0]), "decidable": np.array([True, False])}
        >>> with_twin_risk(c, (-1.0, -0.1))["expected"].round(2).tolist()                  # sqrt(9 + 11.92)
        [4.57, 3.0]
    """
    if logit is None or "twin_mm" not in columns:
        return columns
    extra = np.where(columns["decidable"].astype(bool), twin.twin_variance(columns["twin_mm"], logit), 0.0)
    return {**columns, "expected": np.sqrt(columns["expected"] ** 2 + extra)}


def choose_floor(ed: dict[str, NDArray], expected: dict[str, NDArray]) -> float:
    """The floor (mm) that brings RMS E.D. / RMS expected error nearest 1 at every level at once."""
    worst = [max(abs(np.log(rms(ed[k]) / rms(np.hypot(expected[k], f)))) for k in ed) for f in FLOORS_MM]
    return float(FLOORS_MM[int(np.argmin(worst))])


def accepted(columns: dict[str, NDArray], floor_mm: float, variance_threshold: float, limit_mm: float) -> NDArray:
    """Which slices the service would accept with these settings (``columns``: one level's slices)."""
    unsure, high = acceptance.over_limits(columns["variance"], variance_threshold,
                                          np.hypot(columns["expected"], floor_mm), limit_mm)
    return ~np.isin(columns["reason"], OTHER_REASONS) & ~unsure & ~high


def rates(columns: dict[str, NDArray], ok: NDArray) -> dict[str, float]:
    """The share of good (E.D. < 5 mm) and of bad (> 10 mm) slices accepted, against the truth and twin-min."""
    out = {}
    for name, key in (("", "ed"), ("_twin_min", "ed_min")):
        e = columns[key]
        good, bad = e < GOOD_MM, e > BAD_MM
        out[f"good_accepted{name}"] = float(ok[good].mean()) if good.any() else float("nan")
        out[f"bad_accepted{name}"] = float(ok[bad].mean()) if bad.any() else float("nan")
        out[f"bad_slices{name}"] = int(bad.sum())
    out["accepted"] = float(ok.mean())
    return out


def calibrate(by_level: dict[str, dict[str, NDArray]]) -> dict:
    """The four settings (module docstring) from each level's slice columns, and how they do per level.
    :class:`ValueError` where no slice lies within :data:`GOOD_MM` of the truth: a model that places no
    slice well (a short run) gives no variance of a good slice to set the threshold by."""
    good = sum(int((np.asarray(c["ed"]) < GOOD_MM).sum()) for c in by_level.values())
    if not good:
        raise ValueError(f"accept flags: none of the {sum(len(c['ed']) for c in by_level.values())} slices lies within "
                         f"{GOOD_MM:g} mm of the truth; the model cannot be calibrated yet (train it longer, or start "
                         "from a shipped checkpoint with train --init)")
    logit = choose_twin_risk(by_level)
    by_level = {k: with_twin_risk(c, logit) for k, c in by_level.items()}
    floor = choose_floor({k: c["ed"] for k, c in by_level.items()}, {k: c["expected"] for k, c in by_level.items()})
    good_var = np.concatenate([c["variance"][c["ed"] < GOOD_MM] for c in by_level.values()])
    variance_threshold = float(np.percentile(good_var[np.isfinite(good_var)], GOOD_VARIANCE_QUANTILE))
    targets = [k for k in TARGET_LEVELS if k in by_level]
    judged = [k for k in targets if int((by_level[k]["ed"] > BAD_MM).sum()) >= MIN_BAD_SLICES] or targets

    def worst_bad(limit: float) -> float:
        r = [rates(by_level[k], accepted(by_level[k], floor, variance_threshold, limit))["bad_accepted"] for k in judged]
        return float(np.nanmax(r)) if np.isfinite(r).any() else 0.0

    bad = np.array([worst_bad(t) for t in LIMITS_MM])
    feasible = np.flatnonzero(bad <= MAX_BAD_ACCEPTED)
    limit = float(LIMITS_MM[feasible[-1]] if len(feasible) else LIMITS_MM[int(np.argmin(bad))])
    levels = {}
    for k, c in by_level.items():
        levels[k] = {"slices": len(c["ed"]), "ed_mean": float(c["ed"].mean()), "ed_twin_min_mean": float(c["ed_min"].mean()),
                     "rms_ed_over_rms_expected": rms(c["ed"]) / rms(np.hypot(c["expected"], floor)),
                     "rms_ed_over_rms_expected_before": rms(c["ed"]) / rms(c["expected"]),
                     **rates(c, accepted(c, floor, variance_threshold, limit))}
    return {"twin_risk_logit": None if logit is None else list(logit),
            "expected_error_floor_mm": floor, "variance_threshold": variance_threshold, "max_expected_error_mm": limit,
            "limit_meets_target": bool(len(feasible)), "judged_levels": judged, "levels": levels,
            "trade_off": {f"{t:g}": v for t, v in trade_off(by_level, floor, variance_threshold).items()}}


def level_columns(npz: Path | list[Path], levels: tuple[str, ...]) -> dict[str, dict[str, NDArray]]:
    """Each level's per-slice columns (slices with brain) from an ``evaluate_acquisitions`` ``.npz``;
    from several, their slices pooled (a level that a file does not hold comes from the others):
    more acquisitions, fewer slices over :data:`BAD_MM` that a limit tips on alone."""
    files = [Path(npz)] if isinstance(npz, (str, Path)) else [Path(p) for p in npz]
    parts: dict[str, list[dict[str, NDArray]]] = {lv: [] for lv in levels}
    for path in files:
        with np.load(path) as f:
            for lv in levels:
                if f"{lv}/mask_pixels" not in f:
                    continue
                keep = f[f"{lv}/mask_pixels"] >= MIN_MASK_PIXELS
                parts[lv].append({key: f[f"{lv}/{key}"][keep] for key in ("ed", "ed_min", "expected", "variance", "reason",
                                                                       "twin_mm", "decidable") if f"{lv}/{key}" in f})
    out = {}
    for lv, found in parts.items():
        if not found:
            continue
        keys = set.intersection(*(set(c) for c in found))
        out[lv] = {key: np.concatenate([c[key] for c in found]) for key in sorted(keys)}
        out[lv]["expected"] = np.where(np.isinf(out[lv]["expected"]), np.nan, out[lv]["expected"])
    return out


def measuring(info: ModelInfo) -> ModelInfo:
    """``info`` with its floor, limit and twin risk switched off: the expected errors and flags as
    they are measured for :func:`calibrate` (which chooses those three); its noise and frame errors
    too, which are calibrated after the accept flags, on their settings (``calibrate-noise``,
    ``calibrate-frame``): a model that carries them is calibrated again as it was first."""
    return replace(info, expected_error_floor_mm=0.0, max_expected_error_mm=None, twin_risk_logit=None, noise_error=None,
                   frame_error=None)


def measure(estimator, volumes: list, per_volume: int, seed: int = 1, levels: tuple[str, ...] = LEVELS,  # noqa: ANN001
            slices: Path | None = None) -> dict:
    """:func:`calibrate` on acquisitions of ``volumes`` through the pipeline, the estimator's own
    floor, limit and twin risk switched off while they are measured; ``slices``: keep every slice's columns
    there (``.npz``, as :func:`~model_export.evaluate_acquisitions.evaluate_acquisitions` writes them)."""
    estimator = copy(estimator)                  # the caller's keeps its calibration
    estimator.info = measuring(estimator.info)
    with tempfile.TemporaryDirectory() as tmp:
        npz = slices or Path(tmp) / "slices.npz"
        evaluate_acquisitions(volumes, estimator, np.random.default_rng(seed), levels=levels, per_volume=per_volume,
                              slices=npz)
        return calibrate(level_columns(npz, levels))


FLAGS = ("twin_risk_logit", "expected_error_floor_mm", "variance_threshold", "max_expected_error_mm")
"""What :func:`calibrate` chooses, under the names of the model's metadata the service reads."""


def flag_metadata(result: dict) -> dict[str, str]:
    """The calibrated :data:`FLAGS` of ``result`` as metadata values (4 significant digits; the twin
    risk's two coefficients comma-separated, empty where none was fitted).

    Example:
        >>> flag_metadata({"twin_risk_logit": [-1.234, -0.13579], "expected_error_floor_mm": 2.1234,
        ...                "variance_threshold": 484.47, "max_expected_error_mm": 4.2})
        {'twin_risk_logit': '-1.234,-0.1358', 'expected_error_floor_mm': '2.123', 'variance_threshold': '484.5', 'max_expected_error_mm': '4.2'}
    """
    def text(value: object) -> str:
        if value is None:
            return ""
        return ",".join(f"{v:.4g}" for v in value) if isinstance(value, (list, tuple)) else f"{value:.4g}"

    return {k: text(result.get(k)) for k in FLAGS}


def trade_off(by_level: dict[str, dict[str, NDArray]], floor_mm: float, variance_threshold: float,
              limits_mm: tuple[float, ...] = (3.0, 4.0, 5.0, 6.0, 8.0)) -> dict[float, dict[str, tuple[float, float]]]:
    """For each limit, each level's share of good and of bad slices accepted (what a request's
    ``max_expected_error_mm`` buys)."""
    out = {}
    for limit in limits_mm:
        row = {}
        for k, c in by_level.items():
            r = rates(c, accepted(c, floor_mm, variance_threshold, limit))
            row[k] = (r["good_accepted"], r["bad_accepted"])
        out[limit] = row
    return out


def _logit_text(logit: list[float] | None) -> str:
    """The twin risk's curve in words, with its chance at a few distances."""
    if logit is None:
        return "none fitted"
    at = ", ".join(f"{d} mm {float(twin.twin_risk(d, tuple(logit))):.1%}" for d in (5, 10, 20, 40))
    return f"logit {logit[0]:.3f} {logit[1]:+.4f} d (chance on the twin at {at})"


def share(x: float) -> str:
    """A share as a percentage; ``-`` where there was nothing to count."""
    return f"{x:.0%}" if np.isfinite(x) else "-"


def markdown(result: dict, title: str) -> str:
    """The calibration's report: the settings, then per level the accuracy and what the flags accept."""
    rows = [f"# {title}", "",
            f"- twin risk: {_logit_text(result.get('twin_risk_logit'))}",
            f"- expected-error floor: {result['expected_error_floor_mm']:.1f} mm (in quadrature)",
            f"- variance threshold: {result['variance_threshold']:.1f} ({GOOD_VARIANCE_QUANTILE} % of slices with E.D. < 5 mm under it)",
            f"- max expected error: {result['max_expected_error_mm']:.2f} mm "
            f"({'meets' if result['limit_meets_target'] else 'does NOT meet'} <= {MAX_BAD_ACCEPTED:.0%} of E.D. > 10 mm "
            f"accepted at {', '.join(result.get('judged_levels', TARGET_LEVELS))}; a level with fewer than "
            f"{MIN_BAD_SLICES} such slices is reported, not judged)", "",
            "| motion | slices | E.D. mean (truth / twin-min) | RMS E.D. / RMS expected (before floor) | accepted "
            "| E.D. < 5 mm accepted (truth / twin-min) | E.D. > 10 mm accepted (truth / twin-min; slices) |",
            "|---|---|---|---|---|---|---|"]
    for k, v in result["levels"].items():
        rows.append(f"| {k} | {v['slices']} | {v['ed_mean']:.2f} / {v['ed_twin_min_mean']:.2f} | "
                    f"{v['rms_ed_over_rms_expected']:.2f} ({v['rms_ed_over_rms_expected_before']:.2f}) | {share(v['accepted'])} | "
                    f"{share(v['good_accepted'])} / {share(v['good_accepted_twin_min'])} | "
                    f"{share(v['bad_accepted'])} / {share(v['bad_accepted_twin_min'])} "
                    f"({v['bad_slices']} / {v['bad_slices_twin_min']}) |")
    rows += ["", "What other limits accept (`max_expected_error_mm`; E.D. < 5 mm / E.D. > 10 mm accepted, against the truth):",
             "", "| limit (mm) | " + " | ".join(result["levels"]) + " |", "|---|" + "---|" * len(result["levels"])]
    for limit, row in result["trade_off"].items():
        rows.append(f"| {limit} | " + " | ".join(f"{share(g)} / {share(b)}" for g, b in row.values()) + " |")
    return "\n".join(rows) + "\n"
