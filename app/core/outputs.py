"""Output jobs: videos, meshes and point clouds made from a trained job's model (API and ``outputs`` workers).

An output job has the lease lifecycle every kind of queued work shares (:mod:`app.core.lease`: claim with a
fence, lease renewal, progress, cancel, finish, stale sweep, re-send of a lost message, worker deaths);
:data:`OUTPUTS` is its kind: a claim starts the output again from its first frame, and progress counts ``done``
of ``total`` frames (video) or views (exports).

What an output is made from: a ``succeeded`` training job, or a ``cancelled`` one that kept a checkpoint (the
output is then marked ``partial``: an unfinished model); :func:`trained_source` is that rule, which
``POST /render`` follows too.

Files: ``<runs_dir>/<job id>/outputs/<output id>/<file>`` (``video.mp4`` with ``video.mp4.camera_path.json``
beside it, ``mesh.ply``, ``pointcloud.ply``), written by the engine under a temporary name and renamed when
complete. With an object store (:mod:`app.core.storage`) the finished directory is uploaded as
``outputs/<output id>`` and fetched into a process's cache when it is downloaded there.

Video requests are checked here with the engine's torch-free camera-path rules (:mod:`voxnerf.cameras.paths`),
so the API refuses a malformed path (422 naming the key) before anything is queued.
"""

from __future__ import annotations

import shutil
from pathlib import Path

from app.core import storage, tokens
from app.core.celery_app import OUTPUT_TASK
from app.core.db import session_scope
from app.core.jobstore import get_scene, new_id
from app.core.lease import WorkKind
from app.core.models import JobRow, OutputRow
from app.core.progress import json_safe
from app.core.settings import Settings
from app.core.tokens import Principal
from voxnerf.cameras.paths import CameraPathError, check_frame_count, parse_nerfstudio
from voxnerf.config import TrainConfig
from voxnerf.files import CHECKPOINT
from voxnerf.inference.export_plan import view_count, view_size

OUTPUTS_DIR = "outputs"  # under a run directory, and the object store's prefix
FILE_NAMES = {"video": "video.mp4", "mesh": "mesh.ply", "pointcloud": "pointcloud.ply"}
MEDIA_TYPES = {"video": "video/mp4", "mesh": "application/octet-stream", "pointcloud": "application/octet-stream"}
UNITS = {"video": "frames", "mesh": "views", "pointcloud": "views"}
GENERATORS = ("interpolate", "orbit")  # through the training cameras, around their centre


class NotRenderable(Exception):
    """The trained job cannot be rendered from (the API answers 409 with this message)."""


# ------------------------------------------------------------------------------------------------ the source


def has_checkpoint(settings: Settings, job_id: str) -> bool:
    """Whether job ``job_id``'s run holds a checkpoint: in this process's cache, or in the object store."""
    if (settings.runs_dir / job_id / CHECKPOINT).is_file():
        return True
    store = storage.open_store(settings)
    if store is None:
        return False
    marker = storage.read_marker(store, f"{storage.RUNS}/{job_id}")
    return marker is not None and CHECKPOINT in marker["files"]


def trained_source(settings: Settings, job: JobRow) -> bool:
    """Whether renders of ``job`` are *partial*: False for a succeeded job, True for a cancelled one that kept
    a checkpoint. Raises NotRenderable for any other job."""
    if job.state == "succeeded":
        return False
    if job.state == "cancelled" and has_checkpoint(settings, job.id):
        return True
    why = "without a checkpoint" if job.state == "cancelled" else ""
    raise NotRenderable(
        f"job {job.id} is {job.state}{' ' + why if why else ''}; only a succeeded job, or a cancelled one that "
        "kept a checkpoint, can be rendered"
    )


# ------------------------------------------------------------------------------------------------ requests


def _even_size(width: int, height: int, key: str) -> None:
    """The engine's video rule (:mod:`voxnerf.inference.video`: H.264 yuv420p needs even sizes), checked before
    queueing."""
    if width % 2 or height % 2:
        raise CameraPathError(f"a video needs even sizes (H.264 yuv420p), got {width}x{height}", key)


