"""Hostile and malformed input to the REST API: every refusal is a 4xx with a useful ``detail``, and a refused
upload stores nothing (no scene directory, no staging leftovers, no database row).

One API process over real HTTP (uvicorn on 127.0.0.1), token auth on, and no workers: nothing here trains.
"""

from __future__ import annotations

import io
import json
import stat
import struct
import zipfile
import zlib

import imageio.v3 as iio
import numpy as np
import pytest
from service_fixtures import Service, start_service, zip_scene

TOKEN = "s3cret-token"
MiB = 1024 * 1024
LIMITS = {
    "VOXNERF_MAX_UPLOAD_BYTES": str(8 * MiB),
    "VOXNERF_MAX_SCENE_BYTES": str(16 * MiB),
    "VOXNERF_MAX_IMAGE_PIXELS": str(4_000_000),
    "VOXNERF_HEALTH_TIMEOUT_S": "0.2",
}


@pytest.fixture(scope="module")
def api(tmp_path_factory):
    """The API alone (no workers), with a token and small upload limits."""
    service = start_service(
        tmp_path_factory.mktemp("validation"), token=TOKEN, settings=LIMITS, workers=False
    )
    yield service
    service.stop()


@pytest.fixture(scope="module")
def client(api):
    with api.client() as c:
        yield c


@pytest.fixture(scope="module")
def good_zip(small_room) -> bytes:
    return zip_scene(small_room)


def _stored(api: Service) -> tuple:
    """Everything an upload could leave behind: scene dirs, staging entries, database rows."""
    data = api.data_dir
    scenes = sorted(p.name for p in (data / "scenes").iterdir()) if (data / "scenes").is_dir() else []
    staging = sorted(p.name for p in (data / "staging").iterdir()) if (data / "staging").is_dir() else []
    with api.client() as c:
        rows = sorted(s["id"] for s in c.get("/scenes").json())
    return scenes, staging, rows


def _rezip(original: bytes, *, drop: tuple[str, ...] = (), replace: dict | None = None, add=()) -> bytes:
    """A copy of a zip with entries dropped, replaced ({name: bytes}) or added ([(ZipInfo|name, bytes)])."""
    replace = replace or {}
    out = io.BytesIO()
    with zipfile.ZipFile(io.BytesIO(original)) as src, zipfile.ZipFile(out, "w", zipfile.ZIP_DEFLATED) as dst:
        for info in src.infolist():
            if info.filename in drop:
                continue
            dst.writestr(info.filename, replace.get(info.filename, src.read(info)))
        for name, data in add:
            dst.writestr(name, data)
    return out.getvalue()


def _png_header_only(width: int, height: int) -> bytes:
    """A PNG signature and a valid IHDR chunk declaring ``width x height``; no pixel data."""
    ihdr = struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0)
    chunk = struct.pack(">I", len(ihdr)) + b"IHDR" + ihdr + struct.pack(">I", zlib.crc32(b"IHDR" + ihdr))
    return b"\x89PNG\r\n\x1a\n" + chunk


def _refused(api, client, payload: bytes, status: int, needle: str, filename: str = "scene.zip") -> str:
    before = _stored(api)
    response = client.post("/scenes", files={"file": (filename, payload, "application/zip")})
    assert response.status_code == status, response.text
    detail = response.json()["detail"]
    assert needle in str(detail), detail
    assert _stored(api) == before, "a refused upload left something behind"
    return detail


def _first_image(small_room) -> str:
    meta = json.loads((small_room / "transforms.json").read_text())
    return "room/" + meta["frames"][0]["file_path"]


def test_archive_entries_escaping_the_scene_are_refused(api, client, good_zip):
    _refused(api, client, _rezip(good_zip, add=[("room/../../evil.png", b"x")]), 422, "escape")
    _refused(api, client, _rezip(good_zip, add=[("/etc/evil.png", b"x")]), 422, "absolute path")
    _refused(api, client, _rezip(good_zip, add=[("C:/evil.png", b"x")]), 422, "absolute path")
    _refused(api, client, _rezip(good_zip, add=[("room\\..\\evil.png", b"x")]), 422, "backslash")


def test_symlink_entries_are_refused(api, client, good_zip):
    link = zipfile.ZipInfo("room/images/link.png")
    link.create_system = 3
    link.external_attr = (stat.S_IFLNK | 0o777) << 16
    _refused(api, client, _rezip(good_zip, add=[(link, b"/etc/passwd")]), 422, "symbolic link")


def test_zip_bombs_and_oversized_archives_are_refused_before_extraction(api, client, good_zip):
    bomb = _rezip(good_zip, add=[("room/images/bomb.png", bytes(6 * MiB))])
    assert len(bomb) < len(good_zip) + MiB // 10  # 6 MiB of zeros compress to a few kB
    _refused(api, client, bomb, 422, "zip bomb")
    huge = _rezip(good_zip, add=[("room/big.npy", bytes(20 * MiB))])
    _refused(api, client, huge, 413, "bytes uncompressed")


