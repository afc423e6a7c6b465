"""``voxnerf import rosbag``: redkitchen re-expressed as a robot's bags (ROS 2 sqlite3 and MCAP, ROS 1; colour,
depth, CameraInfo, a /tf chain over a static camera mount) comes back with the source's poses to 1e-6, its
pixels and depth; bags without a camera, a pose or a readable depth give one-line errors and write nothing."""

from __future__ import annotations

import json
import math
from dataclasses import replace
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import pytest
from rosbag_fixtures import REDKITCHEN, BagSpec, make_frames, write_bag

from voxnerf.cli import main
from voxnerf.data.importers import PaperSplitRule, RosbagOptions, import_rosbag, paper_splits
from voxnerf.errors import SceneError

pytestmark = pytest.mark.skipif(not (REDKITCHEN / "transforms.json").is_file(),
                                reason="shared redkitchen data not present")
ALL = RosbagOptions(all_frames=True)


@pytest.fixture(scope="module")
def frames():
    return make_frames()


@pytest.fixture(scope="module")
def few(frames):
    """Four frames, for the bags the error tests break."""
    return frames[:4]


@pytest.fixture(scope="module")
def bags(tmp_path_factory, frames) -> dict[str, Path]:
    root = tmp_path_factory.mktemp("bags")
    return {
        "sqlite3": write_bag(root / "kitchen_sqlite3", BagSpec(frames), "sqlite3"),
        "mcap": write_bag(root / "kitchen_mcap", BagSpec(frames, colour="jpeg", depth_encoding="32FC1",
                                                        tf="bracket"), "mcap"),
        "ros1": write_bag(root / "kitchen.bag", BagSpec(frames, colour_encoding="bgr8"), "ros1"),
    }


def scene(out: Path) -> dict:
    return json.loads((out / "transforms.json").read_text())


def assert_poses(meta: dict, frames) -> None:
    assert len(meta["frames"]) == len(frames)
    for got, want in zip(meta["frames"], frames, strict=True):
        np.testing.assert_allclose(got["transform_matrix"], want.c2w_gl, atol=1e-6, rtol=0)


@pytest.mark.parametrize("kind", ["sqlite3", "ros1"])
def test_raw_images_and_millimetre_depth_round_trip(bags, frames, tmp_path, kind):
    summary = import_rosbag(bags[kind], tmp_path / "scene", options=ALL)
    meta = scene(tmp_path / "scene")
    assert_poses(meta, frames)
    assert [f["file_path"] for f in meta["frames"]] == [f"images/frame_{i:05d}.png" for i in range(20)]
    assert {k: meta[k] for k in ("camera_model", "fl_x", "fl_y", "cx", "cy", "w", "h")} == {
        "camera_model": "PINHOLE", "fl_x": 292.5, "fl_y": 292.5, "cx": 160.0, "cy": 120.0, "w": 320, "h": 240}
    assert meta["depth_unit_scale_factor"] == 0.001 and "depth_intrinsics" not in meta
    for entry, frame in zip(meta["frames"], frames, strict=True):
        rgb = iio.imread(tmp_path / "scene" / entry["file_path"])
        np.testing.assert_array_equal(rgb, iio.imread(frame.colour)[::2, ::2])  # bgr8 too: channels put back
        depth = iio.imread(tmp_path / "scene" / entry["depth_file_path"])
        assert depth.dtype == np.uint16
        np.testing.assert_array_equal(depth, iio.imread(frame.depth)[::2, ::2])
    assert summary["frames"] == 20 and summary["depth_frames"] == 20 and summary["skipped"] == {}
    assert summary["topics"] == {"rgb": "/camera/color/image_raw", "depth": "/camera/aligned_depth_to_color/image_raw",
                                 "poses": "/tf and /tf_static"}
    assert summary["fixed_frame"] == "map" and summary["camera_frame"] == "camera_color_optical_frame"


