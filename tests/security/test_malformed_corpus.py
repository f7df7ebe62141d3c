"""The malformed-upload corpus of the campaign, generated here (fixed seeds, nothing binary in the repo):
for every file and both upload routes, the exact status, a problem+json naming the client's file (and
the ZIP member), no job or file left behind, and a healthy server afterwards."""

from __future__ import annotations

import struct
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np
import pytest
from fastapi.testclient import TestClient
from pydicom import uid

from service.inference.registry import ModelRegistry
from tests.support import corpus
from tests.api.conftest import OracleEstimator, make_client
from tests.io.test_headers import COMMENTS, mha, nrrd

RNG = np.random.default_rng(15)
STACK = (RNG.random((12, 10, 6)) * 100).astype(np.float32)
SLICES = [(RNG.random((8, 6)) * 1000).astype(np.uint16) for _ in range(3)]
ROWS = b"\x28\x00\x10\x00US\x02\x00\x08\x00"                  # (0028,0010) Rows = 8, explicit VR
LIMIT_MB = 8


def _series(uid_suffix: str) -> dict[str, bytes]:
    out = {}
    for k, p in enumerate(SLICES):
        data = corpus.dicom(p, k)
        out[f"{uid_suffix}/IM{k}"] = data.replace(corpus.SERIES.encode(), (corpus.SERIES[:-1] + uid_suffix).encode())
    return out


def _position_twice(data: bytes, k: int) -> bytes:
    """``data`` (slice ``k`` of :func:`_series`) with an ImagePositionPatient before its own, placing it
    where slice ``2 - k`` lies: GDCM reads the first, pydicom the last (the series reversed)."""
    value = f"0\\0\\{3.0 * (2 - k)}".encode()
    value += b" " * (len(value) % 2)
    at = data.find(b"\x20\x00\x32\x00DS")
    return data[:at] + struct.pack("<HH2sH", 0x20, 0x32, b"DS", len(value)) + value + data[at:]


def _patched(data: bytes, offset: int, values: np.ndarray) -> bytes:
    """``data`` with ``values``' bytes written at ``offset``."""
    return data[:offset] + values.tobytes() + data[offset + values.nbytes:]


def _nrrd_header(fields: bytes, data: bytes = b"") -> bytes:
    return b"NRRD0004\ntype: float\ndimension: 3\nendian: little\n" + fields + b"\n" + data


