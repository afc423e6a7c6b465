"""Live events and webhooks through real HTTP (uvicorn, a real Celery training worker, the embedded broker):

- a short real job's ``GET /jobs/{id}/events`` stream from its first event (queued) to its final state, with its
  stages and evaluations, read in two connections: the second resumes with ``Last-Event-ID`` and gets no event
  twice; a replay after the end ends the same way; ``Last-Event-ID`` of the final event gets 204;
- that job's webhooks, posted to a loopback receiver (allowed by VOXNERF_WEBHOOK_ALLOW_PRIVATE) that answers 500
  to each event's first delivery: every state change arrives, signed, after a retry, and each delivery's log
  shows both attempts;
- the job page of a running job drawn from its events: one GET /jobs/{id}, then the stream, in a real browser;
- without workers: a queued job's stream (its state, keep-alive comments), the stream limit (429), a cancel seen
  on the open stream, unknown jobs (404), loopback and private callback URLs refused (422) without the setting.
"""

from __future__ import annotations

import hashlib
import hmac
import json
import signal
import threading
import time
from collections.abc import Iterator
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

import pytest
from browser_fixtures import browser_page, csp_reports
from service_fixtures import start_redis, start_service, stop_process, upload_scene, wait_for

from app.core.settings import Settings
from app.core.tokens import TokenError, webhook_secret
from app.webhooks import CallbackRefused, checked_addresses, signature

pytestmark = pytest.mark.slow

TOKEN = "events-token"
JOB = {"max_iters": 30, "compile": False, "downscale": 4}
TIMEOUT_S = 300
SET_UP_STAGES = {"load_scene", "prior", "octree"}


def read_events(lines: Iterator[str], stop=lambda event: False) -> tuple[list[dict], list[str]]:
    """The events of an SSE response's lines (``{"id", "event", "data"}``, data parsed) and its comment lines,
    until the stream ends or ``stop(event)`` is true for one just read."""
    events, comments, fields = [], [], {}
    for line in lines:
        if line.startswith(":"):
            comments.append(line)
        elif line:
            name, _, value = line.partition(":")
            fields[name] = value.removeprefix(" ")
        elif fields:
            event = {"id": int(fields["id"]), "event": fields["event"], "data": json.loads(fields["data"])}
            events.append(event)
            fields = {}
            if stop(event):
                break
    return events, comments


class Receiver(ThreadingHTTPServer):
    """A webhook receiver on 127.0.0.1 that answers 500 to the first delivery of each event id, 204 after."""

    def __init__(self) -> None:
        super().__init__(("127.0.0.1", 0), _ReceiverHandler)
        self.calls: list[tuple[dict, bytes, int]] = []  # headers, body, the status answered
        self.lock = threading.Lock()

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.server_address[1]}/hooks/voxnerf"


class _ReceiverHandler(BaseHTTPRequestHandler):
    def do_POST(self) -> None:  # noqa: N802 (http.server's name)
        body = self.rfile.read(int(self.headers["Content-Length"]))
        receiver: Receiver = self.server
        with receiver.lock:
            event_id = self.headers["X-VoxNeRF-Event-Id"]
            seen = any(headers["X-VoxNeRF-Event-Id"] == event_id for headers, _, _ in receiver.calls)
            status = 204 if seen else 500
            receiver.calls.append((dict(self.headers), body, status))
        self.send_response(status)
        self.send_header("Content-Length", "0")
        self.end_headers()

    def log_message(self, *_args) -> None:
        pass


@pytest.fixture(scope="module")
def receiver():
    server = Receiver()
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    try:
        yield server
    finally:
        server.shutdown()
        server.server_close()


@pytest.fixture(scope="module")
def service(tmp_path_factory):
    svc = start_service(tmp_path_factory.mktemp("events"), token=TOKEN, settings={
        "VOXNERF_WEBHOOK_ALLOW_PRIVATE": "1",
        "VOXNERF_WEBHOOK_RETRY_S": "0.5",
        "VOXNERF_WEBHOOK_POLL_S": "0.2",
        "VOXNERF_EVENT_POLL_S": "0.2",
        "VOXNERF_PROGRESS_INTERVAL_S": "0.2",
    })
    try:
        yield svc
    finally:
        svc.stop()


@pytest.fixture(scope="module")
def tokens(service) -> dict[str, dict]:
    """Named tokens made by the admin: ``ci`` (scope write, makes the job) and ``viewer`` (scope read)."""
    with service.client() as client:
        made = {name: client.post("/tokens", json={"name": name, "scope": scope}) for name, scope in
                (("ci", "write"), ("viewer", "read"))}
    assert all(response.status_code == 201 for response in made.values()), made
    return {name: response.json() for name, response in made.items()}


