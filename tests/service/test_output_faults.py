"""Output jobs and renders are never orphaned and stop when nobody waits (issue #42, items 3 and 5), against real
processes: the uvicorn API, Celery ``outputs`` and ``render`` workers (``python -m worker``), the embedded
filesystem broker, all on loopback. The trained job is an untrained model written directly as its run's
checkpoint (:func:`tiny_run.write_tiny_run`): outputs and renders need a checkpoint, not a good model.

- A queued video whose message is lost is sent again by the API's sweep once, a video queued behind it keeps its
  one message however long it waits (today a copy piled up every ``resend_queued_after_s``), both are made
  exactly once when an outputs worker starts, and then their training job can be deleted (409 before).
- A render the API gave up on (504) stops at the worker's next pass over its rays (the worker logs it) and the
  worker answers the next render; today it rendered all of the abandoned image first.
"""

from __future__ import annotations

import time

import httpx
import pytest
from service_fixtures import Service, first_pose, start_service, upload_scene, wait_for
from tiny_run import write_tiny_run

from app.core import jobstore
from app.core.db import session_scope
from app.core.models import JobRow
from app.core.outputs import OUTPUTS
from app.core.settings import Settings

pytestmark = pytest.mark.slow

RESEND_AFTER_S = 3
RENDER_TIMEOUT_S = 5
BIG = 2048  # a side of the abandoned render: 4 194 304 rays, minutes of the CPU for this model
SETTINGS = {
    "VOXNERF_RESEND_QUEUED_AFTER_S": str(RESEND_AFTER_S),
    "VOXNERF_RENDER_TIMEOUT_S": str(RENDER_TIMEOUT_S),
    "VOXNERF_MAX_RENDER_PIXELS": str(BIG * BIG),
    "OMP_NUM_THREADS": "1",
}
VIDEO = {"path": "orbit", "frames": 4, "fps": 8, "width": 16, "height": 12}
TIMEOUT_S = 240


@pytest.fixture(scope="module")
def service(tmp_path_factory) -> Service:
    """The API and a render worker; the outputs worker starts in its test, once the queue is set up."""
    svc = start_service(tmp_path_factory.mktemp("output-faults"), settings=SETTINGS, workers=False)
    try:
        svc.start_worker("render")
        wait_for(lambda: "ready" in (svc.root / "worker-render.log").read_text(errors="replace"), 120,
                 "the render worker to be ready")
        yield svc
    finally:
        svc.stop()


@pytest.fixture(scope="module")
def client(service) -> httpx.Client:
    with service.client() as c:
        yield c


@pytest.fixture(scope="module")
def scene_id(client, small_room) -> str:
    return upload_scene(client, small_room)["id"]


@pytest.fixture
def trained(service, scene_id) -> str:
    """A succeeded job on the uploaded room whose run holds an untrained model (no training worker runs)."""
    store = Settings(_env_file=None, data_dir=service.data_dir)
    job = jobstore.create_job(store, scene_id, {"max_iters": 1})
    write_tiny_run(service.data_dir / "runs" / job.id)
    with session_scope(store) as session:
        row = session.get(JobRow, job.id)
        row.state, row.stage, row.finished_at = "succeeded", "done", time.time()
    return job.id


def _waiting(service: Service) -> list[str]:
    """The names of the messages waiting in the outputs queue."""
    return sorted(path.name for path in (service.data_dir / "broker" / "queue").glob("*.outputs.msg"))


def _final(service: Service, client: httpx.Client, output_id: str) -> dict:
    def final():
        body = client.get(f"/outputs/{output_id}").json()
        return body if body["state"] in ("succeeded", "failed", "cancelled") else None

    try:
        return wait_for(final, TIMEOUT_S, f"output {output_id} to finish", 0.5)
    except AssertionError:
        pytest.fail(f"output {output_id} did not finish\n{service.logs()}")


def test_a_lost_output_is_sent_again_once_a_waiting_one_keeps_one_message_and_the_job_can_then_go(
    service, client, trained
):
    lost, waiting = (client.post(f"/jobs/{trained}/videos", json=VIDEO).json()["id"] for _ in range(2))
    first_message = _waiting(service)[0]  # messages are named in send order: the first is the lost video's
    (service.data_dir / "broker" / "queue" / first_message).unlink()
    wait_for(lambda: len(_waiting(service)) >= 2, 60, "the sweep to send the lost message again")
    time.sleep(3 * RESEND_AFTER_S)  # three more re-send periods: neither output gets another copy
    assert len(_waiting(service)) == 2, _waiting(service)
    response = client.delete(f"/jobs/{trained}")
    assert response.status_code == 409 and "queued or running" in response.json()["detail"]
    service.start_worker("outputs")
    store = Settings(_env_file=None, data_dir=service.data_dir)
    for output_id in (lost, waiting):
        output = _final(service, client, output_id)
        assert output["state"] == "succeeded", f"{output['error']}\n{service.logs()}"
        assert output["done"] == 4
        assert OUTPUTS.get(store, output_id).attempt == 1  # made once: every other copy would be refused
    assert _waiting(service) == []
    response = client.get(f"/jobs/{trained}/outputs")
    assert sorted(o["id"] for o in response.json()) == sorted([lost, waiting])
    assert client.delete(f"/jobs/{trained}").status_code == 204  # nothing of it is queued any more
    assert client.get(f"/outputs/{lost}").status_code == 404


def test_a_render_the_api_gave_up_on_stops_and_frees_the_worker(service, client, trained, small_room):
    render_log = service.root / "worker-render.log"
    pose = first_pose(small_room)
    body = {"job_id": trained, "transform_matrix": pose, "format": "png"}
    wait_for(lambda: client.post("/render", json={**body, "width": 16, "height": 16}).status_code == 200, 120,
             "a small render to answer (the model loaded)")
    abandoned = client.post("/render", json={**body, "width": BIG, "height": BIG})
    assert abandoned.status_code == 504, abandoned.text
    # (a small render of the warm-up above may have been given up on too, on a loaded machine: its line is not this)
    stopped = wait_for(lambda: [line for line in render_log.read_text(errors="replace").splitlines()
                                if "stopped after" in line and f"of {BIG * BIG} rays" in line], 120,
                       "the render worker to stop the abandoned render")
    (line,) = stopped
    assert "nothing is delivered" in line
    answered = client.post("/render", json={**body, "width": 16, "height": 16})
    assert answered.status_code == 200 and answered.headers["content-type"] == "image/png"