def test_mcap_jpeg_metre_depth_and_interpolated_transforms(bags, frames, tmp_path):
    """Compressed colour is kept byte for byte; 32FC1 depth becomes .npy metres (NaN where the sensor had none);
    the /tf samples bracket each image 10 ms either side, so every pose is an interpolation."""
    import_rosbag(bags["mcap"], tmp_path / "scene", options=ALL)
    meta = scene(tmp_path / "scene")
    assert_poses(meta, frames)
    assert (meta["w"], meta["h"], meta["cx"]) == (640, 480, 320.0) and "depth_unit_scale_factor" not in meta
    for entry, frame in zip(meta["frames"], frames, strict=True):
        assert entry["file_path"].endswith(".jpg")
        assert (tmp_path / "scene" / entry["file_path"]).read_bytes() == frame.colour.read_bytes()
        depth = np.load(tmp_path / "scene" / entry["depth_file_path"])
        mm = iio.imread(frame.depth)
        np.testing.assert_array_equal(np.isnan(depth), mm == 0)
        np.testing.assert_allclose(depth[mm > 0], mm[mm > 0] / 1000.0, rtol=1e-6)


def test_depth_at_its_own_resolution_and_a_compressed_twin(few, tmp_path):
    """A depth camera with its own lower-resolution CameraInfo gives depth_intrinsics; image_transport's
    ``<raw>/compressed`` twin of the colour topic is not a second camera."""
    spec = BagSpec(few, colour="both", depth_topic="/camera/depth/image_rect_raw", depth_scale=4)
    summary = import_rosbag(write_bag(tmp_path / "bag", spec, "sqlite3"), tmp_path / "scene", options=ALL)
    meta = scene(tmp_path / "scene")
    assert summary["topics"]["rgb"] == "/camera/color/image_raw" and summary["depth_frames"] == 4
    assert meta["depth_intrinsics"] == {"fl_x": 146.25, "fl_y": 146.25, "cx": 80.0, "cy": 60.0, "w": 160, "h": 120}
    assert iio.imread(tmp_path / "scene" / meta["frames"][0]["depth_file_path"]).shape == (120, 160)
    from voxnerf.data.scene import load_scene

    load_scene(tmp_path / "scene")


def test_depth_in_its_own_frame_must_be_registered_to_the_colour_camera(few, tmp_path):
    bag = write_bag(tmp_path / "near", BagSpec(few, scale=4, depth_offset=[0.0002, 0.0, 0.0]), "mcap")
    summary = import_rosbag(bag, tmp_path / "scene", options=ALL)
    assert summary["depth_frames"] == 4
    bag = write_bag(tmp_path / "apart", BagSpec(few, scale=4, depth_offset=[0.015, 0.0, 0.0]), "mcap")
    refused(bag, tmp_path / "scene2", r"/camera/aligned_depth_to_color/image_raw: depth is in frame "
            r"'camera_depth_optical_frame', 15.0 mm and 0.00 degrees from the colour frame "
            r"'camera_color_optical_frame': the scene format needs depth registered to the colour camera")


@pytest.mark.parametrize("encoding", ["16UC1", "32FC1"])
def test_compressed_depth(few, tmp_path, encoding):
    """image_transport's compressedDepth: 16UC1's PNG kept as recorded, 32FC1's quantised inverse depth decoded
    to metres (within one quantisation step, depth^2 / A: 0.1 mm at 1 m with the publisher's defaults)."""
    bag = write_bag(tmp_path / "bag", BagSpec(few, depth_encoding=encoding, depth_compressed="only"), "mcap")
    summary = import_rosbag(bag, tmp_path / "scene", options=ALL)
    assert summary["topics"]["depth"] == "/camera/aligned_depth_to_color/image_raw/compressedDepth"
    meta = scene(tmp_path / "scene")
    for entry, frame in zip(meta["frames"], few, strict=True):
        mm = iio.imread(frame.depth)[::2, ::2]
        if encoding == "16UC1":
            np.testing.assert_array_equal(iio.imread(tmp_path / "scene" / entry["depth_file_path"]), mm)
        else:
            depth = np.load(tmp_path / "scene" / entry["depth_file_path"])
            np.testing.assert_array_equal(np.isnan(depth), mm == 0)
            want = mm[mm > 0] / 1000.0
            assert np.all(np.abs(depth[mm > 0] - want) <= want**2 / 10100.0 * 1.01 + 1e-6)
    from voxnerf.data.scene import load_scene

    load_scene(tmp_path / "scene")