def test_unsupported_files_are_refused(api, client, good_zip):
    _refused(
        api,
        client,
        _rezip(good_zip, add=[("room/tools/run.sh", b"#!/bin/sh\n")]),
        415,
        "unsupported file type",
    )


def test_too_large_uploads_are_cut_off(api, client):
    before = _stored(api)
    response = client.post("/scenes", files={"file": ("big.zip", bytes(9 * MiB), "application/zip")})
    assert response.status_code == 413
    assert "larger than" in response.json()["detail"]
    assert _stored(api) == before


def test_huge_declared_image_size_is_refused_before_decoding(api, client, good_zip, small_room):
    payload = _rezip(good_zip, replace={_first_image(small_room): _png_header_only(100_000, 100_000)})
    detail = _refused(api, client, payload, 422, "declared image size 100000x100000")
    assert "images/" in detail


def test_malformed_scenes_are_refused_with_the_file_and_key(api, client, good_zip, small_room):
    _refused(api, client, b"this is not a zip", 422, "zip archive")
    _refused(api, client, _rezip(good_zip, drop=("room/transforms.json",)), 422, "transforms.json not found")
    _refused(
        api, client, _rezip(good_zip, replace={"room/transforms.json": b"{not json"}), 422, "invalid JSON"
    )
    meta = json.loads((small_room / "transforms.json").read_text())
    del meta["frames"][3]["transform_matrix"]
    detail = _refused(
        api,
        client,
        _rezip(good_zip, replace={"room/transforms.json": json.dumps(meta).encode()}),
        422,
        "frames[3].transform_matrix",
    )
    assert "transforms.json" in detail and "/staging/" not in detail
    small = iio.imwrite("<bytes>", np.zeros((24, 32, 3), np.uint8), extension=".png")
    _refused(api, client, _rezip(good_zip, replace={_first_image(small_room): small}), 422, "image is 32x24")


def test_upload_as_files_and_top_level_folder_zip_are_both_accepted(api, client, good_zip, small_room):
    response = client.post("/scenes", files={"file": ("room.zip", good_zip, "application/zip")})
    assert response.status_code == 201, response.text
    scene = response.json()
    assert scene["name"] == "room"
    meta = json.loads((small_room / "transforms.json").read_text())
    assert scene["summary"]["frames"] == len(meta["frames"])
    assert scene["summary"]["image_size"] == [64, 48]
    assert scene["summary"]["image_sizes"] == {"64x48": len(meta["frames"])}
    assert scene["summary"]["prior"]["kind"] == "points"
    assert scene["summary"]["prior"]["sigma"] == pytest.approx(0.02)
    assert (api.data_dir / "scenes" / scene["id"] / "transforms.json").is_file()

    files = [
        ("files", (p.relative_to(small_room).as_posix(), p.read_bytes()))
        for p in sorted(small_room.rglob("*"))
        if p.is_file() and p.name != "gt_mesh.ply"
    ]
    response = client.post("/scenes", files=files, data={"name": "as parts"})
    assert response.status_code == 201, response.text
    assert response.json()["name"] == "as parts"
    assert response.json()["summary"] == scene["summary"]

    before = _stored(api)
    bad = files[:1] + [("files", ("../escape.png", b"x"))]
    response = client.post("/scenes", files=bad)
    assert response.status_code == 422 and "escape" in response.json()["detail"]
    response = client.post("/scenes", data={"name": "nothing"})
    assert response.status_code == 422 and "multipart" in response.json()["detail"]
    assert _stored(api) == before


def test_bad_ids_in_urls_never_reach_the_filesystem(api, client):
    for url in (
        "/scenes/abc",
        "/scenes/..%2F..%2Fetc",
        "/jobs/ABCDEF" + "0" * 26,
        "/jobs/%2E%2E",
        "/jobs/" + "0" * 31 + "g/renders",
    ):
        response = client.get(url)
        assert response.status_code in (404, 422), url
        assert response.json()["detail"], url
    missing = "0" * 32
    assert client.get(f"/scenes/{missing}").status_code == 404
    assert "no job" in client.get(f"/jobs/{missing}").json()["detail"]
    assert client.delete("/scenes/..%2F..").status_code in (404, 422)
    assert client.post(f"/jobs/{missing}/cancel").status_code == 404
    response = client.post(
        "/render", json={"job_id": "../../etc/passwd", "transform_matrix": np.eye(4).tolist()}
    )
    assert response.status_code == 422


@pytest.fixture(scope="module")
def queued_job(api, client, good_zip):
    """A job that stays queued (this API has no workers), on its own scene."""
    scene = client.post("/scenes", files={"file": ("q.zip", good_zip, "application/zip")}).json()
    response = client.post(f"/scenes/{scene['id']}/jobs", json={"max_iters": 10, "compile": False})
    assert response.status_code == 202, response.text
    job = response.json()
    assert job["state"] == "queued" and job["scene_id"] == scene["id"]
    return job


