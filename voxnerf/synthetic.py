"""Synthetic indoor test scene: a textured, furnished room ray-cast on the CPU, written as SCENE_FORMAT.md.

World frame: metres, +Z up, the room spans ``x in [-W/2, W/2]``, ``y in [-D/2, D/2]``, ``z in [0, H]``.
Cameras are camera-to-world in the OpenGL / nerfstudio convention (camera looks along -Z, +Y up, +X right).

The room is built from trimesh primitives (boxes, cylinders) placed deterministically from a seed, each
object with a procedural solid texture evaluated at the 3D hit point (no UVs). Images are Lambertian:
ambient light plus two point lights with shadow rays, supersampled, written as 8-bit sRGB PNGs. Splits mimic
the real redkitchen scene (``shared/data/README.md``): every ``train_every``-th frame trains except inside
``n_gaps`` gaps; interpolation frames lie midway between training frames, extrapolation frames in the gaps.
"""

from __future__ import annotations

import itertools
import json
import math
import os
import shutil
import tempfile
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass
from functools import cached_property
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import open3d as o3d
import trimesh

ROOM_SIZE: tuple[float, float, float] = (5.0, 4.0, 2.6)
"""Room width (x), depth (y) and height (z) in metres."""

HORIZONTAL_FOV_DEG = 65.0
DEPTH_UNIT_SCALE = 0.001
"""Metres per unit of the 16-bit depth PNGs (millimetres)."""

PRIOR_KINDS = ("points", "mesh", "none")
PRIOR_OUTLIER_FRACTION = 0.02
PRIOR_HOLES = 2
PRIOR_HOLE_RADIUS = (0.3, 0.45)
"""Metres: the radius range of the spherical regions removed from a point-cloud prior."""
PRIOR_MESH_MAX_EDGE = 0.08
"""Metres: the true mesh is subdivided to this edge length before its vertices are displaced."""


# --------------------------------------------------------------------------------------------- materials


@dataclass(frozen=True)
class Material:
    """A procedural, view-independent (Lambertian) solid texture.

    ``pattern`` names a function of the 3D hit point (see ``_PATTERNS``); ``base`` and ``accent`` are linear
    RGB albedos in [0, 1]; ``scale`` is the pattern's period in metres; ``emission`` adds unshaded radiance
    (``emission * albedo``) for light-emitting surfaces such as the window's view.
    """

    pattern: str
    base: tuple[float, float, float]
    accent: tuple[float, float, float]
    scale: float
    emission: float = 0.0


_LATTICE_SIZE = 64
_LATTICE = np.random.default_rng(20240611).random((_LATTICE_SIZE,) * 3)
"""Fixed random values on a periodic 64^3 integer lattice; seeds select different offsets into it."""


def _seed_offset(seed: int) -> np.ndarray:
    """Integer lattice offset [3] for ``seed``, so different seeds see different parts of ``_LATTICE``."""
    mixed = (seed * 0x9E3779B97F4A7C15 + 0x632BE59BD9B4E019) & 0xFFFFFFFFFFFFFFFF
    return np.array([(mixed >> shift) % _LATTICE_SIZE for shift in (0, 21, 42)], np.int64)


def _lattice(ix: np.ndarray, iy: np.ndarray, iz: np.ndarray, seed: int) -> np.ndarray:
    """Deterministic pseudo-random value in [0, 1) per integer lattice point: int64 [N] x3 -> float64 [N]."""
    off = _seed_offset(seed)
    m = _LATTICE_SIZE - 1
    return _LATTICE[(ix + off[0]) & m, (iy + off[1]) & m, (iz + off[2]) & m]


def _value_noise(p: np.ndarray, seed: int) -> np.ndarray:
    """Smooth 3D value noise in [0, 1] with unit lattice spacing (period 64): [N, 3] -> [N]."""
    base = np.floor(p)
    f = p - base
    u = f * f * (3.0 - 2.0 * f)
    i = base.astype(np.int64) + _seed_offset(seed)
    m, size = _LATTICE_SIZE - 1, _LATTICE_SIZE
    flat = _LATTICE.ravel()
    xs = [((i[:, 0] + d) & m) * size * size for d in (0, 1)]
    ys = [((i[:, 1] + d) & m) * size for d in (0, 1)]
    zs = [(i[:, 2] + d) & m for d in (0, 1)]

    def along_z(x: np.ndarray, y: np.ndarray) -> np.ndarray:
        xy = x + y
        lo = flat[xy + zs[0]]
        return lo + (flat[xy + zs[1]] - lo) * u[:, 2]

    def along_yz(x: np.ndarray) -> np.ndarray:
        lo = along_z(x, ys[0])
        return lo + (along_z(x, ys[1]) - lo) * u[:, 1]

    lo = along_yz(xs[0])
    return lo + (along_yz(xs[1]) - lo) * u[:, 0]


def _fbm(p: np.ndarray, seed: int, octaves: int = 4) -> np.ndarray:
    """Fractal (multi-octave) value noise in [0, 1]: [N, 3] -> [N]."""
    total, norm, amp = np.zeros(len(p)), 0.0, 1.0
    for k in range(octaves):
        total += amp * _value_noise(p * (2.0**k), seed + 101 * k)
        norm += amp
        amp *= 0.5
    return total / norm


def _mix(a: tuple[float, float, float], b: tuple[float, float, float], t: np.ndarray) -> np.ndarray:
    """Linear blend of two colours by ``t`` [N] in [0, 1] -> [N, 3]."""
    t = np.clip(t, 0.0, 1.0)[:, None]
    return np.asarray(a)[None] * (1.0 - t) + np.asarray(b)[None] * t


