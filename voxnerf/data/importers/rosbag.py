"""``voxnerf import rosbag``: a robot's log (ROS 1 ``.bag``, ROS 2 sqlite3 or MCAP) as a docs/scene-format.md scene.

Read with the pure-Python ``rosbags`` package (no ROS install). What is taken from the bag:

- **Colour**: one ``sensor_msgs/Image`` (``rgb8 bgr8 rgba8 bgra8 mono8``, written as lossless PNG) or
  ``sensor_msgs/CompressedImage`` (JPEG or PNG, written as the bytes recorded) topic.
- **Depth** (optional): one ``sensor_msgs/Image`` topic in ``16UC1`` (millimetres, written as a 16-bit PNG with
  ``depth_unit_scale_factor`` 0.001) or ``32FC1`` (metres, written as float32 ``.npy``; NaN and inf stay "no depth",
  as REP 117 defines them), or image_transport's ``compressedDepth`` PNG of either. Each colour image takes the
  depth image nearest in stamp when within the sync tolerance. The depth must be registered to the colour camera
  (same frame, or a frame the transforms put within a millimetre and 0.1 degrees of it); its own ``CameraInfo``
  gives ``depth_intrinsics``.
- **Camera**: ``sensor_msgs/CameraInfo``: ``K`` (OpenCV pixel-index convention, so the scene's continuous
  ``cx, cy`` are ``K``'s plus 0.5) and ``D`` by ``distortion_model``: ``plumb_bob`` (``k1 k2 p1 p2 k3``) and
  ``rational_polynomial`` whose ``k4 k5 k6`` are zero become ``OPENCV``, ``equidistant`` (``k1 k2 k3 k4``)
  becomes ``OPENCV_FISHEYE``, all-zero coefficients ``PINHOLE``. Binning and ROI are refused.
- **Poses**: the image's ``header.frame_id`` is its optical frame (REP 103: x right, y down, z forward, as
  sensor_msgs defines the field), posed in a fixed frame by the chain of ``/tf`` (interpolated at the image's
  stamp: translation linearly, rotation by slerp) and ``/tf_static`` transforms; or by a pose topic
  (``PoseStamped``, ``PoseWithCovarianceStamped``, ``Odometry``, ``TransformStamped``) giving the pose of a body
  frame (``child_frame_id``, ``--pose-frame``, else the camera's frame) chained to the camera by the transforms.
  The fixed frame is ``--fixed-frame`` or the root of the camera's transform tree. Poses are converted from the
  optical frame's OpenCV axes to OpenGL camera axes; the fixed frame is the scene's world frame.
- **Frames kept**: in stamp order, a frame whose pose moved at least ``min_translation`` metres or
  ``min_rotation`` degrees from the last kept one (every synchronised, posed frame with ``all_frames``);
  files ``images/frame_NNNNN`` numbered in capture order. Dropped frames are counted by reason in the summary.

Topics are found by message type (and encoding) when one candidate is left; otherwise the error lists the
candidates and the flag that chooses. Every refusal is a :class:`SceneError` naming the bag (and the topic).
"""

from __future__ import annotations

import io
import math
import struct
from dataclasses import dataclass, field
from pathlib import Path

import imageio.v3 as iio
import numpy as np

from voxnerf.data.image_io import PNG_SIGNATURE, read_rgb
from voxnerf.data.importers import writer
from voxnerf.data.importers.ros_transforms import TransformTree, TransformTreeError
from voxnerf.data.importers.splits import PaperSplitRule, SplitError, split_keys
from voxnerf.errors import SceneError

IMAGE = "sensor_msgs/msg/Image"
COMPRESSED_IMAGE = "sensor_msgs/msg/CompressedImage"
CAMERA_INFO = "sensor_msgs/msg/CameraInfo"
TF_MESSAGE = "tf2_msgs/msg/TFMessage"
POSE_STAMPED = "geometry_msgs/msg/PoseStamped"
POSE_WITH_COVARIANCE = "geometry_msgs/msg/PoseWithCovarianceStamped"
ODOMETRY = "nav_msgs/msg/Odometry"
TRANSFORM_STAMPED = "geometry_msgs/msg/TransformStamped"
POSE_TYPES = (POSE_STAMPED, POSE_WITH_COVARIANCE, ODOMETRY, TRANSFORM_STAMPED)
TF_TOPIC, TF_STATIC_TOPIC = "/tf", "/tf_static"

# encoding -> (channels, the channel order that gives R G B, or None for grey)
COLOUR_ENCODINGS = {"rgb8": (3, (0, 1, 2)), "bgr8": (3, (2, 1, 0)), "rgba8": (4, (0, 1, 2)),
                    "bgra8": (4, (2, 1, 0)), "mono8": (1, None)}
DEPTH_ENCODINGS = {"16UC1": "millimetres", "32FC1": "metres"}
COMPRESSED_DEPTH_FORMATS = ("compressedDepth", "compressedDepth png")  # image_transport's, after "ENCODING; "
COMPRESSED_DEPTH_HEADER = struct.Struct("<iff")  # its ConfigHeader: format enum, depthQuantA, depthQuantB
DEPTH_UNIT_SCALE = 0.001
JPEG_MAGIC = b"\xff\xd8\xff"
REGISTERED_DEPTH_OFFSET = 1e-3  # metres: depth in another frame this close to the colour frame counts as registered
REGISTERED_DEPTH_ANGLE = 0.1  # degrees
NO_DEPTH = "none"  # ``--depth none``: import colour only


