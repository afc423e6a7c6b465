"""voxnerf.client against tiny real HTTP servers on loopback that answer as the service would when it is busy,
unavailable, not yet listening or streaming events: retries with back-off (Retry-After honoured), the one-line
error of a refusal, and an event stream followed across a dropped connection with ``Last-Event-ID``."""

from __future__ import annotations

import json
import threading
import time
from collections.abc import Callable
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

import pytest
from service_fixtures import free_port

from app.core.models import ImportRow, JobRow
from app.schemas import ImportOut, JobOut
from voxnerf.client import ApiError, Client
from voxnerf.errors import VoxNeRFError

JOB_ID = "ab" * 16
SCENE_ID = "cd" * 16


class Recorder:
    """What the tiny server saw: each request's method, path and headers."""

    def __init__(self) -> None:
        self.requests: list[tuple[str, str, dict]] = []
        self.times: list[float] = []
        self.bodies: list[bytes] = []


def _serve(answer: Callable[[BaseHTTPRequestHandler, int], None], port: int | None = None):
    """A threaded HTTP server on 127.0.0.1 whose every request is answered by ``answer(handler, n)`` (n: the
    request's number, from 0); the server and its recorder."""
    recorder = Recorder()

    class Handler(BaseHTTPRequestHandler):
        protocol_version = "HTTP/1.1"

        def _any(self) -> None:
            length = int(self.headers.get("content-length") or 0)
            recorder.bodies.append(self.rfile.read(length) if length else b"")
            recorder.requests.append((self.command, self.path, dict(self.headers)))
            recorder.times.append(time.monotonic())
            answer(self, len(recorder.requests) - 1)

        do_GET = do_POST = do_PUT = do_DELETE = _any

        def log_message(self, *_args) -> None:
            pass

    server = ThreadingHTTPServer(("127.0.0.1", port or 0), Handler)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    return server, recorder


def _reply(handler: BaseHTTPRequestHandler, status: int, body: object, headers: dict | None = None) -> None:
    data = json.dumps(body).encode()
    handler.send_response(status)
    handler.send_header("Content-Type", "application/json")
    handler.send_header("Content-Length", str(len(data)))
    for key, value in (headers or {}).items():
        handler.send_header(key, value)
    handler.end_headers()
    handler.wfile.write(data)


def _job(state: str) -> dict:
    """A job as GET /jobs/{id} answers it, made from a (never stored) row of the jobs table."""
    row = JobRow(id=JOB_ID, scene_id=SCENE_ID, state=state, cancel_requested=False, options={"max_iters": 2},
                 attempt=1, requeues=0, created_at=1.0e9)
    return JobOut.from_row(row).model_dump(mode="json")


@pytest.fixture
def servers():
    started = []

    def start(answer, port=None):
        server, recorder = _serve(answer, port)
        started.append(server)
        return server, recorder

    yield start
    for server in started:
        server.shutdown()
        server.server_close()


def test_503_then_200_is_retried_with_back_off(servers):
    def answer(handler, n):
        if n < 2:
            _reply(handler, 503, {"detail": "the train queue is unavailable; try again later"})
        else:
            _reply(handler, 200, [])

    server, seen = servers(answer)
    with Client(f"http://127.0.0.1:{server.server_port}", "t0ken", backoff_s=0.2) as client:
        assert client.scenes() == []
    assert len(seen.requests) == 3
    assert all(headers["Authorization"] == "Bearer t0ken" for _, _, headers in seen.requests)
    gaps = [b - a for a, b in zip(seen.times, seen.times[1:], strict=False)]
    assert gaps[0] >= 0.09 and gaps[1] >= 0.19  # 0.2 x 2^n, jittered down to half at most


def test_429_waits_as_long_as_retry_after_says_and_a_post_is_retried(servers):
    def answer(handler, n):
        if n == 0:
            _reply(handler, 429, {"detail": "100 jobs queued"}, {"Retry-After": "1"})
        else:
            _reply(handler, 202, _job("queued"))

    server, seen = servers(answer)
    with Client(f"http://127.0.0.1:{server.server_port}", backoff_s=0.01) as client:
        job = client.train(SCENE_ID, max_iters=2)
    assert job.id == JOB_ID and job.state == "queued"
    assert [method for method, _, _ in seen.requests] == ["POST", "POST"]
    assert json.loads(seen.bodies[0]) == json.loads(seen.bodies[1]) == {"max_iters": 2}  # the options as set
    assert seen.times[1] - seen.times[0] >= 0.95


