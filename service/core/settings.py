"""All runtime settings, read once from ``SVRNET_*`` environment variables (pydantic-settings).

Example:
    >>> import os
    >>> os.environ["SVRNET_PORT"] = "9000"
    >>> Settings().port
    9000
    >>> del os.environ["SVRNET_PORT"]
    >>> sorted(Settings(api_keys="a, b").key_set())
    ['a', 'b']
    >>> [p[:48] for p in Settings(api_keys="a, café").problems() if p.startswith("SVRNET_API_KEYS")]
    ['SVRNET_API_KEYS: a key holds a character that is', 'SVRNET_API_KEYS: a key of 1 characters is guesse']
"""

from __future__ import annotations

import logging
import os
from collections.abc import Mapping
from pathlib import Path
from urllib.parse import urlsplit

from pydantic import Field, ValidationError, field_validator
from pydantic_settings import BaseSettings, SettingsConfigDict

DEFAULT_MODELS_DIR = Path(__file__).resolve().parents[1] / "models"
DEFAULT_LOCALISERS_DIR = Path(__file__).resolve().parents[1] / "localisers"
MIN_KEY_LENGTH = 20
"""The fewest characters an API key may have: a short key is guessed by trying (the server answers a
wrong key at once) or, from a copy of the job store, which holds each job owner's key digest."""


