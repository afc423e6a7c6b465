"""The API reference (issue #44, item 1): every operation of ``/openapi.json`` has a summary and a description,
every request body an example that its model accepts, every documented error an example ``detail``; a handful of
routes' real 4xx answers are among the statuses their operation documents; the schema is behind the token while
the ``/docs`` and ``/redoc`` shells are not, under a policy that allows no inline script and nothing from another
origin; the ReDoc bundle as served names no outside host.

Real parts: the app served by uvicorn on 127.0.0.1 in a thread (no workers: a route that would queue work is not
asked here).
"""

from __future__ import annotations

import json
import re
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import httpx
import pytest
import uvicorn
from fastapi.routing import APIRoute, iter_route_contexts
from pydantic import TypeAdapter
from service_fixtures import free_port, wait_for

from app.api_reference import ASSETS_URL, REDOC_BUNDLE, REFERENCE_CSP, ErrorOut, error_responses
from app.core.settings import Settings
from app.main import create_app
from app.origin_guard import CONTENT_SECURITY_POLICY

TOKEN = "reference-token"
UNKNOWN = "0" * 32
POSE = [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 2], [0, 0, 0, 1]]


def _settings(root: Path, **overrides) -> Settings:
    values = {"data_dir": root / "data", "device": "cpu", "sweep_interval_s": 3600.0, "health_timeout_s": 0.2}
    return Settings(**{**values, **overrides})


@pytest.fixture(scope="module")
def app(tmp_path_factory):
    return create_app(_settings(tmp_path_factory.mktemp("reference"), api_token=TOKEN))


@contextmanager
def _serving(app) -> Iterator[str]:
    """The base URL of ``app`` served by uvicorn on a free loopback port in a thread."""
    server = uvicorn.Server(uvicorn.Config(app, host="127.0.0.1", port=free_port(), log_level="warning"))
    thread = threading.Thread(target=server.run, daemon=True)
    thread.start()
    try:
        wait_for(lambda: server.started, 60, "uvicorn to start")
        yield f"http://127.0.0.1:{server.config.port}"
    finally:
        server.should_exit = True
        thread.join(30)


def _operations(schema: dict) -> Iterator[tuple[str, str, dict]]:
    for path, operations in schema["paths"].items():
        for method, operation in operations.items():
            yield method.upper(), path, operation


def _resolve(schema: dict, node: dict) -> dict:
    while "$ref" in node:
        node = schema["components"]["schemas"][node["$ref"].rsplit("/", 1)[1]]
    return node


def _has_example(media: dict, schema: dict) -> bool:
    """Whether a media type object shows an example: its own, or its schema's."""
    target = _resolve(schema, media.get("schema", {}))
    return any(key in node for node in (media, target) for key in ("example", "examples"))


def test_every_operation_has_a_summary_a_description_and_examples(app):
    schema = app.openapi()
    lacking = []
    for method, path, operation in _operations(schema):
        where = f"{method} {path}"
        if not operation.get("summary"):
            lacking.append(f"{where}: no summary")
        if not operation.get("description"):
            lacking.append(f"{where}: no description")
        for media_type, media in operation.get("requestBody", {}).get("content", {}).items():
            if not _has_example(media, schema):
                lacking.append(f"{where}: request body {media_type} has no example")
        for status, response in operation["responses"].items():
            if int(status) < 400:
                continue
            media = response.get("content", {}).get("application/json")
            if media is None or not _has_example(media, schema):
                lacking.append(f"{where}: error {status} has no JSON example")
    assert not lacking, "\n".join(lacking)
    assert len(list(_operations(schema))) >= 28


def test_every_reference_in_the_schema_resolves(app):
    schema = app.openapi()
    refs = set(re.findall(r'"\$ref": "#/components/schemas/([^"]+)"', json.dumps(schema)))
    assert refs and not refs - set(schema["components"]["schemas"]), refs - set(schema["components"]["schemas"])


def test_every_operation_documents_the_guards_and_the_protected_ones_the_token(app):
    for method, path, operation in _operations(app.openapi()):
        responses = operation["responses"]
        assert {"400", "403"} <= set(responses), f"{method} {path}"
        protected = path != "/healthz"
        assert ("401" in responses) == protected, f"{method} {path}"
        assert (operation.get("security") == [{"bearerAuth": []}]) == protected, f"{method} {path}"
        if "requestBody" in operation:
            assert "413" in responses, f"{method} {path}"


def test_the_error_examples_are_error_bodies(app):
    schema = app.openapi()
    for _method, path, operation in _operations(schema):
        for status, response in operation["responses"].items():
            if int(status) >= 400 and path != "/healthz":
                example = response["content"]["application/json"]["example"]
                ErrorOut.model_validate(example)  # {"detail": one sentence, or the validation errors}
    assert error_responses(404, e404="no scene x")[404]["content"]["application/json"]["example"] == {
        "detail": "no scene x"}


def test_every_body_example_is_a_request_its_route_accepts(app):
    """Each JSON body's examples validated by the route's own body model (a wrong example fails here)."""
    checked = 0
    for route in iter_route_contexts(app.routes):
        if not isinstance(route.original_route, APIRoute) or route.body_field is None:
            continue
        adapter = TypeAdapter(route.body_field.field_info.annotation)
        examples = adapter.json_schema().get("examples", [])
        assert examples, f"{route.path}: its body model has no examples"
        for example in examples:
            adapter.validate_python(example)
            checked += 1
    assert checked >= 8