def video_params(settings: Settings, request: dict) -> tuple[dict, int]:
    """The stored parameters and frame count of a video request (``VideoRequest``'s fields, None when left out).

    A ``camera_path`` (nerfstudio's camera-path JSON, with ``dataparser_transforms`` when its poses are in a
    nerfstudio run's frame) is parsed here and stored in scene units; a generator (``path``: interpolate or
    orbit) keeps its fields for the worker, which knows the scene's cameras. Limits: ``max_video_frames``
    frames and :meth:`~app.core.settings.Settings.render_pixel_limit` pixels per frame. Raises CameraPathError naming
    the key at fault.
    """
    if request.get("camera_path") is not None:
        path = parse_nerfstudio(
            request["camera_path"],
            dataparser_transforms=request.get("dataparser_transforms"),
            max_frames=settings.max_video_frames,
            max_pixels=settings.render_pixel_limit(),
        )
        width, height = path.size
        _even_size(width, height, "camera_path.render_width, render_height")
        params = {"camera_path": path.to_nerfstudio(), "width": width, "height": height, "fps": path.fps}
        return {**params, "frames": len(path)}, len(path)
    check_frame_count(request.get("frames"), settings.max_video_frames, key="frames")
    width, height = request.get("width"), request.get("height")
    if width is not None and height is not None:
        if width * height > settings.render_pixel_limit():
            raise CameraPathError(
                f"{width}x{height} exceeds the limit of {settings.render_pixel_limit()} pixels", "width, height"
            )
        _even_size(width, height, "width, height")
    keys = ("path", "frames", "fps", "width", "height", "radius", "height_above")
    return {key: request.get(key) for key in keys}, request["frames"]


class OutputTooCostly(Exception):
    """An output would render more pixels than ``max_output_pixels`` (the API answers 422 with this message)."""


def trained_size(settings: Settings, job: JobRow) -> tuple[int, int] | None:
    """The size of job ``job``'s training images, a generated video's default frame size: the scene's image size
    over the job's ``downscale`` (the engine's rule, :class:`voxnerf.data.scene.Scene`); None when the scene's
    row is gone (the worker then fails the output: it needs the scene's cameras)."""
    scene = get_scene(settings, job.scene_id)
    if scene is None or not scene.summary.get("image_size"):
        return None
    downscale = int(job.options.get("downscale") or TrainConfig.model_fields["downscale"].default)
    width, height = scene.summary["image_size"]
    return width // downscale, height // downscale


