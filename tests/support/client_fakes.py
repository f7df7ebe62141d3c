"""Fakes of the HTTP API v1 contract for the client's tests: ``/v1/predict``, ``/v1/masks``, ``/v1/models``
and the reconstruction routes, served through ``httpx.MockTransport`` (no server, no torch)."""

from __future__ import annotations

import email
import http.server
import email.policy
import io
import json
import re
import zipfile
from typing import Any

import httpx


def parse_multipart(request: httpx.Request) -> tuple[dict[str, list[str]], list[tuple[str, str, str, bytes]]]:
    """(form fields, [(field, filename, content type, bytes)]) of a multipart request, via the stdlib."""
    head = f"Content-Type: {request.headers['content-type']}\r\nMIME-Version: 1.0\r\n\r\n".encode()
    msg = email.message_from_bytes(head + request.content, policy=email.policy.HTTP)
    assert msg.is_multipart()
    fields: dict[str, list[str]] = {}
    files = []
    for part in msg.iter_parts():
        name = part.get_param("name", header="content-disposition")
        payload = part.get_payload(decode=True)
        if part.get_filename() is None:
            fields.setdefault(name, []).append(payload.decode())
        else:
            files.append((name, part.get_filename(), part.get_content_type(), payload))
    return fields, files


def problem(status: int, detail: str, title: str = "Problem") -> dict[str, Any]:
    return {"type": "about:blank", "title": title, "status": status, "detail": detail, "request_id": "rid-1"}


def _atlas_from_voxel(k: int) -> list[list[float]]:
    """Slice ``k`` of the fake stack placed 2 mm further right each slice (1 x 1 x 3 mm voxels)."""
    return [[1.0, 0.0, 0.0, 2.0 * k], [0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 3.0, 0.0], [0.0, 0.0, 0.0, 1.0]]


PREDICT_BODY = {
    "request_id": "abc", "model": {"name": "default", "version": "1", "backbone": "b", "sha256": "0" * 64},
    "mc_samples": 5, "variance_threshold": 10.0, "timing_ms": {"total": 12.0},
    "stacks": [{"index": 0, "filename": "stack.nii.gz", "shape": [24, 24, 4], "spacing_mm": [1, 1, 3],
                "slice_axis": 2, "scanner_from_voxel": _atlas_from_voxel(0), "slices": [
                    {"index": 0, "accepted": True, "reason": None, "geodesic_variance": 1.0,
                     "expected_error_mm": 2.0, "atlas_from_voxel": _atlas_from_voxel(0)},
                    {"index": 1, "accepted": True, "reason": None, "geodesic_variance": 3.0,
                     "expected_error_mm": 2.5, "atlas_from_voxel": _atlas_from_voxel(1)},
                    {"index": 2, "accepted": False, "reason": "high_variance", "geodesic_variance": 40.0,
                     "expected_error_mm": 9.0, "atlas_from_voxel": _atlas_from_voxel(2)},
                    {"index": 3, "accepted": False, "reason": "empty", "geodesic_variance": None,
                     "expected_error_mm": None, "atlas_from_voxel": _atlas_from_voxel(3)}],
                "localisation": {"method": "network", "brain_volume_ml": 312.4, "confidence": 0.93}}],
}


def masks_archive() -> bytes:
    """What /v1/masks answers, plus a member that names a path (never written)."""
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w") as z:
        z.writestr("stack_mask.nii.gz", b"mask bytes")
        z.writestr("../escape.json", b"{}")
        z.writestr("report.json", json.dumps([{"filename": "stack.nii.gz", "mask": "stack_mask.nii.gz",
                                               "brain_volume_ml": 301.0, "confidence": 0.91, "slices_with_brain": 17,
                                               "localiser": {"version": "1.2.0"}}]))
    return buffer.getvalue()


