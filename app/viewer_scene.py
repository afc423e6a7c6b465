"""What the viewer draws of a scene: its cameras and a sparse sample of its prior, read by the engine's own scene
rules (:func:`voxnerf.data.scene.load_scene`) in a child process, since that module imports torch and the API process
must not.

:func:`read_scene_view` runs :func:`scene_view` in a child of the multiprocessing *forkserver* that
:mod:`app.uploads.sandbox` set up (its preload holds ``voxnerf.data.scene``, so a child starts in milliseconds) and
waits at most ``timeout_s`` for its answer. A stored scene was validated at upload and never changes, so the
answer can be cached by scene id (:class:`SceneViewCache`).
"""

from __future__ import annotations

import multiprocessing
import threading
from collections import OrderedDict
from multiprocessing.connection import Connection, wait
from pathlib import Path

import numpy as np

PREVIEW_POINTS = 4000  # prior points sent to the viewer: enough to show the room, small as JSON
PREVIEW_SEED = 0  # the same scene gives the same sample
REAP_TIMEOUT_S = 10.0
_CONTEXT = multiprocessing.get_context("forkserver")


class SceneViewError(Exception):
    """The scene could not be read (the API answers 503 with this message; a stored scene was valid)."""


def scene_view(scene_root: Path, fallback_prior: Path | None, max_points: int = PREVIEW_POINTS) -> dict:
    """The cameras and prior sample of the scene at ``scene_root`` (runs where torch may be imported).

    Returns ``{"frames": [...], "depth_unit_scale", "metric", "prior": {...} | None}``; each frame is
    ``{"index", "name", "splits", "transform_matrix" (4x4 camera-to-world, OpenGL axes, scene units),
    "fl_x", "fl_y", "cx", "cy", "width", "height" (pixels, the undistorted view)}``. The prior is the scene's
    prior file, else ``fallback_prior`` (a run's fused prior) when it exists: ``{"points": [N*3] scene units,
    "colors": [N*3] in [0, 1] or None, "total": points in the file}``. ``metric``: the scene carries sensor
    depth maps, which are metres (``depth_unit_scale_factor`` metres per unit), so its poses are in metres.
    """
    from voxnerf.data.scene import load_scene  # preloaded by the forkserver: no import happens here

    scene = load_scene(scene_root, load_images=False)
    splits_of: dict[int, list[str]] = {}
    for name, indices in scene.splits.items():
        for index in indices:
            splits_of.setdefault(index, []).append(name)
    frames = [_frame_json(i, frame, splits_of.get(i, [])) for i, frame in enumerate(scene.frames)]
    prior_path = scene.prior_path
    if prior_path is None and fallback_prior is not None and fallback_prior.is_file():
        prior_path = fallback_prior
    return {
        "frames": frames,
        "depth_unit_scale": scene.depth_unit_scale,
        "metric": any(frame.depth_path is not None for frame in scene.frames),
        "prior": None if prior_path is None else prior_sample(prior_path, max_points),
    }


def _frame_json(index: int, frame, splits: list[str]) -> dict:
    intr = frame.intrinsics
    return {
        "index": index,
        "name": frame.file_path,
        "splits": splits,
        "transform_matrix": np.asarray(frame.c2w, dtype=np.float64).tolist(),
        "fl_x": intr.fl_x, "fl_y": intr.fl_y, "cx": intr.cx, "cy": intr.cy,
        "width": intr.width, "height": intr.height,
        "image_path": str(frame.image_path),
    }


def prior_sample(path: Path, max_points: int) -> dict:
    """At most ``max_points`` vertices of the geometry file ``path`` (a point cloud or a mesh), picked at random
    with a fixed seed, as flat lists: ``points`` [N*3] float (scene units), ``colors`` [N*3] in [0, 1] or None."""
    import trimesh

    loaded = trimesh.load(path, process=False)
    parts = loaded.dump() if isinstance(loaded, trimesh.Scene) else [loaded]
    points, colors = [], []
    for part in parts:
        vertices = np.asarray(getattr(part, "vertices", np.zeros((0, 3))), dtype=np.float64).reshape(-1, 3)
        points.append(vertices)
        colors.append(_vertex_colors(part, len(vertices)))
    xyz = np.concatenate(points) if points else np.zeros((0, 3))
    rgb = None if any(c is None for c in colors) or not colors else np.concatenate(colors)
    keep = np.isfinite(xyz).all(axis=1)
    xyz, rgb = xyz[keep], None if rgb is None else rgb[keep]
    total = len(xyz)
    if total > max_points:
        pick = np.sort(np.random.default_rng(PREVIEW_SEED).choice(total, max_points, replace=False))
        xyz, rgb = xyz[pick], None if rgb is None else rgb[pick]
    return {
        "points": np.round(xyz, 4).reshape(-1).tolist(),
        "colors": None if rgb is None else np.round(rgb, 3).reshape(-1).tolist(),
        "total": total,
    }


def _vertex_colors(geometry, count: int) -> np.ndarray | None:
    """Per-vertex RGB in [0, 1] [count, 3], or None when the file has none."""
    source = getattr(geometry, "colors", None)
    visual = getattr(geometry, "visual", None)
    if (source is None or len(source) == 0) and visual is not None and getattr(visual, "kind", None) == "vertex":
        source = visual.vertex_colors
    if source is None or len(source) != count:
        return None
    return np.asarray(source, dtype=np.float64)[:, :3] / 255.0


# ------------------------------------------------------------------------------------------------ the child


def _child_main(scene_root: Path, fallback_prior: Path | None, sender: Connection) -> None:
    try:
        outcome: tuple = ("ok", scene_view(scene_root, fallback_prior))
    except Exception as err:  # a scene that was valid at upload: the store or the disk changed under it
        outcome = ("error", f"{type(err).__name__}: {err}")
    sender.send(outcome)
    sender.close()


def read_scene_view(scene_root: Path, fallback_prior: Path | None, timeout_s: float) -> dict:
    """:func:`scene_view` computed in a forkserver child; SceneViewError when it fails, dies or times out."""
    receiver, sender = _CONTEXT.Pipe(duplex=False)
    child = _CONTEXT.Process(target=_child_main, args=(scene_root, fallback_prior, sender),
                             name="voxnerf-scene-view", daemon=True)
    child.start()
    sender.close()  # the child holds the only sending end: its death reads as EOF here
    try:
        outcome = None
        if wait([receiver, child.sentinel], timeout_s):
            try:
                outcome = receiver.recv()
            except EOFError:
                outcome = None
    finally:
        receiver.close()
        if child.is_alive():
            child.kill()
        child.join(REAP_TIMEOUT_S)
    if outcome is None:
        raise SceneViewError(f"reading the scene's cameras gave no answer within {timeout_s:g} s")
    if outcome[0] != "ok":
        raise SceneViewError(f"the scene's cameras cannot be read: {outcome[1]}")
    return outcome[1]


class SceneViewCache:
    """The last ``size`` scenes' views by scene id (a stored scene never changes); safe across threads."""

    def __init__(self, size: int = 16) -> None:
        self.size = size
        self._views: OrderedDict[str, dict] = OrderedDict()
        self._lock = threading.Lock()

    def get(self, scene_id: str) -> dict | None:
        with self._lock:
            view = self._views.get(scene_id)
            if view is not None:
                self._views.move_to_end(scene_id)
            return view

    def put(self, scene_id: str, view: dict) -> None:
        with self._lock:
            self._views[scene_id] = view
            self._views.move_to_end(scene_id)
            while len(self._views) > self.size:
                self._views.popitem(last=False)
