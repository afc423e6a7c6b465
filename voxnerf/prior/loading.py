"""The scene geometry prior (paper III-B): a mesh or a point cloud, turned into points with a noise level.

A mesh is sampled uniformly over its surface; a point cloud is cleaned with statistical outlier removal.
Either way the result carries ``sigma``, the standard deviation of the prior's noise, given by the scene or
estimated here; the Sparse Voxel Octree is built from ``points`` with leaves of side ``sigma``.
"""

from __future__ import annotations

import json
import math
import struct
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import trimesh

from voxnerf.errors import SceneError

SUPPORTED_EXTENSIONS = (".ply", ".obj", ".glb", ".off")
# Mesh surface samples are ~sigma / 3 apart, so that nearly every sigma-sized octree leaf the surface crosses
# holds a sample and rays do not slip through the octree (docs/engine.md gives the measured rates).
SAMPLES_PER_SIGMA = 3
OUTLIER_NEIGHBOURS = 20
OUTLIER_STD_RATIO = 2.0
_PLANE_NEIGHBOURS = 32
_SIGMA_MAX_QUERIES = 50_000
# A GLB's JSON chunk this large is refused before it is read (a prior's layout is a few kilobytes).
MAX_GLB_JSON_BYTES = 64 * 1024 * 1024


@dataclass
class GeometryPrior:
    """Prior geometry as points (and the mesh, when there is one), in one coordinate frame.

    Attributes:
        kind: "mesh" or "points".
        points: [N, 3] float64, mesh surface samples or the filtered point cloud.
        mesh: the mesh (kind "mesh" only).
        sigma: noise standard deviation, same units as ``points``.
        sigma_estimated: True when ``sigma`` came from :func:`estimate_sigma` rather than the scene.
        num_input_points: points (kind "points") or vertices (kind "mesh") in the file.
        num_outliers_removed: points dropped by statistical outlier removal.
        num_nonfinite_removed: NaN/inf vertices dropped (with their faces, for a mesh).
    """

    kind: str
    points: np.ndarray
    mesh: trimesh.Trimesh | None
    sigma: float
    sigma_estimated: bool
    num_input_points: int
    num_outliers_removed: int
    num_nonfinite_removed: int = 0

    def transformed(self, center: np.ndarray, scale: float) -> GeometryPrior:
        """The prior in another frame: ``x -> (x - center) * scale`` (scale > 0); sigma scales too."""
        if not (math.isfinite(scale) and scale > 0):
            raise ValueError(f"scale must be positive and finite, got {scale}")
        center = np.asarray(center, dtype=np.float64).reshape(3)
        mesh = None
        if self.mesh is not None:
            mesh = self.mesh.copy()
            mesh.vertices = (np.asarray(mesh.vertices) - center) * scale
        return replace(self, points=(self.points - center) * scale, mesh=mesh, sigma=self.sigma * scale)

    def summary(self) -> dict:
        """JSON-able description for run reports."""
        return {
            "kind": self.kind,
            "sigma": float(self.sigma),
            "sigma_estimated": self.sigma_estimated,
            "points": int(len(self.points)),
            "input_points": self.num_input_points,
            "outliers_removed": self.num_outliers_removed,
            "nonfinite_removed": self.num_nonfinite_removed,
            "faces": int(len(self.mesh.faces)) if self.mesh is not None else 0,
        }


def load_prior(
    path: Path, sigma: float | None, *, max_points: int = 2_000_000, seed: int = 0
) -> GeometryPrior:
    """Load a prior from .ply/.obj/.glb/.off.

    Args:
        path: the geometry file. A file with faces is a mesh, one with vertices only a point cloud.
        sigma: the prior's noise standard deviation in the file's units, or None to estimate it.
        max_points: cap on the points kept (mesh samples or cloud points, randomly subsampled).
        seed: seed of the surface sampling and subsampling.
    Raises:
        SceneError naming ``path`` for a missing, unreadable or unsupported file, one without finite geometry,
        and a non-positive or non-finite ``sigma`` (key ``prior_sigma``).
    """
    path = Path(path)
    if sigma is not None and not (math.isfinite(sigma) and sigma > 0):
        raise SceneError(path, f"must be a positive finite number, got {sigma!r}", key="prior_sigma")
    vertices, faces = _read_geometry(path)
    rng = np.random.default_rng(seed)
    finite = np.isfinite(vertices).all(axis=1)
    num_nonfinite = int((~finite).sum())
    if faces is not None:
        return _mesh_prior(path, vertices, faces, finite, num_nonfinite, sigma, max_points, seed)
    points = vertices[finite]
    if len(points) == 0:
        raise SceneError(path, f"all {len(vertices)} points are NaN or inf")
    if len(points) > max_points:
        points = points[np.sort(rng.choice(len(points), max_points, replace=False))]
    points, removed = _remove_outliers(points)
    return GeometryPrior(
        kind="points",
        points=points,
        mesh=None,
        sigma=_resolve_sigma(path, sigma, points),
        sigma_estimated=sigma is None,
        num_input_points=len(vertices),
        num_outliers_removed=removed,
        num_nonfinite_removed=num_nonfinite,
    )


