"""Request and response bodies of the REST API (pydantic). Field names are the public contract.

Built from the engine's models rather than repeating them: :data:`JobOptions` takes its fields' defaults,
limits and descriptions from :class:`voxnerf.config.TrainConfig` (adding only REST limits), and
:data:`JobOut`'s progress fields, history and stages come from :class:`voxnerf.training.records.ProgressEvent`,
:class:`EvalRecord` and :class:`StageRecord` (through :data:`app.core.progress.PROGRESS_FIELDS`). The render
request is :class:`app.core.render_request.RenderRequest`, which the render worker parses too.
"""

from __future__ import annotations

import math
from datetime import datetime, timezone
from typing import Annotated, Any, Literal

from pydantic import BaseModel, ConfigDict, Field, create_model, model_validator

from app.core import outputs, progress
from app.core.models import JOB_STATES, OUTPUT_KINDS
from voxnerf.cameras.paths import MAX_FPS
from voxnerf.config import field_info, settings_for
from voxnerf.training.records import EvalRecord, ProgressEvent, StageRecord

JobState = Literal[JOB_STATES]


def _utc(seconds: float | None) -> datetime | None:
    return None if seconds is None else datetime.fromtimestamp(seconds, tz=timezone.utc)


# ------------------------------------------------------------------------------------------------ scenes


CREATED_BY_DOC = ("who made it: a token's name, 'admin' (VOXNERF_API_TOKEN) or 'local' (a tokenless service); null "
                  "when made before tokens existed")
CANCELLED_BY_DOC = "who asked to cancel it (as created_by); null when no one did"


class PriorSummary(BaseModel):
    model_config = ConfigDict(extra="allow")

    file: str
    kind: str | None = None
    sigma: float | None = Field(None, description="standard deviation of the prior's noise, scene units")
    source: str | None = Field(None, description="where the prior came from: prior_file_path, nerfstudio's "
                               "ply_file_path, or a prior.ply found in the scene")
    sigma_estimated: bool | None = None


class SceneSummary(BaseModel):
    """What :func:`voxnerf.data.scene.inspect_scene` found in the upload."""

    model_config = ConfigDict(extra="allow")

    frames: int
    splits: dict[str, int] = Field(description="frames per split (train, test, named evaluation splits)")
    image_size: list[int] = Field(description="[width, height] of the first training image, pixels")
    image_sizes: dict[str, int] | None = Field(
        None, description="frames per image size, e.g. {\"1000x657\": 12, \"1000x659\": 11} (a scene may mix sizes)")
    prior: PriorSummary | None
    depth: bool = Field(description="whether frames carry sensor depth maps")
    depth_frames: dict[str, int] | None = Field(
        None, description="frames with a depth map: all, and training frames (whose depth makes the prior when "
        "there is no prior file, and supervises training)")
    camera_models: dict[str, int] | None = Field(
        None, description="frames per camera model and how it was decided, e.g. {\"OPENCV (camera_model)\": 40}")
    warnings: list[str] = []


class ImportSummary(BaseModel):
    """What an importer (:mod:`voxnerf.data.importers`) made of an upload to import (a COLMAP model, a ScanNet
    export, a phone app's export, a ROS bag)."""

    model_config = ConfigDict(extra="allow")

    format: str = Field(description="the importer: colmap, scannet, record3d, polycam, stray or rosbag")
    frames: int = Field(description="frames written")
    skipped: dict[str, int] = Field(description="frames left out, counted by reason (missing image, invalid pose)")
    camera_models: list[str] = Field(description="camera models, e.g. 'SIMPLE_RADIAL -> OPENCV' (COLMAP -> ours)")
    depth_frames: int = Field(description="frames with a sensor depth map")
    prior: dict[str, Any] | None = Field(
        description="the point cloud made from COLMAP's points3D: file, points, sigma (scene units) and the rule "
        "that estimated it; null without one"
    )
    splits: dict[str, Any] | None = Field(
        description="the split rule's parameters and frames per split when splits=paper; null without"
    )
    notes: list[str] = []


