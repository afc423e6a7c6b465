"""``POST /scenes`` with a zip of a COLMAP project or a ScanNet export: detected, imported into the staging
scene, validated and stored, the importer's summary in ``imported``; bad archives are a 422 naming the file,
with nothing stored. Real HTTP through one API process (no workers: nothing trains)."""

from __future__ import annotations

import io
import json
import subprocess
import sys
import zipfile

import numpy as np
import pytest
from PIL import Image
from service_fixtures import REPO, start_service, zip_scene

W, H, F = 32, 24, 30.0


@pytest.fixture(scope="module")
def api(tmp_path_factory):
    service = start_service(tmp_path_factory.mktemp("upload_import"), workers=False)
    yield service
    service.stop()


@pytest.fixture(scope="module")
def client(api):
    with api.client() as c:
        yield c


def _image(path, seed: int, fmt: str = "PNG") -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    rgb = np.random.default_rng(seed).integers(0, 255, (H, W, 3), dtype=np.uint8)
    Image.fromarray(rgb).save(path, fmt)


def _centres(n: int) -> np.ndarray:
    return np.stack([np.linspace(-0.5, 0.5, n), np.zeros(n), np.zeros(n)], axis=1)


def tiny_colmap(root, n: int = 8, camera: str = f"1 PINHOLE {W} {H} {F} {F} {W / 2} {H / 2}"):
    """``root/sparse/0`` (text) and ``root/images``: n cameras along x looking down +z (OpenCV), a few points."""
    model = root / "sparse" / "0"
    model.mkdir(parents=True)
    (model / "cameras.txt").write_text(camera + "\n")
    points = np.array([[x, y, 3.0] for x in (-0.4, 0.0, 0.4) for y in (-0.3, 0.3)])
    lines, tracks = [], {i: [] for i in range(len(points))}
    for i, c in enumerate(_centres(n)):
        obs = []
        for pid, p in enumerate(points):
            cam = p - c
            obs.append(f"{F * cam[0] / cam[2] + W / 2} {F * cam[1] / cam[2] + H / 2} {pid + 1}")
            tracks[pid].append(f"{i + 1} {pid}")
        lines += [f"{i + 1} 1 0 0 0 {-c[0]} {-c[1]} {-c[2]} 1 {i:03d}.png", " ".join(obs)]
        _image(root / "images" / f"{i:03d}.png", i)
    (model / "images.txt").write_text("\n".join(lines) + "\n")
    rows = [f"{pid + 1} {p[0]} {p[1]} {p[2]} 10 20 30 0.5 {' '.join(tracks[pid])}" for pid, p in enumerate(points)]
    (model / "points3D.txt").write_text("\n".join(rows) + "\n")
    return root


def tiny_scannet(root, n: int = 60):
    """ScanNet's export layout: n frames (colour jpg, 16-bit depth, OpenCV camera-to-world), one pose invalid."""
    k = np.array([[F, 0, W / 2, 0], [0, F, H / 2, 0], [0, 0, 1, 0], [0, 0, 0, 1]])
    (root / "intrinsic").mkdir(parents=True)
    np.savetxt(root / "intrinsic" / "intrinsic_color.txt", k)
    np.savetxt(root / "intrinsic" / "intrinsic_depth.txt", k)
    (root / "pose").mkdir()
    (root / "depth").mkdir()
    for i, c in enumerate(_centres(n)):
        _image(root / "color" / f"{i}.jpg", i, "JPEG")
        pose = np.eye(4)
        pose[:3, 3] = c
        np.savetxt(root / "pose" / f"{i}.txt", pose)
        Image.fromarray(np.full((H, W), 3000, dtype=np.uint16)).save(root / "depth" / f"{i}.png")
    (root / "pose" / f"{n - 1}.txt").write_text("-inf -inf -inf -inf\n" * 4)
    return root


def _stored(api) -> tuple:
    data = api.data_dir
    listing = [sorted(p.name for p in (data / d).iterdir()) if (data / d).is_dir() else [] for d in ("scenes",
                                                                                                      "staging")]
    with api.client() as c:
        return (*listing, sorted(s["id"] for s in c.get("/scenes").json()))


def _post(client, payload: bytes, **data):
    return client.post("/scenes", files={"file": ("upload.zip", payload, "application/zip")}, data=data)


def _refused(api, client, payload: bytes, status: int, text: str, **data) -> str:
    before = _stored(api)
    response = _post(client, payload, **data)
    assert response.status_code == status, response.text
    detail = response.json()["detail"]
    assert text in detail and "\n" not in detail and "staging" not in detail, detail
    assert _stored(api) == before
    return detail


