"""Disks that fill up (issue #42, item 6), on the API's side: the data directory's quota and the free-space
floor refuse an upload or an output with 507 and a JSON ``detail``, and a refused upload leaves nothing behind.

The quota is tested through real HTTP against a uvicorn API (``start_service`` without workers) whose
``VOXNERF_DATA_DIR_QUOTA_BYTES`` is 64 MiB: a filler file in its data directory takes the room, since the
API counts what the directory holds at each request. An upload with a ``Content-Length`` is refused before
its body is read; a chunked one (no declared length) once it is unpacked. The free-space floor and the
counting rules are tested directly (no filesystem here can be filled without root).
"""

from __future__ import annotations

import errno
import os
import shutil
import time
from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest
from service_fixtures import Service, start_service, zip_scene
from synthetic_fixtures import make_micro_scene

from app.core import jobstore
from app.core.db import session_scope
from app.core.disk_space import InsufficientStorage, directory_bytes, require_room
from app.core.models import JobRow, OutputRow, SceneRow
from app.core.settings import Settings
from app.schemas import JobOptions
from app.uploads import staging

MiB = 1024 * 1024
QUOTA = 64 * MiB


@pytest.fixture(scope="module")
def scene_zip(tmp_path_factory) -> bytes:
    return zip_scene(make_micro_scene(tmp_path_factory, "disk-space"))


@pytest.fixture(scope="module")
def service(tmp_path_factory) -> Iterator[Service]:
    svc = start_service(tmp_path_factory.mktemp("disk-space"), workers=False,
                        settings={"VOXNERF_DATA_DIR_QUOTA_BYTES": str(QUOTA)})
    yield svc
    svc.stop()


def _store(service: Service) -> Settings:
    return Settings(_env_file=None, data_dir=service.data_dir)


def _fill(service: Service, leave: int) -> Path:
    """A filler file that leaves ``leave`` bytes of the quota (negative: the directory is over it)."""
    filler = service.data_dir / "filler.bin"
    filler.unlink(missing_ok=True)
    size = QUOTA - directory_bytes(service.data_dir) - leave
    with open(filler, "wb") as out:
        out.truncate(size)  # the quota counts st_size, so a sparse file takes its room
    return filler


def _nothing_left_behind(service: Service, scenes_before: set[str]) -> None:
    assert not list((service.data_dir / "staging").iterdir())
    assert {p.name for p in (service.data_dir / "scenes").iterdir()} == scenes_before
    with session_scope(_store(service)) as session:
        assert {row.id for row in session.query(SceneRow)} == scenes_before


def _refused_for_quota(response: httpx.Response) -> None:
    assert response.status_code == 507, response.text
    detail = response.json()["detail"]
    assert "quota" in detail and "VOXNERF_DATA_DIR_QUOTA_BYTES" in detail, detail