class SceneOut(BaseModel):
    id: str
    name: str
    created_at: datetime
    size_bytes: int
    summary: SceneSummary
    imported: ImportSummary | None = Field(
        None, description="for an imported upload (COLMAP, ScanNet, Record3D, Polycam), what its importer wrote; "
        "null for a scene directory"
    )
    created_by: str | None = Field(None, description=CREATED_BY_DOC)

    @classmethod
    def from_row(cls, row) -> SceneOut:
        summary = dict(row.summary)
        imported = summary.pop("imported", None)
        return cls(
            id=row.id,
            name=row.name,
            created_at=_utc(row.created_at),
            size_bytes=row.size_bytes,
            summary=SceneSummary.model_validate(summary),
            imported=ImportSummary.model_validate(imported) if imported is not None else None,
            created_by=row.created_by,
        )


# ------------------------------------------------------------------------------------------------ jobs

# Who may set each TrainConfig setting is said where the setting is defined (voxnerf/config.py, JOB and WORKER):
# a job's options, named as the flat settings (and the CLI's `voxnerf train` flags) name them; the settings the
# worker's deployment sets (VOXNERF_DEVICE, VOXNERF_CHECKPOINT_EVERY_S, VOXNERF_MAX_EVAL_AT_SECONDS); the rest are
# internal, reachable from the Python API and `voxnerf train --set` only.
JOB_OPTION_FIELDS = settings_for("job")
WORKER_SET_FIELDS = frozenset(settings_for("worker"))
INTERNAL_TRAIN_FIELDS = frozenset(settings_for("internal"))
MAX_JOB_SECONDS = 7 * 24 * 3600
# Limits the REST API adds to TrainConfig's own: a public endpoint bounds what one request can ask for.
REST_LIMITS: dict[str, Any] = {
    "max_seconds": Field(le=MAX_JOB_SECONDS),
    "max_iters": Field(le=10_000_000),
    "seed": Field(ge=0, le=2**31 - 1),
    "eval_at": Field(max_length=64),
    "smooth_patches": Field(le=64),
    "n_importance": Field(le=1024),
    "n_rest": Field(le=1024),
}


CALLBACK_URL_MAX_CHARS = 2048


class _JobOptionsRules(BaseModel):
    """Training options, named as TrainConfig's fields (the CLI's ``voxnerf train`` flags). Defaults, limits and
    descriptions are TrainConfig's, with a few tighter REST limits. At least one bound is required. Besides them,
    ``callback_url``: where the job's state changes are posted (webhooks)."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False, json_schema_extra={"examples": [
        {"max_seconds": 300, "eval_every_s": 30.0}, {"max_iters": 2000, "seed": 1}]})

    callback_url: str | None = Field(
        None,
        max_length=CALLBACK_URL_MAX_CHARS,
        description="http(s) URL the job's state changes (queued, running, succeeded, failed, cancelled) are POSTed "
        "to, signed with the creating token's webhook secret (X-VoxNeRF-Signature); its host must not resolve to a "
        "private, loopback, link-local or reserved address unless VOXNERF_WEBHOOK_ALLOW_PRIVATE is set",
        examples=["https://ci.example.org/hooks/voxnerf"],
    )

    @model_validator(mode="after")
    def _bounded(self) -> _JobOptionsRules:
        if self.max_seconds is None and self.max_iters is None:
            raise ValueError("give max_seconds or max_iters (or both)")
        if any(not (math.isfinite(t) and t > 0) for t in self.eval_at):
            raise ValueError("eval_at: seconds must be positive finite numbers")
        return self


def _engine_field(name: str) -> Any:
    """TrainConfig's field ``name`` (type, default, limits, description) plus its REST limits, if any."""
    info = field_info(name)
    extra = [REST_LIMITS[name]] if name in REST_LIMITS else []
    return Annotated[(info.annotation, info, *extra)]


JobOptions = create_model(
    "JobOptions",
    __base__=_JobOptionsRules,
    __doc__=_JobOptionsRules.__doc__,
    **{name: _engine_field(name) for name in JOB_OPTION_FIELDS},
)


class HistoryPoint(EvalRecord):
    """One evaluation during training (the engine's EvalRecord): PSNR (dB) per split against training seconds.

    Extra keys are kept, so history written by older versions of the engine still reads."""

    model_config = ConfigDict(extra="allow")


class StageInfo(StageRecord):
    """One pipeline stage (the engine's StageRecord): whether it ran, why, and its seconds. Extra keys are kept
    and ``seconds`` may be null, so stages written by older versions (or a non-finite time) still read."""

    model_config = ConfigDict(extra="allow")

    seconds: float | None = 0.0


# How the API shows the progress columns whose stored form is a list of engine records.
_PROGRESS_ITEM_TYPES = {"history": list[HistoryPoint], "stages": list[StageInfo]}


