"""voxnerf.model.voxnerf_model: the ray-box slab test, the sampler a config chooses, clipping rays to the scene box,
and a
checkpoint's state dict that rebuilds the same model."""

from __future__ import annotations

import math

import pytest
import torch

from voxnerf.config import TrainConfig
from voxnerf.data.scene import SceneTransform
from voxnerf.model.colour_prior import ColourPrior
from voxnerf.model.samplers import OccGridSampler, UniformSampler, VoxNeRFSampler
from voxnerf.model.voxnerf_model import NEAR_MIN, VoxNeRFModel, field_for, ray_aabb
from voxnerf.prior.octree import SparseVoxelOctree

BOX = torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])
SMALL = dict(compile=False, hash_kernel=False, hash_levels=4, hash_log2_size=12, hidden_dim=16,
             occgrid_resolution=8)


def _model(sampler: str = "voxnerf", octree: SparseVoxelOctree | None = None) -> VoxNeRFModel:
    torch.manual_seed(0)
    cfg = TrainConfig(max_iters=1, sampler=sampler, **SMALL)
    return VoxNeRFModel.create(cfg, SceneTransform((0.5, -1.0, 2.0), 0.25), BOX * 0.8, octree, torch.device("cpu"))


def _octree() -> SparseVoxelOctree:
    points = torch.tensor([[0.1, 0.1, 0.1], [-0.3, 0.2, 0.4], [0.5, -0.5, 0.0]])
    return SparseVoxelOctree.from_points(points, 0.05)


def test_ray_aabb_enters_and_leaves_the_box():
    origins = torch.tensor([[-3.0, 0.0, 0.0], [0.0, 0.0, 0.0]])
    dirs = torch.tensor([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])
    t0, t1 = ray_aabb(origins, dirs, BOX)
    assert t0.tolist() == [2.0, -1.0] and t1.tolist() == [4.0, 1.0]


def test_ray_aabb_axis_parallel_rays_have_no_nan():
    origins = torch.tensor([[0.5, 0.5, -5.0], [2.0, 0.0, -5.0]])  # the second runs outside the x slab
    dirs = torch.tensor([[0.0, 0.0, 1.0], [0.0, 0.0, 1.0]])
    t0, t1 = ray_aabb(origins, dirs, BOX)
    assert torch.isfinite(t0).all() and torch.isfinite(t1).all()
    assert (t0[0].item(), t1[0].item()) == (4.0, 6.0)
    assert t0[1] > t1[1]  # a miss


def test_ray_aabb_miss_gives_an_empty_range():
    t0, t1 = ray_aabb(torch.tensor([[0.0, 5.0, 0.0]]), torch.tensor([[1.0, 0.0, 0.0]]), BOX)
    assert t0.item() > t1.item()


def test_ray_bundle_clips_to_the_box_and_keeps_misses_empty():
    model = _model()
    origins = torch.tensor([[0.0, 0.0, 0.0], [0.0, 5.0, 0.0]])
    dirs = torch.nn.functional.normalize(torch.tensor([[1.0, 0.0, 0.0], [1.0, 0.1, 0.0]]), dim=-1)
    rays = model.ray_bundle(origins, dirs)
    assert rays.near[0].item() == pytest.approx(NEAR_MIN)
    assert rays.far[0].item() == pytest.approx(0.8)
    assert rays.near[1].item() == pytest.approx(NEAR_MIN)
    assert 0 < rays.far[1] - rays.near[1] <= 1e-5


@pytest.mark.parametrize(
    ("sampler", "with_octree", "expected"),
    [("uniform", True, UniformSampler), ("occgrid", True, OccGridSampler), ("voxnerf", True, VoxNeRFSampler),
     ("voxnerf", False, OccGridSampler), ("auto", True, VoxNeRFSampler), ("auto", False, OccGridSampler)],
)
def test_sampler_follows_the_config_and_the_octree(sampler, with_octree, expected):
    model = _model(sampler, _octree() if with_octree else None)
    assert type(model.sampler()) is expected


def test_use_sampler_switches_the_sampler_and_the_config_a_checkpoint_keeps():
    model = _model("auto", _octree())
    model.use_sampler("occgrid")
    assert type(model.sampler()) is OccGridSampler and model.config.for_model()["sampling"]["sampler"] == "occgrid"


def test_the_voxnerf_sampler_fills_octree_misses_as_the_config_says_on_the_model_s_device(monkeypatch):
    model = _model("voxnerf", _octree())
    assert model.sampler().misses == "gather"  # "auto" on a CPU
    model.config = model.config.updated(octree_misses="mask")
    assert model.sampler().misses == "mask"
    model.config = model.config.updated(octree_misses="auto")
    monkeypatch.setattr(VoxNeRFModel, "device", property(lambda self: torch.device("cuda")))  # a GPU's model
    assert model.sampler().misses == "mask"


