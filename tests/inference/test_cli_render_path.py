"""``voxnerf render`` with --camera-path, --path interpolate|orbit and --frame: every mode end to end, and one
line naming the file or flag for every refusal, with nothing written."""

from __future__ import annotations

import json
import math

import imageio.v3 as iio
import imageio_ffmpeg
import numpy as np
import pytest
import torch
from tiny_run import DEFAULT_INTRINSICS, write_tiny_run

from voxnerf.cameras.paths import FRAMES_PER_KEY, read_nerfstudio
from voxnerf.cameras.rules import Intrinsics
from voxnerf.cli import main
from voxnerf.data.scene import load_scene
from voxnerf.inference.encoding import encode_outputs
from voxnerf.inference.render import CHECKPOINT, load_model, render

N_FRAMES = 9  # frames 0 and 8 are held out (every eighth): 7 training cameras


def _look_at_origin(angle: float) -> np.ndarray:
    """A level camera on a circle of radius 1.5 at z = 0.3 looking at the z axis, +Y along +z."""
    eye = np.array([1.5 * math.cos(angle), 1.5 * math.sin(angle), 0.3])
    forward = -np.array([eye[0], eye[1], 0.0]) / 1.5
    right = np.cross(forward, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    pose = np.eye(4)
    pose[:3, 0], pose[:3, 1], pose[:3, 2], pose[:3, 3] = right, np.cross(right, forward), -forward, eye
    return pose


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    """9 cameras around the tiny run's box, 16x12 images; frame f04 has an OPENCV lens."""
    root = tmp_path_factory.mktemp("scene") / "ring"
    (root / "images").mkdir(parents=True)
    frames = []
    for i in range(N_FRAMES):
        iio.imwrite(root / "images" / f"f{i:02d}.png", np.full((12, 16, 3), 20 * i, np.uint8))
        frames.append({"file_path": f"images/f{i:02d}.png",
                       "transform_matrix": _look_at_origin(0.5 * i).tolist()})
    frames[4].update(camera_model="OPENCV", k1=-0.3)
    meta = {"fl_x": 20.0, "fl_y": 18.0, "cx": 7.5, "cy": 6.5, "w": 16, "h": 12, "frames": frames}
    (root / "transforms.json").write_text(json.dumps(meta))
    return root


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    return write_tiny_run(tmp_path_factory.mktemp("tiny") / "run")


@pytest.fixture(scope="module")
def run_with_scene(tmp_path_factory, scene):
    """The tiny run, its checkpoint recording ``scene`` as the scene it trained on."""
    run = write_tiny_run(tmp_path_factory.mktemp("tiny") / "run")
    state = torch.load(run / CHECKPOINT, weights_only=False)
    state["scene_dir"] = str(scene)
    torch.save(state, run / CHECKPOINT)
    return run


def _render(run, *flags) -> int:
    return main(["render", str(run), "--device", "cpu", *map(str, flags)])


def _training_poses(scene) -> np.ndarray:
    loaded = load_scene(scene, load_images=False)
    return np.stack([loaded.frames[i].c2w for i in loaded.train_indices])


def _viewer_doc(poses: np.ndarray, width: int = 16, height: int = 12, fps: float = 8.0) -> dict:
    return {"camera_type": "perspective", "render_width": width, "render_height": height, "fps": fps,
            "seconds": len(poses) / fps,
            "camera_path": [{"camera_to_world": p.reshape(-1).tolist(), "fov": 45.0, "aspect": width / height}
                            for p in poses]}


# ------------------------------------------------------------------------------------------------ modes


def test_camera_path_to_mp4(run, tmp_path, capsys):
    poses = np.stack([_look_at_origin(0.3 * i) for i in range(4)])
    (tmp_path / "path.json").write_text(json.dumps(_viewer_doc(poses, fps=8.0)))
    out = tmp_path / "out" / "video.mp4"
    assert _render(run, "--camera-path", tmp_path / "path.json", "--out", out) == 0
    assert imageio_ffmpeg.count_frames_and_secs(str(out))[0] == 4
    captured = capsys.readouterr()
    assert f"wrote {out} (4 frames, 16x12, 8 fps)" in captured.out
    assert f"wrote {out}.camera_path.json" in captured.out
    assert "4/4" in captured.err  # the progress bar


def test_camera_path_with_dataparser_transforms_renders_scene_poses(run, tmp_path):
    scene_poses = np.stack([_look_at_origin(0.4 * i) for i in range(3)])
    rot = np.array([[0.0, 1, 0], [-1, 0, 0], [0, 0, 1]])
    transform, scale = np.concatenate([rot, [[0.5], [-0.2], [0.1]]], axis=1), 0.4
    viewer = np.stack([np.vstack([transform, [0, 0, 0, 1]]) @ p for p in scene_poses])
    viewer[:, :3, 3] *= scale
    (tmp_path / "path.json").write_text(json.dumps(_viewer_doc(viewer)))
    (tmp_path / "dataparser_transforms.json").write_text(json.dumps({"transform": transform.tolist(),
                                                                     "scale": scale}))
    out = tmp_path / "frames"
    assert _render(run, "--camera-path", tmp_path / "path.json", "--dataparser-transforms",
                   tmp_path / "dataparser_transforms.json", "--out", out, "--format", "exr") == 0
    assert sorted(p.name for p in out.iterdir()) == ["camera_path.json", "frame_00000.exr", "frame_00001.exr",
                                                      "frame_00002.exr"]
    np.testing.assert_allclose(read_nerfstudio(out / "camera_path.json").poses, scene_poses, atol=1e-9)


def test_interpolate_through_training_cameras_with_depth(run, scene, tmp_path):
    out = tmp_path / "frames"
    frames = 7 * FRAMES_PER_KEY  # enough for every one of the 7 training cameras to be a key camera
    assert _render(run, "--path", "interpolate", "--scene", scene, "--frames", frames, "--fps", 5, "--depth",
                   "--out", out) == 0
    names = sorted(p.name for p in out.iterdir())
    assert len(names) == 1 + 2 * frames and f"frame_{frames - 1:05d}_depth.png" in names
    path = read_nerfstudio(out / "camera_path.json")
    assert len(path) == frames and path.fps == 5 and path.size == (DEFAULT_INTRINSICS.width, DEFAULT_INTRINSICS.height)
    keys = _training_poses(scene)
    np.testing.assert_allclose(path.poses[0], keys[0], atol=1e-9)
    np.testing.assert_allclose(path.poses[-1], keys[-1], atol=1e-9)
    for key in keys:  # every training camera is one of the frames
        assert np.abs(path.poses - key).sum(axis=(1, 2)).min() < 1e-6


def test_interpolate_through_keyframes(run, scene, tmp_path):
    out = tmp_path / "frames"
    assert _render(run, "--path", "interpolate", "--scene", scene, "--frames", 3, "--keyframes", 3,
                   "--out", out) == 0
    keys = _training_poses(scene)[[0, 3, 6]]  # 3 of the 7, evenly spaced
    np.testing.assert_allclose(read_nerfstudio(out / "camera_path.json").poses, keys, atol=1e-9)


def test_orbit_with_the_runs_recorded_scene(run_with_scene, scene, tmp_path):
    out = tmp_path / "orbit.mp4"
    assert _render(run_with_scene, "--path", "orbit", "--seconds", 0.5, "--fps", 8, "--width", 16, "--height", 12,
                   "--radius", 1.0, "--height-above", 0.2, "--out", out) == 0
    meta = next(imageio_ffmpeg.read_frames(str(out)))
    assert meta["size"] == (16, 12) and meta["fps"] == 8.0
    assert imageio_ffmpeg.count_frames_and_secs(str(out))[0] == 4
    path = read_nerfstudio(tmp_path / "orbit.mp4.camera_path.json")
    center = _training_poses(scene)[:, :3, 3].mean(axis=0)
    offsets = path.poses[:, :3, 3] - center
    np.testing.assert_allclose(offsets[:, 2], 0.2, atol=1e-9)  # the cameras' up is +z
    np.testing.assert_allclose(np.linalg.norm(offsets[:, :2], axis=1), 1.0, atol=1e-9)


def test_orbit_defaults_circle_the_training_cameras(run, scene, tmp_path):
    out = tmp_path / "frames"
    assert _render(run, "--path", "orbit", "--scene", scene, "--frames", 2, "--out", out) == 0
    path = read_nerfstudio(out / "camera_path.json")
    train = _training_poses(scene)[:, :3, 3]
    center = train.mean(axis=0)
    radius = np.linalg.norm(train[:, :2] - center[:2], axis=1).mean()
    np.testing.assert_allclose(np.linalg.norm(path.poses[:, :2, 3] - center[:2], axis=1), radius, atol=1e-9)


@pytest.mark.parametrize("name", ["images/f03.png", "f03", "f03.png"])
def test_frame_renders_the_scenes_camera(run, scene, tmp_path, name):
    out = tmp_path / "view.png"
    assert _render(run, "--frame", name, "--scene", scene, "--out", out) == 0
    frame = load_scene(scene, load_images=False).frames[3]
    expected = encode_outputs(render(load_model(run, "cpu"), frame.c2w, frame.intrinsics, ["rgb"]), "png", ["rgb"],
                              1.0)
    assert out.read_bytes() == expected


def test_frame_with_lens_renders_through_it(run, scene, tmp_path):
    frame = load_scene(scene, load_images=False).frames[4]
    assert frame.intrinsics.lens is not None
    trained = load_model(run, "cpu")
    assert _render(run, "--frame", "f04", "--scene", scene, "--out", tmp_path / "plain.png") == 0
    assert _render(run, "--frame", "f04", "--scene", scene, "--with-lens", "--out", tmp_path / "lens.png") == 0
    plain = render(trained, frame.c2w, frame.intrinsics.undistorted(), ["rgb"])
    lens = render(trained, frame.c2w, frame.intrinsics, ["rgb"])
    assert (tmp_path / "plain.png").read_bytes() == encode_outputs(plain, "png", ["rgb"], 1.0)
    assert (tmp_path / "lens.png").read_bytes() == encode_outputs(lens, "png", ["rgb"], 1.0)
    assert (tmp_path / "plain.png").read_bytes() != (tmp_path / "lens.png").read_bytes()


def test_no_antialias_renders_each_pixel_from_its_centre_ray(run, scene, tmp_path):
    frame = load_scene(scene, load_images=False).frames[3]
    trained = load_model(run, "cpu")
    assert _render(run, "--frame", "f03", "--scene", scene, "--out", tmp_path / "default.png") == 0
    assert _render(run, "--frame", "f03", "--scene", scene, "--no-antialias", "--out", tmp_path / "centre.png") == 0
    camera = frame.intrinsics.undistorted()
    antialiased = render(trained, frame.c2w, camera, ["rgb"])  # the run's setting: antialiased
    centre = render(trained, frame.c2w, camera, ["rgb"], antialias=False)
    assert (tmp_path / "default.png").read_bytes() == encode_outputs(antialiased, "png", ["rgb"], 1.0)
    assert (tmp_path / "centre.png").read_bytes() == encode_outputs(centre, "png", ["rgb"], 1.0)
    assert (tmp_path / "default.png").read_bytes() != (tmp_path / "centre.png").read_bytes()
    out = tmp_path / "frames"
    assert _render(run, "--path", "orbit", "--frames", 2, "--no-antialias", "--out", out, "--scene", scene) == 0
    assert len(list(out.glob("frame_*.png"))) == 2


def test_frame_at_another_size_scales_its_camera(run, scene, tmp_path):
    assert _render(run, "--frame", "f02", "--scene", scene, "--width", 32, "--height", 24, "--depth",
                   "--out", tmp_path / "view.exr") == 0
    frame = load_scene(scene, load_images=False).frames[2]
    camera = Intrinsics(40.0, 36.0, 15.0, 13.0, 32, 24)
    assert frame.intrinsics.scaled(2.0) == camera
    from voxnerf.data.image_io import decode_exr

    channels = decode_exr((tmp_path / "view.exr").read_bytes())
    np.testing.assert_allclose(channels["Z"], render(load_model(run, "cpu"), frame.c2w, camera, ["depth"])["depth"],
                               rtol=1e-6)


# ------------------------------------------------------------------------------------------------ refusals


def _bad_camera_path(tmp_path):
    doc = _viewer_doc(np.stack([_look_at_origin(0.0)] * 2))
    doc["camera_path"][1]["fov"] = 0
    (tmp_path / "bad.json").write_text(json.dumps(doc))
    return tmp_path / "bad.json"


@pytest.mark.parametrize(
    ("flags", "message"),
    [
        (lambda t, s: ["--camera-path", _bad_camera_path(t), "--out", t / "out" / "v.mp4"],
         lambda t, s: f"{t / 'bad.json'}: camera_path[1].fov: must be a number in (0, 180) degrees, got 0"),
        (lambda t, s: ["--camera-path", t / "absent.json", "--out", t / "out" / "v.mp4"],
         lambda t, s: f"{t / 'absent.json'}: cannot read JSON"),
        (lambda t, s: ["--pose", t / "p.json", "--dataparser-transforms", t / "d.json", "--out", t / "out" / "x.png"],
         lambda t, s: "--dataparser-transforms: applies to --camera-path only"),
        (lambda t, s: ["--path", "interpolate", "--radius", 1, "--scene", s, "--out", t / "out"],
         lambda t, s: "--radius: applies to --path orbit only"),
        (lambda t, s: ["--camera-path", t / "p.json", "--frames", 3, "--out", t / "out"],
         lambda t, s: "--frames: applies to --path interpolate / --path orbit only"),
        (lambda t, s: ["--pose", t / "p.json", "--format", "exr", "--out", t / "out" / "x.png"],
         lambda t, s: "--format: applies to --camera-path / --path interpolate / --path orbit only"),
        (lambda t, s: ["--path", "orbit", "--frames", 0, "--scene", s, "--out", t / "out"],
         lambda t, s: "--frames: must be a whole number of frames from 1 to 10000, got 0"),
        (lambda t, s: ["--path", "orbit", "--seconds", 1000, "--scene", s, "--out", t / "out"],
         lambda t, s: "--seconds: must be a whole number of frames from 1 to 10000, got 30000"),
        (lambda t, s: ["--path", "orbit", "--seconds", 1e308, "--scene", s, "--out", t / "out"],
         lambda t, s: "--seconds: must be a whole number of frames from 1 to 10000, got inf"),
        (lambda t, s: ["--path", "orbit", "--frames", 3, "--seconds", 1, "--scene", s, "--out", t / "out"],
         lambda t, s: "--frames, --seconds: give one of them"),
        (lambda t, s: ["--path", "orbit", "--fps", "nan", "--scene", s, "--out", t / "out"],
         lambda t, s: "--fps, --seconds: must be positive numbers, got nan fps, 10 s"),
        (lambda t, s: ["--path", "orbit", "--radius", -1, "--frames", 2, "--scene", s, "--out", t / "out"],
         lambda t, s: "--radius: must be a positive finite number, got -1.0"),
        (lambda t, s: ["--path", "orbit", "--width", 16, "--frames", 2, "--scene", s, "--out", t / "out"],
         lambda t, s: "--width, --height: give width and height together"),
        (lambda t, s: ["--path", "interpolate", "--frames", 3, "--keyframes", 7, "--scene", s, "--out", t / "out"],
         lambda t, s: "--frames: 3 frames cannot pass through 7 cameras (one frame each)"),
        (lambda t, s: ["--path", "interpolate", "--keyframes", 1, "--scene", s, "--out", t / "out"],
         lambda t, s: "--keyframes: must be at least 2, got 1"),
        (lambda t, s: ["--path", "orbit", "--frames", 2, "--out", t / "out"],
         lambda t, s: "the run does not record its scene; pass --scene"),
        (lambda t, s: ["--path", "orbit", "--frames", 2, "--scene", t / "noscene", "--out", t / "out"],
         lambda t, s: f"{t / 'noscene'}"),
        (lambda t, s: ["--path", "orbit", "--frames", 2, "--scene", s, "--out", t / "out" / "x.png"],
         lambda t, s: f"{t / 'out' / 'x.png'}: a path renders to VIDEO.mp4 or a frames directory"),
        (lambda t, s: ["--path", "orbit", "--frames", 2, "--scene", s, "--depth", "--out", t / "out" / "v.mp4"],
         lambda t, s: f"{t / 'out' / 'v.mp4'}: a video holds rgb only; render depth to a frames directory"),
        (lambda t, s: ["--path", "orbit", "--frames", 2, "--scene", s, "--width", 15, "--height", 12,
                       "--out", t / "out" / "v.mp4"],
         lambda t, s: f"{t / 'out' / 'v.mp4'}: width, height: H.264 (yuv420p) needs even sizes, got 15x12"),
        (lambda t, s: ["--path", "orbit", "--frames", 2, "--scene", s, "--format", "exr", "--out", t / "out" / "v.mp4"],
         lambda t, s: "an MP4 video must end in .mp4 and a frames directory must not (format exr)"),
        (lambda t, s: ["--frame", "nope", "--scene", s, "--out", t / "out" / "x.png"],
         lambda t, s: f"--frame: no frame 'nope' in {s / 'transforms.json'}"),
        (lambda t, s: ["--frame", "f01", "--out", t / "out" / "x.png"],
         lambda t, s: "the run does not record its scene; pass --scene"),
        (lambda t, s: ["--frame", "f01", "--scene", s, "--out", t / "out" / "x.mp4"],
         lambda t, s: "output must end in .png or .exr"),
    ],
)
def test_refusals_are_one_line_and_write_nothing(run, scene, tmp_path, capsys, flags, message):
    assert _render(run, *flags(tmp_path, scene)) == 2
    err = capsys.readouterr().err
    assert err.startswith("voxnerf: error: ") and err.count("\n") == 1, err
    assert message(tmp_path, scene) in err, err
    assert not (tmp_path / "out").exists()


def test_modes_exclude_each_other(run, tmp_path, capsys):
    with pytest.raises(SystemExit) as exit_:
        _render(run, "--pose", "p.json", "--path", "orbit", "--out", tmp_path / "x.png")
    assert exit_.value.code == 2 and "not allowed with argument" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        _render(run, "--out", tmp_path / "x.png")
    assert "one of the arguments --pose --frame --camera-path --path is required" in capsys.readouterr().err
