"""``POST /scenes`` with a zip of a Record3D or Polycam export (redkitchen written in the app's layout): detected,
imported with its LiDAR depth, validated and stored; a broken export is a 422 naming the file, with nothing
stored. Real HTTP through one API process (no workers: nothing trains)."""

from __future__ import annotations

import json

import numpy as np
import pytest
from phone_app_fixtures import needs_redkitchen, redkitchen_frames, write_polycam, write_record3d
from service_fixtures import start_service, zip_scene

from voxnerf.data.image_io import encode_exr

pytestmark = needs_redkitchen
N_FRAMES = 12


@pytest.fixture(scope="module")
def api(tmp_path_factory):
    # Room for 640 x 480 colour images and 256 x 192 depth, not for much more (an EXR's header is checked).
    service = start_service(tmp_path_factory.mktemp("upload_apps"), workers=False,
                            settings={"VOXNERF_MAX_IMAGE_PIXELS": "400000"})
    yield service
    service.stop()


@pytest.fixture(scope="module")
def client(api):
    with api.client() as c:
        yield c


def _post(client, payload: bytes, **data):
    return client.post("/scenes", files={"file": ("capture.zip", payload, "application/zip")}, data=data)


def _stored(api) -> list[str]:
    scenes = api.data_dir / "scenes"
    return sorted(p.name for p in scenes.iterdir()) if scenes.is_dir() else []


def test_record3d_zip_is_imported_with_its_depth(api, client, tmp_path):
    export = write_record3d(tmp_path / "capture", redkitchen_frames(N_FRAMES)) / "EXR_RGBD"
    response = _post(client, zip_scene(export, top_folder="EXR_RGBD", skip=()))
    assert response.status_code == 201, response.text
    body = response.json()
    assert body["imported"]["format"] == "record3d" and body["imported"]["frames"] == N_FRAMES
    assert body["imported"]["depth_frames"] == 3 and body["summary"]["depth"] is True
    meta = json.loads((api.data_dir / "scenes" / body["id"] / "transforms.json").read_text())
    assert meta["frames"][0]["depth_intrinsics"]["w"] == 256
    assert not list((api.data_dir / "staging").iterdir())


def test_polycam_zip_is_imported_with_its_depth(api, client, tmp_path):
    export = write_polycam(tmp_path / "capture", redkitchen_frames(N_FRAMES))
    response = _post(client, zip_scene(export, top_folder="polycam-scan", skip=()))
    assert response.status_code == 201, response.text
    imported = response.json()["imported"]
    assert imported["format"] == "polycam" and imported["frames"] == N_FRAMES and imported["depth_frames"] == 3
    assert any("below medium confidence dropped" in note for note in imported["notes"])


def test_broken_exports_are_refused_naming_the_file(api, client, tmp_path):
    export = write_record3d(tmp_path / "capture", redkitchen_frames(N_FRAMES)) / "EXR_RGBD"
    meta = json.loads((export / "metadata.json").read_text())
    del meta["K"]
    (export / "metadata.json").write_text(json.dumps(meta))
    before = _stored(api)
    response = _post(client, zip_scene(export, top_folder="EXR_RGBD", skip=()))
    assert response.status_code == 422, response.text
    detail = response.json()["detail"]
    assert detail == "record3d import: metadata.json: K: missing (a Record3D export's metadata has w, h, K, poses)"
    # An EXR declaring more pixels than allowed is refused from its header, before it is decoded.
    meta["K"] = [585.0, 0, 0, 0, 585.0, 0, 320.0, 240.0, 1]
    (export / "metadata.json").write_text(json.dumps(meta))
    noise = np.random.default_rng(0).random((2, 250_000), dtype=np.float32)  # incompressible: not a zip bomb
    (export / "depth" / "5.exr").write_bytes(encode_exr({"R": noise}))
    response = _post(client, zip_scene(export, top_folder="EXR_RGBD", skip=()))
    assert response.status_code == 422, response.text
    assert response.json()["detail"] == ("depth/5.exr: declared image size 250000x2 (500000 pixels) exceeds the "
                                         "limit of 400000 pixels")
    assert _stored(api) == before and not list((api.data_dir / "staging").iterdir())
