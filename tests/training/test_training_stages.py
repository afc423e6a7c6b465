"""The set-up stages (voxnerf/training/stages/): what each records, and why, on small stub inputs."""

from __future__ import annotations

import os
import random
import subprocess
import sys
from types import SimpleNamespace

import numpy as np
import pytest
import torch
from synthetic_fixtures import make_micro_scene, micro_config

from voxnerf.config import TrainConfig
from voxnerf.data.scene import load_scene
from voxnerf.model import hash_kernel
from voxnerf.training import stages
from voxnerf.training.records import StageRecord

CPU = torch.device("cpu")


def _scene(prior_path=None):
    frames = [SimpleNamespace(c2w=np.eye(4), depth_path=None), SimpleNamespace(c2w=np.eye(4), depth_path=None)]
    frames[1].c2w[:3, 3] = [2.0, 0.0, 0.0]
    return SimpleNamespace(prior_path=prior_path, frames=frames, train_indices=[0, 1])


def test_seeding_makes_every_generator_repeat():
    stages.seed_everything(3)
    first = (random.random(), np.random.rand(), float(torch.rand(())))
    stages.seed_everything(3)
    assert (random.random(), np.random.rand(), float(torch.rand(()))) == first


@pytest.mark.parametrize(("cfg", "warning"), [
    (TrainConfig(max_iters=1, sampler="voxnerf", depth_loss=True), "sampler 'voxnerf' and the depth loss need a prior"),
    (TrainConfig(max_iters=1, sampler="occgrid", depth_loss=True), "sampler 'occgrid' and the depth loss need"),
    (TrainConfig(max_iters=1, sampler="voxnerf", depth_loss=False), "sampler 'voxnerf' need a prior"),
    (TrainConfig(max_iters=1, sampler="occgrid", depth_loss=False), None),
])
def test_a_scene_without_prior_warns_only_when_something_needs_one(cfg, warning):
    found = stages.prior_stage(_scene(), cfg)
    assert found.prior is None and found.record.name == "prior" and not found.record.ran
    needs = warning is not None
    assert found.record.why == "the scene has no prior" + (" and no training frame has a depth map" if needs else "")
    assert (found.warning is None) if warning is None else (warning in found.warning)


@pytest.mark.parametrize(("depth_loss", "warning"), [
    (True, "the depth loss needs a prior; the scene has none, so no depth loss is used (sampler 'auto' takes the "
           "occupancy grid)"),
    (False, None),
])
def test_without_a_prior_sampler_auto_warns_only_for_the_depth_loss(depth_loss, warning):
    """Sampler 'auto' needs no prior (without one it chooses the grid): only the depth loss misses it."""
    found = stages.prior_stage(_scene(), TrainConfig(max_iters=1, depth_loss=depth_loss))
    assert found.prior is None and not found.record.ran and found.warning == warning


def test_hash_kernel_stage_says_why_it_did_not_run():
    off = stages.hash_kernel_stage(TrainConfig(max_iters=1, hash_kernel=False), CPU)
    assert not off.ran and off.why.startswith("disabled (--no-hash-kernel)")
    cuda = stages.hash_kernel_stage(TrainConfig(max_iters=1), torch.device("cuda"))
    assert not cuda.ran and cuda.why == "on cuda the hash encoding stays in PyTorch"


def test_hash_kernel_stage_reports_an_unavailable_kernel(monkeypatch):
    monkeypatch.setattr(hash_kernel, "available", lambda: False)
    monkeypatch.setattr(hash_kernel, "unavailable_reason", lambda: "no compiler")
    record = stages.hash_kernel_stage(TrainConfig(max_iters=1), CPU)
    assert record == StageRecord(name="hash_kernel", ran=False, seconds=record.seconds,
                                 why="C kernel unavailable (no compiler): the hash encoding stays in PyTorch")


def test_without_prior_the_box_is_the_cameras_grown_by_their_extent():
    transform, aabb = stages.scene_box(_scene(), None)
    centres = transform.points_to_normalized(np.array([[0.0, 0.0, 0.0], [2.0, 0.0, 0.0]]))
    assert aabb.shape == (2, 3) and (aabb[0] < centres.min(0)).all() and (aabb[1] > centres.max(0)).all()
    assert (aabb >= -1.0).all() and (aabb <= 1.0).all()


