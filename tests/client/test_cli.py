"""The ``svrnet`` CLI against ``httpx.MockTransport`` fakes of the contract: what each command prints and
writes, its exit codes, and what it refuses before uploading anything."""

from __future__ import annotations

import io
import json
import re
import socket
import zipfile
from collections.abc import Callable
from pathlib import Path
from typing import Any

import httpx
import pytest
from typer.testing import CliRunner

import client.cli as cli
import client.job_views as job_views
import client.stream_views as stream_views
import client.views as views
from client import SVRnetClient
from client.launch import installed_version
from tests.support.client_fakes import PREDICT_BODY, FakeJobs, FakeServer, parse_multipart, send_json


@pytest.fixture
def fake_cli(monkeypatch: pytest.MonkeyPatch, no_sleep: list[float]) -> Callable[..., tuple[FakeServer, list]]:
    def install(**kwargs: Any) -> tuple[FakeServer, list]:
        fake = FakeServer(**kwargs)
        made: list[tuple[str, str | None]] = []

        def factory(server: str, api_key: str | None) -> SVRnetClient:
            made.append((server, api_key))
            return SVRnetClient(server, api_key=api_key, transport=httpx.MockTransport(fake), retries=1)

        monkeypatch.setattr(cli, "make_client", factory)
        return fake, made

    return install


def invoke(args: list[str], **env: str) -> Any:
    return CliRunner().invoke(cli.app, args, env={"COLUMNS": "200", **env})


def test_cli_predict_writes_its_files_before_it_prints(fake_cli: Callable, stack_file: Path, tmp_path: Path,
                                                      monkeypatch: pytest.MonkeyPatch) -> None:
    """Its output piped to a reader that closes early (`| head`): the answer is on disk all the same."""
    def closed(*args: Any) -> None:
        raise BrokenPipeError

    fake_cli()
    monkeypatch.setattr(cli, "summarise", closed)
    out = tmp_path / "poses.json"
    invoke(["predict", str(stack_file), "--out", str(out)])
    assert json.loads(out.read_text()) == PREDICT_BODY


def test_an_output_under_home_is_written_where_it_was_checked(fake_cli: Callable, stack_file: Path, tmp_path: Path,
                                                              monkeypatch: pytest.MonkeyPatch) -> None:
    """``--out=~/x`` reaches the program unexpanded (a shell leaves it so, an argument list always):
    it is written under the home folder, where it was checked before the upload, not lost after it."""
    fake_cli()
    home = tmp_path / "home"
    home.mkdir()
    monkeypatch.setenv("HOME", str(home))
    monkeypatch.chdir(tmp_path)
    r = invoke(["predict", str(stack_file), "--out=~/poses.json"], HOME=str(home))
    assert r.exit_code == 0, r.output
    assert json.loads((home / "poses.json").read_text()) == PREDICT_BODY and not (tmp_path / "~").exists()
    r = invoke(["masks", str(stack_file), "--out-dir", "~/masks"], HOME=str(home))
    assert r.exit_code == 0 and (home / "masks" / "stack_mask.nii.gz").exists() and not (tmp_path / "~").exists()


def test_cli_predict_writes_json_and_prints_a_summary(fake_cli: Callable, stack_file: Path, tmp_path: Path) -> None:
    fake, made = fake_cli()
    out = tmp_path / "poses.json"
    r = invoke(["predict", str(stack_file), "--out", str(out), "--mc-samples", "5", "--no-bias-correction",
                "--no-stack-consistency", "--no-image-consistency", "--masks-hold-csf", "--server", "http://scanner:9000"])
    assert r.exit_code == 0, r.output
    assert json.loads(out.read_text()) == PREDICT_BODY
    assert made == [("http://scanner:9000", None)]
    assert "stack.nii.gz" in r.stdout and "empty 1" in r.stdout and "variance 1" in r.stdout and "variance = high_variance" in " ".join(r.stdout.split()) and "3" in r.stdout
    assert "variance" in r.stdout and "their medians" in r.stdout and "abc" in r.stdout
    assert "312 ml" in r.stdout and "(0.93)" in r.stdout and "2 of 3" in r.stdout      # of the slices with brain
    assert "no slice accepted" not in r.stdout
    fields, files = parse_multipart(fake.requests[0])
    assert fields == {"mc_samples": ["5"], "bias_correction": ["false"], "stack_consistency": ["false"],
                      "image_consistency": ["false"], "masks_hold_csf": ["true"]}
    assert files[0][1] == "stack.nii.gz"
    assert "--masks-hold-csf: no --mask given, so it does nothing" in " ".join(r.stderr.split())   # sent all the same
    with_mask = invoke(["predict", str(stack_file), "--mask", str(stack_file), "--masks-hold-csf"])
    assert with_mask.exit_code == 0 and "does nothing" not in with_mask.stderr, with_mask.output


@pytest.mark.parametrize("name", ["axial1_lr.nii.gz", "sub-000_ses-01_T2w_haste_coronal_run-2.nii.gz"])
def test_the_summary_fits_an_80_column_terminal_and_cuts_no_cell_short(name: str) -> None:
    from rich.console import Console

    stack = PREDICT_BODY["stacks"][0]
    reasons = ["empty", "high_expected_error", "outside_atlas", "inconsistent_with_stack"]
    body = {**PREDICT_BODY, "max_expected_error_mm": 4.2, "stacks": [
        {**stack, "filename": name, "slices": [{"index": i, "accepted": False, "reason": reasons[i % 4],
                                                "expected_error_mm": 50.0, "geodesic_variance": 123.0}
                                               for i in range(40)]}] * 2}
    console = Console(width=80, record=True, file=io.StringIO())
    console.print(views.summarise(body))
    text = console.export_text()
    assert max(len(line) for line in text.splitlines()) <= 80 and "…" not in text
    assert "0 of 30" in text and "50.0 mm" in text and "123" in text and "312 ml" in text and "variance" in text
    for word in ("empty 10", "error 10", "outside 10", "inconsistent 10"):   # each reason whole, on its own line
        assert word in text
    if len(name) <= views.NAME_WIDTH:
        assert name in text                                       # a usual name stays whole
    else:                                                         # a long one folds, nothing of it dropped
        first_column = "".join(re.split(r"\s{2,}", line.strip())[0] for line in text.splitlines())
        assert name in first_column


def test_the_summary_medians_leave_out_empty_slices() -> None:
    from rich.console import Console

    stack = {**PREDICT_BODY["stacks"][0], "slices": [
        {"index": i, "accepted": False, "reason": "empty" if i < 6 else "high_expected_error",
         "expected_error_mm": 60.0 if i < 6 else 7.5, "geodesic_variance": 900.0 if i < 6 else 40.0} for i in range(10)]}
    console = Console(width=100, record=True, file=io.StringIO())
    console.print(views.summarise({**PREDICT_BODY, "stacks": [stack]}))
    text = console.export_text()
    assert "7.5 mm" in text and "60.0" not in text and " 40 " in text and "900" not in text and "0 of 4" in text


def test_the_masks_table_fits_an_80_column_terminal_and_cuts_no_name_short() -> None:
    from rich.console import Console

    name = "sub-000_ses-01_T2w_haste_coronal_run-2.nii.gz"
    row = {"filename": name, "mask": name.replace(".nii.gz", "_mask.nii.gz"), "brain_volume_ml": 301.4,
           "confidence": 0.91, "slices_with_brain": 17}
    console = Console(width=80, record=True, file=io.StringIO())
    console.print(views.masks_table([row, row], "/data/masks"))
    text = console.export_text()
    assert max(len(line) for line in text.splitlines()) <= 80 and "…" not in text
    assert text.count("run-2") == 4 and "301" in text and "0.91" in text      # both names of both rows, to the end
    bare = Console(width=80, record=True, file=io.StringIO())                # the fields api-v1 names alone
    bare.print(views.masks_table([{k: v for k, v in row.items() if k != "mask"}], "/data/masks"))
    shown = bare.export_text()
    assert "301" in shown and "0.91" in shown