@dataclass(frozen=True)
class RosbagOptions:
    """What ``voxnerf import rosbag`` lets a user choose; None finds the topic (or frame) in the bag."""

    rgb: str | None = None
    depth: str | None = None  # a topic, NO_DEPTH for colour only, None to find one
    camera_info: str | None = None
    fixed_frame: str | None = None
    pose_topic: str | None = None
    pose_frame: str | None = None  # the frame a PoseStamped's pose is of (default: the camera's frame)
    all_frames: bool = False
    min_translation: float = 0.05  # metres
    min_rotation: float = 5.0  # degrees
    sync_tolerance: float = 0.02  # seconds between a colour image's stamp and its depth image's

    def check(self) -> None:
        for name in ("min_translation", "min_rotation", "sync_tolerance"):
            value = getattr(self, name)
            if not (isinstance(value, int | float) and math.isfinite(value) and value >= 0):
                raise ValueError(f"{name} must be a finite number >= 0, got {value!r}")


@dataclass
class _Image:
    """One image message found in the first pass: its place in its topic and its header."""

    index: int
    stamp: int  # header stamp, nanoseconds
    frame_id: str
    c2w: np.ndarray | None = None
    depth: _Image | None = None


@dataclass
class _Camera:
    """A CameraInfo as the scene's intrinsics keys, and its lens model."""

    keys: dict
    model: str


@dataclass
class _Bag:
    """What the first pass read, and what the import drops and notes."""

    path: Path
    reader: object
    topics: dict  # topic -> msgtype
    skipped: dict = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)

    def error(self, message: str, topic: str | None = None) -> SceneError:
        return SceneError(self.path, message, key=topic)

    def skip(self, reason: str) -> None:
        self.skipped[reason] = self.skipped.get(reason, 0) + 1

    def connections(self, topic: str) -> list:
        return [c for c in self.reader.connections if c.topic == topic]

    def messages(self, topic: str):
        """``(index, message)`` of ``topic`` in the bag's order; a message that cannot be read or decoded (a
        truncated or corrupt bag) is an error."""
        stream = self.reader.messages(connections=self.connections(topic))
        index = 0
        while True:
            try:
                item = next(stream, None)
                if item is None:
                    return
                conn, _, raw = item
                msg = self.reader.deserialize(raw, conn.msgtype)
            except Exception as err:  # rosbags and its storage back-ends raise their own types for corrupt data
                raise self.error(f"message {index} cannot be read: {writer.one_line(err)}", topic) from None
            yield index, msg
            index += 1

    def first(self, topic: str):
        return next((msg for _, msg in self.messages(topic)), None)


def _stamp(header) -> int:
    return int(header.stamp.sec) * 1_000_000_000 + int(header.stamp.nanosec)


def _field(msg, name: str):
    """A CameraInfo matrix by its ROS 2 name (``k``, ``d``), also under its ROS 1 name (``K``, ``D``)."""
    return getattr(msg, name) if hasattr(msg, name) else getattr(msg, name.upper())


def _namespace(topic: str) -> str:
    return topic.rsplit("/", 1)[0]


# ------------------------------------------------------------------------------------------------ topics


def _typed(bag: _Bag, *msgtypes: str) -> list[str]:
    return sorted(t for t, msgtype in bag.topics.items() if msgtype in msgtypes)


def _given_topic(bag: _Bag, topic: str, msgtypes: tuple[str, ...], flag: str) -> str:
    if topic not in bag.topics:
        raise bag.error(f"{flag} {topic}: no such topic (topics: {', '.join(sorted(bag.topics)) or 'none'})")
    if bag.topics[topic] not in msgtypes:
        raise bag.error(f"{flag}: topic is {bag.topics[topic]}, expected {' or '.join(msgtypes)}", topic)
    return topic


def _one_of(bag: _Bag, candidates: list[str], what: str, flag: str) -> str | None:
    if len(candidates) > 1:
        raise bag.error(f"{len(candidates)} {what} topics ({', '.join(candidates)}): choose one with {flag} TOPIC")
    return candidates[0] if candidates else None


def _colour_topic(bag: _Bag, options: RosbagOptions, encodings: dict) -> str:
    if options.rgb:
        return _given_topic(bag, options.rgb, (IMAGE, COMPRESSED_IMAGE), "--rgb")
    raw = [t for t in _typed(bag, IMAGE) if encodings.get(t) in COLOUR_ENCODINGS]
    rgb = [t for t in raw if encodings[t] != "mono8"]
    compressed = [t for t in _typed(bag, COMPRESSED_IMAGE) if t in encodings and "depth" not in encodings[t].lower()
                  and _namespace(t) not in raw]  # image_transport's <raw>/compressed repeats a raw topic
    candidates = rgb + compressed or raw
    if not candidates:
        images = _typed(bag, IMAGE, COMPRESSED_IMAGE)
        found = ", ".join(f"{t} ({encodings.get(t) or 'no messages'})" for t in images) or "none"
        raise bag.error(f"no camera topic: no sensor_msgs/Image in {', '.join(COLOUR_ENCODINGS)} and no "
                        f"sensor_msgs/CompressedImage (image topics: {found})")
    return _one_of(bag, candidates, "colour image", "--rgb")


