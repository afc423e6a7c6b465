"""render_path: H.264 videos and frames directories of a camera path, nothing left behind when stopped."""

from __future__ import annotations

import json

import imageio.v3 as iio
import imageio_ffmpeg
import numpy as np
import pytest
from tiny_run import DEPTH_UNIT_SCALE, write_tiny_run

from voxnerf.cameras.paths import CameraPath, orbit_path, read_nerfstudio
from voxnerf.cameras.rules import Intrinsics
from voxnerf.data.image_io import decode_exr, read_png_header
from voxnerf.errors import RunError
from voxnerf.inference.encoding import encode_outputs
from voxnerf.inference.render import load_model, render
from voxnerf.inference.video import render_path

CAMERA = Intrinsics(fl_x=30.0, fl_y=30.0, cx=16.0, cy=12.0, width=32, height=24)


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    return load_model(write_tiny_run(tmp_path_factory.mktemp("tiny") / "run"), "cpu")


def _orbit(n_frames: int = 5, camera: Intrinsics = CAMERA, fps: float = 12.0) -> CameraPath:
    return orbit_path(np.zeros(3), radius=3.0, height=0.5, n_frames=n_frames, intrinsics=camera, fps=fps)


def _decoded(video) -> tuple[dict, list[np.ndarray]]:
    reader = imageio_ffmpeg.read_frames(str(video))
    meta = next(reader)
    frames = [np.frombuffer(f, np.uint8).reshape(meta["size"][1], meta["size"][0], 3) for f in reader]
    return meta, frames


def test_mp4_has_the_paths_frames_size_and_fps(trained, tmp_path):
    path = _orbit(n_frames=5, fps=12.0)
    calls = []
    result = render_path(trained, path, tmp_path / "v.mp4", on_frame=lambda done, total: calls.append((done, total)))
    assert (result.frames, result.stopped, result.out) == (5, False, tmp_path / "v.mp4")
    assert calls == [(i, 5) for i in range(1, 6)]
    meta, frames = _decoded(tmp_path / "v.mp4")
    assert len(frames) == 5 and meta["size"] == (32, 24) and meta["fps"] == 12.0
    assert meta["codec"] == "h264" and meta["pix_fmt"].startswith("yuv420p")
    assert imageio_ffmpeg.count_frames_and_secs(str(tmp_path / "v.mp4"))[0] == 5
    # the first frame is the render of the first pose, up to H.264's loss
    expected = render(trained, path.poses[0], path.intrinsics[0], ["rgb"])["rgb"] * 255
    assert np.abs(frames[0].astype(float) - expected).mean() < 8
    # the path is saved beside the video, nerfstudio's format, and reads back to the same path
    assert result.path_file == tmp_path / "v.mp4.camera_path.json"
    np.testing.assert_array_equal(read_nerfstudio(result.path_file).poses, path.poses)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["v.mp4", "v.mp4.camera_path.json"]


def test_frames_of_a_nerfstudio_path_are_renders_of_its_poses(trained, tmp_path):
    """A camera path written the viewer's way renders the poses it names, with the camera its fov gives."""
    poses = _orbit(n_frames=3).poses
    doc = {"camera_type": "perspective", "render_width": 20, "render_height": 14, "fps": 24, "seconds": 3 / 24,
           "camera_path": [{"camera_to_world": p.reshape(-1).tolist(), "fov": 50.0, "aspect": 20 / 14}
                           for p in poses]}
    (tmp_path / "path.json").write_text(json.dumps(doc))
    path = read_nerfstudio(tmp_path / "path.json")
    result = render_path(trained, path, tmp_path / "frames")
    assert result.frames == 3 and result.path_file == tmp_path / "frames" / "camera_path.json"
    assert sorted(p.name for p in (tmp_path / "frames").iterdir()) == [
        "camera_path.json", "frame_00000.png", "frame_00001.png", "frame_00002.png"]
    focal = 7.0 / np.tan(np.radians(25.0))
    camera = Intrinsics(focal, focal, 10.0, 7.0, 20, 14)
    expected = render(trained, poses[2], camera, ["rgb"])["rgb"]
    frame = iio.imread(tmp_path / "frames" / "frame_00002.png")
    assert frame.shape == (14, 20, 3)
    assert np.abs(frame / 255.0 - expected).max() <= 1 / 255 + 1e-6
    assert np.abs(frame / 255.0 - render(trained, poses[0], camera, ["rgb"])["rgb"]).max() > 1 / 255  # not any


