"""`svrnet-train ship`'s order of work, with every measurement stubbed (no atlas, no torch run)."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch
from typer.testing import CliRunner


@pytest.mark.parametrize("budget", [[], ["--slices-per-volume", "7", "--acceptance-per-volume", "2",
                                     "--quant-slices", "32", "--noise-per-volume", "3", "--frame-per-volume", "1"]],
                         ids=["defaults", "a quick look"])
def test_ship_calibrates_the_spread_before_the_accept_flags(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                                             budget: list[str]) -> None:
    """The accept flags are measured on the expected error, so the spread's calibration (which sets
    ``mc_error_scale``) comes first; every calibration, the variance threshold's included, measures
    the int8 file the service will run, so quantising comes before them, all on the checkpoint's own
    validation volumes; the acceptance report is written beside the evaluation report. A smaller
    budget reaches every step, and the card states it; without one each keeps its own."""
    import model_export.atlas as atlas
    import model_export.calibrate as calibrate
    import model_export.calibrate_acceptance as acceptance
    import model_export.calibrate_frame as frame
    import model_export.calibrate_noise as noise
    import model_export.card as card
    import model_export.evaluate as evaluate
    import model_export.packaging as packaging
    import model_export.quantise as quantise
    import model_export.spread as spread
    import model_export.train as train
    import service.inference.estimator as estimator
    import service.inference.model_file as model_file
    from model_export.cli import app
    from service.inference.views import SHIPPED_VIEWS

    calls: list[str] = []
    views: list[int] = []
    sizes: dict[str, object] = {}
    held_out: list[list[str]] = []
    card_budget: list[list] = []

    def threshold(checkpoint: Path, root: Path, **k: object) -> dict:
        calls.append(f"threshold on {k['model_file'].name}, {k['model_file'].read_bytes().decode()}")
        sizes.update(threshold=k.get("per_volume"))
        return {"threshold": 50.0, "auroc": 0.8}

    def export(checkpoint: Path, output: Path, **kw: object) -> Path:
        views.append(kw["tta_views"])
        output.write_bytes(b"onnx")
        return output

    class Loaded:
        info = type("Info", (), {"metadata": {}, "input_size": 96, "pixel_spacing_mm": 1.25})()

    monkeypatch.setattr(calibrate, "calibrate", threshold)
    monkeypatch.setattr(packaging, "export_checkpoint", export)
    monkeypatch.setattr(packaging, "load_checkpoint", lambda p: (None, {"train_seconds": 1.0, "samples_seen": 1, "step": 1,
                                                                       "config": {"train_volumes": [],
                                                                                  "val_volumes": ["STA30"]}}))
    monkeypatch.setattr(quantise, "calibration_slices", lambda **k: calls.append(f"slices {k['size']}") or
                        sizes.update(quant=k["count"]) or "slices")
    monkeypatch.setattr(quantise, "quantise", lambda src, out, slices: calls.append(f"int8 {slices}") or
                        out.write_bytes(b"int8") and out)
    monkeypatch.setattr(spread, "calibrate_spread", lambda *a, **k: calls.append("spread") or sizes.update(
        spread=k.get("per_volume")) or {"mc_error_scale": 0.7})
    monkeypatch.setattr(spread, "write_metadata", lambda *a, **k: calls.append("flags written"))
    monkeypatch.setattr(evaluate, "evaluate", lambda *a, **k: calls.append("evaluate") or sizes.update(
        evaluate=k.get("per_volume")) or {})
    monkeypatch.setattr(train, "prior_history", lambda ck: [])
    monkeypatch.setattr(train, "totals", lambda history: {})
    monkeypatch.setattr(atlas, "split", lambda root, validation: held_out.append(list(validation)) or ([], []))
    monkeypatch.setattr(atlas, "load_volumes", lambda names, root: [])
    monkeypatch.setattr(acceptance, "measure", lambda *a, **k: calls.append("acceptance") or sizes.update(
        acceptance=k["per_volume"]) or {"expected_error_floor_mm": 2.0, "variance_threshold": 480.0,
                                        "max_expected_error_mm": 4.0})
    monkeypatch.setattr(acceptance, "markdown", lambda flags, title: f"# {title}\n")
    monkeypatch.setattr(noise, "measure", lambda *a, **k: calls.append("noise") or sizes.update(noise=a[2]) or {})
    monkeypatch.setattr(noise, "calibrate", lambda columns: {"noise_error": [0.09, 50.0]})
    monkeypatch.setattr(noise, "markdown", lambda result: "noise table")
    monkeypatch.setattr(frame, "measure", lambda *a, **k: calls.append("frame") or sizes.update(frame=a[2]) or {})
    monkeypatch.setattr(frame, "calibrate", lambda columns: {"frame_error": [9.5, 0.26]})
    monkeypatch.setattr(frame, "markdown", lambda result: "frame table")
    monkeypatch.setattr(estimator, "OnnxPoseEstimator", lambda model: None)
    monkeypatch.setattr(model_file, "load_model", lambda path: Loaded())
    monkeypatch.setattr(quantise, "load_model", lambda path: Loaded())
    monkeypatch.setattr(card, "write_card", lambda out, **kw: card_budget.append(kw["budget"]) or out.write_text("# card\n"))
    checkpoint = tmp_path / "run.pt"
    torch.save({"model_config": {}}, checkpoint)              # a pose network's, as the command checks
    report = tmp_path / "reports" / "default.md"
    report.parent.mkdir()

    result = CliRunner().invoke(app, ["ship", str(checkpoint), "--out", str(tmp_path / "model"), "--report", str(report),
                                      *budget])

    assert result.exit_code == 0, result.output
    assert calls == ["slices 96", "int8 slices", "threshold on model.onnx, int8", "flags written", "spread", "evaluate",
                     "acceptance", "flags written", "noise", "flags written", "frame", "flags written"]
    assert held_out == [["STA30"]]
    given = [row[1] for row in card_budget[0]]
    assert given == ([7, 7, 7, 2, 32, 3, 1] if budget else [None] * 7)
    assert sizes == ({"threshold": 7, "quant": 32, "spread": 7, "evaluate": 7, "acceptance": 2, "noise": 3, "frame": 1}
                     if budget else
                     {"threshold": None, "quant": quantise.CALIBRATION_SLICES, "spread": None, "evaluate": None,
                      "acceptance": acceptance.PER_VOLUME, "noise": noise.PER_VOLUME, "frame": frame.PER_VOLUME})
    assert (report.parent / "noise.md").read_text().endswith("noise table\n")
    assert (report.parent / "frame.md").read_text().endswith("frame table\n")
    assert views == [SHIPPED_VIEWS]
    assert (report.parent / "acceptance.md").read_text().startswith("# Accept flags of")
    assert "## Accept flags" in (tmp_path / "model" / "card.md").read_text()
    assert "## Noise error\n\nnoise table" in (tmp_path / "model" / "card.md").read_text()
    assert "## Frame error\n\nframe table" in (tmp_path / "model" / "card.md").read_text()
    # A model folder is never replaced unasked, nor left half-shipped: the new one takes its place whole.
    again = ["ship", str(checkpoint), "--out", str(tmp_path / "model")]
    refused = CliRunner().invoke(app, again, env={"COLUMNS": "250"})
    assert refused.exit_code != 0 and "holds a model already; --force replaces it" in refused.output, refused.output
    monkeypatch.setattr(evaluate, "evaluate", lambda *a, **k: (_ for _ in ()).throw(RuntimeError("stopped")))
    assert CliRunner().invoke(app, [*again, "--force"]).exit_code != 0
    assert (tmp_path / "model" / "card.md").read_text().startswith("# card") and \
        (tmp_path / "model" / "model.onnx").read_bytes() == b"int8"    # the shipped (quantised) file
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".")] == []   # nothing half-made to be served
    monkeypatch.setattr(evaluate, "evaluate", lambda model, report, *a, **k: report.write_text("# report") and {})
    inside = CliRunner().invoke(app, [*again, "--force", "--report", str(tmp_path / "model" / "eval" / "r.md")])
    assert inside.exit_code == 0, inside.output                              # a report inside --out moves in with it
    assert (tmp_path / "model" / "eval" / "r.md").read_text() == "# report"
    monkeypatch.setattr(evaluate, "evaluate", lambda *a, **k: {})
    replaced = CliRunner().invoke(app, [*again, "--force"])
    assert replaced.exit_code == 0, replaced.output
    assert sorted(p.name for p in tmp_path.iterdir() if p.name.startswith(".")) == []
    assert (tmp_path / "model" / "acceptance.md").exists()              # the report's default place: the model's folder
    calls.clear()
    unmeasured = CliRunner().invoke(app, [*again, "--force", "--noise-per-volume", "0", "--frame-per-volume", "0"])
    assert unmeasured.exit_code == 0 and "acceptance" in calls and "noise" not in calls and "frame" not in calls, \
        unmeasured.output
    assert "## Noise error" not in (tmp_path / "model" / "card.md").read_text()
    assert "## Frame error" not in (tmp_path / "model" / "card.md").read_text()


def test_export_takes_over_another_models_calibration(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """``export --calibration-from`` writes the other model's spread and accept-flag settings and its
    test-time views (a network compared with it is run as it is) and calibrates nothing; the network
    and its own facts stay the checkpoint's."""
    import torch

    import model_export.calibrate as calibrate
    import model_export.packaging as packaging
    from model_export.cli import app
    from model_export.export import build_metadata, export_onnx
    from model_export.model import SVRNet
    from model_export.packaging import CALIBRATION
    from service.inference.model_file import load_model

    torch.manual_seed(0)
    model = SVRNet("compact", 0.25, "anchor", 64, hidden=16, dropout=0.5).eval()

    def own(checkpoint: Path, output: Path, **kw: float) -> Path:
        meta = build_metadata(model, name="tuned", version="0.0.2", pixel_mm=2.0, variance_threshold=kw["variance_threshold"],
                              atlas_id="phantom", training_data="none", licences="n/a",
                              extra={"tta_views": kw["tta_views"], **(kw.get("extra") or {})})
        return export_onnx(model, output, meta)

    source_meta = build_metadata(model, name="shipped", version="1.0.0", pixel_mm=2.0, variance_threshold=123.0,
                                 atlas_id="phantom", training_data="none", licences="n/a")
    source_meta.update(mc_error_scale="0.7", mc_error_shape="1,2,1,1,1,3", mc_error_depth_gain="0.25",
                       expected_error_floor_mm="2.2", max_expected_error_mm="4.5", twin_risk_logit="-0.5,-0.2",
                       noise_error="0.09,52", frame_error="9.5,0.26", tta_views="4")
    source = export_onnx(model, tmp_path / "shipped.onnx", source_meta)
    monkeypatch.setattr(calibrate, "calibrate", lambda *a, **k: pytest.fail("calibrated although told not to"))
    monkeypatch.setattr(packaging, "export_checkpoint", own)
    out = tmp_path / "tuned.onnx"
    torch.save({"model_config": {}}, tmp_path / "run.pt")          # a pose network's, as the command checks

    result = CliRunner().invoke(app, ["export", str(tmp_path / "run.pt"), str(out), "--calibration-from", str(source)])

    assert result.exit_code == 0, result.output
    got, want = load_model(out).info, load_model(source).info
    for key in CALIBRATION:
        assert getattr(got, key) == getattr(want, key), key
    assert got.noise_error == (0.09, 52.0) and got.frame_error == (9.5, 0.26)
    assert got.variance_threshold == 123.0 and got.metadata["name"] == "tuned"
    assert got.tta_views == 4

    # what would write a calibration that does not hold for the file is refused, naming the option
    for extra, option in ((["--threshold", "40"], "--threshold"), (["--tta-views", "8"], "--tta-views")):
        refused = CliRunner().invoke(app, ["export", str(tmp_path / "run.pt"), str(tmp_path / "other.onnx"),
                                           "--calibration-from", str(source), *extra])
        assert refused.exit_code == 2 and option in refused.output, refused.output
        assert not (tmp_path / "other.onnx").exists()


