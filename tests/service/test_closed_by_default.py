"""Closed by default (issue #22, item 2): without a token the service serves loopback only and refuses to bind
beyond it; cross-site state changes are refused with or without a token; no CDN (/docs and /redoc load nothing from
outside); the
dashboard's security headers; docs/service.md names exactly the open paths; an anonymous /healthz is a cheap,
shared, status-only answer that a flood cannot use to tie up the API's threads.

Real parts: uvicorn serving the app on 127.0.0.1 in a thread (or httpx's ASGI transport where a remote client
address is needed), and ``voxnerf serve`` / ``python -m app.serve`` as subprocesses. No workers run, so a
health check's worker inspection waits its full timeout; one test holds the inspection until released.
"""

from __future__ import annotations

import asyncio
import io
import os
import re
import subprocess
import sys
import threading
import time
import zipfile
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from pathlib import Path

import httpx
import pytest
import uvicorn
from service_fixtures import REPO, free_port, wait_for
from starlette.routing import Mount, Route

from app.core.settings import Settings
from app.main import STATIC_DIR, create_app
from app.origin_guard import UnsafeBindError, check_bind, is_loopback

TOKEN = "closed-token"
EVIL = "http://evil.example"
JOB_ID = "0" * 32
DOC = REPO / "docs" / "service.md"


def _settings(root: Path, **overrides) -> Settings:
    values = {"data_dir": root / "data", "device": "cpu", "sweep_interval_s": 3600.0, "health_timeout_s": 0.2}
    return Settings(**{**values, **overrides})


@contextmanager
def _serving(settings: Settings) -> Iterator[tuple[str, object]]:
    """``(base_url, app)``: the app for ``settings`` served by uvicorn on a free loopback port in a thread."""
    app = create_app(settings)
    server = uvicorn.Server(uvicorn.Config(app, host="127.0.0.1", port=free_port(), log_level="warning"))
    thread = threading.Thread(target=server.run, daemon=True)
    thread.start()
    try:
        wait_for(lambda: server.started, 60, "uvicorn to start")
        yield f"http://127.0.0.1:{server.config.port}", app
    finally:
        server.should_exit = True
        thread.join(30)


@pytest.fixture(scope="module", params=[None, TOKEN], ids=["no-token", "token"])
def served(request, tmp_path_factory) -> Iterator[tuple[str, str | None]]:
    """``(base_url, token)`` of a served app without a token, then with one."""
    with _serving(_settings(tmp_path_factory.mktemp("closed"), api_token=request.param)) as (url, _app):
        yield url, request.param


def _client(base_url: str, token: str | None = None) -> httpx.Client:
    headers = {"Authorization": f"Bearer {token}"} if token else {}
    return httpx.Client(base_url=base_url, headers=headers, timeout=30, trust_env=False)


def _tiny_zip() -> bytes:
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w") as archive:
        archive.writestr("room/readme.txt", "not a scene")
    return buffer.getvalue()


# --- binding beyond loopback -------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("host", "loopback"),
    [("127.0.0.1", True), ("127.8.9.10", True), ("localhost", True), ("::1", True), ("[::1]", True),
     ("::ffff:127.0.0.1", True), ("0.0.0.0", False), ("::", False), ("192.0.2.7", False), ("", False),
     ("example.org", False)],
)
def test_is_loopback(host: str, loopback: bool):
    assert is_loopback(host) is loopback


def test_check_bind_refuses_every_interface_without_a_token(tmp_path):
    with pytest.raises(UnsafeBindError, match="VOXNERF_API_TOKEN"):
        check_bind("0.0.0.0", _settings(tmp_path))
    check_bind("127.0.0.1", _settings(tmp_path))
    check_bind("0.0.0.0", _settings(tmp_path, api_token=TOKEN))
    check_bind("0.0.0.0", _settings(tmp_path, allow_unauthenticated_remote=True))


def _env(tmp_path: Path, **extra: str) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if not k.startswith("VOXNERF_")}
    env.update({"VOXNERF_DATA_DIR": str(tmp_path / "data"), "PYTHONPATH": str(REPO), "NO_PROXY": "*"}, **extra)
    return env


@pytest.mark.parametrize(
    "command",
    [["-m", "voxnerf", "serve"], ["-m", "app.serve", "--api-only"]],
    ids=["voxnerf-serve", "api-entry"],
)
def test_serving_every_interface_without_a_token_refuses_to_start(tmp_path, command):
    result = subprocess.run(
        [sys.executable, *command, "--host", "0.0.0.0", "--port", str(free_port())],
        cwd=REPO, env=_env(tmp_path), capture_output=True, text=True, timeout=120,
    )
    assert result.returncode == 2, result.stderr
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and "refusing to serve on 0.0.0.0 without VOXNERF_API_TOKEN" in lines[0], lines
    assert not (tmp_path / "data").exists(), "nothing is started or created before the refusal"


