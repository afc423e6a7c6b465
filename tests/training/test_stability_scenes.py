"""Whole scenes on the CPU (issue 6, items 2, 3 and 5): units and placement invariance, degenerate priors and
scenes, and the divergence safeguard.

Every degenerate case has a defined outcome: a SceneError naming the file and the key (one line and exit code
2 from the CLI, before any training), or a finished run whose report, metrics and renders hold no NaN.
"""

from __future__ import annotations

import json
import math
import shutil
from collections.abc import Callable
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import open3d as o3d
import pytest
import torch
import trimesh
from synthetic_fixtures import make_micro_scene

import voxnerf.model.voxnerf_model as model_module
from voxnerf.cameras.rays import Intrinsics
from voxnerf.cli import main
from voxnerf.config import TrainConfig
from voxnerf.data.scene import SceneTransform, load_scene
from voxnerf.errors import SceneError, TrainingDiverged
from voxnerf.inference.evaluation import evaluate_views
from voxnerf.inference.render import load_model, render
from voxnerf.prior.loading import load_prior
from voxnerf.synthetic import RoomSpec, make_room_scene
from voxnerf.training.eval_passes import eval_views_of
from voxnerf.training.records import TrainReport
from voxnerf.training.run import train
from voxnerf.training.stages import FROM_CACHE

# Scale cases: x -> x * scale + offset for every position, lengths times scale.
UNITS = {"millimetres": (1e3, 0.0), "kilometres": (1e-3, 0.0), "offset_1e5": (1.0, 1e5)}
PSNR_TOLERANCE_DB = 1.0


def small_config(**overrides) -> TrainConfig:
    """A field small enough for a 2-core CPU: 6 hash levels of 2^12 entries, 8 + 4 samples per ray."""
    values = dict(rays_per_batch=256, compile=False, device="cpu", eval_every_s=1e9, checkpoint_every_s=1e9,
                  hash_levels=6, hash_log2_size=12, hash_max_resolution=128, hidden_dim=32, n_importance=8,
                  n_rest=4, smooth_patches=2)
    return TrainConfig(**{**values, **overrides})


def strict_json(path: Path) -> dict:
    """Parse a JSON file, refusing the NaN/Infinity extensions Python would otherwise accept."""
    def refuse(name: str):
        raise AssertionError(f"{path} holds {name}")

    return json.loads(path.read_text(), parse_constant=refuse)


def write_points(path: Path, points: np.ndarray) -> None:
    """A point-cloud PLY with float64 coordinates (open3d; trimesh would write float32)."""
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(points, dtype=np.float64)))
    assert o3d.io.write_point_cloud(str(path), cloud)


def prior_points(scene: Path) -> np.ndarray:
    return np.asarray(trimesh.load(scene / "prior.ply", process=False).vertices, dtype=np.float64)


def rescale_scene(src: Path, dst: Path, scale: float, offset: float) -> Path:
    """Copy scene ``src`` to ``dst`` in other units and placement: pose translations and prior points map
    ``x -> x * scale + offset``, ``prior_sigma`` scales, and ``depth_unit_scale_factor`` scales so that the
    same 16-bit depth PNGs mean the same distances. Images are untouched."""
    shutil.copytree(src, dst)
    meta = json.loads((dst / "transforms.json").read_text())
    for frame in meta["frames"]:
        pose = np.asarray(frame["transform_matrix"], dtype=np.float64)
        pose[:3, 3] = pose[:3, 3] * scale + offset
        frame["transform_matrix"] = pose.tolist()
    meta["prior_sigma"] *= scale
    meta["depth_unit_scale_factor"] *= scale
    (dst / "transforms.json").write_text(json.dumps(meta))
    write_points(dst / "prior.ply", prior_points(src) * scale + offset)
    return dst


def heldout_psnr(run: Path, scene: Path) -> dict[str, float]:
    """PSNR of every evaluation split, rendered from the run's checkpoint (LPIPS left out: time)."""
    trained = load_model(run, "cpu")
    views = eval_views_of(load_scene(scene), trained.model.transform)
    metrics = evaluate_views(trained.model, views, trained.model.config, lpips=False)
    return {split: m["psnr"] for split, m in metrics.items()}


# ------------------------------------------------------------------------------------ scale and placement


