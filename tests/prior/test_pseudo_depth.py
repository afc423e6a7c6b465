"""Pseudo ground-truth depth: mesh ray casting against analytic distances, point clouds through the octree."""

from __future__ import annotations

import numpy as np
import pytest
import torch
import trimesh

from voxnerf.prior import pseudo_depth
from voxnerf.prior.loading import load_prior
from voxnerf.prior.octree import SparseVoxelOctree
from voxnerf.prior.pseudo_depth import MeshCaster, PriorDepthRenderer


def renderer_for(path, sigma: float) -> tuple[PriorDepthRenderer, SparseVoxelOctree]:
    prior = load_prior(path, sigma)
    svo = SparseVoxelOctree.from_points(torch.from_numpy(prior.points).float(), prior.sigma)
    return PriorDepthRenderer(prior, svo), svo


def test_mesh_distance_inside_a_box_is_analytic(tmp_path):
    half = np.array([1.0, 0.75, 0.5])
    path = tmp_path / "room.ply"
    trimesh.creation.box(extents=2 * half).export(path)
    renderer, _ = renderer_for(path, 0.05)
    rng = np.random.default_rng(0)
    n = 2000
    o = rng.uniform(-0.8, 0.8, (n, 3)) * half
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    # Distance from inside a box to its wall along d: the nearest positive slab exit.
    expected = ((np.sign(d) * half - o) / d).min(axis=1)
    t, valid = renderer.ray_distance(torch.from_numpy(o).float(), torch.from_numpy(d).float(), 0.0, 10.0)
    assert valid.all() and t.dtype == torch.float32
    assert np.allclose(t.numpy(), expected, atol=1e-4)


