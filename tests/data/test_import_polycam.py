"""``voxnerf import polycam``: redkitchen written as Polycam's raw-data export comes back with its poses (to
1e-6), per-keyframe cameras, LiDAR depth registered through its own camera and low-confidence depth dropped;
corrected cameras are preferred; bad exports give one-line errors naming the file, or counted skips."""

from __future__ import annotations

import json
import shutil

import imageio.v3 as iio
import numpy as np
import pytest
from phone_app_fixtures import (
    DEPTH_H,
    DEPTH_W,
    HEIGHT,
    HIGH,
    LOW,
    MEDIUM,
    WIDTH,
    check_depth_registration,
    check_poses,
    lidar_confidence,
    lidar_depth_mm,
    needs_redkitchen,
    polycam_stem,
    redkitchen_frames,
    write_polycam,
)

from voxnerf.cli import main
from voxnerf.data.importers.polycam import import_polycam
from voxnerf.errors import SceneError

pytestmark = needs_redkitchen
N_FRAMES = 12


@pytest.fixture()
def export(tmp_path):
    return write_polycam(tmp_path / "capture", redkitchen_frames(N_FRAMES))


@pytest.mark.parametrize(("min_confidence", "level"), [("medium", MEDIUM), ("high", HIGH), ("low", LOW)])
def test_round_trip_poses_and_depth_with_confidence(export, tmp_path, min_confidence, level):
    source = redkitchen_frames(N_FRAMES)
    summary = import_polycam(export, tmp_path / "scene", min_confidence=min_confidence)
    meta = check_poses(tmp_path / "scene", source, quaternions=False)
    assert [f["file_path"] for f in meta["frames"]] == [f"images/{polycam_stem(i)}.jpg" for i in range(N_FRAMES)]
    assert summary["format"] == "polycam" and summary["frames"] == N_FRAMES and summary["depth_frames"] == 3
    assert check_depth_registration(tmp_path / "scene", source, lidar_confidence(), level) == 3
    measured = sum(int((lidar_depth_mm(f) > 0).sum()) for f in source if "depth_file_path" in f)
    dropped = sum(int(((lidar_depth_mm(f) > 0) & (lidar_confidence() < level)).sum())
                  for f in source if "depth_file_path" in f)
    expected = (f"all {measured} measured depth pixels kept (no confidence filter)" if level == LOW else
                f"{dropped} of {measured} measured depth pixels")
    assert dropped > 0 or level == LOW
    assert any(expected in note for note in summary["notes"])


def test_corrected_cameras_are_preferred_and_depth_keeps_its_camera(export, tmp_path):
    """Corrected images cropped by 16 px with their own camera: depth stays on the original camera."""
    root = export / "keyframes"
    (root / "corrected_images").mkdir()
    (root / "corrected_cameras").mkdir()
    source = redkitchen_frames(N_FRAMES)
    shifted = []
    for i, frame in enumerate(source):
        stem = polycam_stem(i)
        image = iio.imread(root / "images" / f"{stem}.jpg")
        iio.imwrite(root / "corrected_images" / f"{stem}.png", image[16:-16, 16:-16])
        camera = json.loads((root / "cameras" / f"{stem}.json").read_text())
        camera.update(cx=camera["cx"] - 16, cy=camera["cy"] - 16, width=WIDTH - 32, height=HEIGHT - 32)
        pose = np.asarray(frame["transform_matrix"], dtype=np.float64)
        pose[:3, 3] += [0.01, -0.02, 0.005]  # refined poses
        camera.update({f"t_{r}{c}": float(pose[r, c]) for r in range(3) for c in range(4)})
        (root / "corrected_cameras" / f"{stem}.json").write_text(json.dumps(camera))
        shifted.append({**frame, "transform_matrix": pose.tolist()})
    summary = import_polycam(export, tmp_path / "scene")
    meta = json.loads((tmp_path / "scene" / "transforms.json").read_text())
    assert (meta["w"], meta["h"], meta["cx"], meta["cy"]) == (WIDTH - 32, HEIGHT - 32, 304, 224)
    for got, want in zip(meta["frames"], shifted, strict=True):
        np.testing.assert_allclose(got["transform_matrix"], want["transform_matrix"], atol=1e-12)
        if "depth_file_path" in got:  # the original camera, scaled to the LiDAR grid
            assert got["depth_intrinsics"] == {"fl_x": 234.0, "fl_y": 234.0, "cx": 128.0, "cy": 96.0,
                                               "w": DEPTH_W, "h": DEPTH_H}
    assert any("corrected_cameras/ and corrected_images/" in note for note in summary["notes"])

    from voxnerf.data.scene import depth_on_image, load_scene

    loaded = load_scene(tmp_path / "scene", load_images=False)
    frame = loaded.frames[0]
    got = depth_on_image(frame, loaded.depth_unit_scale, 1)
    depth = lidar_depth_mm(source[0]) * 0.001
    depth[(lidar_depth_mm(source[0]) == 0) | (lidar_confidence() < MEDIUM)] = np.nan
    # Cropped pixel (x, y) is original pixel (x + 16, y + 16); take pixels whose centre is off every LiDAR edge.
    for y, x in [(3, 3), (100, 200), (300, 500), (440, 590)]:
        row, col = int((y + 16.5) * DEPTH_H / HEIGHT), int((x + 16.5) * DEPTH_W / WIDTH)
        np.testing.assert_equal(got[y, x], np.float32(depth[row, col]))


