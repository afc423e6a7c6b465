"""The work of the ``outputs`` queue: make an output job's video, mesh or point cloud from a trained model. Loads
the engine (torch); the Celery task is :func:`worker.tasks.make_output`.

The task holds the output (:func:`worker.lease.hold`: claimed in the job store, fenced by its attempt, its lease
renewed every ``heartbeat_s`` and its cancel flag turned into ``should_stop``, so a cancelled output stops at its
next frame or view); :func:`produce` loads the trained job's model through this process's model cache
(:func:`worker.model_cache.job_model`; with an object store the run's checkpoint is fetched first), and runs the
engine: :func:`voxnerf.inference.video.render_path` for a video, :func:`voxnerf.inference.export.export_geometry`
for a mesh or point cloud. Progress (frames or views done, ETA) is written at most every ``progress_interval_s``.
The engine writes each file under a temporary name and renames it when complete; a failed or cancelled output's
directory is removed, a succeeded one's is uploaded to the object store (when there is one).

Generated video paths need the scene's training cameras (:func:`voxnerf.cameras.paths.generated_path`:
``interpolate`` through evenly spaced ones, ``orbit`` around their centre). Exports render from them too.
"""

from __future__ import annotations

import logging
import time

import numpy as np

from app.core import outputs, storage
from app.core.jobstore import JOBS
from app.core.models import OutputRow
from app.core.outputs import OUTPUTS
from app.core.redact import public_error
from app.core.settings import Settings
from voxnerf.cameras import paths as camera_paths
from voxnerf.cameras.paths import CameraPath, parse_nerfstudio
from voxnerf.cameras.rules import CameraError, resolve_intrinsics
from voxnerf.data.scene import Scene, load_scene
from voxnerf.errors import RunError, VoxNeRFError
from voxnerf.inference.export import export_geometry
from voxnerf.inference.render import TrainedModel, scene_as_trained
from voxnerf.inference.video import render_path
from worker.disk_full import disk_full_message
from worker.lease import Lease
from worker.model_cache import job_model

log = logging.getLogger(__name__)


class OutputProgress:
    """``on_frame`` / ``on_view`` callback: writes ``done`` of ``total`` and an ETA to the job store, at most
    once per ``progress_interval_s`` (the last step always)."""

    def __init__(self, settings: Settings, output_id: str, attempt: int) -> None:
        self.settings = settings
        self.output_id = output_id
        self.attempt = attempt
        self._started = time.monotonic()
        self._last_write = -float("inf")

    def __call__(self, done: int, total: int) -> None:
        now = time.monotonic()
        if done < total and now - self._last_write < self.settings.progress_interval_s:
            return
        self._last_write = now
        eta_s = (now - self._started) * (total - done) / done if done > 0 else None
        OUTPUTS.record_progress(self.settings, self.output_id, self.attempt, done, total, eta_s)


# ------------------------------------------------------------------------------------------------ inputs


def scene_of(settings: Settings, job, trained: TrainedModel) -> Scene:
    """The cameras (no images) of the scene job ``job`` trained on, at the trained downscale."""
    scene_dir = storage.ensure_scene(settings, job.scene_id)
    if not scene_dir.is_dir():
        raise RunError(f"scene {job.scene_id} of job {job.id} was deleted: its cameras are needed")
    return scene_as_trained(load_scene(scene_dir, downscale=int(trained.model.config.run.downscale), load_images=False),
                            trained.model)


def generated_path(settings: Settings, params: dict, trained: TrainedModel, scene: Scene) -> CameraPath:
    """The ``interpolate`` or ``orbit`` path of a video's ``params`` around ``scene``'s training cameras in
    capture order (:func:`voxnerf.cameras.paths.generated_path`, the rule of ``voxnerf render --path`` too)."""
    intrinsics = resolve_intrinsics(
        trained.default_intrinsics, width=params["width"], height=params["height"],
        max_pixels=settings.render_pixel_limit(trained.model.device.type),
    ).undistorted()
    poses = np.stack([scene.frames[i].c2w for i in sorted(scene.train_indices)])
    return camera_paths.generated_path(params["path"], poses, intrinsics, n_frames=params["frames"],
                                       fps=params["fps"], radius=params["radius"] or None,
                                       height=params["height_above"] or 0.0)


