"""How solid and how complete each trained run's geometry is, against a synthetic room's true mesh.

For every configuration's run of one room (as `benchmarks/suite.py` leaves them under ``RUNS/<scene>/<config>``):

- **residual on seen rays**: the mean transmittance left after the field (1 - opacity) on the interpolation views.
  Every such ray ends on a wall, so anything above zero is a translucent surface that the background shows
  through (and that the background colour then tints);
- **mesh accuracy / completeness**: the run's mesh as ``voxnerf export --mesh`` makes it (``--voxel-size``),
  accuracy as its vertices' distance to the true mesh, completeness as the distance from the surface the
  training views saw (their depth maps back-projected) to the exported mesh; mean and 90th percentile, cm.

    .venv/bin/python benchmarks/suite_geometry.py --runs OUT/runs --scene studio --scene-dir SCENES/studio \\
        --configs defaults,random-bg-mean --out OUT/geometry-studio.md
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

import numpy as np
import torch
import trimesh
from suite import measure_runs, print_table

from voxnerf.data.scene import load_scene
from voxnerf.inference.export import distances_to_mesh, export_geometry
from voxnerf.inference.render import load_model, render_normalized, scene_as_trained
from voxnerf.prior.depth_fusion import DepthView, backproject
from voxnerf.training.eval_passes import eval_views_of

SEEN_SPLIT = "interpolation"


@torch.no_grad()
def seen_residual(trained, scene, max_views: int) -> float:
    """Mean 1 - opacity over every pixel of the first ``max_views`` interpolation views."""
    views = eval_views_of(scene, trained.model.transform, [SEEN_SPLIT])[SEEN_SPLIT][:max_views]
    residuals = [1.0 - render_normalized(trained.model, v.c2w, v.intrinsics, ("opacity",))["opacity"].mean()
                 for v in views]
    return float(torch.stack(residuals).mean())


def seen_surface(scene, stride: int) -> np.ndarray:
    """[N, 3] the training views' depth maps back-projected (scene units), every ``stride``-th pixel."""
    return np.concatenate([backproject(DepthView(scene.depths[i], scene.intrinsics(i), scene.frames[i].c2w), stride)
                           for i in scene.train_indices])


def geometry(run: Path, scene_dir: Path, voxel: float, max_views: int) -> dict[str, float]:
    trained = load_model(run, "cpu")
    scene = scene_as_trained(load_scene(scene_dir, downscale=int(trained.model.config.run.downscale)), trained.model)
    truth = trimesh.load(scene_dir / "gt_mesh.ply", process=False)
    with tempfile.TemporaryDirectory() as tmp:
        export_geometry(trained, Path(tmp) / "mesh.ply", "mesh", scene=scene, voxel_size=voxel)
        mesh = trimesh.load(Path(tmp) / "mesh.ply", process=False)
    accuracy = distances_to_mesh(np.asarray(mesh.vertices), truth) * 100
    completeness = distances_to_mesh(seen_surface(scene, 4), mesh) * 100
    return {"residual on seen rays": seen_residual(trained, scene, max_views),
            "accuracy mean (cm)": float(accuracy.mean()), "accuracy p90 (cm)": float(np.percentile(accuracy, 90)),
            "completeness mean (cm)": float(completeness.mean()),
            "completeness p90 (cm)": float(np.percentile(completeness, 90))}


def table(scene: str, rows: list[tuple[str, dict[str, float]]]) -> str:
    keys = list(rows[0][1])
    head = f"**{scene}**: geometry of each run (residual: mean 1 - opacity on the {SEEN_SPLIT} views)\n\n"
    return (head + f"| config | {' | '.join(keys)} |\n| --- |" + " --- |" * len(keys) + "\n"
            + "\n".join(f"| {c} | " + " | ".join(f"{r[k]:.3f}" if "residual" in k else f"{r[k]:.2f}" for k in keys)
                        + " |" for c, r in rows))


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--runs", type=Path, required=True)
    p.add_argument("--scene", required=True)
    p.add_argument("--scene-dir", type=Path, required=True, help="the room (with its gt_mesh.ply)")
    p.add_argument("--configs", default="defaults")
    p.add_argument("--voxel-size", type=float, default=0.02, help="the export's voxel (scene units)")
    p.add_argument("--max-views", type=int, default=5, help="interpolation views for the residual")
    p.add_argument("--out", type=Path)
    args = p.parse_args(argv)
    if not (args.scene_dir / "gt_mesh.ply").is_file():
        print(f"{args.scene_dir / 'gt_mesh.ply'}: no true mesh (only synthetic rooms have one)", file=sys.stderr)
        return 2
    rows = measure_runs(args.runs, args.scene, args.configs,
                        lambda run: geometry(run, args.scene_dir, args.voxel_size, args.max_views))
    return print_table(table(args.scene, rows), args.out) if rows else 1


if __name__ == "__main__":
    sys.exit(main())
