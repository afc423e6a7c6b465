"""Free-space carving of the sampler octree by measured depth (voxnerf.prior.carving) and SparseVoxelOctree's
keep_leaves."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from voxnerf.prior.carving import MIN_FREE_VOTES, carve_free_space, remove_empty
from voxnerf.prior.octree import SparseVoxelOctree

LEAF = 0.05


def _wall_and_outliers() -> tuple[torch.Tensor, torch.Tensor]:
    """A wall of points on x = 1 (y, z in [-0.3, 0.3]) and a cluster of outliers around (0.5, 0, 0)."""
    g = torch.linspace(-0.3, 0.3, 25)
    yy, zz = torch.meshgrid(g, g, indexing="ij")
    wall = torch.stack([torch.ones_like(yy), yy, zz], dim=-1).reshape(-1, 3)
    outliers = torch.tensor([[0.5, 0.0, 0.0], [0.5, 0.01, 0.0], [0.52, -0.01, 0.01]])
    return wall, outliers


def _rays_to_wall(n: int = 25, spread: float = 0.02) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """``n`` rays from near (-0.2, 0, 0) along +x, offset in y and z by up to ``spread``; measured depth: the
    wall's."""
    offsets = torch.linspace(-spread, spread, int(math.sqrt(n)))
    oy, oz = torch.meshgrid(offsets, offsets, indexing="ij")
    origins = torch.stack([torch.full_like(oy, -0.2), oy, oz], dim=-1).reshape(-1, 3)
    dirs = torch.tensor([[1.0, 0.0, 0.0]]).expand_as(origins).contiguous()
    return origins, dirs, torch.full((len(origins),), 1.2)


def _first_hit(tree: SparseVoxelOctree, origins: torch.Tensor, dirs: torch.Tensor) -> torch.Tensor:
    near, far = torch.zeros(len(origins)), torch.full((len(origins),), 3.0)
    t, hit = tree.first_hit(origins, dirs, near, far)
    return torch.where(hit, t, torch.full_like(t, math.inf))


def test_keep_leaves_keeps_the_chosen_leaves_on_the_same_grid():
    wall, outliers = _wall_and_outliers()
    tree = SparseVoxelOctree.from_points(torch.cat([wall, outliers]), LEAF)
    outlier_leaves = tree.leaf_index(outliers)[0]
    keep = torch.ones(tree.codes[-1].numel(), dtype=torch.bool)
    keep[outlier_leaves] = False
    kept = tree.keep_leaves(keep)
    assert kept.codes[-1].numel() == tree.codes[-1].numel() - outlier_leaves.unique().numel()
    assert torch.equal(kept.origin, tree.origin) and kept.leaf_size == tree.leaf_size and kept.levels == tree.levels
    assert kept.leaf_occupied(wall).all() and not kept.leaf_occupied(outliers).any()
    for parent, child in zip(kept.codes[:-1], kept.codes[1:], strict=True):  # every node's parent is there
        assert torch.isin(child >> 3, parent).all()
    origins, dirs, _ = _rays_to_wall()
    assert (_first_hit(tree, origins, dirs) < 0.9).any()
    assert (_first_hit(kept, origins, dirs) > 1.1).all() and (_first_hit(kept, origins, dirs) < 1.3).all()


@pytest.mark.parametrize(("keep", "message"), [
    (lambda n: torch.zeros(n, dtype=torch.bool), "empty"),
    (lambda n: torch.ones(n + 1, dtype=torch.bool), "shape"),
    (lambda n: torch.ones(n), "bool"),
])
def test_keep_leaves_refuses_an_empty_or_misshapen_mask(keep, message):
    tree = SparseVoxelOctree.from_points(_wall_and_outliers()[0], LEAF)
    with pytest.raises(ValueError, match=message):
        tree.keep_leaves(keep(tree.codes[-1].numel()))


def test_rays_that_see_the_wall_carve_the_outliers_in_front_of_it():
    wall, outliers = _wall_and_outliers()
    tree = SparseVoxelOctree.from_points(torch.cat([wall, outliers]), LEAF)
    origins, dirs, depth = _rays_to_wall()
    carving = carve_free_space(tree, origins + depth[:, None] * dirs, origins, dirs, depth - 2 * LEAF)
    assert carving.carved == tree.codes[-1].numel() - carving.octree.codes[-1].numel() > 0
    assert not carving.octree.leaf_occupied(outliers).any() and carving.octree.leaf_occupied(wall).all()
    hits = _first_hit(carving.octree, origins, dirs)
    assert ((hits > 1.1) & (hits < 1.3)).all()  # each ray now stops at the wall it measured
    assert carving.rays == len(origins) and carving.leaves == tree.codes[-1].numel()
    assert f"carved {carving.carved} of {carving.leaves} leaves" in carving.describe()