class FakeServer:
    """/v1/predict and /v1/models with an optional key, plus the job routes; ``mode`` forces failures;
    ``predict_body``: what /v1/predict answers (default :data:`PREDICT_BODY`)."""

    def __init__(self, key: str | None = None, mode: str = "ok", jobs: str = "succeeded", workers: int = 1,
                 predict_body: dict | None = None) -> None:
        self.key, self.mode = key, mode
        self.predict_body = PREDICT_BODY if predict_body is None else predict_body
        self.jobs = FakeJobs(jobs, workers)
        self.requests: list[httpx.Request] = []

    def __call__(self, request: httpx.Request) -> httpx.Response:
        self.requests.append(request)
        if self.mode == "down":
            raise httpx.ConnectError("[Errno 111] Connection refused", request=request)
        if self.key and request.headers.get("authorization") != f"Bearer {self.key}":
            return httpx.Response(401, json=problem(401, "Authorization: a valid API key is required"))
        if self.mode == "422":
            return httpx.Response(422, json=problem(422, "stacks: flat.nii.gz is a 2D image", "Unusable image"))
        if request.url.path == "/v1/predict":
            return httpx.Response(200, json=self.predict_body)
        if request.url.path == "/v1/masks":
            return httpx.Response(200, content=masks_archive(), headers={"content-type": "application/zip"})
        if request.url.path == "/v1/models":
            return httpx.Response(200, json=[{"name": "default", "version": "1", "backbone": "b",
                                              "sha256": "0" * 64, "input_size": 128, "spacing_mm": 0.8,
                                              "label_type": "anchor", "variance_threshold": 449.0,
                                              "max_expected_error_mm": 4.5, "trained_on": "atlas"}])
        return self.jobs(request)


