"""The parts of ``GET /metrics`` and of the JSON logs on their own: the job store's metrics from rows of known
times and stage records (bucket counts, NaN stage seconds left out), the broker's queue depth on the embedded
broker and on a real redis-server, a GPU worker's report from ``nvidia-smi``'s output, and the JSON formatter
(one object per line, work ids, credentials masked in messages and tracebacks)."""

from __future__ import annotations

import json
import logging
import math
import stat

from prometheus_client.parser import text_string_to_metric_families
from service_fixtures import start_redis

from app.core.celery_app import create_celery
from app.core.db import session_scope
from app.core.jobstore import JOBS
from app.core.log_format import JsonFormatter, work_ids
from app.core.metrics import ApiMetrics, QueueCollector, StoreCollector, scrape
from app.core.models import ImportRow, JobRow
from app.core.outputs import OUTPUTS
from app.core.progress import initial_values
from app.core.redact import install_log_masking
from app.core.settings import Settings
from app.routes.health import check_health
from worker.device_report import device_report, gpu_index, parse_smi_memory


def _settings(tmp_path) -> Settings:
    settings = Settings(data_dir=tmp_path / "data", device="cpu", health_timeout_s=0.2)
    settings.make_dirs()
    return settings


def _job(i: int, state: str, seconds: float | None, stages: list | None = None) -> JobRow:
    row = JOBS.new_row(f"{i:032x}", scene_id="a" * 32, options={}, **initial_values())
    row.state = state
    if seconds is not None:
        row.started_at, row.finished_at = 1000.0, 1000.0 + seconds
    row.stages = stages or []
    return row


def _samples(collector) -> dict[tuple[str, tuple], float]:
    return {(s.name, tuple(sorted(s.labels.items()))): s.value
            for family in collector.collect() for s in family.samples}


def test_the_store_metrics_count_and_bucket_finished_work(tmp_path):
    settings = _settings(tmp_path)
    stages = [{"name": "load", "ran": True, "why": "", "seconds": 0.3},
              {"name": "prior", "ran": False, "why": "none", "seconds": 0.0},
              {"name": "train", "ran": True, "why": "", "seconds": math.nan}]
    with session_scope(settings) as session:
        session.add_all([_job(1, "succeeded", 3.0, stages), _job(2, "succeeded", 40.0),
                         _job(3, "failed", 4000.0), _job(4, "running", None)])
        video = OUTPUTS.new_row("b" * 32, job_id="1" * 32, kind="video", params={}, partial=False)
        video.state, video.started_at, video.finished_at = "succeeded", 10.0, 12.5
        session.add(video)
        session.add(ImportRow(id="c" * 32, name="bag", layout="rosbag", state="queued", params={}, size_bytes=1,
                              created_at=1.0))
    samples = _samples(StoreCollector(settings))
    assert samples[("voxnerf_jobs", (("kind", "train"), ("state", "succeeded")))] == 2
    assert samples[("voxnerf_jobs", (("kind", "train"), ("state", "running")))] == 1
    assert samples[("voxnerf_jobs", (("kind", "video"), ("state", "succeeded")))] == 1
    assert samples[("voxnerf_jobs", (("kind", "mesh"), ("state", "queued")))] == 0
    assert samples[("voxnerf_jobs", (("kind", "import"), ("state", "queued")))] == 1
    train_ok = (("kind", "train"), ("state", "succeeded"))
    assert samples[("voxnerf_job_duration_seconds_bucket", (("kind", "train"), ("le", "1.0"), train_ok[1]))] == 0
    assert samples[("voxnerf_job_duration_seconds_bucket", (("kind", "train"), ("le", "5.0"), train_ok[1]))] == 1
    assert samples[("voxnerf_job_duration_seconds_bucket", (("kind", "train"), ("le", "60.0"), train_ok[1]))] == 2
    assert samples[("voxnerf_job_duration_seconds_count", train_ok)] == 2
    assert samples[("voxnerf_job_duration_seconds_sum", train_ok)] == 43.0
    assert samples[("voxnerf_job_duration_seconds_sum", (("kind", "train"), ("state", "failed")))] == 4000.0
    assert samples[("voxnerf_job_duration_seconds_sum", (("kind", "video"), ("state", "succeeded")))] == 2.5
    # stages: the one that ran with finite seconds; one that did not run and one with NaN seconds are left out
    stage_counts = {k: v for k, v in samples.items() if k[0] == "voxnerf_stage_duration_seconds_count"}
    assert stage_counts == {("voxnerf_stage_duration_seconds_count", (("stage", "load"),)): 1}


def test_queue_depth_counts_the_messages_the_embedded_broker_holds(tmp_path):
    settings = _settings(tmp_path)
    celery = create_celery(settings)
    for _ in range(3):
        celery.send_task("voxnerf.output", args=["d" * 32])
    samples = _samples(QueueCollector(settings, celery))
    assert samples == {("voxnerf_queue_messages", (("queue", q),)): n for q, n in
                       (("train", 0), ("render", 0), ("outputs", 3))}


def test_queue_depth_counts_the_messages_redis_holds(tmp_path):
    redis = start_redis(tmp_path / "redis")
    try:
        settings = Settings(data_dir=tmp_path / "data", device="cpu", broker_url=redis.url)
        celery = create_celery(settings)
        for queue_task, n in (("voxnerf.train", 2), ("voxnerf.output", 1)):
            for _ in range(n):
                celery.send_task(queue_task, args=["d" * 32])
        samples = _samples(QueueCollector(settings, celery))
    finally:
        redis.stop()
    assert samples == {("voxnerf_queue_messages", (("queue", q),)): n for q, n in
                       (("train", 2), ("render", 0), ("outputs", 1))}


