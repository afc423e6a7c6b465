"""Imperfect geometry priors from a scene's ground truth, one per prior source of the paper.

From a scene that has ground truth (``gt_mesh.ply``, e.g. the synthetic room of ``voxnerf synth``) and depth
maps for its training views, write sibling scene directories ``<scene>-monosdf``, ``<scene>-slam`` and
``<scene>-tsdf``. Each is a complete SCENE_FORMAT.md scene: the source's ``transforms.json`` with its own
``prior_file_path`` / ``prior_sigma`` and a ``voxnerf_prior`` block describing how the prior was made; images,
depth maps and the GT mesh are hard-linked (copied where linking fails). The three sources:

- ``monosdf`` (implicit-surface stand-in): the true mesh subdivided, Taubin smoothed with open3d (rounded
  corners, thin parts shrunk), Gaussian vertex noise, and holes (faces removed in spherical patches);
- ``slam`` (SLAM point cloud): the training depth maps back-projected, with depth noise ``s0 * d^2`` (d in
  metres), uniform outliers, and gaps (a rectangle of some frames dropped); only what training cameras saw;
- ``tsdf`` (TSDF fusion): open3d ``VoxelBlockGrid`` fusion of the training depth maps with the same kind of
  depth noise, meshed by marching cubes.

``prior_sigma`` of each is measured against the GT surface: ``median(d) / 0.6745`` of the unsigned distances
``d`` of the prior's points (mesh: area-uniform surface samples) to the GT mesh. For Gaussian noise of std s
about a locally flat surface ``d`` is half-normal with median 0.6745 s, so this recovers s while ignoring
outliers. It is floored at ``SIGMA_FLOOR``. Everything is seeded: the same inputs give the same files.

    .venv/bin/python benchmarks/make_priors.py SCENE [--out DIR] [--sources monosdf,slam,tsdf] [--seed 0]
"""

from __future__ import annotations

import argparse
import json
import math
import os
import shutil
import sys
import tempfile
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import trimesh

from voxnerf.cameras.rays import Intrinsics
from voxnerf.data.image_io import read_depth
from voxnerf.data.scene import load_scene
from voxnerf.errors import SceneError

SOURCES = ("monosdf", "slam", "tsdf")
SIGMA_FLOOR = 0.01
"""Metres: the smallest prior_sigma written (the octree's leaf side; smaller leaves only cost memory)."""
HALF_NORMAL_MEDIAN = 0.6745
"""Median of |N(0, 1)|: ``median(distance) / HALF_NORMAL_MEDIAN`` estimates a Gaussian noise's std."""
SIGMA_SAMPLES = 200_000
"""Surface samples of a mesh prior used to measure its distance to the GT surface."""
_OPENGL_TO_OPENCV = np.diag([1.0, -1.0, -1.0, 1.0])


@dataclass
class TrainingView:
    """One training frame: camera-to-world ``c2w`` float64 [4, 4] (OpenGL axes, metres), its intrinsics and
    its z-depth map ``depth`` float32 [H, W] in metres (NaN where there is no depth)."""

    c2w: np.ndarray
    intrinsics: Intrinsics
    depth: np.ndarray


@dataclass
class GroundTruth:
    """What the generators start from: the GT surface and the training views with depth."""

    mesh: trimesh.Trimesh
    views: list[TrainingView]


@dataclass(frozen=True)
class PriorSettings:
    """Noise parameters of the three generators (metres unless stated)."""

    monosdf_max_edge: float = 0.08
    monosdf_smooth_iterations: int = 20
    monosdf_vertex_noise: float = 0.02
    monosdf_holes: int = 4
    monosdf_hole_radius: tuple[float, float] = (0.2, 0.4)
    slam_s0: float = 0.006
    """Depth noise std at 1 m; it grows as ``s0 * d^2``."""
    slam_outlier_fraction: float = 0.02
    slam_gap_frame_fraction: float = 0.3
    """Fraction of training frames that lose a rectangle (a quarter of the image area) of their points."""
    slam_max_points: int = 300_000
    tsdf_s0: float = 0.004
    tsdf_voxel: float = 0.03
    tsdf_trunc_voxels: float = 4.0
    tsdf_depth_max: float = 8.0