def _depth_topic(bag: _Bag, options: RosbagOptions, encodings: dict, colour: str) -> str | None:
    if options.depth == NO_DEPTH:
        return None
    if options.depth:
        topic = _given_topic(bag, options.depth, (IMAGE, COMPRESSED_IMAGE), "--depth")
        _check_depth_encoding(bag, topic, encodings.get(topic))
        return topic
    images = [t for t in _typed(bag, IMAGE, COMPRESSED_IMAGE) if t != colour]
    raw = [t for t in _typed(bag, IMAGE) if t != colour and _readable_depth(encodings.get(t))]
    candidates = raw + [t for t in _typed(bag, COMPRESSED_IMAGE) if _readable_depth(encodings.get(t))
                        and _namespace(t) not in raw]  # image_transport's <raw>/compressedDepth repeats a raw topic
    if not candidates:
        for topic in images:  # a depth stream the importer cannot read is an error, not a silent colour-only scene
            if "depth" in topic.lower() and encodings.get(topic) is not None:
                _check_depth_encoding(bag, topic, encodings[topic])
    return _one_of(bag, candidates, "depth image", "--depth") if candidates else None


def _readable_depth(encoding: str | None) -> bool:
    """Whether depth in ``encoding`` (an Image's ``encoding`` or a CompressedImage's ``format``) can be read:
    16UC1 or 32FC1, raw or in image_transport's compressedDepth PNG (not its RVL)."""
    base, _, compression = (encoding or "").partition(";")
    return base.strip() in DEPTH_ENCODINGS and (not compression or compression.strip() in COMPRESSED_DEPTH_FORMATS)


def _check_depth_encoding(bag: _Bag, topic: str, encoding: str | None) -> None:
    if not _readable_depth(encoding):
        raise bag.error(f"depth encoding {encoding!r} is not supported (16UC1 millimetres or 32FC1 metres, raw or "
                        f"compressedDepth png; --depth none imports colour only)", topic)


def _camera_info_topic(bag: _Bag, image_topic: str, frame_id: str, given: str | None, exclude: str | None,
                       flag: str) -> str | None:
    """The CameraInfo topic of ``image_topic``: ``given``, else the one beside it, else the only one whose
    frame is ``frame_id``, else the bag's only one (``exclude``: a topic already taken by another camera)."""
    if given:
        return _given_topic(bag, given, (CAMERA_INFO,), flag)
    infos = [t for t in _typed(bag, CAMERA_INFO) if t != exclude]
    beside = [t for t in infos if _namespace(t) in (_namespace(image_topic), _namespace(_namespace(image_topic)))
              and _namespace(t) != ""]
    if len(beside) == 1:
        return beside[0]
    same_frame = [t for t in infos if (msg := bag.first(t)) is not None and msg.header.frame_id == frame_id]
    if len(same_frame) == 1:
        return same_frame[0]
    if exclude is None and len(infos) > 1:
        raise bag.error(f"{len(infos)} CameraInfo topics ({', '.join(infos)}) and none is beside {image_topic}: "
                        f"choose one with {flag} TOPIC")
    return infos[0] if len(infos) == 1 and exclude is None else None


def _encodings(bag: _Bag) -> dict:
    """Topic -> the encoding (Image) or format (CompressedImage) of its first message."""
    found = {}
    for topic in _typed(bag, IMAGE, COMPRESSED_IMAGE):
        msg = bag.first(topic)
        if msg is not None:
            found[topic] = msg.encoding if bag.topics[topic] == IMAGE else msg.format
    return found


# ------------------------------------------------------------------------------------------------ camera


def _camera(bag: _Bag, topic: str, size: tuple[int, int] | None) -> _Camera:
    """The intrinsics of ``topic``'s CameraInfo messages (all alike), for images of ``size`` when given."""
    first, first_index = None, 0
    for index, msg in bag.messages(topic):
        if first is None:
            first, first_index = msg, index
        elif (list(_field(msg, "k")) != list(_field(first, "k")) or list(_field(msg, "d")) != list(_field(first, "d"))
              or (msg.width, msg.height) != (first.width, first.height)):
            raise bag.error(f"the camera's K, D or size changes at message {index} (from message {first_index}); "
                            "one calibration per topic is supported", topic)
    if first is None:
        raise bag.error("no CameraInfo message", topic)
    k = np.asarray(_field(first, "k"), dtype=np.float64).reshape(3, 3)
    w, h = int(first.width), int(first.height)
    if not np.isfinite(k).all() or k[0, 0] <= 0 or k[1, 1] <= 0 or w <= 0 or h <= 0:
        raise bag.error(f"K must be finite with positive focal lengths and the size positive (K {k.ravel().tolist()}, "
                        f"{w}x{h})", topic)
    roi = first.roi
    if max(first.binning_x, 1) > 1 or max(first.binning_y, 1) > 1 or (roi.width and (roi.width, roi.height) != (w, h)):
        raise bag.error("binning or a region of interest is set: only full-resolution images are supported", topic)
    if size is not None and size != (w, h):
        raise bag.error(f"CameraInfo is {w}x{h} but the images are {size[0]}x{size[1]}", topic)
    keys = {"fl_x": float(k[0, 0]), "fl_y": float(k[1, 1]), "cx": float(k[0, 2]) + 0.5, "cy": float(k[1, 2]) + 0.5,
            "w": w, "h": h}
    model, lens = _lens(bag, topic, first.distortion_model, [float(v) for v in _field(first, "d")])
    return _Camera({"camera_model": model, **keys, **lens}, model)


