"""The TSDF prior from depth maps (voxnerf/prior/depth_fusion.py): geometry, the measured noise, bad and extreme
depth."""

from __future__ import annotations

import numpy as np
import open3d as o3d
import pytest
import trimesh

from voxnerf.cameras.rules import Intrinsics
from voxnerf.prior.depth_fusion import (
    DepthView,
    FusionError,
    backproject,
    canonical_mesh,
    fit_noise,
    fuse_depth_prior,
    fuse_tsdf,
)
from voxnerf.synthetic.cameras import look_at_c2w

ROOM = trimesh.creation.box(extents=(4.0, 3.0, 2.5))  # the inside of a 4 x 3 x 2.5 m room, centred at 0
CAMERA = Intrinsics(fl_x=120.0, fl_y=120.0, cx=80.0, cy=60.0, width=160, height=120)
S0, S2 = 0.004, 0.003  # the simulated sensor: sigma(z) = 4 mm + 3 mm/m^2 z^2


def _look(yaw: float, pitch: float, position) -> np.ndarray:
    """camera-to-world (OpenGL axes) looking along yaw / pitch (radians) from ``position``."""
    forward = np.array([np.cos(pitch) * np.cos(yaw), np.cos(pitch) * np.sin(yaw), np.sin(pitch)])
    return look_at_c2w(np.asarray(position, dtype=np.float64), forward)


def _true_depth(c2w: np.ndarray, camera: Intrinsics = CAMERA) -> np.ndarray:
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(ROOM.vertices.astype(np.float32)),
                        o3d.core.Tensor(ROOM.faces.astype(np.uint32)))
    v, u = np.mgrid[0 : camera.height, 0 : camera.width]
    cam = np.stack([(u + 0.5 - camera.cx) / camera.fl_x, -(v + 0.5 - camera.cy) / camera.fl_y,
                    -np.ones(u.shape)], axis=-1).reshape(-1, 3)
    dirs = cam @ c2w[:3, :3].T
    rays = np.concatenate([np.broadcast_to(c2w[:3, 3], dirs.shape), dirs], axis=1).astype(np.float32)
    return scene.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy().reshape(camera.height, camera.width)


def _views(noise: bool = True, n: int = 24, seed: int = 0) -> list[DepthView]:
    rng = np.random.default_rng(seed)
    views = []
    for i in range(n):
        c2w = _look(2 * np.pi * i / n, rng.uniform(-0.4, 0.4), rng.uniform([-1, -0.8, -0.5], [1, 0.8, 0.5]))
        z = _true_depth(c2w).astype(np.float64)
        if noise:
            z = z + rng.normal(size=z.shape) * (S0 + S2 * z * z)
        views.append(DepthView(z.astype(np.float32), CAMERA, c2w))
    return views


def _distance_to_room(points: np.ndarray) -> np.ndarray:
    half = np.array([2.0, 1.5, 1.25])
    return np.min(half - np.abs(points), axis=1)  # inside the box: distance to the nearest wall


def test_fused_prior_lies_on_the_walls_and_measures_the_simulated_noise():
    fused = fuse_depth_prior(_views())
    dist = np.abs(_distance_to_room(np.asarray(fused.mesh.vertices)))
    assert np.median(dist) < 0.5 * fused.voxel
    truth = S0 + S2 * fused.noise.median_depth ** 2
    assert fused.noise.at_median == pytest.approx(truth, rel=0.35)
    assert fused.noise.s2 > 0  # noise grows with depth, as simulated
    assert fused.sigma == fused.voxel and fused.truncation == pytest.approx(4 * fused.voxel)
    assert "training frames with depth -> TSDF prior" in fused.describe()
    assert fused.voxel_rule in fused.describe()
    assert fused.summary()["source"] == "tsdf_fusion" and 0.9 < fused.summary()["valid_depth_fraction"] <= 1.0


def test_voxel_never_goes_below_two_pixel_footprints():
    fused = fuse_depth_prior(_views(noise=False))  # exact depth: the measured noise is only discretisation
    footprint = fused.noise.median_depth / CAMERA.fl_x
    assert fused.voxel == pytest.approx(2 * footprint, rel=0.05)
    assert fused.voxel_rule == "2 pixel footprints at the median depth"


def test_backproject_inverts_the_depth_maps():
    view = _views(noise=False, n=1)[0]
    points = backproject(view, stride=3)
    assert len(points) > 100 and np.abs(_distance_to_room(points)).max() < 1e-3


def test_fit_noise_recovers_a_known_model():
    rng = np.random.default_rng(1)
    z = rng.uniform(0.5, 5.0, 200_000)
    residual = rng.normal(size=z.size) * (0.002 + 0.0015 * z * z)
    noise = fit_noise(z, residual, fallback=0.01)
    assert noise.s0 == pytest.approx(0.002, abs=0.001) and noise.s2 == pytest.approx(0.0015, rel=0.2)
    assert noise.residuals == z.size and np.isfinite(noise.sigma(np.array([0.0, 100.0]))).all()


def test_fit_noise_with_few_or_no_residuals_stays_finite_and_positive():
    assert fit_noise(np.zeros(0), np.zeros(0), fallback=0.01).at_median == 0.01
    few = fit_noise(np.array([1.0, 2.0, 3.0]), np.array([0.01, -0.01, 0.0]), fallback=0.05)
    assert few.s2 == 0 and few.s0 > 0
    constant = fit_noise(np.full(1000, 2.0), np.zeros(1000), fallback=0.03)  # no spread at all
    assert constant.at_median == 0.03


@pytest.mark.parametrize("fill", [np.nan, 0.0, np.inf])
def test_depth_maps_without_valid_depth_are_a_fusion_error(fill):
    views = [DepthView(np.full((120, 160), fill, np.float32), CAMERA, np.eye(4))]
    with pytest.raises(FusionError, match="hold no valid depth"):
        fuse_depth_prior(views)
    with pytest.raises(FusionError, match="no training frame has a depth map"):
        fuse_depth_prior([])


def test_extreme_depth_values_give_a_finite_prior_or_a_clear_error():
    views = _views(noise=False, n=6)
    for view in views:
        view.depth[::7, ::5] = 3e38  # near float32's maximum
        view.depth[1::9, ::4] = 1e-30
    try:
        fused = fuse_depth_prior(views)
    except FusionError as err:
        assert "left no surface" in str(err)
    else:
        assert np.isfinite(fused.mesh.vertices).all() and np.isfinite(fused.sigma) and fused.sigma > 0
        assert np.isfinite(fused.noise.s0) and np.isfinite(fused.noise.s2)


def test_fusion_beyond_depth_max_leaves_no_surface():
    with pytest.raises(FusionError, match="left no surface"):
        fuse_tsdf(_views(noise=False, n=2), voxel=0.05, truncation=0.2, depth_max=0.1)


def test_fusion_is_deterministic_and_canonical_keeps_the_surface():
    views = _views(n=8)
    first, second = (fuse_tsdf(views, 0.03, 0.12, 10.0) for _ in range(2))
    assert np.array_equal(first.vertices, second.vertices) and np.array_equal(first.faces, second.faces)
    shuffled = trimesh.Trimesh(first.vertices[::-1], (len(first.vertices) - 1 - first.faces)[::-1], process=False)
    again = canonical_mesh(shuffled)
    assert np.array_equal(again.vertices, first.vertices) and np.array_equal(again.faces, first.faces)
    normals = trimesh.Trimesh(first.vertices, first.faces, process=False).face_normals
    assert np.allclose(np.sort(normals, axis=0), np.sort(again.face_normals, axis=0))  # orientation kept
