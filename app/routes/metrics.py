"""``GET /metrics``: the service's metrics in Prometheus' text format (:mod:`app.core.metrics` says what each is).

Behind the token like every other route (a scrape config sends it: docs/integration.md, "Metrics"). A scrape reads the
job store and the broker's queues, takes the health check's view of the workers (the check of ``/healthz``: at most
``VOXNERF_HEALTH_CACHE_S`` old, else one runs, up to about 2 x ``VOXNERF_HEALTH_TIMEOUT_S``), and asks those workers
for their device memory (one broadcast that ends when they have all answered).
"""

from __future__ import annotations

from fastapi import APIRouter, Request, Response
from fastapi.concurrency import run_in_threadpool
from prometheus_client import CONTENT_TYPE_LATEST

from app.core.metrics import device_reports, scrape
from app.core.settings import Settings
from app.routes.health import health_probe

router = APIRouter(tags=["metrics"])
EXAMPLE = """# HELP voxnerf_jobs work in the job store by kind (train, video, mesh, pointcloud, import) and state
# TYPE voxnerf_jobs gauge
voxnerf_jobs{kind="train",state="succeeded"} 12.0
voxnerf_jobs{kind="train",state="running"} 1.0
# HELP voxnerf_queue_messages messages waiting in a broker queue, not yet taken by a worker
# TYPE voxnerf_queue_messages gauge
voxnerf_queue_messages{queue="train"} 3.0
"""


@router.get(
    "/metrics",
    response_class=Response,
    responses={200: {"content": {CONTENT_TYPE_LATEST: {"example": EXAMPLE}},
                     "description": "every metric, Prometheus text format 0.0.4"}},
    summary="Metrics in Prometheus' text format (jobs, queues, durations, renders, workers, uploads)",
)
async def metrics(request: Request) -> Response:
    """Jobs by kind and state, messages waiting per queue, durations of finished work and of training stages,
    render latency and upload bytes of this API process, live workers per queue, whether the database and the
    broker answer, and the memory of the workers' GPUs (absent on CPU workers). Names start with ``voxnerf_``;
    docs/service.md lists them."""
    settings: Settings = request.app.state.settings
    health = await health_probe(request).recent(settings.health_cache_s)
    workers = [name for names in (health.workers or {}).values() for name in names]
    celery = request.app.state.celery
    devices = await run_in_threadpool(device_reports, celery, workers, settings.health_timeout_s)
    body = await run_in_threadpool(scrape, settings, celery, request.app.state.metrics, health, devices)
    return Response(body, media_type=CONTENT_TYPE_LATEST)
