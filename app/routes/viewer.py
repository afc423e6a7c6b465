"""What the viewer page (``/static/viewer.html``) reads besides ``POST /render``: a job's scene cameras, a sparse
sample of its prior, a camera's ground-truth image, and video paths made from keyframes.

The scene is read by the engine's scene rules in a child process (:mod:`app.viewer_scene`; the API process never
imports torch) under an upload validation's limits, cached by scene id, one read per scene shared by the requests
that come while it runs, and at most ``max_concurrent_scene_reads`` reads at once (more: 429 with Retry-After).
A scene without a prior file shows the prior its job's run fused, read the same way. A camera's image is found
through the validated scene's own frame list, never through a path from the request.
"""

from __future__ import annotations

import mimetypes
import threading
from pathlib import Path

import numpy as np
from fastapi import APIRouter, HTTPException, Request
from fastapi.responses import FileResponse

from app.api_reference import EXAMPLE_ID, error_responses
from app.core import storage
from app.core.jobstore import JOBS
from app.core.models import JobRow
from app.core.redact import public_error
from app.core.settings import Settings
from app.deps import JobId, SettingsDep
from app.routes import work
from app.schemas import CameraPathOut, CameraPathRequest, CamerasOut, PathFrame, PriorPreviewOut, ViewerCamera
from app.viewer_scene import SceneReads, SceneReadsBusy, SceneViewError, prior_sample, read_in_child, scene_view
from voxnerf.cameras.paths import CameraPath, CameraPathError, interpolate_path, parse_nerfstudio
from voxnerf.cameras.rules import CameraError, Intrinsics, resolve_intrinsics
from voxnerf.files import FUSED_PRIOR

router = APIRouter(tags=["viewer"])
SCENE_READ_TIMEOUT_S = 120.0  # a stored scene's transforms.json and image headers; generous for a slow disk
SCENE_READ_RETRY_AFTER_S = 1  # what a client refused for want of a read slot is told to wait
_READS_LOCK = threading.Lock()


def _scene_reads(request: Request, settings: Settings) -> SceneReads:
    """This app's bounded, shared scene reads (:class:`app.viewer_scene.SceneReads`), made on first use."""
    state = request.app.state
    with _READS_LOCK:
        if not hasattr(state, "scene_reads"):
            state.scene_reads = SceneReads(settings.max_concurrent_scene_reads)
        return state.scene_reads


def _shared_read(request: Request, settings: Settings, job: JobRow, key: str, read) -> dict:
    """``read()`` through this app's scene reads under ``key``; 429 when every slot is taken, 503 when the scene
    cannot be fetched or read."""
    try:
        return _scene_reads(request, settings).get(key, read)
    except SceneReadsBusy as busy:
        raise HTTPException(
            429, f"{busy} (VOXNERF_MAX_CONCURRENT_SCENE_READS); retry in {SCENE_READ_RETRY_AFTER_S} s",
            headers={"Retry-After": str(SCENE_READ_RETRY_AFTER_S)},
        ) from None
    except (storage.StorageError, SceneViewError) as err:
        raise HTTPException(503, public_error(f"scene {job.scene_id} of job {job.id}: {err}", settings)) from None


def _scene_view(request: Request, settings: Settings, job_id: str) -> tuple[JobRow, dict]:
    """Job ``job_id`` and its scene's view (cameras, the scene's prior sample); 404 for an unknown job, 429 or
    503 as :func:`_shared_read` says."""
    job = work.found(settings, JOBS, job_id)

    def read() -> dict:
        root = storage.ensure_scene(settings, job.scene_id)
        return read_in_child(scene_view, (root,), settings, SCENE_READ_TIMEOUT_S)

    return job, _shared_read(request, settings, job, f"scene {job.scene_id}", read)


SCENE_READ_ERRORS = error_responses(
    404, 429, 503, e429="2 scene reads are in progress (VOXNERF_MAX_CONCURRENT_SCENE_READS); retry in 1 s",
    e503=f"scene {EXAMPLE_ID} of job {EXAMPLE_ID}: the scene read was killed (out of memory)")


@router.get("/jobs/{job_id}/cameras", response_model=CamerasOut, responses=SCENE_READ_ERRORS,
            summary="The cameras of a job's scene (poses in scene units, intrinsics, splits), for the viewer")