def test_a_refusal_beyond_the_retries_is_one_line_with_the_server_s_detail(servers):
    server, seen = servers(lambda handler, n: _reply(handler, 503, {"detail": "broker\ndown"}))
    with Client(f"http://127.0.0.1:{server.server_port}", retries=2, backoff_s=0.01) as client, \
            pytest.raises(ApiError) as refused:
        client.job(JOB_ID)
    assert len(seen.requests) == 3
    assert refused.value.status == 503 and str(refused.value) == "broker down (HTTP 503)"

    server, seen = servers(lambda handler, n: _reply(handler, 404, {"detail": f"no job {JOB_ID}"}))
    with Client(f"http://127.0.0.1:{server.server_port}", backoff_s=0.01) as client, \
            pytest.raises(ApiError, match=f"no job {JOB_ID}"):
        client.job(JOB_ID)
    assert len(seen.requests) == 1  # a 404 is not retried


def test_bad_options_are_refused_before_anything_is_sent(servers):
    server, seen = servers(lambda handler, n: _reply(handler, 202, _job("queued")))
    with Client(f"http://127.0.0.1:{server.server_port}") as client:
        with pytest.raises(ValueError, match="max_seconds or max_iters"):
            client.train(SCENE_ID, seed=1)
        with pytest.raises(ValueError, match="max_iters"):
            client.train(SCENE_ID, max_iters=float("nan"))
    assert seen.requests == []


def test_a_service_not_listening_yet_is_retried_until_it_is(servers):
    port = free_port()
    threading.Timer(0.8, lambda: servers(lambda handler, n: _reply(handler, 200, []), port)).start()
    with Client(f"http://127.0.0.1:{port}", backoff_s=0.2, retries=8) as client:
        assert client.scenes() == []
    with Client(f"http://127.0.0.1:{free_port()}", backoff_s=0.01, retries=1) as client, \
            pytest.raises(ApiError, match="cannot reach"):
        client.scenes()


def _sse(handler, events: list[tuple[int, str, dict]], close_early: bool) -> None:
    """Stream ``events`` as text/event-stream (chunked, as a streaming response is), then end the stream, or
    drop the connection without ending it (``close_early``)."""
    handler.send_response(200)
    handler.send_header("Content-Type", "text/event-stream")
    handler.send_header("Transfer-Encoding", "chunked")
    handler.end_headers()
    for event_id, name, data in events:
        text = f": keep-alive\n\nid: {event_id}\nevent: {name}\ndata: {json.dumps(data)}\n\n".encode()
        handler.wfile.write(f"{len(text):x}\r\n".encode() + text + b"\r\n")
        handler.wfile.flush()
    if close_early:
        handler.close_connection = True
        handler.wfile.flush()
        handler.connection.shutdown(2)
        return
    handler.wfile.write(b"0\r\n\r\n")


def test_wait_follows_the_events_and_resumes_after_a_dropped_stream(servers):
    stage = {"name": "prior", "ran": True, "why": "a mesh prior", "seconds": 0.5}

    def answer(handler, n):
        if n == 0:
            _sse(handler, [(1, "state", _job("running")), (2, "stage", stage)], close_early=True)
        else:
            _sse(handler, [(3, "progress", _job("running")), (4, "state", _job("succeeded"))], close_early=False)

    server, seen = servers(answer)
    events = []
    with Client(f"http://127.0.0.1:{server.server_port}", backoff_s=0.05) as client:
        job = client.wait(JOB_ID, on_event=events.append)
    assert job.state == "succeeded" and job.id == JOB_ID
    assert [(e.id, e.event) for e in events] == [(1, "state"), (2, "stage"), (3, "progress"), (4, "state")]
    assert events[1].data == stage
    assert [path for _, path, _ in seen.requests] == [f"/jobs/{JOB_ID}/events"] * 2
    first, second = (headers for _, _, headers in seen.requests)
    assert "Last-Event-ID" not in first and second["Last-Event-ID"] == "2"
    assert second["Accept"] == "text/event-stream"


def test_wait_asks_for_the_job_where_the_service_has_no_event_stream(servers):
    def answer(handler, n):
        if handler.path.endswith("/events"):
            _reply(handler, 404, {"detail": "Not Found"})
        else:
            _reply(handler, 200, _job("running" if n < 2 else "failed"))

    server, seen = servers(answer)
    with Client(f"http://127.0.0.1:{server.server_port}") as client:
        assert client.wait(JOB_ID).state == "failed"
    assert [path for _, path, _ in seen.requests] == [f"/jobs/{JOB_ID}/events"] + [f"/jobs/{JOB_ID}"] * 2


