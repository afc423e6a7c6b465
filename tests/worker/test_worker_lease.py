"""What a worker holds its work with (worker/lease.py): the lease renewed from a side thread, cancellation turned
into ``should_stop``, and the fence asked before each write."""

from __future__ import annotations

import time

import pytest
from worker_fixtures import claimed_job, store_with_scene

from app.core import jobstore
from app.core.settings import Settings
from worker.lease import Lease


@pytest.fixture
def settings(tmp_path) -> Settings:
    return store_with_scene(tmp_path, heartbeat_s=0.05)


def test_lease_renews_and_reports_cancellation(settings):
    job = claimed_job(settings)
    before = jobstore.JOBS.get(settings, job.id).heartbeat_at
    with Lease(settings, job.id, job.attempt) as lease:
        time.sleep(0.2)
        assert not lease.should_stop()
        jobstore.JOBS.request_cancel(settings, job.id)
        deadline = time.monotonic() + 5
        while not lease.should_stop() and time.monotonic() < deadline:
            time.sleep(0.02)
        assert lease.cancelled.is_set() and not lease.lost.is_set()
    assert jobstore.JOBS.get(settings, job.id).heartbeat_at > before


def test_the_fence_says_no_for_a_stale_attempt_and_for_a_store_that_cannot_answer(settings):
    job = claimed_job(settings)
    assert Lease(settings, job.id, job.attempt).still_owned()
    stale = Lease(settings, job.id, job.attempt - 1)
    assert not stale.still_owned() and stale.lost.is_set() and stale.should_stop()

    def unreachable(*_args):
        raise ConnectionError("database down")

    down = Lease(settings, job.id, job.attempt, renew=unreachable)
    assert not down.still_owned() and down.lost.is_set()