def test_the_accept_flags_are_calibrated_again_from_kept_slice_columns(tmp_path: Path,
                                                                       monkeypatch: pytest.MonkeyPatch, pose_model_copy: Path) -> None:
    """``--columns`` calibrates from the columns a previous run kept, measuring nothing."""
    import numpy as np

    import model_export.calibrate_acceptance as acceptance
    from model_export.cli import app
    from tests.model_export.test_calibrate_acceptance import level

    monkeypatch.setattr(acceptance, "measure", lambda *a, **k: pytest.fail("measured again"))
    rng = np.random.default_rng(3)
    kept = {}
    for name, scale in (("mild", 1.0), ("moderate", 5.0), ("jumps", 6.0), ("independent", 6.0)):
        columns = level(rng, 400, scale, 2.0)
        kept.update({f"{name}/{k}": v for k, v in columns.items()})
        kept[f"{name}/mask_pixels"] = np.full(400, 500)
    np.savez(tmp_path / "slices.npz", **kept)
    report = tmp_path / "acceptance.md"
    result = CliRunner().invoke(app, ["calibrate-acceptance", str(tmp_path / "model.onnx"), "--no-write",
                                      "--columns", str(tmp_path / "slices.npz"), "--report", str(report)])
    assert result.exit_code == 0, result.output
    assert "max expected error" in report.read_text() and '"judged_levels"' in result.output
    report.unlink()
    result = CliRunner().invoke(app, ["calibrate-acceptance", str(tmp_path / "model.onnx"), "--no-write",
                                      "--columns", str(tmp_path / "slices.npz")])
    assert result.exit_code == 0 and report.exists()                  # beside the model: not the shipped report


