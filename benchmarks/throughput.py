"""Training throughput (samples/s, rays/s) and render time, eager against torch.compile and the hash
encoding in PyTorch against its C kernel (voxnerf/model/hash_kernel.py), side by side.

Runs on one scene (default: the synthetic 160x120 room, generated into a temp dir), alternating the four
configurations in one process so all see the same machine load, and replaces the marked ``throughput``
section of docs/performance.md (``--out`` another page holding the same markers).

    .venv/bin/python benchmarks/throughput.py [--scene DIR] [--downscale N] [--iters 60] [--out docs/performance.md]
        [--section throughput]
"""

from __future__ import annotations

import argparse
import platform
import statistics
import sys
import tempfile
import time
from pathlib import Path

import torch
from docs_section import replace_section

from voxnerf.cameras.rays import Intrinsics
from voxnerf.config import TrainConfig
from voxnerf.inference.render import load_model, render
from voxnerf.model import hash_kernel
from voxnerf.synthetic import RoomSpec, make_room_scene
from voxnerf.training.run import train

PATHS = {  # name: (torch.compile, C kernel)
    "eager, PyTorch encoding": (False, False),
    "eager, C kernel": (False, True),
    "compiled, PyTorch encoding": (True, False),
    "compiled, C kernel (default)": (True, True),
}


def _train_rate(scene: Path, run: Path, compile_step: bool, kernel: bool, iters: int, downscale: int) -> dict:
    cfg = TrainConfig(max_iters=iters, compile=compile_step, hash_kernel=kernel, downscale=downscale, final_eval=False,
                      eval_every_s=1e9)
    report = train(scene, run, cfg, resume=False, progress_bar=False)
    return report.throughput


def _render_seconds(run: Path, compile_render: bool, kernel: bool) -> float:
    """Seconds of one 640x480 render of ``run``'s model, after a warm-up render (which compiles when asked)."""
    trained = load_model(run, "cpu")
    trained.model.config = trained.model.config.updated(compile=compile_render)
    trained.model.field.encoding.use_kernel = kernel
    intr = Intrinsics(525.0, 525.0, 320.0, 240.0, 640, 480)
    c2w = trained.model.transform  # a pose at the scene centre, looking along -Z
    pose = torch.eye(4, dtype=torch.float64).numpy()
    pose[:3, 3] = c2w.center
    render(trained, pose, intr, ("rgb", "depth"))
    t0 = time.perf_counter()
    render(trained, pose, intr, ("rgb", "depth"))
    return time.perf_counter() - t0


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scene", type=Path)
    parser.add_argument("--downscale", type=int, default=1, help="training images downscaled by N")
    parser.add_argument("--iters", type=int, default=60)
    parser.add_argument("--repeats", type=int, default=2, help="alternating rounds per configuration")
    parser.add_argument(
        "--out", type=Path, default=Path("docs/performance.md"), help="page with the section to replace"
    )
    parser.add_argument("--section", default="throughput", help="name of the marked section to replace")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        scene = args.scene or make_room_scene(Path(tmp) / "room", RoomSpec())
        if not hash_kernel.available():
            raise SystemExit(f"the C kernel is unavailable: {hash_kernel.unavailable_reason()}")
        rates: dict[str, list[dict]] = {name: [] for name in PATHS}
        for _ in range(args.repeats):
            for i, (name, (compiled, kernel)) in enumerate(PATHS.items()):
                rates[name].append(_train_rate(scene, Path(tmp) / f"run_{i}", compiled, kernel, args.iters,
                                                args.downscale))
        renders: dict[str, list[float]] = {name: [] for name in PATHS}
        for _ in range(args.repeats):  # alternating, one render per path and round
            for name, (compiled, kernel) in PATHS.items():
                renders[name].append(_render_seconds(Path(tmp) / "run_3", compiled, kernel))
    cfg = TrainConfig().resolved()
    med = {k: statistics.median(r["samples_per_s"] for r in v) for k, v in rates.items()}
    rays = {k: statistics.median(r["rays_per_s"] for r in v) for k, v in rates.items()}
    rend = {k: min(v) for k, v in renders.items()}
    command = " ".join(sys.argv)
    loss = cfg.loss
    patches = (f" + {loss.smooth_patches} patches of {loss.patch_size}x{loss.patch_size}" if loss.smooth_patches
               else " (no smoothness patches)")
    lines = [
        f"Measured {time.strftime('%Y-%m-%d')} on {platform.processor() or platform.machine()}, "
        f"{torch.get_num_threads()} torch threads, torch {torch.__version__}.",
        "",
        f"Command: `.venv/bin/python {command}`",
        "",
        f"Scene: {args.scene or 'the synthetic 160x120 room'}, downscale {args.downscale}. "
        f"Preset `cpu`: {cfg.schedule.rays_per_batch} rays{patches} per step, "
        f"{cfg.sampling.n_importance}+{cfg.sampling.n_rest} samples "
        f"per ray, hash grid "
        f"{cfg.model.hash_levels}x{cfg.model.hash_features}, 2^{cfg.model.hash_log2_size} entries per level. "
        "Training samples/s "
        f"are the training loop's (set-up and the compilation of the first step left out); {args.iters} "
        f"iterations per run, median of {args.repeats} alternating runs.",
        "",
        "| path | training samples/s | training rays/s | 640x480 render (rgb + depth) |",
        "| --- | --- | --- | --- |",
    ]
    for name in PATHS:
        lines.append(f"| {name} | {med[name]:,.0f} | {rays[name]:,.0f} | {rend[name]:.2f} s |")
    default, pytorch, eager = "compiled, C kernel (default)", "compiled, PyTorch encoding", "eager, C kernel"
    lines += [
        "",
        f"Ratios (same run): the C kernel against the PyTorch encoding, both compiled: training "
        f"{med[default] / med[pytorch]:.2f}x, render {rend[pytorch] / rend[default]:.2f}x faster; compiled against "
        f"eager, both with the kernel: training {med[default] / med[eager]:.2f}x, render "
        f"{rend[eager] / rend[default]:.2f}x faster.",
        "",
    ]
    replace_section(args.out, args.section, "\n".join(lines))
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