def bearer(token: dict) -> dict[str, str]:
    return {"Authorization": f"Bearer {token['token']}"}


@pytest.fixture(scope="module")
def job(service, receiver, small_room, tokens):
    """A short job made by token ``ci`` with the receiver as its callback_url, just created."""
    with service.client(auth=False) as client:
        client.headers.update(bearer(tokens["ci"]))
        scene = upload_scene(client, small_room)
        response = client.post(f"/scenes/{scene['id']}/jobs", json={**JOB, "callback_url": receiver.url})
    assert response.status_code == 202, response.text
    assert response.json()["callback_url"] == receiver.url
    return response.json()


def test_a_jobs_stream_runs_from_queued_to_its_final_state_and_resumes_without_repeats(service, job, tokens):
    path = f"/jobs/{job['id']}/events"
    with service.client(auth=False, timeout_s=TIMEOUT_S) as client:  # a read token may follow any job's events
        client.headers.update(bearer(tokens["viewer"]))
        assert client.post(f"/jobs/{job['id']}/cancel").status_code == 403  # and may not act on it
        with client.stream("GET", path) as response:
            assert response.status_code == 200, response.read()
            assert response.headers["content-type"].startswith("text/event-stream")
            first, _ = read_events(response.iter_lines(), stop=lambda e: e["event"] == "stage")
        resumed_after = first[-1]["id"]
        with client.stream("GET", path, headers={"Last-Event-ID": str(resumed_after)}) as response:
            assert response.status_code == 200
            rest, _ = read_events(response.iter_lines())
        whole = first + rest
        ids = [e["id"] for e in whole]
        assert ids == sorted(set(ids)), f"an event came twice or out of order: {ids}"
        assert all(e["id"] > resumed_after for e in rest)
        states = [e["data"]["state"] for e in whole if e["event"] == "state"]
        assert states == ["queued", "running", "succeeded"], (states, service.logs())
        assert whole[0]["event"] == "state" and whole[-1]["event"] == "state" and whole[-1] is rest[-1]
        final = whole[-1]["data"]
        assert final["id"] == job["id"] and final["progress"] == 1.0 and final["metrics"]
        assert final == client.get(f"/jobs/{job['id']}").json()  # the job as GET /jobs/{id} returns it
        stages = [e["data"]["name"] for e in whole if e["event"] == "stage"]
        assert set(stages) >= SET_UP_STAGES and "final_eval" in stages, stages
        assert [e["data"]["name"] for e in rest if e["event"] == "stage"] == stages[1:]  # the one read is not resent
        evaluations = [e["data"] for e in whole if e["event"] == "evaluation"]
        assert evaluations and evaluations[-1]["final"] and evaluations[-1]["psnr"]
        assert any(e["event"] == "progress" and e["data"]["state"] == "running" for e in whole)

        # after the end: a replay ends the same way; a client that saw the final event is told there is no more
        with client.stream("GET", path) as response:
            replay, _ = read_events(response.iter_lines())
        assert [e for e in replay if e["event"] != "progress"] == [e for e in whole if e["event"] != "progress"]
        assert client.get(path, headers={"Last-Event-ID": str(ids[-1])}).status_code == 204
        with client.stream("GET", path, headers={"Last-Event-ID": str(ids[0])}) as response:
            just_final, _ = read_events(response.iter_lines())
        assert just_final == [whole[-1]]
        assert client.get(path, headers={"Last-Event-ID": "seven"}).status_code == 422
        assert service.client(auth=False).get(path).status_code == 401


def test_each_state_change_is_posted_signed_and_retried_after_a_500(service, receiver, job, tokens):
    with service.client() as client:
        deliveries = wait_for(
            lambda: (d := client.get(f"/jobs/{job['id']}/deliveries").json())
            and len(d) == 3 and all(x["outcome"] == "delivered" for x in d) and d,
            TIMEOUT_S, "the three state changes to be delivered",
        )
    assert [d["state"] for d in deliveries] == ["queued", "running", "succeeded"]
    for delivery in deliveries:
        assert [(a["attempt"], a["status"]) for a in delivery["attempts"]] == [(1, 500), (2, 204)], delivery
        assert "HTTP 500" in delivery["attempts"][0]["error"] and delivery["attempts"][1]["error"] is None
        assert delivery["next_attempt_at"] is None

    secret = bytes.fromhex(tokens["ci"]["webhook_secret"])  # the secret of the token that made the job
    delivered = [(headers, body) for headers, body, status in receiver.calls if status == 204]
    assert len(receiver.calls) == 6 and len(delivered) == 3
    for headers, body in delivered:
        timestamp = headers["X-VoxNeRF-Timestamp"]
        expected = "sha256=" + hmac.new(secret, f"{timestamp}.".encode() + body, hashlib.sha256).hexdigest()
        assert hmac.compare_digest(headers["X-VoxNeRF-Signature"], expected)
        assert abs(time.time() - int(timestamp)) < TIMEOUT_S
        payload = json.loads(body)
        assert payload["job_id"] == job["id"] and payload["job"]["state"] == payload["state"]
        assert str(payload["event_id"]) == headers["X-VoxNeRF-Event-Id"]
    # deliveries due together are sent at once, so they may arrive in any order: event_id orders them
    payloads = sorted((json.loads(body) for _, body in delivered), key=lambda payload: payload["event_id"])
    assert [payload["state"] for payload in payloads] == ["queued", "running", "succeeded"]


