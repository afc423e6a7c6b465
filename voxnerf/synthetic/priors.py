"""Imperfect geometry priors sampled from the room's true surface: noisy point clouds and noisy meshes."""

from __future__ import annotations

import math

import numpy as np
import trimesh

from voxnerf.synthetic.geometry import RoomGeometry

PRIOR_KINDS = ("points", "mesh", "none")
"""What ``RoomSpec.prior_kind`` may name: a point-cloud prior, a mesh prior, or none."""
PRIOR_OUTLIER_FRACTION = 0.02
PRIOR_HOLES = 2
PRIOR_HOLE_RADIUS = (0.3, 0.45)
"""Metres: the radius range of the spherical regions removed from a point-cloud prior."""
PRIOR_MESH_MAX_EDGE = 0.08
"""Metres: the true mesh is subdivided to this edge length before its vertices are displaced."""


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

