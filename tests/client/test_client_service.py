"""voxnerf.client and ``voxnerf remote`` against the real service (uvicorn, Celery workers) on the embedded broker
(the client speaks HTTP only: the broker behind the API is tests/service/test_service.py's, on both modes, and a
job's event stream on Redis is test_events.py's): upload (one request, and an upload session), train a tiny job,
wait, render, download; the remote CLI through subprocesses (upload's last line is the scene id; ``train --wait``
exits 0 for a job that succeeded and 1 for one that failed; refusals are one line)."""

from __future__ import annotations

import hashlib
import io
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from PIL import Image
from service_fixtures import REPO, start_service, wait_for, zip_scene

from app.schemas import SceneOut
from voxnerf.client import ApiError, Client

pytestmark = pytest.mark.slow

TOKEN = "client-test-token"
TINY = {"max_iters": 2, "compile": False, "downscale": 4}
TINY_FLAGS = ["--max-iters", "2", "--no-compile", "--downscale", "4"]
JOB_TIMEOUT_S = 300


@pytest.fixture(scope="module")
def service(tmp_path_factory):
    svc = start_service(tmp_path_factory.mktemp("client") / "service", token=TOKEN,
                        settings={"VOXNERF_UPLOAD_PART_BYTES": str(256 * 1024), "OMP_NUM_THREADS": "1"})
    yield svc
    svc.stop()


def _test_frame(scene_dir: Path) -> str:
    return json.loads((scene_dir / "transforms.json").read_text())["test_filenames"][0]


def test_round_trip_upload_train_wait_render_download(service, small_room, tmp_path):
    sizes = []
    with Client(service.base_url, TOKEN) as client:
        scene = client.upload(small_room, progress=lambda done, total: sizes.append((done, total)))
        assert scene.summary.frames == len(json.loads((small_room / "transforms.json").read_text())["frames"])
        assert sizes and sizes[-1][0] == sizes[-1][1]  # the progress reached the whole file

        archive = tmp_path / "room.zip"
        archive.write_bytes(zip_scene(small_room))
        client.session_threshold = 1  # the same scan through an upload session, in 256 KiB parts
        in_parts = client.upload(archive, name="in parts")
        assert in_parts.name == "in parts" and in_parts.summary == scene.summary

        data = archive.read_bytes()  # a session cut short (one part sent), resumed from what the server has
        with service.client() as http:
            session = http.post("/uploads", json={"filename": "room.zip", "total_bytes": len(data)}).json()
            first = data[: session["part_bytes"]]
            sent = http.put(f"/uploads/{session['id']}/parts/0", content=first,
                            headers={"X-Content-SHA256": hashlib.sha256(first).hexdigest()})
            assert sent.status_code == 201, sent.text
        resumed = SceneOut.model_validate(client.resume_upload(session["id"], archive))
        assert resumed.summary == scene.summary
        assert {s.id for s in client.scenes()} >= {scene.id, in_parts.id}

        queued = client.train(scene.id, **TINY)
        assert queued.state == "queued" and queued.options["max_iters"] == 2
        events = []
        job = client.wait(queued.id, on_event=events.append, timeout_s=JOB_TIMEOUT_S)
        assert job.state == "succeeded", f"{job.error}\n{service.logs()}"
        assert events[-1].event == "state" and events[-1].data["state"] == "succeeded"  # followed the stream
        ids = [event.id for event in events]
        assert ids == sorted(set(ids))
        assert client.job(job.id).state == "succeeded" and job.id in {j.id for j in client.jobs(scene.id)}

        frame = _test_frame(small_room)
        png = client.render(job.id, frame=frame, out=tmp_path / "view.png")
        image = np.asarray(Image.open(io.BytesIO(png)))
        width, height = scene.summary.image_size
        assert image.shape[:2] == (height, width) and image.std() > 0
        assert (tmp_path / "view.png").read_bytes() == png
        small = client.render(job.id, frame=Path(frame).stem, width=32, height=24)
        assert Image.open(io.BytesIO(small)).size == (32, 24)
        pose = {"transform_matrix": np.eye(4).tolist()}
        assert Image.open(io.BytesIO(client.render(job.id, pose=pose, width=16, height=12))).size == (16, 12)
        with pytest.raises(Exception, match="names no frame"):
            client.render(job.id, frame="no-such-frame")

        written = client.download(job.id, tmp_path / "run")
        names = {p.relative_to(tmp_path / "run").as_posix() for p in written}
        assert {"report.json", "checkpoint.pt"} <= names
        assert json.loads((tmp_path / "run" / "report.json").read_text())["status"]
        assert (tmp_path / "run" / "checkpoint.pt").stat().st_size > 0
        assert not list((tmp_path / "run").rglob(".*"))  # no temporary file left

        with pytest.raises(ApiError) as finished:
            client.cancel(job.id)
        assert finished.value.status == 409 and "already succeeded" in finished.value.detail


def _remote(service, *args: str, token: str | None = TOKEN, timeout_s: float = JOB_TIMEOUT_S,
            **popen) -> subprocess.CompletedProcess:
    env = {k: v for k, v in service.env.items() if k not in ("VOXNERF_API_TOKEN",)}
    env["VOXNERF_URL"] = service.base_url
    if token:
        env["VOXNERF_API_TOKEN"] = token
    return subprocess.run([sys.executable, "-m", "voxnerf", "remote", *args], cwd=REPO, env=env,
                          capture_output=True, text=True, timeout=timeout_s, **popen)


