"""ROS coordinate frames for the bag importer: a tree of transforms from ``/tf`` and ``/tf_static`` (or a pose
topic), looked up between any two of its frames at a time stamp, as tf2 does. numpy only.

Conventions (ROS's): a transform published with ``header.frame_id = parent`` and ``child_frame_id = child`` is
the child's pose in the parent frame, i.e. ``T_parent_child`` maps child coordinates to parent coordinates.
Quaternions are ``(x, y, z, w)``, Hamilton, normalised here. A dynamic edge is interpolated at a stamp between
its two neighbouring samples: translation linearly, rotation by slerp; a stamp equal to a sample takes it
exactly, and a stamp before the first or after the last sample has no transform (tf2 does not extrapolate
either). Stamps are integer nanoseconds.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

QUATERNION_NORM_TOLERANCE = 1e-2
"""A quaternion whose norm is further than this from 1 is taken as corrupt, not as rounding in the log."""


class TransformTreeError(ValueError):
    """The transforms contradict each other (a frame with two parents, a loop)."""


def quaternion_matrix(q: np.ndarray) -> np.ndarray:
    """The 3x3 rotation of a unit quaternion ``(x, y, z, w)``."""
    x, y, z, w = q
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])


def matrix_quaternion(rot: np.ndarray) -> np.ndarray:
    """A unit quaternion ``(x, y, z, w)`` (w >= 0) of a 3x3 rotation (Shepperd's method, stable for any angle)."""
    m = np.asarray(rot, dtype=np.float64)
    trace = np.trace(m)
    if trace > 0:
        s = 2.0 * np.sqrt(1.0 + trace)
        q = [(m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s, 0.25 * s]
    elif m[0, 0] > m[1, 1] and m[0, 0] > m[2, 2]:
        s = 2.0 * np.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2])
        q = [0.25 * s, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s, (m[2, 1] - m[1, 2]) / s]
    elif m[1, 1] > m[2, 2]:
        s = 2.0 * np.sqrt(1.0 + m[1, 1] - m[0, 0] - m[2, 2])
        q = [(m[0, 1] + m[1, 0]) / s, 0.25 * s, (m[1, 2] + m[2, 1]) / s, (m[0, 2] - m[2, 0]) / s]
    else:
        s = 2.0 * np.sqrt(1.0 + m[2, 2] - m[0, 0] - m[1, 1])
        q = [(m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, 0.25 * s, (m[1, 0] - m[0, 1]) / s]
    q = np.array(q)
    return -q if q[3] < 0 else q


def slerp(q0: np.ndarray, q1: np.ndarray, s: float) -> np.ndarray:
    """Spherical linear interpolation of unit quaternions, ``s`` in [0, 1], along the shorter arc."""
    dot = float(np.dot(q0, q1))
    if dot < 0:
        q1, dot = -q1, -dot
    if dot > 0.9995:  # nearly the same rotation: the linear blend, renormalised, is exact to rounding
        q = q0 + s * (q1 - q0)
        return q / np.linalg.norm(q)
    theta = np.arccos(min(dot, 1.0))
    return (np.sin((1 - s) * theta) * q0 + np.sin(s * theta) * q1) / np.sin(theta)


def rigid(translation: np.ndarray, quaternion: np.ndarray) -> np.ndarray:
    """The 4x4 transform of a translation and a unit quaternion ``(x, y, z, w)``."""
    t = np.eye(4)
    t[:3, :3] = quaternion_matrix(quaternion)
    t[:3, 3] = translation
    return t


def unit_quaternion(values) -> np.ndarray | None:
    """``values`` (x, y, z, w) normalised, or None when non-finite or too far from unit length to be rounding."""
    q = np.asarray(values, dtype=np.float64)
    norm = float(np.linalg.norm(q)) if np.isfinite(q).all() else float("nan")
    if not np.isfinite(norm) or abs(norm - 1.0) > QUATERNION_NORM_TOLERANCE:
        return None
    return q / norm


@dataclass
class _Edge:
    """The samples of one parent -> child transform: one for a static edge, a time series for a dynamic one."""

    parent: str
    static: bool
    stamps: list[int] = field(default_factory=list)
    translations: list[np.ndarray] = field(default_factory=list)
    quaternions: list[np.ndarray] = field(default_factory=list)

    def sorted(self) -> None:
        order = np.argsort(np.asarray(self.stamps, dtype=np.int64), kind="stable")
        self.stamps = [self.stamps[i] for i in order]
        self.translations = [self.translations[i] for i in order]
        self.quaternions = [self.quaternions[i] for i in order]

    def at(self, stamp: int) -> np.ndarray | None:
        """``T_parent_child`` at ``stamp``, or None outside the samples of a dynamic edge."""
        if self.static:
            return rigid(self.translations[-1], self.quaternions[-1])
        stamps = self.stamps
        if not stamps or stamp < stamps[0] or stamp > stamps[-1]:
            return None
        i = int(np.searchsorted(np.asarray(stamps, dtype=np.int64), stamp, side="left"))
        if stamps[i] == stamp:
            return rigid(self.translations[i], self.quaternions[i])
        s = (stamp - stamps[i - 1]) / (stamps[i] - stamps[i - 1])
        translation = (1 - s) * self.translations[i - 1] + s * self.translations[i]
        return rigid(translation, slerp(self.quaternions[i - 1], self.quaternions[i], s))


@dataclass
class TransformTree:
    """Frames linked parent -> child by static or dynamic transforms; each frame has at most one parent."""

    edges: dict[str, _Edge] = field(default_factory=dict)  # child -> its edge to its parent
    ignored: int = 0  # transforms dropped for non-finite values or a quaternion far from unit length

    def add(self, parent: str, child: str, stamp: int, translation, quaternion, static: bool) -> None:
        """One transform sample; TransformTreeError when ``child`` already has another parent."""
        parent, child = parent.lstrip("/"), child.lstrip("/")  # tf2 ignores a leading slash
        q = unit_quaternion(quaternion)
        t = np.asarray(translation, dtype=np.float64)
        if q is None or not np.isfinite(t).all():
            self.ignored += 1
            return
        edge = self.edges.get(child)
        if edge is None:
            edge = self.edges[child] = _Edge(parent, static)
        elif edge.parent != parent:
            raise TransformTreeError(f"frame {child!r} has two parents, {edge.parent!r} and {parent!r}")
        elif edge.static != static:
            raise TransformTreeError(f"frame {child!r} is published both as static and as dynamic")
        edge.stamps.append(int(stamp))
        edge.translations.append(t)
        edge.quaternions.append(q)

    def finish(self) -> None:
        """Sort every dynamic edge's samples by stamp, and check that the frames form no loop (call after the
        last :meth:`add`, before any lookup); TransformTreeError on a loop."""
        for edge in self.edges.values():
            if not edge.static:
                edge.sorted()
        for frame in self.edges:
            self.ancestors(frame)

    def frames(self) -> set[str]:
        return set(self.edges) | {edge.parent for edge in self.edges.values()}

    def ancestors(self, frame: str) -> list[str]:
        """``frame``, its parent, its parent's parent... up to its root; TransformTreeError on a loop."""
        chain = [frame.lstrip("/")]
        while chain[-1] in self.edges:
            parent = self.edges[chain[-1]].parent
            if parent in chain:
                raise TransformTreeError(f"the transforms loop: {' -> '.join([*chain, parent])}")
            chain.append(parent)
        return chain

    def root(self, frame: str) -> str:
        return self.ancestors(frame)[-1]

    def connected(self, a: str, b: str) -> bool:
        return self.root(a) == self.root(b)

    def lookup(self, target: str, source: str, stamp: int) -> tuple[np.ndarray | None, str | None]:
        """``T_target_source`` (source coordinates -> target coordinates) at ``stamp``; or None and the first
        edge without a transform at that stamp, as ``"parent -> child"``. The frames must be connected."""
        up_source, up_target = self.ancestors(source), self.ancestors(target)
        common = next(f for f in up_source if f in set(up_target))
        root_source, missing = self._down(up_source[: up_source.index(common)], stamp)
        if missing is not None:
            return None, missing
        root_target, missing = self._down(up_target[: up_target.index(common)], stamp)
        if missing is not None:
            return None, missing
        return np.linalg.inv(root_target) @ root_source, None

    def _down(self, chain: list[str], stamp: int) -> tuple[np.ndarray, str | None]:
        """``T_ancestor_frame`` for ``chain`` = [frame, parent, ..., the child of the ancestor]."""
        t = np.eye(4)
        for child in chain:
            edge = self.edges[child]
            step = edge.at(stamp)
            if step is None:
                return t, f"{edge.parent} -> {child}"
            t = step @ t
        return t, None

