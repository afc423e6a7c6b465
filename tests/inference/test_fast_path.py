"""voxnerf.inference.fast_path: the fast path composites exactly what the full path does up to its stated bounds, skips
what cannot change a pixel, stays finite on stiff fields, and runs the MLPs in bfloat16 only where asked."""

from __future__ import annotations

import math

import pytest
import torch

from voxnerf.config import TrainConfig
from voxnerf.data.scene import SceneTransform
from voxnerf.errors import RunError
from voxnerf.inference import fast_path as inference
from voxnerf.inference.fast_path import (
    FastSettings,
    FieldRunner,
    field_runner,
    linear_relu,
    native_bfloat16,
    render_rays_fast,
)
from voxnerf.inference.render import render_normalized, resolved_render_path
from voxnerf.model.colour_prior import ColourPrior
from voxnerf.model.voxnerf_model import VoxNeRFModel
from voxnerf.prior.octree import SparseVoxelOctree

BOX = torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])
SMALL = dict(compile=False, hash_kernel=False, hash_levels=4, hash_log2_size=12, hidden_dim=16,
             occgrid_resolution=8)
EXACT = FastSettings(min_transmittance=1e-30, min_weight=0.0, skip_empty=False, precision="float32", block=7)


def _model(sampler: str = "voxnerf", density_bias: float = 0.0, seed: int = 0,
           cone_radius: float | None = None) -> VoxNeRFModel:
    torch.manual_seed(seed)
    cfg = TrainConfig(max_iters=1, sampler=sampler, cone_radius=cone_radius, **SMALL)
    points = torch.rand(400, 3) * 1.2 - 0.6
    octree = SparseVoxelOctree.from_points(points, 0.05) if sampler == "voxnerf" else None
    model = VoxNeRFModel.create(cfg, SceneTransform((0.0, 0.0, 0.0), 1.0), BOX * 0.8, octree, torch.device("cpu"))
    with torch.no_grad():
        model.field.density_mlp[-1].bias[0] += density_bias
        model.field.encoding.table.uniform_(-1.0, 1.0)  # a field with structure, not a near-constant one
    return model


def _rays(model: VoxNeRFModel, n: int = 64, seed: int = 1):
    g = torch.Generator().manual_seed(seed)
    origins = torch.rand(n, 3, generator=g) * 0.4 - 0.2
    dirs = torch.nn.functional.normalize(torch.randn(n, 3, generator=g), dim=-1)
    return model.ray_bundle(origins, dirs)


@pytest.fixture(params=[1, 2], ids=["1-thread", "2-threads"])
def torch_threads(request) -> int:
    """torch's threads for the test (the fast path spreads its blocks over them), restored after."""
    before = torch.get_num_threads()
    torch.set_num_threads(request.param)
    yield request.param
    torch.set_num_threads(before)


@pytest.mark.parametrize("sampler", ["voxnerf", "occgrid", "uniform"])
@pytest.mark.parametrize("cone_radius", [None, 0.02])
def test_without_skipping_the_fast_path_is_the_full_path(sampler, cone_radius, torch_threads):
    model = _model(sampler, cone_radius=cone_radius)
    rays = _rays(model)
    full = model.render_rays(rays, model.sampler())
    fast = render_rays_fast(model, rays, model.sampler(), EXACT)
    for name in ("rgb", "depth", "opacity"):
        assert torch.allclose(fast[name], full[name].detach(), atol=2e-6), name


def test_the_fast_path_shows_the_colour_seen_where_rays_meet_the_prior_as_the_full_path_does(torch_threads):
    model = _model("voxnerf", density_bias=-4.0)  # a faint field: the background shows through
    model.config = model.config.updated(render_background="nearest_seen")
    model.colour_prior = ColourPrior.pool(torch.rand(500, 3) * 1.2 - 0.6, torch.rand(500, 3))
    rays = _rays(model)
    full = model.render_rays(rays, model.sampler())
    fast = render_rays_fast(model, rays, model.sampler(), EXACT)
    model.config = model.config.updated(render_background="colour")
    plain = render_rays_fast(model, rays, model.sampler(), EXACT)
    assert torch.allclose(fast["rgb"], full["rgb"].detach(), atol=2e-6)
    assert not torch.allclose(fast["rgb"], plain["rgb"], atol=1e-3)  # the per-ray colours changed what shows