def test_the_noise_error_is_calibrated_from_several_kept_column_files_pooled(tmp_path: Path,
                                                                             monkeypatch: pytest.MonkeyPatch, pose_model_copy: Path) -> None:
    """``calibrate-noise --columns A --columns B`` pools the slices of both files, measuring nothing."""
    import numpy as np

    import model_export.calibrate_noise as noise
    from model_export.cli import app

    pooled = {}
    monkeypatch.setattr(noise, "measure", lambda *a, **k: pytest.fail("measured again"))
    monkeypatch.setattr(noise, "calibrate", lambda columns: pooled.update(columns) or {"noise_error": [0.1, 70.0]})
    monkeypatch.setattr(noise, "markdown", lambda result: "noise table")
    for name, n in (("a", 3), ("b", 2)):
        np.savez(tmp_path / f"{name}.npz", ed=np.full(n, 2.0), expected=np.full(n, 1.5), input_noise=np.arange(n) / 10)
    result = CliRunner().invoke(app, ["calibrate-noise", str(tmp_path / "model.onnx"), "--no-write", "--columns",
                                      str(tmp_path / "a.npz"), "--columns", str(tmp_path / "b.npz"),
                                      "--report", str(tmp_path / "noise.md")])
    assert result.exit_code == 0, result.output
    assert sorted(pooled) == ["ed", "expected", "input_noise"]
    assert pooled["input_noise"].tolist() == [0.0, 0.1, 0.2, 0.0, 0.1]