def _lens(bag: _Bag, topic: str, model: str, d: list[float]) -> tuple[str, dict]:
    """The scene's ``camera_model`` and coefficients of a CameraInfo's ``distortion_model`` and ``D``."""
    if not all(math.isfinite(v) for v in d):
        raise bag.error(f"D holds non-finite coefficients {d}", topic)
    if not any(d):
        return "PINHOLE", {}
    if model in ("plumb_bob", "rational_polynomial"):
        terms = dict(zip(("k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6"), d, strict=False))
        if len(d) > 8 or any(terms.get(k, 0.0) for k in ("k4", "k5", "k6")):
            raise bag.error(f"{model} with k4-k6 {d[5:8]} has no lens model in the engine (OPENCV has k1 k2 k3 p1 p2)",
                            topic)
        return "OPENCV", {k: terms.get(k, 0.0) for k in ("k1", "k2", "k3", "p1", "p2")}
    if model == "equidistant":
        if len(d) > 4:
            raise bag.error(f"equidistant takes 4 coefficients, got {len(d)}", topic)
        return "OPENCV_FISHEYE", dict(zip(("k1", "k2", "k3", "k4"), [*d, 0.0, 0.0, 0.0, 0.0], strict=False))
    raise bag.error(f"distortion_model {model!r} is not supported (plumb_bob, rational_polynomial, equidistant)", topic)


# ------------------------------------------------------------------------------------------------ poses


def _transforms(bag: _Bag, skip_child: str | None = None) -> TransformTree:
    """The tree of ``/tf`` and ``/tf_static``, leaving out the edge to ``skip_child`` (a pose topic's body frame,
    whose pose the topic gives instead)."""
    tree = TransformTree()
    for topic, static in ((TF_STATIC_TOPIC, True), (TF_TOPIC, False)):
        if bag.topics.get(topic) != TF_MESSAGE:
            continue
        for _, msg in bag.messages(topic):
            for tf in msg.transforms:
                if tf.child_frame_id.lstrip("/") == skip_child:
                    continue
                t, r = tf.transform.translation, tf.transform.rotation
                try:
                    tree.add(tf.header.frame_id, tf.child_frame_id, _stamp(tf.header), (t.x, t.y, t.z),
                             (r.x, r.y, r.z, r.w), static)
                except TransformTreeError as err:
                    raise bag.error(str(err), topic) from None
    try:
        tree.finish()
    except TransformTreeError as err:
        raise bag.error(str(err), f"{TF_TOPIC} and {TF_STATIC_TOPIC}") from None
    return tree


def _pose_samples(bag: _Bag, topic: str, camera_frame: str, pose_frame: str | None):
    """``(parent, child, [(stamp, translation, quaternion)])`` of a pose topic: the pose of ``child_frame_id``
    (Odometry, TransformStamped), else of ``pose_frame``, else of the camera frame, in ``header.frame_id``."""
    msgtype = bag.topics[topic]
    samples, parent, child = [], None, None
    for _, msg in bag.messages(topic):
        if msgtype == TRANSFORM_STAMPED:
            t, r = msg.transform.translation, msg.transform.rotation
            body = msg.child_frame_id
        else:
            pose = msg.pose.pose if msgtype in (ODOMETRY, POSE_WITH_COVARIANCE) else msg.pose
            t, r = pose.position, pose.orientation
            body = msg.child_frame_id if msgtype == ODOMETRY and msg.child_frame_id else None
        body = (body or pose_frame or camera_frame).lstrip("/")
        origin = msg.header.frame_id.lstrip("/") or "pose_origin"
        if (parent, child) not in ((None, None), (origin, body)):
            raise bag.error(f"poses change frames, from {parent} -> {child} to {origin} -> {body}", topic)
        parent, child = origin, body
        samples.append((_stamp(msg.header), (t.x, t.y, t.z), (r.x, r.y, r.z, r.w)))
    if not samples:
        raise bag.error("no pose message", topic)
    return parent, child, samples


def _pose_tree(bag: _Bag, options: RosbagOptions, camera_frame: str) -> tuple[TransformTree, str]:
    """The transforms that pose the camera frame and where they come from (for the summary)."""
    if options.pose_topic:
        topic = _given_topic(bag, options.pose_topic, POSE_TYPES, "--pose-topic")
        return _tree_with_poses(bag, topic, camera_frame, options.pose_frame), f"pose topic {topic}"
    tree = _transforms(bag)
    if camera_frame in tree.frames() and _moves(tree, camera_frame):
        return tree, f"{TF_TOPIC} and {TF_STATIC_TOPIC}"
    pose_topics = _typed(bag, *POSE_TYPES)
    if len(pose_topics) == 1:
        return _tree_with_poses(bag, pose_topics[0], camera_frame, options.pose_frame), f"pose topic {pose_topics[0]}"
    if pose_topics:
        raise bag.error(f"no {TF_TOPIC} transform moves the camera frame {camera_frame!r} and there are "
                        f"{len(pose_topics)} pose topics ({', '.join(pose_topics)}): choose one with "
                        "--pose-topic TOPIC")
    reached = "only static transforms reach it" if camera_frame in tree.frames() else (
        f"{TF_TOPIC} and {TF_STATIC_TOPIC} do not reach it")
    raise bag.error(f"no pose for the camera frame {camera_frame!r}: {reached}, and there is no PoseStamped, "
                    "PoseWithCovarianceStamped, Odometry or TransformStamped topic (name one with --pose-topic)")