def _plane_axes(n: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two in-plane world axes per point (the axes other than the normal's dominant one): [N] each."""
    dominant = np.argmax(np.abs(n), axis=1)
    first = np.where(dominant == 0, 1, 0)
    second = np.where(dominant == 2, 1, 2)
    return first, second


def _planks(p: np.ndarray, n: np.ndarray, m: Material, seed: int) -> np.ndarray:
    """Floor boards along x, ``scale`` wide, with grain, per-board tint and dark seams."""
    row = np.floor(p[:, 1] / m.scale)
    plank_len = 6.0 * m.scale
    shift = _lattice(row.astype(np.int64), np.zeros_like(row, np.int64), np.zeros_like(row, np.int64), seed)
    along = (p[:, 0] + shift * plank_len) / plank_len
    col = np.floor(along)
    tint = 0.8 + 0.4 * _lattice(row.astype(np.int64), col.astype(np.int64), np.ones_like(row, np.int64), seed)
    warp = _fbm(p * np.array([0.6, 12.0, 12.0]), seed + 1)
    grain = 0.5 + 0.5 * np.sin(2 * np.pi * (p[:, 1] / m.scale * 5.0 + 2.5 * warp))
    colour = _mix(m.base, m.accent, grain**2) * tint[:, None]
    seam = (p[:, 1] / m.scale - row < 0.05) | (along - col < 0.012)
    colour[seam] *= 0.3
    return colour


def _wood(p: np.ndarray, n: np.ndarray, m: Material, seed: int) -> np.ndarray:
    """Wood grain: warped stripes across x with fine fibre noise."""
    warp = _fbm(p / m.scale * np.array([0.3, 2.0, 2.0]), seed)
    rings = 0.5 + 0.5 * np.sin(2 * np.pi * ((p[:, 1] + 0.5 * p[:, 2]) / m.scale + 3.0 * warp))
    fibre = _value_noise(p * np.array([8.0, 160.0, 160.0]), seed + 7)
    return _mix(m.base, m.accent, rings**3 * 0.8 + 0.2 * fibre)


def _tiles(p: np.ndarray, n: np.ndarray, m: Material, seed: int) -> np.ndarray:
    """Square tiles of side ``scale`` in a two-colour checker with per-tile tint and light grout."""
    a, b = _plane_axes(n)
    idx = np.arange(len(p))
    ua, ub = p[idx, a] / m.scale, p[idx, b] / m.scale
    ca, cb = np.floor(ua), np.floor(ub)
    checker = (ca + cb) % 2
    tint = 0.85 + 0.3 * _lattice(ca.astype(np.int64), cb.astype(np.int64), a.astype(np.int64), seed)
    colour = _mix(m.base, m.accent, checker) * tint[:, None]
    grout = np.minimum(np.minimum(ua - ca, 1 - (ua - ca)), np.minimum(ub - cb, 1 - (ub - cb))) < 0.04
    colour[grout] = 0.75
    return colour


def _plaster(p: np.ndarray, n: np.ndarray, m: Material, seed: int) -> np.ndarray:
    """Painted plaster: a vertical gradient toward ``accent`` with blotchy low-frequency noise."""
    blotch = _fbm(p / m.scale, seed)
    colour = _mix(m.base, m.accent, p[:, 2] / ROOM_SIZE[2])
    return colour * (0.75 + 0.45 * blotch)[:, None]


def _fabric(p: np.ndarray, n: np.ndarray, m: Material, seed: int) -> np.ndarray:
    """Plaid upholstery: broad crossing stripes of period ``scale`` over a fine weave."""
    a, b = _plane_axes(n)
    idx = np.arange(len(p))
    ua, ub = p[idx, a] / m.scale, p[idx, b] / m.scale
    stripes = np.maximum(np.sin(2 * np.pi * ua), 0) ** 4 + np.maximum(np.sin(2 * np.pi * ub), 0) ** 4
    weave = 0.9 + 0.1 * np.sign(np.sin(2 * np.pi * ua * 12) * np.sin(2 * np.pi * ub * 12))
    return _mix(m.base, m.accent, 0.6 * stripes) * weave[:, None]


def _marble(p: np.ndarray, n: np.ndarray, m: Material, seed: int) -> np.ndarray:
    """Marble: dark veins along a turbulent sine of the summed coordinates."""
    turbulence = _fbm(p / m.scale * 2.0, seed, octaves=5)
    veins = np.abs(np.sin(np.pi * (p.sum(axis=1) / m.scale + 6.0 * turbulence)))
    return _mix(m.accent, m.base, veins**0.35)


def _painting(p: np.ndarray, n: np.ndarray, m: Material, seed: int) -> np.ndarray:
    """A colourful abstract picture: interfering waves per colour channel, quantised into bands."""
    a, b = _plane_axes(n)
    idx = np.arange(len(p))
    ua, ub = p[idx, a] / m.scale, p[idx, b] / m.scale
    phase = 6.0 * _fbm(np.stack([ua, ub, np.zeros_like(ua)], axis=1), seed, octaves=3)
    channels = [
        0.5 + 0.5 * np.sin(2 * np.pi * (1.3 * ua + 0.4 * ub) + phase),
        0.5 + 0.5 * np.sin(2 * np.pi * (0.5 * ua - 1.1 * ub) + 1.7 * phase),
        0.5 + 0.5 * np.sin(2 * np.pi * np.hypot(ua - 2.0, ub - 1.5) + 2.0),
    ]
    bands = np.floor(np.stack(channels, axis=1) * 4.0) / 4.0
    return 0.1 + 0.85 * bands * np.asarray(m.base)[None]


def _plain(p: np.ndarray, n: np.ndarray, m: Material, seed: int) -> np.ndarray:
    """Nearly uniform colour with faint mottling toward ``accent``."""
    return _mix(m.base, m.accent, 0.35 * _fbm(p / m.scale, seed, octaves=3))


def _sky(p: np.ndarray, n: np.ndarray, m: Material, seed: int) -> np.ndarray:
    """The view through the window: a vertical gradient with soft clouds."""
    height = np.clip((p[:, 2] - 0.9) / 1.1, 0.0, 1.0)
    clouds = np.clip(2.0 * _fbm(p / m.scale, seed) - 0.9, 0.0, 1.0)
    return _mix(m.accent, m.base, height) * (1 - clouds[:, None]) + 0.95 * clouds[:, None]


_PATTERNS: dict[str, Callable[[np.ndarray, np.ndarray, Material, int], np.ndarray]] = {
    "planks": _planks,
    "wood": _wood,
    "tiles": _tiles,
    "plaster": _plaster,
    "fabric": _fabric,
    "marble": _marble,
    "painting": _painting,
    "plain": _plain,
    "sky": _sky,
}


# ---------------------------------------------------------------------------------------------- geometry


@dataclass(frozen=True)
class RoomObject:
    """One named object of the room: its material and axis-aligned bounds ``[[min xyz], [max xyz]]`` (m)."""

    name: str
    material: Material
    bounds: tuple[tuple[float, float, float], tuple[float, float, float]]


@dataclass(frozen=True)
class PointLight:
    """An isotropic point light: position (m), linear RGB intensity (falls off with distance)."""

    position: tuple[float, float, float]
    intensity: tuple[float, float, float]


@dataclass
class RoomGeometry:
    """The room as one triangle soup with per-triangle object ids.

    ``vertices`` float64 [V, 3] metres, ``triangles`` int32 [T, 3], ``triangle_object`` int32 [T] indexing
    ``objects``. Surfaces are rendered two-sided, so triangle winding only matters for exported meshes
    (outward for furniture, inward for the room shell).
    """

    vertices: np.ndarray
    triangles: np.ndarray
    triangle_object: np.ndarray
    objects: list[RoomObject]
    lights: list[PointLight]
    seed: int
    room_size: tuple[float, float, float] = ROOM_SIZE

    def object_named(self, name: str) -> RoomObject:
        """The object called ``name`` (KeyError listing the names when absent)."""
        for obj in self.objects:
            if obj.name == name:
                return obj
        raise KeyError(f"no object {name!r}; objects: {[o.name for o in self.objects]}")

    def to_trimesh(self) -> trimesh.Trimesh:
        """The ground-truth surface as a trimesh (vertices are not merged across objects)."""
        return trimesh.Trimesh(self.vertices, self.triangles, process=False)

    @cached_property
    def raycasting_scene(self) -> o3d.t.geometry.RaycastingScene:
        """An open3d ray-casting scene of all triangles (primitive id == triangle index)."""
        scene = o3d.t.geometry.RaycastingScene()
        scene.add_triangles(
            o3d.core.Tensor(self.vertices.astype(np.float32)),
            o3d.core.Tensor(self.triangles.astype(np.uint32)),
        )
        return scene


class _RoomBuilder:
    """Collects trimesh primitives into one triangle soup with object ids."""

    def __init__(self) -> None:
        self.vertices: list[np.ndarray] = []
        self.triangles: list[np.ndarray] = []
        self.ids: list[np.ndarray] = []
        self.objects: list[RoomObject] = []
        self.n_vertices = 0

    def add(self, name: str, mesh: trimesh.Trimesh, material: Material) -> None:
        verts = np.asarray(mesh.vertices, np.float64)
        faces = np.asarray(mesh.faces, np.int64)
        self.vertices.append(verts)
        self.triangles.append(faces + self.n_vertices)
        self.ids.append(np.full(len(faces), len(self.objects), np.int32))
        lo, hi = verts.min(axis=0), verts.max(axis=0)
        bounds = (tuple(round(float(v), 6) for v in lo), tuple(round(float(v), 6) for v in hi))
        self.objects.append(RoomObject(name, material, bounds))
        self.n_vertices += len(verts)

    def box(self, name: str, lo, hi, material: Material, yaw: float = 0.0) -> None:
        """An axis-aligned box from corner ``lo`` to ``hi`` (m), optionally turned by ``yaw`` rad about z."""
        lo, hi = np.asarray(lo, float), np.asarray(hi, float)
        transform = trimesh.transformations.rotation_matrix(yaw, [0, 0, 1])
        transform[:3, 3] = (lo + hi) / 2
        self.add(name, trimesh.creation.box(extents=hi - lo, transform=transform), material)

    def cylinder(self, name: str, centre_xy, z0: float, z1: float, radius: float, material: Material) -> None:
        """A vertical cylinder standing on ``z0`` up to ``z1`` (m)."""
        transform = np.eye(4)
        transform[:3, 3] = (centre_xy[0], centre_xy[1], (z0 + z1) / 2)
        mesh = trimesh.creation.cylinder(radius=radius, height=z1 - z0, sections=24, transform=transform)
        self.add(name, mesh, material)

    def quad(self, name: str, corners: np.ndarray, material: Material) -> None:
        """A planar quad from 4 corners [4, 3] in winding order (normal by the right-hand rule)."""
        self.add(name, trimesh.Trimesh(corners, [[0, 1, 2], [0, 2, 3]], process=False), material)

    def build(self, lights: list[PointLight], seed: int) -> RoomGeometry:
        return RoomGeometry(
            np.concatenate(self.vertices),
            np.concatenate(self.triangles).astype(np.int32),
            np.concatenate(self.ids),
            self.objects,
            lights,
            seed,
        )


def _jitter_colour(rng: np.random.Generator, colour: tuple[float, float, float], amount: float = 0.08):
    return tuple(float(np.clip(c + rng.uniform(-amount, amount), 0.02, 0.95)) for c in colour)


def build_room(seed: int = 0) -> RoomGeometry:
    """The furnished room: shell (floor, ceiling, 4 walls), door, window, table, shelf, sofa, boxes, lamps.

    Furniture positions, sizes and colours are jittered deterministically from ``seed``; the middle of the
    room (the camera path of :func:`camera_path`) stays free.
    """
    rng = np.random.default_rng(seed)
    W, D, H = ROOM_SIZE
    x0, x1, y0, y1 = -W / 2, W / 2, -D / 2, D / 2
    b = _RoomBuilder()

    def mat(pattern: str, base, accent, scale: float, emission: float = 0.0) -> Material:
        return Material(pattern, _jitter_colour(rng, base), _jitter_colour(rng, accent), scale, emission)

    # Shell: quads wound so that their normals face into the room.
    b.quad(
        "floor",
        np.array([[x0, y0, 0], [x1, y0, 0], [x1, y1, 0], [x0, y1, 0]]),
        mat("planks", (0.45, 0.28, 0.14), (0.25, 0.13, 0.06), 0.18),
    )
    b.quad(
        "ceiling",
        np.array([[x0, y0, H], [x0, y1, H], [x1, y1, H], [x1, y0, H]]),
        mat("plaster", (0.85, 0.85, 0.82), (0.75, 0.77, 0.8), 0.7),
    )
    b.quad(
        "wall_south",
        np.array([[x0, y0, 0], [x0, y0, H], [x1, y0, H], [x1, y0, 0]]),
        mat("tiles", (0.75, 0.72, 0.62), (0.35, 0.5, 0.6), 0.3),
    )
    b.quad(
        "wall_north",
        np.array([[x0, y1, 0], [x1, y1, 0], [x1, y1, H], [x0, y1, H]]),
        mat("plaster", (0.55, 0.65, 0.5), (0.8, 0.82, 0.7), 0.5),
    )
    b.quad(
        "wall_west",
        np.array([[x0, y0, 0], [x0, y1, 0], [x0, y1, H], [x0, y0, H]]),
        mat("plaster", (0.7, 0.55, 0.45), (0.85, 0.78, 0.65), 0.4),
    )
    b.quad(
        "wall_east",
        np.array([[x1, y0, 0], [x1, y0, H], [x1, y1, H], [x1, y1, 0]]),
        mat("marble", (0.82, 0.8, 0.78), (0.3, 0.3, 0.35), 0.6),
    )

    # Door with frame and knob on the south wall.
    door_x = -1.15 + rng.uniform(-0.1, 0.1)
    door_wood = mat("wood", (0.55, 0.35, 0.2), (0.3, 0.16, 0.08), 0.25)
    trim = mat("plain", (0.9, 0.9, 0.88), (0.7, 0.7, 0.7), 0.3)
    b.box("door", (door_x - 0.45, y0, 0.0), (door_x + 0.45, y0 + 0.04, 2.05), door_wood)
    b.box("door_trim_left", (door_x - 0.53, y0, 0.0), (door_x - 0.45, y0 + 0.07, 2.13), trim)
    b.box("door_trim_right", (door_x + 0.45, y0, 0.0), (door_x + 0.53, y0 + 0.07, 2.13), trim)
    b.box("door_trim_top", (door_x - 0.45, y0, 2.05), (door_x + 0.45, y0 + 0.07, 2.13), trim)
    b.cylinder(
        "door_knob",
        (door_x + 0.33, y0 + 0.09),
        0.98,
        1.04,
        0.035,
        mat("plain", (0.8, 0.7, 0.3), (0.5, 0.4, 0.1), 0.05),
    )

    # Window on the east wall: the outside view plus frame, cross bars and sill.
    wy0, wy1, wz0, wz1 = 0.2, 1.4, 0.95, 2.0
    frame = mat("plain", (0.92, 0.92, 0.9), (0.8, 0.8, 0.8), 0.3)
    b.box(
        "window_view",
        (x1 - 0.03, wy0, wz0),
        (x1 - 0.01, wy1, wz1),
        mat("sky", (0.35, 0.55, 0.9), (0.75, 0.85, 0.95), 0.5, emission=0.9),
    )
    b.box("window_frame_bottom", (x1 - 0.08, wy0 - 0.06, wz0 - 0.06), (x1, wy1 + 0.06, wz0), frame)
    b.box("window_frame_top", (x1 - 0.08, wy0 - 0.06, wz1), (x1, wy1 + 0.06, wz1 + 0.06), frame)
    b.box("window_frame_left", (x1 - 0.08, wy0 - 0.06, wz0), (x1, wy0, wz1), frame)
    b.box("window_frame_right", (x1 - 0.08, wy1, wz0), (x1, wy1 + 0.06, wz1), frame)
    b.box(
        "window_bar_vertical",
        (x1 - 0.06, (wy0 + wy1) / 2 - 0.02, wz0),
        (x1 - 0.03, (wy0 + wy1) / 2 + 0.02, wz1),
        frame,
    )
    b.box(
        "window_bar_horizontal",
        (x1 - 0.06, wy0, (wz0 + wz1) / 2 - 0.02),
        (x1 - 0.03, wy1, (wz0 + wz1) / 2 + 0.02),
        frame,
    )
    b.box("window_sill", (x1 - 0.2, wy0 - 0.12, wz0 - 0.1), (x1, wy1 + 0.12, wz0 - 0.06), frame)

    # Table (top + 4 legs) near the south-east corner, a box and a vase on it; the top's centre stays clear.
    tx, ty = 1.6 + rng.uniform(-0.08, 0.08), -1.2 + rng.uniform(-0.08, 0.08)
    half_w, half_d, top_z = 0.6, 0.4, 0.75
    table_wood = mat("wood", (0.6, 0.42, 0.25), (0.35, 0.2, 0.1), 0.2)
    b.box(
        "table_top", (tx - half_w, ty - half_d, top_z - 0.04), (tx + half_w, ty + half_d, top_z), table_wood
    )
    for i, (sx, sy) in enumerate(itertools.product((-1, 1), (-1, 1))):
        b.cylinder(
            f"table_leg_{i}",
            (tx + sx * (half_w - 0.07), ty + sy * (half_d - 0.07)),
            0.0,
            top_z - 0.04,
            0.03,
            table_wood,
        )
    b.box(
        "table_box",
        (tx + 0.2, ty - 0.3, top_z),
        (tx + 0.5, ty - 0.1, top_z + 0.15),
        mat("plain", (0.7, 0.2, 0.15), (0.9, 0.5, 0.3), 0.1),
        yaw=rng.uniform(-0.4, 0.4),
    )
    b.cylinder(
        "table_vase",
        (tx - 0.4, ty + 0.2),
        top_z,
        top_z + 0.28,
        0.06,
        mat("marble", (0.2, 0.35, 0.6), (0.9, 0.9, 0.95), 0.1),
    )

    # Bookshelf against the west wall, with rows of books of random size and colour.
    sy0 = -0.2 + rng.uniform(-0.08, 0.08)
    sy1, depth, top = sy0 + 1.3, 0.38, 1.9
    shelf_wood = mat("wood", (0.42, 0.26, 0.15), (0.22, 0.12, 0.06), 0.15)
    b.box("shelf_back", (x0, sy0, 0.0), (x0 + 0.02, sy1, top), shelf_wood)
    b.box("shelf_side_left", (x0, sy0, 0.0), (x0 + depth, sy0 + 0.03, top), shelf_wood)
    b.box("shelf_side_right", (x0, sy1 - 0.03, 0.0), (x0 + depth, sy1, top), shelf_wood)
    levels = [0.05, 0.5, 0.95, 1.4, top - 0.03]
    for i, z in enumerate(levels):
        b.box(f"shelf_board_{i}", (x0 + 0.02, sy0 + 0.03, z - 0.03), (x0 + depth, sy1 - 0.03, z), shelf_wood)
    palette = [
        (0.6, 0.1, 0.1),
        (0.1, 0.3, 0.6),
        (0.15, 0.45, 0.2),
        (0.8, 0.65, 0.2),
        (0.3, 0.2, 0.4),
        (0.85, 0.85, 0.8),
        (0.1, 0.1, 0.12),
        (0.7, 0.35, 0.1),
    ]
    n_books = 0
    for z_bottom, z_next in itertools.pairwise(levels):
        y = sy0 + 0.03 + rng.uniform(0.0, 0.08)
        while True:
            width = rng.uniform(0.025, 0.07)
            if y + width > sy1 - 0.04:
                break
            height = rng.uniform(0.18, min(0.34, z_next - z_bottom - 0.06))
            book_depth = rng.uniform(0.16, 0.26)
            colour = palette[int(rng.integers(len(palette)))]
            b.box(
                f"book_{n_books}",
                (x0 + 0.03, y, z_bottom),
                (x0 + 0.03 + book_depth, y + width, z_bottom + height),
                mat("plain", colour, (0.9, 0.85, 0.7), 0.05),
            )
            n_books += 1
            y += width + (rng.uniform(0.05, 0.2) if rng.random() < 0.12 else 0.002)

    # Paintings on the west wall and above the sofa.
    b.box(
        "painting_west",
        (x0, -1.3, 1.15),
        (x0 + 0.03, -0.45, 1.75),
        mat("painting", (0.6, 0.9, 0.95), (0.2, 0.2, 0.2), 0.2),
    )

    # Sofa against the north wall.
    cx_sofa = 0.6 + rng.uniform(-0.1, 0.1)
    fabric = mat("fabric", (0.25, 0.3, 0.45), (0.75, 0.6, 0.3), 0.16)
    b.box("sofa_base", (cx_sofa - 1.0, y1 - 0.85, 0.1), (cx_sofa + 1.0, y1 - 0.05, 0.42), fabric)
    b.box("sofa_back", (cx_sofa - 1.0, y1 - 0.25, 0.42), (cx_sofa + 1.0, y1 - 0.05, 0.88), fabric)
    b.box("sofa_arm_left", (cx_sofa - 1.0, y1 - 0.85, 0.42), (cx_sofa - 0.8, y1 - 0.25, 0.62), fabric)
    b.box("sofa_arm_right", (cx_sofa + 0.8, y1 - 0.85, 0.42), (cx_sofa + 1.0, y1 - 0.25, 0.62), fabric)
    cushion = mat("plain", (0.7, 0.25, 0.2), (0.9, 0.6, 0.3), 0.1)
    b.box("sofa_cushion_0", (cx_sofa - 0.78, y1 - 0.83, 0.42), (cx_sofa - 0.01, y1 - 0.27, 0.52), cushion)
    b.box("sofa_cushion_1", (cx_sofa + 0.01, y1 - 0.83, 0.42), (cx_sofa + 0.78, y1 - 0.27, 0.52), cushion)
    for i, (sx, sy) in enumerate(itertools.product((-1, 1), (-1, 1))):
        fx, fy = cx_sofa + sx * 0.9, y1 - 0.45 + sy * 0.32
        b.box(f"sofa_foot_{i}", (fx - 0.04, fy - 0.04, 0.0), (fx + 0.04, fy + 0.04, 0.1), shelf_wood)
    b.box(
        "painting",
        (cx_sofa - 0.55, y1 - 0.03, 1.2),
        (cx_sofa + 0.55, y1, 1.9),
        mat("painting", (0.95, 0.85, 0.9), (0.2, 0.2, 0.2), 0.25),
    )

    # Floor objects: stacked crates in the south-west corner, a bin, a floor lamp, a rug.
    crate = mat("wood", (0.7, 0.55, 0.35), (0.45, 0.3, 0.15), 0.08)
    b.box("crate", (x0 + 0.2, y0 + 0.2, 0.0), (x0 + 0.7, y0 + 0.7, 0.5), crate, yaw=rng.uniform(-0.2, 0.2))
    b.box(
        "crate_small",
        (x0 + 0.3, y0 + 0.3, 0.5),
        (x0 + 0.62, y0 + 0.6, 0.75),
        mat("plain", (0.3, 0.55, 0.35), (0.6, 0.8, 0.5), 0.1),
        yaw=rng.uniform(-0.6, 0.6),
    )
    b.cylinder(
        "bin",
        (x1 - 0.35, y1 - 0.35),
        0.0,
        0.42,
        0.16,
        mat("plain", (0.15, 0.15, 0.18), (0.4, 0.4, 0.45), 0.1),
    )
    lamp_xy = (x0 + 0.4, y1 - 0.35)
    b.cylinder(
        "floor_lamp_base", lamp_xy, 0.0, 0.04, 0.15, mat("plain", (0.1, 0.1, 0.1), (0.3, 0.3, 0.3), 0.1)
    )
    b.cylinder(
        "floor_lamp_pole", lamp_xy, 0.04, 1.45, 0.02, mat("plain", (0.6, 0.6, 0.6), (0.8, 0.8, 0.8), 0.1)
    )
    b.cylinder(
        "floor_lamp_shade", lamp_xy, 1.45, 1.72, 0.19, mat("fabric", (0.9, 0.85, 0.7), (0.7, 0.6, 0.4), 0.05)
    )
    b.box("rug", (-1.0, -0.95, 0.0), (1.0, 0.7, 0.012), mat("tiles", (0.6, 0.2, 0.2), (0.85, 0.75, 0.5), 0.2))
    b.cylinder(
        "ceiling_lamp", (0.0, 0.0), H - 0.12, H, 0.22, mat("plain", (0.95, 0.95, 0.9), (0.9, 0.9, 0.8), 0.1)
    )

    lights = [
        PointLight((0.0, 0.0, H - 0.3), (1.6, 1.5, 1.35)),
        PointLight((x1 - 0.6, (wy0 + wy1) / 2, 1.7), (0.55, 0.6, 0.7)),
    ]
    return b.build(lights, seed)


# --------------------------------------------------------------------------------------------- rendering

AMBIENT = 0.22
LIGHT_FALLOFF_M = 2.5
"""Metres at which a point light's irradiance halves (``1 / (1 + (d / LIGHT_FALLOFF_M)^2)``)."""
SHADOW_OFFSET_M = 1e-3


def _linear_to_srgb(x: np.ndarray) -> np.ndarray:
    x = np.clip(x, 0.0, 1.0)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)


def _cast(
    geom: RoomGeometry, origins: np.ndarray, dirs: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Closest hits: ``t`` [N] in units of |dir| (inf on a miss), triangle ids int64 [N] (-1 on a miss),
    triangle normals [N, 3]."""
    rays = o3d.core.Tensor(np.concatenate([origins, dirs], axis=1).astype(np.float32))
    hit = geom.raycasting_scene.cast_rays(rays)
    t = hit["t_hit"].numpy().astype(np.float64)
    prim = hit["primitive_ids"].numpy().astype(np.int64)
    prim[~np.isfinite(t)] = -1
    return t, prim, hit["primitive_normals"].numpy().astype(np.float64)


def _albedo(geom: RoomGeometry, points: np.ndarray, normals: np.ndarray, objects: np.ndarray) -> np.ndarray:
    """Linear albedo [N, 3] in [0, 1] at hit ``points`` [N, 3] with ``normals`` [N, 3] on ``objects`` [N]."""
    albedo = np.zeros((len(points), 3))
    for obj_id in np.unique(objects):
        sel = objects == obj_id
        material = geom.objects[obj_id].material
        albedo[sel] = _PATTERNS[material.pattern](
            points[sel], normals[sel], material, geom.seed * 1000 + int(obj_id)
        )
    return np.clip(albedo, 0.0, 1.0)


def shade(geom: RoomGeometry, origins: np.ndarray, dirs: np.ndarray) -> np.ndarray:
    """Trace rays (origins, dirs [N, 3], any direction length): linear radiance [N, 3], 0 on a miss.

    Lambertian: ``albedo * (AMBIENT + sum_l visible_l * I_l * max(0, n.l) / (1 + (d_l / LIGHT_FALLOFF_M)^2))
    + emission * albedo``, surfaces two-sided (normals flipped toward the ray), shadows by occlusion rays.
    """
    t, prim, normals = _cast(geom, origins, dirs)
    radiance = np.zeros((len(t), 3))
    hit = prim >= 0
    if not hit.any():
        return radiance
    points = origins[hit] + t[hit, None] * dirs[hit]
    n = normals[hit]
    n = np.where((np.sum(n * dirs[hit], axis=1) > 0)[:, None], -n, n)
    objects = geom.triangle_object[prim[hit]]
    albedo = _albedo(geom, points, n, objects)
    emission = np.array([m.material.emission for m in geom.objects])[objects]
    irradiance = np.full((len(points), 3), AMBIENT)
    start = points + SHADOW_OFFSET_M * n
    for light in geom.lights:
        to_light = np.asarray(light.position)[None] - start
        dist = np.linalg.norm(to_light, axis=1)
        cosine = np.maximum(np.sum(n * to_light, axis=1) / np.maximum(dist, 1e-9), 0.0)
        lit = cosine > 0
        rays = o3d.core.Tensor(np.concatenate([start[lit], to_light[lit]], axis=1).astype(np.float32))
        occluded = geom.raycasting_scene.test_occlusions(rays, tnear=0.0, tfar=1.0).numpy()
        visible = np.zeros(len(points), bool)
        visible[np.flatnonzero(lit)[~occluded]] = True
        falloff = 1.0 / (1.0 + (dist / LIGHT_FALLOFF_M) ** 2)
        irradiance += (visible * cosine * falloff)[:, None] * np.asarray(light.intensity)[None]
    radiance[hit] = albedo * irradiance + emission[:, None] * albedo
    return radiance


def _pixel_rays(c2w: np.ndarray, fl: float, cx: float, cy: float, px: np.ndarray, py: np.ndarray):
    """World rays through continuous pixel coordinates ``(px, py)`` [N]; dirs have camera z-component -1.

    The ray parameter of a hit is therefore its z-depth along the camera's -Z axis (OpenGL convention).
    """
    right, up, back = c2w[:3, 0], c2w[:3, 1], c2w[:3, 2]
    # Camera direction ((px - cx) / fl, -(py - cy) / fl, -1) rotated to world, without a (slow here) BLAS call.
    dirs = ((px - cx) / fl)[:, None] * right - ((py - cy) / fl)[:, None] * up - back
    return np.broadcast_to(c2w[:3, 3], dirs.shape).copy(), dirs


def render_view(
    geom: RoomGeometry, c2w: np.ndarray, fl: float, cx: float, cy: float, w: int, h: int, supersample: int = 2
) -> tuple[np.ndarray, np.ndarray]:
    """Render one pinhole view of the room.

    Args:
        c2w: [4, 4] camera-to-world, OpenGL convention (camera looks along -Z, +Y up), metres.
        fl: focal length in pixels (fl_x == fl_y); ``cx, cy`` principal point in continuous pixel coordinates.
        supersample: ``s``: colour is the mean of ``s x s`` rays spread evenly over each pixel.
    Returns:
        rgb: float32 [h, w, 3] sRGB-encoded colour in [0, 1] (the PNG is ``round(255 * rgb)``);
        depth: float32 [h, w] z-depth in metres along the camera's -Z axis at each pixel centre
        ``(x + 0.5, y + 0.5)``, 0 where the ray hits nothing (only possible from outside the room).
    """
    if supersample < 1:
        raise ValueError(f"supersample must be >= 1, got {supersample}")
    c2w = np.asarray(c2w, np.float64)
    offsets = (np.arange(supersample) + 0.5) / supersample
    py, px, oy, ox = np.meshgrid(np.arange(h), np.arange(w), offsets, offsets, indexing="ij")
    origins, dirs = _pixel_rays(c2w, fl, cx, cy, (px + ox).ravel(), (py + oy).ravel())
    radiance = shade(geom, origins, dirs)
    rgb = _linear_to_srgb(radiance.reshape(h, w, supersample * supersample, 3).mean(axis=2))
    cy_grid, cx_grid = np.meshgrid(np.arange(h) + 0.5, np.arange(w) + 0.5, indexing="ij")
    origins, dirs = _pixel_rays(c2w, fl, cx, cy, cx_grid.ravel(), cy_grid.ravel())
    t, _, _ = _cast(geom, origins, dirs)
    depth = np.where(np.isfinite(t), t, 0.0).reshape(h, w)
    return rgb.astype(np.float32), depth.astype(np.float32)


# ------------------------------------------------------------------------------------- cameras and splits


def look_at_c2w(position: np.ndarray, forward: np.ndarray) -> np.ndarray:
    """Camera-to-world [4, 4] (OpenGL: -Z along ``forward``, +Y toward world +Z, +X right), no roll."""
    f = forward / np.linalg.norm(forward)
    right = np.cross(f, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    up = np.cross(right, f)
    c2w = np.eye(4)
    c2w[:3, 0], c2w[:3, 1], c2w[:3, 2], c2w[:3, 3] = right, up, -f, position
    return c2w


def camera_path(n_frames: int) -> np.ndarray:
    """Camera-to-world poses [n_frames, 4, 4] along one smooth loop through the middle of the room.

    The camera walks an ellipse (semi-axes 1.1 m x 0.55 m) at 1.27-1.63 m height, looking 20-60 degrees off
    the outward radial direction toward walls and furniture, slightly downward, with slowly varying yaw and
    pitch; consecutive frames overlap.
    """
    theta = 2 * np.pi * np.arange(n_frames) / n_frames
    poses = np.empty((n_frames, 4, 4))
    for i, th in enumerate(theta):
        position = np.array(
            [0.1 + 1.1 * np.cos(th), -0.15 + 0.55 * np.sin(th), 1.45 + 0.18 * np.sin(2 * th + 0.3)]
        )
        yaw = th + 0.7 + 0.35 * np.sin(3 * th + 1.0)
        pitch = -0.22 + 0.12 * np.sin(2 * th + 2.0)
        forward = np.array([np.cos(yaw) * np.cos(pitch), np.sin(yaw) * np.cos(pitch), np.sin(pitch)])
        poses[i] = look_at_c2w(position, forward)
    return poses


@dataclass(frozen=True)
class FrameSplits:
    """Frame indices (into the camera path) of each split, ascending."""

    train: list[int]
    interpolation: list[int]
    extrapolation: list[int]

    @property
    def used(self) -> list[int]:
        """Every frame some split names, ascending."""
        return sorted(set(self.train) | set(self.interpolation) | set(self.extrapolation))


def split_frames(n_frames: int, train_every: int, n_gaps: int, gap_len: int) -> FrameSplits:
    """Redkitchen-style splits along a path of ``n_frames``.

    Training: every ``train_every``-th frame except those within ``gap_len / 2`` of the centres of
    ``n_gaps`` evenly spaced gaps. Interpolation: the frame midway (``+ train_every // 2``) between two
    consecutive training frames. Extrapolation: frames on the ``train_every // 2`` grid inside a gap that are
    at least ``train_every`` frames from every training frame.
    """
    if train_every < 2:
        raise ValueError(f"train_every must be >= 2, got {train_every}")
    if n_gaps < 0 or gap_len < 0:
        raise ValueError(f"n_gaps and gap_len must be >= 0, got {n_gaps}, {gap_len}")
    centres = [(k + 0.5) * n_frames / n_gaps for k in range(n_gaps)]
    train = [i for i in range(0, n_frames, train_every) if all(abs(i - c) >= gap_len / 2 for c in centres)]
    if len(train) < 2:
        raise ValueError(
            f"only {len(train)} training frame(s) left: n_frames={n_frames}, train_every={train_every}, "
            f"n_gaps={n_gaps}, gap_len={gap_len}"
        )
    half = train_every // 2
    interpolation = [a + half for a, b in itertools.pairwise(train) if b - a == train_every]
    extrapolation = []
    for a, b in itertools.pairwise(train):
        if b - a > train_every:
            extrapolation += [j for j in range(a + half, b, half) if min(j - a, b - j) >= train_every]
    if n_gaps > 0 and not extrapolation:
        raise ValueError(f"gap_len={gap_len} is too short to leave frames far from training frames")
    return FrameSplits(train, interpolation, extrapolation)


# ------------------------------------------------------------------------------------------------- prior


def sample_point_prior(
    geom: RoomGeometry, sigma: float, max_points: int, rng: np.random.Generator
) -> tuple[np.ndarray, dict]:
    """A noisy point-cloud prior [N, 3] float64 and a JSON-able description of how it was made.

    Surface points at about one per ``(sigma / 2)^2`` of area (at most ``max_points``), Gaussian noise of std
    ``sigma`` per axis, ``PRIOR_OUTLIER_FRACTION`` uniform outliers in the room, and ``PRIOR_HOLES`` spherical
    regions (around surface points) left empty.
    """
    mesh = geom.to_trimesh()
    count = int(min(max_points, math.ceil(mesh.area / (sigma / 2) ** 2)))
    points, _ = trimesh.sample.sample_surface(mesh, count, seed=int(rng.integers(2**31)))
    points = points + rng.normal(0.0, sigma, points.shape)
    n_out = int(round(PRIOR_OUTLIER_FRACTION * count))
    outliers = rng.uniform(0.0, 1.0, (n_out, 3)) * np.asarray(geom.room_size) - [
        geom.room_size[0] / 2,
        geom.room_size[1] / 2,
        0.0,
    ]
    points = np.concatenate([points, outliers])
    holes = []
    for _ in range(PRIOR_HOLES):
        centre = points[int(rng.integers(count))]
        radius = float(rng.uniform(*PRIOR_HOLE_RADIUS))
        points = points[np.linalg.norm(points - centre, axis=1) > radius]
        holes.append({"centre": [round(float(c), 4) for c in centre], "radius": round(radius, 4)})
    info = {
        "kind": "points",
        "n_points": len(points),
        "outlier_fraction": PRIOR_OUTLIER_FRACTION,
        "holes": holes,
    }
    return points, info


def noisy_mesh_prior(
    geom: RoomGeometry, sigma: float, rng: np.random.Generator
) -> tuple[trimesh.Trimesh, dict]:
    """The true mesh subdivided to ``PRIOR_MESH_MAX_EDGE``, vertices displaced by N(0, sigma^2) per axis."""
    verts, faces = trimesh.remesh.subdivide_to_size(geom.vertices, geom.triangles, PRIOR_MESH_MAX_EDGE)
    mesh = trimesh.Trimesh(verts, faces, process=False)
    mesh.merge_vertices()
    mesh.vertices = mesh.vertices + rng.normal(0.0, sigma, mesh.vertices.shape)
    info = {
        "kind": "mesh",
        "n_vertices": len(mesh.vertices),
        "n_faces": len(mesh.faces),
        "max_edge": PRIOR_MESH_MAX_EDGE,
    }
    return mesh, info


# ------------------------------------------------------------------------------------------------ writer


@dataclass
class RoomSpec:
    """What :func:`make_room_scene` writes. Defaults give the 5 x 4 x 2.6 m room at 160 x 120 pixels."""

    width: int = 160
    height: int = 120
    n_frames: int = 160
    train_every: int = 10
    n_gaps: int = 2
    gap_len: int = 30
    prior_kind: str = "points"
    prior_sigma: float = 0.02
    prior_max_points: int = 300_000
    write_depth: bool = True
    supersample: int = 2
    seed: int = 0
    hfov_deg: float = HORIZONTAL_FOV_DEG

    def validate(self) -> None:
        """ValueError naming the first bad field."""
        for name in ("width", "height", "n_frames", "train_every", "supersample", "prior_max_points"):
            if not isinstance(getattr(self, name), int) or getattr(self, name) < 1:
                raise ValueError(f"RoomSpec.{name} must be a positive integer, got {getattr(self, name)!r}")
        if self.prior_kind not in PRIOR_KINDS:
            raise ValueError(f"RoomSpec.prior_kind must be one of {PRIOR_KINDS}, got {self.prior_kind!r}")
        if not (math.isfinite(self.prior_sigma) and self.prior_sigma > 0):
            raise ValueError(
                f"RoomSpec.prior_sigma must be a positive number of metres, got {self.prior_sigma!r}"
            )
        if not 10.0 <= self.hfov_deg <= 120.0:
            raise ValueError(f"RoomSpec.hfov_deg must be in [10, 120], got {self.hfov_deg!r}")


def _write_png(path: Path, image: np.ndarray) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    iio.imwrite(path, image, extension=".png")


def _check_out_dir(out_dir: Path) -> None:
    if out_dir.exists() and (not out_dir.is_dir() or any(out_dir.iterdir())):
        raise FileExistsError(f"{out_dir}: output must not exist or be an empty directory")


def make_room_scene(out_dir: Path, spec: RoomSpec | None = None) -> Path:
    """Render the synthetic room into ``out_dir`` (which must not exist or be empty); returns ``out_dir``.

    Writes ``transforms.json``, ``images/frame-NNNNNN.png`` (sRGB), ``depth/frame-NNNNNN.png`` (16-bit mm) for
    the frames some split uses, ``prior.ply`` (unless ``prior_kind == "none"``) and ``gt_mesh.ply``. The whole
    directory is built beside ``out_dir`` and renamed into place, so a partial scene is never visible.
    Same spec -> byte-identical files.
    """
    spec = spec or RoomSpec()
    spec.validate()
    out_dir = Path(out_dir)
    _check_out_dir(out_dir)
    splits = split_frames(spec.n_frames, spec.train_every, spec.n_gaps, spec.gap_len)
    out_dir.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{out_dir.name}.tmp-", dir=out_dir.parent))
    try:
        _write_scene(tmp, spec, splits)
        _check_out_dir(out_dir)
        if out_dir.exists():
            out_dir.rmdir()
        os.replace(tmp, out_dir)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return out_dir


def _write_scene(root: Path, spec: RoomSpec, splits: FrameSplits) -> None:
    geom = build_room(spec.seed)
    poses = camera_path(spec.n_frames)
    w, h = spec.width, spec.height
    fl = (w / 2) / math.tan(math.radians(spec.hfov_deg) / 2)
    cx, cy = w / 2, h / 2

    frames = []
    for i in splits.used:
        name = f"frame-{i:06d}.png"
        rgb, depth = render_view(geom, poses[i], fl, cx, cy, w, h, spec.supersample)
        _write_png(root / "images" / name, np.round(rgb * 255).astype(np.uint8))
        frame = {"file_path": f"images/{name}", "transform_matrix": np.round(poses[i], 8).tolist()}
        if spec.write_depth:
            depth_units = np.clip(np.round(depth / DEPTH_UNIT_SCALE), 0, 65535).astype(np.uint16)
            _write_png(root / "depth" / name, depth_units)
            frame["depth_file_path"] = f"depth/{name}"
        frames.append(frame)

    def paths(indices: list[int]) -> list[str]:
        return [f"images/frame-{i:06d}.png" for i in indices]

    meta: dict = {
        "camera_model": "PINHOLE",
        "fl_x": fl,
        "fl_y": fl,
        "cx": cx,
        "cy": cy,
        "w": w,
        "h": h,
    }
    if spec.write_depth:
        meta["depth_unit_scale_factor"] = DEPTH_UNIT_SCALE
    meta["frames"] = frames
    meta["train_filenames"] = paths(splits.train)
    meta["test_filenames"] = paths(splits.interpolation)
    meta["eval_splits"] = {"interpolation": paths(splits.interpolation)}
    if splits.extrapolation:
        meta["eval_splits"]["extrapolation"] = paths(splits.extrapolation)

    rng = np.random.default_rng([spec.seed, 1])
    prior_info: dict | None = None
    if spec.prior_kind == "points":
        points, prior_info = sample_point_prior(geom, spec.prior_sigma, spec.prior_max_points, rng)
        trimesh.PointCloud(points).export(root / "prior.ply")
    elif spec.prior_kind == "mesh":
        mesh, prior_info = noisy_mesh_prior(geom, spec.prior_sigma, rng)
        mesh.export(root / "prior.ply")
    if prior_info is not None:
        meta["prior_file_path"] = "prior.ply"
        meta["prior_sigma"] = spec.prior_sigma
    geom.to_trimesh().export(root / "gt_mesh.ply")

    meta["voxnerf_synthetic"] = {
        "seed": spec.seed,
        "room_size": list(geom.room_size),
        "world_up": [0.0, 0.0, 1.0],
        "spec": asdict(spec),
        "gt_mesh_file_path": "gt_mesh.ply",
        "prior": prior_info,
        "split_frame_indices": asdict(splits),
        "lights": [asdict(light) for light in geom.lights],
        "objects": {
            o.name: {"pattern": o.material.pattern, "bounds": [list(o.bounds[0]), list(o.bounds[1])]}
            for o in geom.objects
        },
    }
    (root / "transforms.json").write_text(json.dumps(meta, indent=2) + "\n")


def _main() -> None:
    """``python -m voxnerf.synthetic OUT_DIR [SEED]``: write the default scene and print what it holds."""
    import sys

    if len(sys.argv) not in (2, 3):
        raise SystemExit("usage: python -m voxnerf.synthetic OUT_DIR [SEED]")
    spec = RoomSpec(seed=int(sys.argv[2]) if len(sys.argv) == 3 else 0)
    start = time.perf_counter()
    out = make_room_scene(Path(sys.argv[1]), spec)
    meta = json.loads((out / "transforms.json").read_text())
    print(
        json.dumps(
            {
                "seconds": round(time.perf_counter() - start, 2),
                "frames": len(meta["frames"]),
                "splits": {
                    k: len(v) for k, v in [("train", meta["train_filenames"]), *meta["eval_splits"].items()]
                },
                "prior": meta["voxnerf_synthetic"]["prior"],
            },
            indent=2,
        )
    )


if __name__ == "__main__":
    _main()
