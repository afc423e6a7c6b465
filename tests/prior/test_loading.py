"""Geometry prior loading: meshes, point clouds, outlier removal, noise estimation and input errors."""

from __future__ import annotations

import base64
import json
import struct
from pathlib import Path

import numpy as np
import pytest
import trimesh

from voxnerf.errors import SceneError
from voxnerf.prior.loading import estimate_sigma, load_prior

REDKITCHEN = Path(__file__).resolve().parents[3] / "shared" / "data" / "redkitchen"


def noisy_plane(n: int, noise: float, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return np.c_[rng.uniform(0, 1, (n, 2)), rng.normal(0, noise, n)]


def write_ascii_ply(path: Path, points: np.ndarray) -> Path:
    header = f"ply\nformat ascii 1.0\nelement vertex {len(points)}\nproperty float x\nproperty float y\n"
    body = "".join(f"{x} {y} {z}\n" for x, y, z in points.tolist())
    path.write_text(header + "property float z\nend_header\n" + body)
    return path


def test_mesh_ply_is_sampled_on_its_surface(tmp_path):
    path = tmp_path / "box.ply"
    trimesh.creation.box(extents=(2.0, 1.0, 0.5)).export(path)
    prior = load_prior(path, 0.05)
    assert prior.kind == "mesh" and prior.mesh is not None and not prior.sigma_estimated
    area = 2 * (2.0 * 1.0 + 2.0 * 0.5 + 1.0 * 0.5)
    assert len(prior.points) == pytest.approx(area / (0.05 / 3) ** 2, rel=0.01)
    # Every sample lies on a face: one coordinate at its half extent.
    on_face = np.isclose(np.abs(prior.points) / np.array([1.0, 0.5, 0.25]), 1.0, atol=1e-9).any(axis=1)
    assert on_face.all() and (np.abs(prior.points) <= np.array([1.0, 0.5, 0.25]) + 1e-9).all()
    summary = json.loads(json.dumps(prior.summary()))
    assert summary["faces"] == 12 and summary["input_points"] == 8 and summary["sigma"] == 0.05


def test_point_cloud_ply_with_far_outliers(tmp_path):
    plane = noisy_plane(5000, 0.002)
    outliers = np.random.default_rng(1).uniform(20, 30, (25, 3))
    path = tmp_path / "cloud.ply"
    trimesh.PointCloud(np.concatenate([plane, outliers])).export(path)
    prior = load_prior(path, 0.01)
    assert prior.kind == "points" and prior.mesh is None
    assert prior.num_input_points == 5025
    assert prior.num_outliers_removed >= 25
    assert prior.points.max() < 2.0  # every far point is gone
    assert len(prior.points) >= 0.95 * 5000  # and the plane is kept
    assert prior.summary()["faces"] == 0


@pytest.mark.parametrize(("noise", "n"), [(0.005, 20_000), (0.01, 200_000), (0.02, 50_000)])
def test_sigma_estimate_recovers_plane_noise(noise, n):
    estimate = estimate_sigma(noisy_plane(n, noise))
    assert noise / 1.5 < estimate < noise * 1.5


def test_sigma_estimate_of_clean_surface_is_the_spacing():
    grid = np.stack(np.meshgrid(np.arange(100), np.arange(100), indexing="ij"), -1).reshape(-1, 2) * 0.01
    estimate = estimate_sigma(np.c_[grid, np.zeros(len(grid))])
    assert estimate == pytest.approx(0.01, rel=1e-6)


def test_estimated_sigma_is_reported(tmp_path):
    path = tmp_path / "cloud.ply"
    trimesh.PointCloud(noisy_plane(20_000, 0.01)).export(path)
    prior = load_prior(path, None)
    assert prior.sigma_estimated and 0.01 / 1.5 < prior.sigma < 0.015


def test_nonfinite_points_are_dropped_and_counted(tmp_path):
    points = noisy_plane(500, 0.001)
    points[::50, 1] = np.nan
    points[1, 2] = np.inf
    prior = load_prior(write_ascii_ply(tmp_path / "partly_nan.ply", points), 0.01)
    assert prior.num_nonfinite_removed == 11 and prior.summary()["nonfinite_removed"] == 11
    assert np.isfinite(prior.points).all() and len(prior.points) <= 489


def test_transformed_moves_points_mesh_and_sigma(tmp_path):
    path = tmp_path / "box.obj"
    trimesh.creation.box(extents=(1.0, 1.0, 1.0)).export(path)
    prior = load_prior(path, 0.1)
    moved = prior.transformed(np.array([1.0, 2.0, 3.0]), 0.5)
    assert moved.sigma == pytest.approx(0.05)
    assert np.allclose(moved.points, (prior.points - [1.0, 2.0, 3.0]) * 0.5)
    assert np.allclose(moved.mesh.vertices, (prior.mesh.vertices - [1.0, 2.0, 3.0]) * 0.5)
    assert np.allclose(prior.mesh.bounds, [[-0.5] * 3, [0.5] * 3])  # the original is untouched


@pytest.mark.parametrize("suffix", [".glb", ".off", ".obj"])
def test_other_mesh_formats(tmp_path, suffix):
    mesh = trimesh.creation.icosphere(subdivisions=2, radius=1.0)
    mesh.apply_translation([5.0, 0.0, 0.0])
    path = tmp_path / f"sphere{suffix}"
    mesh.export(path)
    prior = load_prior(path, 0.1)
    assert prior.kind == "mesh"
    assert np.allclose(np.linalg.norm(prior.points - [5.0, 0.0, 0.0], axis=1), 1.0, atol=0.05)


def test_errors_name_the_file(tmp_path):
    cases = {
        tmp_path / "missing.ply": "not found",
        write_ascii_ply(tmp_path / "empty.ply", np.zeros((0, 3))): "no geometry",
        write_ascii_ply(tmp_path / "all_nan.ply", np.full((10, 3), np.nan)): "NaN",
        tmp_path / "cloud.xyz": "unsupported",
    }
    (tmp_path / "cloud.xyz").write_text("0 0 0\n")
    for path, message in cases.items():
        with pytest.raises(SceneError) as info:
            load_prior(path, 0.01)
        assert path.name in str(info.value) and message in str(info.value)


@pytest.mark.parametrize("sigma", [0.0, -0.1, float("nan"), float("inf")])
def test_bad_sigma_is_refused(tmp_path, sigma):
    path = tmp_path / "box.ply"
    trimesh.creation.box().export(path)
    with pytest.raises(SceneError) as info:
        load_prior(path, sigma)
    assert info.value.key == "prior_sigma" and "box.ply" in str(info.value)


@pytest.mark.skipif(not (REDKITCHEN / "prior_tsdf.ply").is_file(), reason="redkitchen data not available")
def test_redkitchen_prior():
    prior = load_prior(REDKITCHEN / "prior_tsdf.ply", 0.02)
    summary = prior.summary()
    assert summary["kind"] == "mesh" and summary["faces"] == 166_774 and summary["sigma"] == 0.02
    assert summary["points"] == pytest.approx(prior.mesh.area / (0.02 / 3) ** 2, rel=0.01)
    lo, hi = prior.mesh.bounds
    assert np.all(prior.points >= lo - 1e-9) and np.all(prior.points <= hi + 1e-9)
    assert 3.0 < np.ptp(prior.points, axis=0).max() < 10.0  # a kitchen, in metres


# --- GLB priors that name other files (issue #42, item 8) ---------------------------------------------------


def glb_naming_a_file(directory: Path, name: str = "prior.glb", uri: str = "mesh.bin") -> Path:
    """A sphere as a GLB whose first buffer is the file ``uri`` (written there: a layout trimesh reads,
    following the URI, when nothing refuses it); its other buffers are ``data:`` URIs."""
    layout = sphere_layout()
    directory.mkdir(parents=True, exist_ok=True)
    target = (directory / uri).resolve()
    target.parent.mkdir(parents=True, exist_ok=True)
    target.write_bytes(base64.b64decode(layout["buffers"][0]["uri"].partition("base64,")[2]))
    layout["buffers"][0]["uri"] = uri
    return write_glb(directory / name, layout)


def sphere_layout() -> dict:
    """A sphere's glTF layout with every buffer held in it as a ``data:`` URI."""
    exported = trimesh.creation.icosphere(subdivisions=1).export(file_type="gltf")
    layout = json.loads(exported["model.gltf"])
    for buffer in layout["buffers"]:
        buffer["uri"] = "data:application/octet-stream;base64," + base64.b64encode(exported[buffer["uri"]]).decode()
    return layout


def write_glb(path: Path, layout: dict, binary: bytes = b"") -> Path:
    """A GLB file (glTF 2.0 binary container) of ``layout`` and an optional BIN chunk."""
    text = json.dumps(layout).encode()
    text += b" " * (-len(text) % 4)
    chunks = struct.pack("<I4s", len(text), b"JSON") + text
    if binary:
        binary += b"\0" * (-len(binary) % 4)
        chunks += struct.pack("<I4s", len(binary), b"BIN\0") + binary
    path.write_bytes(struct.pack("<4sII", b"glTF", 2, 12 + len(chunks)) + chunks)
    return path


@pytest.mark.parametrize("uri", ["mesh.bin", "../outside/mesh.bin", "sub/mesh.bin"])
def test_a_glb_naming_another_file_is_refused(tmp_path, uri):
    path = glb_naming_a_file(tmp_path / "scene", uri=uri)
    with pytest.raises(SceneError) as info:
        load_prior(path, 0.01)
    assert info.value.key == "buffers[0].uri" and repr(uri) in str(info.value) and "prior.glb" in str(info.value)


def test_a_glb_image_naming_another_file_is_refused(tmp_path):
    exported = trimesh.creation.icosphere(subdivisions=1).export(file_type="glb")
    layout_bytes = exported[20:20 + struct.unpack("<I", exported[12:16])[0]]
    layout = json.loads(layout_bytes) | {"images": [{"uri": "images/frame-000000.png"}]}
    binary = exported[20 + len(layout_bytes) + 8:]
    with pytest.raises(SceneError, match=r"images\[0\]\.uri: names the external file"):
        load_prior(write_glb(tmp_path / "prior.glb", layout, binary), 0.01)


def test_a_glb_holding_its_data_loads_as_before(tmp_path):
    """Embedded as a BIN chunk (trimesh's own export) or as a ``data:`` URI: loaded."""
    inline = load_prior(write_glb(tmp_path / "inline.glb", sphere_layout()), 0.05)
    (tmp_path / "bin.glb").write_bytes(trimesh.creation.icosphere(subdivisions=1).export(file_type="glb"))
    embedded = load_prior(tmp_path / "bin.glb", 0.05)
    assert inline.kind == embedded.kind == "mesh" and inline.num_input_points == embedded.num_input_points == 42


def test_voxnerf_train_refuses_a_glb_prior_naming_another_file(tmp_path, capsys):
    """The CLI's one-line error names the file and the field; no run is trained."""
    from synthetic_fixtures import MICRO

    from voxnerf.cli import main
    from voxnerf.synthetic import make_room_scene

    scene = make_room_scene(tmp_path / "scene", MICRO)
    meta = json.loads((scene / "transforms.json").read_text())
    glb_naming_a_file(scene, uri="mesh.bin")
    (scene / "prior.ply").unlink()
    (scene / "transforms.json").write_text(json.dumps(meta | {"prior_file_path": "prior.glb"}))
    code = main(["train", str(scene), "--out", str(tmp_path / "run"), "--device", "cpu", "--max-iters", "2"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code != 0 and len(err) == 1, err
    assert "prior.glb: buffers[0].uri: names the external file" in err[0]
    assert not (tmp_path / "run" / "checkpoint.pt").exists()
