"""``voxnerf import record3d``: redkitchen written as Record3D's EXR + JPG export comes back with its poses (to
1e-6), intrinsics and LiDAR depth registered through its own scaled intrinsics; bad exports give one-line errors
naming the file, or counted skips, and never a half-written scene."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest
from phone_app_fixtures import (
    DEPTH_H,
    DEPTH_W,
    REDKITCHEN,
    check_depth_registration,
    check_poses,
    needs_redkitchen,
    redkitchen_frames,
    write_record3d,
)

from voxnerf.cli import main
from voxnerf.data.importers.arkit import pose_from_quaternion, quaternion_rotation
from voxnerf.data.importers.record3d import import_record3d
from voxnerf.errors import SceneError

pytestmark = needs_redkitchen
N_FRAMES = 12


@pytest.fixture()
def export(tmp_path):
    return write_record3d(tmp_path / "capture", redkitchen_frames(N_FRAMES))


def test_quaternion_order_is_x_y_z_w():
    # A quarter turn about +Z, written qx qy qz qw: x goes to y.
    s = np.sqrt(0.5)
    np.testing.assert_allclose(quaternion_rotation(0.0, 0.0, s, s) @ [1, 0, 0], [0, 1, 0], atol=1e-12)
    pose = pose_from_quaternion([0.0, 0.0, 0.0, 1.0], [1.0, 2.0, 3.0])
    np.testing.assert_array_equal(pose[:3, 3], [1, 2, 3])
    with pytest.raises(ValueError, match="quaternion norm 2"):
        quaternion_rotation(0.0, 0.0, 0.0, 2.0)
    with pytest.raises(ValueError, match="non-finite"):
        quaternion_rotation(np.nan, 0.0, 0.0, 1.0)


def test_round_trip_poses_intrinsics_and_depth(export, tmp_path):
    source = redkitchen_frames(N_FRAMES)
    summary = import_record3d(export, tmp_path / "scene")
    meta = check_poses(tmp_path / "scene", source, quaternions=True)
    assert summary["format"] == "record3d" and summary["frames"] == N_FRAMES and summary["skipped"] == {}
    assert summary["depth_frames"] == sum("depth_file_path" in f for f in source) == 3
    for got, want in zip(meta["frames"], source, strict=True):
        assert (tmp_path / "scene" / got["file_path"]).read_bytes() == (REDKITCHEN / want["file_path"]).read_bytes()
        if "depth_file_path" in got:
            assert got["depth_intrinsics"] == {"fl_x": 585 * 0.4, "fl_y": 585 * 0.4, "cx": 128.0, "cy": 96.0,
                                               "w": DEPTH_W, "h": DEPTH_H}
    # No confidence maps in this export: every measured pixel is kept.
    assert check_depth_registration(tmp_path / "scene", source, None, 0) == 3


def test_the_export_folder_or_its_parent(export, tmp_path):
    summary = import_record3d(export / "EXR_RGBD", tmp_path / "scene")
    assert summary["frames"] == N_FRAMES


def test_every_nth_frame(export, tmp_path):
    source = redkitchen_frames(N_FRAMES)[::5]
    summary = import_record3d(export, tmp_path / "scene", every=5)
    check_poses(tmp_path / "scene", source, quaternions=True)
    assert summary["frames"] == 3 and summary["depth_frames"] == 3


def test_missing_images_and_invalid_poses_are_counted(export, tmp_path):
    root = export / "EXR_RGBD"
    (root / "rgb" / "3.jpg").unlink()
    meta = json.loads((root / "metadata.json").read_text())
    meta["poses"][4][:4] = [0.0, 0.0, 0.0, 0.0]
    meta["poses"][6][5] = float("nan")
    (root / "metadata.json").write_text(json.dumps(meta))
    summary = import_record3d(export, tmp_path / "scene")
    assert summary["frames"] == N_FRAMES - 3
    assert summary["skipped"] == {"no image file": 1, "invalid pose (quaternion norm 0, expected 1)": 1,
                                  "invalid pose (non-finite values)": 1}


def test_missing_files_are_one_line_errors_naming_them(export, tmp_path):
    root = export / "EXR_RGBD"
    with pytest.raises(SceneError, match=r"nothing: not a directory"):
        import_record3d(tmp_path / "nothing", tmp_path / "scene")
    shutil.rmtree(root / "rgb")
    with pytest.raises(SceneError, match=r"EXR_RGBD/rgb: folder not found"):
        import_record3d(export, tmp_path / "scene")
    meta = json.loads((root / "metadata.json").read_text())
    del meta["K"]
    (root / "metadata.json").write_text(json.dumps(meta))
    with pytest.raises(SceneError, match=r"metadata\.json: K: missing"):
        import_record3d(export, tmp_path / "scene")
    (root / "metadata.json").unlink()
    with pytest.raises(SceneError, match=r"capture/metadata\.json: file not found") as err:
        import_record3d(export, tmp_path / "scene")
    assert "\n" not in str(err.value)
    assert not (tmp_path / "scene").exists()


def test_an_r3d_file_asks_for_the_exr_export(tmp_path):
    (tmp_path / "scan.r3d").write_bytes(b"PK\x03\x04")
    with pytest.raises(SceneError, match=r"scan\.r3d: Record3D's \.r3d files are not read: export the recording as "
                                         r"'EXR \+ JPG sequence'"):
        import_record3d(tmp_path / "scan.r3d", tmp_path / "scene")


def test_a_broken_depth_file_leaves_nothing_behind(export, tmp_path):
    (export / "EXR_RGBD" / "depth" / "5.exr").write_bytes(b"not an exr")
    with pytest.raises(SceneError, match=r"depth/5\.exr: cannot read depth EXR"):
        import_record3d(export, tmp_path / "scene")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["capture"]


def test_depth_of_another_aspect_ratio_is_refused(export, tmp_path):
    from voxnerf.data.image_io import encode_exr

    (export / "EXR_RGBD" / "depth" / "0.exr").write_bytes(encode_exr({"R": np.ones((192, 192), np.float32)}))
    with pytest.raises(SceneError, match=r"depth/0\.exr: depth map is 192x192, not the aspect ratio"):
        import_record3d(export, tmp_path / "scene")
    assert not (tmp_path / "scene").exists()


def test_cli(export, tmp_path, capsys):
    assert main(["import", "record3d", str(export), "--out", str(tmp_path / "scene")]) == 0
    out = capsys.readouterr().out
    assert f"record3d: imported {N_FRAMES} frames" in out and "frames with depth: 3" in out
    assert main(["import", "record3d", str(tmp_path / "scene"), "--out", str(tmp_path / "other")]) == 2
    err = capsys.readouterr().err.strip()
    assert err == f"voxnerf: error: {tmp_path / 'scene' / 'metadata.json'}: file not found (a Record3D EXR + JPG " \
                  "export has metadata.json, rgb/, depth/)"


def test_per_frame_intrinsics_when_given_for_every_pose(export, tmp_path):
    root = export / "EXR_RGBD"
    meta = json.loads((root / "metadata.json").read_text())
    meta["perFrameIntrinsicCoeffs"] = [[585.0, 585.0, 320.0, 240.0]] * N_FRAMES
    meta["perFrameIntrinsicCoeffs"][5] = [580.0, 581.0, 318.0, 241.0]
    (root / "metadata.json").write_text(json.dumps(meta))
    import_record3d(export, tmp_path / "scene")
    frames = json.loads((tmp_path / "scene" / "transforms.json").read_text())["frames"]
    assert (frames[5]["fl_x"], frames[5]["fl_y"], frames[5]["cx"], frames[5]["cy"]) == (580, 581, 318, 241)
    assert frames[5]["depth_intrinsics"]["cx"] == pytest.approx(318 * 0.4)
    assert all("fl_x" not in f for i, f in enumerate(frames) if i != 5)
    meta["perFrameIntrinsicCoeffs"] = meta["perFrameIntrinsicCoeffs"][:3]  # not one per pose: K for all
    (root / "metadata.json").write_text(json.dumps(meta))
    import_record3d(export, tmp_path / "other")
    assert all("fl_x" not in f for f in json.loads((tmp_path / "other" / "transforms.json").read_text())["frames"])
