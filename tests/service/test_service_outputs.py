"""Output jobs over real HTTP with real Celery workers (train, render, outputs) on the embedded default
(filesystem queue + SQLite, with an API token). The broker carries output messages as it carries a job's: videos
on a redis-server, with their worker killed and the broker restarted, are the soak test's (test_soak.py); a lost
output message is test_output_faults.py's.

The service trains one tiny job (30 iterations: outputs need a checkpoint, not a good model) and one long job
that is cancelled (a checkpoint kept), then: videos (an orbit, a path through the cameras, a posted nerfstudio
camera path) download and decode with the asked frames, size and fps; a mesh and a point cloud download and
parse; a running video is cancelled and leaves nothing; bad requests are refused; a cancelled job renders with
``X-VoxNeRF-Partial: true``. Frames are tiny so that rendering costs little.
"""

from __future__ import annotations

import io
import time

import imageio.v2 as imageio
import numpy as np
import pytest
import trimesh
from service_fixtures import Service, first_pose, start_service, upload_scene, wait_for

pytestmark = pytest.mark.slow

TOKEN = "outputs-token"
TINY_JOB = {"max_iters": 30, "compile": False}  # enough for depth that agrees between views (a mesh)
LONG_JOB = {"max_iters": 100_000, "compile": False}
TIMEOUT_S = 300
SETTINGS = {"VOXNERF_HEARTBEAT_S": "0.5", "VOXNERF_PROGRESS_INTERVAL_S": "0.2", "VOXNERF_MAX_VIDEO_FRAMES": "1000"}


@pytest.fixture(scope="module")
def service(tmp_path_factory):
    svc = start_service(tmp_path_factory.mktemp("outputs") / "service", token=TOKEN, settings=SETTINGS)
    try:
        svc.start_worker("outputs")
        wait_for(lambda: svc.wait_healthy()["workers"].get("outputs"), 120, "an outputs worker in /healthz")
        yield svc
    finally:
        svc.stop()


@pytest.fixture(scope="module")
def client(service):
    with service.client() as c:
        yield c


@pytest.fixture(scope="module")
def scene(client, small_room) -> dict:
    return upload_scene(client, small_room)


def _watch(service: Service, client, url: str, until, timeout_s: float = TIMEOUT_S) -> dict:
    """Poll ``url`` (a job or an output) until ``until(body)``; fails with the service logs."""
    deadline = time.monotonic() + timeout_s
    while True:
        response = client.get(url)
        assert response.status_code == 200, response.text
        body = response.json()
        if until(body):
            return body
        if body["state"] == "failed" or time.monotonic() > deadline:
            pytest.fail(f"{url} is {body['state']} ({body['error']}) after {timeout_s} s\n{service.logs()}")
        time.sleep(0.2)


@pytest.fixture(scope="module")
def trained(service, client, scene) -> dict:
    job = client.post(f"/scenes/{scene['id']}/jobs", json=TINY_JOB).json()
    return _watch(service, client, f"/jobs/{job['id']}", lambda j: j["state"] == "succeeded")


@pytest.fixture(scope="module")
def cancelled(service, client, scene, trained) -> dict:
    """A long job cancelled while training: it keeps its checkpoint. While it runs no output is made from it, and
    before its first checkpoint (60 s of training by default) no render either."""
    job = client.post(f"/scenes/{scene['id']}/jobs", json=LONG_JOB).json()
    url = f"/jobs/{job['id']}"
    _watch(service, client, url, lambda j: j["state"] == "running" and j["iteration"] > 0)
    refused = client.post(f"{url}/videos", json={"path": "orbit", "frames": 2, "width": 16, "height": 12})
    assert refused.status_code == 409 and "running" in refused.json()["detail"]
    assert client.post(f"{url}/exports", json={"kind": "mesh"}).status_code == 409
    assert client.post("/render", json={"job_id": job["id"], "transform_matrix": np.eye(4).tolist()}).status_code == 409
    assert client.post(f"{url}/cancel").status_code == 202
    return _watch(service, client, url, lambda j: j["state"] == "cancelled")