def video_path(settings: Settings, params: dict, trained: TrainedModel, job) -> CameraPath:
    """The camera path of a video output: the stored nerfstudio path (scene units), or a generated one."""
    if params.get("camera_path") is not None:
        return parse_nerfstudio(
            params["camera_path"], max_frames=settings.max_video_frames,
            max_pixels=settings.render_pixel_limit(trained.model.device.type),
        )
    return generated_path(settings, params, trained, scene_of(settings, job, trained))


# ------------------------------------------------------------------------------------------------ making


def make_video(settings: Settings, row: OutputRow, job, trained: TrainedModel, lease: Lease) -> dict | None:
    """Render the video; its summary, or None when cancelled (nothing written)."""
    path = video_path(settings, row.params, trained, job)
    out = outputs.output_dir(settings, row.job_id, row.id) / outputs.FILE_NAMES["video"]
    result = render_path(trained, path, out, on_frame=OutputProgress(settings, row.id, row.attempt),
                         should_stop=lease.should_stop)
    if result.stopped:
        return None
    width, height = path.size
    return {"frames": result.frames, "width": width, "height": height, "fps": path.fps,
            "duration_s": path.seconds, "render_seconds": round(result.seconds, 3), "bytes": out.stat().st_size}


def make_export(settings: Settings, row: OutputRow, job, trained: TrainedModel, lease: Lease) -> dict | None:
    """Export the mesh or point cloud; its summary, or None when cancelled (nothing written)."""
    out = outputs.output_dir(settings, row.job_id, row.id) / outputs.FILE_NAMES[row.kind]
    result = export_geometry(
        trained, out, row.kind, scene=scene_of(settings, job, trained), voxel_size=row.params.get("voxel_size"),
        min_opacity=row.params.get("min_opacity", 0.5), max_views=row.params.get("max_views"),
        on_view=OutputProgress(settings, row.id, row.attempt), should_stop=lease.should_stop,
    )
    if result.stopped:
        return None
    summary = {key: value for key, value in result.summary().items() if key not in ("out", "stopped")}
    return {**summary, "bytes": out.stat().st_size}


def produce(settings: Settings, row: OutputRow, lease: Lease) -> dict:
    """Make a claimed output; the final row values: ``state`` succeeded (summary, file name), cancelled, or
    failed (error)."""
    try:
        job = JOBS.get(settings, row.job_id)
        if job is None:
            raise RunError(f"job {row.job_id} no longer exists")
        with (storage.cache_entry_in_use(settings, storage.SCENES, job.scene_id),
              storage.cache_entry_in_use(settings, storage.RUNS, row.job_id)):
            storage.prune_cache(settings)  # room for what is fetched next (an object store's cache only)
            trained = job_model(settings, row.job_id, job.checkpoint_iteration)
            make = make_video if row.kind == "video" else make_export
            summary = make(settings, row, job, trained, lease)
            if summary is None:
                return {"state": "cancelled"}
            outputs.publish_output(settings, row, outputs.output_dir(settings, row.job_id, row.id))
    except Exception as err:
        return {"state": "failed", "error": public_error(_why_failed(row, err), settings)}
    return {"state": "succeeded", "summary": summary, "file_name": outputs.FILE_NAMES[row.kind]}


def _why_failed(row: OutputRow, err: Exception) -> str:
    """A failed output's error: a full disk said as such, the engine's own errors as they are, anything else an
    internal error (logged with its traceback)."""
    if (full := disk_full_message(err, f"the {row.kind} was written")) is not None:
        log.warning("output %s failed: %s", row.id, full)
        return f"{full}: nothing was kept; free space and ask for it again"
    if isinstance(err, (VoxNeRFError, CameraError)):
        log.warning("output %s failed: %s", row.id, err)
        return f"{type(err).__name__}: {err}"
    log.exception("output %s crashed", row.id)
    return f"internal error: {type(err).__name__}: {err}"


def remove_unfinished(settings: Settings, row: OutputRow, state: str) -> None:
    """What a failed or cancelled output left in this process's data directory goes."""
    if state != "succeeded":
        outputs.remove_files(settings, row)