def get_cameras(job_id: JobId, request: Request, settings: SettingsDep) -> CamerasOut:
    """Every camera of the job's scene as the viewer draws it, with the URL of its ground-truth image, the
    scene's units and the scale of depth renders. The scene is read once (in a child process, under the upload
    validation's limits) and cached."""
    job, view = _scene_view(request, settings, job_id)
    frames = [
        ViewerCamera(**{k: v for k, v in frame.items() if k != "image_path"},
                     image_url=f"/jobs/{job.id}/cameras/{frame['index']}/image")
        for frame in view["frames"]
    ]
    return CamerasOut(job_id=job.id, scene_id=job.scene_id, units="metres" if view["metric"] else "scene units",
                      depth_unit_scale=view["depth_unit_scale"], frames=frames)


@router.get("/jobs/{job_id}/prior-preview", response_model=PriorPreviewOut, responses=SCENE_READ_ERRORS,
            summary="A sparse sample of the prior (at most a few thousand points, scene units), for the viewer")
def get_prior_preview(job_id: JobId, request: Request, settings: SettingsDep) -> PriorPreviewOut:
    """A random sample of the scene's prior file, or of the prior the job's run fused when the scene has none
    (404 when neither exists)."""
    job, view = _scene_view(request, settings, job_id)
    if view["prior"] is not None:
        return PriorPreviewOut(**view["prior"])
    fused = settings.runs_dir / job.id / FUSED_PRIOR  # the prior a run fused when its scene has no prior file
    if not fused.is_file():
        raise HTTPException(404, f"job {job_id}: its scene has no prior and its run fused none")
    sample = _shared_read(request, settings, job, f"run {job.id} fused prior",
                          lambda: read_in_child(prior_sample, (fused,), settings, SCENE_READ_TIMEOUT_S))
    return PriorPreviewOut(**sample)


@router.get("/jobs/{job_id}/cameras/{index}/image", response_class=FileResponse,
            responses={200: {"content": {"image/png": {}, "image/jpeg": {}}}, **SCENE_READ_ERRORS},
            summary="The ground-truth image of one of a job's scene cameras")
def get_camera_image(job_id: JobId, index: int, request: Request, settings: SettingsDep) -> FileResponse:
    """The image file of camera ``index`` (its position in ``GET /jobs/{id}/cameras``), as the scene stores it."""
    job, view = _scene_view(request, settings, job_id)
    if not 0 <= index < len(view["frames"]):
        raise HTTPException(404, f"job {job_id}: its scene has no camera {index}")
    root = storage.ensure_scene(settings, job.scene_id).resolve()
    path = Path(view["frames"][index]["image_path"]).resolve()
    if not path.is_relative_to(root) or not path.is_file():  # the scene rules resolved it inside the scene
        raise HTTPException(404, f"job {job_id}: the image of camera {index} is gone")
    return FileResponse(path, media_type=mimetypes.guess_type(path.name)[0] or "application/octet-stream")


@router.post("/camera-paths", response_model=CameraPathOut,
             responses=error_responses(422, e422="camera_path: 'camera_path' must be a list of keyframes"),
             summary="Interpolate a video path through keyframes, or read a nerfstudio camera path, for the viewer")
def make_camera_path(body: CameraPathRequest, settings: SettingsDep) -> CameraPathOut:
    """The frames of a path (to preview) and its nerfstudio camera-path JSON (to export, or to send to
    ``POST /jobs/{id}/videos``): interpolated through ``keyframes``, or a nerfstudio ``camera_path`` read back
    into scene units. 422 naming the key at fault."""
    try:
        path = _camera_path(body, settings)
    except (CameraPathError, CameraError) as err:
        raise HTTPException(422, str(err)) from None
    width, height = path.size
    frames = [PathFrame(transform_matrix=pose.tolist(), fl_x=intr.fl_x, fl_y=intr.fl_y, cx=intr.cx, cy=intr.cy)
              for pose, intr in zip(path.poses, path.intrinsics, strict=True)]
    return CameraPathOut(width=width, height=height, fps=path.fps, frames=frames, camera_path=path.to_nerfstudio())


def _camera_path(body: CameraPathRequest, settings: Settings) -> CameraPath:
    """The request's path; CameraPathError or CameraError naming the key at fault."""
    if body.camera_path is not None:
        return parse_nerfstudio(body.camera_path, dataparser_transforms=body.dataparser_transforms,
                                max_frames=settings.max_video_frames, max_pixels=settings.render_pixel_limit())
    if body.frames > settings.max_video_frames:
        raise CameraPathError(f"{body.frames} exceeds the limit of {settings.max_video_frames} frames", "frames")
    camera = Intrinsics(body.fl_x, body.fl_y, body.cx, body.cy, body.width, body.height)
    camera = resolve_intrinsics(camera, max_pixels=settings.render_pixel_limit())
    return interpolate_path(np.asarray(body.keyframes, dtype=np.float64), camera, n_frames=body.frames, fps=body.fps)
