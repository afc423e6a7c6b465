"""DNS rebinding and proxies (issue #42, items 1 and 2): the service answers only its own host names, and a
request that came through a proxy is remote unless ``VOXNERF_TRUSTED_PROXIES`` names that proxy.

Real parts: uvicorn serving the app on 127.0.0.1 in a thread, with the options every entry point uses
(``app.origin_guard.SERVER_OPTIONS``) or with uvicorn's defaults (``uvicorn --factory`` run by hand), and
requests sent over HTTP with the headers a browser on a rebound page or a reverse proxy sends.
"""

from __future__ import annotations

import io
import socket
import threading
import zipfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import httpx
import pytest
import uvicorn
from pydantic import ValidationError
from service_fixtures import free_port, wait_for

from app.core.settings import Settings
from app.main import create_app
from app.origin_guard import SERVER_OPTIONS, host_allowed, log_exposure

TOKEN = "rebinding-token"
JOB_ID = "0" * 32


def _settings(root: Path, **overrides) -> Settings:
    values = {"data_dir": root / "data", "device": "cpu", "sweep_interval_s": 3600.0, "health_timeout_s": 0.2}
    return Settings(**{**values, **overrides})


@contextmanager
def _serving(settings: Settings, **server_options) -> Iterator[str]:
    """The app for ``settings`` served by uvicorn on a free loopback port in a thread: its base URL."""
    config = uvicorn.Config(create_app(settings), host="127.0.0.1", port=free_port(), log_level="warning",
                            **server_options)
    server = uvicorn.Server(config)
    thread = threading.Thread(target=server.run, daemon=True)
    thread.start()
    try:
        wait_for(lambda: server.started, 60, "uvicorn to start")
        yield f"http://127.0.0.1:{config.port}"
    finally:
        server.should_exit = True
        thread.join(30)


def _client(base_url: str, token: str | None) -> httpx.Client:
    headers = {"Authorization": f"Bearer {token}"} if token else {}
    return httpx.Client(base_url=base_url, headers=headers, timeout=30, trust_env=False)


def _tiny_zip() -> bytes:
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w") as archive:
        archive.writestr("room/readme.txt", "not a scene")
    return buffer.getvalue()


def _attack(client: httpx.Client, headers: dict[str, str]) -> list[httpx.Response]:
    """What a page on a rebound name tried on 2026-11-28: read, upload, start a video, delete."""
    upload = ("s.zip", _tiny_zip(), "application/zip")
    return [
        client.get("/scenes", headers=headers),
        client.post("/scenes", files={"file": upload}, headers=headers),
        client.post(f"/jobs/{JOB_ID}/videos", json={"kind": "orbit"}, headers=headers),
        client.delete(f"/scenes/{JOB_ID}", headers=headers),
    ]


@pytest.fixture(scope="module", params=[None, TOKEN], ids=["no-token", "token"])
def served(request, tmp_path_factory) -> Iterator[tuple[str, str | None]]:
    """``(base_url, token)``: served as ``voxnerf serve`` serves, without a token, then with one."""
    settings = _settings(tmp_path_factory.mktemp("rebinding"), api_token=request.param)
    with _serving(settings, **SERVER_OPTIONS) as url:
        yield url, request.param


# --- item 1: DNS rebinding ----------------------------------------------------------------------------------


def test_a_rebound_page_can_neither_read_nor_write(served):
    """``Host: evil.example:8000`` with the matching ``Origin`` (what the browser sends once the page's name
    resolves to 127.0.0.1): every request is a 400 with a JSON detail, with and without a token."""
    url, token = served
    rebound = {"Host": "evil.example:8000", "Origin": "http://evil.example:8000", "Sec-Fetch-Site": "same-origin"}
    with _client(url, token) as client:
        answers = _attack(client, rebound)
    for response in answers:
        assert response.status_code == 400, (response.request.method, response.request.url, response.text)
        detail = response.json()["detail"]
        assert detail.startswith("Host 'evil.example:8000' is not a name this service answers to")
        assert "VOXNERF_ALLOWED_HOSTS" in detail


