"""The viewer's scene reads are bounded (issue #42, item 4): ``GET /jobs/{id}/cameras`` and ``/prior-preview`` read
a scene in a child process under an upload validation's memory limit, at most ``max_concurrent_scene_reads`` at
once (more: 429 with Retry-After), one read per scene shared by the requests that come while it runs, cached by
scene (two jobs on one scene share it).

Concurrency is tested over real HTTP against a uvicorn API: the forkserver that starts the API's children is
stopped (SIGSTOP), so the first read of a scene stays in flight for as long as the test wants, and continued
(SIGCONT) once the other requests have arrived. Today's code started one child per request with no limit: the
request for a second scene then waited on the stopped forkserver too instead of being refused.
"""

from __future__ import annotations

import os
import shutil
import signal
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import pytest
from fastapi.testclient import TestClient
from service_fixtures import Service, start_service, upload_scene, wait_for

from app.core import jobstore
from app.core.settings import Settings
from app.main import create_app

SETTLE_S = 2.0  # time for requests already sent to reach their thread (they then wait on the stopped forkserver)


def _forkserver_of(service: Service) -> int:
    """The pid of the API process's multiprocessing forkserver (its child running ``forkserver ... main``)."""
    api = service.procs["api"].pid

    def find() -> int | None:
        for entry in Path("/proc").iterdir():
            if not entry.name.isdigit():
                continue
            try:
                ppid = int((entry / "stat").read_text().rsplit(")", 1)[1].split()[1])
                cmdline = (entry / "cmdline").read_bytes()
            except (OSError, IndexError, ValueError):
                continue
            if ppid == api and b"forkserver" in cmdline:
                return int(entry.name)
        return None

    return wait_for(find, 30, "the API's forkserver")


@pytest.fixture(scope="module")
def service(tmp_path_factory) -> Service:
    svc = start_service(tmp_path_factory.mktemp("viewer-bounds"), workers=False,
                        settings={"VOXNERF_MAX_CONCURRENT_SCENE_READS": "1", "OMP_NUM_THREADS": "1"})
    yield svc
    svc.stop()


@pytest.fixture(scope="module")
def jobs(service, small_room) -> dict[str, str]:
    """Two jobs on scene ``a`` and one on scene ``b`` (queued: the viewer needs no worker). The uploads start
    the forkserver."""
    store = Settings(_env_file=None, data_dir=service.data_dir)
    with service.client() as client:
        scenes = {name: upload_scene(client, small_room)["id"] for name in ("a", "b")}
    return {name: jobstore.create_job(store, scenes[name[0]], {"max_iters": 1}).id for name in ("a1", "a2", "b")}


def test_one_read_per_scene_is_shared_and_another_scene_waits_for_a_free_slot(service, jobs):
    forkserver = _forkserver_of(service)
    urls = [f"/jobs/{jobs['a1']}/cameras"] * 3 + [f"/jobs/{jobs['a2']}/cameras", f"/jobs/{jobs['a1']}/prior-preview"]
    os.kill(forkserver, signal.SIGSTOP)
    try:
        with service.client(timeout_s=120) as client, ThreadPoolExecutor(len(urls)) as pool:
            first = pool.submit(client.get, urls[0])  # takes the one slot, its child waits on the forkserver
            time.sleep(SETTLE_S)
            others = [pool.submit(client.get, url) for url in urls[1:]]  # the same scene: they wait for its read
            time.sleep(SETTLE_S)
            with service.client(timeout_s=30) as other_client:
                refused = other_client.get(f"/jobs/{jobs['b']}/cameras")  # another scene: no slot is free
            assert refused.status_code == 429, refused.text
            assert "VOXNERF_MAX_CONCURRENT_SCENE_READS" in refused.json()["detail"]
            assert refused.headers["Retry-After"] == "1"
            assert not first.done() and not any(f.done() for f in others)  # all still wait on the one read
            os.kill(forkserver, signal.SIGCONT)
            answers = [first.result(), *(f.result() for f in others)]
    finally:
        os.kill(forkserver, signal.SIGCONT)
    assert [a.status_code for a in answers] == [200] * len(urls), [a.text for a in answers]
    cameras = [a.json() for a in answers[:4]]
    poses = [[frame["transform_matrix"] for frame in c["frames"]] for c in cameras]
    assert poses[0] and all(p == poses[0] for p in poses)  # one read, shared by both jobs of scene a
    assert {c["job_id"] for c in cameras} == {jobs["a1"], jobs["a2"]}
    assert answers[4].json()["total"] > 0
    with service.client() as client:
        assert client.get(f"/jobs/{jobs['b']}/cameras").status_code == 200  # the slot is free again


def test_a_scene_read_runs_under_the_upload_validations_memory_limit(tmp_path, small_room):
    """A scene whose read would need more than ``upload_validation_memory_bytes`` is a 503 naming the setting
    (today's child had no limit: a scene near the upload limits parsed to over a gigabyte per child)."""
    settings = Settings(_env_file=None, data_dir=tmp_path / "data", device="cpu", sweep_interval_s=3600,
                        upload_validation_memory_bytes=1024 * 1024)
    with TestClient(create_app(settings)) as client:
        scene_id = jobstore.new_id()
        shutil.copytree(small_room, settings.scenes_dir / scene_id)
        jobstore.add_scene(settings, scene_id, "room", {"frames": 1}, 1)
        job_id = jobstore.create_job(settings, scene_id, {"max_iters": 1}).id
        response = client.get(f"/jobs/{job_id}/cameras")
        assert response.status_code == 503, response.text
        assert "VOXNERF_UPLOAD_VALIDATION_MEMORY_BYTES" in response.json()["detail"]
        roomy = settings.model_copy(update={"upload_validation_memory_bytes": 4096 * 1024 * 1024})
    with TestClient(create_app(roomy)) as client:
        assert client.get(f"/jobs/{job_id}/cameras").status_code == 200