def _progress_field(name: str) -> Any:
    """The API field of progress column ``name``: the event field's type (null while the job has none)."""
    info = ProgressEvent.model_fields[name]
    annotation = _PROGRESS_ITEM_TYPES.get(name, info.annotation)
    if progress.nullable(name):
        annotation = annotation | None
    return (annotation, Field(description=info.description))


class _JobOutBase(BaseModel):
    id: str
    scene_id: str
    state: JobState
    metrics: dict | None = Field(description="report metrics per evaluation split, when succeeded")
    error: str | None
    cancel_requested: bool
    options: dict
    callback_url: str | None = Field(None, description="where the job's state changes are posted, when set")
    attempt: int = Field(description="how many times a worker has claimed the job")
    requeues: int = Field(description="how many times the job was requeued after its worker died")
    created_at: datetime
    started_at: datetime | None
    finished_at: datetime | None
    created_by: str | None = Field(None, description=CREATED_BY_DOC)
    cancelled_by: str | None = Field(None, description=CANCELLED_BY_DOC)

    @classmethod
    def from_row(cls, row) -> _JobOutBase:
        return cls(
            id=row.id,
            scene_id=row.scene_id,
            state=row.state,
            metrics=row.metrics,
            error=row.error,
            cancel_requested=row.cancel_requested,
            options=row.options,
            callback_url=row.callback_url,
            attempt=row.attempt,
            requeues=row.requeues,
            created_at=_utc(row.created_at),
            started_at=_utc(row.started_at),
            finished_at=_utc(row.finished_at),
            created_by=row.created_by,
            cancelled_by=row.cancelled_by,
            **{name: _column(row, name) for name in progress.PROGRESS_FIELDS},
        )


def _column(row, name: str) -> Any:
    value = getattr(row, name)
    return progress.default(name) if value is None and not progress.nullable(name) else value


JobOut = create_model(
    "JobOut",
    __base__=_JobOutBase,
    __doc__="A training job: its state, options, progress (the engine's progress event fields) and results.",
    **{name: _progress_field(name) for name in progress.PROGRESS_FIELDS},
)


class DeliveryAttempt(BaseModel):
    attempt: int = Field(description="1 for the first attempt")
    at: datetime
    status: int | None = Field(description="the receiver's HTTP status; null when no answer came")
    error: str | None = Field(description="why the attempt failed; null when the receiver answered 2xx")


class WebhookDeliveryOut(BaseModel):
    """The delivery of one state change of a job to its ``callback_url``, with every attempt so far."""

    event_id: int = Field(description="the id of the job's state event (as in GET /jobs/{id}/events)")
    state: JobState
    outcome: Literal["pending", "delivered", "abandoned"]
    attempts: list[DeliveryAttempt]
    next_attempt_at: datetime | None = Field(description="when a pending delivery is tried next")

    @classmethod
    def from_row(cls, row) -> WebhookDeliveryOut:
        return cls(
            event_id=row.event_seq,
            state=row.state,
            outcome=row.outcome,
            attempts=[DeliveryAttempt(**{**entry, "at": _utc(entry["at"])}) for entry in row.log or []],
            next_attempt_at=_utc(row.next_at) if row.outcome == "pending" else None,
        )


class EvalRender(BaseModel):
    split: str
    name: str
    url: str


# ------------------------------------------------------------------------------------------------ outputs

OutputKind = Literal[OUTPUT_KINDS]
VideoGenerator = Literal[outputs.GENERATORS]
MAX_OUTPUT_SIDE = 16384


