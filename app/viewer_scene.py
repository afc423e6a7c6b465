"""What the viewer draws of a scene: its cameras and a sparse sample of its prior, read by the engine's own scene
rules (:func:`voxnerf.data.scene.load_scene`) in a child process, since that module imports torch and the API process
must not.

:func:`read_in_child` runs :func:`scene_view` (or :func:`prior_sample` of a run's fused prior) in a child of the
multiprocessing *forkserver* that :mod:`app.uploads.sandbox` set up (its preload holds ``voxnerf.data.scene``, so a
child starts in milliseconds) and waits at most ``timeout_s`` for its answer. The child has the limits of an
upload's validation (:func:`app.uploads.sandbox.limit_child`). A stored scene was validated at upload and never
changes, so its view is cached by scene id, and :class:`SceneReads` bounds the reads: at most
``max_concurrent_scene_reads`` children at once (more: 429), one read per scene shared by the requests that come
while it runs.
"""

from __future__ import annotations

import multiprocessing
import threading
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass, field
from multiprocessing.connection import Connection, wait
from pathlib import Path

import numpy as np

from app.core.settings import Settings
from app.uploads.sandbox import limit_child

PREVIEW_POINTS = 4000  # prior points sent to the viewer: enough to show the room, small as JSON
PREVIEW_SEED = 0  # the same scene gives the same sample
REAP_TIMEOUT_S = 10.0
_CONTEXT = multiprocessing.get_context("forkserver")


class SceneViewError(Exception):
    """The scene could not be read (the API answers 503 with this message; a stored scene was valid)."""


def scene_view(scene_root: Path, max_points: int = PREVIEW_POINTS) -> dict:
    """The cameras and prior sample of the scene at ``scene_root`` (runs where torch may be imported).

    Returns ``{"frames": [...], "depth_unit_scale", "metric", "prior": {...} | None}``; each frame is
    ``{"index", "name", "splits", "transform_matrix" (4x4 camera-to-world, OpenGL axes, scene units),
    "fl_x", "fl_y", "cx", "cy", "width", "height" (pixels, the undistorted view)}``. The prior is a sample of
    the scene's prior file (:func:`prior_sample`), None when it has none. ``metric``: the scene carries sensor
    depth maps, which are metres (``depth_unit_scale_factor`` metres per unit), so its poses are in metres.
    """
    from voxnerf.data.scene import load_scene  # preloaded by the forkserver: no import happens here

    scene = load_scene(scene_root, load_images=False)
    splits_of: dict[int, list[str]] = {}
    for name, indices in scene.splits.items():
        for index in indices:
            splits_of.setdefault(index, []).append(name)
    frames = [_frame_json(i, frame, splits_of.get(i, [])) for i, frame in enumerate(scene.frames)]
    return {
        "frames": frames,
        "depth_unit_scale": scene.depth_unit_scale,
        "metric": any(frame.depth_path is not None for frame in scene.frames),
        "prior": None if scene.prior_path is None else prior_sample(scene.prior_path, max_points),
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


def prior_sample(path: Path, max_points: int = PREVIEW_POINTS) -> dict:
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


def _child_main(read: Callable[..., dict], args: tuple, memory_bytes: int, timeout_s: float,
                sender: Connection) -> None:
    limit_child(memory_bytes, timeout_s)  # an upload's validation's limits: a stored scene passed them once
    try:
        outcome: tuple = ("ok", read(*args))
    except MemoryError:
        outcome = ("error", f"reading it needs more than {memory_bytes // 2**20} MiB of memory "
                            "(VOXNERF_UPLOAD_VALIDATION_MEMORY_BYTES)")
    except Exception as err:  # a scene that was valid at upload: the store or the disk changed under it
        outcome = ("error", f"{type(err).__name__}: {err}")
    try:
        sender.send(outcome)
    except MemoryError:  # the answer itself did not fit
        sender.send(("error", f"its answer needs more than {memory_bytes // 2**20} MiB of memory "
                              "(VOXNERF_UPLOAD_VALIDATION_MEMORY_BYTES)"))
    sender.close()


def read_in_child(read: Callable[..., dict], args: tuple, settings: Settings, timeout_s: float) -> dict:
    """``read(*args)`` (:func:`scene_view` or :func:`prior_sample`) computed in a forkserver child under the
    limits of an upload's validation (:func:`app.uploads.sandbox.limit_child`: ``upload_validation_memory_bytes``
    of address space, CPU time); SceneViewError when it fails, dies or gives no answer within ``timeout_s``."""
    receiver, sender = _CONTEXT.Pipe(duplex=False)
    child = _CONTEXT.Process(target=_child_main, name="voxnerf-scene-view", daemon=True,
                             args=(read, args, settings.upload_validation_memory_bytes, timeout_s, sender))
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
        raise SceneViewError(f"reading the scene gave no answer within {timeout_s:g} s")
    if outcome[0] != "ok":
        raise SceneViewError(f"the scene cannot be read: {outcome[1]}")
    return outcome[1]


# ------------------------------------------------------------------------------------------------ sharing


class SceneReadsBusy(Exception):
    """Every slot for scene reads is taken (the API answers 429 with Retry-After)."""


@dataclass
class _Read:
    """One read in progress: the requests for its key wait on ``done``, then share ``view`` or ``error``."""

    done: threading.Event = field(default_factory=threading.Event)
    view: dict | None = None
    error: Exception | None = None


class SceneReads:
    """The viewer's reads of stored scenes, bounded and shared; safe across threads.

    A view is cached by its key (a scene id, or a run's fused prior: a stored scene never changes), the last
    ``size`` of them. A key that is neither cached nor being read starts one read (:func:`read_in_child`) if one
    of ``slots`` is free, else :class:`SceneReadsBusy`; every request for a key being read waits for that read
    and shares its answer or its error (an error is not cached). So at most ``slots`` children run at once,
    whatever the number of requests, and one scene is read once.
    """

    def __init__(self, slots: int, size: int = 16) -> None:
        self.slots = slots
        self.size = size
        self._views: OrderedDict[str, dict] = OrderedDict()
        self._reads: dict[str, _Read] = {}
        self._lock = threading.Lock()

    def get(self, key: str, read: Callable[[], dict]) -> dict:
        """The view of ``key``: cached, shared with the read in progress, or ``read()`` now (in a free slot)."""
        with self._lock:
            view = self._views.get(key)
            if view is not None:
                self._views.move_to_end(key)
                return view
            current = self._reads.get(key)
            leader = current is None
            if leader:
                if len(self._reads) >= self.slots:
                    raise SceneReadsBusy(f"{self.slots} scene reads are already in progress on this API process")
                current = self._reads[key] = _Read()
        if not leader:
            current.done.wait()
            if current.error is not None:
                raise current.error
            return current.view
        try:
            current.view = read()
        except Exception as err:
            current.error = err
            raise
        finally:
            with self._lock:
                del self._reads[key]
                if current.view is not None:
                    self._views[key] = current.view
                    while len(self._views) > self.size:
                        self._views.popitem(last=False)
            current.done.set()
        return current.view