def test_png_frames_with_depth(trained, tmp_path):
    path = _orbit(n_frames=2)
    render_path(trained, path, tmp_path / "frames", outputs=("rgb", "depth"))
    names = sorted(p.name for p in (tmp_path / "frames").iterdir())
    assert names == ["camera_path.json", "frame_00000.png", "frame_00000_depth.png", "frame_00001.png",
                     "frame_00001_depth.png"]
    assert read_png_header(tmp_path / "frames" / "frame_00001_depth.png")[2:] == (16, 0)
    images = render(trained, path.poses[1], path.intrinsics[1], ["rgb", "depth"])
    expected = encode_outputs(images, "png", ["depth"], DEPTH_UNIT_SCALE)
    assert (tmp_path / "frames" / "frame_00001_depth.png").read_bytes() == expected


def test_exr_frames_hold_rgb_and_depth(trained, tmp_path):
    path = _orbit(n_frames=2)
    render_path(trained, path, tmp_path / "frames", outputs=("rgb", "depth"), fmt="exr")
    assert sorted(p.name for p in (tmp_path / "frames").iterdir()) == [
        "camera_path.json", "frame_00000.exr", "frame_00001.exr"]
    channels = decode_exr((tmp_path / "frames" / "frame_00001.exr").read_bytes())
    assert sorted(channels) == ["B", "G", "R", "Z"] and channels["Z"].shape == (24, 32)
    depth = render(trained, path.poses[1], path.intrinsics[1], ["depth"])["depth"]
    np.testing.assert_allclose(channels["Z"], depth, rtol=1e-6)


def _stop_after(k: int):
    asked = []

    def should_stop() -> bool:
        asked.append(1)
        return len(asked) > k

    return should_stop


@pytest.mark.parametrize("out_name", ["v.mp4", "frames"])
def test_stopped_render_leaves_nothing(trained, tmp_path, out_name):
    result = render_path(trained, _orbit(n_frames=5), tmp_path / out_name, should_stop=_stop_after(2))
    assert result.stopped and result.frames == 2
    assert list(tmp_path.iterdir()) == []  # no output, no path file, no temporary file


@pytest.mark.parametrize("out_name", ["v.mp4", "frames"])
def test_a_failing_render_leaves_nothing(trained, tmp_path, out_name):
    def interrupt(done, total):
        if done == 2:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        render_path(trained, _orbit(n_frames=4), tmp_path / out_name, on_frame=interrupt)
    assert list(tmp_path.iterdir()) == []


def test_mp4_replaces_an_existing_video(trained, tmp_path):
    (tmp_path / "v.mp4").write_bytes(b"old")
    render_path(trained, _orbit(n_frames=2), tmp_path / "v.mp4")
    assert imageio_ffmpeg.count_frames_and_secs(str(tmp_path / "v.mp4"))[0] == 2


@pytest.mark.parametrize(
    ("out_name", "kwargs", "words"),
    [
        ("v.mp4", {"outputs": ("rgb", "depth")}, "a video holds rgb only"),
        ("frames", {"outputs": ("depth",)}, "outputs must hold rgb"),
        ("frames", {"outputs": ("rgb", "normals")}, "outputs must hold rgb"),
        ("v.mp4", {"fmt": "png"}, "must not"),
        ("frames", {"fmt": "mp4"}, "must end in .mp4"),
        ("frames", {"fmt": "gif"}, "unknown format"),
    ],
)
def test_refusals_before_rendering(trained, tmp_path, out_name, kwargs, words):
    with pytest.raises(RunError, match=words):
        render_path(trained, _orbit(n_frames=2), tmp_path / out_name, **kwargs)
    assert list(tmp_path.iterdir()) == []


def test_odd_video_sizes_are_refused(trained, tmp_path):
    odd = Intrinsics(30.0, 30.0, 16.5, 12.0, 33, 24)
    with pytest.raises(RunError, match=r"v.mp4: width, height: H.264 \(yuv420p\) needs even sizes, got 33x24"):
        render_path(trained, _orbit(n_frames=2, camera=odd), tmp_path / "v.mp4")
    render_path(trained, _orbit(n_frames=1, camera=odd), tmp_path / "frames")  # frames may be odd


def test_a_frames_directory_is_not_overwritten(trained, tmp_path):
    (tmp_path / "frames").mkdir()
    (tmp_path / "frames" / "mine.txt").write_text("keep")
    with pytest.raises(RunError, match="exists and is not an empty directory"):
        render_path(trained, _orbit(n_frames=1), tmp_path / "frames")
    assert [p.name for p in (tmp_path / "frames").iterdir()] == ["mine.txt"]
    (tmp_path / "v.mp4").mkdir()
    with pytest.raises(RunError, match="is a directory"):
        render_path(trained, _orbit(n_frames=1), tmp_path / "v.mp4")
