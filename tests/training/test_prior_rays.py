"""Prior rays (voxnerf/training/prior_rays.py): the bank cast at set-up, its draws, and how a step uses them."""

from __future__ import annotations

import numpy as np
import pytest
import torch
import trimesh

from voxnerf.config import TrainConfig
from voxnerf.data.scene import SceneTransform
from voxnerf.model.samplers import RayBundle
from voxnerf.model.voxnerf_model import Batch, VoxNeRFModel
from voxnerf.prior.loading import GeometryPrior
from voxnerf.prior.octree import SparseVoxelOctree
from voxnerf.prior.pseudo_depth import PriorDepthRenderer
from voxnerf.training.prior_rays import PriorRayBank, bank_size, camera_centre_rays, prior_ray_bank, seen_by
from voxnerf.training.step import make_loss_fn


def _box_prior() -> GeometryPrior:
    """The inside of a box of half-side 0.8 (normalised units) as a mesh prior."""
    mesh = trimesh.creation.box(extents=(1.6, 1.6, 1.6))
    points = np.asarray(mesh.sample(20_000, seed=0), dtype=np.float64)
    return GeometryPrior(kind="mesh", points=points, mesh=mesh, sigma=0.05, sigma_estimated=False,
                         num_input_points=len(mesh.vertices), num_outliers_removed=0)


def _model() -> VoxNeRFModel:
    cfg = TrainConfig(max_iters=1, hash_levels=4, hash_log2_size=10, hash_max_resolution=32, hidden_dim=16)
    aabb = torch.tensor([[-0.9, -0.9, -0.9], [0.9, 0.9, 0.9]])
    return VoxNeRFModel.create(cfg, SceneTransform((0.0, 0.0, 0.0), 1.0), aabb, None, torch.device("cpu"))


def test_camera_centre_rays_start_at_a_centre_with_unit_directions_spread_over_the_sphere():
    centres = torch.tensor([[0.1, 0.0, 0.0], [-0.2, 0.3, 0.0]])
    origins, dirs = camera_centre_rays(centres, 4000, torch.Generator().manual_seed(0))
    assert all(any(torch.equal(o, c) for c in centres) for o in origins[:50])
    torch.testing.assert_close(torch.linalg.vector_norm(dirs, dim=-1), torch.ones(4000))
    assert torch.allclose(dirs.mean(0), torch.zeros(3), atol=0.05)  # no preferred direction


def test_the_bank_keeps_rays_that_hit_the_prior_with_its_distance_and_first_hits():
    prior = _box_prior()
    octree = SparseVoxelOctree.from_points(torch.from_numpy(prior.points).float(), prior.sigma)
    renderer = PriorDepthRenderer(prior, octree)
    bank = prior_ray_bank(torch.zeros(1, 3), _model(), renderer, octree, 2000)
    assert 1900 <= len(bank) <= 2000  # from the centre every direction meets a face of the box
    exit_t = 0.8 / bank.rays.dirs.abs().amax(-1)  # where each ray leaves the box from its centre
    torch.testing.assert_close(bank.target_t, exit_t, atol=1e-3, rtol=0)
    assert bool(bank.rays.hit.float().mean() > 0.95)
    hit = bank.rays.hit
    assert float((bank.rays.hit_t[hit] - bank.target_t[hit]).abs().median()) < 0.05  # within a leaf


def test_a_bank_that_never_meets_the_prior_is_empty():
    prior = _box_prior()
    octree = SparseVoxelOctree.from_points(torch.from_numpy(prior.points).float(), prior.sigma)
    outside = torch.tensor([[5.0, 5.0, 5.0]])  # outside the scene box: every ray is empty
    bank = prior_ray_bank(outside, _model(), PriorDepthRenderer(prior, octree), octree, 100)
    assert len(bank) == 0


def test_draws_come_with_their_first_hits_and_the_bank_size_is_bounded():
    n = 10
    rays = RayBundle(torch.zeros(n, 3), torch.eye(3).repeat(4, 1)[:n], torch.zeros(n), torch.ones(n),
                     torch.arange(n).float() - 0.5, torch.ones(n, dtype=torch.bool))
    bank = PriorRayBank(rays, torch.arange(n).float())
    rays, target, unseen = bank.draw(64, torch.Generator().manual_seed(0))
    assert len(rays) == 64 and torch.equal(rays.hit_t, target - 0.5) and unseen is None
    assert bank_size(512) == 65_536 and bank_size(10**6) == 524_288


