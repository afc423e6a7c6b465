"""Geometry export: a trained run's coloured mesh or point cloud, in the scan's own coordinates and units.

Views: every training camera of the scene the run trained on, each also shifted by :data:`OFFSET_OF_EXTENT` of
the scene box along :data:`OFFSET_DIRECTIONS` (its own right/left/up/down, same orientation). Every view is a
pinhole (lenses left out) at the trained resolution, scaled down so that its longer side is at most
:data:`~voxnerf.inference.export_plan.MAX_RENDER_SIDE` pixels (how many views, at what size:
:mod:`voxnerf.inference.export_plan`, torch-free), rendered with :func:`voxnerf.inference.render.render` (rgb,
z-depth in scene units, opacity). Pixels with opacity below ``min_opacity``, or any non-finite output, carry no
surface. Colours are the rendered rgb (composited over the model's background; a surface a training view saw is
opaque, so it shows little of it).
(An orbit looking inward at the cameras' centre was left out: inside a room it crosses the unobserved middle,
whose floaters put its depth decimetres off; docs/engine.md, Geometry export.)

- ``mesh``: TSDF fusion of the views' depth and colour (:func:`voxnerf.prior.depth_fusion.fuse_tsdf`, open3d's tensor
  VoxelBlockGrid, truncation :data:`TRUNCATION_VOXELS` voxels, voxels seen by fewer than :data:`MIN_VIEWS` views
  left out), marching cubes, vertex colours; canonical vertex/face order.
- ``pointcloud``: each view's valid pixels back-projected to world points with colours and normals (from the
  depth map's neighbours, facing the camera), averaged per voxel of ``voxel_size``, points that fewer than
  :data:`MIN_VIEWS` views reach (per cell of ``TRUNCATION_VOXELS`` voxels) left out, in lexicographic order.

Default voxel (and point spacing): 1/:data:`VOXELS_PER_SIDE` of the longest side of the model's scene box, in
scene units. Both kinds are written as binary PLY (vertex colours uchar) through a temporary file, so ``out`` is
either absent or complete.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import trimesh

from voxnerf.cameras.rules import Intrinsics
from voxnerf.data.image_io import write_atomic
from voxnerf.data.scene import Scene, load_scene
from voxnerf.errors import RunError
from voxnerf.inference.export_plan import OFFSET_DIRECTIONS, render_camera
from voxnerf.inference.render import TrainedModel, render, scene_as_trained
from voxnerf.prior.depth_fusion import DepthView, FusionError, fuse_tsdf, point_map

EXPORT_KINDS = ("mesh", "pointcloud")
VOXELS_PER_SIDE = 512  # default voxel: the scene box's longest side over this
MAX_VOXELS_PER_SIDE = 4096  # a finer voxel_size is refused (memory and time grow with its cube)
TRUNCATION_VOXELS = 4.0
MIN_VIEWS = 3  # surface (a mesh voxel, a cloud voxel) that fewer views see is left out: floaters are seen by few
OFFSET_OF_EXTENT = 1 / 40  # offset views: shift of the training camera, as a fraction of the box's longest side
OUTPUTS = ("rgb", "depth", "opacity")


class ExportError(RunError):
    """The geometry cannot be exported (bad option, nothing opaque, nothing fused); one line saying why."""


@dataclass
class ExportResult:
    """What :func:`export_geometry` wrote. ``points``: mesh vertices or cloud points; ``faces`` 0 for a cloud;
    ``voxel_size``: the fusion voxel (mesh) or the point spacing (cloud), scene units. ``stopped``: should_stop
    ended the export early and nothing was written at ``out``."""

    kind: str
    out: Path
    views: int
    points: int
    faces: int
    voxel_size: float | None
    seconds: float
    stopped: bool

    def summary(self) -> dict:
        return {"kind": self.kind, "out": str(self.out), "views": self.views, "points": self.points,
                "faces": self.faces, "voxel_size": self.voxel_size, "seconds": round(self.seconds, 3),
                "stopped": self.stopped}


@dataclass
class ExportView:
    """A camera to render: c2w [4, 4] float64 (OpenGL axes, scene units) and a pinhole camera."""

    c2w: np.ndarray
    intrinsics: Intrinsics


def export_geometry(
    trained: TrainedModel,
    out: Path,
    kind: str,
    *,
    scene: Scene | None = None,
    voxel_size: float | None = None,
    min_opacity: float = 0.5,
    max_views: int | None = None,
    on_view: Callable[[int, int], None] | None = None,
    should_stop: Callable[[], bool] | None = None,
) -> ExportResult:
    """Render ``trained`` from the views of the module docstring and write its ``kind`` geometry to ``out`` (.ply).

    Args:
        scene: the scene the run trained on (default: ``trained.scene_dir``, images not read).
        voxel_size: scene units (default: the box's longest side / 512).
        min_opacity: pixels rendering less opaque than this carry no surface, in (0, 1].
        max_views: render at most this many views, evenly spaced over the list.
        on_view: called with (views done, views in all) after each view.
        should_stop: checked before each view; when it returns True nothing is written.
    Raises:
        ExportError: a bad option, no opaque pixel in any view, or a fusion that leaves no surface.
        SceneError / RunError: the scene cannot be loaded.
    """
    started = time.perf_counter()
    out = Path(out)
    _check_options(out, kind, voxel_size, min_opacity, max_views)
    voxel = float(voxel_size) if voxel_size is not None else box_extent(trained) / VOXELS_PER_SIDE
    _check_voxel(voxel, box_extent(trained))
    cameras = export_views(scene or _scene_of(trained), box_extent(trained), max_views)
    rendered = []
    for done, camera in enumerate(cameras):
        if should_stop is not None and should_stop():
            return ExportResult(kind, out, done, 0, 0, voxel, time.perf_counter() - started, True)
        rendered.append(render_view(trained, camera, min_opacity))
        if on_view is not None:
            on_view(done + 1, len(cameras))
    _check_opaque(rendered, min_opacity)
    out.parent.mkdir(parents=True, exist_ok=True)
    if kind == "mesh":
        mesh = fuse_mesh(rendered, voxel)
        write_atomic(out, mesh.export(file_type="ply", encoding="binary"))
        points, faces = len(mesh.vertices), len(mesh.faces)
    else:
        xyz, rgb, normals = point_cloud(rendered, voxel)
        write_atomic(out, point_cloud_ply(xyz, rgb, normals))
        points, faces = len(xyz), 0
    return ExportResult(kind, out, len(cameras), points, faces, voxel, time.perf_counter() - started, False)


def _check_options(out: Path, kind: str, voxel_size, min_opacity, max_views) -> None:
    if kind not in EXPORT_KINDS:
        raise ExportError(f"kind: must be one of {', '.join(EXPORT_KINDS)}, got {kind!r}")
    if out.suffix.lower() != ".ply":
        raise ExportError(f"{out}: output must end in .ply")
    if voxel_size is not None and not (_is_real(voxel_size) and math.isfinite(voxel_size) and voxel_size > 0):
        raise ExportError(f"voxel_size: must be a positive number of scene units, got {voxel_size!r}")
    if not (_is_real(min_opacity) and 0 < min_opacity <= 1):
        raise ExportError(f"min_opacity: must be in (0, 1], got {min_opacity!r}")
    if max_views is not None and not (isinstance(max_views, int) and not isinstance(max_views, bool)
                                      and max_views >= 1):
        raise ExportError(f"max_views: must be a positive integer, got {max_views!r}")


def _is_real(value) -> bool:
    return isinstance(value, (int, float, np.floating, np.integer)) and not isinstance(value, bool)


def _check_voxel(voxel: float, extent: float) -> None:
    if extent / voxel > MAX_VOXELS_PER_SIDE:
        raise ExportError(f"voxel_size: {voxel:.4g} gives more than {MAX_VOXELS_PER_SIDE} voxels across the scene "
                          f"box ({extent:.4g} scene units); use at least {extent / MAX_VOXELS_PER_SIDE:.4g}")


def _scene_of(trained: TrainedModel) -> Scene:
    if not trained.scene_dir:
        raise ExportError("scene: the run does not record its scene directory; pass the scene (--scene DIR)")
    return scene_as_trained(load_scene(trained.scene_dir, downscale=int(trained.model.config.run.downscale),
                                       load_images=False), trained.model)


def box_extent(trained: TrainedModel) -> float:
    """Longest side of the model's scene box, scene units."""
    model = trained.model
    side = (model.aabb[1] - model.aabb[0]).max().item()
    return float(side / model.transform.scale)


def export_views(scene: Scene, extent: float, max_views: int | None = None) -> list[ExportView]:
    """The training cameras, their offsets and the orbit (module docstring); ``max_views`` evenly spaced."""
    train = [(scene.frames[i].c2w, render_camera(scene.intrinsics(i))) for i in scene.train_indices]
    if not train:
        raise ExportError(f"{scene.root}: train: the scene has no training frame")
    views = [ExportView(np.asarray(c2w, np.float64), k) for c2w, k in train]
    shift = OFFSET_OF_EXTENT * extent
    for c2w, k in train:
        for right, up in OFFSET_DIRECTIONS:
            moved = np.array(c2w, np.float64)
            moved[:3, 3] += shift * (right * moved[:3, 0] + up * moved[:3, 1])
            views.append(ExportView(moved, k))
    if max_views is not None and max_views < len(views):
        views = [views[i] for i in np.unique(np.linspace(0, len(views) - 1, max_views).round().astype(int))]
    return views


def render_view(trained: TrainedModel, camera: ExportView, min_opacity: float) -> DepthView:
    """Render ``camera``: depth float32 [H, W] scene units, NaN where no surface (opacity below ``min_opacity``
    or any non-finite output); rgb uint8 [H, W, 3] as rendered (composited over the model's background), one ray per
    pixel: the fusion averages each surface's colour over many views already, and antialiasing would cost five
    times the rays."""
    images = render(trained, camera.c2w, camera.intrinsics, OUTPUTS, antialias=False)
    depth, opacity, rgb = images["depth"], images["opacity"], images["rgb"]
    surface = (np.isfinite(depth) & (depth > 0) & np.isfinite(opacity) & (opacity >= min_opacity)
               & np.isfinite(rgb).all(axis=-1))
    colour8 = np.round(np.clip(np.nan_to_num(rgb), 0.0, 1.0) * 255).astype(np.uint8)
    return DepthView(np.where(surface, depth, np.nan).astype(np.float32), camera.intrinsics, camera.c2w, colour8)


def _check_opaque(rendered: list[DepthView], min_opacity: float) -> None:
    if not any(np.isfinite(v.depth).any() for v in rendered):
        raise ExportError(f"min_opacity: no pixel of the {len(rendered)} views renders with opacity >= "
                          f"{min_opacity:g}: nothing to export (an untrained or empty model?)")


def fuse_mesh(rendered: list[DepthView], voxel: float) -> trimesh.Trimesh:
    """The coloured TSDF mesh of ``rendered`` (canonical order, scene units)."""
    depth_max = max(float(np.nanmax(v.depth)) for v in rendered if np.isfinite(v.depth).any()) * 1.001
    try:
        # in canonical order; open3d keeps voxels whose weight (views) exceeds the threshold
        return fuse_tsdf(rendered, voxel, TRUNCATION_VOXELS * voxel, depth_max, min_views=MIN_VIEWS - 0.5)
    except FusionError as err:
        raise ExportError(f"mesh: {err}") from None


def view_points(view: DepthView) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """World points [M, 3] float64, colours [M, 3] uint8 and unit normals [M, 3] (facing the camera) of the
    pixels of ``view`` whose four neighbours also have depth (the normal is their cross product)."""
    world = point_map(view)
    du = np.full_like(world, np.nan)
    dv = np.full_like(world, np.nan)
    du[:, 1:-1] = world[:, 2:] - world[:, :-2]
    dv[1:-1] = world[2:] - world[:-2]
    normals = np.cross(du, dv)
    length = np.linalg.norm(normals, axis=-1, keepdims=True)
    keep = np.isfinite(world).all(-1) & np.isfinite(length[..., 0]) & (length[..., 0] > 0)
    normals = normals[keep] / length[keep]
    points = world[keep]
    facing = np.einsum("ij,ij->i", normals, view.c2w[:3, 3] - points) < 0
    normals[facing] *= -1
    return points, view.rgb[keep], normals


def point_cloud(rendered: list[DepthView], voxel: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Points float32 [M, 3] (scene units), colours uint8 [M, 3] and unit normals float32 [M, 3]: the views'
    points averaged per voxel of side ``voxel`` (each view's first, then the views'), sorted lexicographically.
    Points in a cell of side ``TRUNCATION_VOXELS * voxel`` (the mesh's TSDF band) that fewer than
    :data:`MIN_VIEWS` views reach are left out."""
    per_view = []
    for view in rendered:
        points, colours, normals = view_points(view)
        if len(points):
            per_view.append(voxel_means(points, np.concatenate([colours / 255.0, normals], axis=1), voxel)[:2])
    if not per_view:
        raise ExportError(f"pointcloud: no opaque pixel of the {len(rendered)} views has opaque neighbours")
    support = TRUNCATION_VOXELS * voxel
    seen = np.concatenate([np.unique(np.floor(p / support).astype(np.int64), axis=0) for p, _ in per_view])
    cells, views = np.unique(seen, axis=0, return_counts=True)
    points, values = (np.concatenate(x) for x in zip(*per_view, strict=True))
    keep = _rows_in(np.floor(points / support).astype(np.int64), cells[views >= MIN_VIEWS])
    if not keep.any():
        raise ExportError(f"pointcloud: no surface is seen by {MIN_VIEWS} views: nothing to export")
    points, values, _ = voxel_means(points[keep], values[keep], voxel)
    normals = values[:, 3:] / np.maximum(np.linalg.norm(values[:, 3:], axis=1, keepdims=True), 1e-12)
    order = np.lexsort(points.T[::-1])
    rgb8 = np.round(np.clip(values[order, :3], 0.0, 1.0) * 255).astype(np.uint8)
    return points[order].astype(np.float32), rgb8, normals[order].astype(np.float32)


def _rows_in(rows: np.ndarray, table: np.ndarray) -> np.ndarray:
    """Whether each int64 row [N, 3] occurs in ``table`` [T, 3] -> bool [N]."""
    if len(table) == 0:
        return np.zeros(len(rows), bool)
    both = np.concatenate([table, rows])
    _, inverse = np.unique(both, axis=0, return_inverse=True)
    inverse = inverse.reshape(-1)
    present = np.zeros(inverse.max() + 1, bool)
    present[inverse[: len(table)]] = True
    return present[inverse[len(table):]]


def voxel_means(points: np.ndarray, values: np.ndarray, voxel: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Mean point [V, 3] and mean values [V, C] of the points [N, 3] (values [N, C]) in each occupied voxel of
    side ``voxel`` (cells ``floor(point / voxel)``), and the voxel's number of points [V]."""
    cells = np.floor(points / voxel).astype(np.int64)
    _, inverse = np.unique(cells, axis=0, return_inverse=True)
    inverse = inverse.reshape(-1)
    n = np.bincount(inverse)

    def mean(x: np.ndarray) -> np.ndarray:
        return np.stack([np.bincount(inverse, weights=col) for col in x.T], axis=1) / n[:, None]

    return mean(points), mean(values), n
def point_cloud_ply(points: np.ndarray, colours: np.ndarray, normals: np.ndarray) -> bytes:
    """Binary little-endian PLY of points [M, 3], normals [M, 3] (float32) and colours [M, 3] (uchar)."""
    fields = [("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("nx", "<f4"), ("ny", "<f4"), ("nz", "<f4"),
              ("red", "u1"), ("green", "u1"), ("blue", "u1")]
    table = np.empty(len(points), dtype=fields)
    for i, axis in enumerate("xyz"):
        table[axis], table[f"n{axis}"] = points[:, i], normals[:, i]
    for i, channel in enumerate(("red", "green", "blue")):
        table[channel] = colours[:, i]
    types = {"<f4": "float", "u1": "uchar"}
    header = ["ply", "format binary_little_endian 1.0", f"element vertex {len(points)}"]
    header += [f"property {types[t]} {name}" for name, t in fields] + ["end_header"]
    return ("\n".join(header) + "\n").encode() + table.tobytes()


def distances_to_mesh(points: np.ndarray, mesh: trimesh.Trimesh) -> np.ndarray:
    """Unsigned distance [N] from each point [N, 3] to the surface of ``mesh`` (open3d's ray-casting scene),
    in the points' units: the accuracy of an export against a true mesh, or completeness the other way round."""
    import open3d as o3d

    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(np.asarray(mesh.vertices, np.float32)),
                        o3d.core.Tensor(np.asarray(mesh.faces, np.uint32)))
    return scene.compute_distance(o3d.core.Tensor(np.asarray(points, np.float32))).numpy()