def test_remote_cli_upload_train_wait_status_render_download(service, small_room, tmp_path):
    uploaded = _remote(service, "upload", str(small_room), "--name", "from the cli")
    assert uploaded.returncode == 0, uploaded.stderr
    scene_id = uploaded.stdout.strip().splitlines()[-1]
    with service.client() as http:
        assert http.get(f"/scenes/{scene_id}").json()["name"] == "from the cli"

    trained = _remote(service, "train", scene_id, *TINY_FLAGS, "--seed", "3", "--wait")
    assert trained.returncode == 0, trained.stdout + trained.stderr + service.logs()
    job_id = trained.stdout.splitlines()[0]
    assert "succeeded" in trained.stdout.splitlines()[-1]
    with service.client() as http:
        job = http.get(f"/jobs/{job_id}").json()
    assert job["state"] == "succeeded" and job["options"]["seed"] == 3 and job["options"]["downscale"] == 4

    status = _remote(service, "status", job_id, "--json")
    assert status.returncode == 0 and json.loads(status.stdout)["id"] == job_id
    listed = _remote(service, "status")
    assert job_id in listed.stdout

    out = tmp_path / "frame.png"
    rendered = _remote(service, "render", job_id, "--frame", _test_frame(small_room), "--out", str(out))
    assert rendered.returncode == 0, rendered.stderr
    with service.client() as http:
        assert list(Image.open(out).size) == http.get(f"/scenes/{scene_id}").json()["summary"]["image_size"]
    service.start_worker("outputs")
    video = tmp_path / "fly.mp4"
    made = _remote(service, "video", job_id, "--path", "orbit", "--frames", "3", "--width", "32", "--height", "24",
                   "--out", str(video))
    assert made.returncode == 0, made.stderr + service.logs()
    assert made.stdout.splitlines()[-1] == str(video) and video.read_bytes()[4:8] == b"ftyp"
    downloaded = _remote(service, "download", job_id, "--out", str(tmp_path / "run"))
    assert downloaded.returncode == 0 and (tmp_path / "run" / "checkpoint.pt").is_file(), downloaded.stderr
    assert any(line.endswith(".mp4") for line in downloaded.stdout.splitlines())  # the video came with the run


def test_remote_train_wait_exits_1_when_the_job_fails(service, small_room, tmp_path):
    uploaded = _remote(service, "upload", str(small_room))
    scene_id = uploaded.stdout.strip().splitlines()[-1]
    service.kill("train")  # the job waits in the queue while its scene loses its transforms.json
    try:
        (service.data_dir / "scenes" / scene_id / "transforms.json").unlink()
        env = {k: v for k, v in service.env.items() if k != "VOXNERF_API_TOKEN"}
        env |= {"VOXNERF_URL": service.base_url, "VOXNERF_API_TOKEN": TOKEN}
        waiting = subprocess.Popen([sys.executable, "-m", "voxnerf", "remote", "train", scene_id, *TINY_FLAGS,
                                    "--wait"], cwd=REPO, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                                   text=True)
        with service.client() as http:
            wait_for(lambda: http.get("/jobs", params={"scene_id": scene_id}).json(), 60, "the job to be queued")
    finally:
        service.start_worker("train")
    stdout, stderr = waiting.communicate(timeout=JOB_TIMEOUT_S)
    assert waiting.returncode == 1, stdout + stderr + service.logs()
    last = stderr.strip().splitlines()[-1]
    assert last.startswith(f"voxnerf: job {stdout.splitlines()[0]} failed: ") and "transforms.json" in last


def test_remote_refusals_are_one_line(service, small_room, tmp_path):
    unknown = _remote(service, "status", "0" * 32, timeout_s=60)
    assert unknown.returncode == 2 and unknown.stderr == f"voxnerf: error: no job {'0' * 32} (HTTP 404)\n"
    no_token = _remote(service, "status", token=None, timeout_s=60)
    assert no_token.returncode == 2 and len(no_token.stderr.splitlines()) == 1 and "(HTTP 401)" in no_token.stderr
    private = _remote(service, "train", "0" * 32, "--max-iters", "2", "--callback-url", "http://127.0.0.1:9/hook",
                      timeout_s=60)  # the option reaches the service, which refuses a loopback target
    assert private.returncode == 2 and "(HTTP 422)" in private.stderr and len(private.stderr.splitlines()) == 1
    bad_option = _remote(service, "train", "0" * 32, "--max-iters", "2", "--set", "device=cuda", timeout_s=60)
    assert bad_option.returncode == 2 and len(bad_option.stderr.splitlines()) == 1, bad_option.stderr
    assert "device" in bad_option.stderr
    not_zip = tmp_path / "notes.zip"
    not_zip.write_bytes(b"not a zip at all")
    refused = _remote(service, "upload", str(not_zip), timeout_s=120)
    assert refused.returncode == 2 and len(refused.stderr.splitlines()) == 1 and "(HTTP 422)" in refused.stderr
    nowhere = _remote(service, "status", "--url", "http://127.0.0.1:9", "--retries", "1", timeout_s=180)
    assert nowhere.returncode == 2 and "cannot reach http://127.0.0.1:9" in nowhere.stderr