# ------------------------------------------------------------------------------------------ ground truth


def load_ground_truth(scene_dir: Path) -> GroundTruth:
    """The GT mesh and the training views (with depth) of ``scene_dir``.

    The GT mesh is ``voxnerf_synthetic.gt_mesh_file_path`` of transforms.json, else ``gt_mesh.ply``.
    Raises SceneError naming the file when the mesh is missing or a training frame has no depth map.
    """
    scene_dir = Path(scene_dir)
    scene = load_scene(scene_dir, load_images=False)
    meta = json.loads((scene_dir / "transforms.json").read_text())
    rel = (meta.get("voxnerf_synthetic") or {}).get("gt_mesh_file_path", "gt_mesh.ply")
    mesh_path = scene_dir / rel
    if not mesh_path.is_file():
        raise SceneError(
            mesh_path, "ground-truth mesh not found (priors are made from a scene's ground truth)"
        )
    mesh = trimesh.load(mesh_path, process=False, force="mesh")
    if len(mesh.faces) == 0:
        raise SceneError(mesh_path, "ground-truth mesh has no faces")
    views = []
    for index in scene.train_indices:
        frame = scene.frames[index]
        if frame.depth_path is None:
            raise SceneError(
                scene_dir / "transforms.json",
                f"training frame {frame.file_path} has no depth map",
                key="depth_file_path",
            )
        views.append(
            TrainingView(frame.c2w, frame.intrinsics, read_depth(frame.depth_path, scene.depth_unit_scale))
        )
    return GroundTruth(mesh, views)


def distance_to_surface(points: np.ndarray, mesh: trimesh.Trimesh) -> np.ndarray:
    """Unsigned distance float64 [N] (metres) of ``points`` [N, 3] to the surface of ``mesh``."""
    import open3d as o3d  # imported where used: the suite imports this module on machines without open3d
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(
        o3d.core.Tensor(np.asarray(mesh.vertices, np.float32)),
        o3d.core.Tensor(np.asarray(mesh.faces, np.uint32)),
    )
    return scene.compute_distance(o3d.core.Tensor(np.asarray(points, np.float32))).numpy().astype(np.float64)


def prior_points(geometry: trimesh.Trimesh | np.ndarray, seed: int = 0) -> np.ndarray:
    """Points [N, 3] of a prior: a point cloud as is, a mesh as ``SIGMA_SAMPLES`` area-uniform samples."""
    if isinstance(geometry, trimesh.Trimesh):
        samples, _ = trimesh.sample.sample_surface(geometry, SIGMA_SAMPLES, seed=seed)
        return np.asarray(samples, np.float64)
    return np.asarray(geometry, np.float64)


def measure_sigma(geometry: trimesh.Trimesh | np.ndarray, gt_mesh: trimesh.Trimesh) -> dict:
    """Distance statistics (metres) of a prior to the GT surface and the ``prior_sigma`` to state.

    Returns ``{"median", "rms", "p95", "sigma_robust", "prior_sigma"}``: ``sigma_robust`` is
    ``median / HALF_NORMAL_MEDIAN``, ``prior_sigma`` the same floored at ``SIGMA_FLOOR``.
    """
    d = distance_to_surface(prior_points(geometry), gt_mesh)
    if not np.isfinite(d).all():
        raise ValueError("non-finite distance to the GT surface (NaN/inf in the prior)")
    robust = float(np.median(d)) / HALF_NORMAL_MEDIAN
    return {
        "median": float(np.median(d)),
        "rms": float(np.sqrt(np.mean(d**2))),
        "p95": float(np.quantile(d, 0.95)),
        "sigma_robust": robust,
        "prior_sigma": max(robust, SIGMA_FLOOR),
    }


# ------------------------------------------------------------------------------------------- generators


