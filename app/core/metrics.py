"""What ``GET /metrics`` exposes, in Prometheus' text format (``prometheus-client``), every name prefixed ``voxnerf_``.

Two sources:

- **Read at scrape time** (:func:`scrape`), so that every API process answers the same whatever process did the
  work: the job store (work by kind and state, durations of finished work and of training stages:
  :class:`StoreCollector`), the broker's queues (messages waiting: :func:`app.core.dispatch.waiting_messages`), and
  a health check's view of the workers (:class:`WorkersCollector`, with the device memory the workers report).
- **Counted in this API process** (:class:`ApiMetrics`): render latency of ``POST /render`` and the bytes uploads
  sent. Each API process counts its own; a deployment with several scrapes each one (Prometheus sums them).

No torch here: device memory comes from the workers (``worker/device_report.py``).
"""

from __future__ import annotations

import logging
import math
from collections.abc import Iterable, Iterator, Sequence
from typing import Any

from celery import Celery
from prometheus_client import CollectorRegistry, Counter, Histogram, generate_latest
from prometheus_client.core import GaugeMetricFamily, HistogramMetricFamily, Metric
from prometheus_client.registry import Collector
from prometheus_client.utils import floatToGoString
from sqlalchemy import func, select

from app.core.celery_app import DEVICE_REPORT, QUEUES
from app.core.db import session_scope
from app.core.dispatch import waiting_messages
from app.core.models import JOB_STATES, ImportRow, JobRow, OutputRow
from app.core.settings import Settings

log = logging.getLogger(__name__)

PREFIX = "voxnerf_"
FINAL_STATES = ("succeeded", "failed", "cancelled")
# Seconds. Work runs from seconds (a small export) to a day (VOXNERF_MAX_JOB_SECONDS); a stage from well under a
# second (loading a small scene) to hours; a render from tens of milliseconds (a small GPU view) to minutes (a large
# CPU one, up to VOXNERF_RENDER_TIMEOUT_S).
WORK_BUCKETS = (1, 5, 15, 30, 60, 120, 300, 600, 1800, 3600, 7200, 21600, 86400)
STAGE_BUCKETS = (0.1, 0.5, 1, 5, 15, 30, 60, 300, 900, 3600, 14400)
RENDER_BUCKETS = (0.05, 0.1, 0.25, 0.5, 1, 2.5, 5, 10, 30, 60, 120)


class ApiMetrics:
    """The metrics this API process counts itself, in their own registry (one per app)."""

    def __init__(self) -> None:
        self.registry = CollectorRegistry(auto_describe=True)
        self.render_seconds = Histogram(
            f"{PREFIX}render_seconds", "POST /render: seconds from taking a render slot to the answer, by HTTP status",
            ["status"], buckets=RENDER_BUCKETS, registry=self.registry)
        self.upload_bytes = Counter(
            f"{PREFIX}upload_bytes", "bytes of upload bodies (POST /scenes, upload session parts) received by this API "
            "process",
            registry=self.registry)


def _finite(value: Any) -> bool:
    """Whether ``value`` is a finite number (a stage record's seconds may be null, or NaN from an old run)."""
    return isinstance(value, int | float) and not isinstance(value, bool) and math.isfinite(value)


def _histogram(name: str, documentation: str, labels: Sequence[str], buckets: Sequence[float],
               samples: dict[tuple[str, ...], list[float]]) -> HistogramMetricFamily:
    """A histogram family of ``samples`` (label values -> observed values), cumulative over ``buckets``."""
    family = HistogramMetricFamily(name, documentation, labels=list(labels))
    for label_values, values in sorted(samples.items()):
        cumulative = [(floatToGoString(float(bound)), sum(1 for v in values if v <= bound)) for bound in buckets]
        family.add_metric(list(label_values), [*cumulative, ("+Inf", len(values))], sum_value=math.fsum(values))
    return family


# The tables of work, and the kind their rows are counted as: a fixed one, or (None) the row's own ``kind`` column.
WORK_TABLES = ((JobRow, "train"), (OutputRow, None), (ImportRow, "import"))


class StoreCollector(Collector):
    """Work by kind and state, durations of finished work, and seconds per training stage, read from the job store
    at each scrape: one grouped count per table and one read of the finished rows' times and of the finished
    jobs' stage records (the cost grows with the rows kept)."""

    def __init__(self, settings: Settings) -> None:
        self.settings = settings

    def collect(self) -> Iterator[Metric]:
        try:
            counts, durations, stages = self._read()
        except Exception:  # the database is down: voxnerf_up says so; the rest of the scrape stands
            log.warning("metrics: cannot read the job store", exc_info=True)
            return

        work = GaugeMetricFamily(f"{PREFIX}jobs", "work in the job store by kind (train, video, mesh, pointcloud, "
                                 "import) and state", labels=["kind", "state"])
        for kind in ("train", "video", "mesh", "pointcloud", "import"):
            for state in JOB_STATES:
                work.add_metric([kind, state], counts.get((kind, state), 0))
        yield work
        yield _histogram(f"{PREFIX}job_duration_seconds", "seconds from start to end of finished work (train jobs, "
                         "outputs, imports), by kind and final state", ["kind", "state"], WORK_BUCKETS, durations)
        yield _histogram(f"{PREFIX}stage_duration_seconds", "seconds of each stage that ran in finished training "
                         "jobs (the stage records of their runs)", ["stage"], STAGE_BUCKETS, stages)

    def _read(self) -> tuple[dict, dict, dict]:
        """Counts by (kind, state), durations by (kind, state) and stage seconds by (stage,), from the store."""
        counts: dict[tuple[str, str], int] = {}
        durations: dict[tuple[str, str], list[float]] = {}
        stages: dict[tuple[str], list[float]] = {}
        with session_scope(self.settings) as session:
            for table, fixed_kind in WORK_TABLES:
                kind_columns = [] if fixed_kind else [table.kind]
                grouped = select(*kind_columns, table.state, func.count().label("n"))
                for row in session.execute(grouped.group_by(*kind_columns, table.state)):
                    counts[(fixed_kind or row.kind, row.state)] = row.n
                finished = select(*kind_columns, table.state, table.started_at, table.finished_at).where(
                    table.state.in_(FINAL_STATES), table.started_at.is_not(None), table.finished_at.is_not(None))
                for row in session.execute(finished):
                    seconds = max(0.0, row.finished_at - row.started_at)
                    durations.setdefault((fixed_kind or row.kind, row.state), []).append(seconds)
            for (records,) in session.execute(select(JobRow.stages).where(JobRow.state.in_(FINAL_STATES))):
                for record in records or []:
                    if isinstance(record, dict) and record.get("ran") and _finite(record.get("seconds")):
                        stages.setdefault((str(record.get("name")),), []).append(max(0.0, float(record["seconds"])))
        return counts, durations, stages


