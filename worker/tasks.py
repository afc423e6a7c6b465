"""Celery tasks: train a job (queue ``train``) and render a pose of a finished job (queue ``render``).

Training: the task claims the job in the job store (fenced by its attempt number), runs
:func:`voxnerf.trainer.train` with ``resume=True`` (a redelivered job continues from its checkpoint),
writes progress at most every ``progress_interval_s``, and renews its lease every ``heartbeat_s`` from a
side thread that also picks up cancellation. ``acks_late`` + ``reject_on_worker_lost`` give the message
back to the broker if the process dies; the job store's stale-job sweep covers the rest.

With an object store (``VOXNERF_STORAGE_URL``, :mod:`app.storage`) the scene and the run's last uploaded
checkpoint are fetched into this machine's cache first, and the run is uploaded after every checkpoint and
at the end; a render fetches the run's checkpoint when the cache lacks it.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import OrderedDict
from pathlib import Path

import numpy as np
from celery.signals import worker_ready

from app import jobstore, storage
from app.schemas import RenderRequest
from app.settings import get_settings
from voxnerf.config import TrainConfig
from voxnerf.errors import RunError, VoxNeRFError
from voxnerf.render import CHECKPOINT, TrainedModel, load_model, render
from voxnerf.trainer import train
from worker.celery_app import RENDER_TASK, TRAIN_TASK, celery_app
from worker.dispatch import requeue_stale_jobs
from worker.encoding import encode_render
from worker.render_results import RenderOutcome, deliver_outcome

log = logging.getLogger(__name__)


class Lease:
    """Renews a claimed job's heartbeat in a side thread and turns cancellation into ``should_stop``."""

    def __init__(self, job_id: str, attempt: int) -> None:
        self.job_id = job_id
        self.attempt = attempt
        self.cancelled = threading.Event()
        self.lost = threading.Event()
        self._done = threading.Event()
        self._thread = threading.Thread(target=self._run, name=f"lease-{job_id}", daemon=True)

    def _run(self) -> None:
        settings = get_settings()
        while not self._done.wait(settings.heartbeat_s):
            try:
                status = jobstore.renew_lease(settings, self.job_id, self.attempt)
            except Exception:  # the database is briefly unreachable: keep training, retry next beat
                log.warning("job %s: lease renewal failed", self.job_id, exc_info=True)
                continue
            if not status.owned:
                log.warning("job %s: lease lost (requeued elsewhere); stopping", self.job_id)
                self.lost.set()
            if status.cancel_requested:
                self.cancelled.set()

    def should_stop(self) -> bool:
        return self.cancelled.is_set() or self.lost.is_set()

    def __enter__(self) -> Lease:
        self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self._done.set()
        self._thread.join()


class ProgressWriter:
    """``on_progress`` callback: writes the trainer's events to the job store, at most one per interval."""

    def __init__(self, job_id: str, attempt: int, interval_s: float) -> None:
        self.job_id = job_id
        self.attempt = attempt
        self.interval_s = interval_s
        self._last_write = -float("inf")
        self._last_stage: str | None = None
        self.progress = 0.0
        self.iteration = 0

    def __call__(self, event: dict) -> None:
        if event.get("stage") == "done":  # the task writes the final state; cancelled keeps its progress
            return
        now = time.monotonic()
        if event.get("stage") == self._last_stage and now - self._last_write < self.interval_s:
            return
        self._last_write, self._last_stage = now, event.get("stage")
        # Stage events carry iteration 0; an attempt's iteration and progress never go back.
        self.iteration = max(self.iteration, int(event.get("iteration") or 0))
        self.progress = max(self.progress, jobstore.finite_or_none(event.get("progress")) or 0.0)
        values = {
            "stage": event.get("stage"),
            "iteration": self.iteration,
            "progress": self.progress,
            "eta_s": jobstore.finite_or_none(event.get("eta_s")),
            "elapsed_s": jobstore.finite_or_none(event.get("elapsed_s")) or 0.0,
            "loss": jobstore.finite_or_none(event.get("loss")),
            "history": event.get("history") or [],
            "stages": event.get("stages") or [],
        }
        jobstore.record_progress(get_settings(), self.job_id, self.attempt, values)