RUNNING_PAGE_SHOWS_PROGRESS = """() => document.body.dataset.state === 'running'
  && Number(document.querySelector('#summary [role=progressbar]').getAttribute('aria-valuenow')) > 0"""


def test_the_job_page_follows_a_running_job_from_its_events_without_polling(service, small_room):
    with service.client() as client:
        scene = upload_scene(client, small_room)
        job = client.post(f"/scenes/{scene['id']}/jobs", json={"max_seconds": 10, "compile": False,
                                                                 "downscale": 4}).json()
    with browser_page(1200, 800) as page:
        csp = csp_reports(page)
        requests: list[str] = []
        page.on("request", lambda request: requests.append(f"{request.method} {request.url}"))
        page.goto(service.base_url + "/")
        page.evaluate(f"localStorage.setItem('voxnerf.token', {json.dumps(TOKEN)})")
        page.goto(f"{service.base_url}/static/job.html?id={job['id']}")
        page.wait_for_function(RUNNING_PAGE_SHOWS_PROGRESS, timeout=TIMEOUT_S * 1000)
        progress_seen = int(page.get_attribute("#summary [role=progressbar]", "aria-valuenow"))
        page.wait_for_selector('body[data-state="succeeded"]', timeout=TIMEOUT_S * 1000)
        assert page.inner_text("#job-state") == "succeeded" and progress_seen < 100
        assert page.eval_on_selector_all("#stages tbody tr", "rows => rows.length") >= len(SET_UP_STAGES)
    job_url = f"{service.base_url}/jobs/{job['id']}"
    assert requests.count(f"GET {job_url}") == 1, [r for r in requests if "/jobs/" in r]  # no polling
    assert requests.count(f"GET {job_url}/events") == 1  # one stream, from the first event to the final state
    assert not csp, csp


# ------------------------------------------------------------------------------------------------ no workers


IDLE_SETTINGS = {"VOXNERF_MAX_EVENT_STREAMS": "1", "VOXNERF_EVENT_KEEPALIVE_S": "0.5", "VOXNERF_EVENT_POLL_S": "0.1"}


@pytest.fixture(scope="module")
def idle_service(tmp_path_factory):
    """An API without workers (its jobs stay queued) and without the allow-private setting."""
    svc = start_service(tmp_path_factory.mktemp("events_idle"), token=TOKEN, workers=False, settings=IDLE_SETTINGS)
    try:
        yield svc
    finally:
        svc.stop()


def test_a_queued_jobs_stream_keeps_alive_is_bounded_and_ends_when_it_is_cancelled(idle_service, small_room):
    check_a_queued_jobs_stream(idle_service, small_room)


def test_the_stream_is_the_same_with_the_redis_broker(tmp_path, small_room):
    redis = start_redis(tmp_path / "redis")
    try:
        service = start_service(tmp_path / "svc", broker_url=redis.url, token=TOKEN, workers=False,
                                settings=IDLE_SETTINGS)
        try:
            check_a_queued_jobs_stream(service, small_room)
        finally:
            service.stop()
    finally:
        redis.stop()


def check_a_queued_jobs_stream(service, small_room) -> None:
    """A job no worker takes: its stream sends its queued state, then keep-alives; a second stream is refused
    (the limit is 1); a cancel ends the first with the cancelled state; the slot is given back."""
    with service.client(timeout_s=60) as client:
        scene = upload_scene(client, small_room)
        job = client.post(f"/scenes/{scene['id']}/jobs", json=JOB).json()
        path = f"/jobs/{job['id']}/events"
        with client.stream("GET", path) as response:
            assert response.status_code == 200
            lines = response.iter_lines()
            (queued,), _ = read_events(lines, stop=lambda e: True)
            assert queued == {"id": 1, "event": "state", "data": client.get(f"/jobs/{job['id']}").json()}
            assert next(lines) == ": keep-alive"  # nothing happens: a comment every 0.5 s
            refused = client.get(path)  # the one stream allowed is open
            assert refused.status_code == 429 and refused.headers["retry-after"] and refused.json()["detail"]
            cancelled = client.post(f"/jobs/{job['id']}/cancel")
            assert cancelled.status_code == 202
            rest, _ = read_events(lines)
        assert [(e["id"], e["event"], e["data"]["state"]) for e in rest] == [(2, "state", "cancelled")]
        wait_for(lambda: client.get(path, headers={"Last-Event-ID": "1"}).status_code == 200, 10,
                 "the stream's slot to be given back")
        assert client.get(f"/jobs/{'0' * 32}/events").status_code == 404
        assert client.get(f"/jobs/{'0' * 32}/deliveries").status_code == 404
        assert client.get(f"/jobs/{job['id']}/deliveries").json() == []  # no callback_url, no deliveries