def test_the_opt_out_serves_every_interface_with_a_loud_warning(tmp_path):
    port = free_port()
    log_path = tmp_path / "api.log"
    with open(log_path, "wb") as log:
        proc = subprocess.Popen(
            [sys.executable, "-m", "app.serve", "--api-only", "--host", "0.0.0.0", "--port", str(port)],
            cwd=REPO, env=_env(tmp_path, VOXNERF_ALLOW_UNAUTHENTICATED_REMOTE="1"),
            stdout=log, stderr=subprocess.STDOUT, start_new_session=True,
        )
    try:
        wait_for(lambda: "WARNING" in log_path.read_text(), 90, "the start-up warning")
        assert "SERVING WITHOUT AUTHENTICATION" in log_path.read_text()
    finally:
        proc.terminate()
        proc.wait(30)


# --- remote clients without a token --------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("overrides", "allowed"),
    [({}, False), ({"api_token": TOKEN}, True), ({"allow_unauthenticated_remote": True}, True)],
    ids=["no-token", "token", "opt-out"],
)
def test_a_remote_client_is_refused_without_a_token(tmp_path, overrides, allowed):
    app = create_app(_settings(tmp_path, **overrides))

    async def get(client_address: str) -> httpx.Response:
        transport = httpx.ASGITransport(app=app, client=(client_address, 40000))
        async with httpx.AsyncClient(transport=transport, base_url="http://127.0.0.1:8000") as client:
            return await client.get("/")  # the dashboard's shell: open without a token

    remote = asyncio.run(get("203.0.113.9"))
    if allowed:
        assert remote.status_code == 200
    else:
        assert remote.status_code == 403 and "only loopback clients" in remote.json()["detail"]
    assert asyncio.run(get("127.0.0.1")).status_code == 200


# --- cross-site state changes --------------------------------------------------------------------------------


CROSS_SITE = [{"Origin": EVIL}, {"Sec-Fetch-Site": "cross-site"}, {"Origin": "null"},
              {"Origin": "http://127.0.0.1:1"}]


@pytest.mark.parametrize("headers", CROSS_SITE, ids=["origin", "sec-fetch-site", "null-origin", "other-port"])
def test_cross_site_writes_are_refused_with_and_without_a_token(served, headers):
    url, token = served
    with _client(url, token) as client:
        upload = client.post("/scenes", files={"file": ("s.zip", _tiny_zip(), "application/zip")}, headers=headers)
        cancel = client.post(f"/jobs/{JOB_ID}/cancel", headers=headers)
        delete = client.delete(f"/scenes/{JOB_ID}", headers=headers)
    for response in (upload, cancel, delete):
        assert response.status_code == 403, response.text
        assert response.json()["detail"].startswith("cross-site request refused")


def test_same_origin_and_origin_less_writes_pass(served):
    url, token = served
    same_origin = {"Origin": url, "Sec-Fetch-Site": "same-origin"}
    with _client(url, token) as client:
        for headers in (same_origin, {}):  # the dashboard's fetch; curl
            upload = client.post(
                "/scenes", files={"file": ("s.zip", _tiny_zip(), "application/zip")}, headers=headers
            )
            # reached the upload's validation, which refuses a zip that is no scene
            assert 400 <= upload.status_code < 500 and upload.status_code != 403, upload.text
            assert client.post(f"/jobs/{JOB_ID}/cancel", headers=headers).status_code == 404
        assert client.get("/jobs", headers={"Origin": EVIL}).status_code == 200  # reads are not refused


# --- no CDN, security headers, open paths --------------------------------------------------------------------


def test_docs_pages_from_this_host_and_a_dashboard_without_outside_urls(served):
    url, token = served
    with _client(url) as client:
        for page in ("/docs", "/redoc"):  # shells of scripts served here (tests/service/test_api_reference.py)
            assert client.get(page).status_code == 200
        assert client.get("/openapi.json").status_code == (401 if token else 200)
        shell = client.get("/")
        script = client.get("/static/dashboard.js")
    for response in (shell, script):
        assert response.status_code == 200
        policy = response.headers["content-security-policy"]
        assert "default-src 'self'" in policy and "frame-ancestors 'none'" in policy
        assert "'unsafe-inline'" not in policy
        assert response.headers["x-content-type-options"] == "nosniff"
    for path in [STATIC_DIR / "index.html", *sorted(STATIC_DIR.glob("*.css"))]:
        assert not re.search(r"https?://", path.read_text()), f"{path.name} references an outside URL"
    html = shell.text  # what the policy forbids: inline scripts, inline event handlers, style attributes
    assert not re.search(r"<script(?![^>]*\bsrc=)", html) and not re.search(r"<[^>]*\son[a-z]+\s*=", html)
    assert not re.search(r"<[^>]*\sstyle\s*=", html)


