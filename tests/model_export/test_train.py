"""Training that compounds: packed volumes, any device, totals over stages, a wall-clock stop."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from model_export.atlas import load_volumes, pack
from model_export.model import SVRNet
from model_export.stream import validation_set
from model_export.train import _load_init, pose_errors, train
from model_export.train_config import TrainConfig
from model_export.training_record import UNRECORDED_HARDWARE, git_commit, prior_history, totals
from service.geometry import iterators, twin

DEVICES = ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])
SHIPPED_CHECKPOINTS = Path("service/models/default/checkpoint.pt"), Path("service/localisers/default/checkpoint.pt")
needs_shipped_checkpoints = pytest.mark.skipif(not all(p.is_file() for p in SHIPPED_CHECKPOINTS),
                                               reason="needs the shipped networks' checkpoints: a git checkout "
                                                      "(the source distribution leaves them out)")


@pytest.fixture(scope="module")
def packed(phantom_atlas: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    return pack(tmp_path_factory.mktemp("packed"), phantom_atlas)


def test_packed_volumes_simulate_the_same_slices(phantom_atlas: Path, packed: Path) -> None:
    a, b = load_volumes(None, phantom_atlas), load_volumes(None, packed)
    assert [v.name for v in a] == [v.name for v in b]
    assert all(np.allclose(u.centre, v.centre) for u, v in zip(a, b))
    assert b[0].image.size < a[0].image.size                       # cropped to the non-zero box
    names = [a[0].name, a[1].name]
    va, vb = validation_set(names, phantom_atlas, 6), validation_set(names, packed, 6)
    assert np.allclose(va.poses, vb.poses)
    assert np.abs(va.inputs - vb.inputs).max() < 0.05              # 0-255 scale: float32 rounding only


def test_packed_volumes_load_without_simpleitk(packed: Path) -> None:
    code = ("import sys; sys.modules['SimpleITK'] = None\n"
            "from model_export.atlas import load_volumes, split\n"
            f"print(len(load_volumes(None, {str(packed)!r})), len(split({str(packed)!r})[1]))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.split() == ["7", "5"]


def test_a_pack_of_the_training_volumes_uncompressed_holds_the_same_arrays(packed: Path, tmp_path: Path,
                                                                          phantom_atlas: Path) -> None:
    """``pack --training-only --uncompressed``: what travels to a GPU host as one archive."""
    import zipfile

    from model_export.atlas import VALIDATION_VOLUMES, list_volumes, split

    small = pack(tmp_path / "small", phantom_atlas, split(phantom_atlas)[0], compressed=False)
    assert sorted(n for n, *_ in list_volumes(small)) == ["SB_GA27_operated", "STA30"]
    assert not set(n for n, *_ in list_volumes(small)) & set(VALIDATION_VOLUMES)
    with zipfile.ZipFile(small / "STA30.npz") as z:
        assert {i.compress_type for i in z.infolist()} == {zipfile.ZIP_STORED}
    for name in ("STA30", "SB_GA27_operated"):
        with np.load(small / f"{name}.npz") as a, np.load(packed / f"{name}.npz") as b:
            assert all(np.array_equal(a[k], b[k]) for k in ("image", "mask", "affine"))


def test_midplane_reads_a_packed_folder_as_it_reads_the_atlas_folder(phantom_atlas: Path, packed: Path,
                                                                   tmp_path: Path) -> None:
    """The packed volumes are cropped, their affines moved with the crop: the planes stay where they were."""
    from typer.testing import CliRunner

    from model_export.cli import app

    planes = {}
    for name, root in (("atlas", phantom_atlas), ("packed", packed)):
        result = CliRunner().invoke(app, ["midplane", "--root", str(root), "--report", str(tmp_path / f"{name}.md")])
        assert result.exit_code == 0, result.output
        rows = [line.split("|")[1:4] for line in (tmp_path / f"{name}.md").read_text().splitlines()
                if line.startswith("| S")]
        planes[name] = {n.strip(): float(x) for n, _, x in rows}
    assert len(planes["packed"]) == 7 and planes["packed"].keys() == planes["atlas"].keys()
    assert all(abs(planes["packed"][n] - planes["atlas"][n]) < 0.05 for n in planes["atlas"]), planes


def test_git_commit_is_dirty_with_uncommitted_changes_to_tracked_files_only(tmp_path: Path) -> None:
    def git(*args: str) -> str:
        return subprocess.run(["git", "-c", "user.name=t", "-c", "user.email=t@t", *args], cwd=tmp_path,
                              capture_output=True, text=True, check=True).stdout.strip()

    git("init", "-q")
    (tmp_path / "code.py").write_text("x = 1\n")
    git("add", "code.py")
    git("commit", "-qm", "code")
    head = git("rev-parse", "--short", "HEAD")
    assert git_commit(tmp_path) == head
    (tmp_path / "run.log").write_text("untracked: a run's output\n")
    assert git_commit(tmp_path) == head
    (tmp_path / "code.py").write_text("x = 2\n")
    assert git_commit(tmp_path) == f"{head}-dirty"
    git("add", "code.py")                                             # staged, not committed: still dirty
    assert git_commit(tmp_path) == f"{head}-dirty"


def test_installed_code_inside_another_repository_records_no_commit(tmp_path: Path,
                                                                    monkeypatch: pytest.MonkeyPatch) -> None:
    """A virtualenv inside some project's repository: the package's parent folder is in git, but it
    is not this code's checkout, and its commit says nothing of this code."""
    import model_export.training_record as record

    subprocess.run(["git", "init", "-q"], cwd=tmp_path, check=True)
    site = tmp_path / "venv" / "lib" / "site-packages"
    site.mkdir(parents=True)
    monkeypatch.setattr(record, "CHECKOUT", site.resolve())
    assert record.git_commit() == "unknown"


