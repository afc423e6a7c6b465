"""Celery tasks: train a job (queue ``train``) and render a pose of a finished job (queue ``render``); output
jobs (queue ``outputs``: videos, meshes, point clouds) are in :mod:`worker.outputs`; both hold their work with
:mod:`worker.lease` and load models through :mod:`worker.model_cache`.

Training: the task holds the job (:func:`worker.lease.hold`: claimed in the job store, fenced by its attempt
number, its lease renewed every ``heartbeat_s`` from a side thread that also picks up cancellation, its final
state written from the report), runs :func:`voxnerf.trainer.train` with ``resume=True`` (a redelivered job
continues from its checkpoint) and writes progress at most every ``progress_interval_s``. ``acks_late`` +
``reject_on_worker_lost`` give the message back to the broker if the process dies (the Celery main process
notes the death on the job's row first, :class:`worker.lease.DeathNotingRequest`); the dispatcher's sweep
covers the rest, and fails a job whose worker died ``max_worker_deaths`` times. Every job trains for at most
``max_job_seconds`` of wall clock, its ``eval_at`` evaluations for at most ``max_eval_at_seconds``; before each
file it writes, the trainer asks the job store whether this attempt still owns the job
(:meth:`worker.lease.Lease.still_owned`), so a worker that lost its lease writes nothing more into the run.

With an object store (``VOXNERF_STORAGE_URL``, :mod:`app.core.storage`) the scene and the run's last uploaded
checkpoint are fetched into this machine's cache first, and the run is uploaded after every checkpoint and
at the end; a render fetches the run's checkpoint when the cache lacks it.

A disk that fills up while a job trains (``ENOSPC`` or ``EDQUOT`` from any write: a checkpoint, the report, an
evaluation render) does not strand its work: every file the trainer writes is written atomically, so the last
checkpoint it completed is intact, and the job ends ``cancelled`` with that checkpoint (renders, videos and
exports take it, marked partial) and an ``error`` saying the disk filled up at which iteration
(:func:`disk_full_outcome`). Only a job that had no complete checkpoint yet ends ``failed``, nothing being kept.

The tasks are Celery *shared* tasks: no Celery app is built when this module is imported; they bind to the app
:func:`worker.run.run_worker` builds (``app.core.celery_app.create_celery``). The engine's typed records are
the contract with the trainer: ``on_progress`` receives :class:`ProgressEvent` objects and ``train()`` returns a
:class:`TrainReport`.
"""

from __future__ import annotations

import dataclasses
import logging
import os
import signal
import time
from collections.abc import Callable

import numpy as np
from celery import shared_task
from celery.signals import worker_ready

from app.core import jobstore, storage
from app.core.celery_app import RENDER_TASK
from app.core.dispatch import sweep_jobs
from app.core.jobstore import JOBS
from app.core.redact import public_error
from app.core.render_request import RenderRequest
from app.core.render_results import RenderOutcome, deliver_outcome
from app.core.settings import Settings, get_settings
from voxnerf.cameras.rules import CameraError
from voxnerf.config import TrainConfig
from voxnerf.errors import RenderStopped, RunError, VoxNeRFError
from voxnerf.files import CHECKPOINT
from voxnerf.inference.encoding import encode_outputs
from voxnerf.inference.render import render
from voxnerf.trainer import train
from voxnerf.training.checkpoint import load_checkpoint
from voxnerf.training.records import ProgressEvent
from voxnerf.training.run import LeaseLost
from worker.disk_full import DISK_FULL, disk_full_cause
from worker.lease import Lease, hold, leased_task
from worker.model_cache import model_cache

log = logging.getLogger(__name__)


