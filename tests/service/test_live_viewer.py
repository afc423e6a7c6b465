"""The viewer while a job trains (issue #44, item 7), through real HTTP (uvicorn), a real train worker and a real
render worker, and the pages in the headless browser (playwright driving Debian's /usr/bin/chromium): a job of
long ``max_seconds`` with a checkpoint every few seconds answers renders 409 before its first checkpoint, renders
from it while its state is still ``running`` (``X-VoxNeRF-Iteration``, ``X-VoxNeRF-Job-State: running``), renders a
higher iteration after a newer checkpoint, and the render worker loaded each checkpoint once (its log counts the
loads); the job page links the viewer while the job runs, and the viewer shows "iteration N, training" and renders
the view again by itself when a newer checkpoint is written. Cancelled, the job renders its last checkpoint."""

from __future__ import annotations

import re

import pytest
from browser_fixtures import browser_page, csp_reports
from service_fixtures import first_pose, start_service, upload_scene, wait_for, wait_until_final
from synthetic_fixtures import make_micro_scene

pytestmark = pytest.mark.slow

TOKEN = "live-viewer-token"
CHECKPOINT_EVERY_S = 4  # loop seconds between checkpoints: two come within a test's patience
JOB_SECONDS = 600  # far longer than the test: the job is still training when it is viewed, then cancelled
FINAL_TIMEOUT_S = 300


@pytest.fixture(scope="module")
def service(tmp_path_factory):
    svc = start_service(tmp_path_factory.mktemp("live_viewer"), token=TOKEN,
                        settings={"VOXNERF_CHECKPOINT_EVERY_S": str(CHECKPOINT_EVERY_S)})
    try:
        yield svc
    finally:
        svc.stop()


@pytest.fixture
def page():
    with browser_page(1300, 850) as opened:
        yield opened


def _loads(service, job_id: str) -> list[int]:
    """The iterations of job ``job_id``'s checkpoints the render worker loaded, in order (from its log)."""
    text = (service.root / "worker-render.log").read_text(errors="replace")
    return [int(n) for n in re.findall(rf"model cache: loaded run {job_id}, checkpoint of iteration (\d+)", text)]


def test_a_running_job_is_viewed_from_its_latest_checkpoint(service, page, tmp_path, tmp_path_factory):
    scene_dir = make_micro_scene(tmp_path_factory, "live-viewer-scene")
    with service.client() as client:
        scene = upload_scene(client, scene_dir)
        job_id = client.post(f"/scenes/{scene['id']}/jobs",
                             json={"max_seconds": JOB_SECONDS, "compile": False}).json()["id"]
        body = {"job_id": job_id, "transform_matrix": first_pose(scene_dir)}

        def job() -> dict:
            return client.get(f"/jobs/{job_id}").json()

        # before the first checkpoint: 409 saying why (queued, then running without one)
        refusals = []

        def first_checkpoint() -> dict | None:
            row = job()
            if row["checkpoint_iteration"] is not None:
                return row
            response = client.post("/render", json=body)
            if response.status_code == 409:
                refusals.append(response.json()["detail"])
            return None

        row = wait_for(first_checkpoint, FINAL_TIMEOUT_S, "the job's first checkpoint", 0.5)
        assert refusals and all("checkpoint" in detail for detail in refusals), refusals
        assert any("has no checkpoint yet" in detail for detail in refusals), refusals
        assert row["state"] == "running", row

        # the first checkpoint renders while the job trains on
        first = client.post("/render", json=body)
        assert first.status_code == 200, first.text
        first_iteration = int(first.headers["X-VoxNeRF-Iteration"])
        assert first_iteration >= row["checkpoint_iteration"] >= 1
        assert first.headers["X-VoxNeRF-Job-State"] == "running" and first.headers["X-VoxNeRF-Partial"] == "true"
        again = client.post("/render", json=body)
        assert again.status_code == 200 and job()["state"] == "running"

        # a newer checkpoint renders a higher iteration
        wait_for(lambda: job()["checkpoint_iteration"] > first_iteration, FINAL_TIMEOUT_S,
                 "a newer checkpoint", 0.5)
        later = client.post("/render", json=body)
        assert later.status_code == 200 and int(later.headers["X-VoxNeRF-Iteration"]) > first_iteration
        assert later.headers["X-VoxNeRF-Job-State"] == "running"
        rendered = {int(r.headers["X-VoxNeRF-Iteration"]) for r in (first, again, later)}
        loads = _loads(service, job_id)  # each checkpoint loaded once: the same one again costs only a stat
        assert len(loads) == len(set(loads)) and rendered <= set(loads), (loads, rendered)

    # the job page links the viewer while the job trains; the viewer says which checkpoint it shows
    csp = csp_reports(page)
    page.goto(f"{service.base_url}/static/job.html?id={job_id}")
    page.evaluate("token => localStorage.setItem('voxnerf.token', token)", TOKEN)  # as the dashboard saves it
    page.reload()
    page.wait_for_selector("#viewer-link", timeout=60_000)
    assert "training" in page.inner_text("#viewer-link") and page.get_attribute("body", "data-state") == "running"
    page.screenshot(path=str(tmp_path / "job-page-running.png"), full_page=True)
    # the link is updated in place as checkpoints come (a new element per update could swallow the click)
    page.evaluate("() => { window.firstLink = document.getElementById('viewer-link'); "
                  "window.firstIteration = window.firstLink.dataset.iteration; }")
    page.wait_for_function("() => document.getElementById('viewer-link').dataset.iteration !== "
                           "window.firstIteration", timeout=FINAL_TIMEOUT_S * 1000)
    assert page.evaluate("() => document.getElementById('viewer-link') === window.firstLink")
    page.click("#viewer-link")
    page.wait_for_url(f"**/static/viewer.html?job={job_id}")
    page.wait_for_function("() => document.getElementById('checkpoint').dataset.iteration !== ''", timeout=120_000)
    shown = int(page.get_attribute("#checkpoint", "data-iteration"))
    assert page.inner_text("#checkpoint") == f"iteration {shown}, training"
    page.screenshot(path=str(tmp_path / "viewer-training.png"))

    # nobody touches the view: a newer checkpoint is rendered by itself
    page.wait_for_function("n => Number(document.getElementById('checkpoint').dataset.iteration) > n", arg=shown,
                           timeout=180_000)
    newer = int(page.get_attribute("#checkpoint", "data-iteration"))
    assert page.inner_text("#checkpoint") == f"iteration {newer}, training"
    page.screenshot(path=str(tmp_path / "viewer-newer-checkpoint.png"))
    assert csp == [], csp

    # cancelled: the job keeps its last checkpoint, and renders it
    with service.client() as client:
        assert client.post(f"/jobs/{job_id}/cancel").status_code in (200, 202)
        final = wait_until_final(service, client, f"/jobs/{job_id}", FINAL_TIMEOUT_S)
        assert final["state"] == "cancelled" and final["checkpoint_iteration"] >= newer, final
        last = client.post("/render", json=body)
        assert last.status_code == 200 and last.headers["X-VoxNeRF-Job-State"] == "cancelled"
        assert int(last.headers["X-VoxNeRF-Iteration"]) == final["checkpoint_iteration"]
    print(f"live viewer screenshots: {tmp_path}")
