"""The field's weight average (voxnerf/training/weight_average.py): the update rule, the swaps, the checkpoint it
writes, a resumed run and a trained run whose renders are the average."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch
from pydantic import ValidationError
from synthetic_fixtures import make_micro_scene, micro_config
from torch import nn

from voxnerf.config import TrainConfig
from voxnerf.data.scene import load_scene
from voxnerf.files import CHECKPOINT
from voxnerf.inference.evaluation import evaluate_views
from voxnerf.inference.render import load_model, scene_as_trained
from voxnerf.training import stages
from voxnerf.training.checkpoint import load_checkpoint
from voxnerf.training.eval_passes import eval_views_of
from voxnerf.training.loop import LoopState
from voxnerf.training.run import train
from voxnerf.training.weight_average import WEIGHT_AVERAGE_EVERY, WeightAverage


def _field() -> nn.Module:
    torch.manual_seed(0)
    field = nn.Sequential(nn.Linear(3, 4), nn.BatchNorm1d(4))  # parameters and buffers
    return field


def _step(field: nn.Module, iteration: int) -> None:
    """A stand-in optimiser step: every parameter moves by the iteration's number."""
    with torch.no_grad():
        for p in field.parameters():
            p.add_(float(iteration))


def test_the_average_moves_every_few_steps_by_its_rate() -> None:
    field = _field()
    start = [p.detach().clone() for p in field.parameters()]
    average = WeightAverage(field, decay=0.9, every=2)
    expected = [s.clone() for s in start]
    for iteration in range(1, 7):
        _step(field, iteration)
        average.after_step(LoopState(iteration))
        if iteration % 2 == 0:
            rate = max(1 - 0.9**2, 9 / (10 + iteration // 2))
            expected = [e + rate * (p.detach() - e) for e, p in zip(expected, field.parameters(), strict=True)]
    state = average.field_state()
    for (name, live), want in zip(field.named_parameters(), expected, strict=True):
        assert torch.allclose(state[name], want, atol=1e-6)
        assert not torch.allclose(state[name], live)  # the live parameters are left alone
    assert state.keys() == field.state_dict().keys()  # buffers come along as they are
    assert WEIGHT_AVERAGE_EVERY == 4 and WeightAverage(field, 0.99).every == WEIGHT_AVERAGE_EVERY


def test_the_rate_falls_from_the_warm_up_to_the_decay_s_and_stays() -> None:
    average = WeightAverage(_field(), decay=0.995)
    base = 1 - 0.995**WEIGHT_AVERAGE_EVERY
    rates = [average.rate_at(n) for n in (1, 10, 100, 443, 444, 10_000)]
    assert rates[0] == pytest.approx(9 / 11) and rates[2] == pytest.approx(9 / 110)
    assert rates == sorted(rates, reverse=True) and rates[-3] > base and rates[-2:] == [base, base]


def test_a_short_run_s_average_is_not_held_back_by_the_start() -> None:
    """Without the warm-up, 300 steps at decay 0.995 would leave 0.995**300 = 22 % of the random start in the
    average; with it, the start is gone and the average sits among the last steps' parameters."""
    field = _field()
    start = [p.detach().clone() for p in field.parameters()]
    average = WeightAverage(field, decay=0.995)
    for iteration in range(1, 301):
        _step(field, 1)  # every parameter moves by 1 a step: 300 in all
        average.after_step(LoopState(iteration))
    state = average.field_state()
    for (name, _), first in zip(field.named_parameters(), start, strict=True):
        moved = (state[name] - first).mean().item()
        assert 260 < moved < 300, moved  # the last tenth of the run, not 300 * (1 - 0.22) and less


def test_applied_puts_the_average_in_and_the_live_parameters_back_even_after_an_error() -> None:
    field = _field()
    average = WeightAverage(field, decay=0.5, every=1)
    _step(field, 3)
    average.update()
    live = [p.detach().clone() for p in field.parameters()]
    averaged = [v.clone() for k, v in average.field_state().items() if k in dict(field.named_parameters())]
    with pytest.raises(RuntimeError), average.applied():
        assert all(torch.equal(p, a) for p, a in zip(field.parameters(), averaged, strict=True))
        raise RuntimeError("a render failed")
    assert all(torch.equal(p, v) for p, v in zip(field.parameters(), live, strict=True))
    average.apply()
    assert all(torch.equal(p, a) for p, a in zip(field.parameters(), averaged, strict=True))


def test_an_average_starts_from_a_resumed_runs_average() -> None:
    field = _field()
    start = {k: v + 1.0 if v.is_floating_point() else v for k, v in field.state_dict().items()}
    state = WeightAverage(field, decay=0.9, start=start).field_state()
    assert all(torch.equal(state[k], start[k]) for k, _ in field.named_parameters())


@pytest.mark.parametrize("decay", [0.0, 1.0, -0.1, float("nan")])
def test_a_decay_outside_zero_to_one_is_refused(decay: float) -> None:
    with pytest.raises(ValueError, match="decay per step"):
        WeightAverage(_field(), decay)


@pytest.mark.parametrize("value", [1.0, -0.5])
def test_the_setting_lies_in_zero_to_one(value: float) -> None:
    with pytest.raises(ValidationError, match="weight_average"):
        TrainConfig(weight_average=value)
    assert TrainConfig().schedule.weight_average == 0.995  # on by default: issue #46's 300 s verdict
    assert WeightAverage.of(_field(), 0.0) is None


@pytest.fixture(scope="module")
def tiny_room(tmp_path_factory) -> Path:
    return make_micro_scene(tmp_path_factory, "weight-average")


def test_a_run_renders_and_scores_its_average_and_resumes_from_both(tiny_room: Path, tmp_path: Path) -> None:
    config = micro_config(max_iters=4, weight_average=0.8, lr=0.05)
    report = train(tiny_room, tmp_path, config, progress_bar=False)
    saved = load_checkpoint(tmp_path / CHECKPOINT)
    field, live = saved["model"]["field"], saved["field_live"]
    assert field.keys() == live.keys()
    assert any(not torch.equal(field[k], live[k]) for k in field)  # the model renders is the average

    trained = load_model(tmp_path, "cpu")  # what `voxnerf eval`, renders and the viewer load
    scene = scene_as_trained(load_scene(tiny_room, downscale=1), trained.model)
    split = next(iter(report.metrics))
    again = evaluate_views(trained.model, {split: eval_views_of(scene, trained.model.transform, [split])[split]},
                           trained.model.config, lpips=False)[split]
    assert again["psnr"] == pytest.approx(report.metrics[split]["psnr"], abs=1e-4)

    resolved = config.updated(field_weight_decay=0.0, appearance="none", pose_refinement="none")
    built = stages.model_stage(resolved, scene, None, torch.device("cpu"), saved)
    assert built.averaged_field is not None
    assert all(torch.equal(built.averaged_field[k], field[k]) for k in field)
    assert all(torch.equal(v, live[k]) for k, v in built.model.field.state_dict().items())  # training goes on live
    resumed = train(tiny_room, tmp_path, micro_config(max_iters=6, weight_average=0.8, lr=0.05), progress_bar=False)
    assert resumed.resumed_from_iteration == 4 and resumed.iteration == 6