class Settings(BaseSettings):
    """Service settings; every field can be set as ``SVRNET_<FIELD>`` (case-insensitive)."""

    model_config = SettingsConfigDict(env_prefix="SVRNET_", extra="ignore", allow_inf_nan=False)   # inf: no limit

    host: str = Field("127.0.0.1", description="address the server listens on (0.0.0.0: every interface)")
    port: int = Field(8000, ge=1, le=65535, description="port the server listens on")
    models_dir: Path = Field(DEFAULT_MODELS_DIR, description="pose models: <name>/model.onnx with its calibration "
                             "and card (default: the shipped ones)")
    localisers_dir: Path = Field(DEFAULT_LOCALISERS_DIR, description="brain localisers of /v1/predict and /v1/masks: "
                                                         "<name>/model.onnx; reconstruction jobs run its default too")
    default_model: str = Field("default", description="the pose model of a request that names none (default or "
                               "fast)")
    log_level: str = Field("info", description="the service's log level: debug, info, warning, error or critical "
                           "(JSON lines; never file names or DICOM attributes)")
    api_keys: str = Field("", description="comma-separated keys, each of 20 characters or more (e.g. `openssl rand "
                          "-hex 16`, one per client); empty = no authentication")
    allowed_origins: str = Field("", description="without API keys: comma-separated origins "
                                 "(scheme://host[:port]) that may call the service besides its own pages at an "
                                 "address; * = any. Another page's request (it carries an Origin header; scripts "
                                 "send none) is refused, 403, a stream connection too: a web page the user visits "
                                 "must not use a service on their machine. A request to the server by name (its "
                                 "Host) is served only where that origin is listed, as a page whose DNS name was "
                                 "pointed at the server could otherwise read it: scripts that call it by name list "
                                 "it here. With keys, the key decides who is served. With or without keys, a "
                                 "listed origin's pages get the CORS headers their browser needs to read the "
                                 "answers")
    metrics_public: bool = Field(False, description="serve /metrics without an API key even when keys are "
                                 "configured (by default it needs one, like /v1/)")
    max_upload_mb: float = Field(512.0, gt=0, description="limit of one request body (413 above)")
    header_timeout_s: float = Field(60.0, gt=0, description="a connection whose next request's headers are not "
                                    "whole this long after it opened (or after the last answer) is closed")
    upload_idle_s: float = Field(60.0, gt=0, description="a request body that sends nothing for this long is "
                                 "refused (408) and its connection closed")
    upload_timeout_s: float = Field(900.0, gt=0, description="a request body must arrive whole within this (408 "
                                    "after): a client trickling bytes cannot hold a connection for ever")
    max_files: int = Field(32, ge=1, description="most stacks (and masks) per request")
    max_slices_per_stack: int = Field(128, ge=2, description="most slices in one uploaded stack (the stack stage's "
                                      "work grows with the cube of a stack's slices; fetal stacks hold 20-80)")
    max_concurrent: int = Field(2, ge=1, description="requests processed at once (predictions, masks, job "
                                "submissions); a request whose upload is in waits up to slot_wait_s for one, then 503")
    max_admitted: int = Field(0, ge=0, description="requests to those routes admitted at once: receiving their "
                              "upload, waiting for a processing slot or processing; more get 503 before their body is "
                              "read (0 = twice max_concurrent; never fewer than max_concurrent). Slow uploads hold "
                              "admissions, not processing slots")
    slot_wait_s: float = Field(30.0, ge=0, description="how long a request whose upload is in waits for a processing "
                               "slot before it is answered 503")
    preprocess_workers: int = Field(2, ge=1, description="stacks preprocessed in parallel")
    onnx_threads: int = Field(0, ge=0, description="onnxruntime intra-op threads (0 = all cores: two network calls "
                              "at a time, each on half of them)")
    blas_threads: int = Field(1, ge=0, description="numpy's and scipy's BLAS threads in the server, svrnet-mrd, the "
                              "job workers and svrnet-worker (0 = the library's default, every core): the consistency "
                              "stages multiply many small matrices, which one thread does faster, and requests and "
                              "preprocessing workers already use the cores side by side (the streams' stage process "
                              "always uses one)")
    tmp_dir: Path | None = Field(None, description="where uploads are spooled and requests' scratch lives: an "
                                 "existing folder (default: the system temp folder)")
    data_dir: Path = Field(Path.home() / ".svrnet", description="job store: SQLite database and files")
    retry_after_s: int = Field(2, ge=1, description="the Retry-After (seconds) of a 503 or 429 when saturated")
    job_workers: int = Field(1, ge=1, description="reconstruction jobs run at once (worker processes)")
    max_queued_jobs: int = Field(16, ge=1, description="reconstruction jobs waiting at most; more get 429")
    max_decoded_mb: float = Field(128.0, gt=0, description="limit of what one file decodes to: each inflated "
                                  "stream, and its voxels counted as float32 (413 above)")
    max_request_decoded_mb: float = Field(1024.0, gt=0, description="limit of what all files of one request "
                                          "decode to together (413 above)")
    retention_hours: float = Field(72.0, gt=0, description="finished jobs and their files are deleted after this "
                                   "(checked every 10 minutes, or a tenth of it where shorter)")
    job_max_attempts: int = Field(2, ge=1, description="runs of a job whose worker (or server) was lost, at most; "
                                  "then it fails with that reason")
    queue_url: str | None = Field(None, description="redis://host:port/db: the distributed back-end (job records "
                                  "in Redis, an RQ queue, `svrnet-worker` processes anywhere); unset: embedded")
    queue_name: str = Field("svrnet", pattern=r"^[A-Za-z0-9_.-]{1,64}$",
                            description="the RQ queue and the namespace of the job records in Redis")
    queue_maintenance_s: float = Field(15.0, gt=0, description="distributed: how often each API replica re-delivers "
                                       "the jobs of lost workers and fails those past the retry limit")
    job_timeout_h: float = Field(6.0, gt=0, description="a job running longer is stopped and fails")
    worker_lost_after_s: int = Field(60, ge=1, description="distributed: a worker silent this long (beyond its "
                                     "heartbeat interval) is lost and its job re-delivered")
    worker_heartbeat_s: int = Field(10, ge=1, description="distributed: a busy worker's heartbeat interval")
    stream_max_sessions: int = Field(32, ge=1, description="/v1/stream sessions at once; more are closed with "
                                     "code 1013 and a retry_after_s")
    stream_max_slices: int = Field(2000, ge=1, description="slices one stream session may send")
    stream_max_pixels: int = Field(1024 * 1024, ge=4, description="pixels of one streamed slice")
    stream_max_session_mb: float = Field(512.0, gt=0, description="what one stream session may keep in memory: its "
                                         "slices' pixels as float32, their preparations and their stacks' ends "
                                         "(reserved as each slice comes, so that ending a stack stays within the "
                                         "limit), five to six times the pixels; an MRD connection's unread answers "
                                         "as much again")
    stream_idle_s: float = Field(300.0, gt=0, description="a stream session silent this long is closed (code 1001)")
    stream_ping_interval_s: float = Field(20.0, gt=0, description="how often the server pings a WebSocket client")
    stream_ping_timeout_s: float = Field(60.0, gt=0, description="a ping unanswered this long closes the connection "
                                         "(1011): a live client on a busy 2-core host can take longer than "
                                         "uvicorn's 20 s; a client that reads none of its answers this long "
                                         "loses its session")
    stream_workers: int = Field(1, ge=1, description="slices of all stream sessions posed at once (threads; each "
                                "takes up to a core from /v1/predict)")

    @field_validator("log_level")
    @classmethod
    def _known_level(cls, value: str) -> str:
        if not isinstance(logging.getLevelName(value.upper()), int):
            raise ValueError("one of debug, info, warning, error, critical")
        return value.lower()

    @field_validator("queue_url")
    @classmethod
    def _redis_url(cls, value: str | None) -> str | None:
        """A Redis URL whose parts the client can read (a port that is a number, a database that is
        one): checked here, so that a typo stops the start with one line, not a traceback later.

        Example:
            >>> Settings(queue_url="redis://127.0.0.1:6379/0").queue_url
            'redis://127.0.0.1:6379/0'
            >>> Settings(queue_url="redis://127.0.0.1:notaport/0")
            Traceback (most recent call last):
            pydantic_core._pydantic_core.ValidationError: 1 validation error for Settings
            ...
        """
        if not value:
            return None
        if not value.startswith(("redis://", "rediss://", "unix://")):
            raise ValueError("a redis://host:port/db (or rediss://, unix://) URL")
        parts = urlsplit(value)
        try:
            parts.port                                                    # a ValueError where it is no number
        except ValueError:
            raise ValueError("its port is not a number: a redis://host:port/db URL") from None
        if parts.scheme != "unix" and not parts.hostname:
            raise ValueError("it names no host: a redis://host:port/db URL")
        if parts.scheme != "unix" and parts.path.strip("/") and not parts.path.strip("/").isdigit():
            raise ValueError("its database is not a number: a redis://host:port/db URL")
        return value

    def problems(self, needs_default_model: bool = True) -> list[str]:
        """What makes these settings unusable on this machine, each naming its variable: a models
        folder without a model, folders that cannot be written. A server started with them would pass
        its health check and fail every request (see :func:`load_settings`). A localisers folder
        without a localiser is not one: such a server serves requests that send their masks; one whose
        localisers have none named ``default`` is (every request without masks would fail).
        ``needs_default_model``: whether :attr:`default_model` must be among the models (a job
        worker runs the model each job names)."""
        from service.core.onnx import model_files

        out = []
        if self.api_keys.strip() and not self.key_set():
            out.append("SVRNET_API_KEYS: holds separators but no key (unset it to serve without keys)")
        if any(not ("!" <= c <= "~") for k in self.key_set() for c in k):
            out.append("SVRNET_API_KEYS: a key holds a character that is not printable ASCII (HTTP headers carry "
                       "no other reliably)")
        if short := sorted({len(k) for k in self.key_set() if len(k) < MIN_KEY_LENGTH}):
            out.append(f"SVRNET_API_KEYS: a key of {short[0]} characters is guessed by trying; give each client a key "
                       f"of {MIN_KEY_LENGTH} random characters or more (openssl rand -hex 16)")
        names = [p.parent.name for p in model_files(self.models_dir)]
        if not names:
            out.append(f"SVRNET_MODELS_DIR: {self.models_dir} holds no <name>/model.onnx")
        elif needs_default_model and self.default_model not in names:
            out.append(f"SVRNET_DEFAULT_MODEL: no model {self.default_model!r} in {self.models_dir}")
        localisers = [p.parent.name for p in model_files(self.localisers_dir)]
        if localisers and "default" not in localisers:
            out.append(f"SVRNET_LOCALISERS_DIR: {self.localisers_dir} holds localisers ({', '.join(localisers)}) but "
                       "none named default, the one stacks without masks go to: name one's folder default")
        for name, folder, create in (("SVRNET_DATA_DIR", self.data_dir, True), ("SVRNET_TMP_DIR", self.tmp_dir, False)):
            if folder is None:
                continue
            try:
                if create:
                    Path(folder).mkdir(parents=True, exist_ok=True, mode=0o700)   # patient data: the owner's alone
            except OSError as exc:
                out.append(f"{name}: {folder} cannot be created ({exc.strerror})")
                continue
            if not Path(folder).is_dir() or not os.access(folder, os.W_OK | os.X_OK):
                out.append(f"{name}: {folder} is not a folder this process can write")
        return out

    @property
    def max_decoded_bytes(self) -> int:
        return int(self.max_decoded_mb * 2**20)

    @property
    def max_request_decoded_bytes(self) -> int:
        return int(self.max_request_decoded_mb * 2**20)

    def admissions(self) -> int:
        """Requests to the processing routes admitted at once (:attr:`max_admitted`, 0: twice
        :attr:`max_concurrent`; never fewer than it)."""
        return max(self.max_admitted or 2 * self.max_concurrent, self.max_concurrent)

    def origin_set(self) -> set[str]:
        """The origins of :attr:`allowed_origins`, as browsers send them (:func:`plain_origin`)."""
        return {plain_origin(o) for o in self.allowed_origins.split(",") if o.strip()}

    def key_set(self) -> set[str]:
        return {k.strip() for k in self.api_keys.split(",") if k.strip()}