def monosdf_prior(
    gt: GroundTruth, settings: PriorSettings, rng: np.random.Generator
) -> tuple[trimesh.Trimesh, dict]:
    """Implicit-surface-like mesh: GT subdivided, Taubin smoothed, vertex noise, spherical holes."""
    import open3d as o3d  # imported where used: the suite imports this module on machines without open3d
    verts, faces = trimesh.remesh.subdivide_to_size(
        gt.mesh.vertices, gt.mesh.faces, settings.monosdf_max_edge
    )
    merged = trimesh.Trimesh(verts, faces, process=False)
    merged.merge_vertices()
    smoothed = o3d.geometry.TriangleMesh(
        o3d.utility.Vector3dVector(merged.vertices), o3d.utility.Vector3iVector(merged.faces)
    )
    smoothed = smoothed.filter_smooth_taubin(number_of_iterations=settings.monosdf_smooth_iterations)
    mesh = trimesh.Trimesh(np.asarray(smoothed.vertices), np.asarray(smoothed.triangles), process=False)
    mesh.vertices = mesh.vertices + rng.normal(0.0, settings.monosdf_vertex_noise, mesh.vertices.shape)
    centres = mesh.triangles_center
    keep = np.ones(len(mesh.faces), bool)
    holes = []
    for _ in range(settings.monosdf_holes):
        centre = centres[int(rng.integers(len(centres)))]
        radius = float(rng.uniform(*settings.monosdf_hole_radius))
        keep &= np.linalg.norm(centres - centre, axis=1) > radius
        holes.append({"centre": _rounded(centre), "radius": round(radius, 4)})
    mesh.update_faces(keep)
    mesh.remove_unreferenced_vertices()
    info = {
        "source": "monosdf",
        "method": "GT mesh subdivided to max_edge, Taubin smoothed, Gaussian vertex noise, faces removed in "
        "spherical holes",
        "max_edge": settings.monosdf_max_edge,
        "smooth_iterations": settings.monosdf_smooth_iterations,
        "vertex_noise": settings.monosdf_vertex_noise,
        "holes": holes,
        "n_vertices": len(mesh.vertices),
        "n_faces": len(mesh.faces),
    }
    return mesh, info


def noisy_depth(depth: np.ndarray, s0: float, rng: np.random.Generator) -> np.ndarray:
    """``depth`` [H, W] (metres, NaN = none) plus Gaussian noise of std ``s0 * depth^2``; stays > 0."""
    noisy = depth + rng.normal(0.0, 1.0, depth.shape) * s0 * depth**2
    return np.where(noisy > 0, noisy, np.nan).astype(np.float32)


def backproject(view: TrainingView, depth: np.ndarray) -> np.ndarray:
    """World points [N, 3] of the pixels of ``depth`` [H, W] (z-depth, metres) that have a value."""
    intr = view.intrinsics
    v, u = np.nonzero(np.isfinite(depth))
    z = depth[v, u].astype(np.float64)
    cam = np.stack([(u + 0.5 - intr.cx) / intr.fl_x * z, -(v + 0.5 - intr.cy) / intr.fl_y * z, -z], axis=1)
    return cam @ view.c2w[:3, :3].T + view.c2w[:3, 3]


