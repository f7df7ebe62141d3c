"""An exported SVRnet model: the ONNX file, its metadata, an onnxruntime session.

Example (with a model file at hand):
    >>> model = load_model(Path("service/models/default/model.onnx"))  # doctest: +SKIP
    >>> model.info.label_type, model.info.input_size                     # doctest: +SKIP
    ('anchor', 96)
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
import onnxruntime as ort
from numpy.typing import NDArray

from service.core.checksum import file_sha256
from service.core.onnx import session_options, session_threads
from service.geometry import encodings
from service.geometry.twin import DEFAULT_PLANE_X_MM
from service.inference.views import view_count

INPUT_SLICES, INPUT_PASSES, OUTPUT_LABELS = "slices", "passes", "labels"
DRAWS_PREFIX = "dropout_uniform_"
"""Inputs ``dropout_uniform_<k> [1, N, F]`` of a model whose MC-dropout draws are fed, not drawn in
the graph: the uniform numbers the ``k``-th dropout layer's masks are cut from (``>= p`` keeps a
unit), one row per pass, shared by the slices of a call (``model_export.export.fix_draws``)."""
DEFAULT_MC_SEED = 0
"""The seed of a model whose metadata name none (``mc_seed``)."""
MIN_DRAWN_PASSES = 128
"""Passes drawn at least, per draw: a request's passes are a prefix of them."""


@dataclass(frozen=True)
class ModelInfo:
    """What the service needs to know about a model, read from the ONNX metadata."""

    name: str
    version: str
    backbone: str
    label_type: str
    input_size: int
    pixel_spacing_mm: float
    variance_threshold: float
    dropout_p: float
    atlas_id: str
    trained_on: str
    sha256: str
    symmetry_plane_x_mm: float = DEFAULT_PLANE_X_MM
    mc_error_scale: float = 1.0
    """Calibration: expected E.D. of a pose = ``mc_error_scale`` x its MC spread (``PoseEstimate.spread_mm``)."""
    mc_error_shape: tuple[float, ...] | None = None
    """Calibration: the error's variance per coordinate of the network frame, mean 1 (rotation about
    x, y, normal; translation along x, y, normal; :func:`service.consistency.error_shape.error_shape`);
    None (not calibrated): the stage weighs the coordinates alike."""
    mc_error_depth_gain: float = 0.0
    """Calibration: the error's variance outgrows ``mc_error_scale x`` the spread by ``1 + gain rho^2``
    towards a stack's outer slices (:func:`service.consistency.error_shape.depth_gain`)."""
    expected_error_floor_mm: float = 0.0
    """Calibration: the part of every returned pose's error that no stage sees (the request's
    placement in the atlas frame); added in quadrature to each slice's expected error."""
    twin_risk_logit: tuple[float, float] | None = None
    """Calibration: ``(a, b)``, the chance that a slice of a stack the stage found consistent sits
    on its mirror twin, ``1 / (1 + exp(-(a + b d)))`` at distance ``d`` (mm) from it
    (:func:`service.geometry.twin.twin_risk`); None (not calibrated): no such risk is added."""
    max_expected_error_mm: float | None = None
    """Calibration: the default ``max_expected_error_mm`` of the accept flag (``high_expected_error``);
    None (not calibrated): slices are judged by their variance alone unless a request sets it."""
    noise_error: tuple[float, float] | None = None
    """Calibration: ``(onset, slope)``, the error (mm) a stack's slices carry beyond their MC spread
    when its inputs are noisier than the network learnt, ``slope x max(0, input_noise - onset)``
    (:func:`service.preprocess.noise.noise_error_mm`); None (not calibrated): none is added."""
    frame_error: tuple[float, float] | None = None
    """Calibration: ``(onset, slope)``, the error (mm) a request's placement in the atlas frame carries
    beyond the floor when the network is less sure of its slices, ``slope x max(0, sigma - onset)``,
    ``sigma`` the request's network error (:func:`service.consistency.frame_error.frame_error_mm`);
    None (not calibrated): none is added."""
    tta_views: int = 1
    """Test-time views the MC samples are shared among (:mod:`service.inference.views`); the variance
    threshold and ``mc_error_scale`` were calibrated with them."""
    mc_seed: int | None = None
    """The seed of the model's fixed MC-dropout draws (metadata ``mc_seed``, written with its
    :data:`DRAWS_PREFIX` inputs); None: the graph draws its own at every call."""
    licences: str = ""
    """The licences of the model's training data, which the model inherits (metadata ``licences``;
    empty where the file names none)."""
    metadata: dict[str, str] = field(default_factory=dict, repr=False)

    def reference(self, name: str | None = None) -> dict[str, str]:
        """The model as an answer names it: ``name`` (the name it is served under; default its own),
        ``version``, ``backbone`` and ``sha256`` (``/v1/predict``'s ``model``, a stream's ``ready``,
        a job's provenance, ``GET /v1/models``).

        Example:
            >>> info = ModelInfo("default", "2.11.2", "resnet18", "anchor", 96, 1.25, 400.0, 0.5, "", "", "ab")
            >>> info.reference("served")
            {'name': 'served', 'version': '2.11.2', 'backbone': 'resnet18', 'sha256': 'ab'}
        """
        return {"name": self.name if name is None else name, "version": self.version, "backbone": self.backbone,
                "sha256": self.sha256}

    @classmethod
    def from_metadata(cls, meta: dict[str, str], sha256: str) -> "ModelInfo":
        try:
            return cls(
                name=meta["name"], version=meta["version"], backbone=meta["backbone"], label_type=meta["label_type"],
                input_size=int(meta["input_size"]), pixel_spacing_mm=float(meta["pixel_spacing_mm"]),
                variance_threshold=float(meta["variance_threshold"]), dropout_p=float(meta.get("dropout_p", 0.5)),
                atlas_id=meta.get("atlas_id", ""), trained_on=meta.get("training_data", ""), sha256=sha256,
                licences=meta.get("licences", ""),
                symmetry_plane_x_mm=float(meta.get("symmetry_plane_x_mm", DEFAULT_PLANE_X_MM)),
                mc_error_scale=float(meta.get("mc_error_scale", 1.0)), tta_views=view_count(meta.get("tta_views", 1), "tta_views"),
                mc_error_shape=_shape(meta.get("mc_error_shape", "")),
                mc_error_depth_gain=float(meta.get("mc_error_depth_gain", 0.0)),
                expected_error_floor_mm=float(meta.get("expected_error_floor_mm", 0.0)),
                max_expected_error_mm=float(meta["max_expected_error_mm"]) if meta.get("max_expected_error_mm") else None,
                twin_risk_logit=_logit(meta.get("twin_risk_logit", "")),
                noise_error=_hinge(meta.get("noise_error", ""), "noise_error", 1.0, "in [0, 1)"),
                frame_error=_hinge(meta.get("frame_error", ""), "frame_error", np.inf, "(mm, not negative)"),
                mc_seed=int(meta["mc_seed"]) if meta.get("mc_seed") else None,
                metadata=dict(meta),
            )
        except (KeyError, ValueError) as exc:
            raise ValueError(f"model metadata incomplete or invalid: {exc}") from exc