class ProgressWriter:
    """``on_progress`` callback: writes the trainer's events to the job store, at most one per interval.

    A new stage is always written; within a stage, one event per ``progress_interval_s``. The ``done`` event
    is not written: the task records the final state from the report (and a cancelled job keeps its progress).
    """

    def __init__(self, settings: Settings, job_id: str, attempt: int) -> None:
        self.settings = settings
        self.job_id = job_id
        self.attempt = attempt
        self._last_write = -float("inf")
        self._last_stage: str | None = None
        self.progress = 0.0
        self.iteration = 0

    def __call__(self, event: ProgressEvent) -> None:
        if event.stage == "done":
            return
        now = time.monotonic()
        if event.stage == self._last_stage and now - self._last_write < self.settings.progress_interval_s:
            return
        self._last_write, self._last_stage = now, event.stage
        # Stage events carry iteration 0; an attempt's iteration and progress never go back.
        self.iteration = max(self.iteration, event.iteration)
        self.progress = max(self.progress, jobstore.finite_or_none(event.progress) or 0.0)
        event = event.model_copy(update={"iteration": self.iteration, "progress": self.progress})
        JOBS.record_progress(self.settings, self.job_id, self.attempt, event)


def _failed(settings: Settings, error: str) -> dict:
    """A failed job's final columns: ``error`` as clients may read it (:func:`app.core.redact.public_error`)."""
    return {"state": "failed", "error": public_error(error, settings)}


def job_config(settings: Settings, options: dict) -> TrainConfig:
    """A job's training config: its options, with what the deployment decides: the device, the checkpoint
    period, ``max_seconds`` capped at ``max_job_seconds`` (set to it for a ``max_iters``-only job) and the time
    its ``eval_at`` evaluations may take."""
    requested = options.get("max_seconds")
    max_seconds = settings.max_job_seconds if requested is None else min(requested, settings.max_job_seconds)
    return TrainConfig(**{**options, "max_seconds": max_seconds}, device=settings.device,
                       checkpoint_every_s=settings.checkpoint_every_s,
                       eval_at_max_seconds=settings.max_eval_at_seconds)


def _kill_if_poison_test(settings: Settings, scene_id: str) -> None:
    """The poison-job test's hook (``kill_worker_on_scene``, a setting only tests set): die like an out-of-memory
    kill while loading that scene."""
    if settings.kill_worker_on_scene is not None and settings.kill_worker_on_scene == scene_id:
        log.warning("scene %s: kill_worker_on_scene is set, the worker kills itself (SIGKILL)", scene_id)
        os.kill(os.getpid(), signal.SIGKILL)


def disk_full_outcome(settings: Settings, job, cause: OSError, progress: float) -> dict:
    """The final columns of a job whose disk filled up: ``cancelled`` keeping the run's last complete checkpoint
    (it is read back here, so a job said to keep one can be rendered), or ``failed`` when it has none."""
    checkpoint = settings.runs_dir / job.id / CHECKPOINT
    why = f"{DISK_FULL} while the job was writing ({cause.strerror})"
    try:
        iteration = int(load_checkpoint(checkpoint)["iteration"]) if checkpoint.is_file() else None
    except (RunError, KeyError, TypeError, ValueError):
        log.exception("job %s: the checkpoint left after the disk filled up is unreadable", job.id)
        iteration = None
    if iteration is None:
        return _failed(settings, f"{why}, before its first checkpoint: nothing is kept; free space and train again")
    log.warning("job %s: %s; stopped, its checkpoint of iteration %d kept", job.id, why, iteration)
    return {"state": "cancelled", "stage": "cancelled", "iteration": iteration, "progress": progress, "eta_s": None,
            "error": public_error(f"{why}; stopped with its last checkpoint (iteration {iteration}) kept, which "
                                  "renders and outputs use; free space before training again", settings)}


def _train_claimed(settings: Settings, job, lease: Lease) -> dict | None:
    """Train a claimed job; its final columns (:func:`app.core.jobstore.report_outcome`, failed with the error,
    or :func:`disk_full_outcome`), None when its lease was lost."""
    writer = ProgressWriter(settings, job.id, job.attempt)
    try:
        return _train_and_report(settings, job, lease, writer)
    except LeaseLost as err:
        log.warning("job %s: %s", job.id, err)
        return None
    except Exception as err:
        if (cause := disk_full_cause(err)) is not None:
            return disk_full_outcome(settings, job, cause, writer.progress)
        if isinstance(err, VoxNeRFError):
            log.warning("job %s failed: %s", job.id, err)
            return _failed(settings, f"{type(err).__name__}: {err}")
        log.exception("job %s crashed", job.id)
        return _failed(settings, f"internal error: {type(err).__name__}: {err}")