def largest_trained_size(settings: Settings, job: JobRow) -> tuple[tuple[int, int], bool] | None:
    """The largest of job ``job``'s image sizes over its ``downscale`` (by pixel count, from the scene summary's
    ``image_sizes``; a scene from before that key has :func:`trained_size`) and whether the scene's images differ
    in size; None when the scene's row is gone."""
    scene = get_scene(settings, job.scene_id)
    sizes = None if scene is None else scene.summary.get("image_sizes")
    if not sizes:
        size = trained_size(settings, job)
        return None if size is None else (size, False)
    downscale = int(job.options.get("downscale") or TrainConfig.model_fields["downscale"].default)
    width, height = max((tuple(int(v) for v in size.split("x")) for size in sizes), key=lambda wh: wh[0] * wh[1])
    return (width // downscale, height // downscale), len(sizes) > 1


def _training_cameras(settings: Settings, job: JobRow) -> int | None:
    scene = get_scene(settings, job.scene_id)
    return None if scene is None else (scene.summary.get("splits") or {}).get("train")


def check_output_cost(settings: Settings, job: JobRow, kind: str, params: dict, frames: int | None) -> None:
    """Refuse an output that would render more than ``max_output_pixels`` pixels (OutputTooCostly naming the
    limit): its cost, bounded before it is queued. A video renders ``frames`` frames of the request's size, else
    of the job's training size (:func:`trained_size`); an export renders the views
    :mod:`voxnerf.inference.export_plan` makes of the scene's training cameras (at most ``max_views``), each
    counted at the size of the scene's largest images when they differ in size (a bound from above). What
    cannot be known here (the scene's row is gone) is not checked: the worker then fails the output, which
    needs the scene."""
    up_to = ""
    if kind == "video":
        count, unit, hint = frames, "frames", "fewer frames or smaller ones"
        size = (params["width"], params["height"]) if params.get("width") is not None else trained_size(settings, job)
    else:
        cameras = _training_cameras(settings, job)
        count, unit, hint = (None if cameras is None else view_count(cameras, params.get("max_views")), "views",
                             "a lower max_views")
        largest = largest_trained_size(settings, job)
        size = None if largest is None else view_size(*largest[0])
        up_to = "up to " if largest is not None and largest[1] else ""
    if count is None or size is None:
        return
    cost = count * size[0] * size[1]
    if cost > settings.max_output_pixels:
        raise OutputTooCostly(
            f"{count} {unit} of {up_to}{size[0]}x{size[1]} are {cost} pixels, beyond the limit of "
            f"{settings.max_output_pixels} per output (VOXNERF_MAX_OUTPUT_PIXELS): {hint}"
        )


# ------------------------------------------------------------------------------------------------ files


def output_dir(settings: Settings, job_id: str, output_id: str) -> Path:
    """This process's directory of an output's files."""
    return settings.runs_dir / job_id / OUTPUTS_DIR / output_id


def store_key(output_id: str) -> str:
    return f"{OUTPUTS_DIR}/{output_id}"


def publish_output(settings: Settings, output: OutputRow, directory: Path) -> None:
    """Upload a finished output's directory to the object store; no-op without one."""
    store = storage.open_store(settings)
    if store is not None:
        storage.put_dir(store, directory, store_key(output.id))


def output_file(settings: Settings, output: OutputRow) -> Path:
    """The local file of a succeeded output, fetched from the object store when this cache lacks it. Raises
    StorageError when the store does not hold it, FileNotFoundError when the data directory lost it."""
    directory = output_dir(settings, output.job_id, output.id)
    path = directory / output.file_name
    store = storage.open_store(settings)
    if store is not None and not path.is_file():
        storage.fetch_dir(store, store_key(output.id), directory, settings.staging_dir)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: the output's file is missing")
    return path


def remove_files(settings: Settings, output: OutputRow) -> None:
    """Delete what a failed or cancelled output left in this process's data directory."""
    shutil.rmtree(output_dir(settings, output.job_id, output.id), ignore_errors=True)


# ------------------------------------------------------------------------------------------------ rows


def _progress(_settings: Settings, _output_id: str, done: int, total: int, eta_s: float | None) -> dict:
    """The columns of ``done`` of ``total`` (frames or views) and the ETA."""
    progress = min(1.0, done / total) if total > 0 else 0.0
    return {"done": done, "total": total, "progress": progress, "eta_s": eta_s}


OUTPUTS = WorkKind(
    name="output",
    noun="output job",
    table=OutputRow,
    task=OUTPUT_TASK,
    claimed=lambda _row, now: {"started_at": now, "progress": 0.0, "done": 0, "eta_s": None},  # from frame one
    progress=_progress,
)
"""Output jobs' lease lifecycle (:class:`app.core.lease.WorkKind`): ``OUTPUTS.get``, ``claim``,
``record_progress(settings, output_id, attempt, done, total, eta_s)``, ``finish``, ``request_cancel``..."""


def create_output(settings: Settings, job_id: str, kind: str, params: dict, total: int | None,
                  partial: bool, principal: Principal | None = None) -> OutputRow:
    """A new queued output job of trained job ``job_id`` made by ``principal`` (None: outside the API). Raises
    QueueFull when ``max_queued_outputs`` output jobs are queued already, or as many as the principal's own limit
    allows (:meth:`app.core.lease.WorkKind.refuse_beyond`); nothing is written then."""
    row = OUTPUTS.new_row(new_id(), job_id=job_id, kind=kind, params=json_safe(params), partial=partial,
                          progress=0.0, done=0, total=total, created_by=principal and principal.name)
    with session_scope(settings) as session:
        session.add(row)
        session.flush()
        OUTPUTS.refuse_beyond(session, settings.max_queued_outputs, "max_queued_outputs",
                              principal and tokens.queue_quota(settings, principal))
    return row