def _every_route(app) -> set[str]:
    """``METHOD path`` of every route: the OpenAPI schema's and the app's own top-level routes (the
    dashboard shell, the schema itself, ``/static/*`` for the static mount)."""
    found = {f"{m.upper()} {path}" for path, ops in app.openapi()["paths"].items() for m in ops}
    for route in app.routes:
        if isinstance(route, Mount):
            found.add(f"GET {route.path}/*")
        elif isinstance(route, Route):  # APIRoute included
            found.update(f"{m} {route.path}" for m in route.methods - {"HEAD"})
    return found


def _example_url(path: str) -> str:
    """A concrete URL for a route's path: ids and path parameters filled in, ``/*`` a real static file."""
    path = path.replace("/*", "/dashboard.js")
    return re.sub(r"\{[^}]+\}", lambda m: JOB_ID if m[0].endswith("id}") else "x", path)


def test_docs_list_exactly_the_paths_open_without_a_token(tmp_path):
    """Each route asked without a token (over the ASGI transport, from loopback): 401 or not, against the
    list in docs/service.md."""
    paragraph = next(x for x in DOC.read_text().split("\n\n") if x.startswith("**Open without a token**"))
    documented = set(re.findall(r"`((?:GET|POST|PUT|PATCH|DELETE) [^`]+)`", paragraph))
    app = create_app(_settings(tmp_path, api_token=TOKEN))

    async def open_routes() -> set[str]:
        transport = httpx.ASGITransport(app=app, client=("127.0.0.1", 40000))
        async with httpx.AsyncClient(transport=transport, base_url="http://127.0.0.1") as client:
            found = set()
            for route in sorted(_every_route(app)):
                method, path = route.split(" ", 1)
                if (await client.request(method, _example_url(path))).status_code != 401:
                    found.add(route)
            return found

    assert documented == asyncio.run(open_routes())


# --- /healthz -----------------------------------------------------------------------------------------------


def test_anonymous_health_is_status_only_and_the_token_gets_details(tmp_path):
    with _serving(_settings(tmp_path, api_token=TOKEN)) as (url, _app), _client(url) as anonymous:
        bare = anonymous.get("/healthz")
        detailed = anonymous.get("/healthz", headers={"Authorization": f"Bearer {TOKEN}"})
    assert bare.status_code == 503 and bare.json() == {"status": "unavailable"}  # no workers here
    body = detailed.json()
    assert detailed.status_code == 503 and body["database"]["ok"] and body["broker"]["ok"]
    assert body["workers"] == {"train": [], "render": []}


def test_without_a_token_set_every_caller_gets_the_details(tmp_path):
    with _serving(_settings(tmp_path)) as (url, _app), _client(url) as client:
        assert set(client.get("/healthz").json()) == {"status", "database", "broker", "workers"}


def test_a_health_flood_runs_one_inspection_and_blocks_no_other_request(tmp_path):
    """50 anonymous /healthz at once while the inspection is held: GET /jobs still answers, then all 50
    get the one check's status; more anonymous calls within health_cache_s reuse it."""
    settings = _settings(tmp_path, api_token=TOKEN, health_cache_s=60.0)
    with _serving(settings) as (url, app):
        control = app.state.celery.control
        real_inspect = control.inspect
        inspections: list[float] = []
        started, release = threading.Event(), threading.Event()

        def held_inspect(*args, **kwargs):
            inspections.append(time.monotonic())
            started.set()
            release.wait(60)
            return real_inspect(*args, **kwargs)

        control.inspect = held_inspect
        with ThreadPoolExecutor(50) as pool, _client(url, TOKEN) as holder:
            try:
                flood = [pool.submit(httpx.get, f"{url}/healthz", timeout=90, trust_env=False) for _ in range(50)]
                assert started.wait(60), "no health check started"
                meanwhile = holder.get("/jobs", timeout=20)
                pending = sum(not f.done() for f in flood)
            finally:
                release.set()
            answers = [f.result() for f in flood]
            again = [httpx.get(f"{url}/healthz", timeout=30, trust_env=False) for _ in range(5)]
    assert meanwhile.status_code == 200 and meanwhile.json() == []
    assert pending > 0, "the flood had finished before GET /jobs answered: nothing was shown"
    assert {(r.status_code, r.text) for r in answers + again} == {(503, '{"status":"unavailable"}')}
    assert len(inspections) <= 2, f"{len(inspections)} worker inspections for 55 anonymous calls"