@pytest.mark.parametrize("name", ["localhost", "127.0.0.1", "[::1]", "LocalHost.", "127.0.0.2"])
@pytest.mark.parametrize("with_port", [True, False], ids=["port", "no-port"])
def test_loopback_host_names_are_answered(served, name, with_port):
    url, token = served
    host = f"{name}:{url.rsplit(':', 1)[1]}" if with_port else name
    with _client(url, token) as client:
        read = client.get("/scenes", headers={"Host": host})
        # the dashboard's own write: its Origin is the origin its Host names
        write = client.post(f"/jobs/{JOB_ID}/cancel", headers={"Host": host, "Origin": f"http://{host}"})
    assert read.status_code == 200, read.text
    assert write.status_code == 404, write.text  # reached the route: no such job


@pytest.mark.parametrize("token", [None, TOKEN], ids=["no-token", "token"])
def test_allowed_hosts_names_more_host_names(tmp_path, token):
    settings = _settings(tmp_path, api_token=token, allowed_hosts="voxnerf.lan, *.studio.example")
    with _serving(settings, **SERVER_OPTIONS) as url, _client(url, token) as client:
        answered = {host: client.get("/scenes", headers={"Host": host}).status_code
                    for host in ("voxnerf.lan:8000", "VOXNERF.LAN", "a.studio.example", "b.a.studio.example:80",
                                 "studio.example", "voxnerf.lan.evil.example", "evil.example")}
    assert answered == {"voxnerf.lan:8000": 200, "VOXNERF.LAN": 200, "a.studio.example": 200,
                        "b.a.studio.example:80": 200, "studio.example": 400, "voxnerf.lan.evil.example": 400,
                        "evil.example": 400}


def test_a_request_without_a_host_header_is_refused(tmp_path):
    """HTTP/1.0 lets a client leave ``Host`` out: no name, no answer but the refusal."""
    with _serving(_settings(tmp_path), **SERVER_OPTIONS) as url:
        port = int(url.rsplit(":", 1)[1])
        with socket.create_connection(("127.0.0.1", port), timeout=30) as connection:
            connection.sendall(b"GET /scenes HTTP/1.0\r\n\r\n")
            reply = b""
            while chunk := connection.recv(65536):
                reply += chunk
    head, _, body = reply.partition(b"\r\n\r\n")
    assert head.startswith(b"HTTP/1.1 400"), head
    assert b"is not a name this service answers to" in body


@pytest.mark.parametrize(
    ("host", "allowed"),
    [("localhost", True), ("localhost:8000", True), ("127.0.0.1:1", True), ("[::1]:8000", True), ("[::1]", True),
     ("127.9.9.9", True), ("evil.example:8000", False), ("localhost.evil.example", False), ("", False),
     (None, False), ("user@localhost", False), ("localhost/x", False), ("[::1", False), ("0.0.0.0", False),
     ("192.0.2.1", False)],
)
def test_host_allowed(host, allowed):
    assert host_allowed(host, []) is allowed


def test_any_host_without_a_token_is_a_start_up_warning(tmp_path, caplog):
    with caplog.at_level("WARNING", logger="app.origin_guard"):
        log_exposure(_settings(tmp_path, allowed_hosts="*", api_token=TOKEN))
        assert not caplog.records
        log_exposure(_settings(tmp_path, allowed_hosts="*"))
    assert [r.levelname for r in caplog.records] == ["WARNING"] and "DNS rebinding" in caplog.text