def test_a_run_that_holds_out_its_own_volumes_trains_on_none_of_them(packed: Path, tmp_path: Path) -> None:
    train(_tiny(steps=1, val_every=1, val_per_volume=2, val_volumes=["STA30"]), tmp_path / "own", packed,
          progress=False)
    config = torch.load(tmp_path / "own" / "last.pt", weights_only=False)["config"]
    assert config["val_volumes"] == ["STA30"] and "STA30" not in config["train_volumes"]
    assert len(config["train_volumes"]) == 6
    with pytest.raises(ValueError, match="both trained and validated on"):
        train(_tiny(val_volumes=["STA30"], train_volumes=["STA30", "STA24"]), tmp_path / "both", packed, progress=False)


def test_pose_errors_report_the_truth_and_the_nearer_twin() -> None:
    rng = np.random.default_rng(0)
    true = iterators.random_poses(8, rng, tz_max_mm=10.0, centre=np.array([20.0, 0.0, 0.0]))
    pred = true.copy()
    pred[4:] = twin.twin(true[4:], 0.5)
    err = pose_errors(pred, true, plane_x_mm=0.5)
    assert np.allclose(err["ed_twin_mm"], 0.0, atol=1e-9)
    assert np.allclose(err["ed_mm"][:4], 0.0) and np.all(err["ed_mm"][4:] > 1.0)
    assert err["on_twin"].tolist() == [False] * 4 + [True] * 4
    assert np.allclose(err["gd_twin"], 0.0, atol=1e-6) and np.all(err["gd"][4:] > 0.1)     # G.D. both ways too


def test_a_run_given_no_loss_takes_the_mirror_aware_one_for_point_labels() -> None:
    from model_export.train_config import TrainConfig, default_loss

    assert TrainConfig().loss == "" and default_loss("anchor") == default_loss("grid") == "min"
    assert default_loss("euler") == "l2"


def test_totals_add_up_segments_and_checkpoints_without_history() -> None:
    bare = prior_history({"samples_seen": 1000, "train_seconds": 7200.0, "step": 10, "config": {}})
    assert bare[0]["hardware"] == UNRECORDED_HARDWARE and bare[0]["samples"] == 1000
    carried = prior_history({"history": bare[:1] + [{"hardware": "GPU", "samples": 5, "seconds": 1.0, "run": "r"}]})
    assert [seg["hardware"] for seg in carried] == [UNRECORDED_HARDWARE, "GPU"]
    t = totals(bare + [{"hardware": "GPU", "samples": 500, "seconds": 1800.0}])
    assert t["samples"] == 1500 and t["hours"] == pytest.approx(2.5)
    assert t["by_hardware"]["GPU"] == {"samples": 500, "hours": 0.5}


