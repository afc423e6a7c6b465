"""Training throughput and render time of two source trees of VoxNeRF side by side (e.g. before and after a
refactoring that must not cost speed).

Each measurement runs in its own process with ``PYTHONPATH`` set to one tree; the trees alternate in an
ABBA order (before first in even rounds, after first in odd ones), so both see the same machine load and
drift. Every run renders the same checkpoint (the first run's), so the render column compares the render code,
not models whose weights differ run to run. Default path only (compiled step, the C kernel where it builds).
Prints the medians and their ratios and, with ``--out``, replaces the marked section of a docs page.

    .venv/bin/python benchmarks/compare_trees.py --before /tmp/before --after . [--scene DIR] [--downscale N]
        [--iters 200] [--rounds 3] [--out docs/performance.md --section refactor-ab]
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from docs_section import replace_section

# Runs inside the measured tree: train, then time three renders (rgb + depth; 640x480 unless told) of the run
# ``render_run`` (every measurement renders the same checkpoint, the first run's, so the render column compares the
# render code, not the models, whose weights differ run to run) after a warm-up render, and keep their median.
CHILD = r"""
import json, sys, time
import numpy as np
from voxnerf.config import TrainConfig
from voxnerf.trainer import train
try:
    from voxnerf.cameras.rays import Intrinsics
    from voxnerf.inference.render import load_model, render
except ImportError:  # a tree from before the engine's packages (0.1, flat modules)
    from voxnerf.cameras import Intrinsics
    from voxnerf.render import load_model, render
scene, run, iters, downscale, render_run = sys.argv[1], sys.argv[2], int(sys.argv[3]), int(sys.argv[4]), sys.argv[5]
width, height = int(sys.argv[6]), int(sys.argv[7])
cfg = TrainConfig(max_iters=iters, downscale=downscale, final_eval=False, eval_every_s=1e9)
report = train(scene, run, cfg, resume=False, progress_bar=False)
report = report if isinstance(report, dict) else report.to_json_dict()
trained = load_model(render_run, "cpu")
pose = np.eye(4)
pose[:3, 3] = trained.model.transform.center
intr = Intrinsics(525.0 * width / 640, 525.0 * width / 640, width / 2, height / 2, width, height)
render(trained, pose, intr, ("rgb", "depth"))
seconds = []
for _ in range(3):
    t0 = time.perf_counter()
    render(trained, pose, intr, ("rgb", "depth"))
    seconds.append(time.perf_counter() - t0)
print(json.dumps({"samples_per_s": report["throughput"]["samples_per_s"], "render_s": sorted(seconds)[1]}))
"""


def measure(tree: Path, scene: Path, run: Path, iters: int, downscale: int, render_run: Path | None = None,
            render_size: tuple[int, int] = (640, 480)) -> dict:
    """Train ``iters`` steps in ``tree`` into ``run``, then time renders of ``render_run`` (default: ``run``) at
    ``render_size`` (width, height; the table's column is 640x480)."""
    env = {**os.environ, "PYTHONPATH": str(tree.resolve())}
    out = subprocess.run([sys.executable, "-c", CHILD, str(scene), str(run), str(iters), str(downscale),
                          str(render_run or run), *map(str, render_size)],
                         env=env, cwd=tree, capture_output=True, text=True)
    if out.returncode != 0:
        raise SystemExit(f"{tree}: measurement failed:\n{out.stderr[-3000:]}")
    return json.loads(out.stdout.strip().splitlines()[-1])


def table(results: dict[str, list[dict]], args: argparse.Namespace) -> list[str]:
    med = {name: {k: statistics.median(r[k] for r in rs) for k in ("samples_per_s", "render_s")}
           for name, rs in results.items()}
    before, after = med["before"], med["after"]
    lines = [
        f"Measured {time.strftime('%Y-%m-%d')}; command: `.venv/bin/python {' '.join(sys.argv)}`",
        "",
        f"Scene: {args.scene or 'the synthetic 160x120 room'}, downscale {args.downscale}, default config "
        f"(compiled step, C kernel), {args.iters} iterations per run; medians of {args.rounds} rounds in ABBA "
        "order, each run in its own process; a run's render time is the median of three renders of one checkpoint, "
        "the first run's, the same for every run (the renders compare the code, not the models).",
        "",
        "| tree | training samples/s | 640x480 render (rgb + depth) | runs (samples/s) |",
        "| --- | --- | --- | --- |",
    ]
    for name, tree in (("before", args.before), ("after", args.after)):
        runs = ", ".join(f"{r['samples_per_s']:,.0f}" for r in results[name])
        lines.append(f"| {name} (`{tree}`) | {med[name]['samples_per_s']:,.0f} | {med[name]['render_s']:.3f} s | "
                     f"{runs} |")
    lines += ["", f"Ratios after / before: training samples/s {after['samples_per_s'] / before['samples_per_s']:.3f}, "
              f"render time {after['render_s'] / before['render_s']:.3f}.", ""]
    return lines


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--before", type=Path, required=True, help="source tree measured first in each round")
    parser.add_argument("--after", type=Path, required=True)
    parser.add_argument("--scene", type=Path)
    parser.add_argument("--downscale", type=int, default=1)
    parser.add_argument("--iters", type=int, default=200)
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--out", type=Path, help="docs page whose marked section to replace")
    parser.add_argument("--section", default="refactor-ab")
    args = parser.parse_args()
    results: dict[str, list[dict]] = {"before": [], "after": []}
    with tempfile.TemporaryDirectory() as tmp:
        scene = args.scene
        if scene is None:
            from voxnerf.synthetic import RoomSpec, make_room_scene

            scene = make_room_scene(Path(tmp) / "room", RoomSpec())
        order = (("before", args.before), ("after", args.after))
        runs = [(name, tree, Path(tmp) / f"{name}_{i}") for i in range(args.rounds)
                for name, tree in (order if i % 2 == 0 else order[::-1])]
        reference = runs[0][2]  # the first run: the checkpoint every measurement renders
        for name, tree, run in runs:
            results[name].append(measure(tree, Path(scene).resolve(), run, args.iters, args.downscale, reference))
            print(name, results[name][-1], flush=True)
    lines = table(results, args)
    if args.out:
        replace_section(args.out, args.section, "\n".join(lines))
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