class VideoRequest(BaseModel):
    """A fly-through video (H.264 MP4) of a trained job: either ``camera_path`` (nerfstudio's camera-path JSON,
    as its viewer's Render panel writes it, checked by :func:`voxnerf.cameras.paths.parse_nerfstudio`), or a
    generated ``path``: ``interpolate`` (a smooth path through the scene's training cameras) or ``orbit``
    (one turn around their centre), with ``frames``, ``fps`` and optionally ``width``/``height`` (default:
    the scene's size), ``radius`` and ``height_above`` (scene units; orbit only). Sizes must be even."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False, json_schema_extra={"examples": [
        {"path": "orbit", "frames": 120, "fps": 30, "width": 640, "height": 480},
        {"path": "interpolate", "frames": 90}]})

    camera_path: dict | None = Field(None, description="nerfstudio camera-path JSON object")
    dataparser_transforms: dict | None = Field(
        None, description="the nerfstudio run's dataparser_transforms.json, when camera_path's poses are in its frame"
    )
    path: VideoGenerator | None = Field(None, description="a generated path instead of camera_path")
    frames: int | None = Field(None, description="frames of a generated path (1 to VOXNERF_MAX_VIDEO_FRAMES)")
    fps: float = Field(30.0, gt=0, le=MAX_FPS, description="frame rate of a generated path")
    width: int | None = Field(None, ge=1, le=MAX_OUTPUT_SIDE)
    height: int | None = Field(None, ge=1, le=MAX_OUTPUT_SIDE)
    radius: float | None = Field(None, gt=0, description="orbit radius, scene units; default the cameras' own")
    height_above: float | None = Field(
        None, description="orbit height above the cameras' centre along the scene's up, scene units; default 0"
    )
    format: Literal["mp4"] = "mp4"

    @model_validator(mode="after")
    def _one_path(self) -> VideoRequest:
        if (self.camera_path is None) == (self.path is None):
            raise ValueError("give camera_path (nerfstudio JSON) or path (interpolate or orbit), not both")
        generator_only = ("frames", "width", "height", "radius", "height_above")
        if self.camera_path is not None and any(getattr(self, key) is not None for key in generator_only):
            raise ValueError(f"{', '.join(generator_only)} belong to a generated path; camera_path sets its own")
        if self.path is not None and self.frames is None:
            raise ValueError("frames: required with path")
        if (self.width is None) != (self.height is None):
            raise ValueError("give width and height together (or neither, for the scene's size)")
        if self.path != "orbit" and (self.radius is not None or self.height_above is not None):
            raise ValueError("radius and height_above belong to path orbit")
        return self


class ExportRequest(BaseModel):
    """Geometry of a trained job: a triangle ``mesh`` or a coloured ``pointcloud``, as binary PLY in scene
    units (:func:`voxnerf.inference.export.export_geometry`)."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False, json_schema_extra={"examples": [
        {"kind": "mesh", "min_opacity": 0.5}, {"kind": "pointcloud", "max_views": 50}]})

    kind: Literal["mesh", "pointcloud"]
    voxel_size: float | None = Field(None, gt=0, description="scene units; default the engine's for the scene")
    min_opacity: float = Field(0.5, gt=0, le=1, description="opacity a surface point must reach")
    max_views: int | None = Field(
        None, ge=1, le=100_000, description="render at most this many of the engine's views; default all"
    )


class OutputOut(BaseModel):
    """An output job: its state, progress (``done`` of ``total`` frames or views), and when it succeeded, what
    it made (``summary``) and where to download it (``file_url``)."""

    id: str
    job_id: str
    kind: OutputKind
    state: JobState
    partial: bool = Field(description="made from a cancelled job's checkpoint: an unfinished model")
    progress: float
    done: int
    total: int | None
    unit: Literal["frames", "views"]
    eta_s: float | None
    params: dict = Field(description="the request (a camera path is summarised by its frame count)")
    summary: dict | None
    file_name: str | None
    file_url: str | None
    error: str | None
    cancel_requested: bool
    attempt: int
    requeues: int
    created_at: datetime
    started_at: datetime | None
    finished_at: datetime | None
    created_by: str | None = Field(None, description=CREATED_BY_DOC)
    cancelled_by: str | None = Field(None, description=CANCELLED_BY_DOC)

    @classmethod
    def from_row(cls, row) -> OutputOut:
        params = dict(row.params)
        if isinstance(params.get("camera_path"), dict):
            params["camera_path"] = {"frames": len(params["camera_path"].get("camera_path", []))}
        succeeded = row.state == "succeeded"
        return cls(
            id=row.id, job_id=row.job_id, kind=row.kind, state=row.state, partial=row.partial,
            progress=row.progress, done=row.done, total=row.total, unit=outputs.UNITS[row.kind], eta_s=row.eta_s,
            params=params, summary=row.summary, file_name=row.file_name if succeeded else None,
            file_url=f"/outputs/{row.id}/file" if succeeded else None, error=row.error,
            cancel_requested=row.cancel_requested, attempt=row.attempt, requeues=row.requeues,
            created_at=_utc(row.created_at), started_at=_utc(row.started_at), finished_at=_utc(row.finished_at),
            created_by=row.created_by, cancelled_by=row.cancelled_by,
        )


# ------------------------------------------------------------------------------------------------ imports


