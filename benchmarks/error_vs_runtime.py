"""Error against run time: train several configurations on one scene under the same wall-clock budget.

Each configuration is one `voxnerf train` command (run one after the other, never concurrently, so each
has the whole CPU), with full evaluations of every split at fixed training times (``--eval-at``). Writes
a CSV of every evaluation, a markdown table (PSNR/SSIM per split at each time, time-to-PSNR ratios) and,
when matplotlib is installed, a PNG plot, all under ``--out``.

    .venv/bin/python benchmarks/error_vs_runtime.py --scene room --budget 600 --eval-at 120,300,600 \
        --configs voxnerf,occgrid,uniform --out docs/bench/room
    .venv/bin/python benchmarks/error_vs_runtime.py --quick --out /tmp/quick    # CI-sized smoke run

``--scene room`` generates the synthetic 160x120 room (18 training views) into the output directory.
"""

from __future__ import annotations

import argparse
import csv
import json
import shlex
import subprocess
import sys
import time
from pathlib import Path

# name -> extra CLI flags of `voxnerf train`
CONFIGS: dict[str, list[str]] = {
    "voxnerf": ["--sampler", "voxnerf"],
    "voxnerf-no-depth": ["--sampler", "voxnerf", "--no-depth-loss"],
    "occgrid": ["--sampler", "occgrid", "--no-depth-loss"],
    "uniform": ["--sampler", "uniform", "--no-depth-loss"],
}


def _voxnerf() -> list[str]:
    return [sys.executable, "-m", "voxnerf"]


def make_scene(kind: str, out: Path, quick: bool) -> Path:
    """``room``: the synthetic room (generated once into ``out/scene``); anything else: a scene directory."""
    if kind != "room":
        return Path(kind)
    scene = out / "scene"
    if not (scene / "transforms.json").is_file():
        # 220 frames: 18 training views (every 10th frame, minus two gaps), 15 interpolation, 6 extrapolation.
        args = ["synth", str(scene), "--frames", "220"]
        if quick:
            args = ["synth", str(scene), "--width", "64", "--height", "48", "--frames", "120"]
        subprocess.run(_voxnerf() + args, check=True)
    return scene


def run_config(name: str, scene: Path, out: Path, budget: float, eval_at: list[float], extra: list[str]) -> dict:
    run = out / "runs" / name
    cmd = _voxnerf() + ["train", str(scene), "--out", str(run), "--max-seconds", str(budget), "--restart",
                        "--eval-at", ",".join(str(t) for t in eval_at)] + CONFIGS[name] + extra
    t0 = time.perf_counter()
    subprocess.run(cmd, check=True, stderr=subprocess.DEVNULL)
    wall = time.perf_counter() - t0
    report = json.loads((run / "report.json").read_text())
    printable = "voxnerf " + " ".join(shlex.quote(c) for c in cmd[3:])
    return {"name": name, "command": printable, "wall_s": wall, "report": report}


def evaluations(result: dict) -> list[dict]:
    """The full evaluations of a run (``--eval-at`` times and the final one) as flat rows."""
    rows = []
    for entry in result["report"]["history"]:
        if not (entry.get("full") or entry.get("final")):
            continue
        for split, value in entry["psnr"].items():
            ssim = (entry.get("ssim") or {}).get(split)
            if entry.get("final"):
                ssim = result["report"]["metrics"][split]["ssim"]
            rows.append({"config": result["name"], "elapsed_s": entry["elapsed_s"], "iteration": entry["iteration"],
                         "split": split, "psnr": value, "ssim": ssim, "final": bool(entry.get("final"))})
    return rows


def progress_curve(result: dict, split: str) -> list[tuple[float, float]]:
    return [(e["elapsed_s"], e["psnr"][split]) for e in result["report"]["history"] if split in e["psnr"]]


def time_to_psnr(curve: list[tuple[float, float]], target: float) -> float | None:
    """First training time at which the curve reaches ``target`` dB (linear interpolation), or None."""
    for (t0, p0), (t1, p1) in zip(curve, curve[1:], strict=False):
        if p0 >= target:
            return t0
        if p1 >= target:
            return t0 + (t1 - t0) * (target - p0) / (p1 - p0)
    return curve[0][0] if curve and curve[0][1] >= target else None