@pytest.mark.parametrize("dtype", [torch.float32, torch.bfloat16])
@pytest.mark.parametrize("fused", [False, True])
def test_linear_relu_is_relu_of_the_linear_layer(dtype, fused, monkeypatch):
    if fused and not inference._fused_linear_relu(dtype):
        pytest.skip("this torch or CPU has no fused oneDNN linear + ReLU in this dtype")
    monkeypatch.setattr(inference, "_fused_linear_relu", lambda dtype: fused)
    x, w, b = (torch.randn(*shape).to(dtype) for shape in ((300, 24), (64, 24), (64,)))
    out = linear_relu(x, w, b)
    assert out.dtype == dtype and out.shape == (300, 64) and bool((out >= 0).all())
    assert torch.equal(out, torch.nn.functional.linear(x, w, b).relu())


def test_a_dtype_the_cpu_cannot_fuse_is_probed_false_and_runs_unfused(monkeypatch):
    """oneDNN refuses a bfloat16 product on a CPU without AVX-512 (RuntimeError: no primitive descriptor): the probe
    says so for that dtype, and linear_relu then runs the two operations."""
    def refuses(x, *args):
        if x.dtype == torch.bfloat16:
            raise RuntimeError("could not create a primitive descriptor for the inner product forward propagation")
        return torch.nn.functional.linear(x, *args[:2]).relu()

    monkeypatch.setattr(torch.ops.mkldnn, "_linear_pointwise", refuses)
    probe = inference._fused_linear_relu.__wrapped__
    assert probe(torch.float32) and not probe(torch.bfloat16)
    monkeypatch.setattr(inference, "_fused_linear_relu", probe)
    x, w, b = (torch.randn(*shape).to(torch.bfloat16) for shape in ((30, 24), (64, 24), (64,)))
    assert torch.equal(linear_relu(x, w, b), torch.nn.functional.linear(x, w, b).relu())


def test_the_runner_splits_the_field_without_changing_it():
    model = _model()
    x = torch.rand(50, 3) * 2 - 1
    d = torch.nn.functional.normalize(torch.randn(50, 3), dim=-1)
    density, rgb = model.field(x, d)
    runner = FieldRunner(model.field, torch.float32)
    density_r, geo = runner.geometry(x)
    rgb_r = runner.color(geo, runner.direction_features(d))
    assert torch.allclose(density_r, density.detach(), rtol=1e-5)
    assert torch.allclose(rgb_r, rgb.detach(), atol=1e-6)


def test_opaque_rays_stop_early_and_lose_less_than_the_bound():
    model = _model(density_bias=6.0)  # density ~ e^6 per unit: opaque within a few samples
    rays = _rays(model)
    full = model.render_rays(rays, model.sampler())
    runner = field_runner(model, "float32")
    evaluated = []
    geometry = runner.geometry
    runner.geometry = lambda x: (evaluated.append(len(x)), geometry(x))[1]
    settings = FastSettings(min_transmittance=1e-4, min_weight=1e-4, skip_empty=False, precision="float32")
    fast = render_rays_fast(model, rays, model.sampler(), settings)
    samples = len(rays) * model.config.sampling.samples_per_ray
    assert sum(evaluated) < 0.5 * samples  # most samples lie behind the first opaque ones
    bound = settings.min_transmittance + model.config.sampling.samples_per_ray * settings.min_weight
    assert (fast["rgb"] - full["rgb"].detach()).abs().max() <= bound + 1e-6


def test_samples_below_the_weight_bound_get_no_colour_and_cost_at_most_the_bound():
    model = _model(density_bias=-6.0)  # nearly transparent: every weight is tiny
    rays = _rays(model)
    full = model.render_rays(rays, model.sampler())
    settings = FastSettings(min_transmittance=1e-30, min_weight=1e-2, skip_empty=False, precision="float32")
    fast = render_rays_fast(model, rays, model.sampler(), settings)
    bound = model.config.sampling.samples_per_ray * settings.min_weight
    assert (fast["rgb"] - full["rgb"].detach()).abs().max() <= bound
    assert torch.allclose(fast["opacity"], full["opacity"].detach(), atol=1e-6)  # weights are all counted


def test_empty_cells_of_the_occupancy_grid_are_skipped():
    model = _model("occgrid")
    model.grid.occupied.zero_()  # nothing occupied: no sample is evaluated, every ray shows the background
    rays = _rays(model)
    out = render_rays_fast(model, rays, model.sampler(), FastSettings(skip_empty=True, precision="float32"))
    assert torch.equal(out["opacity"], torch.zeros(len(rays)))
    assert torch.allclose(out["rgb"], model.background.expand(len(rays), 3))
    assert torch.equal(out["depth"], rays.far)