def test_init_across_label_types_loads_the_trunk_only() -> None:
    torch.manual_seed(0)
    anchor = SVRNet("compact", 0.25, "anchor", 48, 32, 0.25, 3, 8)
    ck = {"model": anchor.state_dict(), "model_config": anchor.config}
    grid = SVRNet("compact", 0.25, "grid", 48, 32, 0.5, 3, 8)
    assert _load_init(grid, ck, Path("x")) is False
    a, g = anchor.state_dict(), grid.state_dict()
    assert all(torch.equal(a[k], g[k]) for k in a if k.startswith(("trunk.", "grid.", "head.shared.")))
    assert g["head.branches.0.weight"].shape == (192, 32)
    with pytest.raises(ValueError, match="differs"):
        _load_init(SVRNet("compact", 0.25, "grid", 48, 64, 0.5, 3, 8), ck, Path("x"))


def _tiny(**kw: object) -> TrainConfig:
    base = dict(backbone="compact", width=0.25, steps=4, batch=16, lr=1e-3, val_every=2, val_per_volume=4, reuse=2,
                pool=3, hidden=32, grid_channels=8, workers=0, simulation=dict(size=48, pixel_mm=2.5))
    return TrainConfig(**{**base, **kw})


@pytest.mark.parametrize("device", DEVICES)
def test_training_compounds_on_any_device(device: str, packed: Path, tmp_path: Path) -> None:
    """The code path a GPU host runs (there with device="cuda"): stages, totals, a stop and a resume."""
    train(_tiny(device=device, loss="min", channels_last=True), tmp_path / "a", packed, progress=False)
    first = torch.load(tmp_path / "a" / "last.pt", weights_only=False)
    assert first["samples_seen"] == 64 and first["history"][-1]["device"] == device
    assert all(v.device.type == "cpu" for v in first["model"].values())   # checkpoints load anywhere
    assert first["val_twin_ed_mm"] <= first["val_ed_mm"]
    assert first["history"][-1]["commits"] == [git_commit()]          # the code it ran, -dirty with changes
    # A new stage with another label and loss, stopped by its wall-clock budget after one step...
    stage = _tiny(device=device, label_type="grid", loss="invariant", steps=3, max_minutes=0.0)
    with pytest.warns(UserWarning, match="only the trunk"):
        train(stage, tmp_path / "b", packed, init=tmp_path / "a" / "last.pt", progress=False)
    stopped = torch.load(tmp_path / "b" / "last.pt", weights_only=False)
    assert stopped["step"] == 1 and stopped["config"]["init_from"]["whole_network"] is False
    # ... and resumed to its end: one segment per run folder, totals over both stages.
    stage.max_minutes = None
    train(stage, tmp_path / "b", packed, resume=tmp_path / "b" / "last.pt", progress=False)
    done = torch.load(tmp_path / "b" / "last.pt", weights_only=False)
    assert done["step"] == 3 and len(done["history"]) == 2
    # Every start draws its own slices: the stage's start and its resume, and the first stage.
    seeds = [first["history"][-1]["stream_seeds"][0], *done["history"][-1]["stream_seeds"]]
    assert len(seeds) == 3 and len(set(seeds)) == 3, seeds
    assert done["samples_seen"] == 64 + 3 * 16
    assert done["train_seconds"] == pytest.approx(sum(s["seconds"] for s in done["history"]))
    log = (tmp_path / "b" / "log.csv").read_text().splitlines()
    assert log[0].split(",")[7] == "val_twin_ed_mm" and log[-1].startswith("3,")