def test_a_compressed_depth_twin_is_not_a_second_depth_camera(few, tmp_path):
    bag = write_bag(tmp_path / "bag", BagSpec(few, scale=4, depth_compressed="twin"), "mcap")
    summary = import_rosbag(bag, tmp_path / "scene", options=ALL)
    assert summary["topics"]["depth"] == "/camera/aligned_depth_to_color/image_raw"


def test_imported_scene_loads(bags, tmp_path):
    from voxnerf.data.scene import inspect_scene

    import_rosbag(bags["mcap"], tmp_path / "scene", options=ALL)
    summary = inspect_scene(tmp_path / "scene")
    assert summary["frames"] == 20 and summary["depth"]


def test_frames_are_kept_by_motion(bags, frames, tmp_path):
    options = RosbagOptions(min_translation=0.05, min_rotation=5.0)
    summary = import_rosbag(bags["sqlite3"], tmp_path / "scene", options=options)
    meta = scene(tmp_path / "scene")
    kept, last = [], None
    for i, frame in enumerate(frames):  # the rule, recomputed from the source poses
        if last is not None:
            moved = np.linalg.norm(frame.c2w_gl[:3, 3] - last[:3, 3])
            turned = math.degrees(math.acos(np.clip((np.trace(last[:3, :3].T @ frame.c2w_gl[:3, :3]) - 1) / 2, -1, 1)))
            if moved < 0.05 and turned < 5.0:
                continue
        kept.append(i)
        last = frame.c2w_gl
    assert 1 < len(kept) < 20
    assert_poses(meta, [frames[i] for i in kept])
    assert [f["file_path"] for f in meta["frames"]] == [f"images/frame_{n:05d}.png" for n in range(len(kept))]
    assert summary["skipped"] == {
        "moved less than 0.05 m and 5 degrees since the last kept frame": 20 - len(kept)}
    assert f"{len(kept)} of 20 colour images kept" in summary["notes"][0]


@pytest.mark.parametrize("source", ["pose", "odom", "base_pose"])
def test_poses_from_a_pose_topic(frames, tmp_path, source):
    """A PoseStamped of the optical frame, an Odometry of base_link, or a PoseStamped of base_link named by
    --pose-frame; base_link is chained to the camera by /tf_static."""
    bag = write_bag(tmp_path / "bag", BagSpec(frames[:6], tf="none", pose_topic=source), "mcap")
    options = replace(ALL, pose_frame="base_link") if source == "base_pose" else ALL
    summary = import_rosbag(bag, tmp_path / "scene", options=options)
    assert_poses(scene(tmp_path / "scene"), frames[:6])
    topic = {"pose": "/camera_pose", "odom": "/odom", "base_pose": "/base_pose"}[source]
    assert summary["topics"]["poses"] == f"pose topic {topic}" and summary["fixed_frame"] == "map"


def test_paper_splits(tmp_path):
    frames = make_frames(step=1, n=60)
    bag = write_bag(tmp_path / "bag", BagSpec(frames, scale=8), "mcap")
    summary = import_rosbag(bag, tmp_path / "scene", PaperSplitRule(), options=ALL)
    meta = scene(tmp_path / "scene")
    names = [f["file_path"] for f in meta["frames"]]
    idx = paper_splits(60)
    assert meta["train_filenames"] == [names[i] for i in idx.train]
    assert meta["eval_splits"]["extrapolation"] == [names[i] for i in idx.extrapolation]
    assert summary["splits"]["train"] == len(idx.train)
    assert summary["depth_frames"] == 12  # redkitchen has depth on every 5th frame; the rest have none in range
    assert any("48 kept frame(s) without depth" in note for note in summary["notes"])