class _StubModel(VoxNeRFModel):
    def __init__(self) -> None:
        from types import SimpleNamespace

        self.transform = SimpleNamespace(scale=1.0)
        self.appearance = self.pose_refinement = None

    def render_samples(self, origins, dirs, starts, ends, background=None):
        return {"rgb": starts.mean(-1, keepdim=True).expand(-1, 3), "depth": starts[:, 0]}


@pytest.mark.parametrize("n_prior", [0, 4])
def test_prior_rays_enter_the_depth_loss_but_not_the_colour_loss(n_prior):
    g = torch.Generator().manual_seed(0)
    r = 8 + n_prior
    starts = torch.rand(r, 4, generator=g)
    target_rgb = torch.rand(r, 3, generator=g)
    target_rgb[8:] = 100.0  # a prior ray's colour target must never count
    target_t = torch.rand(r, generator=g) + 5.0
    args = (torch.zeros(r, 3), torch.ones(r, 3), starts, starts + 0.1, target_rgb, target_t,
            torch.ones(r, dtype=torch.bool), None, torch.zeros(r, dtype=torch.int64), torch.tensor(0.3))
    total, lc, ld, *_ = make_loss_fn(_StubModel(), TrainConfig(max_iters=1), 0.1, 0, 8, n_prior)(Batch(*args))
    expected_colour = ((starts[:8].mean(-1, keepdim=True) - target_rgb[:8]) ** 2).mean()
    torch.testing.assert_close(lc, expected_colour)
    assert float(ld) > 0 and torch.isfinite(total)


def test_a_point_is_seen_where_a_view_projects_it_in_front_at_its_depth_target():
    c2w = torch.eye(4)[None]  # at the origin, looking down -Z
    intr = torch.tensor([[10.0, 10.0, 5.0, 5.0]])
    depth = torch.ones(1, 10, 10)
    depth[0, 0, 0] = float("nan")  # a pixel without a target sees whatever projects there
    points = torch.tensor([[0.0, 0.0, -1.0],  # at the target: seen
                           [0.0, 0.0, -2.0],  # behind the surface the view saw: unseen
                           [0.0, 0.0, 1.0],  # behind the camera
                           [5.0, 0.0, -1.0],  # outside the image
                           [-0.45, 0.45, -1.0]])  # projects onto pixel (0, 0)
    assert seen_by(points, c2w, intr, depth, tolerance=0.05).tolist() == [True, False, False, False, True]


def test_prior_rays_to_unseen_surfaces_are_pulled_to_the_mean_colour_with_their_weight():
    g = torch.Generator().manual_seed(0)
    r = 8 + 4
    starts = torch.rand(r, 4, generator=g)
    target_rgb = torch.rand(r, 3, generator=g)
    weight = torch.tensor([1.0] * 8 + [0.5, 0.0, 0.5, 0.0])
    args = (torch.zeros(r, 3), torch.ones(r, 3), starts, starts + 0.1, target_rgb, torch.rand(r, generator=g) + 5,
            torch.ones(r, dtype=torch.bool), None, torch.zeros(r, dtype=torch.int64), torch.tensor(0.3), weight)
    _, lc, *_ = make_loss_fn(_StubModel(), TrainConfig(max_iters=1), 0.1, 0, 8, 4)(Batch(*args))
    err = ((starts.mean(-1, keepdim=True) - target_rgb) ** 2).mean(-1)
    torch.testing.assert_close(lc, (err[:8].sum() + 0.5 * (err[8] + err[10])) / 8)


@pytest.mark.parametrize(("prior_rays", "has_prior", "use_depth", "why"), [
    (0, True, True, "prior_rays 0"), (64, False, True, "no prior"), (64, True, False, "no depth loss")])
def test_the_prior_rays_stage_says_why_it_did_not_run(prior_rays, has_prior, use_depth, why):
    from voxnerf.training.stages import prior_rays_stage

    cfg = TrainConfig(max_iters=1, prior_rays=prior_rays)
    stage = prior_rays_stage(cfg, _box_prior() if has_prior else None, use_depth, None, None, None,
                             torch.device("cpu"))
    assert stage.bank is None and not stage.record.ran and stage.record.why == why