@celery_app.task(name=TRAIN_TASK, acks_late=True, reject_on_worker_lost=True)
def train_job(job_id: str) -> None:
    """Train job ``job_id`` to a final state (succeeded, cancelled, failed) unless another worker owns it."""
    settings = get_settings()
    job = jobstore.claim_job(settings, job_id, jobstore.worker_identity())
    if job is None:
        log.info("job %s: nothing to do (finished, cancelled, or running elsewhere)", job_id)
        return
    if job.cancel_requested:
        jobstore.finish_job(settings, job_id, job.attempt, "cancelled", {"stage": "cancelled"})
        return
    config = TrainConfig(
        **job.options, device=settings.device, checkpoint_every_s=settings.checkpoint_every_s
    )
    writer = ProgressWriter(job_id, job.attempt, settings.progress_interval_s)
    with Lease(job_id, job.attempt) as lease:
        try:
            scene_dir = storage.ensure_scene(settings, job.scene_id)
            run_dir = storage.ensure_run(settings, job_id)
            with storage.RunPublisher(settings, job_id, run_dir):
                report = train(
                    scene_dir,
                    run_dir,
                    config,
                    on_progress=writer,
                    should_stop=lease.should_stop,
                    resume=True,
                    progress_bar=False,
                )
        except VoxNeRFError as err:
            log.warning("job %s failed: %s", job_id, err)
            jobstore.finish_job(
                settings,
                job_id,
                job.attempt,
                "failed",
                {"error": f"{type(err).__name__}: {err}", "stage": "failed", "eta_s": None},
            )
            return
        except Exception as err:
            log.exception("job %s crashed", job_id)
            jobstore.finish_job(
                settings,
                job_id,
                job.attempt,
                "failed",
                {"error": f"internal error: {type(err).__name__}: {err}", "stage": "failed", "eta_s": None},
            )
            return
    if lease.lost.is_set():
        return
    succeeded = report.get("status") == "succeeded"
    jobstore.finish_job(
        settings,
        job_id,
        job.attempt,
        "succeeded" if succeeded else "cancelled",
        {
            "stage": "done" if succeeded else "cancelled",
            "progress": 1.0 if succeeded else writer.progress,
            "eta_s": None,
            "iteration": int(report.get("iteration") or 0),
            "elapsed_s": jobstore.finite_or_none(report.get("train_seconds")) or 0.0,
            "history": report.get("history") or [],
            "stages": report.get("stages") or [],
            "metrics": report.get("metrics"),
        },
    )


class ModelCache:
    """The ``size`` most recently used trained models of this process, keyed by checkpoint file and mtime."""

    def __init__(self, size: int) -> None:
        self.size = size
        self._models: OrderedDict[tuple[str, int], TrainedModel] = OrderedDict()

    def get(self, run_dir: Path, device: str) -> TrainedModel:
        checkpoint = run_dir / CHECKPOINT
        try:
            key = (str(checkpoint), checkpoint.stat().st_mtime_ns)
        except FileNotFoundError:
            raise RunError(f"job {run_dir.name} has no checkpoint") from None
        if key in self._models:
            self._models.move_to_end(key)
            return self._models[key]
        model = load_model(run_dir, device)
        self._models[key] = model
        while len(self._models) > self.size:
            self._models.popitem(last=False)
        return model


_models = ModelCache(get_settings().render_cache_size)


def render_outcome(job_id: str, request: RenderRequest) -> RenderOutcome:
    """Render ``request`` with job ``job_id``'s model (loaded through the cache)."""
    settings = get_settings()
    try:
        trained = _models.get(storage.ensure_run(settings, job_id, refresh=False), settings.device)
    except (RunError, storage.StorageError) as err:
        return RenderOutcome(409, detail=f"job {job_id} cannot be rendered: {err}")
    intrinsics = request.intrinsics(trained.default_intrinsics)
    if intrinsics.width * intrinsics.height > settings.max_render_pixels:
        size = f"{intrinsics.width}x{intrinsics.height}"
        return RenderOutcome(422, detail=f"{size} exceeds the limit of {settings.max_render_pixels} pixels")
    images = render(trained, np.asarray(request.transform_matrix), intrinsics, tuple(request.outputs))
    data = encode_render(images, request.format, request.outputs, trained.depth_unit_scale)
    return RenderOutcome(200, request.media_type, data)


@celery_app.task(name=RENDER_TASK)
def render_pose(request_id: str, job_id: str, request: dict) -> None:
    """Render one request and hand its outcome to the waiting API (:mod:`worker.render_results`)."""
    try:
        outcome = render_outcome(job_id, RenderRequest.model_validate(request))
    except Exception as err:
        log.exception("render %s of job %s failed", request_id, job_id)
        outcome = RenderOutcome(500, detail=f"render failed: {type(err).__name__}: {err}")
    deliver_outcome(get_settings(), request_id, outcome)


@worker_ready.connect
def _recover_stale_jobs(**_) -> None:
    """At worker start-up, requeue jobs whose previous worker died (the API also does so periodically)."""
    try:
        requeue_stale_jobs(get_settings(), celery_app)
    except Exception:
        log.exception("start-up recovery of stale jobs failed")
