"""voxnerf.training.stages.colour_prior: the training pixels pooled at their depth targets where renders look it up,
and why it does not run otherwise; a real micro run keeps it in its checkpoint and renders over it."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from synthetic_fixtures import make_micro_scene, micro_config

from voxnerf.files import REPORT
from voxnerf.inference.render import load_model, render
from voxnerf.training.checkpoint import load_checkpoint
from voxnerf.training.pixels import TrainingPixels
from voxnerf.training.run import train
from voxnerf.training.stages.colour_prior import colour_prior_stage


def _pixels(depth_t: torch.Tensor | None) -> TrainingPixels:
    c2w = torch.eye(4)[None]
    return TrainingPixels(torch.zeros(1, 2, 2, 3, dtype=torch.uint8), c2w, torch.tensor([[2.0, 2.0, 1.0, 1.0]]),
                          depth_t=depth_t)


@pytest.mark.parametrize(("overrides", "has_octree", "depth", "why"), [
    ({"render_background": "colour"}, True, True, "render_background 'colour': rendered rays show the background"),
    ({"render_background": "nearest_seen", "sampler": "occgrid"}, True, True,
     "the run samples without the prior's octree (sampler occgrid)"),
    ({"render_background": "nearest_seen", "sampler": "voxnerf"}, False, True,
     "the run samples without the prior's octree (sampler voxnerf)"),
    ({"render_background": "nearest_seen", "sampler": "voxnerf"}, True, False, "no depth target"),
])
def test_the_stage_says_why_it_did_not_run(overrides, has_octree, depth, why):
    pixels = _pixels(torch.full((1, 2, 2), 0.5) if depth else None)
    stage = colour_prior_stage(micro_config(**overrides), has_octree, pixels)
    assert stage.prior is None and not stage.record.ran and stage.record.why.startswith(why)


def test_pixels_without_a_depth_target_are_left_out_and_none_at_all_is_said():
    cfg = micro_config(render_background="nearest_seen", sampler="voxnerf")
    depth = torch.tensor([[[0.5, float("nan")], [float("nan"), 0.25]]])
    stage = colour_prior_stage(cfg, True, _pixels(depth))
    assert stage.record.ran and stage.prior.pixels == 2 and "2 training pixels (50.0%)" in stage.record.why
    none = colour_prior_stage(cfg, True, _pixels(torch.full((1, 2, 2), float("nan"))))
    assert not none.record.ran and none.record.why == "no training pixel has a depth target"


def test_a_pixel_is_pooled_where_its_ray_reaches_its_depth_target():
    depth = torch.tensor([[[0.5, float("nan")], [float("nan"), float("nan")]]])
    pixels = _pixels(depth)
    pixels.images[0, 0, 0] = torch.tensor([255, 0, 0], dtype=torch.uint8)
    prior = colour_prior_stage(micro_config(render_background="nearest_seen", sampler="voxnerf"), True, pixels).prior
    origins, dirs = pixels.rays(torch.tensor([0]), torch.tensor([0]), torch.tensor([0]))
    colour, found = prior.lookup(origins + 0.5 * dirs)
    assert found.all() and colour.tolist() == [[1.0, 0.0, 0.0]]


def test_images_held_channel_by_channel_are_pooled_as_they_are_read():
    # A downscaled import's images can come channel-planar (not contiguous as [N, H, W, 3]).
    depth = torch.full((1, 2, 2), 0.5)
    planar = _pixels(depth)
    planar.images = torch.arange(12, dtype=torch.uint8).view(1, 3, 2, 2).permute(0, 2, 3, 1) * 20
    assert not planar.images.is_contiguous()
    cfg = micro_config(render_background="nearest_seen", sampler="voxnerf")
    prior = colour_prior_stage(cfg, True, planar).prior
    origins, dirs = planar.rays(torch.tensor([0]), torch.tensor([1]), torch.tensor([0]))
    colour, found = prior.lookup(origins + 0.5 * dirs)
    assert found.all()
    torch.testing.assert_close(colour, planar.images[0, 1, 0][None].float() / 255.0)


def test_a_run_rendering_over_the_colour_seen_keeps_it_and_renders_with_it(tmp_path_factory, tmp_path):
    room = make_micro_scene(tmp_path_factory, "colour-prior")
    run = tmp_path / "run"
    train(room, run, micro_config(max_iters=2, final_eval=False, render_background="nearest_seen"),
          progress_bar=False)
    report = json.loads((run / REPORT).read_text())
    stage = next(s for s in report["stages"] if s["name"] == "colour_prior")
    assert stage["ran"] and "training pixels (100.0%) at their depth targets" in stage["why"]
    state = load_checkpoint(run / "checkpoint.pt")
    assert state["model"]["colour_prior"]["pixels"] > 1000
    trained = load_model(run, "cpu")
    assert trained.model.colour_prior is not None
    frame = json.loads((room / "transforms.json").read_text())["frames"][1]
    seen = render(trained, np.array(frame["transform_matrix"]), outputs=("rgb",))["rgb"]
    trained.model.config = trained.model.config.updated(render_background="colour")
    plain = render(trained, np.array(frame["transform_matrix"]), outputs=("rgb",))["rgb"]
    assert np.isfinite(seen).all() and np.abs(seen - plain).max() > 1e-3  # a two-step field: mostly background


def test_a_run_rendering_over_the_background_colour_keeps_no_colour_prior(tmp_path_factory, tmp_path):
    room = make_micro_scene(tmp_path_factory, "colour-prior-off")
    train(room, tmp_path / "run", micro_config(max_iters=1, final_eval=False, render_background="colour"),
          progress_bar=False)
    assert load_checkpoint(tmp_path / "run" / "checkpoint.pt")["model"]["colour_prior"] is None