def test_uploads_fit_the_quota_until_it_is_full(service, scene_zip):
    with service.client() as client:
        first = client.post("/scenes", files={"file": ("room.zip", scene_zip, "application/zip")})
        assert first.status_code == 201, first.text
        scenes = {first.json()["id"]}
        filler = _fill(service, leave=len(scene_zip) // 2)
        try:
            refused = client.post("/scenes", files={"file": ("room.zip", scene_zip, "application/zip")})
            _refused_for_quota(refused)
            _nothing_left_behind(service, scenes)
        finally:
            filler.unlink()
        again = client.post("/scenes", files={"file": ("room.zip", scene_zip, "application/zip")})
        assert again.status_code == 201, again.text


def test_a_chunked_upload_is_refused_once_unpacked(service, scene_zip):
    """No ``Content-Length``: the route cannot refuse it up front, the check after validation does."""
    boundary = "voxnerf-disk-test"
    body = (f"--{boundary}\r\nContent-Disposition: form-data; name=\"file\"; filename=\"room.zip\"\r\n"
            "Content-Type: application/zip\r\n\r\n").encode() + scene_zip + f"\r\n--{boundary}--\r\n".encode()

    def chunks() -> Iterator[bytes]:
        for start in range(0, len(body), 64 * 1024):
            yield body[start:start + 64 * 1024]

    scenes = {p.name for p in (service.data_dir / "scenes").iterdir()}
    filler = _fill(service, leave=len(scene_zip) // 2)
    try:
        with service.client() as client:
            refused = client.post("/scenes", content=chunks(),
                                  headers={"Content-Type": f"multipart/form-data; boundary={boundary}"})
        assert "content-length" not in {k.lower() for k in refused.request.headers}
        _refused_for_quota(refused)
        _nothing_left_behind(service, scenes)
    finally:
        filler.unlink()


def test_an_output_is_refused_when_the_quota_is_full(service):
    settings = _store(service)
    scene_id = next(p.name for p in (service.data_dir / "scenes").iterdir())
    options = JobOptions(max_iters=1).model_dump(exclude_none=True)  # as the route stores them
    job = jobstore.create_job(settings, scene_id, options)
    with session_scope(settings) as session:  # a trained job to render from (no worker runs here)
        row = session.get(JobRow, job.id)
        row.state, row.finished_at = "succeeded", time.time()
    filler = _fill(service, leave=-1024)  # over the quota: training runs grew past it (they are not refused)
    try:
        with service.client() as client:
            for path, body in ((f"/jobs/{job.id}/videos", {"path": "orbit", "frames": 4, "width": 16, "height": 12}),
                               (f"/jobs/{job.id}/exports", {"kind": "pointcloud"})):
                _refused_for_quota(client.post(path, json=body))
    finally:
        filler.unlink()
    with session_scope(settings) as session:
        assert session.query(OutputRow).count() == 0  # nothing was queued


def test_the_free_space_floor_refuses_with_the_setting_named(tmp_path):
    free = shutil.disk_usage(tmp_path).free
    settings = Settings(_env_file=None, data_dir=tmp_path, min_free_bytes=free + 1024**4)
    with pytest.raises(InsufficientStorage) as refused:
        require_room(settings, what="an upload")
    assert refused.value.status_code == 507 and "VOXNERF_MIN_FREE_BYTES" in refused.value.detail
    room = Settings(_env_file=None, data_dir=tmp_path, min_free_bytes=0)
    require_room(room, incoming_bytes=1024)  # room enough: no error
    with pytest.raises(InsufficientStorage, match="VOXNERF_MIN_FREE_BYTES"):  # what the request brings counts
        require_room(room, incoming_bytes=free + 1024**4)


def test_the_quota_counts_every_file_once_and_what_is_counted_apart(tmp_path):
    (tmp_path / "a" / "b").mkdir(parents=True)
    (tmp_path / "a" / "b" / "f").write_bytes(b"x" * 1000)
    (tmp_path / "g").write_bytes(b"y" * 500)
    (tmp_path / "link").symlink_to(tmp_path / "g")  # not followed: counted once
    assert directory_bytes(tmp_path) == 1500
    assert directory_bytes(tmp_path / "missing") == 0
    settings = Settings(_env_file=None, data_dir=tmp_path, min_free_bytes=0, data_dir_quota_bytes=2000)
    require_room(settings, incoming_bytes=500)
    with pytest.raises(InsufficientStorage, match="quota"):
        require_room(settings, incoming_bytes=501)
    require_room(settings, incoming_bytes=1500, counted_apart=1000)  # an upload's zip, gone once unpacked


def test_a_disk_that_fills_up_while_an_upload_is_written_is_a_507_leaving_nothing(tmp_path):
    """The write itself fails (ENOSPC from the copy into staging): 507, the staging directory removed."""
    settings = Settings(_env_file=None, data_dir=tmp_path / "data", min_free_bytes=0)

    def stage(root: Path):
        (root / "images").mkdir()
        (root / "images" / "0001.png").write_bytes(b"part of a file")
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(root / "images" / "0002.png"))

    with pytest.raises(InsufficientStorage) as refused:
        staging.store_scene(settings, "room", stage)
    assert refused.value.status_code == 507
    assert "disk filled up while the upload was stored (No space left on device)" in refused.value.detail
    assert str(tmp_path) not in refused.value.detail
    assert not list(settings.staging_dir.iterdir()) and not list(settings.scenes_dir.iterdir())