def test_a_leaf_holding_a_measured_surface_point_is_kept_though_rays_cross_it():
    wall, outliers = _wall_and_outliers()
    tree = SparseVoxelOctree.from_points(torch.cat([wall, outliers]), LEAF)
    origins, dirs, depth = _rays_to_wall()
    surface = torch.cat([origins + depth[:, None] * dirs, outliers[:1]])  # another view measured an outlier
    carving = carve_free_space(tree, surface, origins, dirs, depth - 2 * LEAF)
    assert carving.octree.leaf_occupied(outliers[:1]).all()


def test_one_ray_alone_does_not_carve():
    wall, outliers = _wall_and_outliers()
    tree = SparseVoxelOctree.from_points(torch.cat([wall, outliers]), LEAF)
    origins, dirs, depth = _rays_to_wall(n=1, spread=0.0)
    assert MIN_FREE_VOTES > 1
    carving = carve_free_space(tree, origins + depth[:, None] * dirs, origins, dirs, depth - 2 * LEAF)
    assert carving.carved == 0 and carving.octree is tree
    assert carve_free_space(tree, wall[:0], origins, dirs, depth, min_votes=1).carved > 0


def test_each_ray_votes_once_for_every_leaf_it_crosses_in_any_direction():
    """Leaf-to-leaf tracing against dense sampling (every 1/50 leaf) on oblique rays through a random cloud: the
    same leaves, one vote per ray (dense sampling can only miss a corner that a ray barely clips)."""
    gen = torch.Generator().manual_seed(0)
    cloud = torch.rand(400, 3, generator=gen)
    tree = SparseVoxelOctree.from_points(cloud, 0.1)
    origins = torch.rand(300, 3, generator=gen) * 0.2 - 0.1
    dirs = torch.nn.functional.normalize(torch.rand(300, 3, generator=gen) + 0.2, dim=1)
    until = torch.rand(300, generator=gen) * 1.5
    from voxnerf.prior.carving import _free_votes

    votes = _free_votes(tree, origins, dirs, until)
    t = torch.arange(1, 2000) * (0.1 / 50)
    dense = torch.zeros_like(votes)
    for o, d, u in zip(origins, dirs, until, strict=True):
        pos, found = tree.leaf_index(o + t[t <= u][:, None] * d)
        dense[pos[found].unique()] += 1
    assert (votes >= dense).all() and (votes == dense).float().mean() > 0.97 and int(votes.sum()) > 100
    assert int(votes.max()) <= 300


def test_free_space_ends_where_the_ray_says():
    """The margin keeps what lies just before the measured depth: free space up to 0.3 carves nothing at 0.5."""
    wall, outliers = _wall_and_outliers()
    tree = SparseVoxelOctree.from_points(torch.cat([wall, outliers]), LEAF)
    origins, dirs, depth = _rays_to_wall()
    carving = carve_free_space(tree, wall[:0], origins, dirs, torch.full_like(depth, 0.5))
    assert carving.carved == 0


def test_rays_without_a_usable_depth_vote_nothing():
    wall, outliers = _wall_and_outliers()
    tree = SparseVoxelOctree.from_points(torch.cat([wall, outliers]), LEAF)
    origins, dirs, depth = _rays_to_wall()
    bad = torch.tensor([math.nan, math.inf, -math.inf, -1.0, 0.0]).repeat(5)[: len(depth)]
    nan_points = torch.full((4, 3), math.nan)
    carving = carve_free_space(tree, nan_points, origins, dirs, bad)
    assert carving.carved == 0 and carving.surface_leaves == 0


def test_carving_that_would_empty_the_octree_leaves_it_whole():
    outliers = _wall_and_outliers()[1]
    tree = SparseVoxelOctree.from_points(outliers, LEAF)
    origins, dirs, depth = _rays_to_wall()
    carving = carve_free_space(tree, outliers[:0], origins, dirs, depth)
    assert carving.octree is tree and carving.carved == 0


def test_misshapen_rays_are_refused():
    tree = SparseVoxelOctree.from_points(_wall_and_outliers()[0], LEAF)
    origins, dirs, depth = _rays_to_wall()
    with pytest.raises(ValueError, match="origins and dirs"):
        carve_free_space(tree, origins, origins, dirs[:, :2], depth)
    with pytest.raises(ValueError, match="free_until"):
        carve_free_space(tree, origins, origins, dirs, depth[:-1])


