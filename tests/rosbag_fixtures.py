"""Bags made for the importer's tests from the shared redkitchen frames, with the ``rosbags`` writers.

A camera on a robot: ``map -> odom`` and ``odom -> base_link`` on ``/tf`` (dynamic), ``base_link -> camera_link``
and ``camera_link -> camera_color_optical_frame`` on ``/tf_static`` (the mount, and REP 103's optical rotation),
composed so that the optical frame's pose in ``map`` is redkitchen's camera-to-world pose (OpenGL axes flipped
to OpenCV's). Colour, depth and CameraInfo as a RealSense driver names them.
"""

from __future__ import annotations

import json
import math
import struct
from dataclasses import dataclass, field
from pathlib import Path

import imageio.v3 as iio
import numpy as np

from voxnerf.data.importers.ros_transforms import matrix_quaternion, quaternion_matrix

REDKITCHEN = Path(__file__).resolve().parents[2] / "shared" / "data" / "redkitchen"
FLIP = np.diag([1.0, -1.0, -1.0, 1.0])
CAMERA_FRAME = "camera_color_optical_frame"
DEPTH_FRAME = "camera_depth_optical_frame"
OPTICAL_IN_LINK = np.array([-0.5, 0.5, -0.5, 0.5])  # REP 103: z forward, x right, y down in a x-forward link frame
T0 = 1_700_000_000 * 10**9  # first stamp, ns
PERIOD = 33_333_333  # ns between images (30 Hz)


def orthonormal(c2w) -> np.ndarray:
    """``c2w`` with its rotation replaced by the nearest rotation: redkitchen's poses are stored with 8 digits,
    5.7e-5 off orthonormal, and a quaternion (what ROS carries) holds only the rotation part of that."""
    m = np.array(c2w, dtype=np.float64)
    u, _, vt = np.linalg.svd(m[:3, :3])
    m[:3, :3] = u @ vt
    return m


def redkitchen_frames(step: int = 5, n: int = 20) -> list[dict]:
    """``n`` redkitchen frames, every ``step``-th (every 5th has depth)."""
    return json.loads((REDKITCHEN / "transforms.json").read_text())["frames"][: step * n : step]


def rigid(rot: np.ndarray, t) -> np.ndarray:
    m = np.eye(4)
    m[:3, :3], m[:3, 3] = rot, t
    return m


def rot_z(angle: float) -> np.ndarray:
    c, s = math.cos(angle), math.sin(angle)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])


def rot_axis(axis, angle: float) -> np.ndarray:
    axis = np.asarray(axis, dtype=np.float64) / np.linalg.norm(axis)
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + math.sin(angle) * k + (1 - math.cos(angle)) * k @ k


MOUNT = rigid(rot_axis([0, 1, 0], 0.2), [0.1, 0.02, 0.5])  # base_link -> camera_link, a tilted mast
LINK_TO_OPTICAL = rigid(quaternion_matrix(OPTICAL_IN_LINK), [0.0, 0.015, 0.0])


def map_to_odom(i: int) -> np.ndarray:
    """A slowly drifting odometry frame, as a localiser corrects it."""
    return rigid(rot_z(0.01 * i), [0.002 * i, -0.001 * i, 0.0])


@dataclass
class Frame:
    stamp: int
    c2w_gl: np.ndarray
    colour: Path
    depth: Path | None


