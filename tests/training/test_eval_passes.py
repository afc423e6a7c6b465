"""Evaluations during training (voxnerf/training/eval_passes.py), with a stub evaluate_views."""

from __future__ import annotations

import math
from types import SimpleNamespace

import pytest
import torch

from voxnerf.config import TrainConfig
from voxnerf.training import eval_passes
from voxnerf.training.budget import Budget


def _view(i: int, width: int = 4, height: int = 3):
    image = torch.arange(width * height * 3, dtype=torch.uint8).reshape(height, width, 3)
    return SimpleNamespace(name=f"v{i}", rays=width * height, c2w=torch.eye(4), image=image,
                           intrinsics=SimpleNamespace(width=width, height=height))


VIEWS = {"test": [_view(i) for i in range(5)], "extra": [_view(i) for i in range(2)]}


@pytest.fixture
def evaluated(monkeypatch):
    calls = []

    def evaluate_views(model, views, cfg, out_dir=None, lpips=False, should_stop=None, half_image=False):
        calls.append({"views": {k: [v.name for v in vs] for k, vs in views.items()}, "out_dir": out_dir,
                      "lpips": lpips})
        half = {"half": {"psnr": 30.0, "ssim": 0.9, "lpips": None}} if half_image else {}
        return {k: {"psnr": 20.0 + len(vs), "ssim": 0.5, "lpips": None, **half,
                    "views": [{"psnr": 10.0 + i} for i in range(len(vs))]}
                for k, vs in views.items()}

    monkeypatch.setattr(eval_passes, "evaluate_views", evaluate_views)
    return calls


def test_spread_keeps_first_and_last():
    assert eval_passes.spread(list(range(10)), 3) == [0, 4, 9]  # linspace 0, 4.5, 9 rounds half to even
    assert eval_passes.spread([1, 2], 3) == [1, 2]


def test_progress_views_psnr_averages_the_progress_views_of_a_full_evaluation():
    metrics = {"test": {"views": [{"psnr": float(i)} for i in range(5)]}}
    assert eval_passes.progress_views_psnr(metrics, VIEWS, 2) == {"test": pytest.approx((0.0 + 4.0) / 2)}


@pytest.fixture
def rendered(monkeypatch):
    """render_pixels stubbed: each pixel's ground truth plus 0.1 (a PSNR of 20 dB), the pixels asked kept."""
    calls = []

    def render_pixel_sets(model, sets, outputs=("rgb",), path="auto", antialias=None):
        assert antialias is False  # progress evaluations cast centre rays
        calls.append([one.pixels.tolist() for one in sets])  # one pass over every view's pixels
        out = []
        for one in sets:
            truth = next(v.image for vs in VIEWS.values() for v in vs if v.intrinsics is one.intrinsics)
            out.append({"rgb": truth.reshape(-1, 3)[one.pixels].float() / 255.0 + 0.1})
        return out

    monkeypatch.setattr(eval_passes, "render_pixel_sets", render_pixel_sets)
    return calls


def test_a_progress_evaluation_scores_its_rays_over_a_few_views_and_records_psnr(evaluated, rendered):
    history = []
    cfg = TrainConfig(max_iters=1, eval_views=2)
    spent, per_ray = eval_passes.progress_eval(None, VIEWS, cfg, history, Budget(None), 7, math.nan, 20)
    assert evaluated == []  # no whole views: 5 of each of the 4 progress views' 12 pixels
    (sets,) = rendered
    assert [len(p) for p in sets] == [5] * 4
    assert sets[0] == sets[1] == eval_passes.scored_pixels(VIEWS["test"][0], 5).tolist()
    (entry,) = history
    assert entry.to_json_dict().keys() == {"elapsed_s", "wall_s", "iteration", "loss", "psnr", "rays"}
    assert entry.iteration == 7 and entry.loss is None and entry.rays == 20
    assert entry.psnr == {"test": pytest.approx(20.0), "extra": pytest.approx(20.0)}
    assert spent >= 0 and per_ray == pytest.approx(spent / 20, abs=1e-4)


def test_a_progress_evaluation_that_affords_every_pixel_scores_whole_views(evaluated, rendered):
    history = []
    eval_passes.progress_eval(None, VIEWS, TrainConfig(max_iters=1, eval_views=2), history, Budget(None), 7, 0.5, 1000)
    assert rendered == [[list(range(12))] * 4] and history[0].rays == 48