def prior_from_mesh(mesh: trimesh.Trimesh, sigma: float, name: str, *, max_points: int = 2_000_000,
                    seed: int = 0) -> GeometryPrior:
    """A mesh prior made in memory (e.g. fused from depth maps), as :func:`load_prior` makes one from a file;
    ``name`` stands for the file in errors."""
    vertices = np.asarray(mesh.vertices, dtype=np.float64)
    finite = np.isfinite(vertices).all(axis=1)
    return _mesh_prior(Path(name), vertices, np.asarray(mesh.faces, dtype=np.int64), finite,
                       int((~finite).sum()), sigma, max_points, seed)


def estimate_sigma(points: np.ndarray) -> float:
    """Noise standard deviation of a surface sampled by ``points`` [N, 3], in their units.

    Method: fit a plane to each point's 32 nearest neighbours (open3d covariances; the smallest eigenvalue is
    the mean squared residual, rescaled by k / (k - 3) for the fitted plane's degrees of freedom) and take the
    median RMS residual. Neighbourhoods narrower than the noise see only part of it, so while the typical
    point spacing is below the estimate, the cloud is randomly thinned and the fit repeated. The result is
    floored by the spacing of the full cloud (median nearest-neighbour distance): leaves smaller than the
    sampling spacing would leave holes in the octree. For a clean mesh's vertices the residual is near zero
    and the floor (vertex spacing) decides.
    """
    points = np.asarray(points, dtype=np.float64)
    if len(points) < _PLANE_NEIGHBOURS + 1:
        raise ValueError(f"need at least {_PLANE_NEIGHBOURS + 1} points to estimate sigma, got {len(points)}")
    rng = np.random.default_rng(0)
    floor = _spacing(points, rng)
    sample = points
    if len(sample) > _SIGMA_MAX_QUERIES:
        sample = sample[rng.choice(len(sample), _SIGMA_MAX_QUERIES, replace=False)]
    residual, spacing = _plane_residual(sample)
    for _ in range(10):
        if spacing >= residual or len(sample) < 4 * _PLANE_NEIGHBOURS:
            break
        keep = max(4 * _PLANE_NEIGHBOURS, int(len(sample) * (spacing / residual) ** 2 / 2))
        sample = sample[rng.choice(len(sample), keep, replace=False)]
        residual, spacing = _plane_residual(sample)
    return float(max(residual, floor))


def _read_geometry(path: Path) -> tuple[np.ndarray, np.ndarray | None]:
    """Vertices [V, 3] float64 and faces [F, 3] (None for a point cloud) of a geometry file."""
    if path.suffix.lower() not in SUPPORTED_EXTENSIONS:
        raise SceneError(path, f"unsupported prior format {path.suffix!r}; use one of {SUPPORTED_EXTENSIONS}")
    if not path.is_file():
        raise SceneError(path, "prior file not found")
    if path.suffix.lower() == ".glb":
        _refuse_external_uris(path)
    try:
        loaded = trimesh.load(path, process=False)
    except Exception as err:  # trimesh raises many types for malformed files
        raise SceneError(path, f"unreadable geometry: {err}") from err
    geometries = loaded.dump() if isinstance(loaded, trimesh.Scene) else [loaded]
    meshes = [g for g in geometries if isinstance(g, trimesh.Trimesh) and len(g.faces) > 0]
    if meshes:
        mesh = meshes[0] if len(meshes) == 1 else trimesh.util.concatenate(meshes)
        return np.asarray(mesh.vertices, dtype=np.float64), np.asarray(mesh.faces, dtype=np.int64)
    clouds = [np.asarray(g.vertices, np.float64).reshape(-1, 3) for g in geometries if hasattr(g, "vertices")]
    vertices = np.concatenate(clouds) if clouds else np.zeros((0, 3))
    if len(vertices) == 0:
        raise SceneError(path, "contains no geometry (no faces and no vertices)")
    return vertices, None


