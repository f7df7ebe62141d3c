"""Every error path of the contract: right status, problem+json, a detail naming the file or field."""

from __future__ import annotations

import gzip
import io
from pathlib import Path

import numpy as np
import pytest
import SimpleITK as sitk
from fastapi.testclient import TestClient

from service.inference.registry import ModelRegistry
from service.io.volume import Volume, write_volume
from tests.api.conftest import make_client


def nifti_bytes(array: np.ndarray, affine: np.ndarray | None = None, tmp: Path | None = None) -> bytes:
    path = (tmp or Path("/tmp")) / f"x{np.random.default_rng().integers(1e9)}.nii.gz"
    write_volume(Volume(array, affine if affine is not None else np.diag([1.0, 1.0, 3.0, 1.0])), path)
    data = path.read_bytes()
    path.unlink()
    return data


def stack(shape=(20, 20, 6), seed=0) -> np.ndarray:
    return np.random.default_rng(seed).random(shape).astype(np.float32) * 100


def post(client: TestClient, files: list, data: dict | None = None):  # noqa: ANN201
    return client.post("/v1/predict", files=files, data=data or {})


def assert_problem(r, status: int, *needles: str) -> None:  # noqa: ANN001
    assert r.status_code == status, r.text
    assert r.headers["content-type"].startswith("application/problem+json")
    body = r.json()
    assert {"type", "title", "status", "detail"} <= set(body) and body["status"] == status
    for n in needles:
        assert n in body["detail"], (n, body["detail"])
    assert "Traceback" not in r.text


def sitk_bytes(image: sitk.Image, tmp_path: Path, name: str) -> bytes:
    path = tmp_path / name
    sitk.WriteImage(image, str(path))
    return path.read_bytes()


@pytest.mark.parametrize(
    ("name", "content", "status", "needle"),
    [
        ("notes.nii.gz", b"hello, this is not an image" * 20, 415, "notes.nii.gz"),
        ("empty.nii", b"", 415, "empty.nii"),
        ("trunc.nii.gz", None, 415, "trunc.nii.gz"),
    ],
)
def test_unreadable_files_are_415(oracle_client: TestClient, name: str, content: bytes | None, status: int,
                                  needle: str) -> None:
    if content is None:
        content = nifti_bytes(stack())[:200]          # a gzip stream cut short
    assert_problem(post(oracle_client, [("stacks", (name, content))]), status, needle)


def test_2d_4d_nan_and_empty_images_are_422(oracle_client: TestClient, tmp_path: Path) -> None:
    two_d = sitk_bytes(sitk.GetImageFromArray(np.ones((8, 8), np.float32)), tmp_path, "a.nii.gz")
    assert_problem(post(oracle_client, [("stacks", ("flat.nii.gz", two_d))]), 422, "flat.nii.gz", "2D")
    four_d = sitk_bytes(sitk.GetImageFromArray(np.ones((2, 4, 8, 8), np.float32)), tmp_path, "b.nii.gz")
    assert_problem(post(oracle_client, [("stacks", ("time.nii.gz", four_d))]), 422, "time.nii.gz", "4D")
    nan = stack()
    nan[3, 3, 3] = np.nan
    assert_problem(post(oracle_client, [("stacks", ("nan.nii.gz", nifti_bytes(nan, tmp=tmp_path)))]), 422, "nan.nii.gz", "NaN")
    single = sitk_bytes(sitk.GetImageFromArray(np.ones((1, 8, 8), np.float32)), tmp_path, "c.nii.gz")
    assert_problem(post(oracle_client, [("stacks", ("one.nii.gz", single))]), 422, "one.nii.gz")