def test_field_for_follows_the_resolved_preset():
    field = field_for(TrainConfig(max_iters=1, preset="cpu", hash_kernel=False))
    cfg = TrainConfig(max_iters=1, preset="cpu").resolved()
    table = next(p for name, p in field.named_parameters() if "encoding" in name)
    assert table.numel() <= cfg.model.hash_levels * 2**cfg.model.hash_log2_size * cfg.model.hash_features
    assert field.encoding.use_kernel is False


def test_render_rays_gives_finite_outputs_of_the_documented_shapes():
    model = _model("voxnerf", _octree())
    rays = model.ray_bundle(torch.zeros(5, 3), torch.nn.functional.normalize(torch.randn(5, 3), dim=-1))
    out = model.render_rays(rays, model.sampler())
    assert out["rgb"].shape == (5, 3) and out["depth"].shape == (5,) and out["opacity"].shape == (5,)
    assert all(torch.isfinite(v).all() for v in out.values())


def test_state_dict_round_trip_renders_the_same():
    model = _model("voxnerf", _octree())
    rebuilt = VoxNeRFModel.from_state_dict(model.state_dict(), torch.device("cpu"))
    assert rebuilt.config == model.config
    assert rebuilt.transform == model.transform
    assert torch.equal(rebuilt.aabb, model.aabb)
    rays = model.ray_bundle(torch.zeros(4, 3), torch.eye(3)[[0, 1, 2, 0]] * torch.tensor([[1.0], [-1.0], [1.0], [-1]]))
    a, b = model.render_rays(rays, model.sampler()), rebuilt.render_rays(rays, rebuilt.sampler())
    for name in a:
        assert torch.equal(a[name], b[name]), name


def test_state_dict_without_octree_rebuilds_without_one():
    model = _model("occgrid")
    rebuilt = VoxNeRFModel.from_state_dict(model.state_dict(), torch.device("cpu"))
    assert rebuilt.octree is None and type(rebuilt.sampler()) is OccGridSampler


def test_background_follows_the_config():
    model = _model()
    assert model.background.tolist() == [0.0, 0.0, 0.0]
    assert math.isclose(model.transform.scale, 0.25)