def test_a_resume_with_more_steps_follows_the_new_schedule(packed: Path, tmp_path: Path) -> None:
    """``--resume`` with a new ``steps``: its milestones are the new run's (at half and three quarters
    of 40 steps), not the first run's (of 4 steps, long passed), so the lr is the full one again."""
    train(_tiny(steps=4, lr_milestones=(0.5, 0.75), lr_gamma=0.1), tmp_path / "r", packed, progress=False)
    longer = _tiny(steps=40, lr_milestones=(0.5, 0.75), lr_gamma=0.1, max_minutes=0.0)      # one more step
    train(longer, tmp_path / "r", packed, resume=tmp_path / "r" / "last.pt", progress=False)
    rows = [line.split(",") for line in (tmp_path / "r" / "log.csv").read_text().splitlines()[1:]]
    lrs = {int(r[0]): float(r[3]) for r in rows}
    assert lrs[2] == pytest.approx(1e-4) and lrs[4] == pytest.approx(1e-5)    # the first run's two decays
    assert lrs[5] == pytest.approx(1e-3)                                       # before the new run's first, at 20
    segment = torch.load(tmp_path / "r" / "last.pt", weights_only=False)["history"][-1]
    assert segment["config"]["steps"] == 40 and tuple(segment["config"]["lr_milestones"]) == (0.5, 0.75)


def test_a_share_of_each_batch_comes_from_scenes_cut_with_the_localisers_masks(packed: Path) -> None:
    """``scene_share`` 0.5 of a 32-slice batch: one group of 16 simulated slices and 16 slices of
    generated whole-uterus scenes the localiser masked, on the network's grid with finite labels;
    the scene slices' inputs are zero outside the localiser's pose mask, so part of each is black."""
    from model_export.simulate import SimulationConfig
    from model_export.stream import SliceStream

    stream = SliceStream(["STA30"], packed, SimulationConfig(size=48, pixel_mm=2.5), "grid", 32, 2, 3, seed=1,
                         scene_share=0.5, scene_reuse=4.0)
    x, y = next(iter(stream))
    assert x.shape[0] > 16 and x.shape[1:] == (1, 48, 48) and y.shape[0] == x.shape[0]
    assert torch.isfinite(y).all()
    scene = x[-16:, 0]
    assert ((scene == 0).float().mean(dim=(1, 2)) > 0.2).all()


@pytest.mark.parametrize("reuse", [2, 16])
def test_each_clean_acquisition_is_corrupted_reuse_times_on_average(packed: Path, reuse: int,
                                                                   monkeypatch: pytest.MonkeyPatch) -> None:
    """``reuse`` is what the stream does, beyond the batch's groups too: four groups a batch, each
    fresh acquisition finished about ``reuse`` times over the batches (it was four at most)."""
    import model_export.stream as stream_module
    from model_export.simulate import SimulationConfig

    made = [0]
    real = stream_module.fresh_acquisition
    monkeypatch.setattr(stream_module, "fresh_acquisition", lambda *a: made.__setitem__(0, made[0] + 1) or real(*a))
    stream = stream_module.SliceStream(["STA30"], packed, SimulationConfig(size=32, pixel_mm=4.0), "grid", 64, reuse,
                                       4, seed=1)
    batches, it = 24, iter(stream)
    for _ in range(batches):
        next(it)
    fresh = made[0] - 4                                              # the first pool
    assert fresh == pytest.approx((batches - 1) * 4 / reuse, abs=1)  # replaced after each batch but the last