@pytest.mark.parametrize(("model", "d", "camera_model", "coefficients"), [
    ("plumb_bob", [0.1, -0.02, 0.001, -0.002, 0.003], "OPENCV",
     {"k1": 0.1, "k2": -0.02, "k3": 0.003, "p1": 0.001, "p2": -0.002}),
    ("rational_polynomial", [0.1, -0.02, 0.001, -0.002, 0.003, 0, 0, 0], "OPENCV",
     {"k1": 0.1, "k2": -0.02, "k3": 0.003, "p1": 0.001, "p2": -0.002}),
    ("equidistant", [0.1, -0.02, 0.003, -0.004], "OPENCV_FISHEYE", {"k1": 0.1, "k2": -0.02, "k3": 0.003, "k4": -0.004}),
    ("plumb_bob", [0.0] * 5, "PINHOLE", {}),
])
def test_camera_info_lens_models(few, tmp_path, model, d, camera_model, coefficients):
    bag = write_bag(tmp_path / "bag", BagSpec(few, scale=4, distortion=(model, d)), "mcap")
    summary = import_rosbag(bag, tmp_path / "scene", options=ALL)
    meta = scene(tmp_path / "scene")
    assert meta["camera_model"] == camera_model and summary["camera_models"] == [camera_model]
    assert {k: meta[k] for k in ("k1", "k2", "k3", "k4", "p1", "p2") if k in meta} == coefficients
    from voxnerf.data.scene import load_scene

    load_scene(tmp_path / "scene")  # the engine takes the lens


