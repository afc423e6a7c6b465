"""A disk that fills up while a job trains (issue #42, item 6): the job keeps its last good checkpoint.

Real processes on loopback: a uvicorn API and a Celery train worker (``python -m worker``). Filling a real
filesystem needs root (no tmpfs, no loop device here), so the worker starts with a ``sitecustomize`` module on
its ``PYTHONPATH`` that makes the write call fail as a full disk does: ``os.fsync`` of a checkpoint's temporary
file raises ``OSError(ENOSPC)`` once ``ALLOWED`` checkpoints were written (counted in a file, across
processes). Everything else is the real worker: the trainer's atomic write, the task's handling, the job store.

- the first job writes one checkpoint, then its next one fails: it ends ``cancelled`` (never ``failed``) with
  an ``error`` naming the full disk and the iteration kept, its ``checkpoint.pt`` is that iteration's and loads,
  no temporary file is left, and a video of it is accepted (partial);
- the second job's first checkpoint already fails: it ends ``failed``, saying nothing was kept.
"""

from __future__ import annotations

import errno
from collections.abc import Iterator

import pytest
from service_fixtures import Service, start_service, upload_scene, wait_for, wait_until_final
from synthetic_fixtures import make_micro_scene

from voxnerf.files import CHECKPOINT
from voxnerf.training.checkpoint import load_checkpoint
from worker.disk_full import disk_full_cause

pytestmark = pytest.mark.slow

JOB_TIMEOUT_S = 300
OPTIONS = {"max_iters": 60, "compile": False, "downscale": 2}
FULL_DISK = '''
import errno
import os
from pathlib import Path

_COUNT = Path({count!r})
_ALLOWED = {allowed}
_real_fsync = os.fsync


def _fsync(fd):
    try:
        name = os.readlink(f"/proc/self/fd/{{fd}}")
    except OSError:
        name = ""
    base = os.path.basename(name)
    if base.startswith(".checkpoint.pt.") and base.endswith(".tmp"):
        written = int(_COUNT.read_text()) if _COUNT.exists() else 0
        if written >= _ALLOWED:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), name)
        _real_fsync(fd)
        _COUNT.write_text(str(written + 1))
        return None
    return _real_fsync(fd)


os.fsync = _fsync
'''
ALLOWED = 1


@pytest.fixture(scope="module")
def service(tmp_path_factory) -> Iterator[Service]:
    root = tmp_path_factory.mktemp("disk-full")
    inject = root / "inject"
    inject.mkdir()
    (inject / "sitecustomize.py").write_text(FULL_DISK.format(count=str(root / "checkpoints-written"),
                                                              allowed=ALLOWED))
    svc = start_service(root / "service", workers=False,
                        settings={"VOXNERF_CHECKPOINT_EVERY_S": "0.2", "OMP_NUM_THREADS": "1"})
    try:
        svc.env["PYTHONPATH"] = f"{inject}:{svc.env['PYTHONPATH']}"  # the worker only: the API writes no checkpoint
        svc.start_worker("train")
        wait_for(lambda: "ready" in (svc.root / "worker-train.log").read_text(errors="replace"), 120,
                 "the train worker to be ready")
    except BaseException:
        svc.stop()
        raise
    yield svc
    svc.stop()


def test_a_full_disk_keeps_the_last_checkpoint_and_the_job_renderable(service, tmp_path_factory):
    with service.client() as client:
        scene_id = upload_scene(client, make_micro_scene(tmp_path_factory, "disk-full-scene"))["id"]
        response = client.post(f"/scenes/{scene_id}/jobs", json=OPTIONS)
        assert response.status_code == 202, response.text
        job = wait_until_final(service, client, f"/jobs/{response.json()['id']}", JOB_TIMEOUT_S)
        assert job["state"] == "cancelled", f"{job['state']}: {job['error']}\n{service.logs()}"
        assert "the disk filled up" in job["error"] and "No space left on device" in job["error"], job["error"]
        run_dir = service.data_dir / "runs" / job["id"]
        kept = load_checkpoint(run_dir / CHECKPOINT)
        assert f"last checkpoint (iteration {kept['iteration']}) kept" in job["error"]
        assert job["iteration"] == kept["iteration"] >= 1
        assert not [p.name for p in run_dir.iterdir() if p.name.endswith(".tmp")]  # the failed write left nothing
        assert str(service.data_dir) not in job["error"]  # no server path in what clients read
        video = client.post(f"/jobs/{job['id']}/videos", json={"path": "orbit", "frames": 2, "width": 16,
                                                               "height": 12})
        assert video.status_code == 202, video.text
        assert video.json()["partial"] is True

        second = client.post(f"/scenes/{scene_id}/jobs", json=OPTIONS)
        assert second.status_code == 202, second.text
        failed = wait_until_final(service, client, f"/jobs/{second.json()['id']}", JOB_TIMEOUT_S)
    assert failed["state"] == "failed", f"{failed['state']}: {failed['error']}\n{service.logs()}"
    assert "before its first checkpoint: nothing is kept" in failed["error"], failed["error"]
    assert not (service.data_dir / "runs" / failed["id"] / CHECKPOINT).exists()


def test_the_full_disk_is_found_behind_a_wrapping_error():
    full = OSError(errno.ENOSPC, "No space left on device")
    try:
        try:
            raise full
        except OSError as err:
            raise RuntimeError("writing the report failed") from err
    except RuntimeError as wrapped:
        assert disk_full_cause(wrapped) is full
    assert disk_full_cause(OSError(errno.EDQUOT, "Disk quota exceeded")).errno == errno.EDQUOT
    assert disk_full_cause(OSError(errno.EACCES, "Permission denied")) is None
    assert disk_full_cause(ValueError("no")) is None
