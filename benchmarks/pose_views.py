"""Held-out views of a pose-refined run, rendered at their given poses and at the poses its refinement moves them
to (the blend of the nearest training cameras' corrections, what every render of such a model does).

Why: pose refinement fits the training cameras' poses, and a scan's held-out frames carry about the pose error
of their neighbours along the path. Scored at their given poses, they measure how far the refinement moved the
field away from the scan's frame as much as how good the field is; this prints both, per split.

    python benchmarks/pose_views.py RUN SCENE [--downscale 2] [--every 1] [--out FILE.json]
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from voxnerf.data.scene import load_scene  # noqa: E402
from voxnerf.files import CHECKPOINT  # noqa: E402
from voxnerf.inference.render import render_normalized, scene_as_trained  # noqa: E402
from voxnerf.model.voxnerf_model import VoxNeRFModel  # noqa: E402
from voxnerf.training.checkpoint import load_checkpoint  # noqa: E402
from voxnerf.training.eval_passes import eval_views_of  # noqa: E402


def view_psnr(model: VoxNeRFModel, view) -> float:
    rgb = render_normalized(model, view.c2w, view.intrinsics, ("rgb",))["rgb"].float().cpu().clamp(0.0, 1.0)
    mse = float(((rgb - view.image.float() / 255.0) ** 2).mean())
    return -10.0 * math.log10(max(mse, 1e-12))


def compare(model: VoxNeRFModel, views: dict, every: int) -> dict:
    """``{split: {"views", "given", "moved"}}``: mean PSNR of every ``every``-th view at each pose."""
    refinement, results = model.pose_refinement, {}
    for split, split_views in views.items():
        chosen = split_views[::every]
        moved = [view_psnr(model, v) for v in chosen]
        model.pose_refinement = None
        try:
            given = [view_psnr(model, v) for v in chosen]
        finally:
            model.pose_refinement = refinement
        results[split] = {"views": len(chosen), "given": sum(given) / len(given), "moved": sum(moved) / len(moved)}
    return results


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("run", type=Path)
    p.add_argument("scene", type=Path)
    p.add_argument("--downscale", type=int, default=1)
    p.add_argument("--every", type=int, default=1, help="score every N-th view of each split")
    p.add_argument("--out", type=Path, help="write the results as JSON")
    args = p.parse_args(argv)
    model = VoxNeRFModel.from_state_dict(load_checkpoint(args.run / CHECKPOINT)["model"], torch.device("cpu"))
    if model.pose_refinement is None:
        print(f"{args.run}: the run did not refine its poses (pose_refinement none)", file=sys.stderr)
        return 2
    scene = scene_as_trained(load_scene(args.scene, downscale=args.downscale), model)
    results = compare(model, eval_views_of(scene, model.transform), args.every)
    for split, r in results.items():
        print(f"{split}: {r['views']} views, PSNR at the given poses {r['given']:.2f} dB, "
              f"at the moved poses {r['moved']:.2f} dB")
    if args.out:
        args.out.write_text(json.dumps({"run": str(args.run), "scene": str(args.scene), "splits": results}, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
