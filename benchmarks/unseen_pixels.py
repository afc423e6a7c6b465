"""Where a run's evaluation error lies: each evaluation pixel by how many training views see its true surface point.

A pixel's true surface point is its depth map's (the scene must have depth maps for its evaluation frames, as the
suite's rooms do), back-projected through its camera. A training view sees that point when it projects inside the
view, in front of it, and within ``--tolerance`` of that view's own depth there (plus 2 % of the distance). The
renders are the run's final evaluation, ``RUN/eval/<split>/<view>.png`` (8-bit). Prints, per split, the share of
pixels and of squared error that falls on points seen by 0, 1, 2 and 3 or more training views, and each group's PSNR
(of the group's pooled squared error: report.json's PSNR is the mean of the views' own); writes them to ``--json``
when given. Pinhole cameras only.

    PYTHONPATH=. .venv/bin/python benchmarks/unseen_pixels.py RUN SCENE [--json OUT.json]
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

import numpy as np

from voxnerf.data.image_io import read_rgb
from voxnerf.data.scene import Scene, SceneTransform, depth_on_image, load_scene
from voxnerf.errors import VoxNeRFError
from voxnerf.training.eval_passes import eval_views_of

GROUPS = ("0", "1", "2", "3+")


def surface_points(scene: Scene, index: int) -> tuple[np.ndarray, np.ndarray]:
    """Frame ``index``'s pixels' true surface points [H, W, 3] (scene units) and which have a depth [H, W]."""
    frame = scene.frames[index]
    if frame.depth_path is None:
        raise VoxNeRFError(f"{scene.root}: frame {frame.file_path} has no depth map to place its pixels")
    k = scene.intrinsics(index)
    if k.lens is not None:
        raise VoxNeRFError(f"{scene.root}: frame {frame.file_path} has a lens; pinhole cameras only")
    depth = depth_on_image(frame, scene.depth_unit_scale, scene.downscale, scene.depth_max)
    v, u = np.mgrid[: depth.shape[0], : depth.shape[1]] + 0.5
    camera = np.stack([(u - k.cx) / k.fl_x * depth, -(v - k.cy) / k.fl_y * depth, -depth], -1)  # OpenGL axes
    return camera @ frame.c2w[:3, :3].T + frame.c2w[:3, 3], np.isfinite(depth) & (depth > 0)


def seen_count(scene: Scene, points: np.ndarray, tolerance: float) -> np.ndarray:
    """[H, W] how many training views see each of ``points`` [H, W, 3]."""
    count = np.zeros(points.shape[:2], dtype=np.int64)
    for i in scene.train_indices:
        frame, k = scene.frames[i], scene.intrinsics(i)
        depth = scene.depths[i] if scene.depths is not None and scene.depths[i] is not None else None
        if depth is None:
            raise VoxNeRFError(f"{scene.root}: training frame {frame.file_path} has no depth map")
        w2c = np.linalg.inv(frame.c2w)
        q = points @ w2c[:3, :3].T + w2c[:3, 3]
        z = -q[..., 2]
        ahead = z > 1e-6
        safe = np.where(ahead, z, 1.0)
        pu, pv = q[..., 0] / safe * k.fl_x + k.cx, -q[..., 1] / safe * k.fl_y + k.cy
        inside = ahead & (pu >= 0) & (pu < depth.shape[1]) & (pv >= 0) & (pv < depth.shape[0])
        iu = np.clip(pu.astype(np.int64), 0, depth.shape[1] - 1)
        iv = np.clip(pv.astype(np.int64), 0, depth.shape[0] - 1)
        count += inside & (np.abs(depth[iv, iu] - z) < tolerance + 0.02 * z)
    return count


def split_error(run: Path, scene: Scene, tolerance: float) -> dict[str, dict]:
    """Per evaluation split: the pixels and squared error per group of :data:`GROUPS`, and each group's PSNR."""
    names = eval_views_of(scene, SceneTransform((0.0, 0.0, 0.0), 1.0))  # the views' images and names
    out: dict[str, dict] = {}
    for split in names:
        sums = {g: [0, 0.0] for g in (*GROUPS, "no depth")}
        for view, index in zip(names[split], scene.splits[split], strict=True):
            render_path = run / "eval" / split / f"{view.name}.png"
            if not render_path.is_file():
                raise VoxNeRFError(f"{render_path}: no render (did the run's final evaluation run?)")
            render = read_rgb(render_path)[..., :3].astype(np.float64) / 255.0
            truth = view.image.numpy()[..., :3].astype(np.float64) / 255.0
            if render.shape != truth.shape:
                raise VoxNeRFError(f"{render_path}: {render.shape[:2]} pixels, the scene's view has {truth.shape[:2]}")
            squared = ((render - truth) ** 2).mean(-1)
            points, valid = surface_points(scene, index)
            count = seen_count(scene, points, tolerance)
            for group, mask in _groups(count, valid).items():
                sums[group][0] += int(mask.sum())
                sums[group][1] += float(squared[mask].sum())
        pixels = sum(n for n, _ in sums.values())
        error = sum(e for _, e in sums.values())
        out[split] = {"psnr": _psnr(error, pixels), "groups": {
            g: {"pixels": n / pixels, "error": e / error if error else 0.0, "psnr": _psnr(e, n)}
            for g, (n, e) in sums.items() if n}}
    return out


def _groups(count: np.ndarray, valid: np.ndarray) -> dict[str, np.ndarray]:
    return {"0": valid & (count == 0), "1": valid & (count == 1), "2": valid & (count == 2),
            "3+": valid & (count >= 3), "no depth": ~valid}


def _psnr(error: float, pixels: int) -> float | None:
    return None if not pixels else (math.inf if error == 0 else -10.0 * math.log10(error / pixels))


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("run", type=Path, help="a run directory with its final evaluation's renders")
    p.add_argument("scene", type=Path, help="the run's scene, with depth maps for its evaluation frames")
    p.add_argument("--tolerance", type=float, default=0.03, help="scene units (default 0.03)")
    p.add_argument("--json", type=Path)
    args = p.parse_args(argv)
    try:
        report = json.loads((args.run / "report.json").read_text())
        scene = load_scene(args.scene, downscale=int(report["config"].get("downscale") or 1))
        result = split_error(args.run, scene, args.tolerance)
    except (OSError, ValueError, KeyError, VoxNeRFError) as exc:
        print(f"unseen_pixels: {exc}", file=sys.stderr)
        return 2
    for split, r in result.items():
        print(f"{split}: PSNR {r['psnr']:.2f}")
        for group, g in r["groups"].items():
            print(f"  seen by {group:8s} {g['pixels']:6.1%} of the pixels, {g['error']:6.1%} of the squared error, "
                  f"PSNR {g['psnr']:.2f}")
    if args.json:
        args.json.write_text(json.dumps(result, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