class ImportOut(BaseModel):
    """A capture import: a raw capture (a ROS bag) a worker turns into a scene. ``scene_id`` names the scene once
    the import has succeeded; ``summary`` is then what the importer wrote."""

    id: str
    name: str
    layout: str = Field(description="the importer that runs: images, video, stray or rosbag")
    state: JobState
    stage: str | None = Field(description="queued, starting, importing, checking, storing, then done, failed or "
                              "cancelled")
    step: str | None = Field(description="what the importer is doing within its stage, for photos and video "
                             "(structure from motion): decoding, extracting features, matching, registering images")
    progress: float
    eta_s: float | None
    size_bytes: int = Field(description="of the raw capture as uploaded")
    params: dict = Field(description="the upload's choices: splits")
    scene_id: str | None
    scene_url: str | None
    summary: ImportSummary | None
    error: str | None
    cancel_requested: bool
    attempt: int
    requeues: int
    created_at: datetime
    started_at: datetime | None
    finished_at: datetime | None
    created_by: str | None = Field(None, description=CREATED_BY_DOC)
    cancelled_by: str | None = Field(None, description=CANCELLED_BY_DOC)

    @classmethod
    def from_row(cls, row) -> ImportOut:
        return cls(
            id=row.id, name=row.name, layout=row.layout, state=row.state, stage=row.stage, step=row.step,
            progress=row.progress,
            eta_s=row.eta_s, size_bytes=row.size_bytes, params=row.params, scene_id=row.scene_id,
            scene_url=f"/scenes/{row.scene_id}" if row.scene_id else None, summary=row.summary, error=row.error,
            cancel_requested=row.cancel_requested, attempt=row.attempt, requeues=row.requeues,
            created_at=_utc(row.created_at), started_at=_utc(row.started_at), finished_at=_utc(row.finished_at),
            created_by=row.created_by, cancelled_by=row.cancelled_by,
        )


# ------------------------------------------------------------------------------------------------ health


class Check(BaseModel):
    ok: bool
    detail: str


class HealthOut(BaseModel):
    """The service's health. Callers without the API token get ``status`` alone (the other fields are left
    out of the JSON); token holders, and everyone when no token is set, get every field."""

    status: Literal["ok", "unavailable"]
    database: Check | None = None
    broker: Check | None = None
    workers: dict[str, list[str]] | None = Field(
        default=None, description="queue name -> names of live workers consuming it"
    )


# ------------------------------------------------------------------------------------------------ viewer

Matrix4 = Annotated[list[Annotated[list[float], Field(min_length=4, max_length=4)]], Field(min_length=4, max_length=4)]


class ViewerCamera(BaseModel):
    """One of the scene's cameras as the viewer draws and snaps to it (the undistorted view of its lens)."""

    index: int = Field(description="the frame's position in transforms.json's frames")
    name: str = Field(description="the frame's file_path in transforms.json")
    splits: list[str] = Field(description="the splits holding the frame: train, test, named evaluation splits")
    transform_matrix: list[list[float]] = Field(description="4x4 camera-to-world, OpenGL axes, scene units")
    fl_x: float
    fl_y: float
    cx: float
    cy: float
    width: int
    height: int
    image_url: str = Field(description="GET it (with the token) for the frame's ground-truth image")


class CamerasOut(BaseModel):
    """A job's scene cameras, and what the viewer needs to show depth and the scene's scale."""

    job_id: str
    scene_id: str
    units: Literal["metres", "scene units"] = Field(
        description="metres when the scene carries sensor depth maps (metres by the scene format), else the "
        "poses' own units")
    depth_unit_scale: float = Field(description="scene units per stored unit of a 16-bit depth PNG render")
    frames: list[ViewerCamera]


class PriorPreviewOut(BaseModel):
    """A sparse random sample of the prior (the scene's prior file, or the run's fused one), for drawing."""

    points: list[float] = Field(description="x y z of each point, flat [N*3], scene units")
    colors: list[float] | None = Field(description="r g b in [0, 1] of each point, flat [N*3]; null without")
    total: int = Field(description="points (vertices) in the prior file")


