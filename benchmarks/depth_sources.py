"""Where the prior and the depth supervision come from, side by side on one scene (issue #19's comparison).

Four runs of the same budget on the same images, one after another in one process tree:

- ``a_prior_file``: the scene's own prior file, the depth loss against the prior's depth (``--depth-source prior``);
- ``b_fused_prior``: no prior file: the engine fuses the training frames' depth maps into a TSDF prior, and the
  depth loss uses that prior's depth (``--depth-source prior``);
- ``c_fused_prior_sensor``: (b) with the sensor's depth as the depth loss's target where it is valid
  (``--depth-source sensor``);
- ``d_plain``: no prior file and no depth maps: the plain NeRF fallback (occupancy grid, no depth loss).

The variants are written as transforms.json files in a temporary folder whose images, depth maps and prior are
hard links to the scene's files (copies only where the temporary folder is on another filesystem; the scene
loader refuses symbolic links that lead outside a scene). Results (PSNR, SSIM, LPIPS per evaluation split, steps
and what each run's report says about its prior and depth) go to a JSON file and a markdown table.

    python benchmarks/depth_sources.py SCENE --seconds 300 --downscale 2 --out /tmp/depth_sources

A synthetic room with depth maps: ``voxnerf synth ROOM --prior points`` first (its prior.ply is variant a's).
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

VARIANTS = {
    "a_prior_file": {"prior": True, "depth": True, "flags": ["--depth-source", "prior"]},
    "b_fused_prior": {"prior": False, "depth": True, "flags": ["--depth-source", "prior"]},
    "c_fused_prior_sensor": {"prior": False, "depth": True, "flags": ["--depth-source", "sensor"]},
    "d_plain": {"prior": False, "depth": False, "flags": []},
}
PRIOR_KEYS = ("prior_file_path", "ply_file_path", "prior_sigma")


def variant_scene(scene: Path, out: Path, prior: bool, depth: bool) -> Path:
    """A scene folder at ``out`` with links to ``scene``'s files and a transforms.json keeping or dropping the
    prior keys and the frames' depth paths."""
    out.mkdir(parents=True)
    meta = json.loads((scene / "transforms.json").read_text())
    for entry in scene.rglob("*"):
        if not entry.is_file() or entry.name == "transforms.json" or (not prior and entry.suffix == ".ply"):
            continue
        target = out / entry.relative_to(scene)
        target.parent.mkdir(parents=True, exist_ok=True)
        try:
            os.link(entry, target)  # the loader refuses links that lead outside the scene; hard links are files
        except OSError:  # another filesystem
            shutil.copy2(entry, target)
    if not prior:
        for key in PRIOR_KEYS:
            meta.pop(key, None)
    if not depth:
        for frame in meta["frames"]:
            frame.pop("depth_file_path", None)
    (out / "transforms.json").write_text(json.dumps(meta))
    return out


def run_variant(scene: Path, run: Path, seconds: float, downscale: int, flags: list[str]) -> dict:
    """One ``voxnerf train`` of ``scene`` in a subprocess, and what its report says."""
    cmd = [sys.executable, "-m", "voxnerf", "train", str(scene), "--out", str(run), "--max-seconds", str(seconds),
           "--downscale", str(downscale), "--restart", *flags]
    started = time.perf_counter()
    subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    report = json.loads((run / "report.json").read_text())
    stages = {s["name"]: s["why"] for s in report["stages"]}
    return {
        "command": " ".join(cmd[1:]),
        "wall_s": time.perf_counter() - started,
        "iterations": report["iteration"],
        "train_s": report["train_seconds"],
        "report_wall_s": report["wall_seconds"],
        "metrics": {split: {k: m.get(k) for k in ("psnr", "ssim", "lpips")} for split, m in report["metrics"].items()},
        "prior": stages.get("prior"),
        "depth_target": stages.get("depth_target"),
        "setup_s": sum(s["seconds"] for s in report["stages"] if s["name"] not in ("train", "final_eval")),
    }


def table(results: dict[str, dict]) -> str:
    splits = sorted({split for r in results.values() for split in r["metrics"]})
    header = ["variant", "steps"] + [f"{s} {m}" for s in splits for m in ("PSNR", "SSIM", "LPIPS")]
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    for name, r in results.items():
        cells = [name, str(r["iterations"])]
        for s in splits:
            m = r["metrics"].get(s, {})
            cells += [f"{m.get('psnr', float('nan')):.2f}", f"{m.get('ssim', float('nan')):.4f}",
                      f"{m['lpips']:.4f}" if m.get("lpips") is not None else "n/a"]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("scene", type=Path)
    parser.add_argument("--seconds", type=float, default=300.0)
    parser.add_argument("--downscale", type=int, default=2)
    parser.add_argument("--out", type=Path, required=True, help="results folder (results.json, table.md)")
    parser.add_argument("--variants", default=",".join(VARIANTS))
    parser.add_argument("--train-args", default="", help="more `voxnerf train` options for every run (quick tests: "
                        "'--no-compile --max-iters 5')")
    args = parser.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    results = {}
    with tempfile.TemporaryDirectory() as tmp:
        for name in args.variants.split(","):
            spec = VARIANTS[name]
            scene = variant_scene(args.scene.resolve(), Path(tmp) / name, spec["prior"], spec["depth"])
            results[name] = run_variant(scene, Path(tmp) / f"run_{name}", args.seconds, args.downscale,
                                        spec["flags"] + args.train_args.split())
            print(name, json.dumps(results[name]["metrics"]), flush=True)
    command = "python benchmarks/depth_sources.py " + " ".join(argv if argv is not None else sys.argv[1:])
    (args.out / "results.json").write_text(json.dumps({"command": command, "results": results}, indent=2))
    (args.out / "table.md").write_text(f"`{command}`\n\n{table(results)}\n")
    print(table(results))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