def test_the_stream_table_fits_an_80_column_terminal_and_cuts_no_cell_short() -> None:
    from rich.console import Console

    console = Console(width=80, record=True, file=io.StringIO())
    rows = [{"stack": "sub-000_ses-01_T2w_haste_coronal_run-2", "index": i, "accepted": i % 2 == 0,
             "reason": None if i % 2 == 0 else "inconsistent_with_stack", "expected_error_mm": 12.25,
             "translation_mm": [-101.4, -40.5, -14.6], "latency_ms": 157.0, "updated": i == 3} for i in range(4)]
    console.print(stream_views.StreamView(console).table(rows, "stack cor: final poses"))
    text = console.export_text()
    assert max(len(line) for line in text.splitlines()) <= 80 and "…" not in text
    assert text.count("✗ inconsistent_with_stack") == 2 and text.count("(-101, -40, -15)") == 4 and "3*" in text


def test_cli_masks_writes_the_masks_and_nothing_outside(fake_cli: Callable, stack_file: Path, tmp_path: Path) -> None:
    fake, _ = fake_cli()
    out = tmp_path / "deep" / "masks"
    r = invoke(["masks", str(stack_file), "--out-dir", str(out), "--model", "default", "--margin-mm", "2.5"])
    assert r.exit_code == 0, r.output
    assert sorted(p.name for p in out.iterdir()) == ["report.json", "stack_mask.nii.gz"]
    assert not (tmp_path / "deep" / "escape.json").exists()
    assert (out / "stack_mask.nii.gz").read_bytes() == b"mask bytes"
    assert "stack_mask.nii.gz" in r.stdout and "0.91" in r.stdout and "301" in r.stdout
    fields, files = parse_multipart(fake.requests[0])
    assert fake.requests[0].url.path == "/v1/masks" and fields == {"model": ["default"], "margin_mm": ["2.5"]}
    assert [f[:2] for f in files] == [("stacks", "stack.nii.gz")]


