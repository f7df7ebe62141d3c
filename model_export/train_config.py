"""A training run's configuration: its fields and defaults, and a stage's configuration from the
command line (``field=value``), from the run it resumes or the checkpoint it starts from.

Example:
    >>> stage_config(parse_fields(argparse.ArgumentParser(), ["steps=5", "loss=min"], TrainConfig)).steps
    5
"""

from __future__ import annotations

import argparse
import json
from dataclasses import dataclass, field
from pathlib import Path

import torch

from service.geometry.twin import POINT_LABELS

__all__ = ["TrainConfig", "HOST_FIELDS", "check_root", "default_loss", "parse_fields", "stage_config"]


@dataclass
class TrainConfig:
    """Everything that defines a training run (saved in every checkpoint)."""

    backbone: str = "compact"
    width: float = 1.0
    label_type: str = "anchor"
    sampling: str = "random"
    steps: int = 20000
    batch: int = 64
    lr: float = 1e-4
    lr_milestones: tuple[float, ...] = (0.6, 0.85)
    lr_gamma: float = 0.2
    dropout: float = 0.5
    hidden: int = 128
    spatial_grid: int = 3
    grid_channels: int = 32
    loss_weights: tuple[float, ...] | None = None
    loss: str = ""
    """``l2``, ``min`` or ``invariant``; empty: ``min`` for point labels (a slice's twin is as right
    as the slice, which one slice cannot tell from it), ``l2`` for the others (:func:`default_loss`)."""
    plane_x_mm: float = 0.0
    seed: int = 0
    val_every: int = 500
    val_per_volume: int = 100
    reuse: int = 6
    pool: int = 24
    threads: int = 1
    workers: int = 2
    device: str = "cpu"
    channels_last: bool = False
    max_minutes: float | None = None
    train_volumes: list[str] | None = None
    val_volumes: list[str] | None = None
    simulation: dict = field(default_factory=dict)
    init_from: dict | None = None
    scene_share: float = 0.0
    """Share of each batch cut with the localiser's own masks from generated whole-uterus scenes
    (:mod:`model_export.scene_slices`): what a stack sent without a mask shows the network."""
    scene_reuse: float = 8.0
    """How many times, on average, each such slice is drawn before its scene is replaced."""


HOST_FIELDS = frozenset({"device", "workers", "threads", "max_minutes", "init_from"})
"""The fields a new stage (``main --init``) does not take from the checkpoint it starts from: they
describe the host and the run, not the network or its training."""


def default_loss(label_type: str) -> str:
    """The loss a run takes when none is given: mirror-aware (``min``) for point labels, else ``l2``.

    Example:
        >>> default_loss("grid"), default_loss("quaternion")
        ('min', 'l2')
    """
    return "min" if label_type in POINT_LABELS else "l2"


def parse_fields(ap: argparse.ArgumentParser, items: list[str], config: type) -> dict:
    """``field=value`` items (JSON values; a bare string as itself) of the dataclass ``config``;
    an unknown field is the parser's usage error.

    Example:
        >>> parse_fields(argparse.ArgumentParser(), ["steps=3", "loss=min", 'simulation={"size": 48}'], TrainConfig)
        {'steps': 3, 'loss': 'min', 'simulation': {'size': 48}}
    """
    values: dict = {}
    for item in items:
        key, equals, raw = item.partition("=")
        if key not in config.__dataclass_fields__:
            ap.error(f"unknown {config.__name__} field {key!r}")
        if not equals:
            ap.error(f"{key}: give it as {key}=VALUE")
        try:
            values[key] = json.loads(raw)
        except json.JSONDecodeError:
            values[key] = raw                      # a bare string: loss=min
        wanted = str(config.__dataclass_fields__[key].type)
        if not _of_type(values[key], wanted):
            ap.error(f"{item}: {key} takes {wanted} (JSON: true/false, numbers, [lists], {{objects}}, null)")
    return values


def _of_type(value: object, annotation: str) -> bool:
    """Whether a parsed ``value`` fits a field annotated ``annotation`` (the dataclass's text: ``int``,
    ``float | None``, ``tuple[float, ...]``, ...): ``True`` is no number, ``"False"`` no boolean.

    Example:
        >>> _of_type(3, "float"), _of_type(True, "int"), _of_type("False", "bool"), _of_type(None, "float | None")
        (True, False, False, True)
    """
    kinds = {"bool": lambda v: isinstance(v, bool),
             "int": lambda v: isinstance(v, int) and not isinstance(v, bool),
             "float": lambda v: isinstance(v, (int, float)) and not isinstance(v, bool),
             "str": lambda v: isinstance(v, str), "dict": lambda v: isinstance(v, dict),
             "tuple": lambda v: isinstance(v, list), "list": lambda v: isinstance(v, list),
             "None": lambda v: v is None}
    return any(kinds.get(part.strip().split("[")[0], lambda v: True)(value) for part in annotation.split("|"))


