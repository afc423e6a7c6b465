"""The work of the ``render`` queue: render a pose of a job's model (its latest checkpoint while it trains) and
hand the outcome to the API that waits for it (:mod:`app.core.render_results`). The model comes through this
process's model cache (:func:`worker.model_cache.job_model`; with an object store the run's checkpoint is fetched
first). Loads the engine (torch); the Celery task is :func:`worker.tasks.render_pose`.
"""

from __future__ import annotations

import dataclasses
import logging
import time
from collections.abc import Callable

import numpy as np

from app.core import storage
from app.core.redact import public_error
from app.core.render_request import RenderRequest
from app.core.render_results import RenderOutcome, deliver_outcome
from app.core.settings import get_settings
from voxnerf.cameras.rules import CameraError
from voxnerf.errors import RenderStopped, RunError
from voxnerf.files import CHECKPOINT
from voxnerf.inference.encoding import encode_outputs
from voxnerf.inference.render import render
from worker.model_cache import job_model

log = logging.getLogger(__name__)


def render_outcome(job_id: str, request: RenderRequest, should_stop: Callable[[], bool] | None = None,
                   checkpoint_iteration: int | None = None) -> RenderOutcome:
    """Render ``request`` with job ``job_id``'s model (:func:`worker.model_cache.job_model`: its latest checkpoint
    while it trains, ``checkpoint_iteration`` being the last one its row names); RenderStopped when
    ``should_stop`` says so between two passes over the rays. The outcome names the checkpoint's iteration."""
    settings = get_settings()
    try:
        with storage.cache_entry_in_use(settings, storage.RUNS, job_id):
            if storage.open_store(settings) is not None and not (settings.runs_dir / job_id / CHECKPOINT).is_file():
                storage.prune_cache(settings)  # room for the checkpoint about to be fetched
            trained = job_model(settings, job_id, checkpoint_iteration)
    except (RunError, storage.StorageError) as err:
        return RenderOutcome(409, detail=f"job {job_id} cannot be rendered: {err}")
    try:  # the scene's default size is only known here, so the pixel limit is checked here too
        intrinsics = request.intrinsics(trained.default_intrinsics,
                                        max_pixels=settings.render_pixel_limit(trained.model.device.type))
    except CameraError as err:
        return RenderOutcome(422, detail=str(err))
    images = render(trained, np.asarray(request.transform_matrix), intrinsics, tuple(request.outputs),
                    path=settings.render_path, should_stop=should_stop, antialias=request.antialias)
    data = encode_outputs(images, request.format, request.outputs, trained.depth_unit_scale)
    return RenderOutcome(200, request.media_type, data, iteration=trained.iteration)


def past(deadline: float | None) -> Callable[[], bool] | None:
    """``should_stop`` of a render whose API gives up at ``deadline`` (a Unix time; None: never)."""
    return None if deadline is None else lambda: time.time() > deadline


def render_and_deliver(request_id: str, job_id: str, request: dict, deadline: float | None = None,
                       checkpoint_iteration: int | None = None) -> None:
    """Render one request and hand its outcome to the waiting API (:mod:`app.core.render_results`). Past the
    ``deadline`` the API answered 504 and waits no more: the render stops at its next pass over the rays and
    nothing is delivered, so the worker is free for the next render. ``checkpoint_iteration``: the job's last
    checkpoint when the API sent the request (:func:`render_outcome`)."""
    try:
        outcome = render_outcome(job_id, RenderRequest.model_validate(request), past(deadline),
                                 checkpoint_iteration)
    except RenderStopped as stopped:
        log.warning("render %s of job %s %s (its deadline passed); nothing is delivered", request_id, job_id,
                    stopped)
        return
    except Exception as err:
        log.exception("render %s of job %s failed", request_id, job_id)
        outcome = RenderOutcome(500, detail=f"render failed: {type(err).__name__}: {err}")
    settings = get_settings()
    if outcome.detail:  # the API answers with it: no server paths, no credentials
        outcome = dataclasses.replace(outcome, detail=public_error(outcome.detail, settings))
    deliver_outcome(settings, request_id, outcome)
