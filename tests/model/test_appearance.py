"""Per-image appearance (voxnerf/model/appearance.py), the half-image evaluation protocol
(voxnerf/inference/metrics.py) and the
training-config knobs that reach the trainer only through ``voxnerf train --set``."""

from __future__ import annotations

import json
import math

import pytest
import torch
from synthetic_fixtures import make_micro_scene, micro_config
from tiny_run import tiny_model

from voxnerf.cameras.rays import Intrinsics
from voxnerf.cli import main
from voxnerf.inference.metrics import fit_colour_affine, half_image_pairs, psnr
from voxnerf.inference.render import render_normalized
from voxnerf.model.appearance import ImageAppearance
from voxnerf.model.voxnerf_model import VoxNeRFModel
from voxnerf.training.run import train


def test_appearance_starts_as_the_identity_and_applies_each_rays_image():
    appearance = ImageAppearance(3)
    rgb = torch.rand(6, 3)
    image = torch.tensor([0, 1, 2, 0, 1, 2])
    torch.testing.assert_close(appearance(rgb, image), rgb)
    with torch.no_grad():  # image 1 twice as bright as image 0, image 2 0.3 brighter: 0 is the darkest
        appearance.log_gain[1] = torch.log(torch.tensor(2.0))
        appearance.bias[2] = 0.3
    out = appearance(rgb, image)
    gain0 = 2.0 ** (-1 / 3)  # the log-gains' mean, log(2) / 3, is taken out; so is the biases', 0.1
    torch.testing.assert_close(out[[0, 3]], gain0 * rgb[[0, 3]] - 0.1)
    torch.testing.assert_close(out[[1, 4]], 2 * gain0 * rgb[[1, 4]] - 0.1)
    torch.testing.assert_close(out[[2, 5]], gain0 * rgb[[2, 5]] + 0.2)
    assert appearance.summary() == {"images": 3, "gain": [pytest.approx(gain0), pytest.approx(2 * gain0)],
                                    "bias": [pytest.approx(-0.1), pytest.approx(0.2)]}


def test_appearance_corrections_keep_zero_mean_so_one_image_gets_none():
    appearance = ImageAppearance(4)
    with torch.no_grad():
        appearance.log_gain.normal_()
        appearance.bias.normal_()
    log_gain, bias = appearance.corrections()
    torch.testing.assert_close(log_gain.mean(0), torch.zeros(3), atol=1e-6, rtol=0)
    torch.testing.assert_close(bias.mean(0), torch.zeros(3), atol=1e-6, rtol=0)
    single = ImageAppearance(1)
    with torch.no_grad():
        single.log_gain.fill_(0.5)
        single.bias.fill_(0.2)
    rgb = torch.rand(5, 3)
    torch.testing.assert_close(single(rgb, torch.zeros(5, dtype=torch.int64)), rgb)


def test_appearance_needs_an_image():
    with pytest.raises(ValueError, match="at least one image"):
        ImageAppearance(0)


def test_a_model_with_appearance_round_trips_and_one_without_loads_as_before():
    model = tiny_model(appearance="affine")
    model.appearance = ImageAppearance(4)
    with torch.no_grad():
        model.appearance.bias.fill_(0.25)
    loaded = VoxNeRFModel.from_state_dict(model.state_dict(), torch.device("cpu"))
    torch.testing.assert_close(loaded.appearance.bias, model.appearance.bias)
    state = model.state_dict()
    del state["appearance"]  # a checkpoint written before appearance existed
    assert VoxNeRFModel.from_state_dict(state, torch.device("cpu")).appearance is None


def test_the_colour_affine_is_recovered_and_a_flat_channel_gets_gain_one():
    pred = torch.rand(20, 30, 3, generator=torch.Generator().manual_seed(0))
    gt = pred * torch.tensor([0.8, 1.1, 1.0]) + torch.tensor([0.05, -0.02, 0.0])
    gain, bias = fit_colour_affine(pred, gt)
    torch.testing.assert_close(gain, torch.tensor([0.8, 1.1, 1.0]), atol=1e-5, rtol=0)
    torch.testing.assert_close(bias, torch.tensor([0.05, -0.02, 0.0]), atol=1e-5, rtol=0)
    flat = torch.full((4, 4, 3), 0.5)
    gain, bias = fit_colour_affine(flat, flat + 0.1)
    torch.testing.assert_close(gain, torch.ones(3))
    torch.testing.assert_close(bias, torch.full((3,), 0.1), atol=1e-6, rtol=0)


def test_half_image_scores_the_right_half_after_the_left_halfs_fit():
    g = torch.Generator().manual_seed(1)
    gt = torch.rand(16, 20, 3, generator=g) * 0.6 + 0.2
    darker = (gt - 0.05) / 1.25  # the same image at another exposure
    pred, target = half_image_pairs(darker, gt)
    assert pred.shape == target.shape == (16, 10, 3)
    torch.testing.assert_close(target, gt[:, 10:].double())
    assert psnr(pred, target) > 60 > psnr(darker[:, 10:], gt[:, 10:])
    odd, _ = half_image_pairs(torch.rand(5, 7, 3), torch.rand(5, 7, 3))
    assert odd.shape == (5, 4, 3) and bool(((odd >= 0) & (odd <= 1)).all())


def test_half_image_pairs_refuse_nan():
    bad = torch.full((4, 4, 3), float("nan"))
    with pytest.raises(ValueError):
        half_image_pairs(bad, torch.zeros(4, 4, 3))