def test_open_streams_end_when_the_server_stops(idle_service, small_room):
    """uvicorn waits for every open response before it stops: a stream of a job that stays queued must end."""
    with idle_service.client(timeout_s=60) as client:
        scene = upload_scene(client, small_room)
        job = client.post(f"/scenes/{scene['id']}/jobs", json=JOB).json()
        with client.stream("GET", f"/jobs/{job['id']}/events") as response:
            lines = response.iter_lines()
            (queued,), _ = read_events(lines, stop=lambda e: True)
            api = idle_service.procs.pop("api")
            started = time.monotonic()
            api.send_signal(signal.SIGTERM)
            try:
                api.wait(timeout=15)
            finally:
                stop_process(api)  # still running: the test fails, and nothing is left behind
            rest, _ = read_events(lines)
        stopped_in = time.monotonic() - started
    idle_service.start_api()
    wait_for(idle_service.answers, 60, "the API to answer again")
    assert queued["data"]["state"] == "queued" and rest == [] and stopped_in < 10, (stopped_in, idle_service.logs())


@pytest.mark.parametrize("url", [
    "http://127.0.0.1:9/hook", "http://localhost/hook", "http://[::1]/hook", "http://10.1.2.3/hook",
    "http://169.254.169.254/latest", "http://192.168.0.10/", "http://[::ffff:127.0.0.1]/", "http://0.0.0.0/",
])
def test_private_and_loopback_callbacks_are_refused_without_the_setting(idle_service, url):
    with idle_service.client() as client:
        response = client.post(f"/scenes/{'0' * 32}/jobs", json={**JOB, "callback_url": url})
    assert response.status_code == 422, response.text
    assert "VOXNERF_WEBHOOK_ALLOW_PRIVATE" in response.json()["detail"]


def test_callback_urls_are_checked_before_the_job_is_made(idle_service):
    with idle_service.client() as client:
        for url, why in [("ftp://example.org/x", "http or https"), ("http://user:pw@93.184.215.14/", "credentials"),
                         ("http:///nohost", "no host"), ("http://no-such-host.invalid/", "does not resolve")]:
            response = client.post(f"/scenes/{'0' * 32}/jobs", json={**JOB, "callback_url": url})
            assert response.status_code == 422 and why in response.json()["detail"], (url, response.text)
        public = client.post(f"/scenes/{'0' * 32}/jobs", json={**JOB, "callback_url": "https://93.184.215.14/h"})
        assert public.status_code == 404  # the URL passed; the scene does not exist


def test_address_rules_and_the_signature():
    assert checked_addresses("http://127.0.0.1:8/x", allow_private=True) == ["127.0.0.1"]
    assert checked_addresses("https://93.184.215.14/x", allow_private=False) == ["93.184.215.14"]
    for url in ("http://224.0.0.1/", "http://240.0.0.1/", "http://100.64.0.1/", "http://[fe80::1]/"):
        with pytest.raises(CallbackRefused):
            checked_addresses(url, allow_private=False)
    mac = hmac.new(b"k", b"1700000000.{}", hashlib.sha256).hexdigest()
    assert signature(b"k", "1700000000", b"{}") == f"sha256={mac}"


def test_webhook_secrets_of_the_principals_without_named_tokens(tmp_path):
    tokenless = Settings(data_dir=tmp_path / "data")
    secret = webhook_secret(tokenless, "local")
    path = tmp_path / "data" / "webhook_secret"
    assert len(secret) == 32 and path.read_bytes() == secret and path.stat().st_mode & 0o777 == 0o600
    assert webhook_secret(tokenless, "local") == secret  # made once
    with pytest.raises(TokenError):
        webhook_secret(tokenless, "admin")  # no VOXNERF_API_TOKEN
    with_token = Settings(data_dir=tmp_path / "data", api_token=TOKEN)
    assert webhook_secret(with_token, "admin") == hmac.new(TOKEN.encode(), b"voxnerf-webhook", hashlib.sha256).digest()
    with pytest.raises(TokenError):
        webhook_secret(with_token, "ci")