@dataclass
class BagSpec:
    """What goes into a test bag; every field has the ordinary robot's value."""

    frames: list[Frame]
    colour: str = "raw"  # "raw" (sensor_msgs/Image), "jpeg" (CompressedImage, the JPEG bytes), "both", "none",
    # or "broken_jpeg" (CompressedImage of a truncated JPEG)
    colour_encoding: str = "rgb8"
    scale: int = 2  # colour and depth are shrunk by this (raw colour only)
    depth_encoding: str | None = "16UC1"  # 16UC1, 32FC1, None for no depth, or any other string as written
    depth_scale: int | None = None  # depth shrunk by this from 640x480, with its own CameraInfo (None: as colour)
    depth_compressed: str | None = None  # image_transport's compressedDepth PNG on <depth_topic>/compressedDepth:
    # "only", or "twin" (beside the raw depth topic)
    depth_offset: list[float] | None = None  # depth in its own optical frame, this far (metres) from the colour one
    distortion: tuple[str, list[float]] = ("plumb_bob", [0.0, 0.0, 0.0, 0.0, 0.0])
    tf: str = "exact"  # "exact" (samples at the image stamps), "bracket" (samples 10 ms either side), "none"
    tf_frames: int | None = None  # /tf for the first this many images only (None: all)
    tf_late: bool = False  # /tf recorded after everything else, newest first (a buffered, reordering relay)
    pose_topic: str | None = None  # "pose" / "base_pose" (PoseStamped of the optical frame / base_link in map),
    # "odom" (Odometry of base_link in map)
    extra_colour: bool = False  # a second rgb8 topic (an infrared-like camera) to make the choice ambiguous
    image_topic: str = "/camera/color/image_raw"
    depth_topic: str = "/camera/aligned_depth_to_color/image_raw"
    extra: list = field(default_factory=list)


def make_frames(step: int = 5, n: int = 20) -> list[Frame]:
    frames = []
    for i, entry in enumerate(redkitchen_frames(step, n)):
        depth = REDKITCHEN / entry["depth_file_path"] if "depth_file_path" in entry else None
        frames.append(Frame(T0 + i * PERIOD, orthonormal(entry["transform_matrix"]), REDKITCHEN / entry["file_path"],
                            depth))
    return frames


def base_pose(frame: Frame, i: int) -> np.ndarray:
    """``T_odom_base`` that puts the optical frame at the frame's pose."""
    t_map_optical = frame.c2w_gl @ FLIP
    return np.linalg.inv(map_to_odom(i)) @ t_map_optical @ np.linalg.inv(MOUNT @ LINK_TO_OPTICAL)


def write_bag(path: Path, spec: BagSpec, kind: str = "sqlite3") -> Path:
    """The bag of ``spec`` at ``path``: ``kind`` "sqlite3" or "mcap" (ROS 2 folders) or "ros1" (a .bag file)."""
    from rosbags.typesys import Stores, get_typestore

    if kind == "ros1":
        from rosbags.rosbag1 import Writer
        from rosbags.typesys import get_types_from_msg

        store = get_typestore(Stores.ROS1_NOETIC)
        # the noetic store lacks tf2_msgs: its one message, as tf2_msgs/msg/TFMessage.msg defines it
        store.register(get_types_from_msg("geometry_msgs/TransformStamped[] transforms", "tf2_msgs/msg/TFMessage"))
        bag = Writer(path)
        serialize = store.serialize_ros1
    else:
        from rosbags.rosbag2 import StoragePlugin, Writer

        store = get_typestore(Stores.ROS2_HUMBLE)
        plugin = StoragePlugin.MCAP if kind == "mcap" else StoragePlugin.SQLITE3
        bag = Writer(path, version=9, storage_plugin=plugin)
        serialize = store.serialize_cdr
    maker = _Messages(store, kind == "ros1")
    with bag:
        conns = {}

        def put(topic: str, msg, stamp: int) -> None:
            if topic not in conns:
                conns[topic] = bag.add_connection(topic, msg.__msgtype__, typestore=store)
            bag.write(conns[topic], stamp, serialize(msg, msg.__msgtype__))

        messages = sorted(_messages(spec, maker), key=lambda m: m[2])
        if spec.tf_late:
            tf = [m for m in messages if m[0] == "/tf"]
            end = messages[-1][2]
            messages = [m for m in messages if m[0] != "/tf"] + [
                (topic, msg, end + n + 1) for n, (topic, msg, _) in enumerate(reversed(tf))]
        for topic, msg, stamp in messages:
            put(topic, msg, stamp)
    return path


