"""A narrower trunk taught by a teacher: the student's start, the views it learns on, a run's record."""

from __future__ import annotations

import csv
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from model_export.atlas import pack
from model_export.distil import DistilConfig, all_views, distil, main, student_of
from model_export.model import SVRNet
from model_export.packaging import load_checkpoint
from model_export.train import train
from model_export.train_config import TrainConfig
from service.inference.views import view_images, views


@pytest.fixture(scope="module")
def teacher(phantom_atlas: Path, tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """A small grid-label network trained a few steps, and the packed phantom atlas it trained on."""
    packed = pack(tmp_path_factory.mktemp("packed"), phantom_atlas)
    cfg = TrainConfig(backbone="compact", width=0.5, label_type="grid", loss="min", steps=2, batch=16, val_every=2,
                      val_per_volume=2, reuse=2, pool=3, hidden=32, grid_channels=8, dropout=0.25, workers=0,
                      simulation=dict(size=48, pixel_mm=2.5))
    out = tmp_path_factory.mktemp("teacher")
    train(cfg, out, packed, progress=False)
    return out / "last.pt", packed


def test_a_sliced_student_starts_from_the_teachers_first_channels_under_its_frozen_head(teacher) -> None:
    model, _ = load_checkpoint(teacher[0])
    student = student_of(model, 0.25, "sliced")
    assert student.config == {**model.config, "width": 0.25}
    t, s = model.state_dict(), student.state_dict()
    first = "trunk.features.0.0.weight"                                  # the first convolution
    assert s[first].shape[0] < t[first].shape[0]
    assert torch.equal(s[first], t[first][: s[first].shape[0], : s[first].shape[1]])
    assert all(torch.equal(s[k], t[k]) for k in s if k.startswith("head.") or k.startswith("label_"))
    assert not any(p.requires_grad for p in student.head.parameters())
    assert all(p.requires_grad for p in student.trunk.parameters())
    fresh = student_of(model, 0.25, "fresh")
    assert not torch.equal(fresh.state_dict()[first], s[first])
    with pytest.raises(ValueError, match="sliced"):
        student_of(model, 0.25, "warm")


def test_students_learn_every_view_the_service_asks_about() -> None:
    x = torch.from_numpy(np.random.default_rng(0).random((3, 1, 8, 8)).astype(np.float32))
    stacked = all_views(x, 8).numpy().reshape(8, 3, 1, 8, 8)
    for i, (k, flip) in enumerate(views(8)):
        assert np.array_equal(stacked[i], view_images(x.numpy(), k, flip))
    assert all_views(x, 1).shape == x.shape and all_views(x, 4).shape[0] == 12


def test_a_run_moves_the_student_towards_the_teacher_and_records_its_segment(teacher, tmp_path: Path) -> None:
    ckpt, packed = teacher
    cfg = DistilConfig(students=["0.25:fresh"], lr=3e-3, warmup_steps=1, minutes=10.0, max_steps=12, batch=16,
                       reuse=2, pool=3, workers=0, val_every_s=0.0, val_per_volume=2, simulation={})
    summary = distil(cfg, tmp_path, ckpt, packed)
    rows = list(csv.reader((tmp_path / "log.csv").open()))
    loss = [float(r[4]) for r in rows[1:]]
    assert len(loss) == 12 and min(loss[-3:]) < loss[0]
    student = torch.load(tmp_path / "w0.25-fresh.pt", weights_only=False)
    teacher_ck = torch.load(ckpt, weights_only=False)
    seg = student["history"][-1]
    assert seg["loss"] == "distil" and seg["steps"] == 12 and seg["samples"] == 12 * 16   # slices, each in
    assert seg["views"] == 8                                                               # eight views
    assert student["samples_seen"] == teacher_ck["samples_seen"] + seg["samples"]
    assert student["model_config"]["width"] == 0.25 and student["config"]["width"] == 0.25
    assert student["val_twin_ed_mm"] <= student["val_ed_mm"]                # against the truth and twin-min
    assert rows[0][4:8] == ["loss[0.25:fresh]", "ed[0.25:fresh]", "twin_ed[0.25:fresh]", "to_teacher[0.25:fresh]"]
    model, _ = load_checkpoint(tmp_path / "w0.25-fresh.pt")          # loads as a trained checkpoint does
    assert isinstance(model, SVRNet) and summary["students"]["0.25:fresh"]["to_teacher_median_mm"] >= 0.0
    # A later run goes on from the student: its weights, its history, a stream of new slices.
    cfg.students, cfg.max_steps = [f"0.25:{tmp_path / 'w0.25-fresh.pt'}"], 2
    distil(cfg, tmp_path / "next", ckpt, packed)
    after = torch.load(tmp_path / "next" / "w0.25-next.pt", weights_only=False)
    assert [h["loss"] for h in after["history"][-2:]] == ["distil", "distil"]
    assert after["samples_seen"] == student["samples_seen"] + 2 * 16
    assert after["history"][-1]["stream_seeds"] != seg["stream_seeds"]


def test_the_module_entry_point_runs_without_the_web_stack_or_simpleitk(teacher, tmp_path: Path,
                                                                        monkeypatch: pytest.MonkeyPatch) -> None:
    ckpt, packed = teacher
    for name in ("SimpleITK", "fastapi", "typer", "rich", "matplotlib"):
        monkeypatch.setitem(sys.modules, name, None)
    summary = main(["--out", str(tmp_path), "--root", str(packed), "--teacher", str(ckpt), "--students",
                    "0.25:sliced", "max_steps=1", "batch=16", "reuse=2", "pool=3", "workers=0", "val_per_volume=2",
                    "simulation={}"])
    assert summary["steps"] == 1 and (tmp_path / "w0.25-sliced.pt").exists()
