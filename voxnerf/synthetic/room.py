"""Building the furnished room from :data:`voxnerf.synthetic.furniture.FURNITURE` for a seed and a style."""

from __future__ import annotations

import colorsys
import itertools
import math
import re
from collections.abc import Mapping
from dataclasses import dataclass, replace

import numpy as np

from voxnerf.synthetic.dimensions import ROOM_SIZE
from voxnerf.synthetic.furniture import FURNITURE, LIGHTS, BookRows, Box, Coord, Cylinder, Group, Piece, Quad
from voxnerf.synthetic.geometry import PointLight, RoomBuilder, RoomGeometry, RoomObject
from voxnerf.synthetic.textures import Material

_TERM = re.compile(r"([+-]?)([^+-]+)")


def coord(expr: Coord, anchors: Mapping[str, float]) -> float:
    """The value (m) of a furniture coordinate: a number, or signed anchor names / numbers added left to right."""
    if not isinstance(expr, str):
        return float(expr)
    value: float | None = None
    for sign, term in _TERM.findall(expr):
        term_value = anchors[term] if term[0].isalpha() or term[0] == "_" else float(term)
        if sign == "-":
            term_value = -term_value
        value = term_value if value is None else value + term_value
    if value is None:
        raise ValueError(f"empty furniture coordinate {expr!r}")
    return value


def room_anchors(room_size: tuple[float, float, float] = ROOM_SIZE) -> dict[str, float]:
    """The anchors of the room frame: the walls ``x0, x1, y0, y1`` and the ceiling height ``H`` (m)."""
    W, D, H = room_size
    return {"x0": -W / 2, "x1": W / 2, "y0": -D / 2, "y1": D / 2, "H": H}


ROOM_SIZE_RANGE: tuple[tuple[float, float], tuple[float, float], tuple[float, float]] = (
    (4.4, 7.0), (4.0, 6.0), (2.4, 3.5)
)
"""Metres: the widths, depths and heights the furniture fits in with the camera path clear (inclusive)."""
LIGHT_TEMPERATURE_RANGE_K = (2000.0, 10000.0)
LIGHT_CLEARANCE_M = 0.3
"""Metres: a jittered light stays this far inside the walls and floor, and below the ceiling lamp's light."""


@dataclass(frozen=True)
class RoomStyle:
    """How a room differs from the default one (the defaults change nothing).

    ``room_size`` (W, D, H) metres within :data:`ROOM_SIZE_RANGE`: the shell, with furniture anchored to the
    walls; ``light_scale`` multiplies every light's intensity; ``light_temperature_k`` tints the lights like a
    black body of that temperature (None: their own colours; 6500 K is neutral); ``light_jitter_m`` moves each
    light by ``uniform(-j, j)`` per axis (never up, never within :data:`LIGHT_CLEARANCE_M` of the shell);
    ``texture_scale`` multiplies every pattern's period; ``palette_shift`` in [0, 1] turns each distinct
    material's hue by up to ``palette_shift / 2`` of the colour circle and scales its saturation by up to
    ``2 ** +-palette_shift``. The random values come from the seed, apart from the furniture's draws.
    """

    room_size: tuple[float, float, float] = ROOM_SIZE
    light_scale: float = 1.0
    light_temperature_k: float | None = None
    light_jitter_m: float = 0.0
    texture_scale: float = 1.0
    palette_shift: float = 0.0


def temperature_rgb(kelvin: float) -> tuple[float, float, float]:
    """Linear RGB tint of a black body at ``kelvin`` (an sRGB-space fit, Tanner Helland's), 6500 K == (1, 1, 1)."""

    def srgb(k: float) -> np.ndarray:
        t = k / 100.0
        r = 255.0 if t <= 66 else 329.698727446 * (t - 60) ** -0.1332047592
        g = 99.4708025861 * math.log(t) - 161.1195681661 if t <= 66 else 288.1221695283 * (t - 60) ** -0.0755148492
        b = 255.0 if t >= 66 else (0.0 if t <= 19 else 138.5177312231 * math.log(t - 10) - 305.0447927307)
        return (np.clip([r, g, b], 0.0, 255.0) / 255.0) ** 2.2

    tint = srgb(kelvin) / srgb(6500.0)
    return tuple(float(c) for c in tint / tint.max())


