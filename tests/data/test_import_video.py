"""``voxnerf import video``: redkitchen's colour frames encoded as a phone would (H.264 MP4, HEVC MOV, rotation
metadata) come back as a scene whose frames are the sharpest of each time window, posed by structure from
motion up to a similarity; videos without decodable frames give one-line errors and write nothing."""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest
from capture_fixtures import (
    REDKITCHEN,
    ffmpeg,
    needs_redkitchen,
    redkitchen_frames,
    redkitchen_rgb,
    scene_pose_errors,
    with_rotation,
    write_video,
)
from PIL import Image, ImageFilter

from voxnerf.cli import main
from voxnerf.data.importers import ImportMonitor, import_video
from voxnerf.data.importers.video import DECODE_REPORT_EVERY, DECODE_SHARE, pick_frames, sharpness
from voxnerf.errors import SceneError

CLIP_SOURCE = range(0, 250, 2)
"""125 redkitchen frames (every 2nd of the first 250) as 15 fps video: 8.3 s, 1.5 m of camera path."""
# Reached on the 25 frames picked from the clip (pycolmap 4.2.1): rotation 2.2 deg at most (median 1.1), centre
# 5.7 % of the trajectory at most (median 3.0 %). The given poses are the depth camera's (7-Scenes does not
# register colour to depth), so part of it is the data's.
ROTATION_DEG = 3.0
CENTRE_FRACTION = 0.08


@pytest.fixture(scope="module")
def clip(tmp_path_factory) -> Path:
    if not (REDKITCHEN / "transforms.json").is_file():
        pytest.skip("shared redkitchen data not present")
    frames = [redkitchen_rgb(i) for i in CLIP_SOURCE]
    return write_video(tmp_path_factory.mktemp("video") / "kitchen.mp4", frames)


def source_pose_of(summary: dict):
    """file_path -> the redkitchen pose of the source frame the video frame was decoded from."""
    poses = [f["transform_matrix"] for f in redkitchen_frames()]
    index_of = {p["file"]: p["frame"] for p in summary["video"]["picked"]}
    return lambda file_path: poses[CLIP_SOURCE[index_of[file_path]]]