def _moves(tree: TransformTree, frame: str) -> bool:
    return any(not tree.edges[f].static for f in tree.ancestors(frame)[:-1])


def _tree_with_poses(bag: _Bag, topic: str, camera_frame: str, pose_frame: str | None) -> TransformTree:
    parent, child, samples = _pose_samples(bag, topic, camera_frame, pose_frame)
    tree = _transforms(bag, skip_child=child)
    try:
        for stamp, translation, quaternion in samples:
            tree.add(parent, child, stamp, translation, quaternion, static=False)
        tree.finish()
    except TransformTreeError as err:
        raise bag.error(f"{err} (the pose topic gives {parent} -> {child})", topic) from None
    if not tree.connected(child, camera_frame):
        raise bag.error(f"the poses are of frame {child!r}, which the transforms do not link to the camera frame "
                        f"{camera_frame!r} (--pose-frame names the frame a PoseStamped is of)", topic)
    return tree


def _pose_frames(bag: _Bag, colour: list[_Image], tree: TransformTree, fixed: str, camera_frame: str) -> list[_Image]:
    """The colour images with a camera-to-world pose (OpenGL camera axes) in ``fixed``; the rest are counted."""
    posed = []
    for image in colour:
        t, missing = tree.lookup(fixed, camera_frame, image.stamp)
        if t is None:
            bag.skip(f"no transform {missing} at the image's stamp")
            continue
        image.c2w = t @ writer.OPENCV_TO_OPENGL
        posed.append(image)
    return posed


def _by_motion(bag: _Bag, frames: list[_Image], options: RosbagOptions) -> list[_Image]:
    if options.all_frames:
        return frames
    kept = []
    for frame in frames:
        if kept:
            last = kept[-1].c2w
            moved = float(np.linalg.norm(frame.c2w[:3, 3] - last[:3, 3]))
            cos = (np.trace(last[:3, :3].T @ frame.c2w[:3, :3]) - 1) / 2
            turned = math.degrees(math.acos(min(1.0, max(-1.0, cos))))
            if moved < options.min_translation and turned < options.min_rotation:
                bag.skip(f"moved less than {options.min_translation:g} m and {options.min_rotation:g} degrees since "
                         "the last kept frame")
                continue
        kept.append(frame)
    return kept


# ------------------------------------------------------------------------------------------------ images


def _encoding(msg) -> str:
    """An Image's ``encoding`` or a CompressedImage's ``format``."""
    return msg.encoding if hasattr(msg, "encoding") else msg.format


def _headers(bag: _Bag, topic: str, encoding_of: str | None) -> list[_Image]:
    """Every image of ``topic`` (header only), in stamp order; an encoding that changes is an error."""
    images = []
    for index, msg in bag.messages(topic):
        if encoding_of is not None and _encoding(msg) != encoding_of:
            raise bag.error(f"message {index} has encoding {_encoding(msg)!r}, the first {encoding_of!r}", topic)
        images.append(_Image(index, _stamp(msg.header), msg.header.frame_id.lstrip("/")))
    if not images:
        raise bag.error("no image message", topic)
    images.sort(key=lambda image: (image.stamp, image.index))
    return images


def _raw_pixels(msg, channels: int, dtype: np.dtype) -> np.ndarray:
    """A ``sensor_msgs/Image``'s pixels [H, W, channels], honouring ``step`` (row padding) and ``is_bigendian``."""
    dtype = np.dtype(dtype).newbyteorder(">" if msg.is_bigendian else "<")
    row = msg.width * channels * dtype.itemsize
    data = np.asarray(msg.data, dtype=np.uint8)
    if msg.step < row or data.size < msg.step * msg.height:
        raise ValueError(f"{data.size} bytes for {msg.width}x{msg.height}x{channels} {dtype.name} "
                         f"with step {msg.step}")
    rows = np.ascontiguousarray(data[: msg.step * msg.height].reshape(msg.height, msg.step)[:, :row])
    return rows.view(dtype).reshape(msg.height, msg.width, channels).astype(dtype.newbyteorder("="))


def _colour_file(msg, msgtype: str) -> tuple[str, bytes]:
    """``(suffix, file bytes)`` of a colour message: a compressed image's bytes as recorded, raw pixels as PNG;
    ValueError when neither can be."""
    if msgtype == COMPRESSED_IMAGE:
        data = bytes(msg.data)
        suffix = ".jpg" if data.startswith(JPEG_MAGIC) else ".png" if data.startswith(PNG_SIGNATURE) else None
        if suffix is None:
            raise ValueError(f"compressed format {msg.format!r} is neither JPEG nor PNG")
        return suffix, data
    if msg.encoding not in COLOUR_ENCODINGS:
        raise ValueError(f"colour encoding {msg.encoding!r} is not supported ({', '.join(COLOUR_ENCODINGS)})")
    channels, order = COLOUR_ENCODINGS[msg.encoding]
    pixels = _raw_pixels(msg, channels, np.uint8)
    pixels = pixels[:, :, 0] if order is None else pixels[:, :, list(order)]
    return ".png", iio.imwrite("<bytes>", pixels, extension=".png")