def slam_prior(gt: GroundTruth, settings: PriorSettings, rng: np.random.Generator) -> tuple[np.ndarray, dict]:
    """SLAM-like point cloud [N, 3] from the training depth maps: distance-growing noise, gaps, outliers."""
    clouds, gaps = [], []
    for index, view in enumerate(gt.views):
        depth = noisy_depth(view.depth, settings.slam_s0, rng)
        if rng.random() < settings.slam_gap_frame_fraction:
            h, w = depth.shape
            top, left = int(rng.integers(0, h - h // 2 + 1)), int(rng.integers(0, w - w // 2 + 1))
            depth[top : top + h // 2, left : left + w // 2] = np.nan
            gaps.append({"view": index, "rows": [top, top + h // 2], "cols": [left, left + w // 2]})
        clouds.append(backproject(view, depth))
    points = np.concatenate(clouds)
    if len(points) > settings.slam_max_points:
        points = points[np.sort(rng.choice(len(points), settings.slam_max_points, replace=False))]
    lo, hi = points.min(axis=0), points.max(axis=0)
    n_out = int(round(settings.slam_outlier_fraction * len(points)))
    points = np.concatenate([points, lo + rng.random((n_out, 3)) * (hi - lo)])
    info = {
        "source": "slam",
        "method": "training depth maps back-projected with depth noise s0 * d^2, a rectangle (1/4 of the "
        "image) dropped in some frames, uniform outliers in the bounding box",
        "s0": settings.slam_s0,
        "outlier_fraction": settings.slam_outlier_fraction,
        "n_outliers": n_out,
        "gaps": gaps,
        "n_points": len(points),
    }
    return points, info


def tsdf_prior(
    gt: GroundTruth, settings: PriorSettings, rng: np.random.Generator
) -> tuple[trimesh.Trimesh, dict]:
    """TSDF fusion (open3d ``VoxelBlockGrid``) of noisy training depth maps, meshed by marching cubes."""
    import open3d as o3d  # imported where used: the suite imports this module on machines without open3d
    grid = o3d.t.geometry.VoxelBlockGrid(
        attr_names=("tsdf", "weight"),
        attr_dtypes=(o3d.core.float32, o3d.core.float32),
        attr_channels=((1,), (1,)),
        voxel_size=settings.tsdf_voxel,
        block_resolution=16,
        block_count=50_000,
    )
    for view in gt.views:
        depth = noisy_depth(view.depth, settings.tsdf_s0, rng)
        image = o3d.t.geometry.Image(np.ascontiguousarray(np.nan_to_num(depth, nan=0.0)))
        intr = view.intrinsics
        k = o3d.core.Tensor(
            [[intr.fl_x, 0.0, intr.cx - 0.5], [0.0, intr.fl_y, intr.cy - 0.5], [0.0, 0.0, 1.0]],
            o3d.core.float64,
        )
        w2c = o3d.core.Tensor(_OPENGL_TO_OPENCV @ np.linalg.inv(view.c2w), o3d.core.float64)
        kwargs = {
            "depth_scale": 1.0,
            "depth_max": settings.tsdf_depth_max,
            "trunc_voxel_multiplier": settings.tsdf_trunc_voxels,
        }
        blocks = grid.compute_unique_block_coordinates(image, k, w2c, **kwargs)
        grid.integrate(blocks, image, k, w2c, **kwargs)
    fused = grid.extract_triangle_mesh(weight_threshold=1.0).to_legacy()
    mesh = trimesh.Trimesh(np.asarray(fused.vertices), np.asarray(fused.triangles), process=False)
    if len(mesh.faces) == 0:
        raise RuntimeError("TSDF fusion produced an empty mesh (no valid depth in the training views?)")
    info = {
        "source": "tsdf",
        "method": "open3d VoxelBlockGrid TSDF fusion of the training depth maps with noise s0 * d^2, "
        "marching cubes (weight threshold 1)",
        "s0": settings.tsdf_s0,
        "voxel": settings.tsdf_voxel,
        "trunc_voxels": settings.tsdf_trunc_voxels,
        "n_vertices": len(mesh.vertices),
        "n_faces": len(mesh.faces),
    }
    return mesh, info


GENERATORS: dict[str, Callable[[GroundTruth, PriorSettings, np.random.Generator], tuple]] = {
    "monosdf": monosdf_prior,
    "slam": slam_prior,
    "tsdf": tsdf_prior,
}


# ------------------------------------------------------------------------------------------------ writer


def prior_scene_dir(scene_dir: Path, source: str, out: Path | None = None) -> Path:
    """Directory of the ``source`` variant of ``scene_dir``: ``<out or its parent>/<scene name>-<source>``."""
    scene_dir = Path(scene_dir)
    return Path(out or scene_dir.parent) / f"{scene_dir.name}-{source}"


def write_prior_scene(
    scene_dir: Path,
    dst: Path,
    geometry: trimesh.Trimesh | np.ndarray,
    sigma: float,
    description: dict,
    transform: Callable[[dict], dict] | None = None,
) -> Path:
    """Write ``dst``: ``scene_dir`` with ``geometry`` as ``prior.ply`` stated at ``sigma`` (metres).

    transforms.json is the source's with ``prior_file_path``, ``prior_sigma`` and a ``voxnerf_prior`` block
    (``description``); ``transform`` may edit the metadata further. Every other file of the scene except the
    old prior is hard-linked (copied across file systems). The directory is built beside ``dst`` and moved
    into place (an existing ``dst`` is replaced), so a partial scene is never visible.
    """
    scene_dir, dst = Path(scene_dir), Path(dst)
    if not (math.isfinite(sigma) and sigma > 0):
        raise ValueError(f"prior sigma must be positive and finite, got {sigma!r}")
    meta = json.loads((scene_dir / "transforms.json").read_text())
    old_prior = meta.get("prior_file_path")
    meta["prior_file_path"] = "prior.ply"
    meta["prior_sigma"] = round(float(sigma), 6)
    meta["voxnerf_prior"] = description
    if transform is not None:
        meta = transform(meta)
    dst.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{dst.name}.tmp-", dir=dst.parent))
    try:
        for path in sorted(scene_dir.rglob("*")):
            rel = path.relative_to(scene_dir)
            if path.is_dir() or rel.as_posix() in ("transforms.json", old_prior):
                continue
            (tmp / rel).parent.mkdir(parents=True, exist_ok=True)
            try:
                os.link(path, tmp / rel)
            except OSError:
                shutil.copy2(path, tmp / rel)
        if isinstance(geometry, trimesh.Trimesh):
            geometry.export(tmp / "prior.ply")
        else:
            trimesh.PointCloud(np.asarray(geometry)).export(tmp / "prior.ply")
        (tmp / "transforms.json").write_text(json.dumps(meta, indent=2) + "\n")
        if dst.exists():
            shutil.rmtree(dst)
        os.replace(tmp, dst)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return dst


def make_priors(
    scene_dir: Path,
    out: Path | None = None,
    sources: tuple[str, ...] = SOURCES,
    seed: int = 0,
    settings: PriorSettings | None = None,
) -> dict[str, Path]:
    """Write one prior scene per source (see the module docstring); returns ``{source: scene dir}``.

    The ``voxnerf_prior`` block of each holds the generator's description, the distance statistics of
    :func:`measure_sigma`, the seed and the source scene.
    """
    settings = settings or PriorSettings()
    unknown = sorted(set(sources) - set(GENERATORS))
    if unknown:
        raise ValueError(f"unknown prior sources {unknown}; choose from {SOURCES}")
    gt = load_ground_truth(scene_dir)
    written = {}
    for source in sources:
        rng = np.random.default_rng([seed, SOURCES.index(source)])
        geometry, info = GENERATORS[source](gt, settings, rng)
        stats = measure_sigma(geometry, gt.mesh)
        info |= {
            "seed": seed,
            "source_scene": Path(scene_dir).name,
            "distance_to_gt": {k2: round(v, 6) for k2, v in stats.items()},
            "prior_sigma_rule": "median distance of prior points to the GT surface / 0.6745, "
            f"floored at {SIGMA_FLOOR} m",
        }
        written[source] = write_prior_scene(
            scene_dir, prior_scene_dir(scene_dir, source, out), geometry, stats["prior_sigma"], info
        )
    return written


def _rounded(values: np.ndarray) -> list[float]:
    return [round(float(v), 4) for v in values]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("scene", type=Path, help="scene directory with gt_mesh.ply and training depth maps")
    parser.add_argument(
        "--out", type=Path, help="parent directory of the prior scenes (default: the scene's)"
    )
    parser.add_argument(
        "--sources", default=",".join(SOURCES), help="comma-separated subset of " + ",".join(SOURCES)
    )
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    try:
        written = make_priors(args.scene, args.out, tuple(s for s in args.sources.split(",") if s), args.seed)
    except (SceneError, ValueError) as err:
        print(f"make_priors: error: {err}", file=sys.stderr)
        return 2
    for source, path in written.items():
        meta = json.loads((path / "transforms.json").read_text())
        stats = meta["voxnerf_prior"]["distance_to_gt"]
        print(
            f"{source}: {path} prior_sigma {meta['prior_sigma']:.4f} m "
            f"(median distance to GT {stats['median']:.4f} m, p95 {stats['p95']:.4f} m)"
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