def plain_origin(origin: str) -> str:
    """An origin as browsers send it: lower case, no trailing slash, no default port.

    Example:
        >>> plain_origin("HTTPS://Viewer.example:443/"), plain_origin("http://127.0.0.1:8000")
        ('https://viewer.example', 'http://127.0.0.1:8000')
    """
    origin = origin.strip().rstrip("/").lower()
    for scheme, port in (("https://", ":443"), ("http://", ":80")):
        if origin.startswith(scheme) and origin.endswith(port):
            return origin[: -len(port)]
    return origin


def load_settings(prog: str, *, needs_default_model: bool = True, **given: object) -> Settings:
    """The settings of a console command (``svrnet-server``, ``svrnet-worker``, ``svrnet-mrd``):
    a value that is wrong, or unusable here (:meth:`Settings.problems`), ends the command with
    one line naming its ``SVRNET_*`` variable (exit status 1), never a traceback. The command's
    files (uploads, job folders, results: patient data) are then created readable by its own
    user only (umask 077), whatever the shell's umask. ``needs_default_model``: as
    :meth:`Settings.problems`.

    Example:
        >>> import os
        >>> os.environ["SVRNET_LOG_LEVEL"] = "verbose"
        >>> try:
        ...     load_settings("svrnet-server")
        ... except SystemExit as end:
        ...     print(end.code)
        svrnet-server: SVRNET_LOG_LEVEL: Value error, one of debug, info, warning, error, critical
        >>> del os.environ["SVRNET_LOG_LEVEL"]
    """
    try:
        settings = Settings(**given)
    except ValidationError as exc:
        raise SystemExit(f"{prog}: " + "; ".join(
            f"SVRNET_{'_'.join(str(p) for p in e['loc']).upper()}: {e['msg']}" for e in exc.errors())) from None
    if problems := settings.problems(needs_default_model):
        raise SystemExit(f"{prog}: " + "; ".join(problems))
    os.umask(0o077)
    return settings