def _compressed_depth(msg) -> tuple[bytes, np.ndarray, float, float]:
    """The PNG bytes, their uint16 values and the quantisation ``(A, B)`` of a compressedDepth message: a 12-byte
    little-endian header (format enum, A, B) then a 16-bit PNG of millimetres (16UC1) or of quantised inverse
    depth ``v`` with depth ``A / (v - B)`` metres and 0 for none (32FC1), as image_transport writes it."""
    data = bytes(msg.data)
    if len(data) <= COMPRESSED_DEPTH_HEADER.size or not data[COMPRESSED_DEPTH_HEADER.size:].startswith(PNG_SIGNATURE):
        raise ValueError(f"format {msg.format!r}: no PNG after the {COMPRESSED_DEPTH_HEADER.size}-byte header")
    _, quant_a, quant_b = COMPRESSED_DEPTH_HEADER.unpack_from(data)
    png = data[COMPRESSED_DEPTH_HEADER.size:]
    try:
        values = iio.imread(png, extension=".png")
    except (OSError, ValueError) as err:
        raise ValueError(f"compressedDepth PNG does not decode: {err}") from None
    if values.dtype != np.uint16 or values.ndim != 2:
        raise ValueError(f"compressedDepth PNG is {values.dtype} {list(values.shape)}, expected 16-bit single-channel")
    return png, values, quant_a, quant_b


def _depth_file(msg) -> tuple[str, bytes, tuple[int, int]]:
    """``(suffix, file bytes, (w, h))`` of a depth message; ValueError when it cannot be decoded."""
    encoding = _encoding(msg).partition(";")[0].strip()
    if hasattr(msg, "format"):  # compressedDepth: 16UC1's PNG is kept as recorded, 32FC1's decoded to metres
        png, values, quant_a, quant_b = _compressed_depth(msg)
        if encoding == "16UC1":
            return ".png", png, values.shape[::-1]
        with np.errstate(divide="ignore"):
            depth = np.where(values > 0, quant_a / (values.astype(np.float32) - np.float32(quant_b)), np.nan)
    elif encoding == "16UC1":
        depth = _raw_pixels(msg, 1, np.uint16)[:, :, 0]
        return ".png", iio.imwrite("<bytes>", depth, extension=".png"), (int(msg.width), int(msg.height))
    else:
        depth = _raw_pixels(msg, 1, np.float32)[:, :, 0]
    depth = depth.astype(np.float32)
    finite = np.isfinite(depth)
    if np.any(depth[finite] < 0):
        raise ValueError(f"negative depth (min {float(depth[finite].min()):.4g} m)")
    depth = np.where(finite, depth, np.float32(np.nan))  # REP 117's NaN, -inf (too near), +inf (too far): no depth
    buf = io.BytesIO()
    np.save(buf, depth, allow_pickle=False)
    return ".npy", buf.getvalue(), depth.shape[::-1]


def _match_depth(bag: _Bag, frames: list[_Image], depth: list[_Image], tolerance: float) -> None:
    stamps = np.asarray([d.stamp for d in depth], dtype=np.int64)
    limit = tolerance * 1e9
    unmatched = 0
    for frame in frames:
        i = int(np.searchsorted(stamps, frame.stamp))
        near = [j for j in (i - 1, i) if 0 <= j < len(depth)]
        j = min(near, key=lambda j: abs(int(stamps[j]) - frame.stamp))
        if abs(int(stamps[j]) - frame.stamp) <= limit:
            frame.depth = depth[j]
        else:
            unmatched += 1
    if unmatched:
        bag.notes.append(f"{unmatched} kept frame(s) without depth: no depth image within {tolerance:g} s")


def _check_depth_frame(bag: _Bag, tree: TransformTree, topic: str, depth_frame: str, camera_frame: str,
                       stamp: int) -> None:
    """A depth image in another frame than the colour one must be registered to it (same pose) at ``stamp``."""
    if depth_frame in ("", camera_frame):
        return
    if depth_frame not in tree.frames() or not tree.connected(depth_frame, camera_frame):
        bag.notes.append(f"depth frame {depth_frame!r} is not linked to the colour frame {camera_frame!r} by the "
                         "transforms: the depth is taken as registered to the colour camera")
        return
    t, _ = tree.lookup(camera_frame, depth_frame, stamp)
    if t is None:
        return
    offset = float(np.linalg.norm(t[:3, 3]))
    angle = math.degrees(math.acos(min(1.0, max(-1.0, (np.trace(t[:3, :3]) - 1) / 2))))
    if offset > REGISTERED_DEPTH_OFFSET or angle > REGISTERED_DEPTH_ANGLE:
        raise bag.error(f"depth is in frame {depth_frame!r}, {offset * 1000:.1f} mm and {angle:.2f} degrees from the "
                        f"colour frame {camera_frame!r}: the scene format needs depth registered to the colour camera "
                        "(record e.g. aligned_depth_to_color)", topic)


# ------------------------------------------------------------------------------------------------ import


@dataclass
class _Plan:
    colour_topic: str
    depth_topic: str | None
    camera: _Camera
    depth_camera: _Camera | None
    frames: list[_Image]  # kept, in capture order
    total: int  # colour images in the bag
    source: str  # where the poses came from
    fixed: str
    camera_frame: str