def _shape(text: str) -> tuple[float, ...] | None:
    """``mc_error_shape`` from its metadata text (six comma-separated positive numbers; absent: None)."""
    if not text:
        return None
    shape = tuple(float(x) for x in text.split(","))
    if len(shape) != 6 or not all(x > 0 for x in shape):
        raise ValueError(f"mc_error_shape must be six positive numbers, not {text!r}")
    return shape


def _hinge(text: str, field: str, onset_below: float, onset_text: str) -> tuple[float, float] | None:
    """A hinge calibration ``(onset, slope)`` from its metadata text: an onset in ``[0, onset_below)``
    and a non-negative slope (absent or empty: None); a :class:`ValueError` naming ``field`` else.

    Example (the noise error's onset is a share of the bright end, the frame error's a distance):
        >>> _hinge("0.1,40", "noise_error", 1.0, "in [0, 1)"), _hinge("13,0.5", "frame_error", np.inf, "(mm)")
        ((0.1, 40.0), (13.0, 0.5))
        >>> _hinge("", "frame_error", np.inf, "(mm)") is None
        True
    """
    if not text:
        return None
    try:
        values = tuple(float(x) for x in text.split(","))
    except ValueError:
        values = ()
    if len(values) != 2 or not (0.0 <= values[0] < onset_below and 0.0 <= values[1] < np.inf):
        raise ValueError(f"{field} must be an onset {onset_text} and a non-negative slope, not {text!r}")
    return values[0], values[1]


def _logit(text: str) -> tuple[float, float] | None:
    """``twin_risk_logit`` from its metadata text (two comma-separated finite numbers, the slope
    negative; absent or empty: None).

    Example:
        >>> _logit("-0.58,-0.186"), _logit("")
        ((-0.58, -0.186), None)
    """
    if not text:
        return None
    a, b = (float(x) for x in text.split(","))
    if not (np.isfinite(a) and np.isfinite(b) and b < 0):
        raise ValueError(f"twin_risk_logit must be two finite numbers, the second < 0, not {text!r}")
    return a, b