class FakeJobs:
    """The contract's reconstruction routes: each status poll moves a job queued -> running -> succeeded
    (``outcome``: ``failed``, ``running`` for ever, or ``incoherent``: succeeded with a volume whose
    stacks do not predict each other). ``workers``: what a queued job's status says serves the queue."""

    VOLUME = b"\x1f\x8b fake nifti volume" * 1000
    STACK_FRAMES = [{"stack": 0, "slices": 12, "motion_mm": 1.3,
                     "scanner_from_atlas": [[1.0, 0, 0, 0], [0, 1.0, 0, 0], [0, 0, 1.0, 0], [0, 0, 0, 1.0]]},
                    {"stack": 1, "slices": 0, "scanner_from_atlas": None, "motion_mm": None}]
    PREVIEW = b"\x89PNG fake"
    TRANSFORMS = b"PK fake zip"

    def __init__(self, outcome: str = "succeeded", workers: int = 1) -> None:
        self.outcome, self.workers = outcome, workers
        self.jobs: dict[str, dict[str, Any]] = {}
        self.uploads: list[tuple[dict, list]] = []

    def __call__(self, request: httpx.Request) -> httpx.Response:
        path, method = request.url.path, request.method
        if path == "/v1/reconstructions" and method == "POST":
            self.uploads.append(parse_multipart(request))
            job_id = f"job{len(self.jobs) + 1}"
            self.jobs[job_id] = {"job_id": job_id, "status": "queued", "stage": "queued", "progress": 0.0,
                                 "error": None, "created_at": "t0", "updated_at": "t0", "result_url": None,
                                 "preview_url": None, "report": None, "workers": self.workers, "polls": 0}
            url = f"/v1/reconstructions/{job_id}"
            return httpx.Response(202, headers={"Location": url},
                                  json={"job_id": job_id, "status": "queued", "status_url": url})
        m = re.fullmatch(r"/v1/reconstructions/([^/]+)(/volume|/preview\.png|/poses|/transforms)?", path)
        if not m or m.group(1) not in self.jobs:
            return httpx.Response(404, json=problem(404, f"job: unknown job {m.group(1) if m else path}"))
        job = self.jobs[m.group(1)]
        if method == "DELETE" and not m.group(2):        # as the server: a queued or running job is cancelled,
            if job["status"] in ("queued", "running"):      # its status still readable; a finished one is deleted
                job.update(status="cancelled", stage="cancelled")
            else:
                del self.jobs[m.group(1)]
            return httpx.Response(204)
        if m.group(2):
            if job["status"] != "succeeded":
                return httpx.Response(409, json=problem(409, f"job {job['job_id']} is {job['status']}"))
            if m.group(2) == "/poses":
                return httpx.Response(200, json=dict(PREDICT_BODY, refined_by={"job_id": job["job_id"]}))
            stack = request.url.params.get("stack")
            if m.group(2) == "/volume" and stack is not None:      # in a stack's scanner coordinates
                if int(stack) >= len(self.STACK_FRAMES) or self.STACK_FRAMES[int(stack)]["scanner_from_atlas"] is None:
                    return httpx.Response(404, json=problem(404, f"stack: stack {stack} has no frame"))
                return httpx.Response(200, content=self.VOLUME + f" placed by stack {stack}".encode())
            content = {"/volume": self.VOLUME, "/preview.png": self.PREVIEW, "/transforms": self.TRANSFORMS}
            return httpx.Response(200, content=content[m.group(2)])
        job["polls"] += 1
        if job["status"] == "cancelled":                    # ended: it moves on no further
            pass
        elif job["polls"] == 2:
            job.update(status="running", stage="svr", progress=0.5, workers=None)
        elif job["polls"] >= 3 and self.outcome in ("succeeded", "incoherent", "one_apart", "one_left_out",
                                                    "lone_scrambled", "blended"):
            report: dict[str, Any] = {"slices": [], "refined_poses": {
                "posed": 3, "in_volume": 2, "placed_by_stack_motion": 1, "placed_by_volume": 0,
                "median_expected_error_mm": 1.9, "median_starting_expected_error_mm": 2.5}}
            if self.STACK_FRAMES is not None:         # None: a server of before stack frames
                report["stack_frames"] = self.STACK_FRAMES
            if self.outcome == "incoherent":          # a volume whose stacks do not predict each other
                report.update(n_stacks=2, quality={"judged_slices": 40, "median_ncc": 0.88, "fraction_ncc_above_0_7": 1.0,
                                                   "coherent": False, "leave_one_stack_out": {
                                                       "median_ncc": 0.13, "per_stack_median_ncc": [0.1, 0.2]}})
            if self.outcome == "one_apart":           # a coherent job with one stack the others do not predict,
                report.update(n_stacks=4, quality={"judged_slices": 60, "median_ncc": 0.97,    # and one not in it
                                                   "fraction_ncc_above_0_7": 1.0, "coherent": True, "leave_one_stack_out": {
                                                       "median_ncc": 0.79, "per_stack_median_ncc": [0.86, 0.44, 0.9, None]}})
            if self.outcome == "blended":             # extreme motion: branches unsettled, scores blind to it
                report["refined_poses"]["median_expected_error_mm"] = 23.3
                report.update(n_stacks=3, quality={"judged_slices": 90, "median_ncc": 0.96, "coherent": True,
                                                   "fraction_ncc_above_0_7": 1.0, "leave_one_stack_out": {
                                                       "median_ncc": 0.85, "per_stack_median_ncc": [0.88, 0.83, 0.85]}})
            if self.outcome == "one_left_out":        # the job made the volume again without the stack apart
                report.update(n_stacks=3, quality={"judged_slices": 50, "median_ncc": 0.97, "stacks_left_out": [1],
                                                   "fraction_ncc_above_0_7": 1.0, "coherent": True, "leave_one_stack_out": {
                                                       "median_ncc": 0.88, "per_stack_median_ncc": [0.86, None, 0.9]}})
            if self.outcome == "lone_scrambled":      # one stack whose alternate slices do not predict each other
                report.update(n_stacks=1, quality={"judged_slices": 22, "median_ncc": 0.95, "fraction_ncc_above_0_7": 1.0,
                                                   "coherent": False, "leave_one_stack_out": {
                                                       "median_ncc": None, "slices": 0, "per_stack_median_ncc": [None]},
                                                   "leave_alternate_slices_out": {
                                                       "median_ncc": -0.02, "even_odd_median_ncc": [-0.04, 0.05]}})
            job.update(status="succeeded", stage="done", progress=1.0, expires_at="2026-12-10T09:30:00.000Z",
                       result_url=f"/v1/reconstructions/{job['job_id']}/volume",
                       preview_url=f"/v1/reconstructions/{job['job_id']}/preview.png", report=report)
        elif job["polls"] >= 3 and self.outcome != "running":
            job.update(status=self.outcome, error="SVR diverged" if self.outcome == "failed" else None)
        return httpx.Response(200, json={k: v for k, v in job.items() if k != "polls"})


def send_json(handler: http.server.BaseHTTPRequestHandler, body: object, status: int = 200) -> None:
    """Answer a real HTTP request (a standard-library server of a test) with ``body`` as JSON."""
    raw = json.dumps(body).encode()
    handler.send_response(status)
    handler.send_header("Content-Type", "application/json")
    handler.send_header("Content-Length", str(len(raw)))
    handler.end_headers()
    handler.wfile.write(raw)