def test_stages_that_have_nothing_to_work_on_say_so():
    cfg = TrainConfig(max_iters=1, sampler="occgrid")
    assert stages.octree_stage(cfg, None, None, None, CPU).record.why == "no prior"
    prior = SimpleNamespace(points=np.zeros((1, 3)), sigma=0.1)
    tree = stages.octree_stage(cfg, prior, None, None, CPU)
    assert tree.octree is None and tree.record.why == "sampler 'occgrid' does not use it"
    depth = stages.pseudo_depth_stage(TrainConfig(max_iters=1, depth_loss=False), None, prior, None, None, None, CPU)
    assert depth.pseudo_t is None and depth.record.why == "depth loss disabled"
    depth = stages.pseudo_depth_stage(TrainConfig(max_iters=1), None, None, None, None, None, CPU)
    assert depth.record.why == "no prior to render depth from"
    hits = stages.first_hit_stage(None, None, None)
    assert hits.hit is None and hits.record == StageRecord(name="first_hit_cache", ran=False, why="no octree",
                                                           seconds=hits.record.seconds)


def test_an_eager_step_records_compile_as_disabled_at_once():
    def loss_fn():
        return None

    compiled = stages.compile_stage(TrainConfig(max_iters=1, compile=False), loss_fn)
    assert compiled.loss_fn is loss_fn
    assert compiled.record.name == "compile" and not compiled.record.ran
    assert compiled.record.why == "disabled (--no-compile)"


def test_a_prior_from_ply_file_path_says_so(tmp_path):
    import trimesh

    rng = np.random.default_rng(0)
    trimesh.PointCloud(np.c_[rng.uniform(-1, 1, (300, 2)), rng.normal(0, 0.01, 300)]).export(tmp_path / "pc.ply")
    scene = SimpleNamespace(prior_path=tmp_path / "pc.ply", prior_sigma=None, prior_key="ply_file_path")
    found = stages.prior_stage(scene, TrainConfig(max_iters=1))
    assert found.record.ran and found.prior is not None and found.prior.sigma_estimated
    assert "(estimated)" in found.record.why and "from nerfstudio's ply_file_path (pc.ply)" in found.record.why


def test_the_compile_stage_keeps_inductors_cache_beside_the_kernels_unless_told(monkeypatch, tmp_path):
    monkeypatch.setenv("VOXNERF_CACHE", str(tmp_path))
    monkeypatch.delenv("TORCHINDUCTOR_CACHE_DIR", raising=False)
    stages.compile_stage(TrainConfig(max_iters=1), lambda x: x)
    assert os.environ["TORCHINDUCTOR_CACHE_DIR"] == str(tmp_path / "inductor")
    monkeypatch.setenv("TORCHINDUCTOR_CACHE_DIR", str(tmp_path / "mine"))
    stages.compile_stage(TrainConfig(max_iters=1), lambda x: x)
    assert os.environ["TORCHINDUCTOR_CACHE_DIR"] == str(tmp_path / "mine")
    assert stages.compile_stage(TrainConfig(max_iters=1, compile=False), lambda x: x).record.why.startswith("disabled")


def test_inductors_default_set_before_the_stage_counts_as_unset(monkeypatch, tmp_path):
    """Building the model's Adam optimizer imports torch._dynamo, which sets TORCHINDUCTOR_CACHE_DIR to inductor's
    default under /tmp before the compile stage runs: the compile stage must still move the cache beside the
    kernels."""
    from torch._inductor.runtime.cache_dir_utils import default_cache_dir

    monkeypatch.setenv("VOXNERF_CACHE", str(tmp_path))
    monkeypatch.setenv("TORCHINDUCTOR_CACHE_DIR", default_cache_dir())
    stages.compile_stage(TrainConfig(max_iters=1), lambda x: x)
    assert os.environ["TORCHINDUCTOR_CACHE_DIR"] == str(tmp_path / "inductor")