@needs_redkitchen
def test_video_frames_are_posed_up_to_a_similarity(clip, tmp_path):
    out = tmp_path / "scene"
    reported: list[tuple[str, float]] = []
    summary = import_video(clip, out, n_frames=25, monitor=ImportMonitor(report=lambda *step: reported.append(step)))
    video = summary["video"]
    assert summary["format"] == "video" and video["codec"] == "h264" and video["size"] == [320, 240]
    assert video["frames_read"] == len(CLIP_SOURCE) and video["frames_picked"] == 25
    # one frame per window of 5, in time order, each inside its own window
    picked = [p["frame"] for p in video["picked"]]
    assert [i // 5 for i in picked] == list(range(25))
    assert [p["time_s"] for p in video["picked"]] == pytest.approx([i / 15 for i in picked], abs=1e-4)
    assert summary["sfm"]["matching"] == "sequential" and summary["sfm"]["cameras"] == "one shared camera"
    assert summary["frames"] == summary["sfm"]["registered"] == 25
    errors = scene_pose_errors(out, source_pose_of(summary))
    assert errors.rotation_deg_max < ROTATION_DEG, errors
    assert errors.centre_max_fraction < CENTRE_FRACTION, errors
    meta = json.loads((out / "transforms.json").read_text())
    assert [f["file_path"] for f in meta["frames"]] == [f"images/frame_{k:05d}.jpg" for k in range(25)]
    assert meta["ply_file_path"] == "sparse_pc.ply" and meta["prior_sigma"] > 0
    # progress: the decoding (every DECODE_REPORT_EVERY frames, against the frames the container announces) in
    # the first DECODE_SHARE, then structure from motion on the 25 frames picked
    decoding = [(step, f) for step, f in reported if step.startswith("decoding")]
    assert decoding[0][0] == f"decoding the video: {DECODE_REPORT_EVERY} of about {len(CLIP_SOURCE)} frames"
    assert all(f <= DECODE_SHARE for _, f in decoding)
    assert [f for _, f in reported] == sorted(f for _, f in reported)
    assert reported[len(decoding)] == ("extracting features: 0 of 25 images", DECODE_SHARE)
    assert reported[-1][0] == "writing the scene"


@needs_redkitchen
def test_cli_imports_a_video_with_the_paper_splits(clip, tmp_path, capsys):
    out = tmp_path / "scene"
    assert main(["import", "video", str(clip), "--out", str(out), "--frames", "50", "--splits", "paper"]) == 0
    printed = capsys.readouterr().out
    imported = re.match(r"video: imported (\d+) frames", printed)
    # SfM's multithreaded SIFT and matching leave a varying few frames unregistered on some runs (8 of 50 seen once)
    assert imported and 40 <= int(imported.group(1)) <= 50
    assert "note: 50 frames picked from 125 (h264, 320x240, 15 fps)" in printed and f"wrote {out}" in printed
    meta = json.loads((out / "transforms.json").read_text())
    assert meta["train_filenames"] and meta["eval_splits"]["interpolation"]


def test_the_sharpest_frame_of_each_window_is_kept(tmp_path):
    """30 frames in 10 windows of 3: one sharp frame per window (at a varying place), the others blurred."""
    rng = np.random.default_rng(0)
    base = rng.integers(0, 256, (60, 80, 3), dtype=np.uint8)
    base = np.array(Image.fromarray(base).resize((320, 240), Image.NEAREST))
    blurred = np.array(Image.fromarray(base).filter(ImageFilter.GaussianBlur(3)))
    sharp_at = [3 * w + (w % 3) for w in range(10)]
    frames = [base if i in sharp_at else blurred for i in range(30)]
    video = write_video(tmp_path / "blur.mp4", frames, fps=10)
    dst = tmp_path / "frames"
    dst.mkdir()
    picked, facts = pick_frames(video, 10, dst)
    assert [p.index for p in picked] == sharp_at
    assert facts["frames_read"] == 30 and sorted(p.name for p in dst.iterdir()) == [p.name for p in picked]
    assert sharpness(base) > 5 * sharpness(blurred)


@needs_redkitchen
@pytest.mark.parametrize(("codec", "suffix", "degrees"), [("libx264", "mp4", 90), ("libx265", "mov", -90)])
def test_rotation_metadata_is_honoured(tmp_path, codec, suffix, degrees):
    """A phone held upright stores landscape frames and a display rotation; the frames come out upright."""
    frames = [redkitchen_rgb(i) for i in range(0, 40, 4)]
    plain = write_video(tmp_path / f"plain.{suffix}", frames, fps=10, codec=codec)
    rotated = with_rotation(plain, tmp_path / f"rotated.{suffix}", degrees)
    dst = tmp_path / "frames"
    dst.mkdir()
    picked, facts = pick_frames(rotated, 5, dst)
    assert facts["size"] == [240, 320] and facts["codec"] == ("h264" if codec == "libx264" else "hevc")
    with Image.open(dst / picked[0].name) as im:
        got = np.asarray(im.convert("RGB"), dtype=np.float64)
    assert got.shape == (320, 240, 3)
    source = frames[picked[0].index].astype(np.float64)
    turned = np.rot90(source, 1 if degrees > 0 else -1)  # display rotation is counter-clockwise
    wrong_way = np.rot90(source, -1 if degrees > 0 else 1)
    assert np.abs(got - turned).mean() < 8.0 < np.abs(got - wrong_way).mean()


@pytest.mark.parametrize("kind", ["garbage", "audio only", "no frames", "missing"])
def test_a_video_without_decodable_frames_is_a_one_line_error(tmp_path, capsys, kind):
    path = tmp_path / "capture.mp4"
    if kind == "garbage":
        path.write_bytes(b"\x00\x00\x00\x18ftypmp42" + bytes(range(256)) * 20)
    elif kind == "audio only":
        path = tmp_path / "capture.m4a"
        ffmpeg("-f", "lavfi", "-i", "sine=duration=1", str(path))
    elif kind == "no frames":  # the header (moved to the front) survives, the frame data does not
        frames = [np.full((48, 64, 3), 40 * i, dtype=np.uint8) for i in range(5)]
        plain = write_video(tmp_path / "plain.mp4", frames)
        ffmpeg("-i", str(plain), "-c", "copy", "-movflags", "+faststart", str(tmp_path / "fast.mp4"))
        data = (tmp_path / "fast.mp4").read_bytes()
        path.write_bytes(data[: data.index(b"mdat") + 4])
        plain.unlink()
        (tmp_path / "fast.mp4").unlink()
    out = tmp_path / "scene"
    assert main(["import", "video", str(path), "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith(f"voxnerf: error: {path}: ") and "\n" not in err
    expected = {"garbage": "no video stream", "audio only": "no video stream", "no frames": "no decodable frames",
                "missing": "video file not found"}[kind]
    assert expected in err
    assert sorted(p.name for p in tmp_path.iterdir()) == ([path.name] if kind != "missing" else [])


def test_frame_count_must_be_in_range(tmp_path):
    path = write_video(tmp_path / "v.mp4", [np.zeros((48, 64, 3), dtype=np.uint8)] * 3)
    with pytest.raises(SceneError, match="--frames must be between 1 and 2000, not 0"):
        import_video(path, tmp_path / "scene", n_frames=0)
    assert not (tmp_path / "scene").exists()