def test_allowed_hosts_and_trusted_proxies_read_from_the_environment(monkeypatch, tmp_path):
    monkeypatch.setenv("VOXNERF_ALLOWED_HOSTS", " voxnerf.lan, *.studio.example ,")
    monkeypatch.setenv("VOXNERF_TRUSTED_PROXIES", "10.0.0.5,10.1.0.0/16")
    settings = Settings(data_dir=tmp_path)
    assert settings.allowed_hosts == ["voxnerf.lan", "*.studio.example"]
    assert settings.trusted_proxies == ["10.0.0.5", "10.1.0.0/16"]
    monkeypatch.setenv("VOXNERF_TRUSTED_PROXIES", "proxy.lan")
    with pytest.raises(ValidationError, match="'proxy.lan' is not an IP address or network"):
        Settings(data_dir=tmp_path)


# --- item 2: proxies ----------------------------------------------------------------------------------------


PROXIED = [{"X-Forwarded-For": "127.0.0.1"}, {"X-Forwarded-For": "203.0.113.9"}, {"Via": "1.1 proxy"},
           {"Forwarded": "for=127.0.0.1"}, {"X-Forwarded-Host": "localhost"}, {"X-Forwarded-Proto": "https"}]
PROXIED_IDS = ["xff-loopback", "xff-remote", "via", "forwarded", "x-forwarded-host", "x-forwarded-proto"]


@pytest.mark.parametrize("server_options", [SERVER_OPTIONS, {}], ids=["voxnerf-serve", "uvicorn-defaults"])
@pytest.mark.parametrize("headers", PROXIED, ids=PROXIED_IDS)
def test_a_proxied_request_is_remote_without_a_trusted_proxy(tmp_path, server_options, headers):
    """From 127.0.0.1 with proxy headers, no token: 403, whether uvicorn reads X-Forwarded-For itself (its
    defaults trust 127.0.0.1) or not. The same request without them, and with a token, is answered."""
    with _serving(_settings(tmp_path), **server_options) as url, _client(url, None) as client:
        proxied = client.get("/scenes", headers=headers)
        direct = client.get("/scenes")
    assert proxied.status_code == 403, proxied.text
    assert "came through a proxy" in proxied.json()["detail"] and "VOXNERF_TRUSTED_PROXIES" in proxied.json()["detail"]
    assert direct.status_code == 200


def test_a_token_holder_may_come_through_any_proxy(tmp_path):
    with _serving(_settings(tmp_path, api_token=TOKEN), **SERVER_OPTIONS) as url, _client(url, TOKEN) as client:
        assert client.get("/scenes", headers={"X-Forwarded-For": "203.0.113.9", "Via": "1.1 p"}).status_code == 200


@pytest.mark.parametrize(
    ("headers", "status"),
    [({"X-Forwarded-For": "127.0.0.1"}, 200),
     ({"Forwarded": 'for="[::1]:4711";proto=http'}, 200),
     ({"X-Forwarded-For": "203.0.113.9"}, 403),
     ({"Forwarded": "for=203.0.113.9;proto=https"}, 403),
     ({"X-Forwarded-For": "127.0.0.1, 203.0.113.9"}, 403),  # the client wrote the first entry itself
     ({"X-Forwarded-For": "unknown"}, 403),
     ({"Via": "1.1 proxy"}, 403),  # the proxy names no client
     ({}, 403)],  # nor here: through a proxy on this machine every client would look local
    ids=["xff-loopback", "forwarded-loopback", "xff-remote", "forwarded-remote", "xff-spoofed", "xff-unknown",
         "via-only", "no-header"],
)
def test_a_trusted_proxy_names_the_client(tmp_path, headers, status):
    """``VOXNERF_TRUSTED_PROXIES=127.0.0.1`` (a reverse proxy on this machine), no token: the client it names
    decides; a request from it that names no client is remote."""
    settings = _settings(tmp_path, trusted_proxies="127.0.0.1")
    with _serving(settings, **SERVER_OPTIONS) as url, _client(url, None) as client:
        response = client.get("/scenes", headers=headers)
    assert response.status_code == status, response.text
    if status == 403:  # the proxy is trusted: its client is remote, and the detail says that alone
        assert "only loopback clients" in response.json()["detail"] and "proxy" not in response.json()["detail"]
