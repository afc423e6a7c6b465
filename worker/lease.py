"""What every kind of queued work does while a worker holds it: renew its lease, notice cancellation, fence its
writes (:class:`Lease`), and note why the worker's pool process died (:class:`DeathNotingRequest`).

Training jobs (:mod:`worker.tasks`) and output jobs (:mod:`worker.outputs`) both use them, with the job store's
functions for their own table.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable

from celery.exceptions import WorkerLostError
from celery.worker.request import Request

from app.core import jobstore
from app.core.models import JobRow
from app.core.settings import Settings, get_settings

log = logging.getLogger(__name__)


class Lease:
    """Renews a claimed job's heartbeat in a side thread and turns cancellation into ``should_stop``.

    ``renew(settings, id, attempt) -> LeaseStatus`` refreshes the lease: a training job's by default
    (:func:`app.core.jobstore.renew_lease`), an output job's with :func:`app.core.outputs.renew_lease`.
    """

    def __init__(
        self,
        settings: Settings,
        job_id: str,
        attempt: int,
        renew: Callable[[Settings, str, int], jobstore.LeaseStatus] = jobstore.renew_lease,
    ) -> None:
        self.settings = settings
        self.job_id = job_id
        self.attempt = attempt
        self.renew = renew
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
    """A task request that, in the worker's main process, notes on the job's row why its pool process died
    (Celery's "Worker exited prematurely: signal 9 (SIGKILL)") before the message goes back to the queue; a
    job failed for dying too often names the last death. ``table``: the rows the task's first argument names."""

    table = JobRow

    def on_failure(self, exc_info, send_failed_event=True, return_ok=False):
        exc = getattr(exc_info, "exception", None)
        exc = getattr(exc, "exc", exc)  # unwrap Celery's ExceptionWithTraceback
        if isinstance(exc, WorkerLostError) and self.args:
            try:
                jobstore.record_worker_death(get_settings(), self.table, self.args[0], str(exc))
            except Exception:  # the store is down: the death still counts, only its reason is lost
                log.warning("cannot note the worker's death on %s", self.args[0], exc_info=True)
        return super().on_failure(exc_info, send_failed_event, return_ok)


