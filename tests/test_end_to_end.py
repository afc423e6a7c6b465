"""End to end on the CPU: generate a small room, train briefly, evaluate, render to PNG/EXR through the CLI."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from voxnerf.cli import main
from voxnerf.data.image_io import decode_exr
from voxnerf.data.scene import load_scene
from voxnerf.inference.evaluation import evaluate_views
from voxnerf.inference.render import load_model, render
from voxnerf.model import hash_kernel
from voxnerf.synthetic import build_room, render_view
from voxnerf.training.eval_passes import eval_views_of

pytestmark = pytest.mark.slow


def test_report_lists_stages_and_history(trained_small_room):
    report = json.loads((trained_small_room / "report.json").read_text())
    assert report["status"] == "succeeded" and report["iteration"] == 500
    stages = {s["name"]: s for s in report["stages"]}
    for name in ("load_scene", "prior", "octree", "pseudo_depth", "first_hit_cache", "train", "final_eval"):
        assert stages[name]["ran"], name
    assert not stages["compile"]["ran"] and stages["compile"]["why"] == "disabled (--no-compile)"
    assert stages["hash_kernel"]["ran"] == hash_kernel.available(), stages["hash_kernel"]["why"]
    assert report["history"] and all("psnr" in h and "elapsed_s" in h for h in report["history"])
    assert set(report["metrics"]) == {"interpolation", "extrapolation"}  # test_filenames == interpolation
    # the final evaluation also scores the progress evaluations' views, so one curve can run through both
    final = report["history"][-1]
    assert final["final"] and set(final["progress_psnr"]) == set(final["psnr"])
    assert all(np.isfinite(v) for v in final["progress_psnr"].values())
    # 1024 random rays per step; the smoothness term (and its patches) is off by default
    assert report["throughput"]["rays_per_step"] == 1024
    assert report["config"]["smooth_patches"] == 0


def test_heldout_psnr_beats_constant_colour_and_depth_tracks_truth(trained_small_room, small_room):
    report = json.loads((trained_small_room / "report.json").read_text())
    scene = load_scene(small_room)
    for split in ("interpolation", "extrapolation"):
        idx = scene.splits[split]
        gts = [torch.from_numpy(scene.images[i]).float() / 255 for i in idx]
        train_mean = np.mean([scene.images[i].reshape(-1, 3).mean(0) for i in scene.train_indices], axis=0) / 255
        const = [float(-10 * torch.log10(((g - torch.tensor(train_mean).float()) ** 2).mean())) for g in gts]
        margin = 3.0 if split == "interpolation" else 0.3  # extrapolation views see much unseen geometry
        assert report["metrics"][split]["psnr"] > np.mean(const) + margin, split

    trained = load_model(trained_small_room, "cpu")
    geom = build_room(0)
    errors = []
    for i in scene.splits["interpolation"][:3]:
        frame = scene.frames[i]
        k = frame.intrinsics
        _, true_z = render_view(geom, frame.c2w, k.fl_x, k.cx, k.cy, k.width, k.height, supersample=1)
        out = render(trained, frame.c2w, k, ("depth",))
        errors.append(np.abs(out["depth"] - true_z) / true_z)
    assert float(np.median(np.concatenate([e.ravel() for e in errors]))) < 0.05


def test_the_fast_render_path_scores_within_a_fifth_of_a_db_of_the_full_path(trained_small_room):
    trained = load_model(trained_small_room, "cpu")
    scene = load_scene(trained.scene_dir, downscale=trained.model.config.run.downscale)
    views = eval_views_of(scene, trained.model.transform)
    fast, full = (evaluate_views(trained.model, views, trained.model.config, lpips=False, path=path)
                  for path in ("fast", "full"))
    for split in views:
        assert abs(fast[split]["psnr"] - full[split]["psnr"]) < 0.2, split
        assert fast[split]["renderer"].startswith("fast") and full[split]["renderer"].startswith("full")


def test_cli_eval_and_render(trained_small_room, tmp_path, capsys):
    assert main(["eval", str(trained_small_room), "--split", "extrapolation", "--json", str(tmp_path / "m.json")]) == 0
    metrics = json.loads((tmp_path / "m.json").read_text())
    assert metrics["split"] == "extrapolation" and {"psnr", "ssim", "lpips", "views"} <= set(metrics)
    frame = load_model(trained_small_room, "cpu")
    c2w = np.eye(4)
    c2w[:3, 3] = [0.0, 0.0, 1.4]
    pose = {"transform_matrix": c2w.tolist(), "w": 40, "h": 30}
    (tmp_path / "pose.json").write_text(json.dumps(pose))
    assert main(["render", str(trained_small_room), "--pose", str(tmp_path / "pose.json"), "--out",
                 str(tmp_path / "v.exr"), "--depth", "--opacity"]) == 0
    channels = decode_exr((tmp_path / "v.exr").read_bytes())
    assert set(channels) == {"R", "G", "B", "Z", "A"} and channels["Z"].shape == (30, 40)
    assert np.isfinite(channels["Z"]).all() and (channels["Z"] > 0).all()
    assert main(["render", str(trained_small_room), "--pose", str(tmp_path / "pose.json"), "--out",
                 str(tmp_path / "v.png")]) == 0
    assert frame.default_intrinsics.width == 64


def test_cli_errors_are_one_line(tmp_path, capsys):
    assert main(["train", str(tmp_path / "nope"), "--out", str(tmp_path / "r"), "--max-iters", "1"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "scene directory not found" in err
    assert main(["render", str(tmp_path), "--pose", "p.json", "--out", str(tmp_path / "x.png")]) == 2
    assert "no checkpoint" in capsys.readouterr().err


def test_cli_smooth_patches_adds_the_smoothness_term(small_room, tmp_path, capsys):
    """``--smooth-patches N`` mixes N 8 x 8 patches into every batch for the paper's depth-smoothness term."""
    run = tmp_path / "smooth"
    args = ["train", str(small_room), "--out", str(run), "--max-iters", "3", "--no-compile", "--smooth-patches", "2"]
    assert main(args) == 0
    report = json.loads((run / "report.json").read_text())
    assert report["config"]["smooth_patches"] == 2
    assert report["throughput"]["rays_per_step"] == 2048 + 2 * 8 * 8
    capsys.readouterr()  # the first run's progress bar
    assert main(["train", str(small_room), "--out", str(tmp_path / "bad"), "--max-iters", "1",
                 "--smooth-patches", "-1"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "smooth_patches" in err
    assert not (tmp_path / "bad").exists(), "a refused option leaves no run directory behind"
