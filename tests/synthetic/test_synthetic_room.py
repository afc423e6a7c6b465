"""voxnerf.synthetic.furniture and .room: the furniture data is consistent and every seed furnishes the room
inside its walls, with the middle (the camera path) left free."""

from __future__ import annotations

import numpy as np
import open3d as o3d
import pytest

from voxnerf.synthetic import ROOM_SIZE, build_room, camera_path
from voxnerf.synthetic.furniture import FURNITURE, LIGHTS, BookRows, Box, Coord, Cylinder, Quad
from voxnerf.synthetic.room import coord, room_anchors
from voxnerf.synthetic.textures import PATTERNS, Material

SEEDS = range(12)


def _coords(piece) -> list[Coord]:
    """Every coordinate a piece names."""
    if isinstance(piece, Box):
        return [*piece.lo, *piece.hi]
    if isinstance(piece, Cylinder):
        return [*piece.centre, *piece.z]
    if isinstance(piece, Quad):
        return [c for corner in piece.corners for c in corner]
    assert isinstance(piece, BookRows), piece
    return [*piece.levels, piece.x, *piece.y]


def _room_bounds(margin: float = 1e-9) -> tuple[np.ndarray, np.ndarray]:
    W, D, H = ROOM_SIZE
    return np.array([-W / 2, -D / 2, 0.0]) - margin, np.array([W / 2, D / 2, H]) + margin


def test_coordinates_add_terms_left_to_right():
    anchors = {"y1": 2.0, "door_x": -1.2}
    assert coord(0.5, anchors) == 0.5 and coord(0, anchors) == 0.0 and isinstance(coord(0, anchors), float)
    assert coord("y1", anchors) == 2.0
    assert coord("door_x-0.45", anchors) == -1.2 - 0.45
    assert coord("y1-0.45+0.32-0.04", anchors) == 2.0 - 0.45 + 0.32 - 0.04
    assert coord("0.05-0.03", anchors) == 0.05 - 0.03
    assert coord("-door_x+1", anchors) == 1.2 + 1.0
    with pytest.raises(KeyError):
        coord("nowhere+0.1", anchors)


def test_furniture_data_is_consistent():
    """Names are unique, every anchor and shared material is defined before use, every pattern exists, and every
    coordinate (at the jitter centres) lies in the room."""
    anchors, materials, names = room_anchors(), set(), []
    lo, hi = _room_bounds()
    for group in FURNITURE:
        for name, (centre, half) in group.jitter.items():
            assert name not in anchors and half > 0, (group.name, name)
            anchors[name] = centre
        for name, expr in group.anchors.items():
            assert name not in anchors, (group.name, name)
            anchors[name] = coord(expr, anchors)
        for name, material in group.materials.items():
            assert name not in materials and material.pattern in PATTERNS, (group.name, name)
            materials.add(name)
        for piece in group.pieces:
            if isinstance(piece, BookRows):
                assert len(piece.levels) >= 2 and len(piece.palette) >= 1
                names.append("book_")
                continue
            names.append(piece.name)
            if isinstance(piece.material, Material):
                assert piece.material.pattern in PATTERNS, piece.name
            else:
                assert piece.material in materials, (piece.name, piece.material)
            values = [coord(c, anchors) for c in _coords(piece)]
            assert all(np.isfinite(values)), piece.name
        for piece in group.pieces:
            if isinstance(piece, Box):
                a, b = np.array([coord(c, anchors) for c in piece.lo]), np.array([coord(c, anchors) for c in piece.hi])
                assert (a < b).all() and (a >= lo).all() and (b <= hi).all(), piece.name
    assert len(names) == len(set(names)), "piece names are unique"
    assert not any(n.startswith("book_") for n in names if n != "book_"), "book names are the book rows' own"
    for position, intensity in LIGHTS:
        p = np.array([coord(c, anchors) for c in position])
        assert (p > lo).all() and (p < hi).all() and min(intensity) > 0


@pytest.mark.parametrize("seed", SEEDS)
def test_every_piece_is_inside_the_room(seed: int):
    geom = build_room(seed)
    lo, hi = _room_bounds()
    assert (geom.vertices >= lo).all() and (geom.vertices <= hi).all()
    for obj in geom.objects:
        a, b = np.asarray(obj.bounds[0]), np.asarray(obj.bounds[1])
        assert (a >= lo).all() and (b <= hi).all(), obj.name
        assert (b - a > 0).sum() >= 2, f"{obj.name} is degenerate"
    for light in geom.lights:
        assert (np.asarray(light.position) > lo).all() and (np.asarray(light.position) < hi).all()
    names = [o.name for o in geom.objects]
    assert len(names) == len(set(names))
    assert any(n.startswith("book_") for n in names)
    assert geom.triangle_object.min() == 0 and geom.triangle_object.max() == len(geom.objects) - 1


@pytest.mark.parametrize("seed", SEEDS)
def test_camera_path_stays_clear_for_every_seed(seed: int):
    positions = camera_path(120)[:, :3, 3].astype(np.float32)
    distance = build_room(seed).raycasting_scene.compute_distance(o3d.core.Tensor(positions)).numpy()
    assert distance.min() > 0.4, "the jittered table (its vase) comes closest to the path"


def test_build_room_is_deterministic_per_seed():
    a, b, other = build_room(4), build_room(4), build_room(5)
    np.testing.assert_array_equal(a.vertices, b.vertices)
    np.testing.assert_array_equal(a.triangles, b.triangles)
    assert a.objects == b.objects and a.lights == b.lights
    assert not np.array_equal(a.object_named("table_top").bounds, other.object_named("table_top").bounds)
    assert a.object_named("door").material != other.object_named("door").material
    with pytest.raises(KeyError, match="objects"):
        a.object_named("piano")