def write_outputs(results: list[dict], out: Path, eval_at: list[float]) -> str:
    rows = [r for res in results for r in evaluations(res)]
    with (out / "evaluations.csv").open("w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(rows[0]) if rows else ["config"])
        writer.writeheader()
        writer.writerows(rows)
    splits = [s for s in ("interpolation", "extrapolation", "test") if any(r["split"] == s for r in rows)][:2]
    lines = ["| config | " + " | ".join(f"{s} @ {t:g} s" for s in splits for t in eval_at) + " | samples/s |",
             "| --- " * (1 + len(splits) * len(eval_at) + 1) + "|"]
    for res in results:
        cells = []
        for split in splits:
            for t in eval_at:
                match = [r for r in rows if r["config"] == res["name"] and r["split"] == split
                         and not r["final"] and abs(r["elapsed_s"] - t) < max(5.0, 0.1 * t)]
                if not match:  # the final evaluation stands in for the last time point
                    match = [r for r in rows if r["config"] == res["name"] and r["split"] == split and r["final"]
                             and t == eval_at[-1]]
                cells.append(f"{match[0]['psnr']:.2f} / {match[0]['ssim']:.3f}" if match and match[0]["ssim"]
                             is not None else (f"{match[0]['psnr']:.2f}" if match else "-"))
        rate = res["report"].get("throughput", {}).get("samples_per_s", 0.0)
        lines.append(f"| {res['name']} | " + " | ".join(cells) + f" | {rate:,.0f} |")
    lines += ["", "PSNR dB / SSIM at each training time (training seconds: wall clock of the command minus "
              "progress evaluations, set-up included).", ""]
    base = {r["name"]: r for r in results}
    if "voxnerf" in base:
        for split in splits:
            target = max(p for _, p in progress_curve(base["voxnerf"], split)) - 1.0
            parts = []
            for name, res in base.items():
                t = time_to_psnr(progress_curve(res, split), target)
                parts.append(f"{name}: {'not reached' if t is None else f'{t:.0f} s'}")
            lines.append(f"Time to {target:.1f} dB {split} (voxnerf's best minus 1 dB): " + ", ".join(parts) + ".")
    lines += ["", "Commands:", ""] + [f"    {res['command']}" for res in results]
    table = "\n".join(lines)
    (out / "table.md").write_text(table + "\n")
    _plot(results, splits, out / "psnr_vs_time.png")
    return table


def _plot(results: list[dict], splits: list[str], path: Path) -> None:
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        print("matplotlib not installed: no plot", file=sys.stderr)
        return
    fig, axes = plt.subplots(1, len(splits), figsize=(6 * len(splits), 4), squeeze=False)
    for ax, split in zip(axes[0], splits, strict=True):
        for res in results:
            curve = progress_curve(res, split)
            ax.plot([t for t, _ in curve], [p for _, p in curve], marker=".", label=res["name"])
        ax.set_title(split)
        ax.set_xlabel("training seconds")
        ax.set_ylabel("PSNR (dB)")
        ax.grid(alpha=0.3)
        ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=100)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scene", default="room", help="'room' (synthetic) or a scene directory")
    parser.add_argument("--budget", type=float, default=600.0, help="--max-seconds of every run")
    parser.add_argument("--eval-at", default="120,300,600")
    parser.add_argument("--configs", default="voxnerf,occgrid,uniform")
    parser.add_argument("--train-args", default="", help="extra `voxnerf train` flags, e.g. '--downscale 2'")
    parser.add_argument("--quick", action="store_true", help="tiny scene, 40 s budget: a smoke test")
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args(argv)
    if args.quick:
        args.budget, args.eval_at = 45.0, "15,30"
    eval_at = [float(t) for t in args.eval_at.split(",") if t]
    args.out.mkdir(parents=True, exist_ok=True)
    scene = make_scene(args.scene, args.out, args.quick)
    extra = shlex.split(args.train_args) + (["--no-compile"] if args.quick else [])
    results = [run_config(name, scene, args.out, args.budget, eval_at, extra) for name in args.configs.split(",")]
    (args.out / "results.json").write_text(json.dumps(
        [{k: v for k, v in r.items() if k != "report"} | {"history": r["report"]["history"],
                                                          "metrics": r["report"].get("metrics")}
         for r in results], indent=2))
    print(write_outputs(results, args.out, eval_at))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