def test_a_compiled_function_lands_in_the_persistent_cache(tmp_path):
    """In a fresh process, as ``voxnerf train`` runs: the compiled code is written under $VOXNERF_CACHE/inductor."""
    code = ("import torch\n"
            "torch.optim.Adam([torch.zeros(1, requires_grad=True)])\n"  # as the set-up does: imports torch._dynamo
            "from voxnerf.config import TrainConfig\n"
            "from voxnerf.training import stages\n"
            "step = stages.compile_stage(TrainConfig(max_iters=1), lambda x: torch.sin(x) * 2 + 1).loss_fn\n"
            "step(torch.ones(8))\n")
    env = {**os.environ, "VOXNERF_CACHE": str(tmp_path)}
    env.pop("TORCHINDUCTOR_CACHE_DIR", None)
    subprocess.run([sys.executable, "-c", code], env=env, check=True, capture_output=True, timeout=600)
    assert any((tmp_path / "inductor").rglob("*.py")), sorted(p.name for p in tmp_path.rglob("*"))[:20]


def test_the_training_mean_background_is_the_mean_colour_of_the_training_images():
    images = [np.full((2, 2, 3), 255, np.uint8), np.zeros((2, 2, 3), np.uint8), np.full((2, 2, 3), 51, np.uint8)]
    scene = SimpleNamespace(train_indices=[0, 2], images=images)
    assert stages.training_mean_colour(scene) == pytest.approx((0.6, 0.6, 0.6))


def test_an_unresolved_training_mean_background_shows_black():
    from voxnerf.data.scene import SceneTransform
    from voxnerf.model.voxnerf_model import VoxNeRFModel

    cfg = TrainConfig(max_iters=1, hash_levels=2, hash_log2_size=10, hash_max_resolution=32, hidden_dim=8,
                      background="training_mean")
    model = VoxNeRFModel.create(cfg, SceneTransform((0.0, 0.0, 0.0), 1.0), torch.tensor([[-1.0] * 3, [1.0] * 3]),
                                None, torch.device("cpu"))
    assert model.background.tolist() == [0.0, 0.0, 0.0]


@pytest.fixture(scope="module")
def micro_room(tmp_path_factory):
    return make_micro_scene(tmp_path_factory, "stages")


def _model_stage(room, previous=None, **overrides):
    cfg = micro_config(appearance="affine", pose_refinement="so3xr3", **overrides)
    return stages.model_stage(cfg, load_scene(room), None, CPU, previous)


def test_the_field_weight_decay_reaches_the_field_alone(micro_room):
    groups = _model_stage(micro_room, field_weight_decay=1e-6).optimizer.param_groups
    assert [g["weight_decay"] for g in groups] == [1e-6, 0.0, 0.0]  # field, appearance, pose corrections


@pytest.mark.parametrize(("decay", "shrinks"), [(0.0, False), (1e-3, True)])
def test_weight_decay_shrinks_features_no_image_asks_for(micro_room, decay, shrinks):
    built = _model_stage(micro_room, field_weight_decay=decay)
    table = built.model.field.encoding.table
    with torch.no_grad():
        table.fill_(1.0)
    for p in built.model.field.parameters():
        p.grad = torch.zeros_like(p)  # no data gradient anywhere
    built.optimizer.step()
    assert bool((table < 1.0).all()) is shrinks and bool((table == 1.0).all()) is not shrinks


def test_the_auto_cone_is_a_training_pixel_s_footprint_and_the_model_keeps_the_number(micro_room):
    scene = load_scene(micro_room)
    k = scene.intrinsics(scene.train_indices[0])
    expected = 1.0 / (3**0.5 * (k.fl_x * k.fl_y) ** 0.5)
    assert stages.training_pixel_cone(scene) == pytest.approx(expected)
    built = _model_stage(micro_room, cone_radius="auto", field_weight_decay=0.0)
    assert built.model.config.model.cone_radius == pytest.approx(expected)
    assert _model_stage(micro_room, field_weight_decay=0.0).model.cone_radius is None


def test_a_resumed_run_decays_as_its_command_says(micro_room, tmp_path):
    from voxnerf.training.run import train

    train(micro_room, tmp_path / "run", micro_config(max_iters=2, field_weight_decay=0.0), progress_bar=False)
    previous = torch.load(tmp_path / "run" / "checkpoint.pt", map_location="cpu", weights_only=False)
    assert previous["optimizer"]["param_groups"][0]["weight_decay"] == 0.0
    cfg = micro_config(field_weight_decay=1e-6, appearance="none", pose_refinement="none")
    groups = stages.model_stage(cfg, load_scene(micro_room), None, CPU, previous).optimizer.param_groups
    assert groups[0]["weight_decay"] == 1e-6