@pytest.fixture(scope="module")
def room(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("stability") / "room"
    return make_room_scene(out, RoomSpec(width=48, height=36, n_frames=120, train_every=6, gap_len=20,
                                         prior_max_points=50_000))


def normalised_inputs(scene_dir: Path) -> tuple[np.ndarray, np.ndarray, float]:
    """What training sees, built from the engine's public pieces as the trainer composes them: poses [N, 4, 4]
    and prior points [P, 3] as float32 in the canonical box, and sigma in box units."""
    scene = load_scene(scene_dir, load_images=False)
    prior = load_prior(scene.prior_path, scene.prior_sigma)
    centres = np.stack([f.c2w[:3, 3] for f in scene.frames])
    transform = SceneTransform.fit(np.concatenate([prior.points, centres]))
    poses = np.stack([transform.c2w_to_normalized(f.c2w) for f in scene.frames]).astype(np.float32)
    boxed = prior.transformed(np.asarray(transform.center), transform.scale)
    return poses, boxed.points.astype(np.float32), boxed.sigma


@pytest.mark.parametrize("units", list(UNITS))
def test_units_and_placement_leave_the_normalised_scene_bit_identical(room, tmp_path, units):
    """Normalisation runs in float64 before the float32 cast: at a 1e5 offset float32 positions are 7.8 mm
    apart (errors up to 4 mm, 1e-3 of the box); here every float32 number training sees is as in metres."""
    scale, offset = UNITS[units]
    other = rescale_scene(room, tmp_path / units, scale, offset)
    poses_m, points_m, sigma_m = normalised_inputs(room)
    poses, points, sigma = normalised_inputs(other)
    np.testing.assert_array_equal(poses, poses_m)
    np.testing.assert_array_equal(points, points_m)
    assert sigma == pytest.approx(sigma_m, rel=1e-12)
    if offset:  # the float32-first path would not be: the test can tell the two apart
        centres = np.stack([np.asarray(f["transform_matrix"])[:3, 3]
                            for f in json.loads((other / "transforms.json").read_text())["frames"]])
        assert np.abs(centres.astype(np.float32).astype(np.float64) - centres).max() > 1e-3


@pytest.fixture(scope="module")
def metre_run(room, tmp_path_factory) -> tuple[Path, dict]:
    run = tmp_path_factory.mktemp("runs") / "metres"
    report = train(room, run, small_config(max_iters=150, rays_per_batch=512, final_eval=False, depth_beta=0.1),
                   progress_bar=False)
    return run, report


@pytest.mark.slow
@pytest.mark.parametrize("units", list(UNITS))
def test_units_and_placement_train_to_the_same_heldout_psnr(room, metre_run, tmp_path, units):
    scale, offset = UNITS[units]
    scene = rescale_scene(room, tmp_path / units, scale, offset)
    run = tmp_path / "run"
    # depth_beta is a length in scene units (TrainConfig): the same 0.1 m, expressed in these units.
    report = train(scene, run, small_config(max_iters=150, rays_per_batch=512, final_eval=False,
                                            depth_beta=0.1 * scale), progress_bar=False)
    base_run, base_report = metre_run
    assert report.status == base_report.status == "succeeded"
    # Same octree in box units, same pseudo-depth coverage, same first hits.
    octree, base_octree = report.octree, base_report.octree
    assert octree["levels"] == base_octree["levels"]
    assert octree["nodes_per_level"] == base_octree["nodes_per_level"]
    assert octree["leaf_size"] == pytest.approx(base_octree["leaf_size"], rel=1e-9)
    np.testing.assert_allclose(octree["root_origin"], base_octree["root_origin"], rtol=0, atol=1e-7)
    whys = [{s.name: s.why.replace(FROM_CACHE, "") for s in r.stages} for r in (report, base_report)]
    for stage in ("octree", "pseudo_depth", "first_hit_cache"):
        assert whys[0][stage] == whys[1][stage], stage
    base, psnr = heldout_psnr(base_run, room), heldout_psnr(run, scene)
    assert set(psnr) == {"interpolation", "extrapolation"}
    for split in psnr:
        assert math.isfinite(psnr[split]) and psnr[split] > 12.0, (split, psnr)
        assert abs(psnr[split] - base[split]) < PSNR_TOLERANCE_DB, (units, split, psnr[split], base[split])
    # Depth comes back in the scene's units: a render of the same pose is the metre render times ``scale``.
    pose = np.asarray(load_scene(room, load_images=False).frames[0].c2w)
    moved = pose.copy()
    moved[:3, 3] = moved[:3, 3] * scale + offset
    k = Intrinsics(12.0, 12.0, 8.0, 6.0, 16, 12)
    depth_m = render(load_model(base_run, "cpu"), pose, k, ("depth",))["depth"]
    depth = render(load_model(run, "cpu"), moved, k, ("depth",))["depth"]
    assert np.isfinite(depth).all()
    np.testing.assert_allclose(depth / scale, depth_m, rtol=0.1)


# ------------------------------------------------------------------------------------- degenerate scenes


@pytest.fixture(scope="module")
def tiny_room(tmp_path_factory) -> Path:
    return make_micro_scene(tmp_path_factory, "stability")


Edit = Callable[[Path, dict], None]


def variant(src: Path, dst: Path, edit: Edit) -> Path:
    """A copy of scene ``src`` with ``edit(scene_dir, transforms_dict)`` applied."""
    shutil.copytree(src, dst)
    meta = json.loads((dst / "transforms.json").read_text())
    edit(dst, meta)
    (dst / "transforms.json").write_text(json.dumps(meta))
    return dst


def _set_pose(index: int, change: Callable[[np.ndarray], None]) -> Edit:
    def edit(_: Path, meta: dict) -> None:
        pose = np.asarray(meta["frames"][index]["transform_matrix"], dtype=np.float64)
        change(pose)
        meta["frames"][index]["transform_matrix"] = pose.tolist()

    return edit


def _prior(make: Callable[[np.ndarray], np.ndarray], sigma: bool = True) -> Edit:
    def edit(root: Path, meta: dict) -> None:
        write_points(root / "prior.ply", make(prior_points(root)))
        if not sigma:
            meta.pop("prior_sigma")

    return edit


def _empty_prior(root: Path, _: dict) -> None:
    header = "ply\nformat ascii 1.0\nelement vertex 0\nproperty float x\nproperty float y\nproperty float z\n"
    (root / "prior.ply").write_text(header + "end_header\n")


def _duplicate_path(_: Path, meta: dict) -> None:
    meta["frames"].append(dict(meta["frames"][0]))


def _scale_rotation(pose: np.ndarray) -> None:
    pose[:3, :3] *= 2.0  # a unit conversion applied to the whole matrix


def _mirror(pose: np.ndarray) -> None:
    pose[:3, 0] *= -1.0  # left-handed camera


def _shear(pose: np.ndarray) -> None:
    pose[:3, :3] = pose[:3, :3] @ np.array([[1.0, 0.3, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])


def _nan_pose(pose: np.ndarray) -> None:
    pose[1, 3] = np.nan


REFUSED = {
    # case: (edit, file the error names, key it names or None for the whole file, words of the message)
    "empty_prior": (_empty_prior, "prior.ply", None, "contains no geometry"),
    "one_point_without_sigma": (_prior(lambda p: p[:1], sigma=False), "prior.ply", None, "give prior_sigma"),
    "all_vertices_nan": (_prior(lambda p: np.full_like(p[:50], np.nan)), "prior.ply", None, "NaN or inf"),
    "coincident_points_without_sigma": (_prior(lambda p: np.repeat(p[:1], 100, 0), sigma=False), "prior.ply",
                                        None, "give prior_sigma"),
    "zero_sigma": (lambda root, meta: meta.update(prior_sigma=0.0), "transforms.json", "prior_sigma",
                   "positive finite"),
    "duplicate_file_path": (_duplicate_path, "transforms.json", "frames[19].file_path", "duplicate"),
    "rotation_scaled_by_2": (_set_pose(3, _scale_rotation), "transforms.json", "frames[3].transform_matrix",
                             "not a proper orthonormal"),
    "rotation_mirrored": (_set_pose(3, _mirror), "transforms.json", "frames[3].transform_matrix", "det = -1"),
    "rotation_sheared": (_set_pose(3, _shear), "transforms.json", "frames[3].transform_matrix",
                         "not a proper orthonormal"),
    "nan_in_pose": (_set_pose(5, _nan_pose), "transforms.json", "frames[5].transform_matrix", "NaN or inf"),
    "no_training_frames": (lambda root, meta: meta.update(train_filenames=[]), "transforms.json",
                           "train_filenames", "no training frames"),
}


@pytest.mark.parametrize("case", list(REFUSED))
def test_degenerate_input_is_refused_before_training(tiny_room, tmp_path, capsys, case):
    edit, file_name, key, words = REFUSED[case]
    scene = variant(tiny_room, tmp_path / "scene", edit)
    with pytest.raises(SceneError) as info:
        train(scene, tmp_path / "run", small_config(max_iters=5), progress_bar=False)
    err = info.value
    assert Path(err.file).name == file_name and err.key == key and words in err.message, str(err)
    assert not (tmp_path / "run" / "checkpoint.pt").exists()

    code = main(["train", str(scene), "--out", str(tmp_path / "cli"), "--max-iters", "5", "--no-compile",
                 "--device", "cpu"])
    stderr = capsys.readouterr().err
    assert code == 2
    assert stderr.count("\n") == 1 and stderr.startswith(f"voxnerf: error: {err.file}: "), stderr
    assert (key is None or f": {key}: " in stderr) and words in stderr


def _black(root: Path, meta: dict) -> None:
    for frame in meta["frames"]:
        iio.imwrite(root / frame["file_path"], np.zeros((18, 24, 3), np.uint8))


def _saturated(root: Path, meta: dict) -> None:
    for frame in meta["frames"]:
        iio.imwrite(root / frame["file_path"], np.full((18, 24, 3), 255, np.uint8))


def _duplicate_frame(root: Path, meta: dict) -> None:
    first = meta["frames"][0]
    shutil.copy(root / first["file_path"], root / "images" / "copy.png")
    meta["frames"].append({**first, "file_path": "images/copy.png"})
    meta["train_filenames"].append("images/copy.png")


def _nonfinite_vertices(points: np.ndarray) -> np.ndarray:
    points = points.copy()
    points[::10, 0] = np.nan
    points[5::10, 2] = np.inf
    return points


def _skew(pose: np.ndarray) -> None:
    pose[:3, :3] = pose[:3, :3] @ np.array([[1.0, 0.01, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])


GRACEFUL: dict[str, tuple[Edit, Callable[[TrainReport], None]]] = {
    # case: (edit, extra check of the report)
    "one_point_prior": (_prior(lambda p: p[:1]),
                        lambda r: r.prior["points"] == 1 and r.octree["nodes_per_level"][-1] == 1),
    "planar_prior": (_prior(lambda p: p[p[:, 2] < 0.05] * [1.0, 1.0, 0.0]),
                     lambda r: r.prior["points"] > 1000),
    "prior_1km_from_cameras": (_prior(lambda p: p + [1000.0, 0.0, 0.0]),
                               lambda r: "(0.0% hit;" in _why(r, "first_hit_cache")),
    "nan_and_inf_vertices": (_prior(_nonfinite_vertices), lambda r: r.prior["nonfinite_removed"] == len(
        range(0, r.prior["input_points"], 10)) + len(range(5, r.prior["input_points"], 10))),
    "sigma_10x_too_small": (lambda root, meta: meta.update(prior_sigma=meta["prior_sigma"] / 10),
                            lambda r: r.prior["sigma"] == pytest.approx(0.002)),
    "sigma_10x_too_large": (lambda root, meta: meta.update(prior_sigma=meta["prior_sigma"] * 10),
                            lambda r: r.prior["sigma"] == pytest.approx(0.2)),
    "single_training_image": (lambda root, meta: meta.update(train_filenames=meta["train_filenames"][:1]),
                              lambda r: r.scene["splits"]["train"] == 1),
    "all_black_images": (_black, lambda r: 0.0 < r.metrics["interpolation"]["psnr"] <= 100.0),
    "saturated_images": (_saturated, lambda r: True),
    "duplicate_frame_content": (_duplicate_frame, lambda r: r.scene["splits"]["train"] == 11),
    "slightly_skewed_rotation": (_set_pose(3, _skew), lambda r: any(
        "frames[3].transform_matrix: rotation re-orthonormalised" in w for w in r.scene["warnings"])),
}


def _why(report: TrainReport, stage: str) -> str:
    return next(s.why for s in report.stages if s.name == stage)


@pytest.mark.slow
@pytest.mark.parametrize("case", list(GRACEFUL))
def test_degenerate_scene_trains_without_nan(tiny_room, tmp_path, case):
    edit, check = GRACEFUL[case]
    scene = variant(tiny_room, tmp_path / "scene", edit)
    run = tmp_path / "run"
    report = train(scene, run, small_config(max_iters=5, rays_per_batch=128), progress_bar=False)
    assert report.status == "succeeded" and report.iteration == 5
    assert strict_json(run / "report.json")["status"] == "succeeded"
    for split, metrics in report.metrics.items():
        assert math.isfinite(metrics["psnr"]) and math.isfinite(metrics["ssim"]), split
        assert metrics["lpips"] is None and "31x31" in metrics["lpips_note"]  # 24x18 views: too small
    assert check(report), json.dumps(report.model_dump(include={"prior", "octree", "scene"}))[:2000]
    trained = load_model(run, "cpu")
    assert all(bool(torch.isfinite(p).all()) for p in trained.model.field.parameters())
    frame = load_scene(scene, load_images=False).frames[0]
    out = render(trained, frame.c2w, Intrinsics(6.0, 6.0, 4.0, 3.0, 8, 6))
    assert all(np.isfinite(v).all() for v in out.values())
    assert (out["depth"] > 0).all() and ((out["opacity"] >= 0) & (out["opacity"] <= 1)).all()


# ---------------------------------------------------------------------------------------- divergence


def _fault_at(call: int, fault: str, monkeypatch) -> None:
    """Make the trainer's colour loss misbehave at its ``call``-th evaluation (0-based): return NaN
    (``"nan_loss"``) or keep a finite value whose gradient is NaN (``"nan_gradient"``), which poisons the
    weights through the optimiser step. Simulates a numerical fault; everything else is the real engine."""
    calls = [0]
    real = model_module.color_loss

    class NanGradient(torch.autograd.Function):
        @staticmethod
        def forward(ctx, x: torch.Tensor) -> torch.Tensor:
            return x.clone()

        @staticmethod
        def backward(ctx, grad: torch.Tensor) -> torch.Tensor:
            return torch.full_like(grad, float("nan"))

    def faulty(pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
        value = real(pred, target)
        calls[0] += 1
        if calls[0] - 1 != call:
            return value
        return value * float("nan") if fault == "nan_loss" else NanGradient.apply(value)

    monkeypatch.setattr(model_module, "color_loss", faulty)


@pytest.mark.parametrize(("fault", "last_good"), [("nan_loss", 6), ("nan_gradient", 6)])
def test_divergence_stops_with_a_clear_error_and_keeps_the_last_good_checkpoint(
    tiny_room, tmp_path, monkeypatch, fault, last_good
):
    """A checkpoint is written after every iteration (checkpoint_every_s tiny). A NaN loss at iteration 6 is
    caught before the optimiser step; a NaN gradient at iteration 6 poisons the weights, which the checkpoint
    check after that step catches. Either way checkpoint.pt stays the one of iteration 6 and loads."""
    _fault_at(6, fault, monkeypatch)
    run = tmp_path / "run"
    with pytest.raises(TrainingDiverged) as info:
        train(tiny_room, run, small_config(max_iters=20, checkpoint_every_s=1e-6), progress_bar=False)
    message = str(info.value)
    assert "\n" not in message and "last good checkpoint kept at" in message and str(run) in message
    assert ("loss became nan at iteration 6" if fault == "nan_loss" else "weights became NaN/inf") in message
    report = strict_json(run / "report.json")
    assert report["status"] == "diverged" and report["checkpoint_kept"] is True
    assert report["error"] and report["error"] in message
    trained = load_model(run, "cpu")
    assert trained.iteration == last_good
    assert all(bool(torch.isfinite(p).all()) for p in trained.model.field.parameters())
    frame = load_scene(tiny_room, load_images=False).frames[0]
    rgb = render(trained, frame.c2w, Intrinsics(6.0, 6.0, 4.0, 3.0, 8, 6), ("rgb",))["rgb"]
    assert np.isfinite(rgb).all()


def test_divergence_before_any_checkpoint_says_so_and_the_cli_exits_2(
    tiny_room, tmp_path, monkeypatch, capsys
):
    _fault_at(0, "nan_loss", monkeypatch)
    code = main(["train", str(tiny_room), "--out", str(tmp_path / "run"), "--max-iters", "3", "--no-compile",
                 "--device", "cpu"])
    stderr = capsys.readouterr().err.strip().splitlines()
    assert code == 2
    assert stderr[-1].startswith("voxnerf: error: loss became nan at iteration 0"), stderr[-1]
    assert stderr[-1].endswith("no checkpoint yet")
    report = strict_json(tmp_path / "run" / "report.json")
    assert report["status"] == "diverged" and report["checkpoint_kept"] is False
    assert not (tmp_path / "run" / "checkpoint.pt").exists()
