"""What a token holder reads names no server path (issue #42, item 8): ``/healthz``'s checks, upload refusals and
every other HTTP ``detail`` go through ``app.core.redact.public_error``; a GLB prior naming another file is
refused at upload.

Real parts: the app served by uvicorn on 127.0.0.1 in a thread (uploads validated in their own processes, as
always), a synthetic scene zipped as a client sends it, a broken filesystem broker.
"""

from __future__ import annotations

import json
import shutil
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import httpx
import pytest
import uvicorn
from service_fixtures import free_port, wait_for, zip_scene

from app.core.settings import Settings
from app.main import create_app
from app.origin_guard import SERVER_OPTIONS

TOKEN = "details-token"


@contextmanager
def _serving(settings: Settings) -> Iterator[httpx.Client]:
    """A token holder's client of the app for ``settings``, served by uvicorn on a free loopback port."""
    config = uvicorn.Config(create_app(settings), host="127.0.0.1", port=free_port(), log_level="warning",
                            **SERVER_OPTIONS)
    server = uvicorn.Server(config)
    thread = threading.Thread(target=server.run, daemon=True)
    thread.start()
    try:
        wait_for(lambda: server.started, 60, "uvicorn to start")
        headers = {"Authorization": f"Bearer {TOKEN}"}
        with httpx.Client(base_url=f"http://127.0.0.1:{config.port}", headers=headers, timeout=120,
                          trust_env=False) as client:
            yield client
    finally:
        server.should_exit = True
        thread.join(30)


@pytest.fixture(scope="module")
def data_dir(tmp_path_factory) -> Path:
    return tmp_path_factory.mktemp("details") / "data"


@pytest.fixture(scope="module")
def client(data_dir) -> Iterator[httpx.Client]:
    settings = Settings(data_dir=data_dir, api_token=TOKEN, device="cpu", sweep_interval_s=3600.0,
                        health_timeout_s=0.2)
    with _serving(settings) as client:
        yield client


@pytest.fixture(scope="module")
def micro_scene(tmp_path_factory) -> Path:
    from synthetic_fixtures import make_micro_scene

    return make_micro_scene(tmp_path_factory, "details-scene")


def _copy(scene: Path, root: Path) -> Path:
    copy = root / "scene"
    shutil.copytree(scene, copy)
    return copy


def _upload(client: httpx.Client, scene: Path) -> httpx.Response:
    return client.post("/scenes", files={"file": ("room.zip", zip_scene(scene), "application/zip")})


def test_an_upload_refusal_names_no_server_path(client, data_dir, micro_scene, tmp_path):
    """An image that is no image: the decoder's message quoted the staging directory's absolute path."""
    scene = _copy(micro_scene, tmp_path)
    first = json.loads((scene / "transforms.json").read_text())["frames"][0]["file_path"]
    (scene / first).write_bytes(b"not an image" * 8)  # no PNG signature: the decoder is asked, and names the file
    response = _upload(client, scene)
    assert response.status_code == 422, response.text
    detail = response.json()["detail"]
    assert first in detail and str(data_dir) not in detail and str(data_dir.resolve()) not in detail, detail


def test_a_glb_prior_naming_another_file_is_refused_at_upload(client, micro_scene, tmp_path):
    """Its buffer is another file of the upload (named ``.obj``, a suffix uploads take): trimesh would read it."""
    from prior.test_loading import glb_naming_a_file

    scene = _copy(micro_scene, tmp_path)
    glb_naming_a_file(scene, uri="buffer.obj")
    (scene / "prior.ply").unlink()
    meta = json.loads((scene / "transforms.json").read_text())
    (scene / "transforms.json").write_text(json.dumps(meta | {"prior_file_path": "prior.glb"}))
    before = client.get("/scenes").json()
    response = _upload(client, scene)
    assert response.status_code == 422, response.text
    assert "prior.glb: buffers[0].uri: names the external file 'buffer.obj'" in response.json()["detail"]
    assert client.get("/scenes").json() == before  # nothing stored


def test_health_details_name_no_server_path(client, data_dir):
    """The broker's check, healthy and then broken (its control directory replaced by a file): relative paths."""
    healthy = client.get("/healthz").json()
    control = data_dir / "broker" / "control"
    shutil.rmtree(control)
    control.write_text("not a directory")
    try:
        broken = client.get("/healthz").json()
    finally:
        control.unlink()
        control.mkdir()
    assert healthy["broker"] == {"ok": True, "detail": "filesystem queue in broker"}
    assert not broken["broker"]["ok"] and "'broker/control'" in broken["broker"]["detail"], broken
    for body in (healthy, broken):
        assert str(data_dir) not in json.dumps(body) and str(data_dir.resolve()) not in json.dumps(body)
