"""A geometry prior from the scan's own depth maps (paper III-B, the "TSDF fusion" source), and the depth noise.

The training frames' depth maps are fused into a truncated signed distance field (open3d's tensor
``VoxelBlockGrid``) and meshed by marching cubes. Nothing is hard-coded to a sensor: the voxel size, the
truncation and the prior's sigma follow from the data.

1. A first fusion at a coarse voxel (four pixel footprints at the median depth, and at least 1/512 of the
   scene's extent) gives a mesh.
2. The sensor's noise is measured against that mesh: each training depth map is compared with the mesh's
   depth along the same rays, the robust spread (1.4826 x MAD) is taken in bins of depth, and
   ``sigma(z) = s0 + s2 z^2`` (the shape of structured-light and time-of-flight noise) is fitted to the bins.
   The residual holds pose error and registration error as well as sensor noise: it is how far the depth maps
   disagree with the fused surface, which is what the prior's sigma must describe.
3. The final fusion uses voxels of the measured sigma at the median depth (never below two pixel footprints or
   1/1024 of the extent), truncation four voxels; the prior's sigma is that voxel size. The noise is measured
   again against the final mesh (a coarse surface adds its own error to the residuals).

Units: depths, poses, voxels and sigmas are in scene units (the depth maps' metres after
``depth_unit_scale_factor``); ``c2w`` are camera-to-world in OpenGL axes (camera looks along -Z).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import trimesh

from voxnerf.cameras.rules import Intrinsics

# OpenGL camera axes (x right, y up, looking along -z) to OpenCV's (x right, y down, looking along +z).
OPENGL_TO_OPENCV = np.diag([1.0, -1.0, -1.0, 1.0])
COARSE_FOOTPRINTS = 4  # pixel footprints at the median depth per voxel of the first fusion
FINE_FOOTPRINTS = 2  # the final voxel is never below this many footprints (finer voxels see single pixels)
TRUNCATION_VOXELS = 4.0
MAX_VOXELS_PER_SIDE = 1024  # the voxel is at least extent / this (bounds memory and time on any scene)
COARSE_VOXELS_PER_SIDE = 512
NOISE_BINS = 8
NOISE_SAMPLES_PER_FRAME = 20_000
FAR_LIMIT_OVER_P99 = 2.0  # depth beyond twice the 99th percentile is left out of the fusion
OUTLIER_VOXELS = 3.0  # residuals beyond this many coarse voxels are misses (edges, moved objects), not noise


class FusionError(ValueError):
    """The depth maps cannot make a prior (no valid depth, nothing fused); the message says why."""


@dataclass(frozen=True)
class DepthView:
    """One frame's depth: float32 [H, W] scene units (NaN invalid), its camera and pose; optionally its colour
    registered to the depth, [H, W, 3] float in [0, 1] or uint8 (fused into vertex colours when every view has
    one)."""

    depth: np.ndarray
    intrinsics: Intrinsics  # of the depth map (its own size)
    c2w: np.ndarray  # [4, 4] float64, OpenGL axes, scene units
    rgb: np.ndarray | None = None


@dataclass(frozen=True)
class DepthNoise:
    """Measured depth noise ``sigma(z) = s0 + s2 * z^2`` (scene units), from ``residuals`` samples."""

    s0: float
    s2: float
    median_depth: float
    residuals: int

    def sigma(self, z):
        """sigma at z-depth ``z`` (array or float), scene units."""
        return self.s0 + self.s2 * z * z

    @property
    def at_median(self) -> float:
        return float(self.sigma(self.median_depth))

    def describe(self) -> str:
        return (f"sigma(z) = {self.s0 * 1000:.3g} mm + {self.s2 * 1000:.3g} mm/m^2 z^2 "
                f"({self.at_median * 100:.2g} cm at the median depth {self.median_depth:.2f}; "
                f"{self.residuals} residuals)")

    def as_dict(self) -> dict:
        return {"s0": self.s0, "s2": self.s2, "median_depth": self.median_depth, "sigma_at_median": self.at_median,
                "residuals": self.residuals}


@dataclass
class FusedPrior:
    """The fused mesh and how it was made."""

    mesh: trimesh.Trimesh
    voxel: float
    truncation: float
    sigma: float
    noise: DepthNoise
    frames: int
    valid_fraction: float
    voxel_rule: str  # which lower bound set the voxel

    def describe(self) -> str:
        return (f"{self.frames} training frames with depth -> TSDF prior, {self.voxel * 100:.2g} cm voxels "
                f"({self.voxel_rule}), sigma {self.sigma * 100:.2g} cm")

    def summary(self) -> dict:
        return {"source": "tsdf_fusion", "frames": self.frames, "voxel": self.voxel, "voxel_rule": self.voxel_rule,
                "truncation": self.truncation,
                "sigma": self.sigma, "valid_depth_fraction": self.valid_fraction, "noise": self.noise.as_dict(),
                "vertices": int(len(self.mesh.vertices)), "faces": int(len(self.mesh.faces))}


def fuse_depth_prior(views: list[DepthView]) -> FusedPrior:
    """The TSDF prior of ``views`` (module docstring). Raises FusionError when no depth is usable."""
    valid = _valid_depths(views)
    median_depth = float(np.median(valid))
    footprint = median_depth / float(np.median([v.intrinsics.fl_x for v in views]))
    extent = _extent(views)
    coarse = max(COARSE_FOOTPRINTS * footprint, extent / COARSE_VOXELS_PER_SIDE)
    # Far outliers (a few saturated or mis-scaled pixels) would stretch the fused volume for nothing.
    depth_max = min(float(valid.max()) * 1.001, FAR_LIMIT_OVER_P99 * float(np.percentile(valid, 99)))
    coarse_mesh = fuse_tsdf(views, coarse, TRUNCATION_VOXELS * coarse, depth_max)
    noise = measure_noise(coarse_mesh, views, OUTLIER_VOXELS * coarse)
    rules = {"the depth noise measured at the median depth": noise.at_median,
             f"{FINE_FOOTPRINTS} pixel footprints at the median depth": FINE_FOOTPRINTS * footprint,
             f"1/{MAX_VOXELS_PER_SIDE} of the scene's extent": extent / MAX_VOXELS_PER_SIDE}
    voxel_rule = max(rules, key=rules.get)
    voxel = rules[voxel_rule]
    mesh = coarse_mesh
    if not math.isclose(voxel, coarse, rel_tol=0.1):
        mesh = fuse_tsdf(views, voxel, TRUNCATION_VOXELS * voxel, depth_max)
        noise = measure_noise(mesh, views, OUTLIER_VOXELS * coarse)  # the finer surface separates noise better
    total = sum(v.depth.size for v in views)
    return FusedPrior(mesh, voxel, TRUNCATION_VOXELS * voxel, voxel, noise, len(views), len(valid) / total,
                      voxel_rule)


def _valid_depths(views: list[DepthView]) -> np.ndarray:
    if not views:
        raise FusionError("no training frame has a depth map")
    valid = np.concatenate([v.depth[np.isfinite(v.depth) & (v.depth > 0)] for v in views])
    if len(valid) == 0:
        raise FusionError(f"the depth maps of the {len(views)} training frames hold no valid depth")
    return valid


def _extent(views: list[DepthView]) -> float:
    """Largest side of the box holding the cameras and (robustly: 1st-99th percentile) the depth points."""
    points = np.concatenate([backproject(v, stride=8) for v in views] + [np.stack([v.c2w[:3, 3] for v in views])])
    lo, hi = np.percentile(points, 1, axis=0), np.percentile(points, 99, axis=0)
    return float(max((hi - lo).max(), 1e-9))


def point_map(view: DepthView) -> np.ndarray:
    """World points float64 [H, W, 3] (scene units) of every pixel's centre at its z-depth; NaN where the depth
    is invalid (non-finite or not positive)."""
    k = view.intrinsics
    v, u = np.mgrid[0 : view.depth.shape[0], 0 : view.depth.shape[1]] + 0.5
    z = view.depth.astype(np.float64)
    z = np.where(np.isfinite(z) & (z > 0), z, np.nan)
    cam = np.stack([(u - k.cx) / k.fl_x * z, -(v - k.cy) / k.fl_y * z, -z], axis=-1)
    return cam @ view.c2w[:3, :3].T + view.c2w[:3, 3]


def backproject(view: DepthView, stride: int = 1) -> np.ndarray:
    """World points [M, 3] of the valid pixels of ``view`` (every ``stride``-th row and column), row-major
    (the order of ``view.depth[valid]``)."""
    points = point_map(view)[::stride, ::stride].reshape(-1, 3)
    return points[np.isfinite(points).all(axis=1)]


def _o3d_camera(view: DepthView):
    import open3d as o3d

    k = view.intrinsics
    # open3d's pixel (0, 0) is at the pixel's centre; cx, cy here are continuous (centre of the image at w/2).
    intrinsic = o3d.core.Tensor([[k.fl_x, 0.0, k.cx - 0.5], [0.0, k.fl_y, k.cy - 0.5], [0.0, 0.0, 1.0]],
                                o3d.core.float64)
    extrinsic = o3d.core.Tensor(OPENGL_TO_OPENCV @ np.linalg.inv(view.c2w), o3d.core.float64)
    return intrinsic, extrinsic


def fuse_tsdf(views: list[DepthView], voxel: float, truncation: float, depth_max: float,
              min_views: float = 0.5) -> trimesh.Trimesh:
    """Marching-cubes mesh of the TSDF of ``views`` (voxel and truncation in scene units), with vertex colours
    (uint8 RGBA) when every view has ``rgb``. Voxels seen by fewer than ``min_views`` views are left out (each
    view adds a weight of 1; the default keeps every surface some view saw).

    Raises FusionError when the fusion leaves no surface (e.g. every depth beyond ``depth_max``).
    """
    import open3d as o3d

    coloured = bool(views) and all(v.rgb is not None for v in views)
    attrs = (("tsdf", 1), ("weight", 1)) + ((("color", 3),) if coloured else ())
    grid = o3d.t.geometry.VoxelBlockGrid(
        attr_names=tuple(name for name, _ in attrs), attr_dtypes=tuple(o3d.core.float32 for _ in attrs),
        attr_channels=tuple((c,) for _, c in attrs), voxel_size=float(voxel), block_resolution=16,
        block_count=50_000,
    )
    kwargs = {"depth_scale": 1.0, "depth_max": float(depth_max), "trunc_voxel_multiplier": float(truncation / voxel)}
    for view in views:
        depth = np.ascontiguousarray(np.nan_to_num(view.depth, nan=0.0, posinf=0.0, neginf=0.0), np.float32)
        image = o3d.t.geometry.Image(depth)
        intrinsic, extrinsic = _o3d_camera(view)
        try:
            blocks = grid.compute_unique_block_coordinates(image, intrinsic, extrinsic, **kwargs)
        except RuntimeError:  # open3d raises when no pixel of this frame lies within depth_max
            continue
        if coloured:
            colour = o3d.t.geometry.Image(np.ascontiguousarray(_unit_rgb(view.rgb), np.float32))
            grid.integrate(blocks, image, colour, intrinsic, extrinsic, **kwargs)
        else:
            grid.integrate(blocks, image, intrinsic, extrinsic, **kwargs)
    try:
        # open3d keeps voxels whose weight exceeds the threshold, and each frame adds 1: by default this keeps
        # every surface some frame saw (a wall seen once is a measurement too).
        fused = grid.extract_triangle_mesh(weight_threshold=float(min_views)).to_legacy()
    except RuntimeError:  # open3d raises on an empty volume
        fused = o3d.geometry.TriangleMesh()
    mesh = trimesh.Trimesh(np.asarray(fused.vertices), np.asarray(fused.triangles), process=False)
    if coloured and fused.has_vertex_colors():
        mesh.visual.vertex_colors = np.round(np.clip(np.asarray(fused.vertex_colors), 0.0, 1.0) * 255).astype(np.uint8)
    if len(mesh.faces) == 0 or not np.isfinite(mesh.vertices).all():
        raise FusionError(f"TSDF fusion of {len(views)} depth maps left no surface (voxel {voxel:.4g})")
    return canonical_mesh(mesh)


def _unit_rgb(rgb: np.ndarray) -> np.ndarray:
    """[H, W, 3] uint8 or float -> float32 in [0, 1]."""
    if rgb.dtype == np.uint8:
        return rgb.astype(np.float32) / 255.0
    return np.clip(np.nan_to_num(rgb.astype(np.float32), nan=0.0), 0.0, 1.0)


def canonical_mesh(mesh: trimesh.Trimesh) -> trimesh.Trimesh:
    """The same mesh with its vertices and faces in a fixed order (open3d's parallel marching cubes emits them
    in a different order from run to run; the prior's surface samples, and so training, depend on it).
    Vertices sort lexicographically; each face is rotated to start at its smallest index (orientation kept),
    then faces sort lexicographically. Vertex colours, when the mesh has them, follow their vertices."""
    vertices = np.asarray(mesh.vertices)
    order = np.lexsort(vertices.T[::-1])
    rank = np.empty_like(order)
    rank[order] = np.arange(len(order))
    faces = rank[np.asarray(mesh.faces)]
    shift = np.argmin(faces, axis=1)
    faces = np.take_along_axis(faces, (shift[:, None] + np.arange(3)[None]) % 3, axis=1)
    faces = faces[np.lexsort(faces.T[::-1])]
    colours = None
    if mesh.visual.kind == "vertex":
        colours = np.asarray(mesh.visual.vertex_colors)[order]
    return trimesh.Trimesh(vertices[order], faces, vertex_colors=colours, process=False)


def _cast_z(scene, view: DepthView, pixels: tuple[np.ndarray, np.ndarray]) -> np.ndarray:
    import open3d as o3d

    k = view.intrinsics
    rows, cols = pixels
    cam = np.stack([(cols + 0.5 - k.cx) / k.fl_x, -(rows + 0.5 - k.cy) / k.fl_y, -np.ones(len(rows))], axis=1)
    dirs = cam @ view.c2w[:3, :3].T  # |cam_z| = 1, so the hit distance along dirs is the z-depth
    rays = np.concatenate([np.broadcast_to(view.c2w[:3, 3], dirs.shape), dirs], axis=1).astype(np.float32)
    return scene.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy().astype(np.float64)


def measure_noise(mesh: trimesh.Trimesh, views: list[DepthView], outlier: float, seed: int = 0) -> DepthNoise:
    """Fit ``sigma(z) = s0 + s2 z^2`` to the depth maps' residuals against ``mesh`` (module docstring).

    Residuals beyond ``outlier`` (scene units) are left out. With too few residuals for a fit, a constant
    sigma from all of them; with none, ``outlier / 3``.
    """
    import open3d as o3d

    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(np.ascontiguousarray(mesh.vertices, np.float32)),
                        o3d.core.Tensor(np.ascontiguousarray(mesh.faces, np.uint32)))
    rng = np.random.default_rng(seed)
    depths, residuals = [], []
    for view in views:
        rows, cols = np.nonzero(np.isfinite(view.depth) & (view.depth > 0))
        if len(rows) > NOISE_SAMPLES_PER_FRAME:
            pick = rng.choice(len(rows), NOISE_SAMPLES_PER_FRAME, replace=False)
            rows, cols = rows[pick], cols[pick]
        z = view.depth[rows, cols].astype(np.float64)
        r = z - _cast_z(scene, view, (rows, cols))
        keep = np.isfinite(r) & (np.abs(r) < outlier)
        depths.append(z[keep])
        residuals.append(r[keep])
    return fit_noise(np.concatenate(depths), np.concatenate(residuals), outlier / 3.0)


def fit_noise(z: np.ndarray, residual: np.ndarray, fallback: float) -> DepthNoise:
    """``sigma(z) = s0 + s2 z^2`` (s0, s2 >= 0) fitted to the robust spread of ``residual`` in depth bins."""
    if len(z) == 0:
        return DepthNoise(fallback, 0.0, 0.0, 0)
    median = float(np.median(z))
    if len(z) < 50 * NOISE_BINS:
        return DepthNoise(_robust_std(residual) or fallback, 0.0, median, len(z))
    edges = np.quantile(z, np.linspace(0, 1, NOISE_BINS + 1))
    centres, spreads = [], []
    for lo, hi in zip(edges[:-1], edges[1:], strict=True):
        inside = (z >= lo) & (z <= hi)
        centres.append(float(np.median(z[inside])))
        spreads.append(_robust_std(residual[inside]))
    s0, s2 = _nonnegative_fit(np.asarray(centres), np.asarray(spreads))
    if not (s0 + s2 * median * median > 0):
        s0 = _robust_std(residual) or fallback
    return DepthNoise(s0, s2, median, len(z))


def _robust_std(x: np.ndarray) -> float:
    return float(1.4826 * np.median(np.abs(x - np.median(x)))) if len(x) else 0.0


def _nonnegative_fit(z: np.ndarray, spread: np.ndarray) -> tuple[float, float]:
    """Least squares ``spread ~ s0 + s2 z^2`` with s0, s2 >= 0 (the better of the free fit clipped, s0 only
    and s2 only)."""
    a = np.stack([np.ones_like(z), z * z], axis=1)
    candidates = [(float(spread.mean()), 0.0), (0.0, float((spread * z * z).sum() / max((z ** 4).sum(), 1e-30)))]
    free, *_ = np.linalg.lstsq(a, spread, rcond=None)
    if free[0] >= 0 and free[1] >= 0:
        candidates.append((float(free[0]), float(free[1])))
    errors = [float(((a @ np.array(c) - spread) ** 2).sum()) for c in candidates]
    return candidates[int(np.argmin(errors))]
