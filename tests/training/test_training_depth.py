"""Sensor depth in training (voxnerf/training/stages/): the prior fused from depth, the depth loss's target and
its beta, and the proof that held-out frames' depth never enters either."""

from __future__ import annotations

import json
from pathlib import Path
from types import SimpleNamespace

import imageio.v3 as iio
import numpy as np
import pytest
import torch

from voxnerf.cameras.lens import undistort
from voxnerf.cameras.rules import Intrinsics, Lens
from voxnerf.config import TrainConfig
from voxnerf.data.scene import SceneTransform, load_scene
from voxnerf.errors import SceneError
from voxnerf.files import FUSED_PRIOR
from voxnerf.prior.depth_fusion import DepthNoise
from voxnerf.training import stages
from voxnerf.training.pixels import TrainingPixels, sensor_ray_distance
from voxnerf.training.run import train

CPU = torch.device("cpu")


def _scene(depths, prior_path=None):
    return SimpleNamespace(depths=depths, train_indices=list(range(len(depths))), root=Path("/scene"),
                           prior_path=prior_path)


@pytest.mark.parametrize(("cfg", "has_depth", "has_prior", "source", "why"), [
    (dict(), True, True, "sensor", "auto: the training frames have depth maps"),
    (dict(), False, True, "prior", "auto: no depth maps, the prior's depth"),
    (dict(), False, False, "none", "auto: no depth maps and no prior"),
    (dict(depth_source="prior"), True, True, "prior", "depth_source 'prior'"),
    (dict(depth_source="prior"), True, False, "none", "depth_source 'prior' but there is no prior"),
    (dict(depth_source="sensor"), True, False, "sensor", "depth_source 'sensor'"),
    (dict(depth_source="none"), True, True, "none", "depth_source 'none'"),
    (dict(depth_loss=False), True, True, "none", "depth loss disabled"),
])
def test_depth_source_resolution_says_why(cfg, has_depth, has_prior, source, why):
    scene = _scene([np.ones((2, 2)) if has_depth else None])
    got = stages.depth_source(TrainConfig(max_iters=1, **cfg), scene, object() if has_prior else None)
    assert got == (source, why)


def test_sensor_depth_asked_for_without_depth_maps_is_a_scene_error():
    with pytest.raises(SceneError, match="depth_source 'sensor' needs depth maps") as info:
        stages.depth_source(TrainConfig(max_iters=1, depth_source="sensor"), _scene([None, None]), object())
    assert info.value.key == "depth_file_path" and info.value.file.endswith("transforms.json")


def _pixels(h=4, w=6) -> TrainingPixels:
    return TrainingPixels(torch.zeros(1, h, w, 3, dtype=torch.uint8), torch.eye(4)[None],
                          torch.tensor([[5.0, 5.0, w / 2, h / 2]]))


def test_ray_distance_of_z_depth_grows_off_axis():
    pixels, scale = _pixels(), 0.5
    z = torch.full((1, 4, 6), 2.0)
    t = sensor_ray_distance(pixels, z, scale)
    u = (torch.arange(6) + 0.5 - 3.0) / 5.0
    v = (torch.arange(4) + 0.5 - 2.0) / 5.0
    expected = 2.0 * scale * torch.sqrt(1 + u[None] ** 2 + v[:, None] ** 2)
    torch.testing.assert_close(t[0], expected)


def test_sensor_target_with_the_prior_behind_it_and_beta_from_the_noise():
    pixels, transform = _pixels(), SceneTransform((0.0, 0.0, 0.0), 0.5)
    z = np.linspace(1.0, 4.0, 24, dtype=np.float32).reshape(4, 6)
    z[0, :3] = np.nan  # no sensor measurement: the prior's depth stands in
    pixels.pseudo_t = torch.full((1, 4, 6), 0.7)
    scene = _scene([z])
    noise = DepthNoise(s0=0.002, s2=0.003, median_depth=2.0, residuals=1000)
    prior = SimpleNamespace(sigma=0.02)
    got = stages.depth_target_stage(TrainConfig(max_iters=1), scene, prior, SimpleNamespace(noise=noise), pixels,
                                    transform)
    sensor_t = sensor_ray_distance(pixels, torch.from_numpy(z)[None], 0.5)
    assert torch.equal(got.target_t[0, 0, :3], pixels.pseudo_t[0, 0, :3])
    assert torch.equal(got.target_t[0, 1:], sensor_t[0, 1:])
    assert got.beta == pytest.approx(5 * 0.02)
    scale = got.beta_scale[0]
    assert torch.all(scale[0, :3] == 1.0)  # prior pixels keep the prior's beta
    expected = (0.002 + 0.003 * torch.from_numpy(z[1:]) ** 2) / 0.02
    torch.testing.assert_close(scale[1:], expected.clamp(*stages.BETA_SCALE_RANGE))
    assert scale[3, 5] > scale[1, 0]  # far pixels are trusted less
    assert got.summary["source"] == "sensor" and got.summary["sensor_fraction"] == pytest.approx(21 / 24)
    assert got.summary["prior_fraction"] == pytest.approx(3 / 24)
    assert "sensor depth on 87.5% of training pixels, the prior's on 12.5%" in got.record.why


