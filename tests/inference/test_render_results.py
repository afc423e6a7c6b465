"""The render-result transport (app/core/render_results.py): from a render worker back to the waiting API,
through files in ``render-results/`` (embedded broker) or a Redis list (``VOXNERF_BROKER_URL=redis://``)."""

from __future__ import annotations

import os
import shutil
import threading
import time

import pytest
from service_fixtures import start_redis

from app.core import render_results
from app.core.render_results import RenderOutcome, deliver_outcome, receive_outcome, remove_old_outcomes
from app.core.settings import Settings

IMAGE = b"\x89PNG\r\n\x1a\n" + bytes(range(256)) * 40  # holds newlines: only the first one splits header/data


def test_the_header_round_trips_without_the_image():
    outcome = RenderOutcome(200, "image/png", IMAGE)
    header = outcome.header()
    assert b"\n" not in header and IMAGE not in header
    assert RenderOutcome.from_parts(header, IMAGE) == outcome
    error = RenderOutcome(422, detail="width, height: 9x9 exceeds the limit of 10 pixels")
    assert RenderOutcome.from_parts(error.header(), None) == error


@pytest.fixture
def embedded(tmp_path) -> Settings:
    settings = Settings(data_dir=tmp_path / "data")
    settings.make_dirs()
    return settings


def test_embedded_outcome_is_delivered_as_files_and_consumed(embedded):
    outcome = RenderOutcome(200, "image/x-exr", IMAGE)
    deliver_outcome(embedded, "r1", outcome)
    assert sorted(p.name for p in embedded.render_results_dir.iterdir()) == ["r1.json", "r1.out"]
    assert receive_outcome(embedded, "r1", timeout_s=5) == outcome
    assert not list(embedded.render_results_dir.iterdir())  # the API removed both files


def test_embedded_receiver_waits_for_the_marker(embedded):
    later = threading.Timer(0.3, deliver_outcome, (embedded, "r2", RenderOutcome(409, detail="not finished")))
    later.start()
    try:
        started = time.monotonic()
        got = receive_outcome(embedded, "r2", timeout_s=10)
    finally:
        later.join()
    assert got == RenderOutcome(409, detail="not finished")
    assert time.monotonic() - started >= 0.25


def test_embedded_receiver_times_out_with_none(embedded):
    assert receive_outcome(embedded, "never", timeout_s=0.1) is None


def test_uncollected_outcomes_are_swept(embedded):
    deliver_outcome(embedded, "old", RenderOutcome(200, "image/png", IMAGE))
    deliver_outcome(embedded, "new", RenderOutcome(200, "image/png", IMAGE))
    past = time.time() - 3600
    for name in ("old.json", "old.out"):
        os.utime(embedded.render_results_dir / name, (past, past))
    assert remove_old_outcomes(embedded.render_results_dir, older_than_s=60) == 2
    assert sorted(p.name for p in embedded.render_results_dir.iterdir()) == ["new.json", "new.out"]


@pytest.fixture(scope="module")
def redis_url(tmp_path_factory):
    if shutil.which("redis-server") is None:
        pytest.skip("redis-server is not installed (scripts/install.sh installs it)")
    server = start_redis(tmp_path_factory.mktemp("redis"))
    try:
        yield server.url
    finally:
        server.stop()


def test_redis_outcome_travels_through_one_expiring_list_item(redis_url, tmp_path):
    # a separate data directory: with Redis the API and its render workers need no directory in common
    worker = Settings(data_dir=tmp_path / "worker", broker_url=redis_url, render_timeout_s=30)
    api = Settings(data_dir=tmp_path / "api", broker_url=redis_url, render_timeout_s=30)
    outcome = RenderOutcome(200, "image/png", IMAGE)
    deliver_outcome(worker, "r3", outcome)
    client = render_results._redis(redis_url)
    key = render_results.redis_key("r3")
    assert client.llen(key) == 1
    assert 30 < client.ttl(key) <= 30 + render_results.REDIS_EXPIRY_MARGIN_S
    assert receive_outcome(api, "r3", timeout_s=5) == outcome
    assert not client.exists(key)
    deliver_outcome(worker, "r4", RenderOutcome(500, detail="render failed"))
    assert receive_outcome(api, "r4", timeout_s=5) == RenderOutcome(500, detail="render failed")


def test_redis_receiver_times_out_with_none(redis_url, tmp_path):
    api = Settings(data_dir=tmp_path / "api", broker_url=redis_url)
    started = time.monotonic()
    assert receive_outcome(api, "never", timeout_s=0.3) is None
    assert time.monotonic() - started < 3
