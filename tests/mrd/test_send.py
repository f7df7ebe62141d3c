"""``svrnet-mrd-send`` against a simulated truth: stack files of any slice axis become MRD images that
place every pixel where the file's affine does, sent in the acquisition order asked; a whole session
against a running ``svrnet-mrd`` answers every image with its true pose; bad options, unreadable
files and an absent server get their exit codes."""

from __future__ import annotations

import json
import socket
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from service.io.volume import Volume, write_volume
from service.mrd import send
from service.mrd.images import slice_from_image
from service.mrd.server import ServerLimits
from tests.mrd.conftest import Case
from tests.mrd.test_images import oblique_stack, pixel_grid
from tests.support.streams import true_sent


@pytest.mark.parametrize("slice_axis", [0, 1, 2])
@pytest.mark.parametrize("mirrored", [False, True])
def test_every_pixel_of_every_image_lies_where_the_files_affine_puts_its_voxel(slice_axis: int, mirrored: bool) -> None:
    stack = oblique_stack((7, 6, 5), seed=slice_axis, mirrored=mirrored)
    order = [0, 1, 2]
    order.remove(2)
    order.insert(slice_axis, 2)                      # the thick axis moved to slice_axis
    volume = Volume(np.transpose(stack.array, order), stack.affine[:, order + [3]])
    images = send.series_images(volume, series=4, order="interleaved")
    n = volume.array.shape[slice_axis]
    assert [i.slice for i in images] == send.send_order(n, "interleaved")
    assert [i.image_index for i in images] == list(range(n)) and {i.image_series_index for i in images} == {4}
    for image in images:
        pixels, scanner_from_voxel = slice_from_image(image)
        k = image.slice
        in_plane = [a for a in range(3) if a != slice_axis]
        ijk = np.zeros((pixels.size, 4))
        grid = pixel_grid(*pixels.shape)
        ijk[:, in_plane[0]], ijk[:, in_plane[1]], ijk[:, slice_axis], ijk[:, 3] = grid[:, 0], grid[:, 1], k, 1.0
        truth = (volume.affine @ ijk.T).T[:, :3]
        np.testing.assert_allclose((scanner_from_voxel @ grid.T).T[:, :3], truth, atol=1e-3)
        np.testing.assert_array_equal(pixels.ravel(), np.take(volume.array, k, axis=slice_axis).ravel())


def test_orders_of_sending() -> None:
    assert send.send_order(5, "sequential") == [0, 1, 2, 3, 4]
    assert send.send_order(5, "interleaved-odd-first") == [1, 3, 0, 2, 4]
    assert send.send_order(4, "1, 3, 0, 2") == [1, 3, 0, 2]
    for bad in ("auto", "0,1,1,2", "0,1,2", "sideways"):
        with pytest.raises(ValueError):
            send.send_order(4, bad)


def write_case_stacks(case: Case, folder: Path) -> list[Path]:
    """The case's stacks as NIfTI files, rebuilt from the images it sends (slice axis last)."""
    paths = []
    for series, images in enumerate(case.images):
        slices = sorted((slice_from_image(i) + (i.slice,) for i in images), key=lambda t: t[2])
        affine = slices[0][1].copy()
        affine[:3, 2] = slices[1][1][:3, 3] - slices[0][1][:3, 3]
        path = folder / f"series{series}.nii.gz"
        write_volume(Volume(np.stack([p for p, _, _ in slices], axis=-1), affine), path)
        paths.append(path)
    return paths


def test_a_session_from_files_answers_every_image_with_its_true_pose(case: Case, serve, tmp_path: Path,
                                                                    capsys: pytest.CaptureFixture) -> None:  # noqa: ANN001
    server = serve()
    paths = write_case_stacks(case, tmp_path)
    out = tmp_path / "answers.jsonl"
    code = send.main([*map(str, paths), "--port", str(server.port), "--order", "interleaved",
                      "--config", json.dumps({"mc_samples": 10, "bias_correction": False}), "--out", str(out)])
    assert code == send.EXIT_OK
    records = [json.loads(line) for line in out.read_text().splitlines()]
    images = [r for r in records if r["type"] == "image"]
    assert [(r["series"], r["slice"]) for r in images] == [(s, k) for s in (0, 1) for k in send.send_order(20, "interleaved")]
    for r in images:
        np.testing.assert_allclose(r["atlas_from_voxel"], true_sent(case.truths[r["series"]], r["slice"]), atol=1e-2)
    assert [r["stack"] for r in records if r["type"] == "stack"] == ["0", "1"]    # one length: each ends at once
    assert records[-1]["type"] == "summary" and records[-1]["slices"] == 40
    printed = capsys.readouterr().out.splitlines()
    assert printed[0].startswith("series 0 (series0.nii.gz): 20 of 20 answered") and "final: " in printed[0]


