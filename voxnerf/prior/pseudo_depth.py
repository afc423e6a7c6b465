"""Pseudo ground-truth depth from the geometry prior: the distance along a ray to the prior's surface.

A mesh prior is ray-cast exactly (open3d's Embree-backed ``RaycastingScene``, or trimesh's Embree intersector
where open3d is not installed). A point-cloud prior has no surface: the ray's first occupied octree leaf stands
in for it, and the depth is where the ray passes the mean of the points in the 3x3x3 leaves around it
(``SparseVoxelOctree.surface_hit``, the voxnerf sampler's window centre too). The leaf's entry point alone would
be biased towards the camera by half a leaf on average, and the depth loss would pull the surface forward.
"""

from __future__ import annotations

import copy
import functools

import numpy as np
import torch
from torch import Tensor

from voxnerf.prior.loading import GeometryPrior
from voxnerf.prior.octree import SparseVoxelOctree


class MeshCaster:
    """First hits of rays on a triangle mesh, cast with Embree.

    ``backend`` "open3d" uses open3d's ``RaycastingScene`` (open3d is a dependency of the package); "embree" uses
    trimesh's intersector over ``embreex``, for machines where open3d has no build (a GPU image on a Python that
    open3d has no wheel for, say). "auto" takes open3d when it imports, else embreex.
    """

    BACKENDS = ("auto", "open3d", "embree")

    def __init__(self, vertices: np.ndarray, faces: np.ndarray, backend: str = "auto") -> None:
        if backend not in self.BACKENDS:
            raise ValueError(f"unknown mesh caster backend {backend!r}; known: {', '.join(self.BACKENDS)}")
        vertices = np.ascontiguousarray(vertices, dtype=np.float32)
        faces = np.ascontiguousarray(faces, dtype=np.int64)
        if backend == "auto":
            backend = "open3d" if _importable("open3d") else "embree"
        self.backend = backend
        self._cast = _open3d_caster(vertices, faces) if backend == "open3d" else _embree_caster(vertices, faces)

    def distance(self, origins: np.ndarray, dirs: np.ndarray) -> np.ndarray:
        """[N] float32 distance along each ray [N, 3] to its first hit, in units of ``|dir|`` (inf where it hits
        nothing)."""
        return self._cast(np.ascontiguousarray(origins, dtype=np.float32), np.ascontiguousarray(dirs, dtype=np.float32))


def _importable(module: str) -> bool:
    """Whether ``module`` imports (an installed open3d can still fail to load a system library it needs)."""
    import importlib

    try:
        importlib.import_module(module)
    except (ImportError, OSError):
        return False
    return True


def _open3d_caster(vertices: np.ndarray, faces: np.ndarray):
    import open3d as o3d  # imported where used: only mesh priors are ray-cast with it

    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(vertices), o3d.core.Tensor(faces.astype(np.uint32)))

    def cast(origins: np.ndarray, dirs: np.ndarray) -> np.ndarray:
        rays = np.ascontiguousarray(np.concatenate([origins, dirs], axis=1))
        return scene.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy()

    return cast


def _embree_caster(vertices: np.ndarray, faces: np.ndarray):
    if not _importable("embreex"):
        raise ImportError("casting rays on a mesh prior needs open3d or embreex; neither is installed")
    import trimesh
    from trimesh.ray.ray_pyembree import RayMeshIntersector

    intersector = RayMeshIntersector(trimesh.Trimesh(vertices, faces, process=False), scale_to_box=False)

    def cast(origins: np.ndarray, dirs: np.ndarray) -> np.ndarray:
        t = np.full(len(origins), np.inf, dtype=np.float32)
        if len(origins) == 0:
            return t
        hits, ray_index, _ = intersector.intersects_location(origins, dirs, multiple_hits=False)
        d = dirs[ray_index].astype(np.float64)
        t[ray_index] = np.einsum("ij,ij->i", hits - origins[ray_index], d) / np.einsum("ij,ij->i", d, d)
        return t

    return cast


class PriorDepthRenderer:
    """Distances to the prior along rays, in the units of the prior (the caller's normalised frame)."""

    def __init__(self, prior: GeometryPrior, svo: SparseVoxelOctree) -> None:
        """``prior`` and ``svo`` must be in the same frame as the rays later passed in."""
        self._caster: MeshCaster | None = None
        if prior.kind == "mesh" and prior.mesh is not None:
            self._caster = MeshCaster(np.asarray(prior.mesh.vertices), np.asarray(prior.mesh.faces))
        elif svo.leaf_means is None:
            svo = copy.copy(svo)  # an octree restored without its means: the prior's points give them
            svo.leaf_means = svo.means_of(torch.from_numpy(prior.points).float().to(svo.device))
        self.svo = svo

    def ray_distance(
        self, origins: Tensor, dirs: Tensor, t_min: Tensor | float, t_max: Tensor | float
    ) -> tuple[Tensor, Tensor]:
        """First surface hit along each ray.

        Args:
            origins, dirs: [N, 3] float (``t`` is in units of ``|dir|``), any device.
            t_min, t_max: [N] or scalars.
        Returns:
            t [N] float32 (``t_max`` where invalid) and valid [N] bool: a hit exists and lies in
            [t_min, t_max]. Both on the inputs' device.
        """
        n = origins.shape[0]
        device = origins.device
        t_min = torch.as_tensor(t_min, dtype=torch.float32, device=device).expand(n)
        t_max = torch.as_tensor(t_max, dtype=torch.float32, device=device).expand(n)
        if self._caster is None:
            return self._point_cloud_distance(origins, dirs, t_min, t_max)
        cpu = functools.partial(torch.Tensor.to, device="cpu", dtype=torch.float32)
        t = torch.from_numpy(self._caster.distance(cpu(origins).numpy(), cpu(dirs).numpy())).to(device)
        valid = torch.isfinite(t) & (t >= t_min) & (t <= t_max)
        return torch.where(valid, t, t_max), valid

    def _point_cloud_distance(
        self, origins: Tensor, dirs: Tensor, t_min: Tensor, t_max: Tensor
    ) -> tuple[Tensor, Tensor]:
        """Where each ray passes the mean of its first occupied leaf's points, within the leaf: t [N], hit [N]."""
        return self.svo.surface_hit(origins, dirs, t_min, t_max)
