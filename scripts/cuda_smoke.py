"""CUDA smoke check: train and render on a GPU through the same engine code the CPU runs.

Needs a CUDA machine; open3d is not needed there (the scene has no prior, and the octree part builds its
octree from a saved point tensor). Prepare the inputs on any machine, then run on the GPU one:

    python scripts/cuda_smoke.py prepare DIR      # writes DIR/room (no prior) and DIR/prior_points.pt
    python scripts/cuda_smoke.py run DIR          # trains, renders, checks finiteness, prints timings
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import numpy as np
import torch


def prepare(out: Path) -> None:
    from voxnerf.synthetic import RoomSpec, build_room, make_room_scene, sample_point_prior

    make_room_scene(out / "room", RoomSpec(prior_kind="none", n_frames=220))
    points, _ = sample_point_prior(build_room(0), 0.02, 200_000, np.random.default_rng(0))
    torch.save(torch.from_numpy(np.asarray(points, dtype=np.float32)), out / "prior_points.pt")


def run(root: Path) -> None:
    from voxnerf.config import TrainConfig
    from voxnerf.data.scene import load_scene
    from voxnerf.inference.render import load_model, render, render_normalized
    from voxnerf.model.voxnerf_model import VoxNeRFModel
    from voxnerf.prior.octree import SparseVoxelOctree
    from voxnerf.training.run import train

    assert torch.cuda.is_available(), "no CUDA device"
    results: dict = {"device": torch.cuda.get_device_name(0), "torch": torch.__version__}
    for sampler, preset in (("occgrid", "cpu"), ("uniform", "paper")):
        cfg = TrainConfig(sampler=sampler, preset=preset, max_iters=300, device="auto", eval_every_s=1e9)
        report = train(root / "room", root / f"run_{sampler}", cfg, resume=False, progress_bar=False)
        results[f"train_{sampler}_{preset}"] = {
            "device": report.device, "psnr": {k: v["psnr"] for k, v in report.metrics.items()},
            "samples_per_s": report.throughput["samples_per_s"],
        }
        trained = load_model(root / f"run_{sampler}", "cuda")
        scene = load_scene(root / "room", load_images=False)
        t0 = time.perf_counter()
        out = render(trained, scene.frames[0].c2w, None, ("rgb", "depth", "opacity"))
        results[f"render_{sampler}_s"] = time.perf_counter() - t0
        assert all(np.isfinite(v).all() for v in out.values())

    # The VoxNeRF sampler and the octree on CUDA: points -> octree -> render a view of the trained field.
    trained = load_model(root / "run_occgrid", "cuda")
    model = trained.model
    points = torch.load(root / "prior_points.pt").cuda()
    pts_n = (points.double() - torch.tensor(model.transform.center, device="cuda")) * model.transform.scale
    octree = SparseVoxelOctree.from_points(pts_n.float(), 0.02 * model.transform.scale)
    vox = VoxNeRFModel(model.config.updated(sampler="voxnerf"), model.transform, model.aabb,
                       model.field, model.grid, octree)
    scene = load_scene(root / "room", load_images=False)
    c2w = torch.from_numpy(model.transform.c2w_to_normalized(scene.frames[0].c2w)).float()
    t0 = time.perf_counter()
    images = render_normalized(vox, c2w, trained.default_intrinsics, ("rgb", "depth"))
    torch.cuda.synchronize()
    results["voxnerf_sampler_render_s"] = time.perf_counter() - t0
    results["octree"] = octree.summary()
    assert all(bool(torch.isfinite(v).all()) and v.is_cuda for v in images.values())
    print(json.dumps(results, indent=2, default=str))


if __name__ == "__main__":
    command, directory = sys.argv[1], Path(sys.argv[2])
    {"prepare": prepare, "run": run}[command](directory)