def _colour_camera(bag: _Bag, options: RosbagOptions, encodings: dict) -> tuple[str, list[_Image], str, str,
                                                                                  _Camera]:
    """The colour topic, its images (headers), the camera frame, the CameraInfo topic and its camera."""
    colour_topic = _colour_topic(bag, options, encodings)
    colour_type = bag.topics[colour_topic]
    if colour_type == IMAGE and encodings.get(colour_topic, "rgb8") not in COLOUR_ENCODINGS:
        raise bag.error(f"colour encoding {encodings[colour_topic]!r} is not supported "
                        f"({', '.join(COLOUR_ENCODINGS)})", colour_topic)
    colour = _headers(bag, colour_topic, encodings.get(colour_topic) if colour_type == IMAGE else None)
    frame_ids = sorted({image.frame_id for image in colour})
    if len(frame_ids) != 1 or not frame_ids[0]:
        raise bag.error(f"the images must name one camera frame in header.frame_id, got {frame_ids}", colour_topic)
    first = bag.first(colour_topic)
    size = (int(first.width), int(first.height)) if colour_type == IMAGE else None
    info_topic = _camera_info_topic(bag, colour_topic, frame_ids[0], options.camera_info, None, "--camera-info")
    if info_topic is None:
        raise bag.error(f"no sensor_msgs/CameraInfo topic for {colour_topic} (name one with --camera-info TOPIC)")
    return colour_topic, colour, frame_ids[0], info_topic, _camera(bag, info_topic, size)


def _depth_camera(bag: _Bag, plan: _Plan, tree: TransformTree, encoding: str, info_topic: str,
                  tolerance: float) -> None:
    """Match the depth images to the kept frames and find the depth camera (``plan.depth_camera``)."""
    depth = _headers(bag, plan.depth_topic, encoding)
    stamp = plan.frames[0].stamp if plan.frames else depth[0].stamp
    _check_depth_frame(bag, tree, plan.depth_topic, depth[0].frame_id, plan.camera_frame, stamp)
    depth_info = _camera_info_topic(bag, plan.depth_topic, depth[0].frame_id, None, info_topic, "--camera-info")
    if depth_info is not None:
        plan.depth_camera = _camera(bag, depth_info, None)
    _match_depth(bag, plan.frames, depth, tolerance)


def _plan(bag: _Bag, options: RosbagOptions) -> _Plan:
    encodings = _encodings(bag)
    colour_topic, colour, camera_frame, info_topic, camera = _colour_camera(bag, options, encodings)
    depth_topic = _depth_topic(bag, options, encodings, colour_topic)
    tree, source = _pose_tree(bag, options, camera_frame)
    fixed = (options.fixed_frame or tree.root(camera_frame)).lstrip("/")
    if fixed not in tree.frames() or not tree.connected(fixed, camera_frame):
        raise bag.error(f"no chain of transforms from the fixed frame {fixed!r} to the camera frame {camera_frame!r} "
                        f"(frames: {', '.join(sorted(tree.frames()))})")
    if tree.ignored:
        bag.notes.append(f"{tree.ignored} transform(s) ignored: non-finite values or a quaternion far from unit length")
    frames = _by_motion(bag, _pose_frames(bag, colour, tree, fixed, camera_frame), options)
    plan = _Plan(colour_topic, depth_topic, camera, None, frames, len(colour), source, fixed, camera_frame)
    if depth_topic is not None:
        _depth_camera(bag, plan, tree, encodings[depth_topic], info_topic, options.sync_tolerance)
    if not frames:
        raise bag.error(f"no usable frame: all {len(colour)} colour images of {colour_topic} are dropped "
                        f"({bag.skipped})")
    return plan


def _write(root: Path, name: str, data: bytes) -> None:
    (root / name).parent.mkdir(parents=True, exist_ok=True)
    (root / name).write_bytes(data)


def _write_colour(bag: _Bag, root: Path, plan: _Plan, order: dict[int, int]) -> dict[int, dict]:
    """The kept frames' colour files; their transforms.json entries by colour message index."""
    entries: dict[int, dict] = {}
    wanted = {frame.index: frame for frame in plan.frames}
    msgtype = bag.topics[plan.colour_topic]
    want_size = (plan.camera.keys["w"], plan.camera.keys["h"])
    for index, msg in bag.messages(plan.colour_topic):
        if index not in wanted:
            continue
        try:
            suffix, data = _colour_file(msg, msgtype)
        except ValueError as err:
            raise bag.error(f"message {index}: {writer.one_line(err)}", plan.colour_topic) from None
        name = f"images/frame_{order[index]:05d}{suffix}"
        _write(root, name, data)
        try:  # decoded as the scene loader will decode it (a compressed image is written as recorded)
            size = read_rgb(root / name).shape[1::-1]
        except SceneError as err:
            raise bag.error(f"message {index}: {err.message}", plan.colour_topic) from None
        if size != want_size:
            raise bag.error(f"message {index} is {size[0]}x{size[1]}, the CameraInfo {want_size[0]}x{want_size[1]}",
                            plan.colour_topic)
        entries[index] = {"file_path": name, "transform_matrix": writer.pose_list(wanted[index].c2w)}
    return entries