def test_missing_camera_files_are_counted_and_missing_confidence_drops_depth(export, tmp_path):
    root = export / "keyframes"
    (root / "cameras" / f"{polycam_stem(1)}.json").unlink()
    (root / "confidence" / f"{polycam_stem(5)}.png").unlink()
    summary = import_polycam(export, tmp_path / "scene")
    assert summary["frames"] == N_FRAMES - 1 and summary["skipped"] == {"no camera file": 1}
    assert summary["depth_frames"] == 2
    assert any("1 frame(s) have a depth map but no confidence map" in note for note in summary["notes"])
    summary = import_polycam(export, tmp_path / "unfiltered", min_confidence="low")
    assert summary["depth_frames"] == 3


def test_bad_files_are_one_line_errors_naming_them(export, tmp_path):
    root = export / "keyframes"
    camera_path = root / "cameras" / f"{polycam_stem(2)}.json"
    camera = json.loads(camera_path.read_text())
    del camera["t_13"]
    camera_path.write_text(json.dumps(camera))
    with pytest.raises(SceneError, match=rf"{polycam_stem(2)}\.json: key 't_13' missing"):
        import_polycam(export, tmp_path / "scene")
    camera_path.write_text("{")
    with pytest.raises(SceneError, match=r"cannot read a Polycam camera"):
        import_polycam(export, tmp_path / "scene")
    shutil.rmtree(root / "cameras")
    with pytest.raises(SceneError, match=r"capture/keyframes/cameras: folder not found"):
        import_polycam(export, tmp_path / "scene")
    assert not (tmp_path / "scene").exists()


def test_a_bad_depth_map_leaves_nothing_behind(export, tmp_path):
    root = export / "keyframes"
    iio.imwrite(root / "depth" / f"{polycam_stem(10)}.png", np.zeros((192, 256, 3), np.uint8))
    with pytest.raises(SceneError, match=rf"depth/{polycam_stem(10)}\.png: depth PNG must be 16-bit"):
        import_polycam(export, tmp_path / "scene")
    iio.imwrite(root / "depth" / f"{polycam_stem(10)}.png", np.zeros((96, 128), np.uint16))
    with pytest.raises(SceneError, match=r"confidence map is \[192, 256\], its depth map \[96, 128\]"):
        import_polycam(export, tmp_path / "scene")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["capture"]


def test_invalid_min_confidence(export, tmp_path):
    with pytest.raises(ValueError, match="min_confidence must be one of low, medium, high"):
        import_polycam(export, tmp_path / "scene", min_confidence="some")


def test_cli(export, tmp_path, capsys):
    assert main(["import", "polycam", str(export), "--out", str(tmp_path / "scene"), "--min-confidence", "high"]) == 0
    out = capsys.readouterr().out
    assert f"polycam: imported {N_FRAMES} frames" in out and "below high confidence dropped" in out


def test_a_keyframe_with_its_own_camera_keeps_it(export, tmp_path):
    path = export / "keyframes" / "cameras" / f"{polycam_stem(5)}.json"
    camera = json.loads(path.read_text())
    camera.update(fx=590.0, fy=589.0, cx=321.5)
    path.write_text(json.dumps(camera))
    import_polycam(export, tmp_path / "scene")
    meta = json.loads((tmp_path / "scene" / "transforms.json").read_text())
    assert meta["fl_x"] == 585 and all("fl_x" not in f for i, f in enumerate(meta["frames"]) if i != 5)
    frame = meta["frames"][5]
    assert (frame["fl_x"], frame["fl_y"], frame["cx"], frame["cy"], frame["w"]) == (590, 589, 321.5, 240, WIDTH)
    assert frame["depth_intrinsics"]["fl_x"] == pytest.approx(590 * DEPTH_W / WIDTH)


def test_an_unreadable_image_names_the_apps_file(export, tmp_path):
    image = export / "keyframes" / "images" / f"{polycam_stem(7)}.jpg"
    image.write_bytes(b"not a jpeg")
    with pytest.raises(SceneError, match=rf"^{image}: frame {polycam_stem(7)}: ") as err:
        import_polycam(export, tmp_path / "scene")
    assert ".tmp" not in str(err.value) and not (tmp_path / "scene").exists()
