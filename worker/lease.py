"""The worker's side of the lease lifecycle every kind of queued work shares (:mod:`app.core.lease`): a task
made with :func:`leased_task` runs its row through :func:`hold`, which claims it (the fence), runs the task's own
work while a :class:`Lease` renews the lease and turns cancellation into ``should_stop``, and writes the final
state; :class:`DeathNotingRequest` notes why the worker's pool process died.

Training jobs, capture imports and output jobs (their tasks are in :mod:`worker.tasks`) all hold their work so,
each with its kind (:data:`app.core.jobstore.JOBS`, :data:`app.core.imports.IMPORTS`,
:data:`app.core.outputs.OUTPUTS`); the task holds only its own work.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable
from typing import Any

from celery import shared_task
from celery.exceptions import WorkerLostError
from celery.worker.request import Request

from app.core.jobstore import JOBS
from app.core.lease import LeaseStatus, WorkKind, worker_identity
from app.core.settings import Settings, get_settings

log = logging.getLogger(__name__)
Work = Callable[[Settings, Any, "Lease"], dict | None]  # a claimed row's work: its final columns, state among them


class Lease:
    """Renews a claimed row's heartbeat in a side thread and turns cancellation into ``should_stop``.

    ``kind``: the row's kind of work (a training job by default); ``renew(settings, id, attempt) ->
    LeaseStatus`` refreshes the lease (the kind's :meth:`~app.core.lease.WorkKind.renew_lease` by default).
    """

    def __init__(
        self,
        settings: Settings,
        job_id: str,
        attempt: int,
        kind: WorkKind = JOBS,
        renew: Callable[[Settings, str, int], LeaseStatus] | None = None,
    ) -> None:
        self.settings = settings
        self.job_id = job_id
        self.attempt = attempt
        self.renew = renew or kind.renew_lease
        self.cancelled = threading.Event()
        self.lost = threading.Event()
        self._done = threading.Event()
        self._thread = threading.Thread(target=self._run, name=f"lease-{job_id}", daemon=True)

    def _run(self) -> None:
        while not self._done.wait(self.settings.heartbeat_s):
            try:
                status = self.renew(self.settings, self.job_id, self.attempt)
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

    def still_owned(self) -> bool:
        """Ask the job store now (the fence before each file the trainer writes) whether this attempt still
        owns the job; a no sets ``lost``. A store that cannot answer counts as a no: better an attempt that
        stops than two that write."""
        if self.lost.is_set():
            return False
        try:
            owned = self.renew(self.settings, self.job_id, self.attempt).owned
        except Exception:
            log.warning("job %s: cannot confirm the lease before writing", self.job_id, exc_info=True)
            owned = False
        if not owned:
            self.lost.set()
        return owned

    def __enter__(self) -> Lease:
        self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self._done.set()
        self._thread.join()


class DeathNotingRequest(Request):
    """A task request that, in the worker's main process, notes on the row why its pool process died (Celery's
    "Worker exited prematurely: signal 9 (SIGKILL)") before the message goes back to the queue; a row failed
    for dying too often names the last death. ``kind``: the kind of work the task's first argument names."""

    kind: WorkKind = JOBS

    def on_failure(self, exc_info, send_failed_event=True, return_ok=False):
        exc = getattr(exc_info, "exception", None)
        exc = getattr(exc, "exc", exc)  # unwrap Celery's ExceptionWithTraceback
        if isinstance(exc, WorkerLostError) and self.args:
            try:
                self.kind.record_worker_death(get_settings(), self.args[0], str(exc))
            except Exception:  # the store is down: the death still counts, only its reason is lost
                log.warning("cannot note the worker's death on %s", self.args[0], exc_info=True)
        return super().on_failure(exc_info, send_failed_event, return_ok)


def leased_task(kind: WorkKind) -> Callable:
    """The Celery (shared) task decorator of ``kind``'s work: the kind's task name, the message acknowledged
    only when the task ends (``acks_late``) and given back to the broker when its process dies
    (``reject_on_worker_lost``), that death noted on the row first (:class:`DeathNotingRequest`)."""
    request = type(f"DeathNoting{kind.name.capitalize()}Request", (DeathNotingRequest,), {"kind": kind})
    return shared_task(name=kind.task, acks_late=True, reject_on_worker_lost=True, Request=request)


def hold(settings: Settings, kind: WorkKind, row_id: str, work: Work,
         ending: Callable[[Settings, Any, str], None] | None = None) -> None:
    """Run row ``row_id`` of ``kind`` to a final state (succeeded, cancelled, failed) unless another worker owns it.

    Claims the row (its ``attempt`` fences every later write); one cancelled before it started is finished
    ``cancelled`` at once. Otherwise ``work(settings, row, lease)`` runs while the :class:`Lease` renews the
    lease (it writes its progress with the kind's ``record_progress`` and stops when ``lease.should_stop()``)
    and returns the row's final columns, ``state`` among them (None: nothing to write, its lease was lost).
    When the lease was lost (the row was requeued elsewhere) nothing more is written: the new owner
    writes the row and the files. ``ending(settings, row, state)`` runs just before the final state is written
    (an output removes what a failed or cancelled attempt left).
    """
    row = kind.claim(settings, row_id, worker_identity())
    if row is None:
        log.info("%s %s: nothing to do (finished, cancelled, or running elsewhere)", kind.name, row_id)
        return
    if row.cancel_requested:
        kind.finish(settings, row_id, row.attempt, "cancelled", {})
        return
    with Lease(settings, row_id, row.attempt, kind) as lease:
        final = work(settings, row, lease)
    if final is None or lease.lost.is_set():
        return
    state = final.pop("state")
    if ending is not None:
        ending(settings, row, state)
    kind.finish(settings, row_id, row.attempt, state, final)