def test_the_exposition_parses_and_has_no_device_memory_without_reports(tmp_path):
    settings = _settings(tmp_path)
    celery = create_celery(settings)
    api = ApiMetrics()
    api.upload_bytes.inc(1234)
    api.render_seconds.labels(status="200").observe(0.3)
    text = scrape(settings, celery, api, check_health(settings, celery), devices={}).decode()
    names = {family.name for family in text_string_to_metric_families(text)}
    assert {"voxnerf_jobs", "voxnerf_upload_bytes", "voxnerf_render_seconds", "voxnerf_workers", "voxnerf_up",
            "voxnerf_queue_messages", "voxnerf_job_duration_seconds", "voxnerf_stage_duration_seconds"} <= names
    assert not any(name.startswith("voxnerf_device") for name in names)
    assert "voxnerf_upload_bytes_total 1234.0" in text


def test_a_gpu_report_reads_nvidia_smi_and_the_cpu_reports_its_device_alone(tmp_path, monkeypatch):
    assert gpu_index("cpu") is None and gpu_index("cuda") == 0 and gpu_index("cuda:2") == 2 and gpu_index("auto") == 0
    assert parse_smi_memory("1024, 2048\n") == (1024 * 2**20, 2048 * 2**20)
    for bad in ("", "N/A, N/A", "12"):
        try:
            parse_smi_memory(bad)
        except (ValueError, IndexError):
            continue
        raise AssertionError(f"{bad!r} parsed")
    assert device_report("cpu") == {"device": "cpu"}
    monkeypatch.setenv("PATH", str(tmp_path))  # no nvidia-smi: a GPU's memory cannot be read
    assert device_report("auto") == {"device": "cpu"}
    assert device_report("cuda:1") == {"device": "cuda:1"}
    smi = tmp_path / "nvidia-smi"  # the driver's tool (this machine has no GPU): failing, then answering
    smi.write_text("#!/bin/sh\nexit 9\n")
    smi.chmod(smi.stat().st_mode | stat.S_IXUSR)
    assert device_report("cuda:0") == {"device": "cuda:0"}
    smi.write_text('#!/bin/sh\n[ "$1" = "--id=1" ] && echo "100, 200"\n')
    assert device_report("cuda:1") == {"device": "cuda:1", "memory_used_bytes": 100 * 2**20,
                                       "memory_total_bytes": 200 * 2**20}


def test_json_lines_name_the_work_and_mask_credentials():
    install_log_masking()
    formatter = JsonFormatter()
    logger = logging.getLogger("voxnerf.test.json")

    def line(*args, **kwargs) -> dict:
        record = logger.makeRecord(logger.name, logging.WARNING, __file__, 1, *args, **kwargs)
        text = formatter.format(record)
        assert "\n" not in text
        return json.loads(text)

    plain = line("broker %s unreachable\nretrying", ("redis://:s3cret@cache:6379/0",), None)
    assert plain["level"] == "WARNING" and plain["logger"] == "voxnerf.test.json"
    assert "s3cret" not in plain["message"] and "redis://:***@cache:6379/0" in plain["message"]
    assert plain["time"].endswith("+00:00") and "job_id" not in plain
    with work_ids(job_id="e" * 32):
        assert line("step", (), None)["job_id"] == "e" * 32
        assert line("out", (), None, extra={"output_id": "f" * 32})["output_id"] == "f" * 32
    try:
        raise RuntimeError("cannot reach s3://key:hunter2@bucket/scenes")
    except RuntimeError:
        import sys

        failed = line("upload failed", (), sys.exc_info())
    assert "RuntimeError" in failed["exception"] and "hunter2" not in json.dumps(failed)


def test_upload_bytes_are_those_of_uploads_and_upload_session_parts():
    from app.main import is_upload

    assert is_upload("POST", "/scenes") and is_upload("PUT", f"/uploads/{'a' * 32}/parts/3")
    assert not any(is_upload(m, p) for m, p in (("GET", "/scenes"), ("POST", "/uploads"), ("POST", "/render"),
                                                 ("POST", f"/uploads/{'a' * 32}/complete")))


def test_a_broker_the_health_check_found_down_is_not_read(tmp_path):
    """Redis down (nothing listens on the port): the scrape answers at once, with voxnerf_up{component="broker"} 0
    and no queue depth, instead of waiting for connection attempts per queue."""
    import time

    from service_fixtures import free_port

    settings = Settings(data_dir=tmp_path / "data", device="cpu", health_timeout_s=0.2,
                        broker_url=f"redis://127.0.0.1:{free_port()}/0")
    settings.make_dirs()
    celery = create_celery(settings)
    health = check_health(settings, celery)
    started = time.monotonic()
    text = scrape(settings, celery, ApiMetrics(), health, devices={}).decode()
    assert time.monotonic() - started < 5  # reading the three queues would try to connect for seconds each
    assert 'voxnerf_up{component="broker"} 0.0' in text and "voxnerf_queue_messages" not in text


def test_a_job_store_that_cannot_be_read_leaves_the_rest_of_the_scrape(tmp_path):
    settings = Settings(data_dir=tmp_path / "data", device="cpu",
                        database_url=f"sqlite:///{tmp_path}/no-such-directory/voxnerf.sqlite")
    assert list(StoreCollector(settings).collect()) == []  # logged, not raised