def test_remove_empty_refuses_a_mask_of_another_shape_and_keeps_an_octree_it_would_empty():
    tree = SparseVoxelOctree.from_points(_wall_and_outliers()[0], LEAF)
    n = tree.codes[-1].numel()
    with pytest.raises(ValueError, match="empty must be a bool tensor"):
        remove_empty(tree, torch.ones(n + 1, dtype=torch.bool), 0, 0)
    with pytest.raises(ValueError, match="empty must be a bool tensor"):
        remove_empty(tree, torch.ones(n), 0, 0)
    whole = remove_empty(tree, torch.ones(n, dtype=torch.bool), 5, 7)
    assert whole.octree is tree and whole.carved == 0 and (whole.surface_leaves, whole.rays) == (5, 7)
    first = torch.zeros(n, dtype=torch.bool)
    first[0] = True
    one = remove_empty(tree, first, 0, 0)
    assert one.carved == 1 and one.octree.codes[-1].numel() == n - 1


# --- the octree_carving stage on a rendered room (noisy point-cloud prior with outliers, exact depth maps) ------


@pytest.fixture(scope="module")
def micro_room(tmp_path_factory):
    from synthetic_fixtures import make_micro_scene

    return make_micro_scene(tmp_path_factory, "carving")


def _short_falls(run) -> float:
    """Fraction of the run's training pixels with depth whose octree first hit lies more than the sampler's
    half window before the measured depth (the importance samples miss the surface the pixel sees)."""
    from voxnerf.data.scene import load_scene
    from voxnerf.inference.render import load_model
    from voxnerf.training.pixels import sensor_ray_distance, training_pixels

    trained = load_model(run, "cpu")
    model, scene = trained.model, load_scene(trained.scene_dir)
    pixels = training_pixels(scene, model.transform, torch.device("cpu"))
    z = torch.from_numpy(np.stack([scene.depths[i] for i in scene.train_indices])).float()
    measured = sensor_ray_distance(pixels, z, model.transform.scale).view(-1)
    n, h, w = pixels.shape
    flat = torch.arange(n * h * w)
    rays = model.ray_bundle(*pixels.rays(flat // (h * w), flat % (h * w) // w, flat % w))
    sampler = model.sampler()
    hit_t, hit = sampler.first_hits(rays)
    seen = torch.isfinite(measured)
    return float((hit & seen & (hit_t < measured - sampler.half_window)).sum() / seen.sum())


def test_the_stage_carves_what_the_depth_maps_see_through_and_rays_stop_at_their_surface(micro_room, tmp_path):
    from synthetic_fixtures import micro_config

    from voxnerf.training.run import train

    reports = {}
    for carve in (True, False):
        cfg = micro_config(max_iters=1, final_eval=False, octree_carving=carve, setup_cache=False)
        reports[carve] = train(micro_room, tmp_path / str(carve), cfg, progress_bar=False)
    why = {carve: {s.name: (s.ran, s.why) for s in r.stages}["octree_carving"] for carve, r in reports.items()}
    assert why[False] == (False, "octree_carving false")
    assert why[True][0] and why[True][1].startswith("carved ") and "sigma(z) before each measured depth" in why[True][1]
    leaves = {carve: r.octree["nodes_per_level"][-1] for carve, r in reports.items()}
    assert 0 < leaves[False] - leaves[True] < 0.2 * leaves[False]
    short = {carve: _short_falls(tmp_path / str(carve)) for carve in (True, False)}
    assert short[True] < 0.9 * short[False]  # on this 24x18 room: 2.7 % of pixels -> 2.2 %


def test_the_stage_says_why_it_did_not_run():
    from types import SimpleNamespace

    from voxnerf.config import TrainConfig
    from voxnerf.training import stages

    tree = SparseVoxelOctree.from_points(_wall_and_outliers()[0], LEAF)
    no_sensor = stages.DepthTargetStage(record=None, target_t=torch.zeros(1, 2, 2), beta=0.1)
    sensor = stages.DepthTargetStage(record=None, target_t=torch.zeros(1, 2, 2), beta=0.1,
                                     sensor_t=torch.zeros(1, 2, 2))
    unmeasured = stages.DepthTargetStage(record=None, target_t=torch.zeros(1, 2, 2), beta=0.1,
                                         sensor_t=torch.full((1, 2, 2), math.nan))
    pixels = SimpleNamespace(shape=(1, 2, 2))
    cases = [(TrainConfig(octree_carving=False), tree, sensor, "octree_carving false"),
             (TrainConfig(), None, sensor, "no octree"),
             (TrainConfig(), tree, no_sensor, "no sensor depth in use (the depth target is not the sensor's)"),
             (TrainConfig(), tree, unmeasured, "no training pixel has sensor depth")]
    for cfg, octree, target, why in cases:
        stage = stages.carving_stage(cfg, octree, pixels, target, 1.0)
        assert stage.octree is None and not stage.record.ran and stage.record.why == why