def test_module_entry_point_trains_without_typer_rich_or_matplotlib(packed: Path, tmp_path: Path,
                                                                     monkeypatch: pytest.MonkeyPatch) -> None:
    """``python -m model_export.train``: what a bare GPU host runs (numpy, scipy, torch only)."""
    from model_export.train import main

    for name in ("rich", "rich.progress", "matplotlib", "typer"):
        monkeypatch.setitem(sys.modules, name, None)
    fields = ["backbone=compact", "width=0.25", "steps=2", "batch=16", "val_every=2", "val_per_volume=4", "reuse=2",
              "pool=3", "hidden=32", "grid_channels=8", "workers=0", "loss=min", "device=cpu",
              'simulation={"size": 48, "pixel_mm": 2.5}', "lr_milestones=[]"]
    best = main(["--out", str(tmp_path / "m"), "--root", str(packed), *fields])
    ck = torch.load(best, weights_only=False)
    assert ck["config"]["loss"] == "min" and ck["step"] == 2 and ck["config"]["lr_milestones"] == ()
    assert not (tmp_path / "m" / "loss.png").exists()
    # Resuming elsewhere (a fresh GPU machine writes to a fresh $OUT) needs only what changes.
    main(["--out", str(tmp_path / "m2"), "--root", str(packed), "--resume", str(tmp_path / "m" / "last.pt"), "steps=3"])
    again = torch.load(tmp_path / "m2" / "last.pt", weights_only=False)
    assert again["step"] == 3 and again["config"]["loss"] == "min" and len(again["history"]) == 2
    # A new stage from a checkpoint keeps its network, labels and loss; the host's fields are this run's.
    main(["--out", str(tmp_path / "m3"), "--root", str(packed), "--init", str(tmp_path / "m" / "last.pt"),
          "steps=1", "workers=0", 'simulation={"size": 48, "pixel_mm": 2.5, "surroundings_share": 0.5}'])
    stage = torch.load(tmp_path / "m3" / "last.pt", weights_only=False)
    assert stage["config"]["init_from"]["whole_network"] is True and stage["config"]["loss"] == "min"
    assert stage["config"]["width"] == 0.25 and stage["simulation"]["surroundings_share"] == 0.5
    with pytest.raises(SystemExit):
        main(["--out", str(tmp_path / "x"), "nonsense=1"])


def test_training_modules_import_without_the_service_stack() -> None:
    """A GPU host has numpy, scipy and torch, not SimpleITK, the web stack or ONNX: the training of
    either network imports none (the pose network's scene share runs the localiser: onnxruntime)."""
    blocked = ("SimpleITK", "pydantic", "fastapi", "starlette", "typer", "pydantic_settings", "redis", "rq",
               "onnx", "onnxruntime")
    code = ("import sys\n" + "".join(f"sys.modules[{n!r}] = None\n" for n in blocked) +
            "import model_export.train, model_export.stream, model_export.simulate\n"
            "import model_export.localiser.train, model_export.localiser.dataset\nprint('ok')")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert out.stdout.strip() == "ok", out.stderr[-2000:]


def test_the_cli_resumes_and_stages_with_the_runs_own_settings(packed: Path, tmp_path: Path) -> None:
    """``svrnet-train train --resume`` continues with the run's settings, not the options' defaults
    (dropout 0.5, anchor labels, l2: a network of another shape or another training); ``--init``
    keeps the stage's, its simulation included; a batch the stream cannot fill is refused."""
    from typer.testing import CliRunner

    from model_export.cli import app

    first = ["train", "--root", str(packed), "--backbone", "compact", "--width", "0.25", "--label-type", "grid",
             "--loss", "min", "--steps", "2", "--batch", "16", "--val-every", "2", "--val-per-volume", "4",
             "--reuse", "2", "--workers", "0", "--dropout", "0.25", "--lr", "5e-5",
             "--simulation", '{"size": 48, "pixel_mm": 2.5, "tz_fraction": 0.5}']
    runner = CliRunner()
    r = runner.invoke(app, [*first, "--out", str(tmp_path / "a")])
    assert r.exit_code == 0, r.output
    r = runner.invoke(app, ["train", "--root", str(packed), "--out", str(tmp_path / "a"), "--steps", "3",
                            "--resume", str(tmp_path / "a" / "last.pt")])
    assert r.exit_code == 0, r.output
    resumed = torch.load(tmp_path / "a" / "last.pt", weights_only=False)
    assert resumed["step"] == 3
    kept = {f.name: f.read_bytes() for f in (tmp_path / "a").iterdir()}
    r = runner.invoke(app, ["train", "--root", str(packed), "--out", str(tmp_path / "a"), "--steps", "3",
                            "--resume", str(tmp_path / "a" / "last.pt")])            # a finished run: said, not redone
    assert r.exit_code == 0 and "nothing to do" in r.output and "3 of 3 steps" in r.output, r.output
    assert {f.name: f.read_bytes() for f in (tmp_path / "a").iterdir()} == kept
    assert {k: resumed["config"][k] for k in ("dropout", "lr", "label_type", "loss", "width")} == {
        "dropout": 0.25, "lr": 5e-5, "label_type": "grid", "loss": "min", "width": 0.25}
    r = runner.invoke(app, ["train", "--root", str(packed), "--out", str(tmp_path / "b"), "--steps", "1",
                            "--workers", "0", "--init", str(tmp_path / "a" / "last.pt"),
                            "--simulation", '{"surroundings_share": 0.3}'])
    assert r.exit_code == 0, r.output
    stage = torch.load(tmp_path / "b" / "last.pt", weights_only=False)
    assert stage["config"]["dropout"] == 0.25
    assert stage["config"]["simulation"] == {"size": 48, "pixel_mm": 2.5, "tz_fraction": 0.5, "surroundings_share": 0.3}
    r = runner.invoke(app, [*first, "--out", str(tmp_path / "c"), "--batch", "24"])
    assert r.exit_code != 0 and "groups of 16" in r.output


