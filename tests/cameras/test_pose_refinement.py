"""Camera pose refinement (voxnerf/cameras/pose_refinement.py): the exponential map, the per-image correction of rays,
its wiring into the loss (image rays only), recovery of a known pose error, and a training run that keeps it."""

from __future__ import annotations

import json
import math
from types import SimpleNamespace

import numpy as np
import pytest
import torch
from synthetic_fixtures import make_micro_scene, micro_config
from tiny_run import tiny_model

from voxnerf.cameras.pose_refinement import PoseRefinement, refined_frames, so3_exp
from voxnerf.cameras.rays import Intrinsics, camera_rays, image_rays
from voxnerf.config import TrainConfig
from voxnerf.data.scene import SceneTransform, load_scene
from voxnerf.inference import render as render_module
from voxnerf.inference.render import render_normalized
from voxnerf.model import hash_kernel
from voxnerf.model.voxnerf_model import Batch, VoxNeRFModel
from voxnerf.training.checkpoint import load_checkpoint
from voxnerf.training.run import train
from voxnerf.training.step import make_loss_fn


def _skew(w: torch.Tensor) -> torch.Tensor:
    x, y, z = w.tolist()
    return torch.tensor([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]], dtype=w.dtype)


@pytest.mark.parametrize("angle", [0.0, 1e-6, 1e-3, 0.3, 2.5])
def test_so3_exp_is_the_matrix_exponential_and_a_rotation(angle):
    axis = torch.nn.functional.normalize(torch.tensor([0.3, -0.5, 0.8], dtype=torch.float64), dim=0)
    w = axis * angle
    r = so3_exp(w[None])[0]
    torch.testing.assert_close(r, torch.linalg.matrix_exp(_skew(w)), atol=1e-12, rtol=0)
    torch.testing.assert_close(r @ r.T, torch.eye(3, dtype=torch.float64), atol=1e-12, rtol=0)


def test_so3_exp_has_a_finite_gradient_at_and_near_zero():
    for scale in (0.0, 1e-9, 1e-5):
        w = (torch.tensor([[1.0, 2.0, -1.0]]) * scale).requires_grad_(True)
        (so3_exp(w) * torch.arange(9.0).view(1, 3, 3)).sum().backward()
        assert bool(torch.isfinite(w.grad).all()) and float(w.grad.abs().sum()) > 0


def test_the_correction_starts_as_the_identity_and_applies_each_rays_image():
    poses = PoseRefinement(3)
    origins = torch.rand(6, 3)
    dirs = torch.nn.functional.normalize(torch.randn(6, 3), dim=-1)
    image = torch.tensor([0, 1, 2, 0, 1, 2])
    o, d = poses(origins, dirs, image)
    assert torch.equal(o, origins) and torch.allclose(d, dirs)
    with torch.no_grad():  # corrections of zero mean, so applied as they are
        poses.delta[0, :3] = torch.tensor([0.0, 0.0, math.pi / 2])  # a quarter turn about +z
        poses.delta[1] = torch.tensor([0.0, 0.0, -math.pi / 2, 0.1, 0.0, -0.2])
        poses.delta[2, 3:] = torch.tensor([-0.1, 0.0, 0.2])
    o, d = poses(origins, dirs, image)
    torch.testing.assert_close(o[[0, 3]], origins[[0, 3]])
    torch.testing.assert_close(o[[1, 4]], origins[[1, 4]] + torch.tensor([0.1, 0.0, -0.2]))
    torch.testing.assert_close(o[[2, 5]], origins[[2, 5]] - torch.tensor([0.1, 0.0, -0.2]))
    turned = torch.stack([-dirs[:, 1], dirs[:, 0], dirs[:, 2]], -1)
    torch.testing.assert_close(d[[0, 3]], turned[[0, 3]], atol=1e-6, rtol=0)
    torch.testing.assert_close(d[[1, 4]], -turned[[1, 4]] * torch.tensor([1.0, 1.0, -1.0]), atol=1e-6, rtol=0)
    torch.testing.assert_close(d[[2, 5]], dirs[[2, 5]])
    torch.testing.assert_close(d.norm(dim=-1), torch.ones(6))


def test_a_correction_shared_by_every_image_is_none():
    """The corrections are held at zero mean: the rig as a whole cannot drift from the evaluation poses."""
    poses = PoseRefinement(3)
    with torch.no_grad():
        poses.delta.copy_(torch.tensor([0.1, -0.2, 0.05, 0.3, 0.0, -0.1]).expand(3, 6))
        poses.delta[2, 3] += 0.6
    torch.testing.assert_close(poses.corrections().mean(0), torch.zeros(6), atol=1e-7, rtol=0)
    torch.testing.assert_close(poses.corrections()[2], torch.tensor([0.0, 0.0, 0.0, 0.4, 0.0, 0.0]))


