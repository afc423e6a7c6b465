"""Evaluations during training (voxnerf/training/eval_passes.py), with a stub evaluate_views."""

from __future__ import annotations

import math
from types import SimpleNamespace

import pytest

from voxnerf.config import TrainConfig
from voxnerf.training import evals
from voxnerf.training.budget import Budget


def _view(i: int, width: int = 4, height: int = 3):
    return SimpleNamespace(name=f"v{i}", rays=width * height)


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

    monkeypatch.setattr(evals, "evaluate_views", evaluate_views)
    return calls


def test_spread_keeps_first_and_last():
    assert evals.spread(list(range(10)), 3) == [0, 4, 9]  # linspace 0, 4.5, 9 rounds half to even
    assert evals.spread([1, 2], 3) == [1, 2]


def test_progress_views_psnr_averages_the_progress_views_of_a_full_evaluation():
    metrics = {"test": {"views": [{"psnr": float(i)} for i in range(5)]}}
    assert evals.progress_views_psnr(metrics, VIEWS, 2) == {"test": pytest.approx((0.0 + 4.0) / 2)}


def test_a_progress_evaluation_scores_a_few_views_and_records_psnr(evaluated):
    history = []
    cfg = TrainConfig(max_iters=1, eval_views=2)
    spent, per_ray = evals.progress_eval(None, VIEWS, cfg, history, Budget(None), 7, math.nan, False)
    assert evaluated == [{"views": {"test": ["v0", "v4"], "extra": ["v0", "v1"]}, "out_dir": None, "lpips": False}]
    (entry,) = history
    assert entry.to_json_dict().keys() == {"elapsed_s", "wall_s", "iteration", "loss", "psnr"}
    assert entry.iteration == 7 and entry.loss is None and entry.psnr == {"test": 22.0, "extra": 22.0}
    assert spent >= 0 and per_ray == pytest.approx(spent / (4 * 12), abs=1e-4)


def test_a_full_evaluation_scores_every_view_with_ssim_and_progress_psnr(evaluated):
    history = []
    evals.progress_eval(None, VIEWS, TrainConfig(max_iters=1, eval_views=2), history, Budget(None), 7, 0.5, True)
    assert evaluated[0]["views"]["test"] == [f"v{i}" for i in range(5)] and evaluated[0]["lpips"]
    entry = history[0].to_json_dict()
    assert entry["full"] and entry["loss"] == 0.5 and entry["ssim"] == {"test": 0.5, "extra": 0.5}
    assert entry["progress_psnr"] == {"test": 12.0, "extra": 10.5}
    assert entry["lpips"] == {"test": None, "extra": None} and entry["half"]["test"]["psnr"] == 30.0


def test_the_final_evaluation_writes_renders_and_records_at_the_given_training_time(evaluated, tmp_path):
    metrics, record = evals.final_eval(None, VIEWS, TrainConfig(max_iters=1, eval_views=2), tmp_path,
                                       Budget(None), 12.34567, 9, math.nan)
    assert evaluated[0]["out_dir"] == tmp_path and set(metrics) == {"test", "extra"}
    data = record.to_json_dict()
    assert data["final"] and data["elapsed_s"] == 12.346 and data["iteration"] == 9 and math.isnan(data["loss"])
    assert data.keys() == {"elapsed_s", "wall_s", "iteration", "loss", "final", "psnr", "progress_psnr"}


def test_view_rays_counts_every_pixel():
    assert evals.view_rays(VIEWS) == 7 * 12


def test_a_warm_up_renders_one_view_first_and_stays_out_of_the_cost_per_ray(monkeypatch):
    """The process's first evaluation pays for compiling the render (or a GPU's first kernels): that must not
    size the final evaluation's reserve."""
    import time

    calls = []

    def evaluate_views(model, views, cfg, out_dir=None, lpips=False, should_stop=None, half_image=False):
        names = {k: [v.name for v in vs] for k, vs in views.items()}
        calls.append(names)
        if len(calls) == 1:
            time.sleep(0.2)  # the cold render
        return {k: {"psnr": 20.0, "ssim": 0.5, "lpips": None, "views": []} for k in views}

    monkeypatch.setattr(evals, "evaluate_views", evaluate_views)
    history = []
    cfg = TrainConfig(max_iters=1, eval_views=2)
    spent, per_ray = evals.progress_eval(None, VIEWS, cfg, history, Budget(None), 7, 0.1, False, warm_up=True)
    assert calls == [{"test": ["v0"]}, {"test": ["v0", "v4"], "extra": ["v0", "v1"]}]
    assert len(history) == 1 and spent >= 0.2
    assert per_ray * 4 * 12 < 0.1  # the timed views alone


def test_only_the_first_progress_evaluation_of_a_process_warms_up():
    from voxnerf.training.run import _progress_evaluator

    seen = []
    evaluate = _progress_evaluator(lambda it, loss, full, warm_up: seen.append((it, warm_up)) or (1.0, 1e-3))
    assert evaluate(1, 0.5, False) == (1.0, 1e-3)
    evaluate(50, 0.4, True)
    evaluate(90, 0.3, False)
    assert seen == [(1, True), (50, False), (90, False)]