def _jitter_colour(rng: np.random.Generator, colour: tuple[float, float, float], amount: float = 0.08):
    return tuple(float(np.clip(c + rng.uniform(-amount, amount), 0.02, 0.95)) for c in colour)


def _jitter_material(rng: np.random.Generator, m: Material) -> Material:
    """``m`` with both colours jittered (base first, then accent)."""
    return Material(m.pattern, _jitter_colour(rng, m.base), _jitter_colour(rng, m.accent), m.scale, m.emission)


class _Placer:
    """Reads furniture groups into a :class:`RoomBuilder`, drawing every random value from one generator."""

    def __init__(self, rng: np.random.Generator, room_size: tuple[float, float, float] = ROOM_SIZE) -> None:
        self.rng = rng
        self.builder = RoomBuilder()
        self.anchors: dict[str, float] = room_anchors(room_size)
        self.wall_shift = {k: v - room_anchors()[k] for k, v in self.anchors.items()}
        self.materials: dict[str, Material] = {}

    def point(self, exprs: tuple[Coord, ...]) -> tuple[float, ...]:
        return tuple(coord(e, self.anchors) for e in exprs)

    def material(self, m: str | Material) -> Material:
        return self.materials[m] if isinstance(m, str) else _jitter_material(self.rng, m)

    def group(self, group: Group) -> None:
        for name, (centre, half) in group.jitter.items():
            if name in group.follow:
                centre = centre + self.wall_shift[group.follow[name]]
            self.anchors[name] = centre + self.rng.uniform(-half, half)
        for name, expr in group.anchors.items():
            self.anchors[name] = coord(expr, self.anchors)
        for name, spec in group.materials.items():
            self.materials[name] = _jitter_material(self.rng, spec)
        for piece in group.pieces:
            self.piece(piece)

    def piece(self, piece: Piece) -> None:
        b = self.builder
        if isinstance(piece, BookRows):
            self.books(piece)
        elif isinstance(piece, Quad):
            b.quad(piece.name, np.array([self.point(c) for c in piece.corners]), self.material(piece.material))
        elif isinstance(piece, Cylinder):
            z0, z1 = self.point(piece.z)
            b.cylinder(piece.name, self.point(piece.centre), z0, z1, piece.radius, self.material(piece.material))
        elif isinstance(piece, Box):
            material = self.material(piece.material)
            yaw = self.rng.uniform(-piece.turn, piece.turn) if piece.turn else 0.0
            b.box(piece.name, self.point(piece.lo), self.point(piece.hi), material, yaw=yaw)
        else:
            raise TypeError(f"not a furniture piece: {piece!r}")

    def books(self, rows: BookRows) -> None:
        rng, x = self.rng, coord(rows.x, self.anchors)
        y_start, y_end = self.point(rows.y)
        n_books = 0
        for z_bottom, z_next in itertools.pairwise(self.point(rows.levels)):
            y = y_start + rng.uniform(*rows.indent)
            while True:
                width = rng.uniform(*rows.width)
                if y + width > y_end:
                    break
                height = rng.uniform(rows.height[0], min(rows.height[1], z_next - z_bottom - rows.headroom))
                depth = rng.uniform(*rows.depth)
                colour = rows.palette[int(rng.integers(len(rows.palette)))]
                cover = _jitter_material(rng, Material("plain", colour, rows.accent, rows.scale))
                self.builder.box(f"book_{n_books}", (x, y, z_bottom), (x + depth, y + width, z_bottom + height), cover)
                n_books += 1
                y += width + (rng.uniform(*rows.gap) if rng.random() < rows.gap_chance else rows.spacing)


