"""Every setting of the service and its workers, in one place (environment variables prefixed ``VOXNERF_``).

Embedded default (no server to run): the job store is SQLite under ``data_dir`` and the Celery broker is
kombu's filesystem transport in ``data_dir/broker``. Setting ``VOXNERF_BROKER_URL=redis://host:6379/0``
switches the broker to Redis; ``VOXNERF_DATABASE_URL`` points the job store at PostgreSQL (or another
SQLAlchemy URL). Without ``storage_url``, scene files and runs live under ``data_dir``, which every API and
worker process must then share (the same directory, or a shared filesystem when they run on several
machines). With ``storage_url`` set (an object store such as ``s3://bucket/prefix``, see
:mod:`app.core.storage`) the store holds them and each process's ``data_dir`` is only a local cache; render
results then travel through Redis, so no directory needs to be shared at all.
"""

from __future__ import annotations

import ipaddress
from functools import lru_cache
from pathlib import Path
from typing import Annotated, Any, Literal

from pydantic import Field, SecretStr, field_validator
from pydantic_settings import BaseSettings, NoDecode, SettingsConfigDict

MiB = 1024 * 1024
# A list read from one variable as comma-separated entries ("a.example, b.example"), not as JSON.
CommaList = Annotated[list[str], NoDecode]
GPU_RENDER_PIXELS = 4096 * 4096  # default pixel limit of one render on a GPU: about a second there
CPU_RENDER_PIXELS = 1920 * 1080  # and on the CPU, where one costs tens of seconds (render_pixel_limit)