def test_mesh_distance_to_a_plane_and_validity(tmp_path):
    path = tmp_path / "floor.obj"
    corners = [[-5, -5, 0], [5, -5, 0], [5, 5, 0], [-5, 5, 0]]
    quad = trimesh.Trimesh(vertices=corners, faces=[[0, 1, 2], [0, 2, 3]])
    quad.export(path)
    renderer, _ = renderer_for(path, 0.1)
    rng = np.random.default_rng(1)
    n = 1000
    o = np.c_[rng.uniform(-1, 1, (n, 2)), rng.uniform(0.5, 2.0, n)]
    d = np.c_[rng.uniform(-0.5, 0.5, (n, 2)), -np.ones(n)]
    d[: n // 10, 2] = 1.0  # looking up: no hit
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    t_max = np.full(n, 10.0)
    t_max[n // 10 : n // 5] = 0.1  # surface beyond t_max
    t, valid = renderer.ray_distance(
        torch.from_numpy(o).float(), torch.from_numpy(d).float(), 0.0, torch.from_numpy(t_max).float()
    )
    expected = -o[:, 2] / d[:, 2]
    assert not valid[: n // 5].any()
    assert torch.equal(t[: n // 5], torch.from_numpy(t_max[: n // 5]).float())
    assert valid[n // 5 :].all()
    assert np.allclose(t[n // 5 :].numpy(), expected[n // 5 :], atol=1e-5)


def test_point_cloud_depth_is_where_the_ray_passes_its_first_leafs_points(tmp_path):
    rng = np.random.default_rng(2)
    wall = np.c_[rng.uniform(-1, 1, (80_000, 2)), rng.normal(0, 0.005, 80_000)]  # ~8 points per voxel
    path = tmp_path / "wall.ply"
    trimesh.PointCloud(wall).export(path)
    renderer, svo = renderer_for(path, 0.02)
    generator = torch.Generator().manual_seed(0)
    o = torch.tensor([[0.0, 0.0, 1.0]]).repeat(500, 1)
    sideways = torch.rand(500, 2, generator=generator) - 0.5
    d = torch.nn.functional.normalize(torch.cat([sideways, -torch.ones(500, 1)], 1), dim=1)
    t_min = torch.rand(500, generator=generator) * 0.5
    t, valid = renderer.ray_distance(o, d, t_min, 3.0)
    t_svo, hit_svo = svo.first_hit(o, d, t_min, 3.0)
    assert torch.equal(valid, hit_svo) and valid.float().mean() > 0.98
    # Within the first leaf: at or after its entry, at most a leaf diagonal later.
    assert (t >= t_svo).all() and (t <= t_svo + 3**0.5 * svo.leaf_size / d[:, 2].abs() + 1e-6).all()
    # Depths lie on the wall z = 0 give or take the noise (std 0.005): the mean of a leaf's ~8 points is
    # far closer than the leaf's entry face, which is up to a leaf (0.02) in front.
    z_mean = (o + t[:, None] * d)[valid, 2]
    z_entry = (o + t_svo[:, None] * d)[valid, 2]
    assert z_mean.abs().max() < 0.012
    assert z_mean.abs().mean() < 0.5 * z_entry.abs().mean()


@pytest.mark.parametrize("t_min", [0.0, 0.6])
def test_mesh_hits_before_t_min_are_invalid(tmp_path, t_min):
    path = tmp_path / "box.ply"
    trimesh.creation.box(extents=(1.0, 1.0, 1.0)).export(path)
    renderer, _ = renderer_for(path, 0.05)
    t, valid = renderer.ray_distance(torch.zeros(1, 3), torch.tensor([[1.0, 0.0, 0.0]]), t_min, 5.0)
    assert valid.item() is (t_min < 0.5)
    assert t.item() == pytest.approx(0.5 if t_min < 0.5 else 5.0)


def _room_and_rays(n: int = 4000):
    room = trimesh.util.concatenate([trimesh.creation.box(extents=[4.0, 3.0, 2.5]), trimesh.creation.icosphere(3, 0.4)])
    rng = np.random.default_rng(1)
    origins = rng.uniform(-1.5, 1.5, (n, 3)) * [1.0, 0.8, 0.6]
    dirs = rng.normal(size=(n, 3)) * rng.uniform(0.5, 2.0, (n, 1))  # not unit: t is in units of |dir|
    dirs[:50] = [0.0, 0.0, 1e-3]  # slow rays still hit
    return room, origins, dirs


def test_mesh_caster_backends_agree():
    room, origins, dirs = _room_and_rays()
    by_open3d = MeshCaster(room.vertices, room.faces, backend="open3d").distance(origins, dirs)
    embree = MeshCaster(room.vertices, room.faces, backend="embree")
    by_embree = embree.distance(origins, dirs)
    assert embree.backend == "embree" and by_embree.dtype == np.float32 and by_embree.shape == (len(origins),)
    assert np.array_equal(np.isfinite(by_open3d), np.isfinite(by_embree))
    hit = np.isfinite(by_open3d)
    assert hit.mean() > 0.9 and np.allclose(by_embree[hit], by_open3d[hit], rtol=1e-4, atol=1e-4)
    outward = MeshCaster(room.vertices, room.faces, backend="embree").distance(np.array([[10.0, 0, 0]]),
                                                                              np.array([[1.0, 0, 0]]))
    assert np.isinf(outward).all()
    assert embree.distance(np.zeros((0, 3)), np.zeros((0, 3))).shape == (0,)


def test_mesh_caster_auto_takes_open3d_when_installed_else_embree(monkeypatch):
    room, _, _ = _room_and_rays(1)
    assert MeshCaster(room.vertices, room.faces).backend == "open3d"
    monkeypatch.setattr(pseudo_depth, "_importable", lambda module: module != "open3d")
    assert MeshCaster(room.vertices, room.faces).backend == "embree"


def test_mesh_caster_refuses_without_a_backend_or_an_unknown_one(monkeypatch):
    room, _, _ = _room_and_rays(1)
    with pytest.raises(ValueError, match="unknown mesh caster backend 'optix'"):
        MeshCaster(room.vertices, room.faces, backend="optix")
    monkeypatch.setattr(pseudo_depth, "_importable", lambda module: False)
    with pytest.raises(ImportError, match="needs open3d or embreex"):
        MeshCaster(room.vertices, room.faces)
