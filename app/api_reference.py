"""The API reference: ``/docs`` (Swagger UI) and ``/redoc`` (ReDoc) served from this host, ``/openapi.json`` behind
the token, and the one rule for documenting what each route can answer as an error.

The viewers' scripts and styles are the ``fastapi-offline`` package's copies (Swagger UI 5, ReDoc 2; served under
``/docs/assets``); their pages are static shells in ``app/static`` (``docs.html``, ``redoc.html``) whose one script,
``api-docs.js``, fetches the schema with the token the dashboard saved and starts the viewer, so the service's
Content-Security-Policy (no inline script or style, nothing from another origin) holds for them as for the
dashboard, with images from ``data:`` added (:data:`REFERENCE_CSP`) and, for ReDoc, the style elements that carry
the nonce made for its page.

Errors: every error body is ``{"detail": ...}``. :func:`error_responses` builds a route's ``responses=`` from the
statuses it raises, each with a description and an example from :data:`ERRORS`; :func:`reference_schema` adds to
every operation the statuses every request can meet (the request guard's 400 and 403, 401 where the token is
required, 413 where a body is read, the validation 422's example), so no route repeats them.
"""

from __future__ import annotations

import secrets
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import fastapi_offline
from fastapi import FastAPI, Request, params
from fastapi.dependencies.models import Dependant
from fastapi.openapi.utils import get_openapi
from fastapi.responses import FileResponse, HTMLResponse, JSONResponse, Response
from fastapi.routing import APIRoute, iter_route_contexts
from fastapi.staticfiles import StaticFiles
from pydantic import BaseModel, Field

from app.origin_guard import CONTENT_SECURITY_POLICY

STATIC_DIR = Path(__file__).parent / "static"
ASSETS_DIR = Path(fastapi_offline.__file__).parent / "static"  # swagger-ui-bundle.js, swagger-ui.css, redoc...
ASSETS_URL = "/docs/assets"
BEARER_SCHEME = "bearerAuth"
# The pages' policy: the service's own, with images also from data: (Swagger UI's stylesheet and bundle draw their
# icons as data: URLs; an image cannot run script). Scripts, styles and connections stay 'self' only.
REFERENCE_CSP = CONTENT_SECURITY_POLICY.replace("img-src 'self' blob:", "img-src 'self' blob: data:")
# ReDoc writes its styles into <style> elements (styled-components): /redoc's policy also allows the style elements
# that carry the nonce made for that response, which the page hands to ReDoc (redoc.html's meta element).
NONCE_PLACEHOLDER = "STYLE_NONCE"
# ReDoc's bundle as served: two changes, each checked present when the app is built. Its side menu's attribution
# shows a logo from cdn.redoc.ly (a request leaving the host: the package's own favicon instead), and the styles it
# injects while the bundle loads (its scrollbar's) would carry no nonce (webpack's nonce, reset when it loads: the
# page's instead).
REDOC_BUNDLE = "redoc.standalone.js"
REDOC_PATCHES = (
    ("https://cdn.redoc.ly/redoc/logo-mini.svg", f"{ASSETS_URL}/favicon.png"),
    ("n.nc=void 0", "n.nc=document.querySelector('meta[name=\"style-nonce\"]').content"),
)
EXAMPLE_ID = "3f2b8c1d9e0a4b5c8d7e6f5a4b3c2d1e"
NOT_RENDERABLE_EXAMPLE = (f"job {EXAMPLE_ID} is running; only a succeeded job, or a cancelled one that kept a "
                          "checkpoint, can be rendered")


class ErrorOut(BaseModel):
    """Every error's body: ``detail`` is one sentence, or for a request that does not match its schema (422 from
    validation) the list of what is wrong, each with its location and message."""

    detail: str | list[dict[str, Any]] = Field(description="what is wrong, in words (or the validation errors)")