# name the client gives, content, status, words the detail must hold besides the name
CORPUS: list[tuple[str, Callable[[], bytes], int, tuple[str, ...]]] = [
    ("empty.nii.gz", lambda: b"", 415, ()),
    ("notes.nii", lambda: b"just some text\n" * 100, 415, ()),
    ("random.bin", lambda: RNG.bytes(4096), 415, ()),
    ("truncated.nii.gz", lambda: corpus.gz(corpus.nifti(STACK))[:300], 415, ("gzip",)),
    ("gzip-garbage.nii.gz", lambda: corpus.gz(RNG.bytes(2000)), 415, ()),
    ("bad-crc.nii.gz", lambda: corpus.gz(corpus.nifti(STACK))[:-8] + b"\0" * 8, 415, ()),
    ("declared-bomb.nii.gz", lambda: corpus.gzip_bomb(32), 413, ("MB",)),
    ("stream-bomb.nii.gz", lambda: corpus.gz(corpus.nifti(STACK) + b"\0" * (12 * 2**20)), 413, ("MB",)),
    ("header-only.nii", lambda: corpus.nifti(STACK)[:352], 415, ()),
    ("flat.nii", lambda: corpus.nifti(STACK[:, :, :1]), 422, ("2D",)),
    ("time.nii", lambda: corpus.nifti(np.zeros((4, 4, 3, 2))), 422, ("4D",)),
    ("nan.nii", lambda: corpus.nifti(np.where(STACK > 50, np.nan, STACK)), 422, ("NaN",)),
    ("pair.hdr", lambda: corpus.nifti(STACK, magic=b"ni1\x00")[:352], 415, ("pair",)),
    ("huge-dims.nii", lambda: corpus.nifti(STACK, dims=(3, 30000, 30000, 30000)), 415, ("truncated",)),
    ("short-data.nii", lambda: corpus.nifti(STACK)[:-100], 415, ("truncated",)),
    ("negative-dims.nii", lambda: corpus.nifti(STACK, dims=(3, -5, 10, 6)), 415, ()),
    ("long-detached.nrrd", lambda: nrrd(b"/etc/passwd"), 415, ("detached",)),
    ("missing-detached.nrrd", lambda: nrrd(b"/no/such/file"), 415, ("detached",)),
    ("list.nrrd", lambda: nrrd(b"LIST", b""), 415, ("detached",)),
    ("endless.nrrd", lambda: b"NRRD0004\n" + b"# x\n" * 300_000, 415, ("longer than",)),
    ("huge.nrrd", lambda: _nrrd_header(b"sizes: 4000 4000 4000\nencoding: gzip\n", corpus.gz(b"")), 413, ("MB",)),
    ("short.nrrd", lambda: _nrrd_header(b"sizes: 8 8 8\nencoding: raw\n", b"\0" * 100), 415, ()),
    ("odd-encoding.nrrd", lambda: _nrrd_header(b"sizes: 2 2 2\nencoding: rot13\n", b"\0" * 32), 415, ()),
    ("detached.mha", lambda: mha(b"/etc/passwd", COMMENTS.replace(b"#", b"Comment =")), 415, ("detached",)),
    ("no-data-line.mha", lambda: b"ObjectType = Image\nNDims = 3\nDimSize = 2 2 2\nElementType = MET_UCHAR\n", 415, ()),
    ("huge.mha", lambda: mha(b"LOCAL").replace(b"8 8 8", b"30000 30000 30000") + b"\0" * 64, 413, ("MB",)),
    ("deflate-bomb.dcm", lambda: corpus.deflate_bomb(64), 413, ("MB",)),
    ("cut.dcm", lambda: corpus.dicom(np.zeros((64, 64), np.uint16))[:-5000], 415, ("shorter",)),
    ("no-pixels.dcm", lambda: corpus.deflated(corpus._dataset(8, 8, 1)), 415, ("without pixel data",)),
    ("jpeg-lies.dcm", lambda: corpus.encapsulated([corpus.jpeg_claiming(30000, 30000)], 8, 8,
                                                  uid.JPEGBaseline8Bit), 415, ("frame 0",)),
    ("rle-bomb.dcm", lambda: corpus.encapsulated([corpus.rle_bomb()], 8, 8, uid.RLELossless), 415, ("frame 0",)),
    ("video.dcm", lambda: corpus.encapsulated([b"\0" * 64], 8, 8, uid.MPEG2MPML), 415, ("transfer syntax",)),
    ("many-frames.dcm", lambda: corpus.dicom(np.zeros((2, 64, 64), np.uint16)).replace(b"IS\x02\x002 ",
                                                                                        b"IS\x06\x0099999 "), 422, ("99999 frames", "at most")),
    # pydicom would decode the data beyond the declared frames as more frames.
    ("excess-pixels.dcm", lambda: corpus.dicom(np.zeros((4, 64, 64), np.uint16)).replace(b"IS\x02\x004 ",
                                                                                         b"IS\x02\x002 "), 415,
     ("longer than its header declares",)),
    # Rows stated twice: GDCM, which builds the series, reads the first value, pydicom the last.
    ("rows-twice.zip", lambda: corpus.zipped({name: data.replace(ROWS, ROWS.replace(b"\x08\x00", b"\x20\x4e") + ROWS)
                                              for name, data in _series("1").items()}), 415, ("states the image size twice",)),
    # ImagePositionPatient stated twice: the series' checks saw one order, GDCM would build another.
    ("position-twice.zip", lambda: corpus.zipped({name: _position_twice(data, k)
                                                  for k, (name, data) in enumerate(_series("1").items())}), 415,
     ("states its position, orientation or pixel spacing twice",)),
    ("multi-frame-series.zip", lambda: corpus.zipped({f"IM{k}": corpus.dicom(np.stack([SLICES[k]] * 2), k)
                                                      for k in range(3)}), 422, ("3 files, 3 of them multi-frame",)),
    ("many-images.zip", lambda: corpus.zipped({f"IM{k}": corpus.dicom(SLICES[0], k) for k in range(129)}), 422,
     ("129 DICOM images in the archive", "at most 128")),
    # Geometry a reader would make up: a qform of NaN (ITK: the identity), an axis of no direction
    # (ITK: 1 mm), frames 0 mm apart (1 mm).
    ("nan-qform.nii", lambda: _patched(corpus.nifti(np.ones((8, 8, 4))), 256, np.array([0, np.nan, 0], "<f4")), 422,
     ("qform holds values that are not finite",)),
    ("no-direction.nrrd", lambda: _nrrd_header(b"sizes: 2 2 2\nspace: left-posterior-superior\nspace directions: "
                                               b"(1,0,0) (0,1,0) none\nencoding: raw\n", b"\0" * 32), 422,
     ("space directions place 2",)),
    ("flat.dcm", lambda: corpus.dicom(np.ones((3, 8, 6), np.uint16)).replace(b"DS\x04\x003.0 ", b"DS\x04\x000.0 "),
     422, ("0 mm apart",)),
    ("palette.dcm", lambda: corpus.dicom(np.ones((3, 8, 6), np.uint16)).replace(b"CS\x0c\x00MONOCHROME2 ",
                                                                                b"CS\x0e\x00PALETTE COLOR "), 422,
     ("PALETTE COLOR",)),
    ("one-slice.dcm", lambda: corpus.dicom(SLICES[0]), 422, ("2D",)),
    ("magic-only.dcm", lambda: b"\0" * 128 + b"DICM", 415, ()),
    ("empty.zip", lambda: corpus.zipped({}), 415, ("no DICOM series",)),
    ("text.zip", lambda: corpus.zipped({"readme.txt": b"hello"}), 415, ("no DICOM series",)),
    ("nested.zip", lambda: corpus.zipped({"inner/series.zip": corpus.zipped(_series("1"))}), 415,
     ("member 1 of 1", "nested")),
    ("nested-gzip.zip", lambda: corpus.zipped({"a.dcm.gz": corpus.gz(corpus.dicom(SLICES[0]))}), 415,
     ("member 1 of 1", "nested")),
    ("two-series.zip", lambda: corpus.zipped({**_series("1"), **_series("2")}), 422, ("2 DICOM series",)),
    ("member-bomb.zip", lambda: corpus.zipped({"IM0": b"\0" * (12 * 2**20)}), 413, ("MB",)),
    ("dicom-bomb.zip", lambda: corpus.zipped({"deep/IM0": corpus.deflate_bomb(64)}), 413, ("member 1 of 1",)),
    ("cut-member.zip", lambda: corpus.zipped({"s/IM7": corpus.dicom(np.zeros((64, 64), np.uint16))[:-5000]}), 415,
     ("member 1 of 1", "shorter")),
    ("encrypted.zip", lambda: corpus.encrypted_zip(_series("1")), 415, ("encrypted",)),
    ("truncated.zip", lambda: corpus.zipped(_series("1"))[:700], 415, ()),
    ("traversal.zip", lambda: corpus.zipped({"../../../../tmp/svrnet-owned.txt": b"owned"}), 415, ("no DICOM series",)),
    ("thousands.zip", lambda: corpus.zipped({f"f{i}": b"" for i in range(5001)}, 0), 422, ("too many",)),
    ("mri\u202egpj.nii.gz", lambda: b"x" * 500, 415, ("mrigpj.nii.gz",)),
    ("../../etc/passwd", lambda: b"x" * 500, 415, ("passwd",)),
    ("a" * 1000 + ".nii", lambda: b"x" * 500, 415, ("a" * 200,)),
]
ROUTES = ("/v1/predict", "/v1/reconstructions")


