"""The work of the ``train`` queue's training jobs: train a claimed job to its final state. Loads the engine
(torch); the Celery task is :func:`worker.tasks.train_job`, which holds the job (:func:`worker.lease.hold`:
claimed in the job store, fenced by its attempt number, its lease renewed every ``heartbeat_s`` from a side thread
that also picks up cancellation) and hands it to :func:`train_claimed`.

:func:`train_claimed` runs :func:`voxnerf.trainer.train` with ``resume=True`` (a redelivered job continues from its
checkpoint), writes progress at most every ``progress_interval_s`` and returns the job's final columns from the
report. Every job trains for at most ``max_job_seconds`` of wall clock, its ``eval_at`` evaluations for at most
``max_eval_at_seconds``; before each file it writes, the trainer asks the job store whether this attempt still
owns the job (:meth:`worker.lease.Lease.still_owned`), so a worker that lost its lease writes nothing more into
the run.

With an object store (``VOXNERF_STORAGE_URL``, :mod:`app.core.storage`) the scene and the run's last uploaded
checkpoint are fetched into this machine's cache first, and the run is uploaded after every checkpoint and
at the end.

A disk that fills up while a job trains (``ENOSPC`` or ``EDQUOT`` from any write: a checkpoint, the report, an
evaluation render) does not strand its work: every file the trainer writes is written atomically, so the last
checkpoint it completed is intact, and the job ends ``cancelled`` with that checkpoint (renders, videos and
exports take it, marked partial) and an ``error`` saying the disk filled up at which iteration
(:func:`disk_full_outcome`). Only a job that had no complete checkpoint yet ends ``failed``, nothing being kept.

The engine's typed records are the contract with the trainer: ``on_progress`` receives :class:`ProgressEvent`
objects and ``train()`` returns a :class:`TrainReport`.
"""

from __future__ import annotations

import logging
import os
import signal
import time

from app.core import jobstore, storage
from app.core.jobstore import JOBS
from app.core.redact import public_error
from app.core.settings import Settings
from voxnerf.config import TrainConfig
from voxnerf.errors import RunError, VoxNeRFError
from voxnerf.files import CHECKPOINT
from voxnerf.trainer import train
from voxnerf.training.checkpoint import load_checkpoint
from voxnerf.training.records import ProgressEvent
from voxnerf.training.run import LeaseLost
from worker.disk_full import DISK_FULL, disk_full_cause
from worker.lease import Lease

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
    return {"state": "cancelled", "stage": "cancelled", "iteration": iteration, "checkpoint_iteration": iteration,
            "progress": progress, "eta_s": None,
            "error": public_error(f"{why}; stopped with its last checkpoint (iteration {iteration}) kept, which "
                                  "renders and outputs use; free space before training again", settings)}


def train_claimed(settings: Settings, job, lease: Lease) -> dict | None:
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