# status -> (when a route answers it, an example detail). One table for every route.
ERRORS: dict[int, tuple[str, Any]] = {
    400: ("the Host header names none of this service's host names (VOXNERF_ALLOWED_HOSTS), or a malformed body",
          "Host 'evil.example:8000' is not a name this service answers to (a web page that re-resolves its own "
          "name to this machine sends it): use localhost, 127.0.0.1 or [::1], or add the name to "
          "VOXNERF_ALLOWED_HOSTS"),
    401: ("the service has an API token and the request does not carry it",
          "missing or wrong bearer token: send 'Authorization: Bearer <VOXNERF_API_TOKEN>'"),
    403: ("a token whose scope does not allow this (or acting on another token's work), a remote client of a "
          "service without a token, or a cross-site state change",
          "POST /scenes needs scope write; token 'dashboards' has scope read"),
    404: ("no such scene, job, output, import or file", f"no job {EXAMPLE_ID}"),
    409: ("the resource is not in a state that allows this",
          f"job {EXAMPLE_ID} is running: its checkpoint is still being written"),
    410: ("the upload session expired: no part arrived for VOXNERF_UPLOAD_SESSION_EXPIRY_S",
          f"upload session {EXAMPLE_ID} expired: no part arrived for 86400 s "
          "(VOXNERF_UPLOAD_SESSION_EXPIRY_S); start a new one"),
    413: ("the request body (or an upload's unpacked scene) is larger than its limit",
          "request body larger than 1048576 bytes"),
    415: ("an uploaded file is of no type a scene holds",
          "entry room/notes.docx: unsupported file type '.docx'; allowed: .glb, .jpeg, .jpg, .json, .mtl, .npy, "
          ".obj, .off, .ply, .png"),
    422: ("the request does not match its schema, or its values break a rule",
          [{"type": "missing", "loc": ["body", "max_seconds"], "msg": "Value error, give max_seconds or "
            "max_iters (or both)", "input": {}}]),
    429: ("a limit of work in progress is reached; retry after Retry-After",
          "2 uploads are already in progress on this API process (VOXNERF_MAX_CONCURRENT_UPLOADS); retry in 10 s"),
    503: ("the broker, the object store or a scene read is unavailable; try again later",
          "the train queue is unavailable (Connection refused); try again later"),
    500: ("the render worker failed while rendering", "render failed: RuntimeError: CUDA out of memory"),
    504: ("no render worker answered in time", "no render worker answered within 120 s"),
    507: ("the data directory has no room for it (VOXNERF_DATA_DIR_QUOTA_BYTES, VOXNERF_MIN_FREE_BYTES)",
          "not enough free disk space for an upload of 2147483648 bytes: 1.50 GiB free, 2.00 GiB needed, and "
          "1.00 GiB is kept free for running jobs (VOXNERF_MIN_FREE_BYTES); delete scenes or jobs, or free space "
          "on the server"),
}
GUARD_STATUSES = (400, 403)  # app.origin_guard answers them for every path


def error_response(status: int, detail: Any = None) -> dict[str, Any]:
    """The OpenAPI response of error ``status``: :class:`ErrorOut`, :data:`ERRORS`' description, and ``detail``
    (default: the table's) as its example."""
    description, example = ERRORS[status]
    return {
        "model": ErrorOut,
        "description": description,
        "content": {"application/json": {"example": {"detail": example if detail is None else detail}}},
    }


def error_responses(*statuses: int, **details: Any) -> dict[int | str, dict[str, Any]]:
    """``responses=`` of a route that raises ``statuses`` (beyond those every route meets, which
    :func:`reference_schema` adds); ``details`` (``e404="no scene ..."``) gives a route its own example."""
    return {status: error_response(status, details.get(f"e{status}")) for status in statuses}


def _uses(dependant: Dependant, checks: set[Callable[..., Any]]) -> bool:
    """Whether ``dependant`` depends, at any depth, on one of ``checks``."""
    return any(dep.call in checks or _uses(dep, checks) for dep in dependant.dependencies)