@dataclass
class LoadedModel:
    """A model file with its session; :meth:`run` returns labels ``[B, N, D]``.

    A model with :data:`DRAWS_PREFIX` inputs gets its dropout draws from :meth:`draws`: a fixed
    ensemble of sub-networks per ``draw`` (the metadata's ``mc_seed``), so a network input gets the
    same samples whichever call it comes in, alone or among others. An older model draws in the graph."""

    path: Path
    info: ModelInfo
    session: ort.InferenceSession
    draw_inputs: list[tuple[str, int]] = field(default_factory=list)
    """The dropout draws' inputs, by name, and the units of each layer (``F``)."""
    mc_seed: int | None = None
    """The seed of the fixed dropout draws; None where the graph draws its own."""
    side_by_side: bool = False
    """Its calls may run two at a time, the session on half the cores (:func:`~service.core.onnx.session_threads`)."""
    _draws: dict[int, tuple[int, dict[str, NDArray[np.float32]]]] = field(default_factory=dict, repr=False)

    def with_seed(self, seed: int) -> "LoadedModel":
        """The same model and session with the draws of ``seed`` (another fixed ensemble: experiments
        that ask how far the MC draws move an answer)."""
        return LoadedModel(self.path, self.info, self.session, self.draw_inputs,
                           seed if self.draw_inputs else None, self.side_by_side)

    def draws(self, n: int, draw: int = 0) -> dict[str, NDArray[np.float32]]:
        """The dropout inputs for ``n`` passes of ensemble ``draw`` (each test-time view has its own):
        uniform numbers from ``(mc_seed, layer, draw)``; the first ``n`` passes are the same for any
        ``n`` (numpy fills the rows in order).

        Example (a model file at hand):
            >>> m = load_model(Path("service/models/default/model.onnx"))          # doctest: +SKIP
            >>> bool((m.draws(5)["dropout_uniform_0"] == m.draws(13)["dropout_uniform_0"][:, :5]).all())  # doctest: +SKIP
            True
        """
        kept = self._draws.get(draw)
        if kept is None or kept[0] < n:                   # one bank per draw, grown to the most passes asked
            most = max(n, MIN_DRAWN_PASSES)
            kept = (most, {name: np.random.default_rng([self.mc_seed, k, draw]).random((1, most, units), np.float32)
                           for k, (name, units) in enumerate(self.draw_inputs)})
            self._draws[draw] = kept
        return {name: bank[:, :n] for name, bank in kept[1].items()}

    def run(self, slices: NDArray[np.float32], passes: NDArray[np.float32], draw: int = 0) -> NDArray[np.float32]:
        """Run the graph on network inputs ``[B, L, L]`` (or ``[B, 1, L, L]``) for ``passes [N]``, with
        dropout draws ``draw`` (:meth:`draws`)."""
        x = np.asarray(slices, dtype=np.float32)
        if x.ndim == 3:
            x = x[:, None]
        passes = np.asarray(passes, np.float32)
        feed = {INPUT_SLICES: x, INPUT_PASSES: passes, **self.draws(len(passes), draw)}
        return self.session.run([OUTPUT_LABELS], feed)[0]


def load_model(path: Path, threads: int = 0) -> LoadedModel:
    """Open an exported model file with onnxruntime and read its metadata; its ``mc_seed`` is the seed it
    runs with (:data:`DEFAULT_MC_SEED` where a file with draw inputs names none)."""
    path = Path(path)
    per_call, side = session_threads(threads)
    sess = ort.InferenceSession(str(path), session_options(per_call), providers=["CPUExecutionProvider"])
    meta = sess.get_modelmeta().custom_metadata_map
    info = ModelInfo.from_metadata(meta, file_sha256(path))
    draws = [(i.name, int(i.shape[-1])) for i in sess.get_inputs() if i.name.startswith(DRAWS_PREFIX)]
    seed = (DEFAULT_MC_SEED if info.mc_seed is None else info.mc_seed) if draws else None
    model = LoadedModel(path, replace(info, mc_seed=seed), sess, draws, seed, side)
    check_runs(model)
    return model


def check_runs(model: LoadedModel) -> None:
    """One deterministic pass on a blank slice of the size the metadata names, whose labels must have
    the size its ``label_type`` needs: a graph of another input size or label than its metadata says
    is refused where the server starts (``ValueError``), not by every request it would serve."""
    size = model.info.input_size
    try:
        out = model.run(np.zeros((1, size, size), np.float32), np.zeros(1, np.float32))
    except Exception as exc:  # noqa: BLE001 - onnxruntime's own errors: one answer naming the metadata
        raise ValueError(f"the graph does not run on slices of {size} x {size} px, the input_size its metadata "
                         f"names ({type(exc).__name__})") from None
    want = encodings.get(model.info.label_type).size
    if np.ndim(out) != 3 or np.shape(out)[:2] != (1, 1) or np.shape(out)[-1] != want:
        raise ValueError(f"the graph gives labels of shape {list(np.shape(out))} for one slice and pass, where its "
                         f"label_type {model.info.label_type!r} needs [1, 1, {want}]")