@pytest.mark.parametrize(("setting", "message"), [
    ("sh_bands=9", "sh_bands: Input should be less than or equal to 4"),
    ("no_such_field=1", "no_such_field: Extra inputs are not permitted"),
    ("lr_schedule=weekly", "lr_schedule: Input should be 'iterations' or 'budget'"),
    ("field_weight_decay=-1",
     "field_weight_decay: Input should be greater than or equal to 0, or input should be 'auto'"),
    ("field_weight_decay=often",
     "field_weight_decay: Input should be a valid number, unable to parse string as a number, or input should be "
     "'auto'"),
])
def test_voxnerf_train_set_refuses_bad_fields_in_one_line_before_training(tmp_path, capsys, setting, message):
    code = main(["train", str(tmp_path / "scene"), "--out", str(tmp_path / "run"), "--max-iters", "1",
                 "--set", setting])
    err = capsys.readouterr().err
    assert code == 2 and err.strip() == f"voxnerf: error: {message}" and not (tmp_path / "run").exists()


def test_voxnerf_train_set_needs_field_equals_value(tmp_path, capsys):
    with pytest.raises(SystemExit) as exc:
        main(["train", str(tmp_path), "--out", str(tmp_path / "run"), "--set", "sh_bands"])
    assert exc.value.code == 2 and "expected FIELD=VALUE" in capsys.readouterr().err


def test_voxnerf_train_set_wins_over_a_flag_of_the_same_field(tmp_path, capsys):
    """--set sampler=... beside the --sampler flag's default: the --set value is the one checked (and refused)."""
    code = main(["train", str(tmp_path / "scene"), "--out", str(tmp_path / "run"), "--max-iters", "1",
                 "--sampler", "voxnerf", "--set", "sampler=\"warp\"", "--set", "depth_loss=false"])
    assert code == 2 and "sampler: Input should be 'auto', 'voxnerf', 'occgrid' or 'uniform'" in capsys.readouterr().err


def _cameras() -> torch.Tensor:
    cameras = torch.eye(4).repeat(3, 1, 1)
    cameras[:, 0, 3] = torch.tensor([0.0, 0.2, 0.4])
    return cameras


def test_a_view_takes_its_nearest_training_cameras_colour_correction():
    appearance = ImageAppearance(3, _cameras())
    with torch.no_grad():  # zero-mean corrections: applied as they are
        appearance.log_gain[:, 0] = torch.tensor([0.2, 0.0, -0.2])
        appearance.bias[:, 1] = torch.tensor([-0.1, 0.0, 0.1])
    rgb = torch.full((2, 2, 3), 0.5)
    own = appearance.view_colour(rgb, _cameras()[0])
    torch.testing.assert_close(own[..., 0], torch.full((2, 2), 0.5 * math.exp(0.2)), atol=1e-4, rtol=0)
    torch.testing.assert_close(own[..., 1], torch.full((2, 2), 0.4), atol=1e-4, rtol=0)
    between = _cameras()[0].clone()
    between[0, 3] = 0.3  # halfway between cameras 1 and 2, camera 0 three times as far
    w = torch.tensor([1 / 0.3, 1 / 0.1, 1 / 0.1])
    w = w / w.sum()
    out = appearance.view_colour(rgb, between)
    torch.testing.assert_close(out[0, 0, 0], 0.5 * torch.exp((w * torch.tensor([0.2, 0.0, -0.2])).sum()))
    torch.testing.assert_close(out[0, 0, 1], 0.5 + (w * torch.tensor([-0.1, 0.0, 0.1])).sum())
    without = ImageAppearance(3)  # no cameras kept: every view takes the mean correction, none
    without.load_state_dict({k: v for k, v in appearance.state_dict().items() if k != "cameras"}, strict=False)
    torch.testing.assert_close(without.view_colour(rgb, between), rgb)
    with pytest.raises(ValueError, match=r"cameras must be \[2, 4, 4\]"):
        ImageAppearance(2, _cameras())


def test_a_render_is_corrected_and_an_old_checkpoint_without_cameras_loads():
    model = tiny_model(sampler="uniform")
    intr = Intrinsics(fl_x=4.0, fl_y=4.0, cx=2.0, cy=2.0, width=4, height=4)
    plain = render_normalized(model, _cameras()[1], intr, ("rgb",))["rgb"]
    model.appearance = ImageAppearance(3, _cameras())
    with torch.no_grad():
        model.appearance.bias[:, 2] = torch.tensor([-0.05, 0.1, -0.05])
    corrected = render_normalized(model, _cameras()[1], intr, ("rgb",))["rgb"]
    torch.testing.assert_close(corrected[..., :2], plain[..., :2])
    assert float((corrected[..., 2] - plain[..., 2]).mean()) > 0.05  # camera 1's blue bias, nearly all of it
    state = model.state_dict()
    del state["appearance"]["cameras"]
    loaded = VoxNeRFModel.from_state_dict(state, torch.device("cpu"))
    torch.testing.assert_close(loaded.appearance.cameras, torch.eye(4).repeat(3, 1, 1))


def test_a_run_with_appearance_and_pose_refinement_says_how_its_views_were_corrected(tmp_path_factory, tmp_path):
    room = make_micro_scene(tmp_path_factory, "appearance-run")
    cfg = micro_config(max_iters=6, appearance="affine", pose_refinement="so3xr3")
    train(room, tmp_path / "run", cfg, progress_bar=False)
    report = json.loads((tmp_path / "run" / "report.json").read_text())
    assert report["appearance"]["images"] == 10 and report["pose_refinement"]["images"] == 10
    assert report["metrics"]
    for split in report["metrics"].values():
        assert split["colours"] == "corrected as the nearest training cameras' images were"
        assert split["poses"].startswith("given, moved by")
    plain = train(room, tmp_path / "plain", micro_config(max_iters=2), progress_bar=False)
    assert all("colours" not in s and "poses" not in s for s in plain.metrics.values())