def reference_schema(app: FastAPI, token_checks: Sequence[params.Depends]) -> dict[str, Any]:
    """The app's OpenAPI schema, built once: FastAPI's, plus the bearer scheme on every operation that depends on
    one of ``token_checks`` (the dependencies the app's protected routes carry) and the statuses every operation
    can meet (:data:`GUARD_STATUSES`, 401 where the token is needed, 413 with a body, 422's example) documented
    with examples."""
    if app.openapi_schema is not None:
        return app.openapi_schema
    schema = get_openapi(title=app.title, version=app.version, summary=app.summary, description=app.description,
                         routes=app.routes, tags=app.openapi_tags)
    schema.setdefault("components", {}).setdefault("schemas", {})
    schema["components"]["securitySchemes"] = {
        BEARER_SCHEME: {"type": "http", "scheme": "bearer",
                        "description": "VOXNERF_API_TOKEN; needed only when the service sets one"}}
    error_schema = ErrorOut.model_json_schema(ref_template="#/components/schemas/{model}")
    schema["components"]["schemas"]["ErrorOut"] = error_schema
    checks = {check.dependency for check in token_checks}
    protected = {(route.path, method.lower()) for route in iter_route_contexts(app.routes)
                 if isinstance(route.original_route, APIRoute) and _uses(route.dependant, checks)
                 for method in route.methods}
    for path, operations in schema["paths"].items():
        for method, operation in operations.items():
            responses = operation.setdefault("responses", {})
            statuses = list(GUARD_STATUSES)
            if (path, method) in protected:
                operation["security"] = [{BEARER_SCHEME: []}]
                statuses.append(401)
            if "requestBody" in operation:
                statuses.append(413)
            if "422" in responses:  # FastAPI's validation error: our body (ErrorOut) with an example
                statuses.append(422)
            for status in statuses:
                documented = responses.get(str(status), {})
                content = documented.get("content", {}).get("application/json", {})
                if "example" in content or "examples" in content:
                    continue
                entry = error_response(status)
                responses[str(status)] = {
                    "description": documented.get("description") or entry["description"],
                    "content": {"application/json": {"schema": {"$ref": "#/components/schemas/ErrorOut"},
                                                     **entry["content"]["application/json"]}},
                }
    schema["components"]["schemas"].pop("HTTPValidationError", None)
    schema["components"]["schemas"].pop("ValidationError", None)
    app.openapi_schema = schema
    return schema


def install_api_reference(app: FastAPI, token_checks: Sequence[params.Depends]) -> None:
    """Add ``/openapi.json`` (behind ``token_checks``, the dependencies of the app's protected routes), ``/docs``,
    ``/redoc`` and their assets to ``app`` (built with ``openapi_url=None, docs_url=None, redoc_url=None``)."""
    app.openapi = lambda: reference_schema(app, token_checks)

    @app.get("/openapi.json", include_in_schema=False, dependencies=list(token_checks))
    def openapi_schema(request: Request) -> JSONResponse:
        """The OpenAPI schema of this service (what /docs and /redoc show)."""
        return JSONResponse(request.app.openapi())

    @app.get("/docs", include_in_schema=False)
    def swagger_ui() -> FileResponse:
        """Swagger UI's shell (static: it fetches the schema with the saved token)."""
        return FileResponse(STATIC_DIR / "docs.html", media_type="text/html",
                            headers={"Content-Security-Policy": REFERENCE_CSP})

    @app.get("/redoc", include_in_schema=False)
    def redoc() -> HTMLResponse:
        """ReDoc's shell (it fetches the schema with the saved token), with this response's style nonce."""
        nonce = secrets.token_urlsafe(18)
        html = (STATIC_DIR / "redoc.html").read_text().replace(NONCE_PLACEHOLDER, nonce)
        policy = REFERENCE_CSP.replace("style-src 'self'", f"style-src 'self' 'nonce-{nonce}'")
        return HTMLResponse(html, headers={"Content-Security-Policy": policy})

    redoc_bundle = patched_redoc_bundle()

    @app.get(f"{ASSETS_URL}/{REDOC_BUNDLE}", include_in_schema=False)
    def redoc_script() -> Response:
        """ReDoc's bundle with :data:`REDOC_PATCHES` applied."""
        return Response(redoc_bundle, media_type="text/javascript")

    app.mount(ASSETS_URL, StaticFiles(directory=ASSETS_DIR), name="docs-assets")


def patched_redoc_bundle() -> bytes:
    """The package's ReDoc bundle with :data:`REDOC_PATCHES` applied; RuntimeError when one does not apply (another
    version of the bundle: look at what it loads before serving it)."""
    text = (ASSETS_DIR / REDOC_BUNDLE).read_text(encoding="utf-8")
    for old, new in REDOC_PATCHES:
        if text.count(old) != 1:
            raise RuntimeError(f"{ASSETS_DIR / REDOC_BUNDLE}: expected {old!r} once, found it {text.count(old)} times")
        text = text.replace(old, new)
    return text.encode()
