"""What a worker holds its work with (worker/lease.py): the lease renewed from a side thread, cancellation turned
into ``should_stop``, and the fence asked before each write."""

from __future__ import annotations

import time

import pytest

from app.core import jobstore
from app.core.settings import Settings
from worker.lease import Lease

SCENE = "a" * 32


@pytest.fixture
def settings(tmp_path) -> Settings:
    s = Settings(data_dir=tmp_path / "data", heartbeat_s=0.05)
    s.make_dirs()
    (s.scenes_dir / SCENE).mkdir()
    jobstore.add_scene(s, SCENE, "room", {"frames": 1}, 10)
    return s


def _claimed(settings: Settings) -> jobstore.JobRow:
    job = jobstore.create_job(settings, SCENE, {"max_iters": 50, "compile": False})
    return jobstore.claim_job(settings, job.id, jobstore.worker_identity())


def test_lease_renews_and_reports_cancellation(settings):
    job = _claimed(settings)
    before = jobstore.get_job(settings, job.id).heartbeat_at
    with Lease(settings, job.id, job.attempt) as lease:
        time.sleep(0.2)
        assert not lease.should_stop()
        jobstore.request_cancel(settings, job.id)
        deadline = time.monotonic() + 5
        while not lease.should_stop() and time.monotonic() < deadline:
            time.sleep(0.02)
        assert lease.cancelled.is_set() and not lease.lost.is_set()
    assert jobstore.get_job(settings, job.id).heartbeat_at > before


def test_the_fence_says_no_for_a_stale_attempt_and_for_a_store_that_cannot_answer(settings):
    job = _claimed(settings)
    assert Lease(settings, job.id, job.attempt).still_owned()
    stale = Lease(settings, job.id, job.attempt - 1)
    assert not stale.still_owned() and stale.lost.is_set() and stale.should_stop()

    def unreachable(*_args):
        raise ConnectionError("database down")

    down = Lease(settings, job.id, job.attempt, renew=unreachable)
    assert not down.still_owned() and down.lost.is_set()
