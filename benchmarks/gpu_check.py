"""Issue #45's GPU check in one process, on one scene: the training step with the voxnerf sampler's octree misses
gathered (a host sync per batch: the path every device took before) and masked (none), side by side.

1. The step profile (``step_profile.py``) of the ``cpu`` and ``paper`` presets by both paths: each phase's time
   with a device sync after it, and on CUDA the host syncs each phase makes per step.
2. Training throughput of both presets by both paths: each trains ``--train-seconds`` (set-up included, as
   ``max_seconds``) and reports the loop's own rate (no syncs added; compilation left out).
3. Render latency of 320x240 and 640x480 held-out views of each preset's masked run, on the device's default render
   path, in passes of the device's chunk (``config.EVAL_CHUNKS``) and of the CPU's 4,096 rays.

    python3 benchmarks/gpu_check.py SCENE --out DIR [--device auto] [--downscale 2] [--steps 30] [--warm 8]
        [--count-syncs 4] [--train-seconds 30] [--renders 8] [--presets cpu,paper] [--overrides JSON]

``--overrides '{"compile": false}'`` sets TrainConfig fields in every run (a quick dry run on a CPU).

``DIR/gpu_check.json`` is rewritten after every measurement (a run cut short keeps what it finished) and
``DIR/gpu_check.md`` holds the tables. ``scripts/gpu_check.sh`` runs this on a bare GPU machine (docs/cuda.md,
"The GPU check").
"""

from __future__ import annotations

import argparse
import json
import platform
import statistics
import sys
import tempfile
import time
from pathlib import Path

import torch
from step_profile import profile_config

from voxnerf.cameras.rules import resolve_intrinsics
from voxnerf.config import EVAL_CHUNKS, TrainConfig
from voxnerf.data.scene import load_scene
from voxnerf.devices import resolve_device
from voxnerf.inference.render import load_model, render, resolved_render_path
from voxnerf.model.samplers import OCTREE_MISSES
from voxnerf.training.run import train

SIZES = ((320, 240), (640, 480))
CORE_PHASES = ("batch (rays, sampling)", "forward + backward", "optimiser update")  # the rest: callbacks
MIN_STEPS = 10  # fewer steps than this give no rate: the first step, which compiles, is most of such a run


def _rows_of(results: dict, part: str) -> dict:
    return results.setdefault(part, {})


