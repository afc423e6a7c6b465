"""``voxnerf import scannet``: the shared redkitchen scene re-expressed in ScanNet's exported layout comes back
with its poses, intrinsics, depth and the paper's splits; bad exports give one-line errors or counted skips."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from voxnerf.cli import main
from voxnerf.data.importers import PaperSplitRule, import_scannet, paper_splits
from voxnerf.errors import SceneError

REDKITCHEN = Path(__file__).resolve().parents[3] / "shared" / "data" / "redkitchen"
needs_redkitchen = pytest.mark.skipif(
    not (REDKITCHEN / "transforms.json").is_file(), reason="shared redkitchen data not present"
)
FLIP = np.diag([1.0, -1.0, -1.0, 1.0])
K_7SCENES = np.array([[585.0, 0, 320, 0], [0, 585, 240, 0], [0, 0, 1, 0], [0, 0, 0, 1]])
N_FRAMES = 100


def redkitchen_frames(n: int = N_FRAMES) -> list[dict]:
    return json.loads((REDKITCHEN / "transforms.json").read_text())["frames"][:n]


def frame_number(file_path: str) -> int:
    return int(Path(file_path).stem.split("-")[1])


def write_scannet(dst: Path, frames: list[dict], k: np.ndarray = K_7SCENES) -> Path:
    """ScanNet's export layout of ``frames`` (redkitchen entries): color/N.jpg, depth/N.png where the frame has
    depth, pose/N.txt (camera-to-world, OpenCV axes), intrinsic/intrinsic_{color,depth}.txt."""
    for sub in ("color", "depth", "pose", "intrinsic"):
        (dst / sub).mkdir(parents=True, exist_ok=True)
    for frame in frames:
        n = frame_number(frame["file_path"])
        shutil.copyfile(REDKITCHEN / frame["file_path"], dst / "color" / f"{n}.jpg")
        if "depth_file_path" in frame:
            shutil.copyfile(REDKITCHEN / frame["depth_file_path"], dst / "depth" / f"{n}.png")
        np.savetxt(dst / "pose" / f"{n}.txt", np.asarray(frame["transform_matrix"]) @ FLIP, fmt="%.17g")
    np.savetxt(dst / "intrinsic" / "intrinsic_color.txt", k, fmt="%.6f")
    np.savetxt(dst / "intrinsic" / "intrinsic_depth.txt", k, fmt="%.6f")
    return dst


@pytest.fixture(scope="module")
def export(tmp_path_factory) -> Path:
    if not (REDKITCHEN / "transforms.json").is_file():
        pytest.skip("shared redkitchen data not present")
    return write_scannet(tmp_path_factory.mktemp("scannet") / "export", redkitchen_frames())


@pytest.fixture()
def small_export(tmp_path, export) -> Path:
    """A copy of the first 12 frames of ``export``, to break."""
    dst = tmp_path / "small"
    for sub in ("color", "depth", "pose"):
        (dst / sub).mkdir(parents=True)
        for path in sorted((export / sub).iterdir(), key=lambda p: int(p.stem))[:12]:
            if int(path.stem) < 12:
                shutil.copyfile(path, dst / sub / path.name)
    shutil.copytree(export / "intrinsic", dst / "intrinsic")
    return dst


@needs_redkitchen
def test_redkitchen_round_trip(export, tmp_path):
    summary = import_scannet(export, tmp_path / "scene", PaperSplitRule())
    meta = json.loads((tmp_path / "scene" / "transforms.json").read_text())
    source = redkitchen_frames()
    assert summary["frames"] == len(meta["frames"]) == N_FRAMES and summary["skipped"] == {}
    assert [frame_number(f["file_path"].replace("images/", "frame-")) for f in meta["frames"]] == list(range(100))
    for got, want in zip(meta["frames"], source, strict=True):
        np.testing.assert_allclose(got["transform_matrix"], want["transform_matrix"], atol=1e-6)
        assert (tmp_path / "scene" / got["file_path"]).read_bytes() == (REDKITCHEN / want["file_path"]).read_bytes()
        assert ("depth_file_path" in got) == ("depth_file_path" in want)
        if "depth_file_path" in got:
            assert (tmp_path / "scene" / got["depth_file_path"]).read_bytes() == (
                REDKITCHEN / want["depth_file_path"]
            ).read_bytes()
    intrinsics = {"fl_x": 585.0, "fl_y": 585.0, "cx": 320.0, "cy": 240.0, "w": 640, "h": 480}
    assert {k: meta[k] for k in intrinsics} == intrinsics and meta["camera_model"] == "PINHOLE"
    assert meta["depth_intrinsics"] == intrinsics and meta["depth_unit_scale_factor"] == 0.001
    assert summary["depth_frames"] == 20 and any("80 frame(s) without a depth map" in n for n in summary["notes"])
    idx = paper_splits(N_FRAMES)
    names = [f["file_path"] for f in meta["frames"]]
    assert meta["train_filenames"] == [names[i] for i in idx.train]
    assert meta["eval_splits"] == {
        "interpolation": [names[i] for i in idx.interpolation],
        "extrapolation": [names[i] for i in idx.extrapolation],
    }
    assert summary["splits"]["train"] == len(idx.train) and summary["splits"]["train_fraction"] == 0.1


@needs_redkitchen
def test_without_splits_no_split_keys(small_export, tmp_path):
    import_scannet(small_export, tmp_path / "scene")
    meta = json.loads((tmp_path / "scene" / "transforms.json").read_text())
    assert not {"train_filenames", "eval_splits", "test_filenames", "val_filenames"} & set(meta)


@needs_redkitchen
def test_imported_scene_loads(small_export, tmp_path):
    from voxnerf.data.scene import inspect_scene

    import_scannet(small_export, tmp_path / "scene")
    summary = inspect_scene(tmp_path / "scene")
    assert summary["frames"] == 12 and summary["depth"]


@needs_redkitchen
def test_invalid_poses_are_skipped_and_counted(small_export, tmp_path):
    (small_export / "pose" / "3.txt").write_text("-inf -inf -inf -inf\n" * 4)
    (small_export / "pose" / "4.txt").write_text("nan 0 0 0\n0 1 0 0\n0 0 1 0\n0 0 0 1\n")
    (small_export / "pose" / "5.txt").write_text("2 0 0 0\n0 1 0 0\n0 0 1 0\n0 0 0 1\n")
    (small_export / "pose" / "6.txt").write_text("not a pose\n")
    (small_export / "pose" / "7.txt").unlink()
    summary = import_scannet(small_export, tmp_path / "scene")
    assert summary["frames"] == 7
    assert summary["skipped"] == {
        "invalid pose (non-finite values)": 2,
        "invalid pose (not a rotation)": 1,
        "unreadable pose file": 1,
        "no pose file": 1,
    }
    meta = json.loads((tmp_path / "scene" / "transforms.json").read_text())
    assert "images/3.jpg" not in {f["file_path"] for f in meta["frames"]}


@needs_redkitchen
def test_missing_depth_files_leave_frames_without_depth(small_export, tmp_path):
    for path in (small_export / "depth").iterdir():
        path.unlink()
    summary = import_scannet(small_export, tmp_path / "scene")
    meta = json.loads((tmp_path / "scene" / "transforms.json").read_text())
    assert summary["depth_frames"] == 0 and summary["frames"] == 12
    assert not any("depth_file_path" in f for f in meta["frames"])
    assert "depth_unit_scale_factor" not in meta and "depth_intrinsics" not in meta
    assert any("no depth maps" in note for note in summary["notes"])


@needs_redkitchen
def test_bad_depth_map_names_the_file(small_export, tmp_path):
    shutil.copyfile(small_export / "color" / "0.jpg", small_export / "depth" / "0.png")
    with pytest.raises(SceneError, match=r"depth/0\.png: ScanNet depth must be a 16-bit"):
        import_scannet(small_export, tmp_path / "scene")
    assert not (tmp_path / "scene").exists() and list(tmp_path.iterdir()) == [small_export]


@needs_redkitchen
def test_all_poses_invalid_is_one_error(small_export, tmp_path):
    for path in (small_export / "pose").iterdir():
        path.write_text("-inf -inf -inf -inf\n" * 4)
    with pytest.raises(SceneError, match="no usable frame: all 12 are skipped"):
        import_scannet(small_export, tmp_path / "scene")


@needs_redkitchen
def test_too_few_frames_for_paper_splits(small_export, tmp_path):
    with pytest.raises(SceneError, match="too few for the paper's splits"):
        import_scannet(small_export, tmp_path / "scene", PaperSplitRule())
    assert not (tmp_path / "scene").exists()


def test_missing_folders_name_them(tmp_path):
    with pytest.raises(SceneError, match="nothing: not a directory"):
        import_scannet(tmp_path / "nothing", tmp_path / "scene")
    (tmp_path / "empty").mkdir()
    with pytest.raises(SceneError, match=r"empty/color: folder not found"):
        import_scannet(tmp_path / "empty", tmp_path / "scene")
    for sub in ("color", "pose"):
        (tmp_path / "empty" / sub).mkdir()
    with pytest.raises(SceneError, match=r"intrinsic_color\.txt: file not found"):
        import_scannet(tmp_path / "empty", tmp_path / "scene")
    (tmp_path / "empty" / "intrinsic").mkdir()
    (tmp_path / "empty" / "intrinsic" / "intrinsic_color.txt").write_text("1 2 3\n")
    with pytest.raises(SceneError, match=r"intrinsic_color\.txt: expected a 4x4"):
        import_scannet(tmp_path / "empty", tmp_path / "scene")
    np.savetxt(tmp_path / "empty" / "intrinsic" / "intrinsic_color.txt", K_7SCENES)
    with pytest.raises(SceneError, match=r"color: no colour images"):
        import_scannet(tmp_path / "empty", tmp_path / "scene")
    assert not (tmp_path / "scene").exists()


@needs_redkitchen
def test_output_must_be_absent_or_empty(small_export, tmp_path):
    out = tmp_path / "scene"
    out.mkdir()
    (out / "keep.txt").write_text("x")
    with pytest.raises(SceneError, match="must not exist or be an empty directory"):
        import_scannet(small_export, out)
    assert [p.name for p in out.iterdir()] == ["keep.txt"]
    (out / "keep.txt").unlink()
    import_scannet(small_export, out)  # an empty directory is fine
    assert (out / "transforms.json").is_file()


@needs_redkitchen
def test_cli_prints_summary_and_one_line_errors(small_export, tmp_path, capsys):
    assert main(["import", "scannet", str(small_export), "--out", str(tmp_path / "scene")]) == 0
    out = capsys.readouterr().out
    assert "scannet: imported 12 frames" in out and f"wrote {tmp_path / 'scene'}" in out
    assert main(["import", "scannet", str(small_export), "--out", str(tmp_path / "scene")]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "scene: the output must not exist" in err and err.startswith("voxnerf: error:")
    assert main(["import", "scannet", str(tmp_path / "missing"), "--out", str(tmp_path / "other")]) == 2
    assert capsys.readouterr().err.strip() == f"voxnerf: error: {tmp_path / 'missing'}: not a directory"


@needs_redkitchen
def test_a_smaller_depth_camera_is_registered_to_the_colour_images(small_export, tmp_path):
    """ScanNet's depth (640x480) is smaller than its colour (1296x968): here the depth maps are halved to
    320x240 with their own intrinsics; the imported scene registers them to the colour pixels on load."""
    import imageio.v3 as iio

    from voxnerf.data.scene import load_scene

    originals = {}
    for path in (small_export / "depth").iterdir():
        originals[int(path.stem)] = iio.imread(path)
        iio.imwrite(path, originals[int(path.stem)][::2, ::2])
    k_depth = K_7SCENES.copy()
    k_depth[:2, :3] /= 2
    np.savetxt(small_export / "intrinsic" / "intrinsic_depth.txt", k_depth, fmt="%.6f")
    import_scannet(small_export, tmp_path / "scene")
    meta = json.loads((tmp_path / "scene" / "transforms.json").read_text())
    assert meta["depth_intrinsics"] == {"fl_x": 292.5, "fl_y": 292.5, "cx": 160.0, "cy": 120.0, "w": 320, "h": 240}
    scene = load_scene(tmp_path / "scene")
    checked = 0
    for i in scene.train_indices:
        if scene.depths[i] is None:
            continue
        halved = originals[frame_number(scene.frames[i].file_path.replace("images/", "frame-"))][::2, ::2]
        expected = np.repeat(np.repeat(halved, 2, axis=0), 2, axis=1).astype(np.float64) * 0.001
        expected[expected == 0] = np.nan
        np.testing.assert_allclose(scene.depths[i], expected, rtol=1e-6)
        checked += 1
    assert checked > 0