def test_cli_masks_keeps_files_already_there_unless_told_and_checks_its_folder_first(
        fake_cli: Callable, stack_file: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A hand-drawn ``stack_mask.nii.gz`` beside its stack is not replaced without ``--overwrite``, and
    nothing else of the answer is written either; a folder that cannot be one is refused before the upload."""
    fake, _ = fake_cli()
    own = tmp_path / "stack_mask.nii.gz"
    own.write_bytes(b"drawn by hand")
    r = invoke(["masks", str(stack_file), "--out-dir", str(tmp_path)])
    assert r.exit_code == 2 and "stack_mask.nii.gz" in r.output and "--overwrite" in r.output, r.output
    assert own.read_bytes() == b"drawn by hand" and not (tmp_path / "report.json").exists()
    assert not fake.requests and "nothing was sent" in " ".join(r.output.split())     # refused before the upload
    r = invoke(["masks", str(stack_file), "--out-dir", str(tmp_path), "--overwrite"])
    assert r.exit_code == 0 and own.read_bytes() == b"mask bytes", r.output
    assert not list(tmp_path.glob(".*.partial"))
    sent = len(fake.requests)
    r = invoke(["masks", str(stack_file), "--out-dir", str(stack_file / "sub")])      # under a file
    assert r.exit_code == 2 and "--out-dir" in r.output and len(fake.requests) == sent, r.output
    real_mkdir = Path.mkdir                 # a folder its parent's permissions allow but the system does not (/proc)

    def refuse(self: Path, *args: object, **kwargs: object) -> None:
        if self.name == "refused":
            raise OSError(30, "Read-only file system")
        real_mkdir(self, *args, **kwargs)

    monkeypatch.setattr(Path, "mkdir", refuse)
    r = invoke(["masks", str(stack_file), "--out-dir", str(tmp_path / "refused")])
    assert r.exit_code == 2 and "cannot be made (Read-only file system)" in " ".join(r.output.split())
    assert len(fake.requests) == sent                                   # nothing sent, no traceback


def test_cli_masks_of_a_second_batch_join_the_folder_s_report(fake_cli: Callable, stack_file: Path,
                                                             tmp_path: Path) -> None:
    """A second `svrnet masks` into a folder of masks: no refusal for its report.json, which then lists
    the masks of both batches (an entry whose mask is gone is dropped), the earlier report in the
    shape this server wrote before api-v1's list."""
    fake_cli()
    (tmp_path / "ax_mask.nii.gz").write_bytes(b"earlier")
    (tmp_path / "report.json").write_text(json.dumps({"localiser": {"version": "0.9"}, "stacks": [
        {"filename": "ax.nii.gz", "mask": "ax_mask.nii.gz", "confidence": 0.8},
        {"filename": "gone.nii.gz", "mask": "gone_mask.nii.gz"}]}))
    r = invoke(["masks", str(stack_file), "--out-dir", str(tmp_path)])
    assert r.exit_code == 0, r.output
    report = json.loads((tmp_path / "report.json").read_text())
    assert [e["mask"] for e in report] == ["ax_mask.nii.gz", "stack_mask.nii.gz"]
    assert report[0]["localiser"] == {"version": "0.9"}                     # made by the earlier localiser
    assert (tmp_path / "ax_mask.nii.gz").read_bytes() == b"earlier"


def test_cli_sends_each_slice_order_as_one_field(fake_cli: Callable, stack_file: Path) -> None:
    fake, _ = fake_cli()
    r = invoke(["predict", str(stack_file), str(stack_file), "--slice-order", "interleaved",
                "--slice-order", "0,2,4,1,3,5"])
    assert r.exit_code == 0, r.output
    fields, _ = parse_multipart(fake.requests[0])
    assert fields == {"slice_order": ["interleaved", "0,2,4,1,3,5"]}


def test_cli_server_and_key_from_the_environment(fake_cli: Callable) -> None:
    fake, made = fake_cli(key="k")
    r = invoke(["models"], SVRNET_SERVER="http://env:1234", SVRNET_API_KEY="k")
    assert r.exit_code == 0, r.output
    assert made == [("http://env:1234", "k")] and "default" in r.stdout and "449" in r.stdout and "4.5 mm" in r.stdout


def test_cli_predict_writes_every_slices_transform_as_a_job_lays_them_out(fake_cli: Callable, stack_file: Path,
                                                                           tmp_path: Path) -> None:
    fake_cli()
    target = tmp_path / "transforms.zip"
    r = invoke(["predict", str(stack_file), "--transforms-out", str(target)])
    assert r.exit_code == 0, r.output
    assert f"wrote {target}" in r.stdout
    with zipfile.ZipFile(target) as z:
        assert sorted(z.namelist()) == sorted([f"transforms/stack0_slice{k:03d}.tfm" for k in range(4)]
                                              + ["transforms/slice_transforms.txt"])
        params = z.read("transforms/stack0_slice002.tfm").decode().splitlines()[3].split()[1:]
        listing = z.read("transforms/slice_transforms.txt").decode().splitlines()
    assert [float(v) for v in params[9:]] == [4.0, 0.0, 0.0]      # atlas 4 mm right (RAS) of the scanner: +4 mm L in LPS
    assert [line.split()[:4] for line in listing[1:]] == [["0", "0", "1", "2.000"], ["0", "1", "1", "2.500"],
                                                          ["0", "2", "0", "9.000"], ["0", "3", "0", "nan"]]


def test_transforms_of_a_server_without_scanner_from_voxel_are_refused_saying_why(
        fake_cli: Callable, stack_file: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from tests.support import client_fakes

    older = json.loads(json.dumps(PREDICT_BODY))
    del older["stacks"][0]["scanner_from_voxel"]
    monkeypatch.setattr(client_fakes, "PREDICT_BODY", older)
    fake_cli()
    r = invoke(["predict", str(stack_file), "--transforms-out", str(tmp_path / "t.zip")])
    assert r.exit_code == 5 and "scanner_from_voxel" in r.stderr and "update the server" in r.stderr, r.output
    assert not (tmp_path / "t.zip").exists()


@pytest.mark.parametrize(("kwargs", "args", "code", "needle"), [
    ({"mode": "down"}, ["models"], 3, "Connection refused"),
    ({"key": "k"}, ["models"], 4, "API key"),
    ({"mode": "422"}, ["predict", "STACK"], 5, "flat.nii.gz"),
    ({}, ["status", "nojob"], 6, "nojob"),
])
def test_cli_exit_codes(fake_cli: Callable, stack_file: Path, kwargs: dict, args: list[str], code: int,
                        needle: str) -> None:
    fake_cli(**kwargs)
    r = invoke([str(stack_file) if a == "STACK" else a for a in args])
    assert r.exit_code == code, r.output
    assert r.stderr.startswith("error: ") and needle in r.stderr and len(r.stderr.strip().splitlines()) == 1
    assert "Traceback" not in r.output and r.stdout == ""


def test_cli_usage_errors_and_help(fake_cli: Callable, stack_file: Path, tmp_path: Path) -> None:
    fake, _ = fake_cli()
    assert invoke(["predict", str(stack_file), str(stack_file), "--mask", str(stack_file)]).exit_code == 2
    assert invoke(["predict", str(tmp_path / "missing.nii.gz")]).exit_code == 2
    assert invoke(["predict", str(stack_file), "--threshold", "0"]).exit_code == 2
    for args in (["status", " "], ["cancel", ""], ["reconstruct", str(stack_file), "--out", str(tmp_path / "no" / "r.nii.gz")],
                 ["predict", str(stack_file), "--out", str(tmp_path / "no" / "p.json")]):
        r = invoke(args)
        assert r.exit_code == 2 and "Traceback" not in r.output, (args, r.output)
    assert not fake.requests                                  # refused before anything was uploaded
    help_text = invoke(["--help"]).stdout
    assert "Exit codes" in help_text and "3 connection failed" in help_text and "10 conflict" in help_text
    assert "Exit codes" in invoke(["predict", "--help"]).stdout
    assert "Exit codes:" in cli.__doc__
    version = invoke(["--version"])
    assert version.exit_code == 0 and version.stdout.strip() == f"svrnet {installed_version()}" and installed_version()


def test_cli_reconstruct_wait_downloads(fake_cli: Callable, stack_file: Path, tmp_path: Path) -> None:
    fake, _ = fake_cli()
    poses = tmp_path / "poses.json"
    poses.write_text(json.dumps(PREDICT_BODY))
    out, preview, refined = tmp_path / "recon.nii.gz", tmp_path / "preview.png", tmp_path / "refined.json"
    transforms = tmp_path / "transforms.zip"
    r = invoke(["reconstruct", str(stack_file), "--poses", str(poses), "--resolution", "0.8", "--svr-iterations",
                "2", "--wait", "--poll", "0.05", "--out", str(out), "--preview", str(preview),
                "--poses-out", str(refined), "--transforms-out", str(transforms), "--no-atlas-frame", "--slice-order",
                "interleaved", "--thickness", "2.5", "--model", "fast", "--max-expected-error", "4"])
    assert r.exit_code == 0, r.output
    assert out.read_bytes() == FakeJobs.VOLUME and preview.read_bytes() == FakeJobs.PREVIEW
    assert transforms.read_bytes() == FakeJobs.TRANSFORMS
    assert json.loads(refined.read_text())["refined_by"] == {"job_id": "job1"}
    assert "job1" in r.stdout and "succeeded" in r.stdout
    # no terminal, no bar: a line per stage on stderr, so that a script's log shows where the job is
    stages = [line for line in r.stderr.splitlines() if line.startswith("job job1: ")]
    assert len(stages) >= 2 and len(set(stages)) == len(stages), r.stderr
    # what the job made of the slices: three posed, all placed; their median refined expected error
    # against the starting poses'
    assert ("refined poses: 3 of 3 posed slices placed (2 in the volume, 1 by their stack's motion, 0 registered "
            "to it); median expected error 1.90 mm (starting poses 2.50 mm)") in " ".join(r.stdout.split())
    fields, files = fake.jobs.uploads[0]
    assert fields == {"resolution_mm": ["0.8"], "svr_iterations": ["2"], "atlas_frame": ["false"],
                      "slice_order": ["interleaved"], "slice_thickness_mm": ["2.5"], "model": ["fast"],
                      "max_expected_error_mm": ["4.0"]} and files[-1][0] == "poses"


def test_cli_reconstruct_says_until_when_the_server_keeps_the_results_and_delete_deletes_them(
        fake_cli: Callable, stack_file: Path, tmp_path: Path) -> None:
    """A finished job's volume is patient data on the server: without ``--delete`` the command says
    until when the server keeps it and how to delete it now; with it (which implies ``--wait``), the
    job is deleted once the files are written; ``fetch --delete`` likewise."""
    fake, _ = fake_cli()
    r = invoke(["reconstruct", str(stack_file), "--wait", "--poll", "0.05", "--out", str(tmp_path / "a.nii.gz")])
    assert r.exit_code == 0, r.output
    assert ("the server keeps the job's results until 2026-12-10T09:30:00.000Z; svrnet cancel job1 deletes them "
            "now") in " ".join(r.stdout.split()) and "job1" in fake.jobs.jobs
    r = invoke(["reconstruct", str(stack_file), "--delete", "--poll", "0.05", "--out", str(tmp_path / "b.nii.gz")])
    assert r.exit_code == 0, r.output
    assert (tmp_path / "b.nii.gz").read_bytes() == FakeJobs.VOLUME
    assert "deleted job job2 and its results on the server" in " ".join(r.stdout.split())
    assert "job2" not in fake.jobs.jobs and "job1" in fake.jobs.jobs
    r = invoke(["fetch", "job1", "--delete", "--poll", "0.05", "--out", str(tmp_path / "c.nii.gz")])
    assert r.exit_code == 0 and "job1" not in fake.jobs.jobs, r.output



def test_a_delete_that_fails_after_the_files_are_written_keeps_the_commands_answer(
        fake_cli: Callable, stack_file: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The files are on disk: a server that cannot delete the job now (busy, gone, a Ctrl-C) is told as a
    warning naming what deletes it later, and the command's exit code stays that of its answer."""
    from client.errors import ServerError

    fake, _ = fake_cli()
    for raised in (ServerError("503 store down"), KeyboardInterrupt()):
        def refuse(self: SVRnetClient, job_id: str, raised: BaseException = raised) -> None:
            raise raised

        monkeypatch.setattr(SVRnetClient, "cancel", refuse)
        out = tmp_path / f"{type(raised).__name__}.nii.gz"
        r = invoke(["reconstruct", str(stack_file), "--delete", "--poll", "0.05", "--out", str(out)])
        assert r.exit_code == 0 and out.read_bytes() == FakeJobs.VOLUME, r.output
        said = " ".join(r.stderr.split())
        assert "the results are written, but the job could not be deleted on the server" in said
        assert "svrnet cancel job" in said and "deleted job" not in r.stdout


def test_cli_fetch_follows_a_job_started_without_wait_and_downloads_its_results(fake_cli: Callable, stack_file: Path,
                                                                               tmp_path: Path) -> None:
    fake_cli()
    r = invoke(["reconstruct", str(stack_file)])
    assert r.exit_code == 0 and "svrnet fetch job1" in r.stdout
    out, refined = tmp_path / "v.nii.gz", tmp_path / "refined.json"
    r = invoke(["fetch", "job1", "--poll", "0.05", "--out", str(out), "--poses-out", str(refined)])
    assert r.exit_code == 0, r.output
    assert out.read_bytes() == FakeJobs.VOLUME and json.loads(refined.read_text())["refined_by"] == {"job_id": "job1"}
    assert "job1 succeeded" in r.stdout and not (tmp_path / "preview.png").exists()
    assert invoke(["fetch", "nojob", "--out", str(tmp_path / "n.nii.gz")]).exit_code == 6


def test_one_file_named_for_two_outputs_stops_the_command_before_anything_is_sent(fake_cli: Callable,
                                                                                   stack_file: Path, tmp_path: Path) -> None:
    """``--out x --preview x`` would write the volume, then the picture over it, and exit 0."""
    fake, _ = fake_cli()
    same = tmp_path / "same.nii.gz"
    again = f"{tmp_path}/../{tmp_path.name}/same.nii.gz"                  # the same file, named otherwise
    for args in (["fetch", "job1", "--out", str(same), "--preview", str(same)],
                 ["reconstruct", str(stack_file), "--wait", "--out", str(same), "--poses-out", again]):
        r = invoke(args)
        assert r.exit_code == 2 and "also given to --out" in r.output and not fake.requests, r.output
    assert not same.exists()


def test_cli_checks_the_default_volume_path_before_uploading(fake_cli: Callable, stack_file: Path, tmp_path: Path,
                                                            monkeypatch: pytest.MonkeyPatch) -> None:
    fake, _ = fake_cli()
    monkeypatch.chdir(tmp_path)
    (tmp_path / "recon.nii.gz").mkdir()                   # where --wait without --out would write
    r = invoke(["reconstruct", str(stack_file), "--wait"])
    assert r.exit_code == 2 and "recon.nii.gz" in r.output and not fake.requests, r.output
    r = invoke(["fetch", "job1"])
    assert r.exit_code == 2 and "recon.nii.gz" in r.output and not fake.requests, r.output


def test_a_ctrl_c_while_a_job_is_followed_says_the_job_goes_on(fake_cli: Callable, stack_file: Path, tmp_path: Path,
                                                                 monkeypatch: pytest.MonkeyPatch) -> None:
    fake_cli()
    monkeypatch.chdir(tmp_path)

    def interrupted(*args: object) -> None:
        raise KeyboardInterrupt

    monkeypatch.setattr(cli, "follow_job", interrupted)
    for args in (["reconstruct", str(stack_file), "--wait"], ["fetch", "job1"]):
        r = invoke(args)
        said = " ".join(r.output.split())
        assert r.exit_code == 130 and "goes on on the server" in said and "svrnet cancel job" in said, r.output
    monkeypatch.setattr(cli, "follow_job", lambda *args: {"status": "succeeded"})
    monkeypatch.setattr(cli, "write_results", interrupted)                # the download interrupted
    r = invoke(["fetch", "job1"])
    said = " ".join(r.output.split())
    assert r.exit_code == 130 and "succeeded and its results wait" in said and "cancel" not in said, r.output


def test_cli_fetch_writes_the_volume_in_a_stack_s_scanner_coordinates(fake_cli: Callable, stack_file: Path,
                                                                      tmp_path: Path) -> None:
    """``--stack-space N`` asks for the volume placed in stack N's scanner coordinates and says how far
    that stack's slices moved about the place; a stack the job could not place is the server's 404."""
    fake, _ = fake_cli()
    invoke(["reconstruct", str(stack_file)])
    out = tmp_path / "v0.nii.gz"
    r = invoke(["fetch", "job1", "--poll", "0.05", "--out", str(out), "--stack-space", "0"])
    assert r.exit_code == 0, r.output
    assert out.read_bytes() == FakeJobs.VOLUME + b" placed by stack 0"
    said = " ".join(r.stdout.split())
    assert "the scanner coordinates of stack 0" in said and "placed by 12 of its slices, which moved 1.3 mm" in said
    assert any(q.url.params.get("stack") == "0" for q in fake.requests)
    r = invoke(["fetch", "job1", "--out", str(tmp_path / "v1.nii.gz"), "--stack-space", "1"])
    assert r.exit_code == 6 and "stack 1 has no slice in the volume" in r.output and not (tmp_path / "v1.nii.gz").exists()
    asked = len(fake.requests)
    r = invoke(["reconstruct", str(stack_file), "--stack-space", "1"])                  # one stack given
    assert r.exit_code == 2 and "not one of the 1 stacks given" in r.output and len(fake.requests) == asked


def test_cli_fetch_refuses_a_stack_space_a_server_cannot_give(fake_cli: Callable, stack_file: Path,
                                                              tmp_path: Path) -> None:
    """A server whose reports have no ``stack_frames`` ignores ``?stack=`` and would send the atlas-space
    volume: nothing is downloaded and the user is told to fetch without the option."""
    fake, _ = fake_cli()
    fake.jobs.STACK_FRAMES = None
    invoke(["reconstruct", str(stack_file)])
    out = tmp_path / "v.nii.gz"
    r = invoke(["fetch", "job1", "--poll", "0.05", "--out", str(out), "--stack-space", "0"])
    assert r.exit_code == 6 and "does not place volumes by a stack" in r.output and not out.exists()
    assert not any(q.url.path.endswith("/volume") for q in fake.requests)


def test_cli_reconstruct_without_wait_and_failed_job(fake_cli: Callable, stack_file: Path, tmp_path: Path) -> None:
    fake_cli()
    r = invoke(["reconstruct", str(stack_file)])
    assert r.exit_code == 0 and "svrnet status job1" in r.stdout
    fake_cli(jobs="failed")
    r = invoke(["reconstruct", str(stack_file), "--wait", "--poll", "0.05", "--out", str(tmp_path / "x.nii.gz")])
    assert r.exit_code == 8 and "SVR diverged" in r.stderr and not (tmp_path / "x.nii.gz").exists()
    r = invoke(["status", "job1"])                        # a script asking later learns the same
    assert r.exit_code == 8 and "failed" in r.stdout
    assert invoke(["status", "job1", "--json"]).exit_code == 8


def test_cli_status_cancel_and_conflict(fake_cli: Callable, stack_file: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    fake, _ = fake_cli()
    assert invoke(["reconstruct", str(stack_file)]).exit_code == 0
    r = invoke(["status", "job1"])
    assert r.exit_code == 0 and "queued" in r.stdout
    r = invoke(["status", "job1", "--json"])
    assert r.exit_code == 0 and json.loads(r.stdout)["job_id"] == "job1"
    r = CliRunner().invoke(cli.app, ["status", "job1", "--json"], env={"FORCE_COLOR": "1"})   # as CI runners set it
    assert r.exit_code == 0 and "\x1b[" not in r.stdout and json.loads(r.stdout)["job_id"] == "job1"
    r = invoke(["cancel", "job1"])                        # the fake's job moves on at each poll: now finished
    assert r.exit_code == 0 and "job1 (succeeded) deleted" in r.stdout
    assert invoke(["cancel", "job1"]).exit_code == 6
    assert invoke(["reconstruct", str(stack_file)]).exit_code == 0
    queued = list(fake.jobs.jobs)[-1]
    r = invoke(["cancel", queued])                        # queued at the first look, still at the DELETE
    assert r.exit_code == 0 and f"job {queued} cancelled" in r.stdout, r.stdout
    assert invoke(["reconstruct", str(stack_file)]).exit_code == 0
    ending = list(fake.jobs.jobs)[-1]
    real_cancel = SVRnetClient.cancel

    def finished_first(self, job_id: str) -> None:         # queued at the first look, finished before the DELETE
        fake.jobs.jobs[job_id].update(status="succeeded")
        real_cancel(self, job_id)

    monkeypatch.setattr(SVRnetClient, "cancel", finished_first)
    r = invoke(["cancel", ending])
    assert r.exit_code == 0 and f"{ending} had ended before the cancel arrived: deleted with its results" in r.stdout


def test_status_of_a_finished_job_prints_how_to_judge_its_volume(fake_cli: Callable, stack_file: Path) -> None:
    fake_cli(jobs="one_apart")
    assert invoke(["reconstruct", *[str(stack_file)] * 4]).exit_code == 0
    for _ in range(3):                                       # the fake's job moves on at each poll
        r = invoke(["status", "job1"])
    assert r.exit_code == 0 and "succeeded" in r.stdout
    assert "leave one stack out 0.79 (per stack 0.86, 0.44, 0.90, - (not in the volume))" in r.stdout
    assert "refined poses: 3 of 3" in r.stdout


def test_a_job_waiting_for_a_worker_that_is_not_running_says_so(fake_cli: Callable, stack_file: Path,
                                                                 tmp_path: Path) -> None:
    fake_cli(workers=0)
    assert invoke(["reconstruct", str(stack_file)]).exit_code == 0
    r = invoke(["status", "job1"])
    assert r.exit_code == 0 and "no worker is running" in r.stdout
    fake_cli(workers=0)
    r = invoke(["reconstruct", str(stack_file), "--wait", "--poll", "0.05", "--out", str(tmp_path / "v.nii.gz")])
    assert r.exit_code == 0 and r.stderr.count("no worker is running (svrnet-worker)") == 1, r.stderr
    fake_cli(workers=2)
    r = invoke(["reconstruct", str(stack_file), "--wait", "--poll", "0.05", "--out", str(tmp_path / "w.nii.gz")])
    assert r.exit_code == 0 and "no worker" not in r.stderr


def test_cli_timeout_from_the_environment(stack_file: Path) -> None:
    r = invoke(["models", "--server", "http://127.0.0.1:9"], SVRNET_TIMEOUT="soon")
    assert r.exit_code == 2 and "SVRNET_TIMEOUT" in r.output
    r = invoke(["models", "--server", "http://127.0.0.1:9"], SVRNET_TIMEOUT="inf")
    assert r.exit_code == 2 and "SVRNET_TIMEOUT" in r.output
    assert cli.make_client("http://x", None)._http.timeout.read == 300.0
    r = invoke(["models", "--server", "http://[::1"])                                  # no URL at all: usage
    assert r.exit_code == 2 and "--server" in r.output, r.output
    r = invoke(["models", "--server", "127.0.0.1:8000"])                               # no scheme: usage, said so
    assert r.exit_code == 2 and "http://127.0.0.1:8000" in " ".join(r.output.split()), r.output


def test_a_bad_api_key_is_named_as_the_key_not_the_server() -> None:
    r = invoke(["models", "--server", "http://127.0.0.1:1", "--api-key", "bad\tkey"])
    said = " ".join(r.output.split())
    assert r.exit_code == 2 and "api_key" in said and "--server" not in said, said


def test_cli_says_where_a_server_speaks_no_tls() -> None:
    import http.server
    import threading

    plain = http.server.HTTPServer(("127.0.0.1", 0), http.server.BaseHTTPRequestHandler)
    threading.Thread(target=plain.serve_forever, daemon=True).start()
    try:
        r = invoke(["models", "--server", f"https://127.0.0.1:{plain.server_port}"])
    finally:
        plain.shutdown()
    said = " ".join(r.output.split())
    assert r.exit_code == 3 and "does not speak TLS" in said and "no server answers" not in said, said


def test_cli_says_where_no_server_answers() -> None:
    with socket.socket() as s:                                   # a port nothing listens on
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    r = invoke(["models", "--server", f"http://127.0.0.1:{port}"])
    said = " ".join(r.output.split())
    assert r.exit_code == 3 and f"no server answers at http://127.0.0.1:{port}" in said and "make serve" in said, said


def _alone(reason: str, confidence: float = 0.9, method: str = "network") -> dict:
    stack = PREDICT_BODY["stacks"][0]
    return {**PREDICT_BODY, "max_expected_error_mm": 4.5, "stacks": [
        {**stack, "localisation": {"method": method, "brain_volume_ml": 300.0, "confidence": confidence},
         "slices": [{"index": i, "accepted": False, "reason": reason, "expected_error_mm": 6.0} for i in range(3)]}]}


def test_predict_without_the_image_stage_blames_the_stage_not_the_images(fake_cli: Callable, stack_file: Path) -> None:
    """Two stacks, none of their slices accepted: with ``--no-image-consistency`` (or
    ``--no-stack-consistency``) the CLI says that stage was off and to send the request with every
    stage on; with every stage on it says the slices do not agree where the image stage left them
    disagreeing, and that the network is unsure of them where nothing says they disagree."""
    two = {**_alone("high_expected_error"), "stacks": [{**st, "image_consistency": {"agreed": False}}
                                                        for st in _alone("high_expected_error")["stacks"] * 2]}
    for option, stage in (("--no-image-consistency", "image"), ("--no-stack-consistency", "stack")):
        fake_cli(predict_body=two)
        off = " ".join(invoke(["predict", str(stack_file), str(stack_file), option]).stdout.split())
        assert f"with the {stage} consistency stage off" in off and "every stage on" in off
        assert "do not agree" not in off
    fake_cli(predict_body=two)
    on = " ".join(invoke(["predict", str(stack_file), str(stack_file)]).stdout.split())
    assert "stage off" not in on and "do not agree" in on
    plain = {**two, "stacks": [{k: v for k, v in st.items() if k != "image_consistency"} for st in two["stacks"]]}
    fake_cli(predict_body=plain)
    unsure = " ".join(invoke(["predict", str(stack_file), str(stack_file)]).stdout.split())
    assert "do not agree" not in unsure and "unsure where these slices lie" in unsure and "6.0 mm" in unsure


def test_a_request_whose_frame_error_holds_its_slices_back_is_told_so_not_that_its_stacks_disagree() -> None:
    """Two stacks, no slice accepted, every expected error raised by the request's frame error: the
    hint names the frame error and that a job starts from the slices whose own errors pass, and
    does not blame the stacks' agreement; without the frame error it does."""
    two = {**_alone("high_expected_error"), "stacks": _alone("high_expected_error")["stacks"] * 2}   # 6 mm over 4.5
    framed = {**two, "stacks": [{**st, "frame": {"request_network_error_mm": 23.6, "expected_error_added_mm": 4.2}}
                                for st in two["stacks"]]}
    hints = views.predict_hints(framed)
    assert len(hints) == 1 and hints[0].startswith("no slice accepted: ")
    assert "4.20 mm for the request's placement" in hints[0] and "24 mm" in hints[0]
    assert "starts from the slices whose own errors pass" in hints[0] and "do not agree" not in hints[0]
    assert "drawn by hand" in hints[0] and "drafts to correct" in hints[0]      # the service's own masks: no remedy
    half = {**framed, "stacks": [{**framed["stacks"][0], "slices": [{**sl, "accepted": True, "reason": None}
                                                                     for sl in framed["stacks"][0]["slices"]]},
                                 framed["stacks"][1]]}
    assert [h for h in views.predict_hints(half) if h.startswith("fewer slices accepted: ")]
    masked = {**framed, "stacks": [{**st, "localisation": {"method": "mask"}} for st in framed["stacks"]]}
    assert "tissue beside the brain" in views.predict_hints(masked)[0]
    two = {**two, "stacks": [{**st, "consistency": {"decidable": False}} for st in two["stacks"]]}
    assert "do not agree" in views.predict_hints(two)[0]
    slight = {**two, "stacks": [{**st, "frame": {"request_network_error_mm": 12.0, "expected_error_added_mm": 0.65}}
                                for st in two["stacks"]]}
    assert "do not agree" in views.predict_hints(slight)[0]      # 6 mm without the frame error too: not its fault
    done = {**framed, "stacks": [{**st, "slices": [{**sl, "accepted": True, "reason": None} for sl in st["slices"]]}
                                 for st in framed["stacks"]]}
    assert views.predict_hints(done) == []                          # accepted all the same: nothing to say


def test_an_answer_with_nothing_usable_says_what_to_do() -> None:
    """A stack sent alone with no slice accepted, a localiser that was unsure, a stack without brain:
    each gets its hint; a usable answer none."""
    assert views.predict_hints(PREDICT_BODY) == []
    alone = views.predict_hints(_alone("high_expected_error"))
    assert len(alone) == 1 and "over 4.5 mm" in alone[0] and "send all the stacks of a scan" in alone[0]
    two = {**_alone("inconsistent_with_stack"), "stacks": _alone("inconsistent_with_stack")["stacks"] * 2}
    assert "do not agree" in views.predict_hints(two)[0] and "over 4.5" not in views.predict_hints(two)[0]
    unsure = views.predict_hints(_alone("high_expected_error", confidence=0.3))
    assert "unsure" in unsure[0] and "0.30" in unsure[0] and "svrnet masks" in unsure[0]
    assert "no brain on the stack" in views.predict_hints(_alone("empty", method="mask"))[0]
    boxed = _alone("high_expected_error", method="mask")
    boxed["stacks"][0]["localisation"]["brain_volume_ml"] = 1180.0                   # a box around the head
    assert "holds 1180 ml, more than any fetal brain" in views.predict_hints(boxed)[0]
    boxed["stacks"][0]["localisation"]["brain_volume_ml"] = 450.0
    assert not [h for h in views.predict_hints(boxed) if "more than any fetal brain" in h]
    assert "localiser found none" in views.predict_hints(_alone("empty", confidence=0.05))[0]
    # A usable answer whose stack is noisier than the poses were calibrated on: told, not alarmed.
    noisy = {**PREDICT_BODY, "stacks": [{**PREDICT_BODY["stacks"][0],
                                         "noise": {"input_noise": 0.124, "beyond_calibration": True}}]}
    assert views.usable(noisy) and [h for h in views.predict_hints(noisy) if "noisier" in h and "0.124" in h
                                    and "less accurate than their expected errors say" in h]
    noisy["stacks"][0]["noise"]["expected_error_added_mm"] = 2.04     # a model calibrated for it says how much
    assert [h for h in views.predict_hints(noisy) if "include 2.04 mm for the noise" in h and "say," not in h]
    noisy["stacks"][0]["noise"]["beyond_calibration"] = False
    assert views.predict_hints(noisy) == []
    # Slices whose brain lost its signal: named, with what to do.
    voided = {**PREDICT_BODY, "stacks": [{**PREDICT_BODY["stacks"][0], "slices": [
        {**s, "index": k, "signal_lost": k in (1, 2)} for k, s in enumerate(PREDICT_BODY["stacks"][0]["slices"] * 3)]}]}
    assert [h for h in views.predict_hints(voided) if "2 slice(s) lost the brain's signal" in h and ": 1, 2)" in h]
    # Slices whose brain the field of view cuts: named, with what to do.
    cut = {**PREDICT_BODY, "stacks": [{**PREDICT_BODY["stacks"][0], "slices": [
        {**s, "index": k, "cut_by_field_of_view": k in (0, 2)} for k, s in enumerate(PREDICT_BODY["stacks"][0]["slices"] * 3)]}]}
    assert [h for h in views.predict_hints(cut) if "field of view ends inside the brain in 2 slice(s) (0, 2)" in h
            and "holds the whole head" in h]
    # One MC pass: no spread was measured; the stacks are not to blame.
    once = _alone("high_variance")
    for s in once["stacks"][0]["slices"]:
        s.update(geodesic_variance=None, expected_error_mm=None)
    hint = views.predict_hints(once)
    assert len(hint) == 1 and "--mc-samples 100" in hint[0] and "agree" not in hint[0]
    # One stack with nothing accepted beside others that have: that stack is named.
    none = {**_alone("high_expected_error")["stacks"][0], "filename": "coronal.nii.gz"}
    mixed = views.predict_hints({**PREDICT_BODY, "stacks": [*PREDICT_BODY["stacks"], none]})
    assert len(mixed) == 1 and mixed[0].startswith("coronal.nii.gz: no slice accepted while the other stacks")
    assert "acquire it again if you need it" in mixed[0]
    # ... and where its branch is the request's and it sits with the others on neither: a mask may help.
    unplaced = {**none, "consistency": {"branch_from_request": True, "branch_agrees_with_request": False}}
    hint = views.predict_hints({**PREDICT_BODY, "stacks": [*PREDICT_BODY["stacks"], unplaced]})
    assert len(hint) == 1 and "left-right branch" in hint[0] and "--mask" in hint[0]


def test_the_cli_prints_the_hints(fake_cli: Callable, stack_file: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    fake_cli()
    monkeypatch.setattr(cli.SVRnetClient, "predict", lambda self, *a, **k: _alone("high_expected_error"))
    r = invoke(["predict", str(stack_file)])
    assert r.exit_code == 12 and "0 of 3" in r.stdout and "send all the stacks of a scan" in r.stdout   # nothing usable


def test_a_volume_that_is_no_coherent_brain_is_written_said_so_and_ends_with_its_exit_code(
        fake_cli: Callable, stack_file: Path, tmp_path: Path) -> None:
    fake_cli(jobs="incoherent")
    out, preview = tmp_path / "recon.nii.gz", tmp_path / "preview.png"
    r = invoke(["reconstruct", str(stack_file), str(stack_file), "--poll", "0.05", "--out", str(out), "--preview",
                str(preview)])
    assert r.exit_code == 12 and "no coherent brain; do not use it" in r.stdout, r.output
    assert out.read_bytes() == FakeJobs.VOLUME and preview.exists()            # the files are still written


def test_a_stack_the_others_do_not_predict_is_named_and_a_scrambled_lone_stack_is_no_coherent_brain(
        fake_cli: Callable, stack_file: Path, tmp_path: Path) -> None:
    fake_cli(jobs="one_apart")
    r = invoke(["reconstruct", *[str(stack_file)] * 4, "--poll", "0.05", "--out", str(tmp_path / "a.nii.gz")])
    text = " ".join(r.stdout.split())
    assert r.exit_code == 0 and "stack 1: the other stacks do not predict it" in text, r.output
    assert "per stack 0.86, 0.44, 0.90, -" in text and "stack 3: no slice of it is in the volume" in text
    whole = [line for line in r.stdout.splitlines() if line.startswith("stack 3: no slice")]   # one line in a pipe
    assert len(whole) == 1 and whole[0].endswith("or send its mask") and len(whole[0]) > 80, r.stdout
    assert "send the job again without it" in text
    fake_cli(jobs="one_left_out")
    r = invoke(["reconstruct", *[str(stack_file)] * 3, "--poll", "0.05", "--out", str(tmp_path / "c.nii.gz")])
    text = " ".join(r.stdout.split())
    assert r.exit_code == 0 and "stack 1: the other stacks do not predict it" in text, r.output
    assert "was made again without it" in text and "no slice of it is in the volume" not in text
    fake_cli(jobs="blended")
    r = invoke(["reconstruct", *[str(stack_file)] * 3, "--poll", "0.05", "--out", str(tmp_path / "d.nii.gz")])
    text = " ".join(r.stdout.split())
    assert r.exit_code == 0 and "median expected error is 23 mm" in text and "mirror image" in text, r.output
    fake_cli(jobs="lone_scrambled")
    r = invoke(["reconstruct", str(stack_file), "--poll", "0.05", "--out", str(tmp_path / "b.nii.gz")])
    text = " ".join(r.stdout.split())
    assert r.exit_code == 12 and "one stack: leave alternate slices out -0.02" in text, r.output
    assert "the stack's slices do not predict each other" in text and "no coherent brain" in text
    assert "no slice of it is in the volume" not in text                   # a lone stack has none to leave out


def test_a_quality_line_says_when_no_stack_can_be_left_out() -> None:
    quality = {"judged_slices": 22, "median_ncc": 0.99, "fraction_ncc_above_0_7": 1.0, "leave_one_stack_out": None}
    assert "one stack: the volume is judged by its own slices only" in job_views.quality_line(quality, stacks=1)
    two = job_views.quality_line(quality, stacks=2)                     # missing for another reason: no blame on the count
    assert two.endswith("leave one stack out: -")


def test_the_models_table_fits_an_80_column_terminal_with_its_thresholds() -> None:
    from rich.console import Console

    model = {"name": "default", "version": "2.11.0", "backbone": "compact", "variance_threshold": 449.0,
             "max_expected_error_mm": 4.5, "sha256": "ab" * 32, "trained_on": ["STA%d" % i for i in range(23)]}
    console = Console(width=80, record=True, file=io.StringIO())
    console.print(views.models_table([model]))
    text = console.export_text()
    assert max(len(line) for line in text.splitlines()) <= 80 and "…" not in text
    assert "default" in text and "2.11.0" in text and "4.5 mm" in text and "449" in text and "STA3" not in text


def test_help_keeps_every_option_name_whole_at_80_columns() -> None:
    for command in ("predict", "reconstruct", "stream", "masks"):
        text = CliRunner().invoke(cli.app, [command, "--help"], env={"COLUMNS": "80"}).stdout
        assert "…" not in text and max(len(line) for line in text.splitlines()) <= 80, command
    text = CliRunner().invoke(cli.app, ["predict", "--help"], env={"COLUMNS": "80"}).stdout
    assert "--max-expected-error" in text and "--no-image-consistency" in text and "interleaved-even-first" in text.replace("\n", "")


def test_every_command_takes_the_api_key_and_an_unauthorised_one_says_how_to_give_it(
        fake_cli: Callable, stack_file: Path, tmp_path: Path) -> None:
    fake, made = fake_cli(key="k")
    assert invoke(["models", "--api-key", "k"]).exit_code == 0 and made[-1][1] == "k"
    assert invoke(["predict", str(stack_file), "--api-key", "k"]).exit_code == 0 and made[-1][1] == "k"
    r = invoke(["models"])
    assert r.exit_code == 4 and "give the key with SVRNET_API_KEY or --api-key" in r.stderr
    r = invoke(["models", "--api-key", "wrong"])
    assert r.exit_code == 4 and "the key sent was refused" in " ".join(r.stderr.split())
    r = invoke(["predict", str(stack_file), "--out", str(tmp_path / "no" / "p.json")])
    assert r.exit_code == 2 and "--out" in r.output and "--preview" not in r.output


def test_a_dicom_folder_goes_as_the_zip_the_server_takes(fake_cli: Callable, tmp_path: Path) -> None:
    fake, _ = fake_cli()
    series = tmp_path / "series 7"
    (series / "sub").mkdir(parents=True)
    (series / "IM0001.dcm").write_bytes(b"first")
    (series / "sub" / "IM0002.dcm").write_bytes(b"second")
    (series / ".DS_Store").write_bytes(b"finder")
    (tmp_path / "secret.txt").write_bytes(b"not of the series")
    (series / "link.dcm").symlink_to(tmp_path / "secret.txt")                 # nothing outside the folder goes
    r = invoke(["predict", str(series)])
    assert r.exit_code == 0, r.output
    _, files = parse_multipart(fake.requests[0])
    (field, filename, content_type, data), = files
    archive = zipfile.ZipFile(io.BytesIO(data))
    assert (field, filename, content_type) == ("stacks", "series 7.zip", "application/zip")
    assert sorted(archive.namelist()) == ["IM0001.dcm", "sub/IM0002.dcm"] and archive.read("IM0001.dcm") == b"first"
    (tmp_path / "empty").mkdir()
    r = invoke(["predict", str(tmp_path / "empty")])
    assert r.exit_code == 2 and "error: stacks: the folder" in r.stderr and "holds no file" in r.stderr
    scan = tmp_path / "scan"                                 # a folder of NIfTI stacks is no DICOM series
    scan.mkdir()
    for name in ("axial.nii.gz", "axial_mask.nii.gz", "LICENSE.txt"):
        (scan / name).write_bytes(b"x")
    r = invoke(["predict", str(scan)])
    out = " ".join(r.stderr.split())
    assert r.exit_code == 2 and "holds image files (axial.nii.gz, axial_mask.nii.gz)" in out and "*.nii.gz" in out


def test_reconstruct_options_out_of_the_servers_range_are_usage_errors_naming_the_option(fake_cli: Callable,
                                                                                        stack_file: Path) -> None:
    """Not the server's 422 naming its form fields (``resolution_mm``), after an upload."""
    fake, _ = fake_cli()
    for args, words in ((["--resolution", "0.1"], "--resolution"), (["--resolution", "6"], "--resolution"),
                        (["--svr-iterations", "11"], "--svr-iterations"),
                        (["--thickness", "3", "--thickness", "2"], "--thickness: 2 values for 1 stacks"),
                        (["--slice-order", "sequential", "--slice-order", "interleaved"], "--slice-order")):
        r = invoke(["reconstruct", str(stack_file), *args])
        assert r.exit_code == 2 and words in r.output, (args, r.output)
    r = invoke(["predict", str(stack_file), "--slice-order", "sequential", "--slice-order", "interleaved"])
    assert r.exit_code == 2 and "--slice-order: 2 values for 1 stacks" in r.output
    assert not fake.jobs.uploads
    assert "at most 5" in invoke(["reconstruct", "--help"]).output


def test_a_slice_order_the_server_cannot_read_is_a_usage_error_before_the_upload(fake_cli: Callable,
                                                                                 stack_file: Path) -> None:
    """A misspelt name (``interleave``) was refused by the server's 422 only after the stacks were sent."""
    fake, _ = fake_cli()
    for command in ("predict", "reconstruct"):
        r = invoke([command, str(stack_file), "--slice-order", "interleave"])
        assert r.exit_code == 2 and "'interleave' is none of auto, sequential" in r.output, r.output
        assert "--slice-order" in r.output
    assert not fake.requests
    r = invoke(["predict", str(stack_file), "--slice-order", " 0, 2,1 "])
    assert r.exit_code == 0, r.output


def test_a_busy_server_s_retry_after_and_a_wait_that_ran_out_say_what_to_do(capsys: pytest.CaptureFixture) -> None:
    import typer

    from client import exits
    from client.errors import Busy, WaitTimeout

    with pytest.raises(typer.Exit) as busy, exits.errors():
        raise Busy("503 Busy: saturated", status=503, retry_after_s=120.0)
    assert busy.value.exit_code == exits.EXIT_BUSY and "retry in 120 s" in capsys.readouterr().err
    svr = cli.make_client("http://svr.test", None)
    svr.status = lambda job_id: {"job_id": job_id, "status": "running"}          # never ends
    with pytest.raises(WaitTimeout, match="svrnet fetch j1 waits for it again"):
        svr.wait("j1", poll_s=0.0, timeout_s=0.0)


def test_a_jobs_urls_are_whole_on_an_80_column_terminal() -> None:
    """``svrnet status`` prints ``preview_url`` and ``result_url`` whole (folded), not cut with an ellipsis."""
    from rich.console import Console

    url = "http://scanner-host.example.org:8000/v1/reconstructions/" + "a1b2c3d4" * 4 + "/preview.png"
    console = Console(width=80, record=True, file=io.StringIO())
    console.print(job_views.job_table({"status": "succeeded", "preview_url": url, "result_url": url[:-12]}, "j"))
    text = re.sub(r"[\s│|]", "", console.export_text())
    assert url in text and "…" not in text


def test_a_stack_the_request_found_mirrored_is_named_with_what_to_do() -> None:
    ok = {"filename": "cor.nii.gz", "consistency": {"mirrored": False}, "slices": [{"accepted": True, "reason": None}] * 3}
    mirrored = {"filename": "ax.nii.gz", "consistency": {"mirrored": True},
                "slices": [{"accepted": False, "reason": "inconsistent_with_stack"}] * 3}
    hints = views.predict_hints({"stacks": [ok, mirrored]})
    assert [h for h in hints if h.startswith("ax.nii.gz: it lies on the mirror image") and "dcm2niix" in h]
    assert not [h for h in hints if h.startswith("cor.nii.gz")]
    assert len([h for h in hints if h.startswith("ax.nii.gz")]) == 1           # not also "too uncertain"
    assert not [h for h in views.predict_hints({"stacks": [ok, ok]}) if "mirror image" in h]


def test_a_stack_of_another_fetus_is_named_with_what_to_do() -> None:
    ok = {"filename": "cor.nii.gz", "consistency": {"apart_from_request": False, "apart_mm": None},
          "slices": [{"accepted": True, "reason": None}] * 3}
    apart = {"filename": "twin.nii.gz", "consistency": {"apart_from_request": True, "apart_mm": 96.4},
             "slices": [{"accepted": False, "reason": "inconsistent_with_stack"}] * 3}
    hints = views.predict_hints({"stacks": [ok, apart]})
    assert [h for h in hints if h.startswith("twin.nii.gz: its brain lies 96 mm from the other stacks'")]
    assert len([h for h in hints if h.startswith("twin.nii.gz")]) == 1         # not also "too uncertain"
    assert not [h for h in views.predict_hints({"stacks": [ok, ok]}) if "another fetus" in h]


def test_a_stack_without_brain_whose_name_says_mask_is_told_to_be_sent_as_a_mask() -> None:
    """A shell glob that sends ``axial_mask.nii.gz`` as a stack: the localiser finds no brain in it, and
    the hint says it may be a mask sent as a stack; a stack of another name is told to send a mask."""
    empty = {"method": "network", "confidence": 0.0}
    body = {"stacks": [{"filename": name, "localisation": empty, "slices": [{"accepted": False, "reason": "empty"}]}
                       for name in ("axial_mask.nii.gz", "coronal.nii.gz")]}
    hints = views.predict_hints(body)
    assert hints[0].startswith("axial_mask.nii.gz: no slice with brain") and "a mask sent as a stack?" in hints[0]
    assert hints[1].startswith("coronal.nii.gz: no slice with brain") and "upload a brain mask with --mask" in hints[1]
    assert "sent as a stack" not in hints[1]
    unmasked = {"stacks": [{**body["stacks"][1], "filename": "sub-01_T2w_unmasked.nii.gz"}]}
    assert "upload a brain mask with --mask" in views.predict_hints(unmasked)[0]     # the word, not a part of one


@pytest.mark.parametrize("command", ["reconstruct", "fetch"])
def test_a_volume_file_not_named_nifti_is_refused_before_anything_is_sent(command: str, fake_cli: Callable,
                                                                          stack_file: Path, tmp_path: Path) -> None:
    """The volume is NIfTI: ``--out recon.mha`` (or ``.nrrd``) would hold gzipped NIfTI that no viewer opens."""
    fake, _ = fake_cli()
    args = [str(stack_file), "--wait"] if command == "reconstruct" else ["job1"]
    r = invoke([command, *args, "--out", str(tmp_path / "recon.mha")])
    assert r.exit_code == 2 and "name it .nii.gz, or .nii" in r.output
    assert not fake.jobs.uploads and not (tmp_path / "recon.mha").exists()


def test_a_sigterm_ends_svrnet_as_a_ctrl_c_does_leaving_no_half_written_file(tmp_path: Path) -> None:
    """systemd, a scheduler's timeout or a CI runner stop a command with SIGTERM: ``svrnet fetch`` in
    the middle of a download ends with exit 130, says that the results wait on the server, and leaves
    no ``.part`` file (before, exit 143 without a word and the part file left behind)."""
    import http.server
    import signal
    import subprocess
    import sys
    import threading
    import time

    class Slow(http.server.BaseHTTPRequestHandler):
        def do_GET(self) -> None:  # noqa: N802 - the standard library's name
            if self.path.endswith("/volume"):
                self.send_response(200)
                self.send_header("Content-Type", "application/gzip")
                self.send_header("Content-Length", "1000000")
                self.end_headers()
                for _ in range(200):                     # a trickle: the command is killed meanwhile
                    self.wfile.write(b"\x1f" * 100)
                    self.wfile.flush()
                    time.sleep(0.1)
                return
            send_json(self, {"job_id": "j1", "status": "succeeded", "stage": "done", "progress": 1.0,
                             "result_url": "/v1/reconstructions/j1/volume", "report": {}})

        def log_message(self, *args: object) -> None:
            pass

    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), Slow)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    try:
        out = tmp_path / "r.nii.gz"
        proc = subprocess.Popen([sys.executable, "-c", "from client.launch import main; main()", "fetch", "j1",
                                 "--out", str(out), "--server", f"http://127.0.0.1:{server.server_address[1]}"],
                                cwd=Path(__file__).resolve().parents[2], stdout=subprocess.PIPE,
                                stderr=subprocess.PIPE, text=True)
        deadline = time.time() + 30
        while not list(tmp_path.glob(".r.nii.gz.part-*")):
            assert time.time() < deadline and proc.poll() is None, proc.communicate()
            time.sleep(0.05)
        proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=30)
    finally:
        server.shutdown()
    assert proc.returncode == 130 and "interrupted; job j1 succeeded and its results wait on the server" in err, err
    assert sorted(p.name for p in tmp_path.iterdir()) == []


def test_a_ctrl_c_while_a_job_is_submitted_names_the_key_that_gets_that_job(stack_file: Path,
                                                                            monkeypatch: pytest.MonkeyPatch) -> None:
    """Interrupted after the upload, before the server's 202: the server may hold the job; the message
    gives the key the submission was sent with, and the same command with ``--idempotency-key`` sends it."""
    keys: list[str] = []

    def interrupted(request: httpx.Request) -> httpx.Response:
        keys.append(request.headers["idempotency-key"])
        request.read()
        raise KeyboardInterrupt

    monkeypatch.setattr(cli, "make_client", lambda server, api_key: SVRnetClient(
        server, transport=httpx.MockTransport(interrupted), retries=0))
    r = invoke(["reconstruct", str(stack_file)])
    assert r.exit_code == 130 and len(keys) == 1, r.output
    assert f"run the same command again with --idempotency-key {keys[0]} to get that job" in " ".join(r.output.split())
    invoke(["reconstruct", str(stack_file), "--idempotency-key", keys[0]])
    assert keys[1] == keys[0]


def test_reconstruct_json_prints_the_submission_for_a_script(fake_cli: Callable, stack_file: Path) -> None:
    """``--json``: the submission's answer and its key as one JSON document on stdout, nothing else;
    with ``--wait`` a usage error before anything is sent."""
    fake, _ = fake_cli()
    r = invoke(["reconstruct", str(stack_file), "--json", "--idempotency-key", "key-of-the-lab-run"])
    assert r.exit_code == 0, r.output
    body = json.loads(r.stdout)
    assert body["job_id"] == "job1" and body["status_url"].endswith("/job1")
    assert body["idempotency_key"] == "key-of-the-lab-run"
    r = invoke(["reconstruct", str(stack_file), "--json", "--wait"])
    assert r.exit_code == 2 and "not with --wait" in r.output and len(fake.jobs.uploads) == 1