def test_render_samples_composites_over_a_given_background_else_the_models():
    model = _model()
    origins, dirs = torch.zeros(2, 3), torch.tensor([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    starts = torch.linspace(0.0, 0.01, 3).expand(2, 3).contiguous()  # a short stretch: mostly transparent
    ends = starts + 0.001
    with torch.no_grad():
        black = model.render_samples(origins, dirs, starts, ends)
        white = model.render_samples(origins, dirs, starts, ends, torch.ones(2, 3))
    residual = (1.0 - black["opacity"])[:, None]
    assert float(residual.min()) > 0.5
    torch.testing.assert_close(white["rgb"], black["rgb"] + residual)


def _cone_model(cone_radius) -> VoxNeRFModel:
    torch.manual_seed(0)
    cfg = TrainConfig(max_iters=1, sampler="occgrid", cone_radius=cone_radius, **SMALL)
    model = VoxNeRFModel.create(cfg, SceneTransform((0.0, 0.0, 0.0), 1.0), BOX * 0.8, None, torch.device("cpu"))
    with torch.no_grad():
        model.field.encoding.table.uniform_(-1.0, 1.0)
    return model


def test_a_cone_reads_each_sample_over_its_distance_times_the_cone_and_survives_the_checkpoint():
    points, cone = _cone_model(None), _cone_model(0.01)
    assert points.cone_radius is None and points.sample_radii(torch.ones(3)) is None
    torch.testing.assert_close(cone.sample_radii(torch.tensor([[0.5, 2.0]])), torch.tensor([0.005, 0.02]))
    origins, dirs = torch.zeros(2, 3), torch.tensor([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    starts = torch.linspace(0.1, 0.6, 5).expand(2, 5).contiguous()
    ends = starts + 0.05
    with torch.no_grad():
        a = points.render_samples(origins, dirs, starts, ends)
        b = cone.render_samples(origins, dirs, starts, ends)
        positions = origins[:, None] + (0.5 * (starts + ends))[..., None] * dirs[:, None]
        expected, _ = cone.field(positions.reshape(-1, 3), dirs.repeat_interleave(5, 0),
                                 (0.5 * (starts + ends)).reshape(-1) * 0.01)
    assert not torch.allclose(a["rgb"], b["rgb"])  # the same weights, read over footprints
    rebuilt = VoxNeRFModel.from_state_dict(cone.state_dict(), torch.device("cpu"))
    assert rebuilt.cone_radius == 0.01
    with torch.no_grad():
        torch.testing.assert_close(rebuilt.render_samples(origins, dirs, starts, ends)["rgb"], b["rgb"])
        density = cone.field.density(positions.reshape(-1, 3), (0.5 * (starts + ends)).reshape(-1) * 0.01)
    torch.testing.assert_close(density, expected)


def test_the_grid_reads_half_a_cell_where_the_field_reads_cones_and_points_otherwise():
    x = torch.rand(16, 3) * 2 - 1
    with torch.no_grad():
        points, cone = _cone_model(None), _cone_model(0.01)
        torch.testing.assert_close(points.grid_density(x), points.field.density(x))
        half_cell = torch.full((16,), 1.0 / cone.grid.resolution)
        torch.testing.assert_close(cone.grid_density(x), cone.field.density(x, half_cell))


def test_an_unresolved_auto_cone_is_refused():
    with pytest.raises(ValueError, match="cone_radius 'auto'"):
        _ = _cone_model("auto").cone_radius


# What rendered rays show behind their last sample: render_background and the colour prior.

GREEN = [0.0, 1.0, 0.0]


def _seen_model(sampler: str = "voxnerf", render_background: str = "nearest_seen") -> VoxNeRFModel:
    """A model whose octree holds one leaf around (0.1, 0.1, 0.1), with a colour prior of green pixels there."""
    octree = SparseVoxelOctree.from_points(torch.tensor([[0.1, 0.1, 0.1]]), 0.05)
    model = _model(sampler, octree)
    model.config = model.config.updated(render_background=render_background, background=(0.2, 0.3, 0.4))
    model.colour_prior = ColourPrior.pool(torch.tensor([[0.1, 0.1, 0.1]]), torch.tensor([GREEN]), finest=64, levels=3)
    return model


def _towards_the_leaf_and_away() -> tuple[torch.Tensor, torch.Tensor]:
    origins = torch.tensor([[-0.5, 0.1, 0.1], [-0.5, 0.1, 0.1]])
    dirs = torch.tensor([[1.0, 0.0, 0.0], [-1.0, 0.0, 0.0]])
    return origins, dirs


def test_a_ray_that_meets_the_prior_shows_the_colour_seen_there_and_one_that_misses_the_background():
    model = _seen_model()
    assert model.config.model.nearest_seen_weight == 1.0  # the default: the colour seen, unshrunk
    rays = model.ray_bundle(*_towards_the_leaf_and_away())
    rays, background = model.view_background(rays, model.sampler())
    torch.testing.assert_close(background, torch.tensor([GREEN, [0.2, 0.3, 0.4]]))
    assert rays.hit.tolist() == [True, False]  # the first hits are kept: the sampler does not cast them again
    assert 0.5 < float(rays.hit_t[0]) < 0.7


def test_the_colour_seen_is_shrunk_towards_the_background_by_its_weight():
    model = _seen_model()
    model.config = model.config.updated(nearest_seen_weight=0.75)
    _, background = model.view_background(model.ray_bundle(*_towards_the_leaf_and_away()), model.sampler())
    shrunk = [0.75 * g + 0.25 * b for g, b in zip(GREEN, [0.2, 0.3, 0.4], strict=True)]
    torch.testing.assert_close(background, torch.tensor([shrunk, [0.2, 0.3, 0.4]]))
    model.config = model.config.updated(nearest_seen_weight=0.0)  # the background alone, as render_background colour
    _, background = model.view_background(model.ray_bundle(*_towards_the_leaf_and_away()), model.sampler())
    torch.testing.assert_close(background, torch.tensor([[0.2, 0.3, 0.4], [0.2, 0.3, 0.4]]))


@pytest.mark.parametrize(("sampler", "render_background", "prior"), [
    ("voxnerf", "colour", True), ("occgrid", "nearest_seen", True), ("voxnerf", "nearest_seen", False)])
def test_otherwise_every_ray_shows_the_background(sampler, render_background, prior):
    model = _seen_model(sampler, render_background)
    if not prior:
        model.colour_prior = None
    rays = model.ray_bundle(*_towards_the_leaf_and_away())
    same, background = model.view_background(rays, model.sampler())
    assert same is rays and background.tolist() == pytest.approx([0.2, 0.3, 0.4])


def test_rendered_rays_composite_over_the_colour_seen_where_they_meet_the_prior():
    model = _seen_model()
    with torch.no_grad():
        model.field.encoding.table.fill_(0.0)
        for module in model.field.modules():  # a field of no density anywhere: every ray shows its background
            if isinstance(module, torch.nn.Linear):
                module.weight.zero_()
                module.bias.fill_(-30.0)
    out = model.render_rays(model.ray_bundle(*_towards_the_leaf_and_away()), model.sampler())
    torch.testing.assert_close(out["rgb"], torch.tensor([GREEN, [0.2, 0.3, 0.4]]), atol=1e-4, rtol=0)


def test_the_colour_prior_survives_the_checkpoint_and_an_older_checkpoint_has_none():
    model = _seen_model()
    rebuilt = VoxNeRFModel.from_state_dict(model.state_dict(), torch.device("cpu"))
    assert rebuilt.colour_prior.summary() == model.colour_prior.summary()
    older = model.state_dict()
    del older["colour_prior"]
    assert VoxNeRFModel.from_state_dict(older, torch.device("cpu")).colour_prior is None