@pytest.mark.parametrize("bias", [60.0, float("inf"), float("nan")])
def test_stiff_and_broken_densities_stay_finite(bias):
    model = _model(density_bias=0.0)
    with torch.no_grad():
        model.field.density_mlp[-1].bias[0] = bias
    out = render_rays_fast(model, _rays(model), model.sampler(), FastSettings(precision="float32"))
    for name, value in out.items():
        assert torch.isfinite(value).all(), name
    assert (out["opacity"] <= 1.0).all() and (out["opacity"] >= 0.0).all()


def test_bfloat16_runs_the_mlps_in_bfloat16_and_stays_close():
    model = _model()
    rays = _rays(model)
    full = model.render_rays(rays, model.sampler())
    settings = FastSettings(min_transmittance=1e-30, min_weight=0.0, skip_empty=False, precision="bfloat16")
    fast = render_rays_fast(model, rays, model.sampler(), settings)
    assert field_runner(model, "bfloat16").color_geo_t.dtype == torch.bfloat16
    assert (fast["rgb"] - full["rgb"].detach()).abs().max() < 3e-2


def test_auto_precision_is_bfloat16_only_where_the_device_has_it():
    model = _model()
    expected = torch.bfloat16 if native_bfloat16(torch.device("cpu")) else torch.float32
    assert field_runner(model, "auto").dtype == expected
    with pytest.raises(ValueError, match="precision"):
        field_runner(model, "half")


def test_render_normalized_takes_either_path_and_refuses_others():
    from voxnerf.cameras.rays import Intrinsics

    model = _model()
    intr = Intrinsics(fl_x=10.0, fl_y=10.0, cx=6.0, cy=4.0, width=12, height=8)
    c2w = torch.eye(4)
    fast = render_normalized(model, c2w, intr, path="fast")
    full = render_normalized(model, c2w, intr, path="full")
    assert fast["rgb"].shape == full["rgb"].shape == (8, 12, 3)
    # The default fast settings: differences stay below their bounds (bfloat16 MLPs where native).
    assert (fast["rgb"] - full["rgb"]).abs().max() < 3e-2
    assert (fast["depth"] - full["depth"]).abs().max() < 3e-2 * math.sqrt(3) * 2
    with pytest.raises(RunError, match="render path"):
        render_normalized(model, c2w, intr, path="slow")
    auto = render_normalized(model, c2w, intr)  # on this CPU: the fast path
    assert torch.equal(auto["rgb"], fast["rgb"])


@pytest.mark.parametrize(("device", "path"), [("cpu", "fast"), ("cuda", "full"), ("cuda:1", "full"), ("mps", "full")])
def test_the_auto_render_path_is_fast_on_the_cpu_and_full_on_a_gpu(device, path):
    assert resolved_render_path("auto", torch.device(device)) == path
    assert resolved_render_path("fast", torch.device(device)) == "fast"
    assert resolved_render_path("full", torch.device(device)) == "full"
    with pytest.raises(RunError, match="unknown render path 'slow'"):
        resolved_render_path("slow", torch.device(device))


def test_the_default_settings_ignore_a_grid_seeded_from_the_prior():
    """Training seeds the grid from the prior and the surface-guided sampler never needs it to follow the
    field, which has density elsewhere: the default fast path must not drop those samples."""
    model = _model()
    model.grid.seed_from_points(torch.tensor([[0.5, 0.5, 0.5]]))  # one occupied corner, the rest "empty"
    rays = _rays(model)
    full = model.render_rays(rays, model.sampler())
    fast = render_rays_fast(model, rays, model.sampler())
    assert (fast["rgb"] - full["rgb"].detach()).abs().max() < 3e-2
    assert (fast["opacity"] - full["opacity"].detach()).abs().max() < 3e-2


def test_the_runner_follows_the_weights_when_training_changes_them():
    """Progress evaluations build the runner mid-training; the final one must see the trained weights."""
    model = _model()
    rays = _rays(model)
    before = render_rays_fast(model, rays, model.sampler(), EXACT)
    optimiser = torch.optim.SGD(model.field.parameters(), lr=0.5)
    loss = model.render_rays(rays, model.sampler())["rgb"].sum()
    loss.backward()
    optimiser.step()  # in place, as training's optimiser does
    after = render_rays_fast(model, rays, model.sampler(), EXACT)
    full = model.render_rays(rays, model.sampler())
    assert not torch.allclose(after["rgb"], before["rgb"])
    assert torch.allclose(after["rgb"], full["rgb"].detach(), atol=2e-6)