def test_colmap_zip_is_imported(api, client, tmp_path):
    payload = zip_scene(tiny_colmap(tmp_path / "proj"), top_folder="proj", skip=())
    response = _post(client, payload)
    assert response.status_code == 201, response.text
    body = response.json()
    assert body["imported"]["format"] == "colmap" and body["imported"]["frames"] == 8
    assert body["imported"]["camera_models"] == ["PINHOLE -> PINHOLE"] and body["imported"]["skipped"] == {}
    assert body["imported"]["prior"]["points"] == 6 and body["imported"]["prior"]["sigma"] > 0
    assert body["summary"]["frames"] == 8 and body["summary"]["prior"]["source"] == "ply_file_path"
    assert "imported" not in body["summary"]
    scene = api.data_dir / "scenes" / body["id"]
    meta = json.loads((scene / "transforms.json").read_text())
    assert meta["ply_file_path"] == "sparse_pc.ply" and (scene / "images" / "000.png").is_file()
    assert not (scene / "sparse").exists() and not list((api.data_dir / "staging").iterdir())
    assert client.get(f"/scenes/{body['id']}").json()["imported"] == body["imported"]


def test_scannet_zip_with_paper_splits(api, client, tmp_path):
    payload = zip_scene(tiny_scannet(tmp_path / "scan"), top_folder=None, skip=())
    response = _post(client, payload, splits="paper")
    assert response.status_code == 201, response.text
    body = response.json()
    imported = body["imported"]
    assert imported["format"] == "scannet" and imported["frames"] == 59 and imported["depth_frames"] == 59
    assert imported["skipped"] == {"invalid pose (non-finite values)": 1}
    assert imported["splits"]["rule"] == "paper" and imported["splits"]["train"] == 4
    assert body["summary"]["depth"] is True and body["summary"]["splits"]["train"] == 4
    meta = json.loads((api.data_dir / "scenes" / body["id"] / "transforms.json").read_text())
    assert meta["depth_unit_scale_factor"] == 0.001 and meta["depth_intrinsics"]["w"] == W
    assert set(meta["eval_splits"]) == {"interpolation", "extrapolation"}


def test_scene_zip_still_has_no_imported_entry(api, client, small_room):
    response = _post(client, zip_scene(small_room))
    assert response.status_code == 201, response.text
    assert response.json()["imported"] is None


def test_bad_archives_are_refused_naming_the_file(api, client, tmp_path):
    bad_camera = tiny_colmap(tmp_path / "bad", camera=f"1 FOV {W} {H} {F} {F} 16 12 0.1")
    detail = _refused(api, client, zip_scene(bad_camera, skip=()), 422, "camera model FOV is not supported")
    assert detail.startswith("colmap import: sparse/0/cameras.txt: camera 1:")
    lost = tiny_scannet(tmp_path / "lost", n=4)
    for pose in (lost / "pose").iterdir():
        pose.write_text("-inf -inf -inf -inf\n" * 4)
    _refused(api, client, zip_scene(lost, skip=()), 422, "pose: no usable frame: all 4 are skipped")
    escaping = tiny_colmap(tmp_path / "escaping", n=3)
    images_txt = escaping / "sparse" / "0" / "images.txt"
    images_txt.write_text(images_txt.read_text().replace("001.png", "../../../etc/passwd"))
    _refused(api, client, zip_scene(escaping, skip=()), 422, "images.txt: image name '../../../etc/passwd'")
    few = tiny_scannet(tmp_path / "few", n=10)
    _refused(api, client, zip_scene(few, skip=()), 422, "too few for the paper's splits", splits="paper")


def test_bad_splits_field_and_stray_text_files(api, client, tmp_path, small_room):
    payload = zip_scene(tiny_colmap(tmp_path / "proj", n=3), skip=())
    _refused(api, client, payload, 422, "splits: expected one of paper", splits="every-8th")
    _refused(api, client, zip_scene(small_room), 422, "a transforms.json scene names its own", splits="paper")
    before = _stored(api)
    parts = client.post("/scenes", files=[("files", ("transforms.json", b"{}"))], data={"splits": "paper"})
    assert parts.status_code == 422 and "only an upload to import" in parts.json()["detail"] and _stored(api) == before
    buffer = io.BytesIO(zip_scene(small_room))
    with zipfile.ZipFile(buffer, "a") as archive:
        archive.writestr("room/notes.txt", "not part of a scene")
    _refused(api, client, buffer.getvalue(), 415, "unsupported file type '.txt'")
    junk = tmp_path / "junk"
    (junk / "stuff").mkdir(parents=True)
    (junk / "stuff" / "a.txt").write_text("x")
    _refused(api, client, zip_scene(junk, top_folder=None, skip=()), 415, "unsupported file type")


def test_importers_do_not_load_torch_or_pycolmap():
    code = ("import sys, json, app.uploads.staging, voxnerf.data.importers; "
            "print(json.dumps([m for m in ('torch', 'pycolmap', 'voxnerf.data.scene') if m in sys.modules]))")
    out = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert json.loads(out.stdout.strip().splitlines()[-1]) == []