def test_a_given_depth_beta_is_used_everywhere():
    pixels = _pixels()
    pixels.pseudo_t = torch.full((1, 4, 6), 0.7)
    z = np.full((4, 6), 2.0, np.float32)
    got = stages.depth_target_stage(TrainConfig(max_iters=1, depth_beta=0.05), _scene([z]), SimpleNamespace(sigma=0.02),
                                    None, pixels, SceneTransform((0.0, 0.0, 0.0), 1.0))
    assert got.beta == 0.05 and got.beta_scale is None and "given (depth_beta)" in got.record.why


def test_prior_source_targets_the_prior_depth():
    pixels = _pixels()
    pixels.pseudo_t = torch.full((1, 4, 6), float("nan"))
    pixels.pseudo_t[0, 0] = 0.3
    got = stages.depth_target_stage(TrainConfig(max_iters=1, depth_source="prior"), _scene([None]),
                                    SimpleNamespace(sigma=0.02), None, pixels, SceneTransform((0.0, 0.0, 0.0), 1.0))
    assert got.target_t is pixels.pseudo_t and got.beta_scale is None and got.summary["source"] == "prior"
    assert "the prior's depth on 25.0% of training pixels" in got.record.why


def test_a_distorted_depth_map_is_resampled_onto_its_pinhole_camera():
    """A plane z = 2 / (1 - 0.5 x) (x the undistorted image coordinate) seen through a lens: after resampling,
    each pinhole pixel holds the plane's depth along its own ray."""
    camera = Intrinsics(40.0, 40.0, 32.0, 24.0, 64, 48, Lens("OPENCV", k1=-0.2, k2=0.05, p1=0.001))
    v, u = np.mgrid[0:48, 0:64]
    xy_d = torch.from_numpy(np.stack([(u + 0.5 - 32.0) / 40.0, (v + 0.5 - 24.0) / 40.0], -1))
    x_u = undistort(xy_d, torch.tensor(camera.lens.coefficients, dtype=torch.float64), "OPENCV")[..., 0].numpy()
    depth = (2.0 / (1 - 0.5 * x_u)).astype(np.float32)
    out, pinhole = stages.pinhole_depth(depth, camera)
    assert pinhole.lens is None and (pinhole.fl_x, pinhole.width) == (40.0, 64)
    expected = 2.0 / (1 - 0.5 * (u + 0.5 - 32.0) / 40.0)
    seen = np.isfinite(out)
    assert seen.mean() > 0.8
    # nearest sampling: within the plane's depth change across one pixel (dz/dx = z^2 / 4, 40 px per unit of x)
    per_pixel = expected ** 2 / 4 / 40
    assert np.all(np.abs(out - expected)[seen] <= 1.2 * per_pixel[seen])
    assert np.abs(depth - expected)[seen].max() > 5 * per_pixel[seen].max()  # unresampled: the lens shows


# --- on a rendered room with depth maps and no prior file --------------------------------------------------


@pytest.fixture(scope="module")
def depth_room(tmp_path_factory) -> Path:
    from voxnerf.synthetic import RoomSpec, make_room_scene

    return make_room_scene(tmp_path_factory.mktemp("depth_room") / "room",
                           RoomSpec(width=48, height=36, n_frames=60, train_every=5, gap_len=15, prior_kind="none"))


TINY_TRAIN = dict(max_iters=3, compile=False, final_eval=False, device="cpu", eval_every_s=1e6)


def test_a_scan_with_depth_and_no_prior_trains_with_the_full_method(depth_room, tmp_path):
    report = train(depth_room, tmp_path / "run", TrainConfig(**TINY_TRAIN), progress_bar=False)
    why = {s.name: (s.ran, s.why) for s in report.stages}
    assert why["prior"][0] and why["prior"][1].startswith("no prior file; ")
    assert "training frames with depth -> TSDF prior" in why["prior"][1]
    assert why["octree"][0] and why["pseudo_depth"][0] and why["first_hit_cache"][0]
    assert why["depth_target"][0] and why["depth_target"][1].startswith("auto: the training frames have depth maps")
    assert report.prior["fused"]["source"] == "tsdf_fusion" and report.prior["kind"] == "mesh"
    assert report.depth["source"] == "sensor" and report.depth["sensor_fraction"] > 0.5
    assert (tmp_path / "run" / FUSED_PRIOR).is_file() and not report.warnings
    saved = json.loads((tmp_path / "run" / "report.json").read_text())
    assert saved["depth"]["noise"]["residuals"] > 0 and saved["depth_beta"] == pytest.approx(report.depth["beta"])