class CameraPathRequest(BaseModel):
    """A video path for the viewer: either ``keyframes`` (camera-to-world poses, scene units, in order) with
    ``frames`` and the camera (``width height fl_x fl_y cx cy``) to interpolate through them
    (:func:`voxnerf.cameras.paths.interpolate_path`, as videos through training cameras do), or a nerfstudio
    ``camera_path`` (with its ``dataparser_transforms`` when needed) to read back in scene units."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False, json_schema_extra={"examples": [
        {"keyframes": [[[1, 0, 0, 0.5], [0, 1, 0, 0.2], [0, 0, 1, 2.0], [0, 0, 0, 1]],
                       [[0, 0, 1, 2.0], [0, 1, 0, 0.2], [-1, 0, 0, 0.5], [0, 0, 0, 1]]],
         "frames": 60, "fps": 30, "width": 640, "height": 480, "fl_x": 525, "fl_y": 525, "cx": 320, "cy": 240}]})

    keyframes: list[Matrix4] | None = Field(None, min_length=2, max_length=1000)
    frames: int | None = Field(None, ge=2)
    fps: float = Field(30.0, gt=0, le=MAX_FPS)
    width: int | None = Field(None, ge=1, le=MAX_OUTPUT_SIDE)
    height: int | None = Field(None, ge=1, le=MAX_OUTPUT_SIDE)
    fl_x: float | None = Field(None, gt=0)
    fl_y: float | None = Field(None, gt=0)
    cx: float | None = None
    cy: float | None = None
    camera_path: dict | None = Field(None, description="nerfstudio camera-path JSON object")
    dataparser_transforms: dict | None = None

    @model_validator(mode="after")
    def _one_source(self) -> CameraPathRequest:
        if (self.keyframes is None) == (self.camera_path is None):
            raise ValueError("give keyframes (to interpolate) or camera_path (nerfstudio JSON), not both")
        camera = ("frames", "width", "height", "fl_x", "fl_y", "cx", "cy")
        if self.keyframes is not None and any(getattr(self, key) is None for key in camera):
            raise ValueError(f"keyframes need {', '.join(camera)}")
        return self


class PathFrame(BaseModel):
    transform_matrix: list[list[float]] = Field(description="4x4 camera-to-world, OpenGL axes, scene units")
    fl_x: float
    fl_y: float
    cx: float
    cy: float


class CameraPathOut(BaseModel):
    """The path's frames (to preview) and its nerfstudio camera-path JSON (to export, or to send as
    ``camera_path`` to ``POST /jobs/{id}/videos``)."""

    width: int
    height: int
    fps: float
    frames: list[PathFrame]
    camera_path: dict


# ------------------------------------------------------------------------------------------------ tokens


class TokenCreate(BaseModel):
    """A named token to make (``POST /tokens``, scope admin)."""

    model_config = ConfigDict(extra="forbid", json_schema_extra={"examples": [
        {"name": "ci", "scope": "write", "max_queued": 10}, {"name": "dashboards", "scope": "read"}]})

    name: str = Field(min_length=1, max_length=64, description="a slug: lowercase letters, digits, '-' and '_'; "
                      "never reused, since work is recorded under it; not 'admin' or 'local'")
    scope: Literal["read", "write", "admin"] = Field(
        description="read: GET only; write: also upload, train, render, outputs, imports, and cancel or delete its "
        "own work; admin: everything, tokens included")
    max_queued: int | None = Field(
        None, ge=1, description="queued rows of each kind it may have; default VOXNERF_MAX_QUEUED_PER_TOKEN")


class TokenOut(BaseModel):
    """A named token as listed: never the token itself (only its hash is kept)."""

    name: str
    scope: Literal["read", "write", "admin"]
    max_queued: int | None
    created_at: datetime
    last_used_at: datetime | None = Field(description="to the minute: written at most once a minute")
    revoked_at: datetime | None

    @classmethod
    def from_row(cls, row) -> TokenOut:
        return cls(name=row.name, scope=row.scope, max_queued=row.max_queued, created_at=_utc(row.created_at),
                   last_used_at=_utc(row.last_used_at), revoked_at=_utc(row.revoked_at))


class TokenCreated(TokenOut):
    """A token just made: ``token`` and ``webhook_secret`` are shown here once and never again."""

    token: str = Field(description="send as 'Authorization: Bearer <token>'; shown only now")
    webhook_secret: str = Field(description="hex key of the HMAC-SHA256 signatures of its work's webhooks")

    @classmethod
    def from_new(cls, made) -> TokenCreated:
        """From :class:`app.core.tokens.NewToken`."""
        return cls(name=made.name, scope=made.scope, max_queued=made.max_queued, created_at=_utc(made.created_at),
                   last_used_at=None, revoked_at=None, token=made.token, webhook_secret=made.webhook_secret)