def _drop(handler) -> None:
    """Close the connection without answering (the request arrived; its answer is lost)."""
    handler.close_connection = True
    handler.connection.shutdown(2)


def test_a_lost_answer_is_asked_again_for_a_get_but_never_for_a_new_job(servers):
    server, seen = servers(lambda handler, n: _drop(handler) if n == 0 else _reply(handler, 200, []))
    with Client(f"http://127.0.0.1:{server.server_port}", backoff_s=0.01) as client:
        assert client.scenes() == []
    assert len(seen.requests) == 2

    server, seen = servers(lambda handler, n: _drop(handler))
    with Client(f"http://127.0.0.1:{server.server_port}", backoff_s=0.01) as client, \
            pytest.raises(ApiError, match="the connection failed"):
        client.train(SCENE_ID, max_iters=2)
    assert len(seen.requests) == 1  # the job may exist: sending it again could train it twice


IMPORT_ID = "ef" * 16


def _import(state: str, error: str | None = None) -> dict:
    """A capture import as GET /imports/{id} answers it, made from a (never stored) row of the imports table."""
    row = ImportRow(id=IMPORT_ID, name="walk", layout="video", state=state, stage=None, params={}, size_bytes=10,
                    progress=1.0 if state == "succeeded" else 0.0, scene_id=SCENE_ID if state == "succeeded" else None,
                    error=error, cancel_requested=False, attempt=1, requeues=0, created_at=1.0e9)
    return ImportOut.from_row(row).model_dump(mode="json")


SCENE = {"id": SCENE_ID, "name": "walk", "created_at": "2026-01-01T00:00:00Z", "size_bytes": 1,
         "summary": {"frames": 3, "splits": {"train": 3}, "image_size": [4, 3], "prior": None, "depth": False}}


def _capture_service(final: dict):
    """Answers of a service that queues the import of an uploaded capture: 202, then the import running, then
    ``final``, then the scene."""
    def answer(handler, n):
        if handler.command == "POST":
            _reply(handler, 202, _import("queued"), {"Location": f"/imports/{IMPORT_ID}"})
        elif handler.path == f"/imports/{IMPORT_ID}":
            _reply(handler, 200, _import("running") if n < 2 else final)
        else:
            _reply(handler, 200, SCENE)

    return answer


def test_an_uploaded_capture_s_import_is_waited_for_and_its_failure_is_one_line(servers, tmp_path):
    capture = tmp_path / "walk.mp4"
    capture.write_bytes(b"\x00\x00\x00\x18ftypmp42" + bytes(100))
    server, seen = servers(_capture_service(_import("succeeded")))
    with Client(f"http://127.0.0.1:{server.server_port}") as client:
        scene = client.upload(capture)
        assert scene.id == SCENE_ID and scene.summary.frames == 3
        assert [path for _, path, _ in seen.requests] == ["/scenes", *[f"/imports/{IMPORT_ID}"] * 2,
                                                          f"/scenes/{SCENE_ID}"]
        assert b'filename="walk.mp4"' in seen.bodies[0] and bytes(100) in seen.bodies[0]
        queued = client.upload(capture, wait=False)
        assert queued.id == IMPORT_ID and queued.state == "queued"

    server, _ = servers(_capture_service(_import("failed", error="no frame sharp enough")))
    with Client(f"http://127.0.0.1:{server.server_port}") as client, \
            pytest.raises(VoxNeRFError, match=f"^import {IMPORT_ID} failed: no frame sharp enough$"):
        client.upload(capture)


def test_the_remote_cli_s_retries_option_sets_the_attempts(servers, capsys):
    from voxnerf.cli import main

    server, seen = servers(lambda handler, n: _reply(handler, 503, {"detail": "broker down"}))
    url = f"http://127.0.0.1:{server.server_port}"
    assert main(["remote", "status", JOB_ID, "--url", url, "--retries", "1"]) == 2
    assert len(seen.requests) == 2
    assert capsys.readouterr().err == "voxnerf: error: broker down (HTTP 503)\n"
    assert main(["remote", "status", JOB_ID, "--url", url, "--retries", "0"]) == 2
    assert len(seen.requests) == 3
    with pytest.raises(SystemExit) as refused:
        main(["remote", "status", JOB_ID, "--url", url, "--retries", "-1"])
    assert refused.value.code == 2 and "--retries: must be >= 0, got -1" in capsys.readouterr().err
    assert len(seen.requests) == 3