def free_port() -> int:
    with socket.socket() as s:                               # a port nobody listens on, once closed
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_exit_codes_name_what_is_wrong(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    stack = tmp_path / "stack.nii.gz"
    write_volume(oblique_stack((6, 6, 4), seed=1), stack)
    (tmp_path / "notes.nii.gz").write_bytes(b"not an image")
    port = free_port()
    assert send.main([str(stack), "--port", str(port)]) == send.EXIT_CONNECTION
    assert f"127.0.0.1:{port}" in capsys.readouterr().err
    assert send.main([str(tmp_path / "notes.nii.gz"), "--port", str(port)]) == send.EXIT_BAD_INPUT
    assert "notes.nii.gz" in capsys.readouterr().err
    assert send.main([str(tmp_path / "mistyped.nii.gz"), "--port", str(port)]) == send.EXIT_USAGE
    assert "mistyped.nii.gz: no such file" in capsys.readouterr().err                # not "corrupt"
    for order in ("auto", "sideways", "0,1,1"):
        assert send.main([str(stack), "--order", order]) == send.EXIT_USAGE
        assert "--order" in capsys.readouterr().err
    assert send.main([str(stack), "--order", "0,1,2"]) == send.EXIT_USAGE     # three indices, four slices
    assert "--order: stack.nii.gz" in capsys.readouterr().err
    assert send.main([str(stack), "--config", "[1]"]) == send.EXIT_USAGE
    assert "--config: not a JSON object" in capsys.readouterr().err
    assert send.main([str(stack), "--out", str(tmp_path / "no" / "such" / "a.jsonl")]) == send.EXIT_USAGE
    assert "--out" in capsys.readouterr().err


def test_a_server_that_does_not_speak_mrd_is_named_so(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    stack = tmp_path / "stack.nii.gz"
    write_volume(oblique_stack((6, 6, 4), seed=1), stack)
    with socket.socket() as listener:
        listener.bind(("127.0.0.1", 0))
        listener.listen(1)

        def answer_http() -> None:
            conn, _ = listener.accept()
            with conn:
                conn.recv(65536)
                conn.sendall(b"HTTP/1.1 400 Bad Request\r\nContent-Length: 0\r\n\r\n")

        threading.Thread(target=answer_http, daemon=True).start()
        code = send.main([str(stack), "--port", str(listener.getsockname()[1]), "--wait-s", "20"])
    assert code == send.EXIT_CONNECTION
    assert "not MRD messages" in capsys.readouterr().err


def test_a_slightly_sheared_file_is_sent_with_orthogonal_axes_where_the_service_places_it() -> None:
    stack = oblique_stack((7, 6, 5), seed=4)
    affine = stack.affine.copy()
    affine[:3, 0] += 5e-4 * np.linalg.norm(affine[:3, 0]) * affine[:3, 1] / np.linalg.norm(affine[:3, 1])
    volume = Volume(stack.array, affine)                    # axes 0.03 deg from right angles (the service takes 0.06)
    for image in send.series_images(volume, series=0):
        _, scanner_from_voxel = slice_from_image(image)
        grid = pixel_grid(7, 6)
        voxel = grid.copy()
        voxel[:, 2] = image.slice
        np.testing.assert_allclose((scanner_from_voxel @ grid.T).T[:, :3], (affine @ voxel.T).T[:, :3], atol=0.02)


def test_a_series_final_poses_are_its_stack_message_as_later_updates_move_them() -> None:
    tally = send.SeriesTally("series 0", sent=3)
    tally.take({"type": "update", "stack": "0", "slices": [{"index": 0, "accepted": True}]})   # before its end: not final
    assert tally.final == {}
    tally.take({"type": "stack", "stack": "0", "reacquire": [{"index": 1}, {"index": 2}], "slices": [
        {"index": k, "accepted": k == 0, "expected_error_mm": e} for k, e in enumerate((2.0, 6.0, None))]})
    tally.take({"type": "update", "stack": "0", "reacquire": [{"index": 2}],
                "slices": [{"index": 1, "accepted": True, "expected_error_mm": 3.0}]})
    tally.take({"type": "update", "stack": "1", "slices": [{"index": 2, "accepted": True}]})   # another series'
    assert tally.line().endswith("final: 2 of 3 accepted, median expected error 2.5 mm, 1 worth acquiring again")


def test_a_server_whose_sessions_are_taken_says_so_and_the_sender_ends_busy(case: Case, serve, tmp_path: Path,
                                                                           capsys: pytest.CaptureFixture) -> None:  # noqa: ANN001
    server = serve(limits=ServerLimits(max_sessions=1))
    holder = send.MrdLink("127.0.0.1", server.port)
    try:
        holder.send(case.images[0][0])
        deadline = time.monotonic() + 60
        while not holder.received:                      # the first session holds the slot once it answers
            assert time.monotonic() < deadline
            holder._reader.join(timeout=0.05)
        paths = write_case_stacks(case, tmp_path)
        assert send.main([str(paths[0]), "--port", str(server.port)]) == send.EXIT_BUSY
        err = capsys.readouterr().err
        assert "error 503" in err and "retry after" in err and "before its summary" in err
    finally:
        holder.close()