def stage_config(given: dict, resume: Path | None = None, init: Path | None = None) -> TrainConfig:
    """The configuration of a run from the fields given (``{field: value}``): with ``resume`` the
    run's own saved configuration, with ``init`` that of the stage that wrote the checkpoint (all but
    :data:`HOST_FIELDS`), else :class:`TrainConfig`'s defaults, each overridden by what is given. So a
    resumed run continues with its own settings (its host's ``device``, ``workers``, ``threads`` and
    time budget too: name them on another host), and a new stage keeps the network, its labels, its
    loss and its simulation unless a field says otherwise (a ``simulation`` given changes the
    settings it names and keeps the others).

    Example:
        >>> stage_config({"steps": 10, "lr_milestones": [0.5]}).lr_milestones
        (0.5,)
    """
    values = dict(given)
    if resume is not None or init is not None:
        path = resume or init
        if not Path(path).is_file():
            raise ValueError(f"{path}: no such checkpoint")
        saved = torch.load(path, map_location="cpu", weights_only=False)
        if not isinstance(saved, dict) or "config" not in saved or "model_config" not in saved:
            raise ValueError(f"{path}: not a pose-network checkpoint of svrnet-train train (a localiser's, or no "
                             "checkpoint at all)")
        if resume is not None and not {"optimizer", "scheduler"} <= saved.keys():
            raise ValueError(f"{resume}: holds the network without its optimiser and schedule (a shipped or pruned "
                             "checkpoint), so no run goes on from it: start a new stage from it with --init")
        keep = TrainConfig.__dataclass_fields__.keys() - (set() if resume is not None else HOST_FIELDS)
        old = {k: v for k, v in saved["config"].items() if k in keep}
        if "simulation" in values:                     # a setting given changes the stage's, the others stay
            values["simulation"] = {**(old.get("simulation") or {}), **values["simulation"]}
        values = {**old, **values}
    if resume is not None or init is not None:         # its weights are that network's: no other fits them
        fixed = [k for k in ARCHITECTURE_FIELDS if resume is not None or k != "label_type"]   # a new stage may
        changed = {k: (saved["config"].get(k), values[k]) for k in fixed        # take other labels: a new head
                   if k in given and k in saved["config"] and given[k] != saved["config"][k]}
        if changed:
            raise ValueError(f"{resume or init}: its network has {changed} (saved, given)" +
                             ("; a run goes on with its own network: start a new stage from it with --init"
                              if resume is not None else "; a new stage starts from the same network"))
    from model_export.simulate import SimulationConfig   # its dataclass only (the module is imported by train)

    unknown = sorted(set(values.get("simulation") or {}) - set(SimulationConfig.__dataclass_fields__))
    if unknown:
        raise ValueError(f"simulation: no such setting {unknown} (model_export/simulate.py, SimulationConfig)")
    for key in ("lr_milestones", "loss_weights"):
        if values.get(key) is not None:
            values[key] = tuple(values[key])
    cfg = TrainConfig(**values)
    from model_export.backbones import BACKBONES
    from model_export.losses import check_label_type
    from service.geometry.encodings import LABEL_TYPES

    if cfg.label_type not in LABEL_TYPES:
        raise ValueError(f"label_type {cfg.label_type!r}: one of {', '.join(LABEL_TYPES)}")
    if cfg.backbone not in BACKBONES:
        raise ValueError(f"backbone {cfg.backbone!r}: one of {', '.join(BACKBONES)}")
    check_label_type(cfg.label_type, cfg.loss or default_loss(cfg.label_type))
    if cfg.device.startswith("cuda") and not torch.cuda.is_available():
        raise ValueError(f"device {cfg.device}: this torch sees no CUDA device (device=auto takes one where there is)")
    return cfg


def check_root(root: Path, cfg: TrainConfig) -> None:
    """A :class:`ValueError` in one line where ``root`` holds no atlas volumes, or not the validation
    volumes a run holds out (a ``pack --training-only`` folder: the localiser's scenes only)."""
    from model_export.atlas import VALIDATION_VOLUMES, split

    try:
        split(root, cfg.val_volumes or VALIDATION_VOLUMES)
    except (OSError, ValueError) as bad:
        raise ValueError(f"--root {root}: {getattr(bad, 'strerror', None) or bad}") from None


ARCHITECTURE_FIELDS = ("backbone", "width", "label_type", "hidden", "spatial_grid", "grid_channels")
"""The fields that make the network: a resumed run cannot change them."""