def _k(w: int) -> list[float]:
    """redkitchen's K (585 px focal length at 640x480, centred) at width ``w``, in ROS's pixel-index convention."""
    s = w / 640
    return [585.0 * s, 0, 320.0 * s - 0.5, 0, 585.0 * s, 240.0 * s - 0.5, 0, 0, 1]


def _namespace(topic: str) -> str:
    return topic.rsplit("/", 1)[0]


def _messages(spec: BagSpec, m: _Messages):
    """(topic, message, stamp) of every message of the bag."""
    first = spec.frames[0].stamp
    w, h = 640 // spec.scale, 480 // spec.scale
    if spec.colour == "jpeg":
        w, h = 640, 480
    model, d = spec.distortion
    yield "/camera/color/camera_info", m.camera_info(first, CAMERA_FRAME, w, h, _k(w), model, d), first
    depth_w = 640 // spec.depth_scale if spec.depth_scale else w
    if spec.depth_scale:
        yield (_namespace(spec.depth_topic) + "/camera_info",
               m.camera_info(first, CAMERA_FRAME, depth_w, depth_w * 3 // 4, _k(depth_w), "plumb_bob", [0.0] * 5),
               first)
    yield "/tf_static", m.tf([("base_link", "camera_link", first, MOUNT),
                              ("camera_link", CAMERA_FRAME, first, LINK_TO_OPTICAL)]), first
    depth_frame = CAMERA_FRAME
    if spec.depth_offset is not None:
        depth_frame = DEPTH_FRAME
        yield "/tf_static", m.tf([("camera_link", DEPTH_FRAME, first,
                                   LINK_TO_OPTICAL @ rigid(np.eye(3), spec.depth_offset))]), first
    for i, frame in enumerate(spec.frames):
        if spec.colour in ("raw", "both"):
            rgb = iio.imread(frame.colour)[:: spec.scale, :: spec.scale]
            yield spec.image_topic, m.image(frame.stamp, CAMERA_FRAME, rgb, spec.colour_encoding), frame.stamp
        if spec.colour in ("jpeg", "both"):
            yield spec.image_topic + "/compressed", m.compressed(frame.stamp, frame.colour.read_bytes()), frame.stamp
        elif spec.colour == "broken_jpeg":  # a JPEG's first 600 bytes: its header, and pixels cut short
            yield spec.image_topic + "/compressed", m.compressed(frame.stamp, frame.colour.read_bytes()[:600]), \
                frame.stamp
        if spec.extra_colour:
            rgb = iio.imread(frame.colour)[:: spec.scale * 2, :: spec.scale * 2]
            yield "/camera/infra_rgb/image_raw", m.image(frame.stamp, CAMERA_FRAME, rgb, "rgb8"), frame.stamp
        if spec.depth_encoding is not None and frame.depth is not None:
            step = 640 // depth_w
            mm = iio.imread(frame.depth)[::step, ::step]
            if spec.depth_compressed:
                yield (spec.depth_topic + "/compressedDepth",
                       m.compressed_depth(frame.stamp, depth_frame, mm, spec.depth_encoding), frame.stamp)
            if spec.depth_compressed != "only":
                yield spec.depth_topic, m.depth(frame.stamp, depth_frame, mm, spec.depth_encoding), frame.stamp
        t_map_odom, t_odom_base = map_to_odom(i), base_pose(frame, i)
        if spec.tf_frames is not None and i >= spec.tf_frames:
            pass
        elif spec.tf == "exact":
            yield "/tf", m.tf([("map", "odom", frame.stamp, t_map_odom), ("odom", "base_link", frame.stamp,
                                                                              t_odom_base)]), frame.stamp
        elif spec.tf == "bracket":
            yield from _bracketing(m, frame.stamp, t_map_odom, t_odom_base)
        if spec.pose_topic == "pose":
            yield "/camera_pose", m.pose_stamped(frame.stamp, "map", frame.c2w_gl @ FLIP), frame.stamp
        elif spec.pose_topic == "base_pose":
            yield "/base_pose", m.pose_stamped(frame.stamp, "map", map_to_odom(i) @ t_odom_base), frame.stamp
        elif spec.pose_topic == "odom":
            yield "/odom", m.odometry(frame.stamp, "map", "base_link", map_to_odom(i) @ t_odom_base), frame.stamp
    yield from spec.extra


DELTA = 10_000_000  # ns either side of an image stamp for bracketing transforms


def _bracketing(m: _Messages, stamp: int, t_map_odom: np.ndarray, t_odom_base: np.ndarray):
    """Samples 10 ms before and after ``stamp`` whose interpolation at ``stamp`` is exactly the given transforms:
    each moves by a rotation about a fixed axis and a straight translation, which slerp and lerp follow."""
    for sign in (-1, 1):
        spin = rigid(rot_axis([0.3, -0.5, 0.8], sign * 0.05), [0, 0, 0])
        shift = np.array([0.01, -0.02, 0.005]) * sign
        a, b = t_map_odom @ spin, t_odom_base @ spin
        a[:3, 3] = t_map_odom[:3, 3] + shift
        b[:3, 3] = t_odom_base[:3, 3] - shift
        s = stamp + sign * DELTA
        yield "/tf", m.tf([("map", "odom", s, a), ("odom", "base_link", s, b)]), s


class _Messages:
    """Message constructors for one typestore (ROS 1 headers carry ``seq``; CameraInfo's fields are upper-case)."""

    def __init__(self, store, ros1: bool) -> None:
        self.store, self.ros1, self.types = store, ros1, store.types

    def header(self, stamp: int, frame_id: str):
        time = self.types["builtin_interfaces/msg/Time"](sec=stamp // 10**9, nanosec=stamp % 10**9)
        header = self.types["std_msgs/msg/Header"]
        return header(seq=0, stamp=time, frame_id=frame_id) if self.ros1 else header(stamp=time, frame_id=frame_id)

    def image(self, stamp: int, frame_id: str, rgb: np.ndarray, encoding: str):
        pixels = {"rgb8": rgb, "bgr8": rgb[:, :, ::-1], "mono8": rgb[:, :, 1]}.get(encoding, rgb)
        pixels = np.ascontiguousarray(pixels)
        h, w = pixels.shape[:2]
        return self.types["sensor_msgs/msg/Image"](
            header=self.header(stamp, frame_id), height=h, width=w, encoding=encoding, is_bigendian=0,
            step=pixels.strides[0], data=pixels.reshape(-1).view(np.uint8))

    def depth(self, stamp: int, frame_id: str, mm: np.ndarray, encoding: str):
        values = (mm.astype(np.float32) / 1000.0) if encoding == "32FC1" else mm.astype(np.uint16)
        if encoding == "32FC1":
            values[mm == 0] = np.nan
        values = np.ascontiguousarray(values)
        h, w = values.shape
        return self.types["sensor_msgs/msg/Image"](
            header=self.header(stamp, frame_id), height=h, width=w, encoding=encoding, is_bigendian=0,
            step=values.strides[0], data=values.reshape(-1).view(np.uint8))

    def compressed_depth(self, stamp: int, frame_id: str, mm: np.ndarray, encoding: str):
        """image_transport's compressedDepth PNG: a 12-byte header (format enum, A, B), then a 16-bit PNG of the
        millimetres (16UC1) or of the inverse depth quantised as the publisher does by default (depth_max 10 m,
        depth_quantization 100: v = A / depth + B truncated, 0 beyond depth_max or for no depth) (32FC1)."""
        if encoding == "32FC1":
            metres = mm.astype(np.float32) / np.float32(1000.0)
            quant_a = np.float32(100.0 * 101.0)
            quant_b = np.float32(1.0) - quant_a / np.float32(10.0)
            with np.errstate(divide="ignore"):
                values = np.where((mm > 0) & (metres < 10.0), quant_a / metres + quant_b, 0).astype(np.uint16)
        else:
            quant_a, quant_b, values = 0.0, 0.0, mm.astype(np.uint16)
        data = struct.pack("<iff", 0, quant_a, quant_b) + iio.imwrite("<bytes>", values, extension=".png")
        return self.types["sensor_msgs/msg/CompressedImage"](
            header=self.header(stamp, frame_id), format=f"{encoding}; compressedDepth png",
            data=np.frombuffer(data, dtype=np.uint8))

    def compressed(self, stamp: int, data: bytes):
        return self.types["sensor_msgs/msg/CompressedImage"](
            header=self.header(stamp, CAMERA_FRAME), format="jpeg", data=np.frombuffer(data, dtype=np.uint8))

    def camera_info(self, stamp: int, frame_id: str, w: int, h: int, k: list, model: str, d: list):
        roi = self.types["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0,
                                                            do_rectify=False)
        p = [k[0], 0, k[2], 0, 0, k[4], k[5], 0, 0, 0, 1, 0]
        mats = {"d": np.array(d, dtype=np.float64), "k": np.array(k, dtype=np.float64),
                "r": np.eye(3).reshape(-1), "p": np.array(p, dtype=np.float64)}
        if self.ros1:
            mats = {key.upper(): value for key, value in mats.items()}
        return self.types["sensor_msgs/msg/CameraInfo"](
            header=self.header(stamp, frame_id), height=h, width=w, distortion_model=model, binning_x=0,
            binning_y=0, roi=roi, **mats)

    def transform(self, m: np.ndarray):
        q = matrix_quaternion(m[:3, :3])
        vec = self.types["geometry_msgs/msg/Vector3"](x=m[0, 3], y=m[1, 3], z=m[2, 3])
        quat = self.types["geometry_msgs/msg/Quaternion"](x=q[0], y=q[1], z=q[2], w=q[3])
        return self.types["geometry_msgs/msg/Transform"](translation=vec, rotation=quat)

    def tf(self, edges: list):
        stamped = self.types["geometry_msgs/msg/TransformStamped"]
        return self.types["tf2_msgs/msg/TFMessage"](transforms=[
            stamped(header=self.header(stamp, parent), child_frame_id=child, transform=self.transform(m))
            for parent, child, stamp, m in edges])

    def pose(self, m: np.ndarray):
        q = matrix_quaternion(m[:3, :3])
        point = self.types["geometry_msgs/msg/Point"](x=m[0, 3], y=m[1, 3], z=m[2, 3])
        quat = self.types["geometry_msgs/msg/Quaternion"](x=q[0], y=q[1], z=q[2], w=q[3])
        return self.types["geometry_msgs/msg/Pose"](position=point, orientation=quat)

    def pose_stamped(self, stamp: int, frame_id: str, m: np.ndarray):
        return self.types["geometry_msgs/msg/PoseStamped"](header=self.header(stamp, frame_id), pose=self.pose(m))

    def odometry(self, stamp: int, frame_id: str, child: str, m: np.ndarray):
        pose = self.types["geometry_msgs/msg/PoseWithCovariance"](pose=self.pose(m), covariance=np.zeros(36))
        twist = self.types["geometry_msgs/msg/TwistWithCovariance"](
            twist=self.types["geometry_msgs/msg/Twist"](
                linear=self.types["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0),
                angular=self.types["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0)),
            covariance=np.zeros(36))
        return self.types["nav_msgs/msg/Odometry"](header=self.header(stamp, frame_id), child_frame_id=child,
                                                   pose=pose, twist=twist)