def held_out_poses(scene_dir: Path, count: int) -> list:
    """Up to ``count`` poses (scene units) spread over the scene's evaluation splits."""
    scene = load_scene(scene_dir, load_images=False)
    frames = [i for name in scene.eval_split_names for i in scene.splits[name]]
    if not frames:
        raise SystemExit(f"{scene_dir}: no evaluation views to render")
    step = max(1, len(frames) // max(count, 1))
    return [scene.frames[i].c2w for i in frames[::step][:count]]


def step_profiles(args: argparse.Namespace, work: Path, results: dict, save) -> None:
    rows = _rows_of(results, "step_profile")
    for preset in args.presets:
        for misses in OCTREE_MISSES:
            name = f"{preset}, {misses}"
            rows[name] = profile_config(args.scene, work / f"profile-{preset}-{misses}",
                                        args.overrides | {"preset": preset, "octree_misses": misses}, args.downscale,
                                        args.steps, args.warm, 0, args.device, args.count_syncs)
            rows[name].pop("trace")
            print(f"step profile {name}: {rows[name]['step_ms']:.2f} ms per synced step, host syncs per step "
                  f"{rows[name]['host_syncs_per_step']}", flush=True)
            save()


def throughputs(args: argparse.Namespace, work: Path, results: dict, save) -> dict[str, Path]:
    """Train each preset by each path for ``--train-seconds``; the masked runs' directories by preset."""
    rows, runs = _rows_of(results, "throughput"), {}
    for preset in args.presets:
        for misses in OCTREE_MISSES:
            run_dir = work / f"train-{preset}-{misses}"
            cfg = TrainConfig(**args.overrides | dict(
                preset=preset, octree_misses=misses, max_seconds=args.train_seconds, final_eval=False, eval_every_s=1e9,
                checkpoint_every_s=1e9, downscale=args.downscale, device=args.device))
            report = train(args.scene, run_dir, cfg, resume=False, progress_bar=False)
            t = report.throughput if report.iteration >= MIN_STEPS and report.throughput else {}
            rows[f"{preset}, {misses}"] = {
                "steps": report.iteration, "octree_misses": (report.runtime or {}).get("octree_misses"),
                "rays_per_step": t.get("rays_per_step"), "samples_per_s": t.get("samples_per_s"),
                "rays_per_s": t.get("rays_per_s"), "loop_seconds_excluding_compile": t.get("seconds_excluding_compile"),
                "ms_per_step": 1000 * t["seconds_excluding_compile"] / report.iteration if t and report.iteration
                else None,
                "stages_s": {s.name: round(s.seconds, 2) for s in report.stages}}
            print(f"throughput {preset}, {misses}: {report.iteration} steps, "
                  f"{(t.get('samples_per_s') or 0) / 1e6:.2f} M samples/s", flush=True)
            save()
            if misses == "mask":
                runs[preset] = run_dir
    return runs


def render_latencies(args: argparse.Namespace, runs: dict[str, Path], results: dict, save) -> None:
    rows = _rows_of(results, "render")
    device = resolve_device(args.device)
    poses = held_out_poses(args.scene, args.renders)
    chunks = sorted({EVAL_CHUNKS[device.type], EVAL_CHUNKS["cpu"]}, reverse=True)
    for preset, run_dir in runs.items():
        trained = load_model(run_dir, args.device)
        path = resolved_render_path("auto", trained.model.device)
        for chunk in chunks:
            trained.model.config = trained.model.config.updated(eval_chunk=chunk)
            for width, height in SIZES:
                camera = resolve_intrinsics(trained.default_intrinsics.undistorted(), width=width, height=height)
                started = time.perf_counter()
                render(trained, poses[0], camera, ("rgb",))  # warm: the full path compiles its pass here
                warm_s = time.perf_counter() - started
                seconds = []
                for pose in poses:
                    started = time.perf_counter()
                    render(trained, pose, camera, ("rgb",))  # a numpy image back: the device has finished
                    seconds.append(time.perf_counter() - started)
                name = f"{preset}, {width}x{height}, chunk {chunk}"
                rows[name] = {"path": path, "chunk": chunk, "views": len(seconds), "first_s": warm_s,
                              "median_ms": 1000 * statistics.median(seconds),
                              "mean_ms": 1000 * statistics.fmean(seconds), "max_ms": 1000 * max(seconds)}
                print(f"render {name} ({path} path): median {rows[name]['median_ms']:.1f} ms", flush=True)
                save()


def tables(results: dict) -> str:
    """The markdown tables of what ``results`` holds."""
    lines = [f"GPU check on {results['device']} ({results['device_name']}), torch {results['torch']}, scene "
             f"{results['scene']}, downscale {results['downscale']}.", ""]
    if results.get("step_profile"):
        lines += ["Step profile (a device sync after each phase; ms per step):", "",
                  "| preset, octree misses | batch (rays, sampling) | forward + backward | optimiser | periodic duties "
                  "| step (synced) | host syncs per step |", "| --- | --- | --- | --- | --- | --- | --- |"]
        for name, row in results["step_profile"].items():
            ms, syncs = row["phases_ms"], row["host_syncs_per_step"]
            core = [ms.get(phase, 0.0) for phase in CORE_PHASES]
            sync_text = "-" if syncs is None else ", ".join(f"{k} {v:g}" for k, v in sorted(syncs.items()) if v)
            lines.append(f"| {name} | " + " | ".join(f"{v:.2f}" for v in core) +
                         f" | {row['step_ms'] - sum(core):.2f} | {row['step_ms']:.2f} | {sync_text or 'none'} |")
        lines.append("")
    if results.get("throughput"):
        lines += [f"Training throughput (the loop's own rate, no added syncs, compilation left out; none under "
                  f"{MIN_STEPS} steps):", "",
                  "| preset, octree misses | steps | ms per step | M samples/s | K rays/s |",
                  "| --- | --- | --- | --- | --- |"]
        for name, row in results["throughput"].items():
            if row["ms_per_step"] is None:  # too few steps for a rate
                lines.append(f"| {name} | {row['steps']} | - | - | - |")
                continue
            lines.append(f"| {name} | {row['steps']} | {row['ms_per_step']:.2f} | {row['samples_per_s'] / 1e6:.2f} | "
                         f"{row['rays_per_s'] / 1e3:.1f} |")
        lines.append("")
    if results.get("render"):
        lines += ["Render latency per view (held-out poses, warm; rgb only):", "",
                  "| preset, size, rays per pass | path | median ms | mean ms | max ms | first (compiles) s |",
                  "| --- | --- | --- | --- | --- | --- |"]
        for name, row in results["render"].items():
            lines.append(f"| {name} | {row['path']} | {row['median_ms']:.1f} | {row['mean_ms']:.1f} | "
                         f"{row['max_ms']:.1f} | {row['first_s']:.2f} |")
        lines.append("")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("scene", type=Path)
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--device", default="auto")
    p.add_argument("--downscale", type=int, default=2)
    p.add_argument("--steps", type=int, default=30, help="timed steps per step-profile row")
    p.add_argument("--warm", type=int, default=8, help="steps before the timed ones (compilation)")
    p.add_argument("--count-syncs", type=int, default=4, help="steps whose host syncs are counted (CUDA)")
    p.add_argument("--train-seconds", type=float, default=30.0, help="max_seconds of each throughput run")
    p.add_argument("--renders", type=int, default=8, help="timed views per size and chunk")
    p.add_argument("--presets", type=lambda text: text.split(","), default=["cpu", "paper"])
    p.add_argument("--parts", type=lambda text: text.split(","), default=["profile", "throughput", "render"],
                   help="which of profile, throughput, render to run (render needs throughput's runs)")
    p.add_argument("--overrides", type=json.loads, default={}, help="JSON object of TrainConfig fields for every run")
    args = p.parse_args(argv)
    device = resolve_device(args.device)
    args.out.mkdir(parents=True, exist_ok=True)
    results = {"command": " ".join(sys.argv), "device": str(device), "torch": torch.__version__,
               "device_name": (torch.cuda.get_device_name(device) if device.type == "cuda"
                               else platform.processor() or platform.machine()),
               "scene": str(args.scene), "downscale": args.downscale, "started": time.strftime("%Y-%m-%d %H:%M:%S %Z")}

    def save() -> None:
        (args.out / "gpu_check.json").write_text(json.dumps(results, indent=1, default=str))
        (args.out / "gpu_check.md").write_text(tables(results))

    started = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        if "profile" in args.parts:
            step_profiles(args, work, results, save)
        runs = throughputs(args, work, results, save) if "throughput" in args.parts else {}
        if "render" in args.parts and runs:
            render_latencies(args, runs, results, save)
    results["seconds"] = time.perf_counter() - started
    save()
    print(tables(results))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