# Requests that reach a route and fail, each with the status it gets: (method, url, request kwargs, status).
REAL_ERRORS = [
    ("GET", f"/jobs/{UNKNOWN}", {}, 404),
    ("GET", "/jobs/not-an-id", {}, 422),
    ("DELETE", f"/scenes/{UNKNOWN}", {}, 404),
    ("POST", f"/scenes/{UNKNOWN}/jobs", {"json": {}}, 422),
    ("POST", f"/scenes/{UNKNOWN}/jobs", {"json": {"max_iters": 5}}, 404),
    ("POST", f"/jobs/{UNKNOWN}/cancel", {}, 404),
    ("GET", f"/jobs/{UNKNOWN}/checkpoint", {}, 404),
    ("POST", f"/jobs/{UNKNOWN}/videos", {"json": {"path": "orbit", "frames": 5}}, 404),
    ("POST", f"/jobs/{UNKNOWN}/exports", {"json": {"kind": "cube"}}, 422),
    ("GET", f"/outputs/{UNKNOWN}/file", {}, 404),
    ("POST", f"/imports/{UNKNOWN}/cancel", {}, 404),
    ("POST", "/render", {"json": {"job_id": UNKNOWN, "transform_matrix": POSE}}, 404),
    ("POST", "/render", {"json": {"job_id": UNKNOWN, "transform_matrix": [[2, 0, 0, 0]] * 4}}, 422),
    ("POST", "/camera-paths", {"json": {"frames": 3}}, 422),
    ("POST", "/scenes", {"files": {"file": ("s.zip", b"not a zip", "application/zip")}}, 422),
    ("POST", "/scenes", {"files": {"files": ("notes.docx", b"x", "application/octet-stream")}}, 415),
    ("GET", "/scenes", {"headers": {"Authorization": "Bearer wrong"}}, 401),
    ("POST", f"/jobs/{UNKNOWN}/cancel", {"headers": {"Origin": "http://evil.example"}}, 403),
    ("GET", "/jobs", {"headers": {"Host": "evil.example"}}, 400),
]


def _operation_of(schema: dict, method: str, url: str) -> dict:
    for path, operations in schema["paths"].items():
        pattern = "^" + re.sub(r"\\\{[^}]+\\\}", "[^/]+", re.escape(path)) + "$"
        if re.match(pattern, url) and method.lower() in operations:
            return operations[method.lower()]
    raise AssertionError(f"no operation for {method} {url}")


def test_real_errors_are_among_the_documented_ones(app):
    schema = app.openapi()
    headers = {"Authorization": f"Bearer {TOKEN}"}
    with _serving(app) as url, httpx.Client(base_url=url, headers=headers, trust_env=False, timeout=60) as client:
        for method, target, kwargs, expected in REAL_ERRORS:
            response = client.request(method, target, **kwargs)
            assert response.status_code == expected, (method, target, response.text)
            assert "detail" in response.json()
            documented = _operation_of(schema, method, target.split("?")[0])["responses"]
            assert str(expected) in documented, f"{method} {target} answers {expected}, not documented"


def test_the_schema_needs_the_token_and_the_pages_do_not(app):
    with _serving(app) as url, httpx.Client(base_url=url, trust_env=False, timeout=60) as client:
        refused = client.get("/openapi.json")
        schema = client.get("/openapi.json", headers={"Authorization": f"Bearer {TOKEN}"})
        pages = [client.get("/docs"), client.get("/redoc"), client.get("/redoc")]
        bundle = client.get(f"{ASSETS_URL}/{REDOC_BUNDLE}")
        swagger = client.get(f"{ASSETS_URL}/swagger-ui-bundle.js")
    assert refused.status_code == 401 and "bearer token" in refused.json()["detail"]
    assert schema.status_code == 200 and schema.json()["paths"]
    for page in pages:
        assert page.status_code == 200 and page.headers["content-type"].startswith("text/html")
        policy = page.headers["content-security-policy"]
        assert "script-src 'self';" in policy and "connect-src 'self';" in policy and "'unsafe-inline'" not in policy
        assert "default-src 'self'" in policy and "frame-ancestors 'none'" in policy
        html = page.text
        assert not re.search(r"<script(?![^>]*\bsrc=)", html) and not re.search(r"<[^>]*\son[a-z]+\s*=", html)
        assert not re.search(r"<[^>]*\sstyle\s*=", html) and not re.search(r"https?://", html)
    # ReDoc's page: a fresh style nonce per response, the one its policy names
    nonces = [re.search(r'name="style-nonce" content="([^"]+)"', page.text)[1] for page in pages[1:]]
    assert nonces[0] != nonces[1] and f"'nonce-{nonces[1]}'" in pages[2].headers["content-security-policy"]
    assert CONTENT_SECURITY_POLICY.replace("img-src 'self' blob:", "img-src 'self' blob: data:") == REFERENCE_CSP
    assert bundle.status_code == 200 and b"cdn.redoc.ly" not in bundle.content
    assert swagger.status_code == 200 and len(swagger.content) > 500_000