def test_refined_poses_give_the_corrected_rays():
    poses = PoseRefinement(2)
    with torch.no_grad():
        poses.delta.copy_(torch.tensor([[0.02, -0.01, 0.03, 0.05, 0.0, -0.02], [0.0, 0.1, 0.0, 0.0, 0.01, 0.0]]))
    c2w = torch.eye(4).repeat(2, 1, 1)
    c2w[1, :3, 3] = torch.tensor([0.3, -0.2, 0.1])
    px, py = torch.tensor([0, 5, 9]), torch.tensor([2, 7, 1])
    for i in range(2):
        o, d, _ = camera_rays(c2w[i], 10.0, 10.0, 5.0, 4.0, px, py)
        o_fix, d_fix = poses(o, d, torch.full((3,), i))
        o_ref, d_ref, _ = camera_rays(poses.refined_c2w(c2w)[i], 10.0, 10.0, 5.0, 4.0, px, py)
        torch.testing.assert_close(o_fix, o_ref)
        torch.testing.assert_close(d_fix, d_ref, atol=1e-6, rtol=0)


def test_summary_gives_degrees_and_scene_units_and_an_image_is_needed():
    poses = PoseRefinement(2)
    with torch.no_grad():
        poses.delta[0] = torch.tensor([math.radians(2.0), 0.0, 0.0, 0.0, 0.3, 0.4])
        poses.delta[1] = torch.tensor([math.radians(-1.0), 0.0, 0.0, 0.0, -0.3, -0.4])
    summary = poses.summary(scene_scale=0.5)  # 0.5 normalised units per scene unit
    assert summary["images"] == 2  # corrections as applied: less the mean, 0.5 degrees about x
    assert summary["rotation_deg"] == {"mean": pytest.approx(1.5), "max": pytest.approx(1.5)}
    assert summary["translation"] == {"mean": pytest.approx(1.0), "max": pytest.approx(1.0)}
    with pytest.raises(ValueError, match="at least one image"):
        PoseRefinement(0)


def test_a_model_with_pose_refinement_round_trips_and_one_without_loads_as_before():
    model = tiny_model()
    model.pose_refinement = PoseRefinement(4)
    with torch.no_grad():
        model.pose_refinement.delta.fill_(0.01)
    loaded = VoxNeRFModel.from_state_dict(model.state_dict(), torch.device("cpu"))
    torch.testing.assert_close(loaded.pose_refinement.delta, model.pose_refinement.delta)
    state = model.state_dict()
    del state["pose_refinement"]  # a checkpoint written before pose refinement existed
    assert VoxNeRFModel.from_state_dict(state, torch.device("cpu")).pose_refinement is None


class _PatternModel(VoxNeRFModel):
    """Renders a smooth colour pattern of the point one unit along each ray (so a ray's colour depends on its
    pose), like a field that has learnt a textured wall; ``pose_refinement`` as a real model carries it."""

    def __init__(self, images: int) -> None:
        self.transform = SimpleNamespace(scale=1.0)
        self.appearance = None
        self.pose_refinement = PoseRefinement(images)

    @staticmethod
    def colour(origins, dirs):
        p = origins + dirs
        return torch.sigmoid(torch.stack([torch.sin(3 * p[:, 0]), torch.cos(2 * p[:, 1] + p[:, 2]),
                                          torch.sin(2 * p[:, 2] - p[:, 0])], -1))

    def render_samples(self, origins, dirs, starts, ends, background=None):
        return {"rgb": self.colour(origins, dirs), "depth": starts[:, 0]}