def _finished(service, client, output: dict) -> dict:
    return _watch(service, client, f"/outputs/{output['id']}", lambda o: o["state"] == "succeeded")


def _start(client, job_id: str, kind: str, body: dict) -> dict:
    response = client.post(f"/jobs/{job_id}/{kind}", json=body)
    assert response.status_code == 202, response.text
    output = response.json()
    assert output["state"] == "queued" and output["job_id"] == job_id
    return output


def _decode(data: bytes, tmp_path) -> tuple[list[np.ndarray], dict]:
    """Every frame of an MP4 (decoded by imageio-ffmpeg's ffmpeg) and the container's metadata."""
    path = tmp_path / "video.mp4"
    path.write_bytes(data)
    with imageio.get_reader(path, format="FFMPEG") as reader:
        return [frame for frame in reader], reader.get_meta_data()


def _download_video(client, output: dict, tmp_path) -> tuple[list[np.ndarray], dict]:
    response = client.get(output["file_url"])
    assert response.status_code == 200 and response.headers["content-type"] == "video/mp4"
    assert "video.mp4" in response.headers["content-disposition"]
    return _decode(response.content, tmp_path)


def test_an_orbit_video_downloads_and_decodes_with_its_frames_size_and_fps(service, client, trained, tmp_path):
    body = {"path": "orbit", "frames": 6, "fps": 12, "width": 32, "height": 24}
    output = _start(client, trained["id"], "videos", body)
    done = _finished(service, client, output)
    assert done["done"] == done["total"] == 6 and done["unit"] == "frames" and done["progress"] == 1.0
    assert not done["partial"] and done["summary"]["frames"] == 6 and done["eta_s"] is None
    frames, meta = _download_video(client, done, tmp_path)
    assert len(frames) == 6 and frames[0].shape == (24, 32, 3)
    assert meta["fps"] == pytest.approx(12) and meta["codec"] == "h264"
    assert [o["id"] for o in client.get(f"/jobs/{trained['id']}/outputs").json()][0] == output["id"]


def test_a_video_through_the_cameras(service, client, trained, tmp_path):
    output = _start(client, trained["id"], "videos", {"path": "interpolate", "frames": 10, "fps": 24})
    frames, meta = _download_video(client, _finished(service, client, output), tmp_path)
    assert len(frames) == 10 and frames[0].shape == (48, 64, 3)  # the scene's size
    assert meta["fps"] == pytest.approx(24)
    assert np.ptp(np.stack(frames).astype(float)) > 0  # the frames show something


def test_a_posted_nerfstudio_camera_path_renders_its_frames(service, client, trained, small_room, tmp_path):
    pose = np.asarray(first_pose(small_room))
    entries = []
    for step in range(4):
        moved = pose.copy()
        moved[:3, 3] += 0.05 * step * moved[:3, 0]
        entries.append({"camera_to_world": moved.reshape(-1).tolist(), "fov": 50.0, "aspect": 4 / 3})
    camera_path = {"render_width": 40, "render_height": 30, "fps": 8, "seconds": 0.5, "camera_path": entries}
    output = _start(client, trained["id"], "videos", {"camera_path": camera_path})
    assert output["params"]["camera_path"] == {"frames": 4} and output["total"] == 4
    frames, meta = _download_video(client, _finished(service, client, output), tmp_path)
    assert len(frames) == 4 and frames[0].shape == (30, 40, 3) and meta["fps"] == pytest.approx(8)


@pytest.mark.parametrize("kind", ["mesh", "pointcloud"])
def test_an_export_downloads_as_a_non_empty_ply(service, client, trained, kind):
    # a model of a few iterations is barely opaque: a low min_opacity still finds its surfaces
    body = {"kind": kind, "voxel_size": 0.04, "max_views": 12, "min_opacity": 0.2}
    done = _finished(service, client, _start(client, trained["id"], "exports", body))
    assert done["unit"] == "views" and done["done"] == done["total"] == 12
    response = client.get(done["file_url"])
    assert response.status_code == 200 and response.headers["content-type"] == "application/octet-stream"
    assert f"{kind}.ply" in response.headers["content-disposition"]
    geometry = trimesh.load(io.BytesIO(response.content), file_type="ply")
    assert len(geometry.vertices) == done["summary"]["points"] > 0
    assert np.isfinite(np.asarray(geometry.vertices)).all()
    if kind == "mesh":
        assert len(geometry.faces) == done["summary"]["faces"] > 0