def test_cli_help_states_the_importer_s_defaults(capsys):
    from voxnerf.data.importers.rosbag import NO_DEPTH

    with pytest.raises(SystemExit):
        main(["import", "rosbag", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    defaults = RosbagOptions()
    assert f"metres (default {defaults.min_translation:g})" in text
    assert f"degrees (default {defaults.min_rotation:g})" in text
    assert f"it takes (default {defaults.sync_tolerance:g})" in text and f"'{NO_DEPTH}' imports colour only" in text


def test_cli_imports_and_reports(bags, tmp_path, capsys):
    assert main(["import", "rosbag", str(bags["ros1"]), "--out", str(tmp_path / "scene"), "--all-frames"]) == 0
    out = capsys.readouterr().out
    assert "rosbag: imported 20 frames" in out and "poses from /tf and /tf_static in frame 'map'" in out
    assert main(["import", "rosbag", str(bags["ros1"]), "--out", str(tmp_path / "moved"), "--min-translation",
                 "0.3", "--min-rotation", "90"]) == 0
    kept = len(scene(tmp_path / "moved")["frames"])
    assert f"rosbag: imported {kept} frames, skipped {20 - kept} (" in capsys.readouterr().out
    assert 1 <= kept < 8  # fewer than the default rule keeps on these frames
    with pytest.raises(SystemExit) as exit_:
        main(["import", "rosbag", str(bags["ros1"]), "--out", str(tmp_path / "other"), "--min-translation", "-1"])
    assert exit_.value.code == 2 and "must be a finite number >= 0, got '-1'" in capsys.readouterr().err
    assert main(["import", "rosbag", str(bags["ros1"]), "--out", str(tmp_path / "other"), "--rgb", "/x"]) == 2
    err = capsys.readouterr().err.splitlines()
    assert err == [f"voxnerf: error: {bags['ros1']}: --rgb /x: no such topic (topics: /camera/aligned_depth_to_color/"
                   "image_raw, /camera/color/camera_info, /camera/color/image_raw, /tf, /tf_static)"]
    assert not (tmp_path / "other").exists()


# ------------------------------------------------------------------------------------------------ bad input


def refused(bag: Path, out: Path, match: str, options: RosbagOptions = ALL) -> None:
    """The import raises one line matching ``match`` and naming the bag, and leaves nothing at ``out``."""
    with pytest.raises(SceneError, match=match) as err:
        import_rosbag(bag, out, options=options)
    assert str(err.value).startswith(f"{bag}: ") and "\n" not in str(err.value)
    assert not out.exists() and not list(out.parent.glob(f".{out.name}*"))


@pytest.mark.parametrize(("spec", "match"), [
    ({"colour": "none"}, r"no camera topic: no sensor_msgs/Image in rgb8.* \(image topics: "
                         r"/camera/aligned_depth_to_color/image_raw \(16UC1\)\)"),
    ({"tf": "none"}, r"no pose for the camera frame 'camera_color_optical_frame': only static transforms reach it, "
                     r"and there is no PoseStamped.*--pose-topic"),
    ({"depth_encoding": "mono16"}, r"/camera/aligned_depth_to_color/image_raw: depth encoding 'mono16' is not "
     r"supported \(16UC1 millimetres or 32FC1 metres, raw or compressedDepth png; --depth none imports colour only\)"),
    ({"extra_colour": True}, r"2 colour image topics \(/camera/color/image_raw, /camera/infra_rgb/image_raw\): "
                             r"choose one with --rgb TOPIC"),
    ({"colour_encoding": "yuv422"}, r"no camera topic"),
    ({"colour": "broken_jpeg"}, r"/camera/color/image_raw/compressed: message 0: cannot decode image: "),
    ({"distortion": ("rational_polynomial", [0.1, 0, 0, 0, 0, 0.2, 0, 0])}, r"/camera/color/camera_info: "
     r"rational_polynomial with k4-k6 \[0.2, 0.0, 0.0\] has no lens model in the engine"),
    ({"distortion": ("kannala_brandt", [0.1, 0, 0, 0])}, r"distortion_model 'kannala_brandt' is not supported"),
])
def test_bad_bags_are_one_line_errors(few, tmp_path, spec, match):
    bag = write_bag(tmp_path / "bag.bag", BagSpec(few, scale=4, **spec), "ros1")
    refused(bag, tmp_path / "scene", match)


def test_the_flags_resolve_what_the_bag_leaves_open(few, tmp_path):
    bag = write_bag(tmp_path / "bag", BagSpec(few, scale=4, extra_colour=True, depth_encoding="mono16"), "sqlite3")
    options = replace(ALL, rgb="/camera/color/image_raw", depth="none")
    summary = import_rosbag(bag, tmp_path / "scene", options=options)
    assert summary["frames"] == 4 and summary["depth_frames"] == 0 and summary["topics"]["depth"] is None
    assert_poses(scene(tmp_path / "scene"), few)
    refused(bag, tmp_path / "x", r"/camera/aligned_depth_to_color/image_raw: colour encoding 'mono16' is not "
            r"supported \(rgb8, bgr8", replace(ALL, rgb="/camera/aligned_depth_to_color/image_raw"))
    refused(bag, tmp_path / "x", r"--rgb /nope: no such topic \(topics: /camera/aligned", replace(ALL, rgb="/nope"))
    refused(bag, tmp_path / "x", r"/tf_static: --pose-topic: topic is tf2_msgs/msg/TFMessage, expected",
            replace(options, pose_topic="/tf_static"))
    refused(bag, tmp_path / "x", r"no chain of transforms from the fixed frame 'earth' to the camera frame",
            replace(options, fixed_frame="earth"))


def test_transforms_recorded_out_of_order(frames, tmp_path):
    """/tf messages recorded newest first, after the images: the samples are ordered by their own stamps."""
    bag = write_bag(tmp_path / "bag", BagSpec(frames[:8], scale=4, tf="bracket", tf_late=True), "mcap")
    import_rosbag(bag, tmp_path / "scene", options=ALL)
    assert_poses(scene(tmp_path / "scene"), frames[:8])


def test_images_outside_the_transforms_are_dropped_and_counted(frames, tmp_path):
    """/tf ends before the last images: those have no pose and are counted, the rest imported."""
    bag = write_bag(tmp_path / "bag", BagSpec(frames[:8], scale=4, tf_frames=5), "mcap")
    summary = import_rosbag(bag, tmp_path / "scene", options=ALL)
    assert summary["frames"] == 5 and summary["skipped"] == {"no transform odom -> base_link at the image's stamp": 3}
    assert_poses(scene(tmp_path / "scene"), frames[:5])


def test_not_a_bag(tmp_path):
    path = tmp_path / "notes.bag"
    path.write_bytes(b"not a bag at all")
    refused(path, tmp_path / "scene", r"not a readable ROS 1 or ROS 2 bag: ")
    refused(tmp_path / "missing_bag", tmp_path / "scene", r"not found")


def test_raw_pixels_honour_row_padding_and_byte_order():
    """A row ``step`` longer than the pixels (drivers pad rows) and big-endian 16-bit depth."""
    from types import SimpleNamespace

    from voxnerf.data.importers.rosbag import _depth_file

    mm = np.arange(12, dtype=np.uint16).reshape(3, 4) * 1000
    rows = np.zeros((3, 10), dtype=np.uint8)
    rows[:, :8] = mm.astype(">u2").view(np.uint8).reshape(3, 8)
    msg = SimpleNamespace(encoding="16UC1", width=4, height=3, step=10, is_bigendian=1, data=rows.reshape(-1))
    suffix, data, size = _depth_file(msg)
    assert suffix == ".png" and size == (4, 3)
    np.testing.assert_array_equal(iio.imread(data, extension=".png"), mm)
    short = SimpleNamespace(**{**vars(msg), "data": rows.reshape(-1)[:-1]})
    with pytest.raises(ValueError, match="29 bytes for 4x3x1 uint16 with step 10"):
        _depth_file(short)


def test_the_benchmark_measures_a_small_bag(tmp_path):
    """benchmarks/import_rosbag.py end to end on 15 frames: exact poses, every frame kept with --all-frames."""
    import subprocess
    import sys

    script = Path(__file__).resolve().parents[2] / "benchmarks" / "import_rosbag.py"
    subprocess.run([sys.executable, str(script), "--frames", "15", "--out", str(tmp_path / "bench")], check=True,
                   capture_output=True, timeout=600)
    results = json.loads((tmp_path / "bench" / "results.json").read_text())
    assert results["all_frames"]["kept"] == 15 and results["all_frames"]["depth_frames"] == 3
    assert 1 <= results["by_motion"]["kept"] < 15
    for name in ("by_motion", "all_frames"):
        assert results[name]["rotation_error_deg"] < 1e-4 and results[name]["centre_error_of_trajectory"] < 1e-9


@pytest.mark.parametrize("kind", ["sqlite3", "mcap", "ros1"])
def test_truncated_bags_are_one_line_errors(few, tmp_path, kind):
    """A bag cut short (a copy that stopped, a recorder killed) is refused in one line, nothing written."""
    bag = write_bag(tmp_path / ("bag.bag" if kind == "ros1" else "bag"), BagSpec(few, scale=4), kind)
    data = bag if kind == "ros1" else next(p for p in bag.iterdir() if p.suffix in (".db3", ".mcap"))
    raw = data.read_bytes()
    data.write_bytes(raw[: len(raw) // 2])
    refused(bag, tmp_path / "scene", r"not a readable ROS 1 or ROS 2 bag: (Cannot open database .*malformed|"
            r"File end magic is invalid|Bag index looks damaged)")


def test_a_ros2_bag_without_message_definitions_decodes_with_the_standard_messages(few, tmp_path):
    """rosbag2 before format 8 stored no message definitions: the standard messages (Humble's) decode them."""
    import sqlite3

    from rosbags.highlevel import AnyReader

    bag = write_bag(tmp_path / "bag", BagSpec(few, scale=4), "sqlite3")
    db = sqlite3.connect(next(bag.glob("*.db3")))
    db.execute("DELETE FROM message_definitions")
    db.commit()
    db.close()
    with pytest.raises(Exception, match="no type definitions"):
        AnyReader([bag]).open()
    import_rosbag(bag, tmp_path / "scene", options=ALL)
    assert_poses(scene(tmp_path / "scene"), few)