def test_mask_problems(oracle_client: TestClient, tmp_path: Path) -> None:
    s = nifti_bytes(stack(), tmp=tmp_path)
    wrong_shape = nifti_bytes(np.ones((20, 20, 5), np.float32), tmp=tmp_path)
    r = post(oracle_client, [("stacks", ("s.nii.gz", s)), ("masks", ("m.nii.gz", wrong_shape))])
    assert_problem(r, 422, "masks", "m.nii.gz", "s.nii.gz")
    shifted = nifti_bytes(np.ones((20, 20, 6), np.float32), np.array([[1, 0, 0, 5.0], [0, 1, 0, 0], [0, 0, 3, 0], [0, 0, 0, 1]]), tmp_path)
    assert_problem(post(oracle_client, [("stacks", ("s.nii.gz", s)), ("masks", ("m2.nii.gz", shifted))]), 422, "m2.nii.gz", "grid")
    # the mask's slices 1.5 mm apart where the stack's are 3 mm: the same shape, another grid
    denser = nifti_bytes(np.ones((20, 20, 6), np.float32), np.diag([1.0, 1.0, 1.5, 1.0]), tmp_path)
    assert_problem(post(oracle_client, [("stacks", ("s.nii.gz", s)), ("masks", ("m3.nii.gz", denser))]), 422, "m3.nii.gz", "grid")
    two_masks = [("stacks", ("s.nii.gz", s)), ("masks", ("a.nii.gz", s)), ("masks", ("b.nii.gz", s))]
    assert_problem(post(oracle_client, two_masks), 400, "masks", "2 masks for 1 stacks")
    # a mask that does not read, named as its stack is (two folders' files): the problem says it is the mask
    r = post(oracle_client, [("stacks", ("s.nii.gz", s)), ("masks", ("s.nii.gz", s[: len(s) // 2]))])
    assert r.status_code in (415, 422) and r.json()["detail"].startswith("masks: s.nii.gz"), r.json()
    r = post(oracle_client, [("stacks", ("s.nii.gz", s[: len(s) // 2])), ("masks", ("s.nii.gz", s))])
    assert r.status_code in (415, 422) and r.json()["detail"].startswith("s.nii.gz"), r.json()


def test_a_mask_of_more_than_a_fetal_head_is_422_naming_it(real_client: TestClient, tmp_path: Path) -> None:
    """A mask of ones over a whole field of view (the body's, the uterus's) is no brain mask: refused,
    for /v1/predict and for a reconstruction job at its submission, where it would make every step
    work on the whole image; a head-sized mask of the same field of view is taken."""
    wide = np.diag([4.0, 4.0, 6.0, 1.0])                    # 160 x 160 x 150 mm
    image = nifti_bytes(stack((40, 40, 25)), wide, tmp_path)
    ones = np.ones((40, 40, 25), np.uint8)                  # 3,840 ml
    files = [("stacks", ("s.nii.gz", image)), ("masks", ("body.nii.gz", nifti_bytes(ones, wide, tmp_path)))]
    assert_problem(post(real_client, files), 422, "masks", "body.nii.gz", "3840 ml", "fetal brain")
    assert_problem(real_client.post("/v1/reconstructions", files=files), 422, "body.nii.gz", "3840 ml")
    head = np.zeros((40, 40, 25), np.uint8)
    head[10:30, 10:30, 5:20] = 1                             # 80 x 80 x 90 mm: 576 ml
    files = [("stacks", ("s.nii.gz", image)), ("masks", ("head.nii.gz", nifti_bytes(head, wide, tmp_path)))]
    assert post(real_client, files).status_code == 200


def test_a_mask_saved_as_signed_numbers_marks_the_same_brain(real_client: TestClient, tmp_path: Path) -> None:
    """A mask of 255 saved as signed bytes holds -1 where the brain is: its nonzero voxels are the
    brain, as for the same mask of 1, not the complement an image's magnitude would make of it."""
    s = nifti_bytes(stack(), tmp=tmp_path)
    box = np.zeros((20, 20, 6), np.int16)
    box[5:15, 5:15, 1:5] = 1
    volumes = []
    for label in (1, -1):
        r = post(real_client, [("stacks", ("s.nii.gz", s)), ("masks", ("m.nii.gz", nifti_bytes(label * box, tmp=tmp_path)))],
                 {"mc_samples": "2"})
        assert r.status_code == 200, r.text
        volumes.append(r.json()["stacks"][0]["localisation"]["brain_volume_ml"])
    assert volumes[0] == volumes[1] == 1.2                     # 400 voxels of 3 mm^3


def test_stacks_without_masks_on_a_server_without_a_localiser_are_told_to_send_masks(oracle, tmp_path: Path) -> None:  # noqa: ANN001
    """Not a 404 about a localiser the client never named: the field to fix is ``masks``."""
    (tmp_path / "none").mkdir()
    with make_client(ModelRegistry({"default": oracle}), localisers_dir=tmp_path / "none") as client:
        r = post(client, [("stacks", ("s.nii.gz", nifti_bytes(stack(), tmp=tmp_path)))])
    assert_problem(r, 400, "masks", "no brain localiser")


def test_parameters_and_models(oracle_client: TestClient, tmp_path: Path) -> None:
    s = nifti_bytes(stack(), tmp=tmp_path)
    for field, value in [("mc_samples", "0"), ("mc_samples", "1001"), ("mc_samples", "many"),
                         ("variance_threshold", "-1"), ("variance_threshold", "inf"), ("bias_correction", "perhaps"),
                         ("max_expected_error_mm", "0"), ("max_expected_error_mm", "inf"), ("max_expected_error_mm", "x")]:
        assert_problem(post(oracle_client, [("stacks", ("s.nii.gz", s))], {field: value}), 400, field)
    for field in ("variance_threshold", "max_expected_error_mm"):       # not a number: named so, not as "> 0"
        for value in ("nan", "inf"):
            assert_problem(post(oracle_client, [("stacks", ("s.nii.gz", s))], {field: value}), 400, field, "finite")
    assert_problem(post(oracle_client, [("stacks", ("s.nii.gz", s))], {"model": "nope"}), 404, "model", "nope")
    assert_problem(post(oracle_client, []), 400, "stacks")
    r = post(oracle_client, [], {"stacks": "s.nii.gz"})                   # a path as text, not the file
    assert_problem(r, 400, "stacks[0]: must be a file part")
    assert "UploadFile" not in r.text and "class" not in r.text
    r = post(oracle_client, [("stacks", ("s.nii.gz", s))], {"slice_order": "zigzag"})
    assert "Value error" not in r.text and "slice_order[0]" in r.json()["detail"]


def test_a_slice_order_that_says_nothing_known_or_does_not_fit_is_400(oracle, oracle_client: TestClient,  # noqa: ANN001
                                                                     tmp_path: Path) -> None:
    s = nifti_bytes(stack(), tmp=tmp_path)                   # 6 slices
    one = [("stacks", ("s.nii.gz", s))]
    r = post(oracle_client, one, {"slice_order": "zigzag"})
    assert_problem(r, 400, "slice_order", "interleaved-even-first", "e.g. 0,2,4,1,3")
    assert "pattern" not in r.json()["detail"]                   # the values it may take, not a regex
    assert_problem(post(oracle_client, one, {"slice_order": ["sequential", "auto"]}), 400,
                   "slice_order", "2 values for 1 stacks")
    oracle.truth = np.repeat(np.eye(4)[None], 6, axis=0)
    r = post(oracle_client, one, {"slice_order": "0,2,4,1,3"})
    assert_problem(r, 400, "slice_order, stack 0 (s.nii.gz)", "5 indices given for a stack of 6 slices")
    two = one + [("stacks", ("t.nii.gz", nifti_bytes(stack((20, 20, 5), seed=1), tmp=tmp_path)))]
    oracle.truth = np.repeat(np.eye(4)[None], 11, axis=0)
    r = post(oracle_client, two, {"slice_order": "0,2,4,1,3,5"})       # one value the client gave for both
    assert_problem(r, 400, "slice_order, stack 1 (t.nii.gz)", "6 indices")
    oracle.truth = np.repeat(np.eye(4)[None], 6, axis=0)
    r = post(oracle_client, one, {"slice_order": "0,2,4,1,3,5", "bias_correction": "false"})
    assert r.status_code == 200, r.text


def test_too_many_files_and_too_large(oracle: object, tmp_path: Path) -> None:
    s = nifti_bytes(stack(), tmp=tmp_path)
    with make_client(ModelRegistry({"default": oracle}), max_files=2) as client:
        assert_problem(post(client, [("stacks", (f"s{i}.nii.gz", s)) for i in range(3)]), 400, "stacks", "at most 2")
        oracle.truth = np.repeat(np.eye(4)[None], 12, axis=0)             # exactly the limit is taken
        two = [("stacks", (f"s{i}.nii.gz", nifti_bytes(stack(seed=i), tmp=tmp_path))) for i in range(2)]
        r = post(client, two, {"bias_correction": "false"})
        assert r.status_code == 200, r.text
    with make_client(ModelRegistry({"default": oracle}), max_upload_mb=0.001) as client:
        r = post(client, [("stacks", ("big.nii.gz", s + b"\0" * 4096))])
        assert_problem(r, 413, "request body", "limit", "SVRNET_MAX_UPLOAD_MB", "gzipped")


def test_a_stack_of_more_slices_than_the_limit_is_422_before_any_stage(oracle: object, tmp_path: Path) -> None:
    """The stack stage's work grows with the cube of a stack's slices: a few MB of 16 x 16 slices must
    not hold a processing slot for minutes."""
    long = nifti_bytes(np.ones((8, 16, 12), np.float32), tmp=tmp_path)
    with make_client(ModelRegistry({"default": oracle}), max_slices_per_stack=10) as client:
        for route in ("/v1/predict", "/v1/masks", "/v1/reconstructions"):
            r = client.post(route, files=[("stacks", ("long.nii.gz", long))])
            assert_problem(r, 422, "long.nii.gz", "12 slices along its array axis 2", "at most 10")
        assert not client.app.state.job_store.queued()
        oracle.truth = np.repeat(np.eye(4)[None], 10, axis=0)             # exactly the limit is taken
        r = post(client, [("stacks", ("ten.nii.gz", nifti_bytes(np.ones((8, 16, 10), np.float32), tmp=tmp_path)))],
                 {"bias_correction": "false"})
        assert r.status_code == 200, r.text


def test_a_grid_of_more_slices_than_the_limit_along_every_axis_is_422_from_its_header(
        oracle: object, tmp_path: Path) -> None:
    """Told from the header, before the voxels are inflated: a few hundred kB of gzip could otherwise
    decode to the file's limit (and a request's every file) before its slices were counted. Its
    voxels here are cut short, which a decoded file would answer with a 415."""
    whole = nifti_bytes(np.zeros((24, 20, 12), np.float32), tmp=tmp_path)
    plain = gzip.decompress(whole)
    cut = gzip.compress(plain[:400])
    with make_client(ModelRegistry({"default": oracle}), max_slices_per_stack=10) as client:
        for name, body in (("whole.nii.gz", whole), ("cut.nii.gz", cut), ("plain.nii", plain)):
            r = client.post("/v1/predict", files=[("stacks", (name, body))])
            assert_problem(r, 422, name, "a grid of 24 x 20 x 12 voxels holds over 10 slices along each axis",
                           "SVRNET_MAX_SLICES_PER_STACK")


def test_malformed_multipart_is_400_never_500(oracle_client: TestClient) -> None:
    r = oracle_client.post("/v1/predict", content=b"--xx\r\nnot multipart", headers={"content-type": "multipart/form-data; boundary=xx"})
    assert r.status_code == 400, r.text
    r = oracle_client.post("/v1/predict", content=b"{}", headers={"content-type": "application/json"})
    assert r.status_code == 400


def test_a_body_cut_off_before_its_closing_boundary_is_400_not_answered_for_its_first_parts(
        oracle_client: TestClient, tmp_path: Path) -> None:
    """The form parser keeps the parts it finished: a body cut off in its second stack (or its mask)
    would be answered for the first stack alone. It is refused, naming what happened."""
    whole = nifti_bytes(stack(), tmp=tmp_path)
    part = lambda name, filename, data: (f"--zz\r\nContent-Disposition: form-data; name=\"{name}\"; "  # noqa: E731
                                         f"filename=\"{filename}\"\r\n\r\n").encode() + data + b"\r\n"
    body = part("stacks", "a.nii.gz", whole) + part("stacks", "b.nii.gz", whole[: len(whole) // 2])
    for route in ("/v1/predict", "/v1/reconstructions", "/v1/masks"):
        r = oracle_client.post(route, content=body, headers={"content-type": "multipart/form-data; boundary=zz"})
        assert_problem(r, 400, "closing boundary", "cut off")
    r = oracle_client.post("/v1/predict", content=body + b"--zz--\r\n",      # closed: the half file is the fault
                           headers={"content-type": "multipart/form-data; boundary=zz"})
    assert_problem(r, 415, "b.nii.gz")
    for spelt in ("boundary = zz", "boundary\t=\tzz", 'x-boundary=yy; boundary="zz" ; charset=utf-8'):
        r = oracle_client.post("/v1/predict", content=body,                 # read as the form parser reads it
                               headers={"content-type": f"multipart/form-data; {spelt}"})
        assert_problem(r, 400, "closing boundary", "cut off")
    closed = body + b"--zz--\r\n" + b"an epilogue, which RFC 2046 allows\r\n" * 60      # 2 KB after the end
    for spelt in ("boundary = zz", 'x-boundary=yy; boundary="zz" ; charset=utf-8'):
        r = oracle_client.post("/v1/predict", content=closed, headers={"content-type": f"multipart/form-data; {spelt}"})
        assert_problem(r, 415, "b.nii.gz")                      # whole: every part read, the half file named


def test_gzip_of_garbage_is_415(oracle_client: TestClient) -> None:
    data = gzip.compress(b"\0" * 4000)
    assert_problem(post(oracle_client, [("stacks", ("zeros.nii.gz", data))]), 415, "zeros.nii.gz")
    assert_problem(post(oracle_client, [("stacks", ("a.zip", io.BytesIO(b"PK\x03\x04broken").read()))]), 415, "a.zip")


def test_a_chunked_body_over_the_limit_is_413_not_a_parser_400(oracle: object, tmp_path: Path) -> None:
    s = nifti_bytes(stack(), tmp=tmp_path)
    body = (b"--xx\r\nContent-Disposition: form-data; name=\"stacks\"; filename=\"big.nii.gz\"\r\n"
            b"Content-Type: application/octet-stream\r\n\r\n" + s + b"\0" * 8192 + b"\r\n--xx--\r\n")

    def chunks():  # noqa: ANN202 - no Content-Length: the limit is found while reading
        for i in range(0, len(body), 1024):
            yield body[i:i + 1024]

    with make_client(ModelRegistry({"default": oracle}), max_upload_mb=0.002) as client:
        r = client.post("/v1/predict", content=chunks(), headers={"content-type": "multipart/form-data; boundary=xx"})
    assert "content-length" not in {k.lower() for k in r.request.headers}
    assert_problem(r, 413, "limit")
    assert r.headers["x-request-id"]


def test_header_tricks_and_bombs_are_refused(oracle: object, tmp_path: Path) -> None:
    # Headers that point at a file of the server (one SimpleITK would read happily).
    secret = tmp_path / "secret.raw"
    secret.write_bytes(bytes(range(64)))
    nrrd = (b"NRRD0004\ntype: uchar\ndimension: 3\nsizes: 4 4 4\nencoding: raw\n"
            b"data file: " + str(secret).encode() + b"\n\n")
    probe = tmp_path / "probe.nrrd"
    probe.write_bytes(nrrd)
    assert sitk.ReadImage(str(probe)).GetSize() == (4, 4, 4)      # the hole is real
    assert_problem(post_to(oracle, [("stacks", ("x.nrrd", nrrd))]), 415, "x.nrrd", "detached")
    mha = (b"ObjectType = Image\nNDims = 3\nDimSize = 4 4 4\nElementType = MET_UCHAR\n"
           b"ElementDataFile = " + str(secret).encode() + b"\n")
    assert_problem(post_to(oracle, [("stacks", ("x.mha", mha))]), 415, "x.mha", "detached")
    # A gzip stream and an NRRD header that declare more voxel data than the limit.
    big = nifti_bytes(np.zeros((64, 64, 64), np.float32), tmp=tmp_path)
    assert_problem(post_to(oracle, [("stacks", ("bomb.nii.gz", big))], max_decoded_mb=0.5), 413, "bomb.nii.gz")
    huge = b"NRRD0004\ntype: float\ndimension: 3\nsizes: 4000 4000 4000\nendian: little\nencoding: gzip\n\n" + gzip.compress(b"")
    assert_problem(post_to(oracle, [("stacks", ("huge.nrrd", huge))]), 413, "huge.nrrd")


def post_to(oracle: object, files: list, **settings: object):  # noqa: ANN201
    with make_client(ModelRegistry({"default": oracle}), **settings) as client:
        return post(client, files)


def test_a_zip_with_a_corrupt_member_or_too_much_inside(oracle: object, tmp_path: Path) -> None:
    import zipfile

    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_DEFLATED) as z:
        z.writestr("a.dcm", b"\0" * 200_000)
    data = bytearray(buf.getvalue())
    data[60:80] = b"\xff" * 20                      # inside the deflate stream
    assert_problem(post_to(oracle, [("stacks", ("bad.zip", bytes(data)))]), 415, "bad.zip")
    assert_problem(post_to(oracle, [("stacks", ("big.zip", buf.getvalue()))], max_decoded_mb=0.1), 413, "big.zip")


class Broken:
    """An estimator with a bug: the app must still answer problem+json with the request id."""

    info = None

    def estimate(self, inputs, mc_samples):  # noqa: ANN001, ANN201
        raise RuntimeError("/srv/secret/path exploded")


def test_a_server_fault_is_a_500_problem_with_the_request_id_and_no_internals(oracle: object, tmp_path: Path) -> None:
    broken = Broken()
    broken.info = oracle.info
    with make_client(ModelRegistry({"default": broken})) as client:
        r = post(client, [("stacks", ("s.nii.gz", nifti_bytes(stack(), tmp=tmp_path)))])
        assert_problem(r, 500, "request id")
        assert r.headers["x-request-id"] == r.json()["request_id"]
        assert "secret" not in r.text and "RuntimeError" not in r.text
        assert 'status="500"' in client.get("/metrics").text


def test_many_bombs_in_one_request_stop_at_the_request_limit(oracle: object) -> None:
    """Each file is within its own limit; together they pass the request's (413 naming one)."""
    from tests.support.corpus import gzip_bomb

    bomb = gzip_bomb(2)
    files = [("stacks", (f"b{i}.nii.gz", bomb)) for i in range(8)]
    r = post_to(oracle, files, max_decoded_mb=4, max_request_decoded_mb=9)
    assert_problem(r, 413, "nii.gz", "the files of this request decode to more than 9 MB in total")


def test_a_dicom_deflate_bomb_is_413_naming_the_file(oracle: object) -> None:
    from tests.support.corpus import deflate_bomb

    assert_problem(post_to(oracle, [("stacks", ("bomb.dcm", deflate_bomb(64)))], max_decoded_mb=16), 413,
                   "bomb.dcm")


def test_a_full_disk_while_a_file_is_decoded_is_507_not_the_clients_corrupt_file(
        oracle_client: TestClient, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The temporary folder fills while a gzipped stack is inflated to it: the answer says the server's
    disk is full (507, Retry-After), not that the client's file is truncated or corrupt (415)."""
    import builtins
    import errno

    import service.io.readers as readers

    class FullDisk(io.RawIOBase):
        def writable(self) -> bool:
            return True

        def write(self, b) -> int:  # noqa: ANN001
            raise OSError(errno.ENOSPC, "No space left on device")

    def full_open(file, mode="r", *args, **kwargs):  # noqa: ANN001, ANN002, ANN003, ANN202
        return FullDisk() if "w" in mode else builtins.open(file, mode, *args, **kwargs)

    monkeypatch.setattr(readers, "open", full_open, raising=False)
    r = post(oracle_client, [("stacks", ("a.nii.gz", nifti_bytes(stack(), tmp=tmp_path)))])
    assert_problem(r, 507, "disk is full")
    assert r.json()["type"] == "/problems/insufficient-storage" and int(r.headers["Retry-After"]) > 0
    monkeypatch.undo()
    assert post(oracle_client, [("stacks", ("a.nii.gz", b"\x1f\x8b not gzip at all"))]).status_code == 415


def test_a_full_disk_while_the_upload_is_received_is_507_not_a_malformed_body(
        oracle_client: TestClient, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The temporary folder fills while the form parser spools the request's files: 507 with
    Retry-After, not the 400 "the request body could not be parsed" that blames the client."""
    import errno

    from starlette.datastructures import UploadFile

    async def full(self, data: bytes) -> None:  # noqa: ANN001
        raise OSError(errno.EDQUOT, "Disk quota exceeded")

    monkeypatch.setattr(UploadFile, "write", full)
    r = post(oracle_client, [("stacks", ("a.nii.gz", nifti_bytes(stack(), tmp=tmp_path)))])
    assert_problem(r, 507, "disk is full")
    assert int(r.headers["Retry-After"]) > 0
    monkeypatch.undo()
    broken = oracle_client.post("/v1/predict", content=b"--xx\r\nno headers", headers={
        "content-type": "multipart/form-data; boundary=xx"})
    assert broken.status_code == 400                      # a broken body is still the client's


def test_a_stack_sent_twice_is_refused_naming_both_files(oracle_client: TestClient, tmp_path: Path) -> None:
    """A copy would count as a second acquisition that agrees with the first: 400, before any work."""
    data = nifti_bytes(stack(), tmp=tmp_path)
    r = post(oracle_client, [("stacks", ("ax.nii.gz", data)), ("stacks", ("copy_of_ax.nii.gz", data))])
    assert_problem(r, 400, "copy_of_ax.nii.gz is the same image as ax.nii.gz")
    scaled = nifti_bytes((stack() * 37 + 1000).astype(np.int16), tmp=tmp_path)     # exported again, rescaled
    r = post(oracle_client, [("stacks", ("ax.nii.gz", data)), ("stacks", ("ax_int16.nii.gz", scaled))])
    assert_problem(r, 400, "ax_int16.nii.gz is the same image as ax.nii.gz", "up to a scale and an offset")


def test_a_stack_acquired_again_on_the_same_planning_is_no_copy(oracle, oracle_client: TestClient,  # noqa: ANN001
                                                                tmp_path: Path) -> None:
    """The same grid, the same brain, another acquisition's noise (a signal-to-noise ratio of 30): two stacks."""
    voxels = stack()
    again = voxels + np.random.default_rng(7).normal(0, voxels.std() / 30, voxels.shape).astype(np.float32)
    oracle.truth = np.broadcast_to(np.eye(4), (2 * voxels.shape[2], 4, 4)).copy()
    r = post(oracle_client, [("stacks", ("ax.nii.gz", nifti_bytes(voxels, tmp=tmp_path))),
                             ("stacks", ("ax_again.nii.gz", nifti_bytes(again, tmp=tmp_path)))], {"bias_correction": "false"})
    assert r.status_code == 200, r.text


def test_a_stack_sent_twice_in_two_voxel_orders_is_refused_too(oracle_client: TestClient, tmp_path: Path) -> None:
    """A copy a reorienting tool wrote (slices reversed, slice axis first) is the same image: it was
    taken for a second acquisition, and the answer was surer than the scan allows."""
    from service.geometry.pose import index_reversal

    voxels, affine = stack(), np.diag([1.0, 1.0, 3.0, 1.0])
    data = nifti_bytes(voxels, affine, tmp=tmp_path)
    reversed_k = nifti_bytes(np.ascontiguousarray(voxels[:, :, ::-1]), affine @ index_reversal(2, voxels.shape[2]),
                             tmp=tmp_path)
    slice_first = nifti_bytes(np.ascontiguousarray(np.transpose(voxels, (2, 0, 1))), affine[:, [2, 0, 1, 3]], tmp=tmp_path)
    for name, copy in (("reversed.nii.gz", reversed_k), ("slice_first.nii.gz", slice_first)):
        r = post(oracle_client, [("stacks", ("ax.nii.gz", data)), ("stacks", (name, copy))])
        assert_problem(r, 400, f"{name} is the same image as ax.nii.gz")
    from service.io.volume import Volume
    from service.pipeline.stack_upload import StackUpload, check_distinct_stacks

    other = Volume(np.ascontiguousarray(stack(seed=1)[:, :, ::-1]), affine @ index_reversal(2, voxels.shape[2]))
    check_distinct_stacks([StackUpload("ax.nii.gz", Volume(voxels, affine)), StackUpload("other.nii.gz", other)])


def test_a_mask_sent_as_a_stack_is_refused_naming_it_on_predict_and_a_job(oracle_client: TestClient,
                                                                          tmp_path: Path) -> None:
    """A folder's ``*.nii.gz`` sent as stacks takes its masks along: each is 422 naming the mask, before
    any stage, not an answer with its slices empty."""
    voxels = stack()
    mask = (voxels > 50).astype(np.uint8)
    files = [("stacks", ("ax.nii.gz", nifti_bytes(voxels, tmp=tmp_path))),
             ("stacks", ("ax_mask.nii.gz", nifti_bytes(mask, tmp=tmp_path)))]
    assert_problem(post(oracle_client, files), 422, "ax_mask.nii.gz holds the values 0 and 1 alone", "send it as its stack's mask")
    r = oracle_client.post("/v1/reconstructions", files=files)
    assert_problem(r, 422, "ax_mask.nii.gz holds the values 0 and 1 alone")