OTHER_VARIABLES = frozenset({"SVRNET_SERVER", "SVRNET_API_KEY", "SVRNET_TIMEOUT", "SVRNET_BIND", "SVRNET_MRD_BIND"})
"""``SVRNET_`` variables that are not the service's settings and share its environment: the client's
(``svrnet``) and docker compose's."""
OTHER_PREFIXES = ("SVRNET_TEST_", "SVRNET_SCHEMATHESIS_")
"""Prefixes of the tests' ``SVRNET_`` variables."""


def unknown_variables(environ: Mapping[str, str] | None = None) -> list[str]:
    """The ``SVRNET_`` variables of ``environ`` (default the process's) that no setting reads: a
    misspelt one (``SVRNET_THREADS``) would otherwise be ignored without a word.

    Example:
        >>> unknown_variables({"SVRNET_THREADS": "1", "SVRNET_ONNX_THREADS": "1", "SVRNET_SERVER": "x",
        ...                    "SVRNET_API_KEYSS": "k", "HOME": "/"})
        ['SVRNET_API_KEYSS', 'SVRNET_THREADS']
    """
    env = os.environ if environ is None else environ
    known = {f"SVRNET_{name.upper()}" for name in Settings.model_fields} | OTHER_VARIABLES
    return sorted(k for k in env if k.upper().startswith("SVRNET_") and k.upper() not in known
                  and not k.upper().startswith(OTHER_PREFIXES))


def warn_unknown_variables(prog: str) -> None:
    """Log one warning naming the :func:`unknown_variables` (call once logging is configured)."""
    log = logging.getLogger(__name__)
    if names := unknown_variables():
        log.warning("%s: no setting reads %s; ignored (the settings: docs/configuration.md)", prog, ", ".join(names))
    upper = {k.upper() for k in os.environ}
    if "SVRNET_API_KEY" in upper and "SVRNET_API_KEYS" not in upper:
        log.warning("%s: SVRNET_API_KEY is the client's key; the server's keys are SVRNET_API_KEYS (none set: "
                    "no authentication)", prog)