def _write_depth(bag: _Bag, root: Path, plan: _Plan, order: dict[int, int], entries: dict[int, dict]) -> None:
    """The matched depth files, named as their colour frames; ``depth_file_path`` added to ``entries``."""
    depth_of = {frame.depth.index: frame.index for frame in plan.frames if frame.depth is not None}
    for index, msg in bag.messages(plan.depth_topic):
        if index not in depth_of:
            continue
        try:
            suffix, data, size = _depth_file(msg)
        except ValueError as err:
            raise bag.error(f"message {index}: {writer.one_line(err)}", plan.depth_topic) from None
        _check_depth_size(bag, plan, size)
        colour_index = depth_of[index]
        name = f"depth/frame_{order[colour_index]:05d}{suffix}"
        _write(root, name, data)
        entries[colour_index]["depth_file_path"] = name


def _check_depth_size(bag: _Bag, plan: _Plan, size: tuple[int, int]) -> None:
    if plan.depth_camera is not None:
        want = (plan.depth_camera.keys["w"], plan.depth_camera.keys["h"])
        if size != want:
            raise bag.error(f"depth is {size[0]}x{size[1]}, its CameraInfo {want[0]}x{want[1]}", plan.depth_topic)
        return
    w, h = plan.camera.keys["w"], plan.camera.keys["h"]
    if size[0] * h != size[1] * w:
        raise bag.error(f"depth is {size[0]}x{size[1]}, colour {w}x{h}, and no CameraInfo for the depth camera "
                        "relates them", plan.depth_topic)


def _fill(root: Path, bag: _Bag, plan: _Plan, splits: PaperSplitRule | None) -> dict:
    order = {frame.index: n for n, frame in enumerate(plan.frames)}
    entries = _write_colour(bag, root, plan, order)
    if plan.depth_topic is not None:
        _write_depth(bag, root, plan, order, entries)
    meta: dict = dict(plan.camera.keys)
    depth_frames = sum("depth_file_path" in e for e in entries.values())
    if depth_frames:
        if any(e.get("depth_file_path", "").endswith(".png") for e in entries.values()):
            meta["depth_unit_scale_factor"] = DEPTH_UNIT_SCALE
        if plan.depth_camera is not None and plan.depth_camera.keys != plan.camera.keys:
            meta["depth_intrinsics"] = {k: plan.depth_camera.keys[k] for k in ("fl_x", "fl_y", "cx", "cy", "w", "h")}
            if plan.depth_camera.model != "PINHOLE":
                bag.notes.append(f"the depth camera's {plan.depth_camera.model} distortion is not applied "
                                 "(depth_intrinsics are pinhole)")
        bag.notes.append("no prior file: the engine fuses one from the training frames' depth maps")
    meta["frames"] = [entries[frame.index] for frame in plan.frames]
    split_summary = None
    if splits is not None:
        try:
            keys, split_summary = split_keys([f["file_path"] for f in meta["frames"]], splits)
        except SplitError as err:
            raise SceneError(bag.path, str(err), key="--splits paper") from None
        meta.update(keys)
    writer.write_transforms(root, meta)
    return {
        "format": "rosbag",
        "frames": len(plan.frames),
        "skipped": dict(bag.skipped),
        "camera_models": [plan.camera.model],
        "depth_frames": depth_frames,
        "prior": None,
        "splits": split_summary,
        "topics": {"rgb": plan.colour_topic, "depth": plan.depth_topic, "poses": plan.source},
        "fixed_frame": plan.fixed,
        "camera_frame": plan.camera_frame,
        "notes": bag.notes,
    }


def _open(path: Path):
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    if not path.exists():
        raise SceneError(path, "not found")
    try:
        # ROS 2 bags before format version 8 hold no message definitions: Humble's standard messages decode them
        reader = AnyReader([path], default_typestore=get_typestore(Stores.ROS2_HUMBLE))
        reader.open()
    except Exception as err:  # rosbags and its storage back-ends raise their own types for unreadable files
        raise SceneError(path, f"not a readable ROS 1 or ROS 2 bag: {writer.one_line(err)}") from None
    return reader


def import_rosbag(bag_path: str | Path, out: str | Path, splits: PaperSplitRule | None = None,
                  options: RosbagOptions | None = None) -> dict:
    """Write the ROS bag at ``bag_path`` (a ROS 1 ``.bag``, a ROS 2 bag folder, or its ``.db3`` / ``.mcap``) as a
    scene at ``out`` (absent or empty); returns the summary. Raises SceneError naming the bag (and topic) at
    fault; on any error nothing is left at ``out``."""
    bag_path, out = Path(bag_path), Path(out)
    options = options or RosbagOptions()
    options.check()
    writer.check_out_dir(out)
    reader = _open(bag_path)
    try:
        bag = _Bag(bag_path, reader, {topic: info.msgtype for topic, info in reader.topics.items()})
        plan = _plan(bag, options)
        bag.notes[:0] = [f"colour {plan.colour_topic}, depth {plan.depth_topic or 'none'}, poses from {plan.source} "
                         f"in frame {plan.fixed!r}; {len(plan.frames)} of {plan.total} colour images kept"]
        if "optical" not in plan.camera_frame:
            bag.notes.append(f"camera frame {plan.camera_frame!r} is taken as an optical frame (x right, y down, "
                             "z forward), as sensor_msgs defines header.frame_id")
        return writer.build_scene(out, lambda root: _fill(root, bag, plan, splits))
    finally:
        reader.close()

