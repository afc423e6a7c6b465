"""``voxnerf import colmap``: the shared redkitchen scene written as a COLMAP text model (and binary, through
pycolmap) comes back with its poses, intrinsics, prior points and sigma; bad models give one-line errors."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import trimesh

from voxnerf.cli import main
from voxnerf.data.importers import PaperSplitRule, import_colmap, paper_splits
from voxnerf.data.importers.colmap import CAMERA_MODELS
from voxnerf.errors import SceneError

REDKITCHEN = Path(__file__).resolve().parents[3] / "shared" / "data" / "redkitchen"
needs_redkitchen = pytest.mark.skipif(
    not (REDKITCHEN / "transforms.json").is_file(), reason="shared redkitchen data not present"
)
FLIP = np.diag([1.0, -1.0, -1.0, 1.0])
N_FRAMES = 100
N_POINTS = 3000
ERROR_PX = 0.8


def quaternion(rot: np.ndarray) -> np.ndarray:
    """``qw qx qy qz`` of a rotation matrix (Shepperd's method)."""
    m = rot
    trace = np.trace(m)
    if trace > 0:
        s = 2 * np.sqrt(trace + 1)
        q = [0.25 * s, (m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s]
    else:
        i = int(np.argmax(np.diag(m)))
        j, k = (i + 1) % 3, (i + 2) % 3
        s = 2 * np.sqrt(1 + m[i, i] - m[j, j] - m[k, k])
        q = [0.0] * 4
        q[0] = (m[k, j] - m[j, k]) / s
        q[1 + i] = 0.25 * s
        q[1 + j] = (m[j, i] + m[i, j]) / s
        q[1 + k] = (m[k, i] + m[i, k]) / s
    q = np.array(q)
    return q / np.linalg.norm(q)


def w2c_opencv(c2w_gl) -> np.ndarray:
    return np.linalg.inv(np.asarray(c2w_gl) @ FLIP)


def write_colmap_text(
    dst: Path,
    frames: list[dict],
    points: np.ndarray,
    cameras: list[str] = ("1 PINHOLE 640 480 585 585 320 240",),
    camera_of=lambda i: 1,
    max_track: int = 3,
) -> dict:
    """cameras.txt, images.txt and points3D.txt of ``frames`` (redkitchen entries, image names as there) and
    ``points`` observed by up to ``max_track`` frames that see them; returns ``{point index: [(frame, z)]}``."""
    dst.mkdir(parents=True, exist_ok=True)
    (dst / "cameras.txt").write_text("# CAMERA_ID MODEL W H PARAMS\n" + "\n".join(cameras) + "\n")
    w2cs = [w2c_opencv(f["transform_matrix"]) for f in frames]
    observations: dict[int, list] = {}
    points2d: list[list] = [[] for _ in frames]
    for pid, xyz in enumerate(points):
        for i, w2c in enumerate(w2cs):
            cam = w2c[:3, :3] @ xyz + w2c[:3, 3]
            if cam[2] <= 0.1:
                continue
            u, v = 585 * cam[0] / cam[2] + 320, 585 * cam[1] / cam[2] + 240
            if 0 <= u < 640 and 0 <= v < 480:
                observations.setdefault(pid, []).append((i, len(points2d[i]), float(cam[2])))
                points2d[i].append((float(u), float(v), pid + 1))
            if len(observations.get(pid, [])) >= max_track:
                break
    lines = ["# IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME"]
    for i, (frame, w2c) in enumerate(zip(frames, w2cs, strict=True)):
        q, t = quaternion(w2c[:3, :3]), w2c[:3, 3]
        pose = " ".join(repr(float(x)) for x in [*q, *t])
        lines.append(f"{i + 1} {pose} {camera_of(i)} {Path(frame['file_path']).name}")
        lines.append(" ".join(f"{u!r} {v!r} {p}" for u, v, p in points2d[i]))
    (dst / "images.txt").write_text("\n".join(lines) + "\n")
    plines = ["# POINT3D_ID X Y Z R G B ERROR TRACK[] as (IMAGE_ID, POINT2D_IDX)"]
    for pid, obs in observations.items():
        x, y, z = (float(c) for c in points[pid])
        track = " ".join(f"{i + 1} {idx}" for i, idx, _ in obs)
        plines.append(f"{pid + 1} {x!r} {y!r} {z!r} 200 100 50 {ERROR_PX} {track}")
    (dst / "points3D.txt").write_text("\n".join(plines) + "\n")
    return observations


def rigid(c2w) -> list[list[float]]:
    """``c2w`` with its rotation replaced by the nearest rotation (7-Scenes' poses are slightly scaled; a
    COLMAP quaternion holds a rotation only)."""
    c2w = np.array(c2w, dtype=np.float64)
    u, _, vt = np.linalg.svd(c2w[:3, :3])
    c2w[:3, :3] = u @ vt
    return c2w.tolist()


def redkitchen_frames(n: int = N_FRAMES) -> list[dict]:
    """The first ``n`` redkitchen frames, their poses made rigid."""
    frames = json.loads((REDKITCHEN / "transforms.json").read_text())["frames"][:n]
    return [{**f, "transform_matrix": rigid(f["transform_matrix"])} for f in frames]


def link_images(dst: Path, frames: list[dict]) -> Path:
    (dst / "images").mkdir(parents=True, exist_ok=True)
    for frame in frames:
        shutil.copyfile(REDKITCHEN / frame["file_path"], dst / "images" / Path(frame["file_path"]).name)
    return dst


@pytest.fixture(scope="module")
def project(tmp_path_factory) -> tuple[Path, dict]:
    """``DIR/sparse/0`` (text) and ``DIR/images`` of the first 100 redkitchen frames and 3000 prior vertices."""
    if not (REDKITCHEN / "transforms.json").is_file():
        pytest.skip("shared redkitchen data not present")
    root = tmp_path_factory.mktemp("colmap") / "project"
    frames = redkitchen_frames()
    vertices = np.asarray(trimesh.load(REDKITCHEN / "prior_tsdf.ply", process=False).vertices, dtype=np.float64)
    points = vertices[np.random.default_rng(0).choice(len(vertices), N_POINTS, replace=False)]
    observations = write_colmap_text(root / "sparse" / "0", frames, points)
    link_images(root, frames)
    return root, {"frames": frames, "points": points, "observations": observations}


@pytest.fixture()
def small(tmp_path) -> Path:
    """A text model of 6 frames with a few points, to break."""
    if not (REDKITCHEN / "transforms.json").is_file():
        pytest.skip("shared redkitchen data not present")
    frames = redkitchen_frames(6)
    root = tmp_path / "small"
    vertices = np.asarray(trimesh.load(REDKITCHEN / "prior_tsdf.ply", process=False).vertices)[::500]
    write_colmap_text(root / "sparse", frames, vertices)
    return link_images(root, frames)


@needs_redkitchen
def test_redkitchen_round_trip(project, tmp_path):
    root, truth = project
    summary = import_colmap(root, tmp_path / "scene", PaperSplitRule())
    scene = tmp_path / "scene"
    meta = json.loads((scene / "transforms.json").read_text())
    assert summary["frames"] == N_FRAMES and summary["skipped"] == {} and summary["model"] == "sparse/0"
    assert summary["camera_models"] == ["PINHOLE -> PINHOLE"]
    intrinsics = {"camera_model": "PINHOLE", "fl_x": 585.0, "fl_y": 585.0, "cx": 320.0, "cy": 240.0, "w": 640,
                  "h": 480}
    assert {k: meta[k] for k in intrinsics} == intrinsics
    for got, want in zip(meta["frames"], truth["frames"], strict=True):
        assert got["file_path"] == want["file_path"] and set(got) == {"file_path", "transform_matrix"}
        np.testing.assert_allclose(got["transform_matrix"], want["transform_matrix"], atol=1e-6)
        assert (scene / got["file_path"]).read_bytes() == (REDKITCHEN / want["file_path"]).read_bytes()
    # the prior: every observed point, in COLMAP's world frame, with its colour
    cloud = trimesh.load(scene / meta["ply_file_path"], process=False)
    observed = sorted(truth["observations"])
    np.testing.assert_allclose(cloud.vertices, truth["points"][observed], atol=1e-5)
    assert (np.asarray(cloud.colors)[:, :3] == [200, 100, 50]).all()
    assert summary["prior"]["points"] == len(observed) > 1000
    expected = np.median([ERROR_PX * np.median([z for _, _, z in obs]) / 585 for obs in truth["observations"].values()])
    assert meta["prior_sigma"] == pytest.approx(expected, rel=1e-6) == summary["prior"]["sigma"]
    idx = paper_splits(N_FRAMES)
    names = [f["file_path"] for f in meta["frames"]]
    assert meta["train_filenames"] == [names[i] for i in idx.train]
    assert meta["eval_splits"]["extrapolation"] == [names[i] for i in idx.extrapolation]


@needs_redkitchen
def test_binary_model_reads_the_same(project, tmp_path):
    import pycolmap

    root, _ = project
    binary = tmp_path / "bin"
    (binary / "sparse").mkdir(parents=True)
    pycolmap.Reconstruction(str(root / "sparse" / "0")).write_binary(str(binary / "sparse"))
    assert (binary / "sparse" / "cameras.bin").is_file()
    import_colmap(root, tmp_path / "from_text")
    import_colmap(binary, tmp_path / "from_bin", images=root / "images")
    text_meta = json.loads((tmp_path / "from_text" / "transforms.json").read_text())
    bin_meta = json.loads((tmp_path / "from_bin" / "transforms.json").read_text())
    assert text_meta == bin_meta and "train_filenames" not in bin_meta


@needs_redkitchen
def test_imported_scene_loads(small, tmp_path):
    from voxnerf.data.scene import inspect_scene

    import_colmap(small, tmp_path / "scene")
    summary = inspect_scene(tmp_path / "scene")
    assert summary["frames"] == 6 and summary["prior"]["source"] == "ply_file_path"


@needs_redkitchen
@pytest.mark.parametrize(
    ("colmap", "params", "model", "expected"),
    [
        ("SIMPLE_PINHOLE", "585 320 240", "PINHOLE", {"fl_x": 585.0, "fl_y": 585.0}),
        ("SIMPLE_RADIAL", "585 320 240 0.01", "OPENCV", {"k1": 0.01, "k2": 0.0, "p1": 0.0, "p2": 0.0}),
        ("RADIAL", "585 320 240 0.01 -0.02", "OPENCV", {"k1": 0.01, "k2": -0.02, "p1": 0.0, "p2": 0.0}),
        ("OPENCV", "585 586 320 240 0.01 -0.02 0.001 0.002", "OPENCV",
         {"fl_y": 586.0, "k1": 0.01, "k2": -0.02, "p1": 0.001, "p2": 0.002}),
        ("OPENCV_FISHEYE", "585 586 320 240 0.1 0.2 0.3 0.4", "OPENCV_FISHEYE",
         {"k1": 0.1, "k2": 0.2, "k3": 0.3, "k4": 0.4}),
        ("SIMPLE_RADIAL_FISHEYE", "585 320 240 0.1", "OPENCV_FISHEYE", {"k1": 0.1, "k2": 0.0, "k3": 0.0, "k4": 0.0}),
        ("RADIAL_FISHEYE", "585 320 240 0.1 0.2", "OPENCV_FISHEYE", {"k1": 0.1, "k2": 0.2, "k3": 0.0, "k4": 0.0}),
    ],
)
def test_camera_models_map_as_nerfstudio(small, tmp_path, colmap, params, model, expected):
    (small / "sparse" / "cameras.txt").write_text(f"1 {colmap} 640 480 {params}\n")
    summary = import_colmap(small, tmp_path / "scene")
    meta = json.loads((tmp_path / "scene" / "transforms.json").read_text())
    assert meta["camera_model"] == model and summary["camera_models"] == [f"{colmap} -> {model}"]
    assert {k: meta[k] for k in expected} == pytest.approx(expected)
    assert (meta["cx"], meta["cy"], meta["w"], meta["h"]) == (320.0, 240.0, 640, 480)
    assert "k3" not in meta or model == "OPENCV_FISHEYE"


@needs_redkitchen
def test_several_cameras_give_per_frame_intrinsics(tmp_path):
    frames = redkitchen_frames(4)
    root = link_images(tmp_path / "multi", frames)
    cams = ["1 PINHOLE 640 480 585 585 320 240", "2 SIMPLE_RADIAL 640 480 590 321 239 0.02"]
    write_colmap_text(root / "sparse" / "0", frames, np.zeros((0, 3)), cams, camera_of=lambda i: 1 + i % 2)
    summary = import_colmap(root, tmp_path / "scene")
    meta = json.loads((tmp_path / "scene" / "transforms.json").read_text())
    assert "fl_x" not in meta and "camera_model" not in meta
    assert [f["camera_model"] for f in meta["frames"]] == ["PINHOLE", "OPENCV"] * 2
    assert meta["frames"][1]["fl_x"] == 590.0 and meta["frames"][1]["k1"] == 0.02
    assert summary["camera_models"] == ["PINHOLE -> PINHOLE", "SIMPLE_RADIAL -> OPENCV"]


@needs_redkitchen
def test_unsupported_camera_model_is_refused(small, tmp_path, capsys):
    (small / "sparse" / "cameras.txt").write_text("1 FULL_OPENCV 640 480 585 585 320 240 0 0 0 0 0 0 0 0\n")
    with pytest.raises(SceneError, match=r"cameras\.txt: camera 1: camera model FULL_OPENCV is not supported"):
        import_colmap(small, tmp_path / "scene")
    assert not (tmp_path / "scene").exists()
    assert main(["import", "colmap", str(small), "--out", str(tmp_path / "scene")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "FULL_OPENCV" in err and "cameras.txt" in err


@needs_redkitchen
def test_model_without_points_gives_a_scene_without_prior(small, tmp_path, capsys):
    (small / "sparse" / "points3D.txt").write_text("# no points\n")
    summary = import_colmap(small, tmp_path / "scene")
    meta = json.loads((tmp_path / "scene" / "transforms.json").read_text())
    assert summary["prior"] is None and "no 3D points" in summary["notes"][0]
    assert "ply_file_path" not in meta and "prior_sigma" not in meta
    assert not (tmp_path / "scene" / "sparse_pc.ply").exists() and len(meta["frames"]) == 6
    assert main(["import", "colmap", str(small), "--out", str(tmp_path / "cli")]) == 0
    assert "note: the model has no 3D points" in capsys.readouterr().out


@needs_redkitchen
def test_points_without_errors_keep_the_prior_without_sigma(small, tmp_path):
    path = small / "sparse" / "points3D.txt"
    lines = [line.split() for line in path.read_text().splitlines() if not line.startswith("#")]
    path.write_text("\n".join(" ".join([*p[:7], "-1", *p[8:]]) for p in lines) + "\n")
    summary = import_colmap(small, tmp_path / "scene")
    meta = json.loads((tmp_path / "scene" / "transforms.json").read_text())
    assert meta["ply_file_path"] == "sparse_pc.ply" and "prior_sigma" not in meta
    assert summary["prior"]["sigma"] is None and "engine estimates" in summary["prior"]["sigma_rule"]


@needs_redkitchen
def test_missing_images_are_skipped_and_counted(small, tmp_path):
    for name in ("frame-000001.jpg", "frame-000004.jpg"):
        (small / "images" / name).unlink()
    summary = import_colmap(small, tmp_path / "scene")
    assert summary["frames"] == 4 and summary["skipped"] == {"image file missing": 2}
    for path in (small / "images").iterdir():
        path.unlink()
    with pytest.raises(SceneError, match=r"images: none of the model's 6 images is here"):
        import_colmap(small, tmp_path / "other")
    assert not (tmp_path / "other").exists()


@needs_redkitchen
def test_image_size_must_match_the_camera(small, tmp_path):
    (small / "sparse" / "cameras.txt").write_text("1 PINHOLE 320 240 292 292 160 120\n")
    with pytest.raises(SceneError, match=r"frame-000000\.jpg: image is 640x480 but camera 1 of cameras\.txt"):
        import_colmap(small, tmp_path / "scene")


@needs_redkitchen
def test_image_names_cannot_leave_the_image_folder(small, tmp_path):
    path = small / "sparse" / "images.txt"
    path.write_text(path.read_text().replace("frame-000002.jpg", "../../etc/passwd"))
    with pytest.raises(SceneError, match=r"images\.txt: image name '\.\./\.\./etc/passwd'"):
        import_colmap(small, tmp_path / "scene")


def test_empty_and_missing_folders(tmp_path, capsys):
    with pytest.raises(SceneError, match="not a directory"):
        import_colmap(tmp_path / "nothing", tmp_path / "scene")
    (tmp_path / "empty").mkdir()
    with pytest.raises(SceneError, match="no COLMAP model: cameras.bin or cameras.txt not found"):
        import_colmap(tmp_path / "empty", tmp_path / "scene")
    (tmp_path / "empty" / "sparse").mkdir()
    (tmp_path / "empty" / "sparse" / "cameras.txt").write_text("1 PINHOLE 640 480 585 585 320 240\n")
    with pytest.raises(SceneError, match=r"empty/images: image folder not found"):
        import_colmap(tmp_path / "empty", tmp_path / "scene")
    (tmp_path / "empty" / "images").mkdir()
    with pytest.raises(SceneError, match=r"empty/sparse: cannot read the COLMAP model"):
        import_colmap(tmp_path / "empty", tmp_path / "scene")
    for name in ("images.txt", "points3D.txt"):
        (tmp_path / "empty" / "sparse" / name).write_text("# nothing\n")
    with pytest.raises(SceneError, match=r"images\.txt: the COLMAP model lists no images"):
        import_colmap(tmp_path / "empty", tmp_path / "scene")
    assert main(["import", "colmap", str(tmp_path / "empty"), "--out", str(tmp_path / "scene")]) == 2
    assert capsys.readouterr().err.count("\n") == 1
    assert not (tmp_path / "scene").exists()


@needs_redkitchen
def test_output_must_be_absent_or_empty(small, tmp_path):
    (tmp_path / "scene").mkdir()
    (tmp_path / "scene" / "x.json").write_text("{}")
    with pytest.raises(SceneError, match=r"scene: the output must not exist or be an empty directory"):
        import_colmap(small, tmp_path / "scene")
    (tmp_path / "file").write_text("x")
    with pytest.raises(SceneError, match="must not exist"):
        import_colmap(small, tmp_path / "file")


def test_camera_table_matches_the_brief():
    assert {k: v[0] for k, v in CAMERA_MODELS.items()} == {
        "SIMPLE_PINHOLE": "PINHOLE", "PINHOLE": "PINHOLE", "SIMPLE_RADIAL": "OPENCV", "RADIAL": "OPENCV",
        "OPENCV": "OPENCV", "OPENCV_FISHEYE": "OPENCV_FISHEYE", "SIMPLE_RADIAL_FISHEYE": "OPENCV_FISHEYE",
        "RADIAL_FISHEYE": "OPENCV_FISHEYE",
    }
