"""The furnished room as data: groups of boxes, cylinders and quads placed relative to named anchors.

:func:`voxnerf.synthetic.room.build_room` reads :data:`FURNITURE` group by group. A coordinate (:data:`Coord`)
is a number or a string such as ``"door_x-0.45"`` or ``"y1-0.45+0.32-0.04"``: signed terms, each an anchor name
or a decimal number (no exponent), added left to right. The room frame gives the anchors ``x0, x1`` (west and
east walls), ``y0, y1`` (south and north walls) and ``H`` (ceiling height); groups add more.

Everything random comes from one generator seeded with the room's seed, in this order per group: the
``jitter`` anchors (``centre + uniform(-half, half)``, in order), the shared ``materials`` (in order), then per
piece its inline material and its random turn. Every material's two colours are jittered when it is drawn.
A shared material stays available to later groups by name.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field

from voxnerf.synthetic.textures import Material

Coord = float | str
"""A number (m), or anchor names and numbers joined by ``+`` / ``-``, added left to right."""
Point2 = tuple[Coord, Coord]
Point3 = tuple[Coord, Coord, Coord]
RGB = tuple[float, float, float]


@dataclass(frozen=True)
class Box:
    """A box from corner ``lo`` to corner ``hi``, turned about z by ``uniform(-turn, turn)`` rad when ``turn``."""

    name: str
    lo: Point3
    hi: Point3
    material: str | Material
    turn: float = 0.0


@dataclass(frozen=True)
class Cylinder:
    """A vertical cylinder (24 sections) around ``centre`` from height ``z[0]`` up to ``z[1]``."""

    name: str
    centre: Point2
    z: tuple[Coord, Coord]
    radius: float
    material: str | Material


@dataclass(frozen=True)
class Quad:
    """A planar quad from 4 corners in winding order (its normal by the right-hand rule)."""

    name: str
    corners: tuple[Point3, Point3, Point3, Point3]
    material: str | Material


@dataclass(frozen=True)
class BookRows:
    """Books named ``book_<n>`` standing in rows on shelf boards, random in size, spacing and colour.

    Each row stands on ``levels[k]`` (z), runs along +y from ``y[0]`` (plus a random indent) while a book
    still ends before ``y[1]``, and is at most ``levels[k + 1] - levels[k] - headroom`` tall. Books have their
    back at ``x`` and extend ``depth`` along +x. A book's colour is a random ``palette`` entry; after a book
    there is a random ``gap`` with probability ``gap_chance``, else ``spacing``.
    """

    levels: tuple[Coord, ...]
    x: Coord
    y: tuple[Coord, Coord]
    palette: tuple[RGB, ...]
    accent: RGB
    scale: float
    indent: tuple[float, float] = (0.0, 0.08)
    width: tuple[float, float] = (0.025, 0.07)
    height: tuple[float, float] = (0.18, 0.34)
    headroom: float = 0.06
    depth: tuple[float, float] = (0.16, 0.26)
    gap_chance: float = 0.12
    gap: tuple[float, float] = (0.05, 0.2)
    spacing: float = 0.002


Piece = Box | Cylinder | Quad | BookRows


@dataclass(frozen=True)
class Group:
    """Pieces placed together: ``jitter`` maps new anchors to ``(centre, half range)``, ``anchors`` maps
    derived anchors to coordinates, ``materials`` names materials the pieces share (see the module doc);
    ``follow`` keeps a jitter centre at its distance from a wall in a resized room."""

    name: str
    pieces: tuple[Piece, ...]
    jitter: Mapping[str, tuple[float, float]] = field(default_factory=dict)
    anchors: Mapping[str, Coord] = field(default_factory=dict)
    materials: Mapping[str, Material] = field(default_factory=dict)
    follow: Mapping[str, str] = field(default_factory=dict)
    """Jitter anchors whose centre moves with a wall (``x0 x1 y0 y1``) when the room is resized."""


def _plain(base: RGB, accent: RGB, scale: float = 0.1) -> Material:
    return Material("plain", base, accent, scale)


SHELF_LEVELS: tuple[Coord, ...] = (0.05, 0.5, 0.95, 1.4, "shelf_top-0.03")
"""Heights (m) of the bookshelf's boards' top faces."""

BOOK_PALETTE: tuple[RGB, ...] = (
    (0.6, 0.1, 0.1),
    (0.1, 0.3, 0.6),
    (0.15, 0.45, 0.2),
    (0.8, 0.65, 0.2),
    (0.3, 0.2, 0.4),
    (0.85, 0.85, 0.8),
    (0.1, 0.1, 0.12),
    (0.7, 0.35, 0.1),
)

SHELL = Group(
    "shell",
    (  # normals face into the room
        Quad("floor", (("x0", "y0", 0), ("x1", "y0", 0), ("x1", "y1", 0), ("x0", "y1", 0)),
             Material("planks", (0.45, 0.28, 0.14), (0.25, 0.13, 0.06), 0.18)),
        Quad("ceiling", (("x0", "y0", "H"), ("x0", "y1", "H"), ("x1", "y1", "H"), ("x1", "y0", "H")),
             Material("plaster", (0.85, 0.85, 0.82), (0.75, 0.77, 0.8), 0.7)),
        Quad("wall_south", (("x0", "y0", 0), ("x0", "y0", "H"), ("x1", "y0", "H"), ("x1", "y0", 0)),
             Material("tiles", (0.75, 0.72, 0.62), (0.35, 0.5, 0.6), 0.3)),
        Quad("wall_north", (("x0", "y1", 0), ("x1", "y1", 0), ("x1", "y1", "H"), ("x0", "y1", "H")),
             Material("plaster", (0.55, 0.65, 0.5), (0.8, 0.82, 0.7), 0.5)),
        Quad("wall_west", (("x0", "y0", 0), ("x0", "y1", 0), ("x0", "y1", "H"), ("x0", "y0", "H")),
             Material("plaster", (0.7, 0.55, 0.45), (0.85, 0.78, 0.65), 0.4)),
        Quad("wall_east", (("x1", "y0", 0), ("x1", "y0", "H"), ("x1", "y1", "H"), ("x1", "y1", 0)),
             Material("marble", (0.82, 0.8, 0.78), (0.3, 0.3, 0.35), 0.6)),
    ),
)

DOOR = Group(
    "door",  # on the south wall, with frame and knob
    (
        Box("door", ("door_x-0.45", "y0", 0.0), ("door_x+0.45", "y0+0.04", 2.05), "door_wood"),
        Box("door_trim_left", ("door_x-0.53", "y0", 0.0), ("door_x-0.45", "y0+0.07", 2.13), "trim"),
        Box("door_trim_right", ("door_x+0.45", "y0", 0.0), ("door_x+0.53", "y0+0.07", 2.13), "trim"),
        Box("door_trim_top", ("door_x-0.45", "y0", 2.05), ("door_x+0.45", "y0+0.07", 2.13), "trim"),
        Cylinder("door_knob", ("door_x+0.33", "y0+0.09"), (0.98, 1.04), 0.035,
                 Material("plain", (0.8, 0.7, 0.3), (0.5, 0.4, 0.1), 0.05)),
    ),
    jitter={"door_x": (-1.15, 0.1)},
    follow={"door_x": "x0"},
    materials={
        "door_wood": Material("wood", (0.55, 0.35, 0.2), (0.3, 0.16, 0.08), 0.25),
        "trim": Material("plain", (0.9, 0.9, 0.88), (0.7, 0.7, 0.7), 0.3),
    },
)

WINDOW = Group(
    "window",  # on the east wall: the outside view (light-emitting) plus frame, cross bars and sill
    (
        Box("window_view", ("x1-0.03", "wy0", "wz0"), ("x1-0.01", "wy1", "wz1"),
            Material("sky", (0.35, 0.55, 0.9), (0.75, 0.85, 0.95), 0.5, emission=0.9)),
        Box("window_frame_bottom", ("x1-0.08", "wy0-0.06", "wz0-0.06"), ("x1", "wy1+0.06", "wz0"), "frame"),
        Box("window_frame_top", ("x1-0.08", "wy0-0.06", "wz1"), ("x1", "wy1+0.06", "wz1+0.06"), "frame"),
        Box("window_frame_left", ("x1-0.08", "wy0-0.06", "wz0"), ("x1", "wy0", "wz1"), "frame"),
        Box("window_frame_right", ("x1-0.08", "wy1", "wz0"), ("x1", "wy1+0.06", "wz1"), "frame"),
        Box("window_bar_vertical", ("x1-0.06", "wy_mid-0.02", "wz0"), ("x1-0.03", "wy_mid+0.02", "wz1"), "frame"),
        Box("window_bar_horizontal", ("x1-0.06", "wy0", "wz_mid-0.02"), ("x1-0.03", "wy1", "wz_mid+0.02"), "frame"),
        Box("window_sill", ("x1-0.2", "wy0-0.12", "wz0-0.1"), ("x1", "wy1+0.12", "wz0-0.06"), "frame"),
    ),
    anchors={"wy0": 0.2, "wy1": 1.4, "wz0": 0.95, "wz1": 2.0, "wy_mid": (0.2 + 1.4) / 2, "wz_mid": (0.95 + 2.0) / 2},
    materials={"frame": Material("plain", (0.92, 0.92, 0.9), (0.8, 0.8, 0.8), 0.3)},
)

TABLE = Group(
    "table",  # near the south-east corner: top and 4 legs, a box and a vase on it; the top's centre stays clear
    (
        Box("table_top", ("tx-0.6", "ty-0.4", "top_z-0.04"), ("tx+0.6", "ty+0.4", "top_z"), "table_wood"),
        Cylinder("table_leg_0", ("tx-0.53", "ty-0.33"), (0.0, "top_z-0.04"), 0.03, "table_wood"),
        Cylinder("table_leg_1", ("tx-0.53", "ty+0.33"), (0.0, "top_z-0.04"), 0.03, "table_wood"),
        Cylinder("table_leg_2", ("tx+0.53", "ty-0.33"), (0.0, "top_z-0.04"), 0.03, "table_wood"),
        Cylinder("table_leg_3", ("tx+0.53", "ty+0.33"), (0.0, "top_z-0.04"), 0.03, "table_wood"),
        Box("table_box", ("tx+0.2", "ty-0.3", "top_z"), ("tx+0.5", "ty-0.1", "top_z+0.15"),
            Material("plain", (0.7, 0.2, 0.15), (0.9, 0.5, 0.3), 0.1), turn=0.4),
        Cylinder("table_vase", ("tx-0.4", "ty+0.2"), ("top_z", "top_z+0.28"), 0.06,
                 Material("marble", (0.2, 0.35, 0.6), (0.9, 0.9, 0.95), 0.1)),
    ),
    jitter={"tx": (1.6, 0.08), "ty": (-1.2, 0.08)},
    follow={"tx": "x1", "ty": "y0"},
    anchors={"top_z": 0.75},
    materials={"table_wood": Material("wood", (0.6, 0.42, 0.25), (0.35, 0.2, 0.1), 0.2)},
)

SHELF = Group(
    "shelf",  # against the west wall (0.38 m deep), with rows of books; a painting beside it
    (
        Box("shelf_back", ("x0", "sy0", 0.0), ("x0+0.02", "sy1", "shelf_top"), "shelf_wood"),
        Box("shelf_side_left", ("x0", "sy0", 0.0), ("x0+0.38", "sy0+0.03", "shelf_top"), "shelf_wood"),
        Box("shelf_side_right", ("x0", "sy1-0.03", 0.0), ("x0+0.38", "sy1", "shelf_top"), "shelf_wood"),
        Box("shelf_board_0", ("x0+0.02", "sy0+0.03", "0.05-0.03"), ("x0+0.38", "sy1-0.03", 0.05), "shelf_wood"),
        Box("shelf_board_1", ("x0+0.02", "sy0+0.03", "0.5-0.03"), ("x0+0.38", "sy1-0.03", 0.5), "shelf_wood"),
        Box("shelf_board_2", ("x0+0.02", "sy0+0.03", "0.95-0.03"), ("x0+0.38", "sy1-0.03", 0.95), "shelf_wood"),
        Box("shelf_board_3", ("x0+0.02", "sy0+0.03", "1.4-0.03"), ("x0+0.38", "sy1-0.03", 1.4), "shelf_wood"),
        Box("shelf_board_4", ("x0+0.02", "sy0+0.03", "shelf_top-0.03-0.03"), ("x0+0.38", "sy1-0.03", "shelf_top-0.03"),
            "shelf_wood"),
        BookRows(SHELF_LEVELS, "x0+0.03", ("sy0+0.03", "sy1-0.04"), BOOK_PALETTE, (0.9, 0.85, 0.7), 0.05),
        Box("painting_west", ("x0", -1.3, 1.15), ("x0+0.03", -0.45, 1.75),
            Material("painting", (0.6, 0.9, 0.95), (0.2, 0.2, 0.2), 0.2)),
    ),
    jitter={"sy0": (-0.2, 0.08)},
    anchors={"sy1": "sy0+1.3", "shelf_top": 1.9},
    materials={"shelf_wood": Material("wood", (0.42, 0.26, 0.15), (0.22, 0.12, 0.06), 0.15)},
)

SOFA = Group(
    "sofa",  # against the north wall, on feet of the shelf's wood, with a painting above it
    (
        Box("sofa_base", ("cx_sofa-1.0", "y1-0.85", 0.1), ("cx_sofa+1.0", "y1-0.05", 0.42), "fabric"),
        Box("sofa_back", ("cx_sofa-1.0", "y1-0.25", 0.42), ("cx_sofa+1.0", "y1-0.05", 0.88), "fabric"),
        Box("sofa_arm_left", ("cx_sofa-1.0", "y1-0.85", 0.42), ("cx_sofa-0.8", "y1-0.25", 0.62), "fabric"),
        Box("sofa_arm_right", ("cx_sofa+0.8", "y1-0.85", 0.42), ("cx_sofa+1.0", "y1-0.25", 0.62), "fabric"),
        Box("sofa_cushion_0", ("cx_sofa-0.78", "y1-0.83", 0.42), ("cx_sofa-0.01", "y1-0.27", 0.52), "cushion"),
        Box("sofa_cushion_1", ("cx_sofa+0.01", "y1-0.83", 0.42), ("cx_sofa+0.78", "y1-0.27", 0.52), "cushion"),
        Box("sofa_foot_0", ("cx_sofa-0.9-0.04", "y1-0.45-0.32-0.04", 0.0),
            ("cx_sofa-0.9+0.04", "y1-0.45-0.32+0.04", 0.1), "shelf_wood"),
        Box("sofa_foot_1", ("cx_sofa-0.9-0.04", "y1-0.45+0.32-0.04", 0.0),
            ("cx_sofa-0.9+0.04", "y1-0.45+0.32+0.04", 0.1), "shelf_wood"),
        Box("sofa_foot_2", ("cx_sofa+0.9-0.04", "y1-0.45-0.32-0.04", 0.0),
            ("cx_sofa+0.9+0.04", "y1-0.45-0.32+0.04", 0.1), "shelf_wood"),
        Box("sofa_foot_3", ("cx_sofa+0.9-0.04", "y1-0.45+0.32-0.04", 0.0),
            ("cx_sofa+0.9+0.04", "y1-0.45+0.32+0.04", 0.1), "shelf_wood"),
        Box("painting", ("cx_sofa-0.55", "y1-0.03", 1.2), ("cx_sofa+0.55", "y1", 1.9),
            Material("painting", (0.95, 0.85, 0.9), (0.2, 0.2, 0.2), 0.25)),
    ),
    jitter={"cx_sofa": (0.6, 0.1)},
    materials={
        "fabric": Material("fabric", (0.25, 0.3, 0.45), (0.75, 0.6, 0.3), 0.16),
        "cushion": Material("plain", (0.7, 0.25, 0.2), (0.9, 0.6, 0.3), 0.1),
    },
)

FLOOR_OBJECTS = Group(
    "floor_objects",  # stacked crates in the south-west corner, a bin, a floor lamp, a rug; the ceiling lamp
    (
        Box("crate", ("x0+0.2", "y0+0.2", 0.0), ("x0+0.7", "y0+0.7", 0.5),
            Material("wood", (0.7, 0.55, 0.35), (0.45, 0.3, 0.15), 0.08), turn=0.2),
        Box("crate_small", ("x0+0.3", "y0+0.3", 0.5), ("x0+0.62", "y0+0.6", 0.75),
            _plain((0.3, 0.55, 0.35), (0.6, 0.8, 0.5)), turn=0.6),
        Cylinder("bin", ("x1-0.35", "y1-0.35"), (0.0, 0.42), 0.16, _plain((0.15, 0.15, 0.18), (0.4, 0.4, 0.45))),
        Cylinder("floor_lamp_base", ("lamp_x", "lamp_y"), (0.0, 0.04), 0.15, _plain((0.1, 0.1, 0.1), (0.3, 0.3, 0.3))),
        Cylinder("floor_lamp_pole", ("lamp_x", "lamp_y"), (0.04, 1.45), 0.02, _plain((0.6, 0.6, 0.6), (0.8, 0.8, 0.8))),
        Cylinder("floor_lamp_shade", ("lamp_x", "lamp_y"), (1.45, 1.72), 0.19,
                 Material("fabric", (0.9, 0.85, 0.7), (0.7, 0.6, 0.4), 0.05)),
        Box("rug", (-1.0, -0.95, 0.0), (1.0, 0.7, 0.012), Material("tiles", (0.6, 0.2, 0.2), (0.85, 0.75, 0.5), 0.2)),
        Cylinder("ceiling_lamp", (0.0, 0.0), ("H-0.12", "H"), 0.22, _plain((0.95, 0.95, 0.9), (0.9, 0.9, 0.8))),
    ),
    anchors={"lamp_x": "x0+0.4", "lamp_y": "y1-0.35"},
)

FURNITURE: tuple[Group, ...] = (SHELL, DOOR, WINDOW, TABLE, SHELF, SOFA, FLOOR_OBJECTS)
"""The room's groups in build order (which is also the order of its objects and of the random draws)."""

LIGHTS: tuple[tuple[Point3, RGB], ...] = (
    ((0.0, 0.0, "H-0.3"), (1.6, 1.5, 1.35)),  # under the ceiling lamp
    (("x1-0.6", "wy_mid", 1.7), (0.55, 0.6, 0.7)),  # in front of the window
)
"""Point lights: position and linear RGB intensity, read after every group's anchors are known."""
