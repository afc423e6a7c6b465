"""The room as a triangle soup: named objects with materials and bounds, point lights, and the mesh builder.

World frame: metres, +Z up, the room spans ``x in [-W/2, W/2]``, ``y in [-D/2, D/2]``, ``z in [0, H]`` with
``(W, D, H)`` the room's size (``voxnerf.synthetic.dimensions.ROOM_SIZE`` by default).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property
from typing import TYPE_CHECKING

import numpy as np
import trimesh

from voxnerf.synthetic.dimensions import ROOM_SIZE

if TYPE_CHECKING:
    import open3d as o3d

    from voxnerf.synthetic.textures import Material



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
        import open3d as o3d  # imported where used: a machine without open3d can still load the package

        scene = o3d.t.geometry.RaycastingScene()
        scene.add_triangles(
            o3d.core.Tensor(self.vertices.astype(np.float32)),
            o3d.core.Tensor(self.triangles.astype(np.uint32)),
        )
        return scene


class RoomBuilder:
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