class QueueCollector(Collector):
    """Messages waiting in each broker queue (the embedded broker's files, or Redis' lists); nothing for a broker
    whose queues cannot be read, one the health check found down (``broker_up`` false: a scrape does not wait for
    its connection attempts), or when reading fails (logged)."""

    def __init__(self, settings: Settings, celery: Celery, broker_up: bool = True) -> None:
        self.settings = settings
        self.celery = celery
        self.broker_up = broker_up

    def collect(self) -> Iterator[Metric]:
        if not self.broker_up:
            return
        family = GaugeMetricFamily(f"{PREFIX}queue_messages", "messages waiting in a broker queue, not yet taken by "
                                   "a worker", labels=["queue"])
        for queue in QUEUES:
            try:
                messages = waiting_messages(self.settings, self.celery, queue)
            except Exception:  # the broker is down: the health metrics say so; the rest of the scrape stands
                log.warning("metrics: cannot read broker queue %s", queue, exc_info=True)
                return
            if messages is None:
                return
            family.add_metric([queue], len(messages))
        yield family


class WorkersCollector(Collector):
    """What a health check found (:func:`app.routes.health.check_health`): whether the database and the broker
    answer, live workers per queue; and the device memory each worker reported (absent for CPU workers)."""

    def __init__(self, health: Any, devices: dict[str, dict]) -> None:
        self.health = health
        self.devices = devices

    def collect(self) -> Iterator[Metric]:
        up = GaugeMetricFamily(f"{PREFIX}up", "1 when the component answered the last health check, else 0",
                               labels=["component"])
        for component in ("database", "broker"):
            check = getattr(self.health, component)
            up.add_metric([component], 1 if check is not None and check.ok else 0)
        yield up
        workers = GaugeMetricFamily(f"{PREFIX}workers", "live workers consuming a queue (answered the last health "
                                    "check)", labels=["queue"])
        found = self.health.workers or {}
        for queue in sorted(set(QUEUES) | set(found)):  # every queue, 0 where no worker answered
            workers.add_metric([queue], len(found.get(queue, [])))
        yield workers
        used = GaugeMetricFamily(f"{PREFIX}device_memory_used_bytes", "memory in use on a worker's GPU (every "
                                 "process on it, as its driver reports)", labels=["worker", "device"])
        total = GaugeMetricFamily(f"{PREFIX}device_memory_total_bytes", "memory of a worker's GPU",
                                  labels=["worker", "device"])
        for worker, report in sorted(self.devices.items()):
            if "memory_used_bytes" in report and "memory_total_bytes" in report:
                used.add_metric([worker, str(report["device"])], report["memory_used_bytes"])
                total.add_metric([worker, str(report["device"])], report["memory_total_bytes"])
        if used.samples:
            yield used
            yield total


def device_reports(celery: Celery, worker_names: Iterable[str], timeout_s: float) -> dict[str, dict]:
    """``{worker: report}`` of :data:`DEVICE_REPORT` from the named workers. The broadcast waits for their
    replies only (``limit``): one round trip, up to ``timeout_s`` when one of them does not answer."""
    names = sorted(set(worker_names))
    if not names:
        return {}
    try:
        replies = celery.control.broadcast(DEVICE_REPORT, reply=True, timeout=timeout_s, destination=names,
                                           limit=len(names)) or []
    except Exception:  # the broker is down: no device metrics this time
        log.warning("metrics: the workers' device reports could not be asked for", exc_info=True)
        return {}
    found = {}
    for reply in replies:
        for worker, report in reply.items():
            if isinstance(report, dict) and "device" in report:
                found[worker] = report
    return found


def scrape(settings: Settings, celery: Celery, api: ApiMetrics, health: Any, devices: dict[str, dict]) -> bytes:
    """The exposition of every metric: this process's (:class:`ApiMetrics`) and those read now (blocking: the job
    store and the broker's queues are read)."""
    registry = CollectorRegistry(auto_describe=False)
    broker_up = health.broker is not None and health.broker.ok
    for collector in (api.registry, StoreCollector(settings), QueueCollector(settings, celery, broker_up),
                      WorkersCollector(health, devices)):
        registry.register(collector)
    return generate_latest(registry)