class Settings(BaseSettings):
    """Service settings; each field is read from ``VOXNERF_<FIELD NAME IN CAPITALS>``."""

    # An empty variable means unset (compose files pass optional settings as ${VAR:-}).
    model_config = SettingsConfigDict(env_prefix="VOXNERF_", extra="ignore", env_ignore_empty=True)

    data_dir: Path = Field(default=Path("data"), description="scenes, runs, broker queue and SQLite database")
    database_url: str | None = Field(
        default=None,
        description="SQLAlchemy URL of the job store; default sqlite:///<data_dir>/voxnerf.sqlite",
    )
    broker_url: str | None = Field(
        default=None, description="Celery broker, e.g. redis://127.0.0.1:6379/0; default: filesystem queue"
    )
    broker_polling_interval_s: float = Field(
        default=0.05, gt=0, le=5,
        description="how often a worker running a task (any worker, without inotify) looks into the filesystem queue",
    )
    render_polling_interval_s: float = Field(
        default=0.01, gt=0, le=5,
        description="the same for a worker that consumes the render queue (a render queued behind another waits up "
        "to this long after it)",
    )
    api_token: SecretStr | None = Field(
        default=None,
        description="when set, every endpoint but /healthz needs 'Authorization: Bearer <token>': this one (the "
        "principal 'admin', scope admin) or a named token made with voxnerf tokens create",
    )
    allow_unauthenticated_remote: bool = Field(
        default=False,
        description="without api_token the service answers only loopback clients and refuses to bind another "
        "address; true lifts both (logged as a WARNING): anyone who reaches the port then controls the service",
    )
    allowed_hosts: CommaList = Field(
        default_factory=list,
        description="Host names the service answers besides localhost, 127.0.0.1 and [::1] (always answered), "
        "comma-separated: a name, *.example.org (its subdomains) or * (any). A request whose Host header names "
        "another is refused with 400: a web page re-resolving its own name to this machine (DNS rebinding)",
    )
    trusted_proxies: CommaList = Field(
        default_factory=list,
        description="addresses or networks (comma-separated) of reverse proxies whose Forwarded or "
        "X-Forwarded-For header names the client; a request carrying Forwarded, Via or X-Forwarded-* from any "
        "other address counts as remote (it needs the token)",
    )

    max_upload_bytes: int = Field(default=2048 * MiB, gt=0, description="request body of POST /scenes")
    max_request_bytes: int = Field(default=1 * MiB, gt=0, description="request body of every other endpoint")
    max_scene_bytes: int = Field(default=8192 * MiB, gt=0, description="total uncompressed size of a scene")
    max_files: int = Field(default=20_000, gt=0, description="files in one uploaded scene")
    max_compression_ratio: float = Field(
        default=200.0, gt=1, description="uncompressed/compressed size above which a zip entry is a bomb"
    )
    max_image_pixels: int = Field(
        default=64_000_000, gt=0, description="declared width x height of one image"
    )
    max_scene_pixels: int = Field(
        default=2_000_000_000,
        gt=0,
        description="declared width x height summed over every image and depth map of one uploaded scene",
    )
    max_transforms_bytes: int = Field(
        default=64 * MiB, gt=0, description="size of an uploaded transforms.json, checked before it is parsed"
    )
    max_concurrent_uploads: int = Field(
        default=2,
        ge=1,
        le=32,
        description="POST /scenes requests one API process takes at once; more are answered 429 with "
        "Retry-After (each holds a worker thread, staging disk and a validation process)",
    )
    max_upload_session_bytes: int = Field(
        default=65536 * MiB, gt=0,
        description="the whole file of one upload session (POST /uploads), sent in parts; larger than "
        "max_upload_bytes, the limit of a one-request upload",
    )
    upload_part_bytes: int = Field(
        default=64 * MiB, ge=64 * 1024, le=1024 * MiB,
        description="size of the parts of an upload session (the last one is shorter); a file of more than "
        "max_upload_parts such parts gets larger parts, so that it needs no more",
    )
    max_upload_parts: int = Field(default=10_000, ge=1, le=100_000, description="parts of one upload session")
    max_upload_sessions: int = Field(
        default=16, ge=1, le=1000,
        description="upload sessions open at once (created, not yet completed, deleted or expired); one more "
        "is answered 429",
    )
    upload_session_expiry_s: float = Field(
        default=86_400.0, gt=0,
        description="an upload session no part was sent to for this long expires: the API's sweeper removes it "
        "and its parts",
    )
    upload_validation_memory_bytes: int = Field(
        default=4096 * MiB,
        gt=0,
        description="address space an upload's validation process may add to what it starts with "
        "(RLIMIT_AS); past it the upload is refused with 413",
    )
    upload_validation_timeout_s: float = Field(
        default=900.0, gt=0, description="wall-clock seconds an upload's validation may take; then it is killed"
    )
    max_render_pixels: int | None = Field(
        default=None, gt=0,
        description="width x height of one render and of each video frame; unset: what fits the device the "
        f"workers render on, {GPU_RENDER_PIXELS} on a GPU and {CPU_RENDER_PIXELS} on the CPU "
        "(:meth:`Settings.render_pixel_limit`)",
    )
    max_video_frames: int = Field(
        default=3600, ge=1, le=10_000, description="frames of one video job (POST /jobs/{id}/videos)"
    )
    max_output_pixels: int = Field(
        default=2_000_000_000, gt=0,
        description="pixels one output job renders, frames (video) or views (export) x pixels each: its cost; "
        "a request beyond it is answered 422",
    )
    max_queued_outputs: int = Field(
        default=100, ge=1,
        description="queued output jobs (videos, meshes, point clouds) of all clients together, counted apart from "
        "training jobs; POST /jobs/{id}/videos or /exports beyond it is answered 429",
    )
    max_concurrent_scene_reads: int = Field(
        default=2, ge=1, le=32,
        description="scene reads for the viewer (GET /jobs/{id}/cameras, /prior-preview) one API process runs at "
        "once, each a child process under the upload validation's limits; more are answered 429 with Retry-After",
    )

    render_timeout_s: float = Field(
        default=120.0, gt=0, description="POST /render waits this long for a worker"
    )
    render_cache_size: int = Field(default=2, ge=1, description="loaded models each render process keeps")
    render_path: Literal["auto", "fast", "full"] = Field(
        default="auto",
        description="how render workers render: fast (rays stop when opaque, no compiling), full (every sample), "
        "or auto (fast on the CPU, full on a GPU)",
    )
    max_concurrent_renders: int = Field(
        default=8,
        ge=1,
        le=32,
        description="POST /render requests one API process serves at once; more are answered 429 with "
        "Retry-After (each one in progress holds one of the API's 40 worker threads)",
    )
    device: str = Field(default="auto", description="torch device of the workers: auto, cpu or cuda[:N]")
    worker_preload: bool = Field(
        default=True,
        description="a worker loads the engine (torch) for its queues' work when it starts, so its first task "
        "starts at once; 0: each task kind loads it when its first task runs (the worker is up in about 3 s instead "
        "of 7 and holds no engine until it works)",
    )

    progress_interval_s: float = Field(default=1.0, ge=0, description="least time between progress writes")
    heartbeat_s: float = Field(default=2.0, gt=0, description="how often a training task renews its lease")
    checkpoint_every_s: float = Field(
        default=60.0,
        gt=0,
        description="wall-clock seconds between a training job's checkpoints: about the most work a killed "
        "worker loses",
    )
    stale_after_s: float = Field(
        default=60.0, gt=0, description="a running job whose lease is this old is requeued (its worker died)"
    )
    sweep_interval_s: float = Field(default=10.0, gt=0, description="how often the API looks for stale jobs")
    leftover_age_s: float = Field(
        default=3600.0, ge=0,
        description="at start-up the API removes what a crash left: staging directories and scene directories "
        "without a database row, once nothing in them changed for this long (younger ones may belong to "
        "another process sharing data_dir)",
    )
    max_worker_deaths: int = Field(
        default=3, ge=1, le=100,
        description="a training or output job whose worker died this many times while running it (killed, out of "
        "memory, crashed) is failed naming why, not requeued again",
    )
    worker_lost_wait_s: float = Field(
        default=10.0, gt=0,
        description="how long a worker waits for the result of a task whose process died before it counts the task "
        "lost (Celery's worker_lost_wait): the death is then recorded against the job",
    )
    resend_queued_after_s: float = Field(
        default=300.0, gt=0,
        description="a job or output job queued this long since its message was sent has the message sent again "
        "(it may have been lost) unless the broker still holds it (the embedded queue and Redis are read); a "
        "duplicate is refused by the claim's fence",
    )
    max_job_seconds: float = Field(
        default=86_400.0, gt=0,
        description="cap of every training job's training seconds: the worker trains for min(max_seconds, this), a "
        "max_iters-only job included (set-up, compilation and the final evaluation come on top, docs/engine.md)",
    )
    max_eval_at_seconds: float = Field(
        default=600.0, ge=0,
        description="seconds a training job may spend in its eval_at evaluations (they are not charged to "
        "max_seconds); once spent, the later eval_at times are skipped",
    )
    max_queued_jobs: int = Field(
        default=100, ge=1,
        description="queued training jobs (and, counted apart, capture imports) of all clients together; "
        "POST /scenes/{id}/jobs beyond it is answered 429",
    )
    max_queued_per_token: int | None = Field(
        default=None, ge=1,
        description="queued training jobs, imports and output jobs (each kind counted apart) one principal may "
        "have: a named token, VOXNERF_API_TOKEN's holder, or everyone on a tokenless service; a token made with "
        "--max-queued has its own. Beyond it the request is answered 429 naming whose limit it is. Unset: only "
        "max_queued_jobs and max_queued_outputs apply",
    )
    kill_worker_on_scene: str | None = Field(
        default=None,
        description="tests only: a training worker that loads this scene id kills itself with SIGKILL (a poison "
        "job); no upload can set it",
    )
    health_timeout_s: float = Field(
        default=1.0, gt=0, description="how long /healthz waits for worker replies"
    )
    log_format: Literal["text", "json"] = Field(
        default="text",
        description="how the API and the workers log: text lines, or one JSON object per line (time, level, "
        "logger, message, job_id / output_id / import_id when known, exception) for log shippers",
    )
    health_cache_s: float = Field(
        default=2.0, gt=0, le=60,
        description="an anonymous /healthz answer (status only) is reused this long before one check refreshes it",
    )

    storage_url: str | None = Field(
        default=None,
        description="object store for scenes and runs (any fsspec URL, e.g. s3://bucket/prefix); each "
        "process then keeps only a local cache under data_dir. Unset: data_dir alone holds them",
    )
    storage_endpoint_url: str | None = Field(
        default=None, description="S3-compatible endpoint of an s3:// store (MinIO, Ceph...); default AWS"
    )
    storage_key: SecretStr | None = Field(default=None, description="access key id of an s3:// store")
    storage_secret: SecretStr | None = Field(default=None, description="secret access key of an s3:// store")
    storage_options: dict[str, Any] = Field(
        default_factory=dict, description="further fsspec options of the store, as a JSON object"
    )
    storage_sync_interval_s: float = Field(
        default=10.0, gt=0, description="how often a training worker uploads a newly saved checkpoint"
    )

    data_dir_quota_bytes: int | None = Field(
        default=None, gt=0,
        description="most bytes data_dir may hold (scenes, runs and their outputs, staging, broker queue, SQLite "
        "database); an upload or an output that would pass it is refused with 507. Unset: no quota",
    )
    min_free_bytes: int = Field(
        default=1024 * MiB, ge=0,
        description="free space the data_dir's filesystem keeps: an upload (with its declared size) or an output "
        "that would leave less is refused with 507, so a running job's checkpoints still fit. 0: no floor",
    )
    worker_cache_bytes: int = Field(
        default=20 * 1024 * MiB, gt=0,
        description="with storage_url: the most bytes of scenes and runs a worker machine keeps in its local "
        "cache; the least recently used ones no task is using are removed past it (the store keeps them)",
    )

    # Live events and webhooks (GET /jobs/{id}/events, a job's callback_url: app/routes/events.py, app/webhooks.py)
    max_event_streams: int = Field(
        default=64, ge=1, le=10_000,
        description="GET /jobs/{id}/events streams one API process keeps open at once; more are answered 429 "
        "with Retry-After",
    )
    event_poll_s: float = Field(
        default=0.5, gt=0, le=10, description="how often an open event stream reads its job's new events"
    )
    event_keepalive_s: float = Field(
        default=15.0, gt=0, le=300, description="an event stream with nothing to say sends a comment this often"
    )
    webhook_allow_private: bool = Field(
        default=False,
        description="callback_url may name a host whose addresses are private, loopback, link-local or reserved "
        "(a receiver on this machine or network); off, such a URL is refused at job creation (422) and at "
        "delivery",
    )
    webhook_timeout_s: float = Field(
        default=5.0, gt=0, le=60, description="how long one webhook delivery attempt waits for its receiver"
    )
    webhook_max_attempts: int = Field(
        default=8, ge=1, le=100, description="attempts of one webhook delivery before it is abandoned"
    )
    webhook_retry_s: float = Field(
        default=5.0, gt=0, le=3600,
        description="wait before a failed webhook delivery's second attempt; it doubles after each further one",
    )
    webhook_poll_s: float = Field(
        default=1.0, gt=0, le=60, description="how often the API looks for webhook deliveries that are due"
    )

    @field_validator("allowed_hosts", "trusted_proxies", mode="before")
    @classmethod
    def _comma_separated(cls, value: Any) -> Any:
        if isinstance(value, str):
            return [entry.strip() for entry in value.split(",") if entry.strip()]
        return value

    @field_validator("trusted_proxies")
    @classmethod
    def _networks(cls, value: list[str]) -> list[str]:
        for entry in value:
            try:
                ipaddress.ip_network(entry, strict=False)
            except ValueError:
                raise ValueError(f"{entry!r} is not an IP address or network (e.g. 10.0.0.5, 10.0.0.0/24)") from None
        return value

    @field_validator("data_dir")
    @classmethod
    def _absolute(cls, value: Path) -> Path:
        return value.expanduser().resolve()

    def render_pixel_limit(self, device_type: str | None = None) -> int:
        """The most pixels of one render (and of each video frame): ``max_render_pixels`` when it is set, else
        what fits the device: :data:`GPU_RENDER_PIXELS` on a GPU, :data:`CPU_RENDER_PIXELS` on the CPU.
        ``device_type`` is the torch device type a worker renders on (``cpu``, ``cuda``...); None is the API's
        view, which knows only the ``device`` setting: ``cpu`` there means the CPU's limit, anything else the
        GPU's, and each worker refuses what is beyond its own."""
        if self.max_render_pixels is not None:
            return self.max_render_pixels
        device = device_type or self.device.split(":")[0]
        return CPU_RENDER_PIXELS if device == "cpu" else GPU_RENDER_PIXELS

    @property
    def embedded_broker(self) -> bool:
        """True when no broker URL is set: the filesystem queue under ``data_dir`` carries the messages."""
        return not self.broker_url

    @property
    def sqlalchemy_url(self) -> str:
        return self.database_url or f"sqlite:///{self.data_dir / 'voxnerf.sqlite'}"

    @property
    def scenes_dir(self) -> Path:
        return self.data_dir / "scenes"

    @property
    def runs_dir(self) -> Path:
        return self.data_dir / "runs"

    @property
    def imports_dir(self) -> Path:
        """Raw captures waiting for their import (a worker turns each into a scene, then removes it)."""
        return self.data_dir / "imports"

    @property
    def upload_sessions_dir(self) -> Path:
        """Upload sessions: each one's description and the parts received so far (:mod:`app.uploads.sessions`)."""
        return self.data_dir / "upload-sessions"

    @property
    def max_upload_part_bytes(self) -> int:
        """The largest part any upload session can have: ``upload_part_bytes``, or the part of a session of
        ``max_upload_session_bytes`` split into ``max_upload_parts`` parts when that is larger."""
        return max(self.upload_part_bytes, -(-self.max_upload_session_bytes // self.max_upload_parts))

    @property
    def staging_dir(self) -> Path:
        """Uploads are unpacked and validated here, then renamed into ``scenes_dir`` (same filesystem)."""
        return self.data_dir / "staging"

    @property
    def render_results_dir(self) -> Path:
        """Render workers write finished images here; the API picks them up and deletes them."""
        return self.data_dir / "render-results"

    @property
    def broker_dir(self) -> Path:
        return self.data_dir / "broker"

    def make_dirs(self) -> None:
        """Create every directory the service writes to (idempotent)."""
        for path in (self.scenes_dir, self.runs_dir, self.staging_dir, self.imports_dir, self.render_results_dir,
                     self.upload_sessions_dir):
            path.mkdir(parents=True, exist_ok=True)
        if self.embedded_broker:
            (self.broker_dir / "queue").mkdir(parents=True, exist_ok=True)
            (self.broker_dir / "control").mkdir(parents=True, exist_ok=True)
            (self.broker_dir / "claimed").mkdir(parents=True, exist_ok=True)


@lru_cache(maxsize=1)
def get_settings() -> Settings:
    """The process-wide settings, read from the environment once."""
    return Settings()