def test_rays_are_shared_out_evenly_and_a_small_view_gives_what_it_cannot_take_to_the_others():
    views = {"a": [_view(0), _view(1)], "b": [_view(2, width=3, height=1)]}
    assert eval_passes.pixels_per_view(views, 20) == [9, 8, 3]
    assert eval_passes.pixels_per_view(views, 2) == [1, 0, 1]
    assert eval_passes.pixels_per_view(views, 100) == [12, 12, 3]


def test_the_scored_pixels_are_fixed_sorted_and_nested():
    view = _view(0, width=40, height=30)
    few, more = eval_passes.scored_pixels(view, 50), eval_passes.scored_pixels(view, 300)
    assert torch.equal(few, eval_passes.scored_pixels(view, 50)) and bool((few[1:] > few[:-1]).all())
    assert set(few.tolist()) <= set(more.tolist()) and len(set(more.tolist())) == 300
    assert torch.equal(eval_passes.scored_pixels(view, 5000), torch.arange(1200))


def test_a_full_evaluation_scores_every_view_with_ssim_and_progress_psnr(evaluated):
    history = []
    eval_passes.progress_eval(None, VIEWS, TrainConfig(max_iters=1, eval_views=2), history, Budget(None), 7, 0.5, None)
    assert evaluated[0]["views"]["test"] == [f"v{i}" for i in range(5)] and evaluated[0]["lpips"]
    entry = history[0].to_json_dict()
    assert entry["full"] and entry["loss"] == 0.5 and entry["ssim"] == {"test": 0.5, "extra": 0.5}
    assert entry["progress_psnr"] == {"test": 12.0, "extra": 10.5}
    assert entry["lpips"] == {"test": None, "extra": None} and entry["half"]["test"]["psnr"] == 30.0


def test_the_final_evaluation_writes_renders_and_records_at_the_given_training_time(evaluated, tmp_path):
    metrics, record = eval_passes.final_eval(None, VIEWS, TrainConfig(max_iters=1, eval_views=2), tmp_path,
                                       Budget(None), 12.34567, 9, math.nan)
    assert evaluated[0]["out_dir"] == tmp_path and set(metrics) == {"test", "extra"}
    data = record.to_json_dict()
    assert data["final"] and data["elapsed_s"] == 12.346 and data["iteration"] == 9 and math.isnan(data["loss"])
    assert data.keys() == {"elapsed_s", "wall_s", "iteration", "loss", "final", "psnr", "progress_psnr"}


def test_view_rays_counts_every_pixel():
    assert eval_passes.view_rays(VIEWS) == 7 * 12


def test_a_warm_up_renders_a_few_pixels_first_and_stays_out_of_the_cost_per_ray(monkeypatch):
    """The process's first evaluation pays for compiling the render (or a GPU's first kernels): that must not
    size the later progress evaluations."""
    import time

    calls = []

    def render_pixels(model, c2w, intrinsics, pixels, outputs=("rgb",), path="auto", antialias=None):
        assert antialias is False
        calls.append(len(pixels))
        time.sleep(0.2)  # the cold render
        return {"rgb": torch.zeros(len(pixels), 3)}

    def render_pixel_sets(model, sets, outputs=("rgb",), path="auto", antialias=None):
        assert antialias is False  # progress evaluations cast centre rays
        calls.append([len(one.pixels) for one in sets])
        return [{"rgb": torch.zeros(len(one.pixels), 3)} for one in sets]

    monkeypatch.setattr(eval_passes, "render_pixels", render_pixels)
    monkeypatch.setattr(eval_passes, "render_pixel_sets", render_pixel_sets)
    big = {"test": [_view(i, width=64, height=48) for i in range(3)]}
    history = []
    cfg = TrainConfig(max_iters=1, eval_views=2)
    spent, per_ray = eval_passes.progress_eval(None, big, cfg, history, Budget(None), 7, 0.1, 4000, warm_up=True)
    assert calls == [eval_passes.WARM_UP_RAYS, [2000, 2000]]
    assert len(history) == 1 and spent >= 0.2
    assert per_ray * 4000 < 0.1  # the timed pixels alone


def test_only_the_first_progress_evaluation_of_a_process_warms_up():
    from voxnerf.training.run import _progress_evaluator

    seen = []
    evaluate = _progress_evaluator(lambda it, loss, full, warm_up: seen.append((it, warm_up)) or (1.0, 1e-3))
    assert evaluate(1, 0.5, 4096) == (1.0, 1e-3)
    evaluate(50, 0.4, None)
    evaluate(90, 0.3, 4096)
    assert seen == [(1, True), (50, False), (90, False)]