def test_job_options_are_validated(api, client, queued_job):
    scene_id = queued_job["scene_id"]
    for body, needle in (
        ({}, "max_seconds or max_iters"),
        ({"max_iters": -1}, "max_iters"),
        ({"max_iters": 5, "sampler": "magic"}, "sampler"),
        ({"max_iters": 5, "lr": 1}, "lr"),
    ):
        response = client.post(f"/scenes/{scene_id}/jobs", json=body)
        assert response.status_code == 422, body
        assert needle in json.dumps(response.json()["detail"]), (body, response.json())
    assert client.post(f"/scenes/{'0' * 32}/jobs", json={"max_iters": 5}).status_code == 404


def test_bad_poses_and_render_requests_are_refused(client, queued_job):
    job_id = queued_job["id"]
    eye = np.eye(4)
    cases = [
        ({"transform_matrix": (eye * 2).tolist()}, "last row"),
        ({"transform_matrix": np.diag([2.0, 1, 1, 1]).tolist()}, "orthonormal"),
        ({"transform_matrix": np.diag([-1.0, 1, 1, 1]).tolist()}, "det"),
        ({"transform_matrix": np.eye(3).tolist()}, "4x4"),
        ({"transform_matrix": eye.tolist(), "width": 64}, "width and height together"),
        ({"transform_matrix": eye.tolist(), "outputs": ["rgb", "depth"]}, "PNG holds one output"),
        ({"transform_matrix": eye.tolist(), "outputs": ["normals"]}, "outputs"),
        ({"transform_matrix": eye.tolist(), "format": "jpg"}, "format"),
        ({"transform_matrix": eye.tolist(), "fl_x": -3}, "fl_x"),
    ]
    for extra, needle in cases:
        response = client.post("/render", json={"job_id": job_id, **extra})
        assert response.status_code == 422, extra
        assert needle in json.dumps(response.json()["detail"]), (extra, response.json())
    nan_pose = json.dumps({"job_id": job_id, "transform_matrix": [[float("nan")] * 4] * 3 + [[0, 0, 0, 1]]})
    response = client.post("/render", content=nan_pose, headers={"Content-Type": "application/json"})
    assert response.status_code == 422 and "NaN" in json.dumps(response.json()["detail"])


def test_render_of_an_unfinished_job_is_409_and_busy_scene_cannot_be_deleted(api, client, queued_job):
    response = client.post(
        "/render", json={"job_id": queued_job["id"], "transform_matrix": np.eye(4).tolist()}
    )
    assert response.status_code == 409 and "queued" in response.json()["detail"]
    response = client.post("/render", json={"job_id": "f" * 32, "transform_matrix": np.eye(4).tolist()})
    assert response.status_code == 404

    scene_id = queued_job["scene_id"]
    response = client.delete(f"/scenes/{scene_id}")
    assert response.status_code == 409 and queued_job["id"] in response.json()["detail"]
    cancelled = client.post(f"/jobs/{queued_job['id']}/cancel")
    assert cancelled.status_code == 202 and cancelled.json()["state"] == "cancelled"
    assert client.post(f"/jobs/{queued_job['id']}/cancel").json()["state"] == "cancelled"
    assert client.delete(f"/scenes/{scene_id}").status_code == 204
    assert not (api.data_dir / "scenes" / scene_id).exists()
    assert client.get(f"/scenes/{scene_id}").status_code == 404
    assert client.get(f"/jobs/{queued_job['id']}").json()["state"] == "cancelled"


def test_token_is_required_everywhere_but_health_and_the_dashboard_shell(api):
    with api.client(auth=False) as anonymous:
        for method, url in (
            ("GET", "/scenes"),
            ("POST", "/scenes"),
            ("GET", "/jobs"),
            ("GET", f"/jobs/{'0' * 32}"),
            ("POST", f"/jobs/{'0' * 32}/cancel"),
            ("POST", "/render"),
            ("POST", f"/scenes/{'0' * 32}/jobs"),
        ):
            response = anonymous.request(method, url)
            assert response.status_code == 401, (method, url)
            assert "Bearer" in response.json()["detail"] and response.headers["www-authenticate"] == "Bearer"
        wrong = anonymous.get("/jobs", headers={"Authorization": "Bearer nope"})
        assert wrong.status_code == 401
        health = anonymous.get("/healthz")
        assert health.status_code == 503  # no workers here, but no token needed either
        assert health.json() == {"status": "unavailable"}  # anonymous: the status alone
        with api.client() as authed:
            body = authed.get("/healthz").json()
        assert (
            body["database"]["ok"] and body["broker"]["ok"] and body["workers"] == {"train": [], "render": []}
        )
        shell = anonymous.get("/")
        assert shell.status_code == 200 and "dashboard.js" in shell.text
        assert anonymous.get("/static/dashboard.js").status_code == 200
