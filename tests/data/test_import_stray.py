"""``voxnerf import stray``: redkitchen written as a Stray Scanner recording (an MP4 of its colour frames, OpenCV-axes
odometry, 256 x 192 depth and confidence) comes back with its poses (to 1e-6), each video frame on its own pose,
and its depth registered; bad recordings give one-line errors naming the file, or counted skips."""

from __future__ import annotations

import json

import imageio.v3 as iio
import numpy as np
import pytest
from phone_app_fixtures import (
    MEDIUM,
    REDKITCHEN,
    check_depth_registration,
    check_poses,
    lidar_confidence,
    needs_redkitchen,
    redkitchen_frames,
    write_stray,
)

from voxnerf.cli import main
from voxnerf.data.importers.stray import import_stray
from voxnerf.errors import SceneError

pytestmark = needs_redkitchen
N_FRAMES = 15


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    return write_stray(tmp_path_factory.mktemp("stray") / "recording", redkitchen_frames(N_FRAMES))


@pytest.fixture()
def copy(recording, tmp_path):
    import shutil

    return shutil.copytree(recording, tmp_path / "copy")


def test_round_trip_poses_frames_and_depth(recording, tmp_path):
    source = redkitchen_frames(N_FRAMES)
    summary = import_stray(recording, tmp_path / "scene")
    meta = check_poses(tmp_path / "scene", source, quaternions=True)
    assert summary["format"] == "stray" and summary["frames"] == N_FRAMES and summary["skipped"] == {}
    assert [f["file_path"] for f in meta["frames"]] == [f"images/{i:06d}.jpg" for i in range(N_FRAMES)]
    assert check_depth_registration(tmp_path / "scene", source, lidar_confidence(), MEDIUM) == 3
    # Each written frame is its own source frame (H.264 is lossy), not a neighbour's.
    originals = [iio.imread(REDKITCHEN / f["file_path"]).astype(float) for f in source]
    for i, entry in enumerate(meta["frames"]):
        got = iio.imread(tmp_path / "scene" / entry["file_path"]).astype(float)
        errors = [np.abs(got - original).mean() for original in originals]
        assert int(np.argmin(errors)) == i and errors[i] < 6.0


def test_every_nth_row(recording, tmp_path):
    source = redkitchen_frames(N_FRAMES)[::4]
    summary = import_stray(recording, tmp_path / "scene", every=4)
    meta = check_poses(tmp_path / "scene", source, quaternions=True)
    assert summary["frames"] == 4 and [f["file_path"] for f in meta["frames"]][-1] == "images/000012.jpg"
    originals = [iio.imread(REDKITCHEN / f["file_path"]).astype(float) for f in redkitchen_frames(N_FRAMES)]
    got = iio.imread(tmp_path / "scene" / "images" / "000012.jpg").astype(float)
    assert int(np.argmin([np.abs(got - o).mean() for o in originals])) == 12


def test_rows_past_the_video_and_invalid_poses_are_counted(copy, tmp_path):
    lines = (copy / "odometry.csv").read_text().splitlines()
    lines[3] = lines[3].rsplit(",", 1)[0] + ", nan"
    last = lines[-1].split(",")
    lines.append(", ".join([last[0], f"{N_FRAMES:06d}", *last[2:]]))
    (copy / "odometry.csv").write_text("\n".join(lines) + "\n")
    summary = import_stray(copy, tmp_path / "scene")
    assert summary["frames"] == N_FRAMES - 1
    assert summary["skipped"] == {"invalid pose (non-finite values)": 1, "no video frame": 1}


def test_missing_files_are_one_line_errors_naming_them(copy, tmp_path):
    (copy / "camera_matrix.csv").write_text("585, 0, 320\n0, 585, 240\n")
    with pytest.raises(SceneError, match=r"camera_matrix\.csv: expected 3 rows of 3"):
        import_stray(copy, tmp_path / "scene")
    lines = (copy / "odometry.csv").read_text().splitlines()
    (copy / "odometry.csv").write_text("\n".join([lines[0], lines[1], "1.0, 000001, 0.1, x"]))
    (copy / "camera_matrix.csv").write_text("585, 0, 320\n0, 585, 240\n0, 0, 1\n")
    with pytest.raises(SceneError, match=r"odometry\.csv: line 3: expected 9 numbers"):
        import_stray(copy, tmp_path / "scene")
    (copy / "odometry.csv").write_text("1.0, 000001, 0, 0, 0, 0, 0, 0, 1\n")
    with pytest.raises(SceneError, match=r"odometry\.csv: line 1: header lacks frame, x, y, z"):
        import_stray(copy, tmp_path / "scene")
    (copy / "odometry.csv").unlink()
    with pytest.raises(SceneError, match=r"copy/odometry\.csv: file not found") as err:
        import_stray(copy, tmp_path / "scene")
    assert "\n" not in str(err.value) and not (tmp_path / "scene").exists()


def test_a_video_without_decodable_frames(copy, tmp_path):
    (copy / "rgb.mp4").write_bytes(b"\x00\x00\x00\x18ftypmp42" + bytes(200))
    with pytest.raises(SceneError, match=r"rgb\.mp4: (cannot decode video|no decodable video frames)") as err:
        import_stray(copy, tmp_path / "scene")
    assert "\n" not in str(err.value) and not (tmp_path / "scene").exists()


def test_a_bad_confidence_map_leaves_nothing_behind(copy, tmp_path):
    iio.imwrite(copy / "confidence" / "000010.png", np.full((192, 256), 7, np.uint8))
    with pytest.raises(SceneError, match=r"confidence/000010\.png: expected a single-channel map of levels 0, 1, 2"):
        import_stray(copy, tmp_path / "scene")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["copy"]


def test_cli_with_splits(tmp_path, capsys):
    recording = write_stray(tmp_path / "long", redkitchen_frames(60))
    assert main(["import", "stray", str(recording), "--out", str(tmp_path / "scene"), "--splits", "paper"]) == 0
    out = capsys.readouterr().out
    assert "stray: imported 60 frames" in out and "splits (rule=paper" in out
    meta = json.loads((tmp_path / "scene" / "transforms.json").read_text())
    assert meta["train_filenames"][:2] == ["images/000000.jpg", "images/000010.jpg"]
    with pytest.raises(SystemExit) as exit_:
        main(["import", "stray", str(recording), "--out", str(tmp_path / "other"), "--every", "0"])
    assert exit_.value.code == 2 and "argument --every: must be >= 1, got 0" in capsys.readouterr().err