def _corrupt_held_out_depth(scene_dir: Path) -> int:
    scene = load_scene(scene_dir, load_images=False)
    held_out = [i for i in range(len(scene.frames)) if i not in set(scene.train_indices)]
    rng = np.random.default_rng(5)
    for i in held_out:
        path = scene.frames[i].depth_path
        shape = iio.imread(path).shape
        iio.imwrite(path, rng.integers(1, 60000, shape).astype(np.uint16))
    return len(held_out)


def test_held_out_depth_never_enters_the_prior_or_training(depth_room, tmp_path):
    import shutil

    corrupted = tmp_path / "corrupted"
    shutil.copytree(depth_room, corrupted)
    assert _corrupt_held_out_depth(corrupted) > 0
    runs = {}
    for name, scene_dir in (("clean", depth_room), ("corrupted", corrupted)):
        train(scene_dir, tmp_path / name, TrainConfig(**TINY_TRAIN), progress_bar=False)
        runs[name] = torch.load(tmp_path / name / "checkpoint.pt", weights_only=False)["model"]["field"]
    clean_mesh = (tmp_path / "clean" / FUSED_PRIOR).read_bytes()
    assert clean_mesh == (tmp_path / "corrupted" / FUSED_PRIOR).read_bytes()
    for key, value in runs["clean"].items():
        assert torch.equal(value, runs["corrupted"][key]), key


def test_depth_maps_without_a_valid_pixel_leave_the_scene_prior_less_and_say_why(tmp_path):
    (tmp_path / "images").mkdir()
    (tmp_path / "depth").mkdir()
    frames = []
    for i in range(3):
        iio.imwrite(tmp_path / "images" / f"f{i}.png", np.full((6, 8, 3), 40 * i, np.uint8))
        iio.imwrite(tmp_path / "depth" / f"d{i}.png", np.zeros((6, 8), np.uint16))  # 0: no measurement
        pose = np.eye(4)
        pose[0, 3] = 0.1 * i
        frames.append({"file_path": f"images/f{i}.png", "depth_file_path": f"depth/d{i}.png",
                       "transform_matrix": pose.tolist()})
    (tmp_path / "transforms.json").write_text(json.dumps(
        {"fl_x": 8.0, "fl_y": 8.0, "cx": 4.0, "cy": 3.0, "w": 8, "h": 6, "frames": frames}))
    found = stages.prior_stage(load_scene(tmp_path), TrainConfig(max_iters=1))
    assert found.prior is None and not found.record.ran
    assert found.record.why == ("no prior file, and the depth maps make none: the depth maps of the 2 training "
                                "frames hold no valid depth")
    assert "needs a prior; the scene has none" in found.warning


def test_sensor_depth_without_depth_maps_is_refused_when_the_scene_loads(tmp_path):
    """The mismatch is found before any set-up work (prior, octree, pseudo depth) is spent."""
    (tmp_path / "images").mkdir()
    frames = []
    for i in range(3):
        iio.imwrite(tmp_path / "images" / f"f{i}.png", np.full((6, 8, 3), 40 * i, np.uint8))
        frames.append({"file_path": f"images/f{i}.png", "transform_matrix": np.eye(4).tolist()})
    (tmp_path / "transforms.json").write_text(json.dumps(
        {"fl_x": 8.0, "fl_y": 8.0, "cx": 4.0, "cy": 3.0, "w": 8, "h": 6, "frames": frames}))
    with pytest.raises(SceneError, match="depth_source 'sensor' needs depth maps"):
        stages.load_scene_stage(tmp_path, TrainConfig(max_iters=1, depth_source="sensor"))
    assert stages.load_scene_stage(tmp_path, TrainConfig(max_iters=1)).record.ran  # auto: no depth, no error


def test_prior_file_false_leaves_the_prior_file_out_and_fuses_the_depth_maps(tmp_path_factory, tmp_path):
    """As a capture without a prior file trains (issue #46's desk), on a scene that has one."""
    from voxnerf.synthetic import RoomSpec, make_room_scene

    room = make_room_scene(tmp_path_factory.mktemp("prior_and_depth") / "room",
                           RoomSpec(width=48, height=36, n_frames=60, train_every=5, gap_len=15))
    with_file = train(room, tmp_path / "file", TrainConfig(**TINY_TRAIN), progress_bar=False)
    assert with_file.prior["kind"] == "points" and not (tmp_path / "file" / FUSED_PRIOR).exists()
    without = train(room, tmp_path / "fused", TrainConfig(**TINY_TRAIN, prior_file=False), progress_bar=False)
    why = {s.name: s.why for s in without.stages}
    assert why["prior"].startswith("no prior file; ") and "prior.ply left out (prior_file: false)" in why["prior"]
    assert without.prior["fused"]["source"] == "tsdf_fusion" and (tmp_path / "fused" / FUSED_PRIOR).is_file()