def test_a_checkpoint_without_its_optimiser_is_refused_for_resume_and_starts_a_stage(packed: Path,
                                                                                    tmp_path: Path) -> None:
    """A shipped checkpoint (weights, no optimiser or schedule) cannot continue a run: ``--resume``
    names ``--init`` (it was a KeyError after the atlas had loaded); ``--no-constant-lr`` gives a
    stage after one at a constant rate its step decay again."""
    from typer.testing import CliRunner

    from model_export.cli import app
    from model_export.train import main

    runner = CliRunner()
    r = runner.invoke(app, ["train", "--root", str(packed), "--out", str(tmp_path / "a"), "--backbone", "compact",
                            "--width", "0.25", "--steps", "1", "--batch", "16", "--val-every", "1",
                            "--val-per-volume", "2", "--workers", "0", "--constant-lr",
                            "--simulation", '{"size": 48, "pixel_mm": 2.5}'])
    assert r.exit_code == 0, r.output
    state = torch.load(tmp_path / "a" / "last.pt", weights_only=False)
    assert tuple(state["config"]["lr_milestones"]) == ()
    shipped = tmp_path / "shipped.pt"
    torch.save({k: v for k, v in state.items() if k not in ("optimizer", "scheduler")}, shipped)
    r = runner.invoke(app, ["train", "--root", str(packed), "--out", str(tmp_path / "b"), "--resume", str(shipped)])
    assert r.exit_code != 0 and "--init" in r.output and "optimiser" in r.output
    with pytest.raises(SystemExit) as stop:
        main(["--out", str(tmp_path / "c"), "--root", str(packed), "--resume", str(shipped)])
    assert stop.value.code == 2
    r = runner.invoke(app, ["train", "--root", str(packed), "--out", str(tmp_path / "d"), "--init", str(shipped),
                            "--workers", "0", "--no-constant-lr"])
    assert r.exit_code == 0, r.output
    assert torch.load(tmp_path / "d" / "last.pt", weights_only=False)["config"]["lr_milestones"] == (0.6, 0.85)


@needs_shipped_checkpoints
def test_wrong_usage_of_a_training_run_is_one_usage_line_before_any_work(packed: Path, tmp_path: Path,
                                                                         capsys: pytest.CaptureFixture) -> None:
    """On a GPU host's 15 minutes a traceback after the atlas has loaded, or a setting read wrongly, costs
    the run: a value of another type (``channels_last=False`` was the string "False", which is true), a
    setting the simulation does not have, a label type or device that does not exist, a root without
    the validation volumes, a checkpoint that is a localiser's or of another network than the run
    asks, each stops ``python -m model_export.train`` with one line (exit 2), before its folder is made."""
    from model_export.train import main

    run = ["--out", str(tmp_path / "run"), "--root", str(packed)]
    state = torch.load(Path("service/models/default/checkpoint.pt"), map_location="cpu", weights_only=False)
    localiser = Path("service/localisers/default/checkpoint.pt")
    cases = [([*run, "steps=abc"], "steps takes int"), ([*run, "steps"], "steps=VALUE"),
             ([*run, "channels_last=False"], "channels_last takes bool"),
             ([*run, 'simulation={"tz_fractin": 0.5}'], "no such setting ['tz_fractin']"),
             ([*run, "label_type=foo"], "label_type 'foo'"),
             (["--out", str(tmp_path / "run"), "--root", str(tmp_path / "none")], "no atlas volumes"),
             ([*run, "--init", str(localiser)], "not a pose-network checkpoint"),
             ([*run, "--init", str(tmp_path / "absent.pt")], "no such checkpoint"),
             ([*run, "--init", "service/models/default/checkpoint.pt", f"width={state['config']['width'] / 2}"],
              "its network has {'width'")]
    if not torch.cuda.is_available():
        cases.append(([*run, "device=cuda"], "sees no CUDA device"))
    for argv, words in cases:
        with pytest.raises(SystemExit) as stop:
            main(argv)
        err = capsys.readouterr().err
        assert stop.value.code == 2 and words in err and "Traceback" not in err, (argv, err)
    assert not (tmp_path / "run").exists()