def _train_and_report(settings: Settings, job, lease: Lease, writer: ProgressWriter) -> dict:
    """Fetch what the job needs, train it and return its final columns from the report."""
    config = job_config(settings, job.options)
    with (storage.cache_entry_in_use(settings, storage.SCENES, job.scene_id),
          storage.cache_entry_in_use(settings, storage.RUNS, job.id)):
        storage.prune_cache(settings)  # room for what is fetched next (an object store's cache only)
        scene_dir = storage.ensure_scene(settings, job.scene_id)
        _kill_if_poison_test(settings, job.scene_id)
        run_dir = storage.ensure_run(settings, job.id)
        with storage.RunPublisher(settings, job.id, run_dir, may_upload=lease.still_owned):
            report = train(
                scene_dir,
                run_dir,
                config,
                on_progress=writer,
                should_stop=lease.should_stop,
                resume=True,
                progress_bar=False,
                may_write=lease.still_owned,
            )
    storage.prune_cache(settings)  # the run grew
    state, values = jobstore.report_outcome(settings, job.id, report, writer.progress)
    return {"state": state, **values}


@leased_task(JOBS)
def train_job(job_id: str) -> None:
    """Train job ``job_id`` to a final state (succeeded, cancelled, failed) unless another worker owns it."""
    hold(get_settings(), JOBS, job_id, _train_claimed)


def render_outcome(job_id: str, request: RenderRequest,
                   should_stop: Callable[[], bool] | None = None) -> RenderOutcome:
    """Render ``request`` with job ``job_id``'s model (loaded through the cache); RenderStopped when
    ``should_stop`` says so between two passes over the rays."""
    settings = get_settings()
    try:
        with storage.cache_entry_in_use(settings, storage.RUNS, job_id):
            if storage.open_store(settings) is not None and not (settings.runs_dir / job_id / CHECKPOINT).is_file():
                storage.prune_cache(settings)  # room for the checkpoint about to be fetched
            trained = model_cache().get(storage.ensure_run(settings, job_id, refresh=False), settings.device)
    except (RunError, storage.StorageError) as err:
        return RenderOutcome(409, detail=f"job {job_id} cannot be rendered: {err}")
    try:  # the scene's default size is only known here, so the pixel limit is checked here too
        intrinsics = request.intrinsics(trained.default_intrinsics,
                                        max_pixels=settings.render_pixel_limit(trained.model.device.type))
    except CameraError as err:
        return RenderOutcome(422, detail=str(err))
    images = render(trained, np.asarray(request.transform_matrix), intrinsics, tuple(request.outputs),
                    path=settings.render_path, should_stop=should_stop)
    data = encode_outputs(images, request.format, request.outputs, trained.depth_unit_scale)
    return RenderOutcome(200, request.media_type, data)


def past(deadline: float | None) -> Callable[[], bool] | None:
    """``should_stop`` of a render whose API gives up at ``deadline`` (a Unix time; None: never)."""
    return None if deadline is None else lambda: time.time() > deadline


@shared_task(name=RENDER_TASK)
def render_pose(request_id: str, job_id: str, request: dict, deadline: float | None = None) -> None:
    """Render one request and hand its outcome to the waiting API (:mod:`app.core.render_results`). Past the
    ``deadline`` the API answered 504 and waits no more: the render stops at its next pass over the rays and
    nothing is delivered, so the worker is free for the next render."""
    try:
        outcome = render_outcome(job_id, RenderRequest.model_validate(request), past(deadline))
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


@worker_ready.connect
def _recover_stale_jobs(sender=None, **_) -> None:
    """At worker start-up, requeue jobs whose previous worker died and re-send lost messages (the API also
    does so periodically)."""
    try:
        sweep_jobs(get_settings(), sender.app)
    except Exception:
        log.exception("start-up recovery of stale jobs failed")