def _rays(n: int, seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    dirs = torch.nn.functional.normalize(torch.randn(n, 3, generator=g) * 0.8 + torch.tensor([0.0, 0.0, -1.0]), dim=-1)
    return torch.zeros(n, 3), dirs


def test_the_loss_recovers_known_pose_errors():
    """The two images' rays were recorded from cameras turned by about 1.5 degrees and moved 2 cm, in opposite
    directions (errors of zero mean, as the corrections are held): minimising the loss finds those turns and
    moves."""
    model = _PatternModel(2)
    cfg = TrainConfig(max_iters=1, lambda_pose=0.0)
    error = torch.tensor([0.01, -0.02, 0.015, 0.02, -0.01, 0.005])
    truth = torch.stack([-error, error])
    origins, dirs = _rays(512, 0)
    image = torch.arange(512) % 2
    with torch.no_grad():  # the pixels' colours are what the true (corrected) poses see
        model.pose_refinement.delta.copy_(truth)
        target = model.colour(*model.pose_refinement(origins, dirs, image))
        model.pose_refinement.delta.zero_()
    loss_fn = make_loss_fn(model, cfg, 0.1, 0, 8)
    starts = torch.rand(512, 4)
    opt = torch.optim.Adam(model.pose_refinement.parameters(), lr=2e-3)
    for _ in range(400):
        total, *_ = loss_fn(Batch(origins, dirs, starts, starts + 0.1, target, None, None, None, image,
                                  torch.tensor(0.0), pose_corrections=model.pose_refinement.corrections()))
        opt.zero_grad()
        total.backward()
        opt.step()
    torch.testing.assert_close(model.pose_refinement.corrections().detach(), truth, atol=1e-3, rtol=0)


def test_prior_rays_are_not_moved_and_the_regulariser_counts():
    model = _PatternModel(2)
    with torch.no_grad():
        model.pose_refinement.delta[0] = torch.tensor([0.1, 0.0, 0.0, 0.2, 0.0, 0.0])
        model.pose_refinement.delta[1] = -model.pose_refinement.delta[0]
    origins, dirs = _rays(8, 1)
    image = torch.zeros(8, dtype=torch.int64)
    starts = torch.rand(8, 4)
    target = torch.rand(8, 3)
    seen = []
    render = model.render_samples
    model.render_samples = lambda o, d, *a, **k: seen.append((o, d)) or render(o, d, *a, **k)
    args = (origins, dirs, starts, starts + 0.1, target, None, None, None, image, torch.tensor(0.0), None, None,
            model.pose_refinement.corrections())
    loss_fn = make_loss_fn(model, TrainConfig(max_iters=1, lambda_pose=0.5), 0.1, 0, 8, n_prior_rays=3)
    total, lc, *_ = loss_fn(Batch(*args))
    o, d = seen[0]
    torch.testing.assert_close(o[5:], origins[5:])  # the 3 prior rays
    torch.testing.assert_close(d[5:], dirs[5:])
    torch.testing.assert_close(o[:5], origins[:5] + torch.tensor([0.2, 0.0, 0.0]))
    assert float((total - lc).detach()) == pytest.approx(0.05 * 0.1 + 0.5 * 0.2)  # mean norms over the 2 images


@pytest.mark.parametrize("compile_step", [False, pytest.param(True, marks=pytest.mark.skipif(
    not hash_kernel.available(), reason="the compiled step runs the C hash kernel's position gradient"))])
def test_a_run_with_pose_refinement_learns_keeps_and_reports_the_corrections(request, tmp_path, compile_step):
    if compile_step:  # the step a captured scan compiles under the default config, as test_service_runtime.py's runs
        request.getfixturevalue("compiled_captured_step")  # the inductor cache holds this step
        room = request.getfixturevalue("captured_small_room")
        cfg = TrainConfig(max_iters=12, final_eval=False, device="cpu", checkpoint_every_s=1e9)
    else:
        room = make_micro_scene(request.getfixturevalue("tmp_path_factory"), "pose-refinement")
        cfg = micro_config(max_iters=12, pose_refinement="so3xr3", pose_lr=1e-3, pose_every=2, final_eval=False)
    report = train(room, tmp_path / "run", cfg, progress_bar=False)
    assert report.status == "succeeded"
    summary = json.loads((tmp_path / "run" / "report.json").read_text())["pose_refinement"]
    scene = load_scene(room, load_images=False)
    images = len(scene.train_indices)
    assert summary["images"] == images and summary["file"] == "refined_poses.json"
    assert 0 < summary["rotation_deg"]["max"] < 5 and 0 < summary["translation"]["max"] < 0.5
    state = load_checkpoint(tmp_path / "run" / "checkpoint.pt")["model"]["pose_refinement"]
    delta = state["delta"]
    assert delta.shape == (images, 6) and bool(torch.isfinite(delta).all()) and float(delta.abs().max()) > 0
    refined = json.loads((tmp_path / "run" / "refined_poses.json").read_text())["frames"]
    given = [scene.frames[i] for i in scene.train_indices]
    assert [f["file_path"] for f in refined] == [f.file_path for f in given]
    for frame, original in zip(refined, given, strict=True):
        m, m0 = np.array(frame["transform_matrix"]), original.c2w
        np.testing.assert_allclose(m[:3, :3] @ m[:3, :3].T, np.eye(3), atol=1e-6)
        assert 0 < np.abs(m - m0).max() < 0.5


def test_refined_frames_are_the_given_poses_moved_by_the_corrections_in_scene_units():
    poses = PoseRefinement(2)
    c2w = np.stack([np.eye(4), np.eye(4)])
    c2w[1, :3, 3] = [2.0, 1.0, -1.0]
    center, scale = np.array([1.0, 0.0, 0.0]), 0.25
    transform = SceneTransform(tuple(center), scale)
    same = refined_frames(poses, ["a.png", "b.png"], c2w, transform)["frames"]
    assert [f["file_path"] for f in same] == ["a.png", "b.png"]
    np.testing.assert_allclose(np.array([f["transform_matrix"] for f in same]), c2w, atol=1e-12)
    with torch.no_grad():
        poses.delta[1] = torch.tensor([0.0, 0.0, math.pi / 2, 0.1, 0.0, 0.0])  # 0.1 normalised = 0.4 scene units
        poses.delta[0] = -poses.delta[1]
    moved = np.array(refined_frames(poses, ["a.png", "b.png"], c2w, transform)["frames"][1]["transform_matrix"])
    np.testing.assert_allclose(moved[:3, 3], [2.4, 1.0, -1.0], atol=1e-6)
    np.testing.assert_allclose(moved[:3, :3], [[0, -1, 0], [1, 0, 0], [0, 0, 1]], atol=1e-6)


def _cameras() -> torch.Tensor:
    """Four training cameras along x, all looking down -z."""
    cameras = torch.eye(4).repeat(4, 1, 1)
    cameras[:, 0, 3] = torch.tensor([0.0, 0.2, 0.4, 0.6])
    return cameras


def test_a_rendered_pose_takes_its_nearest_training_cameras_corrections():
    poses = PoseRefinement(4, _cameras())
    with torch.no_grad():
        poses.delta[:, 3] = torch.tensor([0.03, 0.01, -0.01, -0.03])  # zero mean: applied as they are
        poses.delta[:, 2] = torch.tensor([0.02, -0.02, 0.02, -0.02])
    own = poses.view_corrections(_cameras())
    torch.testing.assert_close(own, poses.corrections().detach(), atol=1e-5, rtol=0)
    between = _cameras()[:1].clone()
    between[0, 0, 3] = 0.1  # halfway between the first two; the other two at 3x and 5x the distance
    weights = torch.tensor([1 / 0.1, 1 / 0.1, 1 / 0.3, 1 / 0.5])
    expected = (weights[:, None] * poses.corrections().detach()).sum(0) / weights.sum()
    torch.testing.assert_close(poses.view_corrections(between)[0], expected, atol=1e-6, rtol=0)
    moved = poses.correct_views(between)[0]
    torch.testing.assert_close(moved[:3, 3], between[0, :3, 3] + expected[3:])
    torch.testing.assert_close(moved[:3, :3], so3_exp(expected[None, :3])[0])


def test_a_view_looking_elsewhere_counts_as_further():
    poses = PoseRefinement(2, _cameras()[:2])
    turned = _cameras()[:1].clone()
    turned[0, 0, 3] = 0.05  # nearer camera 0, but turned a quarter turn away from both
    turned[0, :3, :3] = so3_exp(torch.tensor([[0.0, math.pi / 2, 0.0]]))[0]
    far = turned.clone()
    far[0, 0, 3] = 0.15
    with torch.no_grad():
        poses.delta[:, 3] = torch.tensor([0.01, -0.01])
    a, b = poses.view_corrections(turned)[0, 3], poses.view_corrections(far)[0, 3]
    assert 0 < float(a) < 0.01 and -0.01 < float(b) < 0  # the angle (the same to both) evens the weights out
    with pytest.raises(ValueError, match=r"cameras must be \[2, 4, 4\]"):
        PoseRefinement(2, _cameras())


def test_rendering_a_pose_moves_it_by_the_learnt_corrections(monkeypatch):
    model = tiny_model(sampler="uniform")
    seen = []
    monkeypatch.setattr(render_module, "image_rays", lambda c2w, intr: seen.append(c2w) or image_rays(c2w, intr))
    intr = Intrinsics(fl_x=4.0, fl_y=4.0, cx=2.0, cy=2.0, width=4, height=4)
    pose = _cameras()[1]
    render_normalized(model, pose, intr, ("rgb",))
    torch.testing.assert_close(seen[-1], pose)  # no refinement: the pose as given
    model.pose_refinement = PoseRefinement(4, _cameras())
    with torch.no_grad():
        model.pose_refinement.delta[:, 4] = torch.tensor([0.05, -0.05, 0.05, -0.05])
    render_normalized(model, pose, intr, ("rgb",))
    torch.testing.assert_close(seen[-1][:3, 3], pose[:3, 3] + torch.tensor([0.0, -0.05, 0.0]))
    loaded = VoxNeRFModel.from_state_dict(model.state_dict(), torch.device("cpu"))
    torch.testing.assert_close(loaded.pose_refinement.cameras, _cameras())