def test_cancelling_a_running_video_leaves_no_file(service, client, trained):
    output = _start(client, trained["id"], "videos", {"path": "orbit", "frames": 1000, "width": 64, "height": 48})
    url = f"/outputs/{output['id']}"
    _watch(service, client, url, lambda o: o["state"] == "running" and o["done"] > 0)
    assert client.get(f"{url}/file").status_code == 409  # never a partial file
    response = client.post(f"{url}/cancel")
    assert response.status_code == 202 and response.json()["cancel_requested"]
    done = _watch(service, client, url, lambda o: o["state"] == "cancelled")
    assert 0 < done["done"] < 1000 and done["file_url"] is None
    assert client.get(f"{url}/file").status_code == 409
    assert not (service.data_dir / "runs" / trained["id"] / "outputs" / output["id"]).exists()
    assert client.post(f"{url}/cancel").status_code == 202  # idempotent


def test_a_cancelled_job_with_a_checkpoint_renders_as_partial(client, cancelled, small_room):
    response = client.post("/render", json={"job_id": cancelled["id"], "transform_matrix": first_pose(small_room)})
    assert response.status_code == 200 and response.headers["x-voxnerf-partial"] == "true"
    output = _start(client, cancelled["id"], "videos", {"path": "orbit", "frames": 2, "width": 16, "height": 12})
    assert output["partial"]
    assert client.post(f"/outputs/{output['id']}/cancel").status_code == 202


@pytest.mark.parametrize(
    ("body", "named"),
    [
        ({"path": "orbit", "frames": 0}, "frames"),
        ({"path": "orbit", "frames": 10**9}, "frames"),
        ({"path": "orbit", "frames": 2, "width": 8192, "height": 4096}, "exceeds the limit"),
        ({"path": "orbit", "frames": 2, "width": 31, "height": 24}, "even"),
        ({"path": "spiral", "frames": 2}, "path"),
        ({"path": "orbit"}, "frames"),
        ({}, "camera_path"),
        ({"camera_path": {"render_width": 32, "render_height": 24, "fps": 10, "camera_path": [
            {"camera_to_world": np.eye(4).reshape(-1).tolist(), "fov": 190, "aspect": 1}]}}, "camera_path[0].fov"),
        ({"camera_path": {"render_height": 24, "fps": 10, "camera_path": []}}, "render_width"),
        ({"camera_path": {"render_width": 32, "render_height": 24, "fps": 10, "camera_path": [
            {"camera_to_world": [1, 0, 0], "fov": 50, "aspect": 1}]}}, "camera_path[0].camera_to_world"),
    ],
)
def test_bad_video_requests_are_422_naming_the_key(client, trained, body, named):
    response = client.post(f"/jobs/{trained['id']}/videos", json=body)
    assert response.status_code == 422, response.text
    assert named in str(response.json()["detail"])


def test_unknown_ids_and_bad_exports(client, trained):
    unknown = "0" * 32
    assert client.get(f"/outputs/{unknown}").status_code == 404
    assert client.get(f"/outputs/{unknown}/file").status_code == 404
    assert client.post(f"/outputs/{unknown}/cancel").status_code == 404
    assert client.get("/outputs/not-an-id").status_code == 422
    assert client.post(f"/jobs/{unknown}/videos", json={"path": "orbit", "frames": 2}).status_code == 404
    assert client.get(f"/jobs/{unknown}/outputs").status_code == 404
    for bad in ({"kind": "voxels"}, {"kind": "mesh", "voxel_size": -1}, {"kind": "mesh", "min_opacity": 2}):
        assert client.post(f"/jobs/{trained['id']}/exports", json=bad).status_code == 422