@needs_shipped_checkpoints
def test_the_cli_refuses_checkpoints_of_the_other_network_by_name(tmp_path: Path) -> None:
    """A localiser's checkpoint given to the pose network's commands, a pose network's to the
    localiser's, a checkpoint or a localiser's file where an exported pose model belongs, a path that
    is not there: one line, not a KeyError, TypeError or onnxruntime traceback."""
    from typer.testing import CliRunner

    from model_export.cli import app

    runner = CliRunner()
    localiser, pose = "service/localisers/default/checkpoint.pt", "service/models/default/checkpoint.pt"
    for argv, words in ((["export", localiser, str(tmp_path / "x.onnx")], "a localiser's?"),
                        (["calibrate", localiser], "a localiser's?"),
                        (["export", str(tmp_path / "nope.pt"), str(tmp_path / "x.onnx")], "no such file"),
                        (["localiser", "train", "--data", str(tmp_path), "--out", str(tmp_path / "l.pt"), "--steps", "1",
                          "--init", pose], "a pose network's?"),
                        (["localiser", "train", "--data", str(tmp_path), "--out", str(tmp_path / "l.pt"), "--steps", "1",
                          "--init", localiser, "--width", "64"], "takes its width or a narrower one"),
                        (["evaluate", "service/localisers/default/model.onnx", "--report", str(tmp_path / "r.md")],
                         "not an exported pose model"),
                        (["calibrate-spread", pose], "not an exported pose model"),
                        (["calibrate", pose, "--model", "service/localisers/default/model.onnx"],
                         "not an exported pose model"),
                        (["quantise", str(tmp_path / "nope.onnx"), str(tmp_path / "x.onnx")], "no such file"),
                        (["fix-draws", str(tmp_path / "nope.onnx")], "no such file")):
        r = runner.invoke(app, argv, env={"COLUMNS": "200"})
        assert r.exit_code == 2 and words in " ".join(r.output.split()), (argv, r.output)
    assert not (tmp_path / "x.onnx").exists() and not (tmp_path / "l.pt").exists()


@needs_shipped_checkpoints
def test_the_measuring_commands_refuse_an_atlas_folder_without_the_validation_volumes(
        phantom_atlas: Path, pose_model_copy: Path, tmp_path: Path) -> None:
    """A folder of ``pack --training-only`` (the training volumes alone) given to the commands that
    measure on the validation volumes: one line naming ``--root``, not a ValueError traceback."""
    from typer.testing import CliRunner

    from model_export.cli import app

    runner = CliRunner()
    packed = tmp_path / "packed"
    assert runner.invoke(app, ["pack", "--out", str(packed), "--root", str(phantom_atlas), "--training-only"]).exit_code == 0
    pose = "service/models/default/checkpoint.pt"
    for argv in (["evaluate", str(pose_model_copy), "--report", str(tmp_path / "r.md")], ["calibrate-spread", str(pose_model_copy)],
                 ["calibrate", pose], ["ship", pose, "--out", str(tmp_path / "m")]):
        r = runner.invoke(app, [*argv, "--root", str(packed)], env={"COLUMNS": "200"})
        said = " ".join(r.output.split())
        assert r.exit_code == 2 and "--root" in said and "validation volumes not found" in said, (argv, r.output)
    assert not (tmp_path / "r.md").exists() and not (tmp_path / "m").exists()
