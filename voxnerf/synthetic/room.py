"""Building the furnished room from :data:`voxnerf.synthetic.furniture.FURNITURE` for a seed."""

from __future__ import annotations

import itertools
import re
from collections.abc import Mapping

import numpy as np

from voxnerf.synthetic.furniture import FURNITURE, LIGHTS, BookRows, Box, Coord, Cylinder, Group, Piece, Quad
from voxnerf.synthetic.geometry import ROOM_SIZE, PointLight, RoomBuilder, RoomGeometry
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


def room_anchors() -> dict[str, float]:
    """The anchors of the room frame: the walls ``x0, x1, y0, y1`` and the ceiling height ``H`` (m)."""
    W, D, H = ROOM_SIZE
    return {"x0": -W / 2, "x1": W / 2, "y0": -D / 2, "y1": D / 2, "H": H}


def _jitter_colour(rng: np.random.Generator, colour: tuple[float, float, float], amount: float = 0.08):
    return tuple(float(np.clip(c + rng.uniform(-amount, amount), 0.02, 0.95)) for c in colour)


def _jitter_material(rng: np.random.Generator, m: Material) -> Material:
    """``m`` with both colours jittered (base first, then accent)."""
    return Material(m.pattern, _jitter_colour(rng, m.base), _jitter_colour(rng, m.accent), m.scale, m.emission)


class _Placer:
    """Reads furniture groups into a :class:`RoomBuilder`, drawing every random value from one generator."""

    def __init__(self, rng: np.random.Generator) -> None:
        self.rng = rng
        self.builder = RoomBuilder()
        self.anchors: dict[str, float] = room_anchors()
        self.materials: dict[str, Material] = {}

    def point(self, exprs: tuple[Coord, ...]) -> tuple[float, ...]:
        return tuple(coord(e, self.anchors) for e in exprs)

    def material(self, m: str | Material) -> Material:
        return self.materials[m] if isinstance(m, str) else _jitter_material(self.rng, m)

    def group(self, group: Group) -> None:
        for name, (centre, half) in group.jitter.items():
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


def build_room(seed: int = 0) -> RoomGeometry:
    """The furnished room: shell (floor, ceiling, 4 walls), door, window, table, shelf, sofa, boxes, lamps.

    Furniture positions, sizes and colours are jittered deterministically from ``seed``; the middle of the
    room (the camera path of :func:`voxnerf.synthetic.cameras.camera_path`) stays free.
    """
    placer = _Placer(np.random.default_rng(seed))
    for group in FURNITURE:
        placer.group(group)
    lights = [PointLight(placer.point(position), intensity) for position, intensity in LIGHTS]
    return placer.builder.build(lights, seed)
