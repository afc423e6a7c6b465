"""Where each trained run's sampler puts its samples on held-out views, against the true surface.

For every configuration's run of one scene (as `benchmarks/suite.py` leaves them under ``RUNS/<scene>/<config>``),
rebuild the sampler the run trained with, as the run left it (the voxnerf sampler's octree window, or the
occupancy grid after training: seeded from the prior or learnt from density alone), sample every ray of the
split's views without jitter, and compare each sample's midpoint with the true surface along its ray (the
view's depth map). Prints and writes (``--out``) a table: per configuration, the share of samples within
2 / 5 / 10 cm of the surface (in scene units x 100, i.e. centimetres for scenes in metres), the share of rays
with at least one sample within 5 cm, and the median distance of a ray's closest sample; for the voxnerf
sampler also the share of rays that stop short (their octree first hit more than the importance window before
the true surface, so the importance samples miss it), the share of rays that pass it (no first hit, or one more
than the window beyond the surface: the octree lacks the leaves there, as where carving removed a true surface),
and each group's share of the squared colour error of the run's own render (the fast path).

    .venv/bin/python benchmarks/sample_placement.py --runs OUT/runs --scene studio --scene-dir SCENES/studio \\
        --configs defaults,occgrid-seeded,occgrid-density --split extrapolation --out OUT/placement-studio.md
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import torch
from suite import measure_runs, print_table

from voxnerf.cameras.rays import image_rays
from voxnerf.data.scene import depth_on_image, load_scene
from voxnerf.inference.render import load_model, render_normalized, scene_as_trained
from voxnerf.model.samplers import VoxNeRFSampler
from voxnerf.training.eval_passes import eval_views_of

BANDS_M = (0.02, 0.05, 0.10)


def true_ray_distance(scene, index: int) -> np.ndarray:
    """[H * W] z-depth (scene units) of frame ``index`` on its image's pixels at the scene's downscale (registered
    through the depth camera, as training registers it), NaN where invalid."""
    return depth_on_image(scene.frames[index], scene.depth_unit_scale, scene.downscale, scene.depth_max).reshape(-1)


@torch.no_grad()
def placement(run: Path, scene_dir: Path, split: str, downscale: int, max_views: int) -> dict[str, float]:
    """Shares of samples / rays near the true surface for the run's own sampler on ``split``'s views."""
    trained = load_model(run, "cpu")
    model = trained.model
    scene = scene_as_trained(load_scene(scene_dir, downscale=downscale), trained.model)
    views = eval_views_of(scene, model.transform, [split])[split][:max_views]
    indices = scene.splits[split][:max_views]
    sampler = model.sampler()
    near_counts = {band: 0 for band in BANDS_M}
    n_samples = rays_near = n_rays = n_short = n_past = 0
    closest_all, error, short_error, past_error = [], 0.0, 0.0, 0.0
    for view, index in zip(views, indices, strict=True):
        origins, dirs, z_per_t = image_rays(view.c2w, view.intrinsics)
        z_true = torch.from_numpy(true_ray_distance(scene, index))
        t_true = z_true.float() * model.transform.scale / z_per_t  # normalised ray distance
        ok = torch.isfinite(t_true)
        rays = model.ray_bundle(origins[ok], dirs[ok])
        starts, ends = sampler(rays, False)
        if isinstance(sampler, VoxNeRFSampler):
            z, hit = sampler.first_hits(rays)
            short = hit & (z < t_true[ok] - sampler.half_window)
            past = ~hit | (z > t_true[ok] + sampler.half_window)
            rgb = render_normalized(model, view.c2w, view.intrinsics, ("rgb",))["rgb"].clamp(0, 1).reshape(-1, 3)
            squared = ((rgb - view.image.float().reshape(-1, 3) / 255.0) ** 2).mean(-1)[ok]
            n_short, n_past = n_short + int(short.sum()), n_past + int(past.sum())
            error += float(squared.sum())
            short_error += float(squared[short].sum())
            past_error += float(squared[past].sum())
        distance_m = (0.5 * (starts + ends) - t_true[ok][:, None]).abs() / model.transform.scale
        for band in BANDS_M:
            near_counts[band] += int((distance_m <= band).sum())
        closest = distance_m.min(dim=1).values
        closest_all.append(closest)
        rays_near += int((closest <= 0.05).sum())
        n_samples += distance_m.numel()
        n_rays += len(closest)
    result = {f"within {band * 100:g} cm": near_counts[band] / n_samples for band in BANDS_M}
    result["rays with a sample within 5 cm"] = rays_near / n_rays
    result["median closest sample (cm)"] = float(torch.cat(closest_all).median()) * 100
    voxnerf = isinstance(sampler, VoxNeRFSampler)
    result["rays stopping short"] = n_short / n_rays if voxnerf else None
    result["their share of the colour error"] = short_error / error if voxnerf and error > 0 else None
    result["rays passing their surface"] = n_past / n_rays if voxnerf else None
    result["their share of the error"] = past_error / error if voxnerf and error > 0 else None
    return result


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--runs", type=Path, required=True)
    p.add_argument("--scene", required=True)
    p.add_argument("--scene-dir", type=Path, required=True)
    p.add_argument("--configs", default="defaults,occgrid-seeded,occgrid-density")
    p.add_argument("--split", default="extrapolation")
    p.add_argument("--downscale", type=int, default=1)
    p.add_argument("--max-views", type=int, default=10)
    p.add_argument("--out", type=Path)
    args = p.parse_args(argv)
    rows = measure_runs(args.runs, args.scene, args.configs,
                        lambda run: placement(run, args.scene_dir, args.split, args.downscale, args.max_views))
    if not rows:
        return 1
    keys = list(rows[0][1])
    text = (f"**{args.scene}, {args.split} views**: samples of each run's own sampler against the true surface\n\n"
            f"| config | {' | '.join(keys)} |\n| --- |" + " --- |" * len(keys) + "\n"
            + "\n".join(f"| {c} | " + " | ".join(_cell(k, r[k]) for k in keys) + " |" for c, r in rows))
    return print_table(text, args.out)


def _cell(key: str, value: float | None) -> str:
    if value is None:
        return "-"
    return f"{value:.1f}" if "cm)" in key else f"{value:.1%}"


if __name__ == "__main__":
    sys.exit(main())