@pytest.fixture(scope="module")
def client(tmp_path_factory: pytest.TempPathFactory) -> Iterator[TestClient]:
    data_dir = tmp_path_factory.mktemp("corpus_jobs")
    with make_client(ModelRegistry({"default": OracleEstimator()}), data_dir=str(data_dir),
                     max_decoded_mb=LIMIT_MB, max_request_decoded_mb=4 * LIMIT_MB) as c:
        yield c


@pytest.mark.parametrize("route", ROUTES)
@pytest.mark.parametrize(("name", "make", "status", "needles"), CORPUS, ids=[c[0][:40] for c in CORPUS])
def test_each_malformed_upload_gets_its_exact_answer(client: TestClient, route: str, name: str,
                                                     make: Callable[[], bytes], status: int,
                                                     needles: tuple[str, ...]) -> None:
    r = client.post(route, files=[("stacks", (name, make()))])
    assert r.status_code == status, (r.status_code, r.text[:500])
    assert r.headers["content-type"].startswith("application/problem+json")
    body = r.json()
    assert body["status"] == status and body["request_id"] == r.headers["x-request-id"]
    shown = "".join(c for c in Path(name.replace("\u202e", "")).name if c.isprintable())[:200]
    assert shown in body["detail"], body["detail"]
    for needle in needles:
        assert needle in body["detail"], (needle, body["detail"])
    assert body["detail"].isprintable() and "svrnet-" not in body["detail"] and "/tmp" not in body["detail"]
    assert "Traceback" not in r.text
    store = client.app.state.job_store
    assert not store.queued() and not any((store.data_dir / "jobs").iterdir())     # nothing left behind
    assert not Path("/tmp/svrnet-owned.txt").exists()
    assert client.get("/healthz").status_code == 200 and client.get("/readyz").status_code == 200


@pytest.mark.parametrize("route", ROUTES)
def test_a_part_header_too_long_to_parse_is_a_malformed_request(client: TestClient, route: str) -> None:
    r = client.post(route, files=[("stacks", ("a" * 9000 + ".nii", b"x" * 500))])
    assert r.status_code == 400 and r.json()["type"] == "/problems/malformed-request"
    assert "could not be parsed" in r.json()["detail"] and client.get("/healthz").status_code == 200


def test_a_bad_file_among_good_ones_is_named(client: TestClient) -> None:
    good = corpus.gz(corpus.nifti(STACK))
    r = client.post("/v1/predict", files=[("stacks", ("good.nii.gz", good)), ("stacks", ("bad.nii.gz", b"x")),
                                          ("stacks", ("good2.nii.gz", good))])
    assert r.status_code == 415 and "bad.nii.gz" in r.json()["detail"] and "good" not in r.json()["detail"]


def test_a_bad_mask_is_named_as_the_mask(client: TestClient) -> None:
    good = corpus.gz(corpus.nifti(STACK))
    r = client.post("/v1/predict", files=[("stacks", ("s.nii.gz", good)), ("masks", ("m.zip", corpus.zipped({})))])
    assert r.status_code == 415 and "m.zip" in r.json()["detail"]