def _restyled_materials(objects: list[RoomObject], style: RoomStyle, rng: np.random.Generator) -> list[RoomObject]:
    """``objects`` with ``style``'s texture scale and palette shift: one random shift per distinct material."""
    if style.texture_scale == 1.0 and style.palette_shift == 0.0:
        return objects
    shifted: dict[Material, Material] = {}
    for obj in objects:
        m = obj.material
        if m not in shifted:
            hue = style.palette_shift * rng.uniform(-0.5, 0.5)
            saturation = 2.0 ** (style.palette_shift * rng.uniform(-1.0, 1.0))
            keep_colour = m.pattern == "sky" or style.palette_shift == 0.0
            base, accent = (m.base, m.accent) if keep_colour else (
                _shift_colour(m.base, hue, saturation), _shift_colour(m.accent, hue, saturation))
            shifted[m] = replace(m, base=base, accent=accent, scale=m.scale * style.texture_scale)
    return [replace(obj, material=shifted[obj.material]) for obj in objects]


def _shift_colour(colour: tuple[float, float, float], hue: float, saturation: float) -> tuple[float, float, float]:
    """``colour`` with its hue turned by ``hue`` (fraction of the circle) and its saturation times ``saturation``."""
    h, s, v = colorsys.rgb_to_hsv(*colour)
    shifted = colorsys.hsv_to_rgb((h + hue) % 1.0, min(s * saturation, 1.0), v)
    return tuple(float(np.clip(c, 0.02, 0.95)) for c in shifted)


def _styled_lights(lights: list[PointLight], style: RoomStyle, rng: np.random.Generator) -> list[PointLight]:
    """``lights`` scaled, tinted and jittered as ``style`` says (unchanged by the default style)."""
    if style.light_scale == 1.0 and style.light_temperature_k is None and style.light_jitter_m == 0.0:
        return lights
    tint = (1.0, 1.0, 1.0) if style.light_temperature_k is None else temperature_rgb(style.light_temperature_k)
    W, D, _ = style.room_size
    lo = np.array([-W / 2, -D / 2, 0.0]) + LIGHT_CLEARANCE_M
    styled = []
    for light in lights:
        position = np.asarray(light.position) + rng.uniform(-1.0, 1.0, 3) * style.light_jitter_m
        hi = np.array([W / 2 - LIGHT_CLEARANCE_M, D / 2 - LIGHT_CLEARANCE_M, light.position[2]])
        position = np.clip(position, lo, hi)
        intensity = tuple(float(i * style.light_scale * t) for i, t in zip(light.intensity, tint, strict=True))
        styled.append(PointLight(tuple(float(p) for p in position), intensity))
    return styled


def build_room(seed: int = 0, style: RoomStyle | None = None) -> RoomGeometry:
    """The furnished room: shell (floor, ceiling, 4 walls), door, window, table, shelf, sofa, boxes, lamps.

    Furniture positions, sizes and colours are jittered deterministically from ``seed``; the middle of the
    room (the camera path of :func:`voxnerf.synthetic.cameras.camera_path`) stays free. ``style`` (default:
    none) resizes the shell (the door, table, shelf and sofa keep their distances to their walls), restyles
    lights and materials (see :class:`RoomStyle`); its random values come from their own generators, so a
    seed's furniture draws the same values whatever the style.
    """
    style = style or RoomStyle()
    placer = _Placer(np.random.default_rng(seed), style.room_size)
    for group in FURNITURE:
        placer.group(group)
    lights = [PointLight(placer.point(position), intensity) for position, intensity in LIGHTS]
    geom = placer.builder.build(_styled_lights(lights, style, np.random.default_rng([seed, 8])), seed)
    geom.objects = _restyled_materials(geom.objects, style, np.random.default_rng([seed, 7]))
    geom.room_size = tuple(style.room_size)
    return geom
