"""Procedural solid textures: a material names a pattern, a function of the 3D hit point (no UVs).

A pattern is ``pattern(points [N, 3] m, normals [N, 3], material, seed, room_height=ROOM_SIZE[2]) -> albedo
[N, 3]``. Patterns are built from value noise on a fixed periodic random lattice; a seed picks the lattice offset,
so every object of the room (seeded by the room's seed and its object id) gets its own variation of its pattern.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from voxnerf.synthetic.dimensions import ROOM_SIZE


@dataclass(frozen=True)
class Material:
    """A procedural, view-independent (Lambertian) solid texture.

    ``pattern`` names a function of the 3D hit point (see ``PATTERNS``); ``base`` and ``accent`` are linear
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


def _planks(p: np.ndarray, n: np.ndarray, m: Material, seed: int, room_height: float = ROOM_SIZE[2]) -> np.ndarray:
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


def _wood(p: np.ndarray, n: np.ndarray, m: Material, seed: int, room_height: float = ROOM_SIZE[2]) -> np.ndarray:
    """Wood grain: warped stripes across x with fine fibre noise."""
    warp = _fbm(p / m.scale * np.array([0.3, 2.0, 2.0]), seed)
    rings = 0.5 + 0.5 * np.sin(2 * np.pi * ((p[:, 1] + 0.5 * p[:, 2]) / m.scale + 3.0 * warp))
    fibre = _value_noise(p * np.array([8.0, 160.0, 160.0]), seed + 7)
    return _mix(m.base, m.accent, rings**3 * 0.8 + 0.2 * fibre)


def _tiles(p: np.ndarray, n: np.ndarray, m: Material, seed: int, room_height: float = ROOM_SIZE[2]) -> np.ndarray:
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


def _plaster(p: np.ndarray, n: np.ndarray, m: Material, seed: int, room_height: float = ROOM_SIZE[2]) -> np.ndarray:
    """Painted plaster: a vertical gradient toward ``accent`` (floor to ceiling) with blotchy low-frequency noise."""
    blotch = _fbm(p / m.scale, seed)
    colour = _mix(m.base, m.accent, p[:, 2] / room_height)
    return colour * (0.75 + 0.45 * blotch)[:, None]


def _fabric(p: np.ndarray, n: np.ndarray, m: Material, seed: int, room_height: float = ROOM_SIZE[2]) -> np.ndarray:
    """Plaid upholstery: broad crossing stripes of period ``scale`` over a fine weave."""
    a, b = _plane_axes(n)
    idx = np.arange(len(p))
    ua, ub = p[idx, a] / m.scale, p[idx, b] / m.scale
    stripes = np.maximum(np.sin(2 * np.pi * ua), 0) ** 4 + np.maximum(np.sin(2 * np.pi * ub), 0) ** 4
    weave = 0.9 + 0.1 * np.sign(np.sin(2 * np.pi * ua * 12) * np.sin(2 * np.pi * ub * 12))
    return _mix(m.base, m.accent, 0.6 * stripes) * weave[:, None]


def _marble(p: np.ndarray, n: np.ndarray, m: Material, seed: int, room_height: float = ROOM_SIZE[2]) -> np.ndarray:
    """Marble: dark veins along a turbulent sine of the summed coordinates."""
    turbulence = _fbm(p / m.scale * 2.0, seed, octaves=5)
    veins = np.abs(np.sin(np.pi * (p.sum(axis=1) / m.scale + 6.0 * turbulence)))
    return _mix(m.accent, m.base, veins**0.35)


def _painting(p: np.ndarray, n: np.ndarray, m: Material, seed: int, room_height: float = ROOM_SIZE[2]) -> np.ndarray:
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


def _plain(p: np.ndarray, n: np.ndarray, m: Material, seed: int, room_height: float = ROOM_SIZE[2]) -> np.ndarray:
    """Nearly uniform colour with faint mottling toward ``accent``."""
    return _mix(m.base, m.accent, 0.35 * _fbm(p / m.scale, seed, octaves=3))


def _sky(p: np.ndarray, n: np.ndarray, m: Material, seed: int, room_height: float = ROOM_SIZE[2]) -> np.ndarray:
    """The view through the window: a vertical gradient with soft clouds."""
    height = np.clip((p[:, 2] - 0.9) / 1.1, 0.0, 1.0)
    clouds = np.clip(2.0 * _fbm(p / m.scale, seed) - 0.9, 0.0, 1.0)
    return _mix(m.accent, m.base, height) * (1 - clouds[:, None]) + 0.95 * clouds[:, None]


PATTERNS: dict[str, Callable[..., np.ndarray]] = {
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