def test_the_frame_error_is_calibrated_from_several_kept_column_files_pooled(tmp_path: Path,
                                                                             monkeypatch: pytest.MonkeyPatch, pose_model_copy: Path) -> None:
    """``calibrate-frame --columns A --columns B`` pools the slices of both files, measuring nothing,
    and writes its report where asked."""
    import numpy as np

    import model_export.calibrate_frame as frame
    from model_export.cli import app

    pooled = {}
    monkeypatch.setattr(frame, "measure", lambda *a, **k: pytest.fail("measured again"))
    monkeypatch.setattr(frame, "calibrate", lambda columns: pooled.update(columns) or {"frame_error": [9.5, 0.26]})
    monkeypatch.setattr(frame, "markdown", lambda result: "frame table")
    for name, n in (("a", 3), ("b", 2)):
        np.savez(tmp_path / f"{name}.npz", ed=np.full(n, 2.0), expected=np.full(n, 1.5), sigma=np.arange(n) * 10.0)
    result = CliRunner().invoke(app, ["calibrate-frame", str(tmp_path / "model.onnx"), "--no-write", "--columns",
                                      str(tmp_path / "a.npz"), "--columns", str(tmp_path / "b.npz"),
                                      "--report", str(tmp_path / "frame.md")])
    assert result.exit_code == 0, result.output
    assert sorted(pooled) == ["ed", "expected", "sigma"]
    assert pooled["sigma"].tolist() == [0.0, 10.0, 20.0, 0.0, 10.0]
    assert (tmp_path / "frame.md").read_text().endswith("frame table\n")