def _refuse_external_uris(path: Path) -> None:
    """Refuse (:class:`SceneError`) a GLB whose layout names another file: a buffer or image ``uri`` that is
    not a ``data:`` URI. trimesh would read it (since 5.0 only from the prior's own directory): a prior is one
    self-contained file, and an uploaded one must not read the scene's other files or anything else. A file
    that is no GLB is left to trimesh, which refuses it."""
    with open(path, "rb") as stream:
        header = stream.read(20)  # magic, version, length; the first chunk's length and type
        if len(header) < 20 or header[:4] != b"glTF" or header[16:20] != b"JSON":
            return
        (json_bytes,) = struct.unpack("<I", header[12:16])
        if json_bytes > MAX_GLB_JSON_BYTES:
            raise SceneError(path, f"GLB JSON chunk of {json_bytes} bytes; the limit is {MAX_GLB_JSON_BYTES}")
        text = stream.read(json_bytes)
    try:
        layout = json.loads(text)
    except (UnicodeDecodeError, ValueError) as err:
        raise SceneError(path, f"unreadable GLB JSON chunk: {err}") from None
    for kind in ("buffers", "images"):
        items = layout.get(kind) if isinstance(layout, dict) else None
        for index, item in enumerate(items if isinstance(items, list) else []):
            uri = item.get("uri") if isinstance(item, dict) else None
            if uri is not None and not (isinstance(uri, str) and uri.lower().startswith("data:")):
                why = f"names the external file {uri!r}: a GLB prior must hold its data itself"
                raise SceneError(path, why, key=f"{kind}[{index}].uri")


def _mesh_prior(
    path: Path,
    vertices: np.ndarray,
    faces: np.ndarray,
    finite: np.ndarray,
    num_nonfinite: int,
    sigma: float | None,
    max_points: int,
    seed: int,
) -> GeometryPrior:
    faces = faces[finite[faces].all(axis=1)]
    if len(faces) == 0:
        raise SceneError(path, f"no face has finite vertices ({num_nonfinite} NaN/inf vertices)")
    mesh = trimesh.Trimesh(vertices=np.where(finite[:, None], vertices, 0.0), faces=faces, process=False)
    mesh.remove_unreferenced_vertices()
    if not mesh.area > 0:
        raise SceneError(path, "mesh has zero surface area")
    value = _resolve_sigma(path, sigma, np.asarray(mesh.vertices))
    count = min(max_points, math.ceil(mesh.area / (value / SAMPLES_PER_SIGMA) ** 2))
    samples, _ = trimesh.sample.sample_surface(mesh, count, seed=seed)
    return GeometryPrior(
        kind="mesh",
        points=np.asarray(samples, dtype=np.float64),
        mesh=mesh,
        sigma=value,
        sigma_estimated=sigma is None,
        num_input_points=len(vertices),
        num_outliers_removed=0,
        num_nonfinite_removed=num_nonfinite,
    )


def _resolve_sigma(path: Path, sigma: float | None, points: np.ndarray) -> float:
    """``sigma`` when given (already checked), else the estimate from ``points`` (mesh vertices or cloud)."""
    if sigma is not None:
        return float(sigma)
    if len(points) <= _PLANE_NEIGHBOURS:
        raise SceneError(path, f"too few points ({len(points)}) to estimate the noise; give prior_sigma")
    estimate = estimate_sigma(points)
    if not (math.isfinite(estimate) and estimate > 0):
        raise SceneError(path, f"noise estimate is {estimate!r} (coincident points?); give prior_sigma")
    return estimate


def _remove_outliers(points: np.ndarray) -> tuple[np.ndarray, int]:
    """Statistical outlier removal (open3d): drop points whose mean distance to their 20 nearest neighbours
    is more than 2 standard deviations above the average."""
    import open3d as o3d  # imported where used: scenes that never need it run without open3d

    if len(points) <= OUTLIER_NEIGHBOURS:
        return points, 0
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    _, kept = cloud.remove_statistical_outlier(nb_neighbors=OUTLIER_NEIGHBOURS, std_ratio=OUTLIER_STD_RATIO)
    kept = np.sort(np.asarray(kept, dtype=np.int64))
    return points[kept], len(points) - len(kept)


def _plane_residual(points: np.ndarray) -> tuple[float, float]:
    """Median RMS residual to the plane of each point's k nearest neighbours, and median NN spacing."""
    import open3d as o3d  # imported where used: scenes that never need it run without open3d

    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    cloud.estimate_covariances(o3d.geometry.KDTreeSearchParamKNN(_PLANE_NEIGHBOURS))
    smallest = np.linalg.eigvalsh(np.asarray(cloud.covariances))[:, 0]
    k = _PLANE_NEIGHBOURS
    residual = float(np.median(np.sqrt(np.clip(smallest, 0.0, None) * k / (k - 3))))
    spacing = float(np.median(np.asarray(cloud.compute_nearest_neighbor_distance())))
    return residual, spacing


def _spacing(points: np.ndarray, rng: np.random.Generator, queries: int = 2000) -> float:
    """Median distance from a random subset of points to their nearest neighbour in the whole cloud."""
    import open3d as o3d  # imported where used: scenes that never need it run without open3d

    tree = o3d.geometry.KDTreeFlann(o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points)))
    picks = rng.choice(len(points), min(queries, len(points)), replace=False)
    distances = [math.sqrt(tree.search_knn_vector_3d(points[i], 2)[2][1]) for i in picks]
    return float(np.median(distances))
