"""The tuning suite: configurations of the trainer on every scene of the suite, side by side, one run at a time.

The suite is the synthetic rooms of :mod:`voxnerf.synthetic.suite` (varied layouts, sizes, fields of view,
lighting and priors, some rendered like captures) plus, with ``--redkitchen``, the real 7-Scenes kitchen at
``--downscale 2`` (``--scenes redkitchen`` runs it alone). Every (scene, configuration) pair is one ``voxnerf
train`` command with ``--max-seconds BUDGET`` (set-up, compilation and the final evaluation included), run alone,
one after the other, scene by scene: a scene's configurations run back to back, so the runs compared on a scene
are minutes apart on a machine whose speed drifts over hours. A run whose report already holds the same command
is reused, so rows can be added over several invocations and the table always covers every run under
``--out``.

Each run's report gives, for every evaluation split: PSNR / SSIM / LPIPS over all views, and the same by the
half-image protocol (a colour gain and bias per channel fitted on each view's left half, scored on its right:
the honest score for runs that learn per-image exposure). ``--eval-at`` adds full evaluations inside the run
(their time is not charged to the budget); note that a schedule over the budget (``lr_schedule=budget``) is
mid-way at such a point, so only the final evaluation is what a run of that length gives.

Writes under ``--out``: ``runs/<scene>/<config>/`` (the runs), ``results.json`` and ``table.md`` (per
configuration: the suite's mean and its worst scene against ``defaults``, then every scene), ``suite.png``
(PSNR change against ``defaults`` per scene; needs matplotlib, the ``bench`` extra), and with ``--write-docs``
the table into docs/benchmarks.md.

    .venv/bin/python benchmarks/suite.py --out OUT --budget 120 --redkitchen ../shared/data/redkitchen \\
        --configs defaults,lr-budget,distortion
    .venv/bin/python benchmarks/suite.py --quick --out /tmp/suite-quick    # CI-sized smoke run
"""

from __future__ import annotations

import argparse
import json
import math
import shlex
import subprocess
import sys
import time
from pathlib import Path

from docs_section import publish
from error_vs_runtime import QUICK_TRAIN_ARGS, train_command

from voxnerf.data.image_io import write_atomic

DOCS_PAGE = Path(__file__).resolve().parent.parent / "docs" / "benchmarks.md"
DOCS_SECTION = "suite"
REDKITCHEN = "redkitchen"
REDKITCHEN_DOWNSCALE = 2
NOISE_DB = 0.3
"""A per-scene change smaller than this is read as noise (the issue's bar for "loses")."""

def _corrections(appearance: bool, pose_lr: float, pose_every: int, lambda_pose: float | None = None) -> dict:
    """The real-scan corrections' fields: pose refinement at ``pose_lr`` on every ``pose_every``-th step
    (regularised by ``lambda_pose`` when given), with per-image appearance or without."""
    fields = {"appearance": "affine" if appearance else "none"}
    fields |= {"pose_refinement": "so3xr3", "pose_lr": pose_lr, "pose_every": pose_every}
    return fields if lambda_pose is None else fields | {"lambda_pose": lambda_pose}


# The defaults before appearance and pose refinement became "auto" (on for a captured scan): neither learnt.
NO_CORRECTIONS = {"appearance": "none", "pose_refinement": "none"}
# The defaults before field_weight_decay became "auto" (a decay in proportion to the training images' noise).
NO_DECAY = {"field_weight_decay": 0.0}
# The defaults before focal_scale became "auto" (a captured scan's colour focal length checked against its prior).
STATED_FOCAL = {"focal_scale": 1.0}

CONFIGS: dict[str, dict] = {
    "defaults": {},
    "lr-budget": {"lr_schedule": "budget", "lr_final": 0.1},
    "distortion": {"distortion_weight": 0.01},
    "coarse-to-fine": {"coarse_to_fine": 0.3},
    "sh-2": {"sh_bands": 2},
    "sh-1": {"sh_bands": 1},
    "depth-decay": {"depth_weight_final": 0.1},
    "appearance": {"appearance": "affine", "pose_refinement": "none"},
    "pose-refine": _corrections(appearance=False, pose_lr=6e-4, pose_every=1),
    "pose-refine-slow": _corrections(appearance=False, pose_lr=1e-4, pose_every=1),
    "appearance-pose": _corrections(appearance=True, pose_lr=1e-4, pose_every=1),
    "pose-refine-every4-lr8": _corrections(appearance=False, pose_lr=8e-4, pose_every=4),
    "appearance-pose-every4": _corrections(appearance=True, pose_lr=1e-4, pose_every=4),
    "appearance-pose-every4-lr2": _corrections(appearance=True, pose_lr=2e-4, pose_every=4),
    "appearance-pose-every4-lr4": _corrections(appearance=True, pose_lr=4e-4, pose_every=4),
    "appearance-pose-every4-lr8": _corrections(appearance=True, pose_lr=8e-4, pose_every=4),
    "appearance-pose-every4-lr16": _corrections(appearance=True, pose_lr=1.6e-3, pose_every=4),
    "appearance-pose-every2-lr8": _corrections(appearance=True, pose_lr=8e-4, pose_every=2),
    "appearance-pose-every8-lr8": _corrections(appearance=True, pose_lr=8e-4, pose_every=8),
    "appearance-pose-lambda-3e-3": _corrections(appearance=True, pose_lr=8e-4, pose_every=4, lambda_pose=3e-3),
    "appearance-pose-lambda-3e-2": _corrections(appearance=True, pose_lr=8e-4, pose_every=4, lambda_pose=3e-2),
    "appearance-pose-distortion": _corrections(appearance=True, pose_lr=8e-4, pose_every=4)
    | {"distortion_weight": 0.01},
    "prior-rays": {"prior_rays": 512},
    "prior-rays-colour": {"prior_rays": 256, "prior_ray_colour": 0.5},
    "no-weight-decay": NO_DECAY,
    "no-corrections": NO_CORRECTIONS | NO_DECAY,
    "previous-defaults": {"train_background": "fixed", "background": [0.0, 0.0, 0.0], "octree_carving": False}
    | NO_CORRECTIONS | NO_DECAY | STATED_FOCAL,
    "stated-focal": STATED_FOCAL,
    "no-carving": {"octree_carving": False},
    "background-mean": {"train_background": "fixed", "background": "training_mean"},
    "background-gray": {"train_background": "fixed", "background": [0.5, 0.5, 0.5]},
    "render-black": {"background": [0.0, 0.0, 0.0]},
    "samples-4-2": {"n_importance": 4, "n_rest": 2},
    "rays-4096": {"rays_per_batch": 4096},
    "table-2^18": {"hash_log2_size": 18},
    "max-res-512": {"hash_max_resolution": 512},
    "max-res-256": {"hash_max_resolution": 256},
    "weight-decay-1e-8": {"field_weight_decay": 1e-8},
    "weight-decay-3e-7": {"field_weight_decay": 3e-7},
    "weight-decay-1e-6": {"field_weight_decay": 1e-6},
    "weight-decay-1e-5": {"field_weight_decay": 1e-5},
    "depth-weight-1": {"lambda_depth": 1.0},
    "no-depth-loss": {"depth_loss": False},
    "occgrid-seeded": {"sampler": "occgrid", "depth_loss": False},
    "occgrid-density": {"sampler": "occgrid", "occgrid_seed": False, "depth_loss": False},
    "paper-preset": {"preset": "paper"},  # the paper's GPU setting (config.PRESETS); for a CUDA machine
}
"""Configuration name -> TrainConfig fields (``voxnerf train --set``) over the defaults."""
BASELINE = "defaults"
QUICK_CONFIGS = ("defaults", "distortion")


def config_flags(overrides: dict) -> list[str]:
    """``--set FIELD=VALUE`` flags (values as JSON) for ``overrides``."""
    return [arg for name, value in overrides.items() for arg in ("--set", f"{name}={json.dumps(value)}")]


def scene_flags(scene: str) -> list[str]:
    return ["--downscale", str(REDKITCHEN_DOWNSCALE)] if scene == REDKITCHEN else []


def run_one(scene: str, scene_dir: Path, config: str, run: Path, budget: float, eval_at: list[float],
            extra: list[str]) -> dict:
    """Train (or reuse a finished run of the same command) -> ``{"scene", "config", "command", "report"}``.

    A two-step run of the same scene and flags comes first (not timed): it fills the inductor cache (both
    graphs of a step that refines poses on every n-th step only), so the timed run loads its compiled step as
    a user's second run does, instead of every new configuration paying a cold compilation inside its
    budget."""
    flags = [*scene_flags(scene), "--eval-every", "100000", *extra, *config_flags(CONFIGS[config])]
    cmd = train_command(scene_dir, run, budget, eval_at, flags)
    command = "voxnerf " + shlex.join(cmd[3:])
    done = run / "suite-run.json"
    if (finished := _finished(done)) is not None and finished.get("command") == command:
        return finished
    if "--no-compile" not in extra:
        _run(train_command(scene_dir, run.parent / f".warm-{config}", budget, [],
                           [*flags, "--max-iters", "2", "--set", "final_eval=false"]))
    t0 = time.perf_counter()
    _run(cmd)
    report = json.loads((run / "report.json").read_text())
    keep = {k: report.get(k) for k in ("history", "metrics", "throughput", "iteration", "stages", "train_seconds",
                                        "wall_seconds")}
    result = {"scene": scene, "config": config, "command": command, "wall_s": time.perf_counter() - t0,
              "report": keep}
    write_atomic(done, json.dumps(result).encode())
    return result


def measure_runs(runs: Path, scene: str, configs: str, measure) -> list[tuple[str, dict]]:
    """``[(config, measure(run))]`` over the comma-separated ``configs``' runs of ``scene`` (``RUNS/<scene>/<config>``,
    as :func:`run_one` leaves them); a run without a checkpoint is skipped, said on stderr."""
    rows = []
    for config in configs.split(","):
        run = runs / scene / config
        if not (run / "checkpoint.pt").is_file():
            print(f"{run}: no checkpoint, skipped", file=sys.stderr)
            continue
        rows.append((config, measure(run)))
    return rows


def print_table(text: str, out: Path | None) -> int:
    """Print ``text`` and write it to ``out`` (when given); 0 for the caller's exit status."""
    print(text)
    if out is not None:
        out.write_text(text + "\n")
    return 0


def _finished(path: Path) -> dict | None:
    """A finished run's record, or None (absent or unreadable: the run is made again)."""
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError):
        return None


def _run(cmd: list[str]) -> None:
    proc = subprocess.run(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    if proc.returncode != 0:
        raise RuntimeError(f"{shlex.join(cmd)} failed: {proc.stderr.strip().splitlines()[-1:]}")


def split_scores(metrics: dict) -> dict[str, dict[str, float | None]]:
    """``{split: {"psnr", "ssim", "lpips", "half_psnr", "half_ssim", "half_lpips"}}`` of a final evaluation."""
    out = {}
    for split, m in metrics.items():
        half = m.get("half") or {}
        out[split] = {"psnr": m["psnr"], "ssim": m["ssim"], "lpips": m.get("lpips"),
                      "half_psnr": half.get("psnr"), "half_ssim": half.get("ssim"), "half_lpips": half.get("lpips")}
    return out


def at_time(result: dict, seconds: float) -> dict[str, dict[str, float | None]] | None:
    """Scores of the run's full evaluation at ``seconds`` of training (an ``--eval-at`` one), if it ran."""
    for h in result["report"]["history"] or []:
        if h.get("full") and not h.get("final") and abs(h["elapsed_s"] - seconds) < 0.05 * seconds + 1:
            return {split: {"psnr": p, "ssim": (h.get("ssim") or {}).get(split),
                            "lpips": (h.get("lpips") or {}).get(split),
                            **{f"half_{k}": v for k, v in ((h.get("half") or {}).get(split) or {}).items()}}
                    for split, p in h["psnr"].items()}
    return None


def _mean(values: list[float | None]) -> float | None:
    values = [v for v in values if v is not None and math.isfinite(v)]
    return sum(values) / len(values) if values else None


def _fmt(value: float | None, digits: int = 2) -> str:
    return "-" if value is None else f"{value:.{digits}f}"


def _signed(value: float | None) -> str:
    return "-" if value is None else f"{value:+.2f}"


SPLITS = ("interpolation", "extrapolation")


def summary_rows(results: list[dict], scenes: list[str], metric: str) -> list[str]:
    """Per configuration: the mean over ``scenes`` of ``metric`` per split, its change against the baseline,
    the worst scene's change and how many scenes lose more than NOISE_DB."""
    by = {(r["scene"], r["config"]): split_scores(r["report"]["metrics"] or {}) for r in results}
    configs = [c for c in CONFIGS if any((s, c) in by for s in scenes)]
    rows = []
    for config in configs:
        cells = []
        for split in SPLITS:
            values = [by.get((s, config), {}).get(split, {}).get(metric) for s in scenes]
            base = [by.get((s, BASELINE), {}).get(split, {}).get(metric) for s in scenes]
            deltas = [v - b for v, b in zip(values, base, strict=True) if v is not None and b is not None]
            cells += [_fmt(_mean(values)), _signed(_mean(deltas) if deltas else None),
                      _signed(min(deltas) if deltas else None),
                      str(sum(d < -NOISE_DB for d in deltas)) if deltas else "-"]
        n = sum((s, config) in by for s in scenes)
        rows.append(f"| {config} | {n} | " + " | ".join(cells) + " |")
    return rows


def scene_rows(results: list[dict], scenes: list[str]) -> list[str]:
    """Per configuration and scene: PSNR / SSIM / LPIPS per split, half-image PSNR, steps."""
    rows = []
    for r in sorted(results, key=lambda r: (list(CONFIGS).index(r["config"]), scenes.index(r["scene"])
                                            if r["scene"] in scenes else 99)):
        scores = split_scores(r["report"]["metrics"] or {})
        cells = []
        for split in SPLITS:
            s = scores.get(split, {})
            cells.append(f"{_fmt(s.get('psnr'))} / {_fmt(s.get('ssim'), 3)} / {_fmt(s.get('lpips'), 3)} "
                         f"({_fmt(s.get('half_psnr'))})")
        rows.append(f"| {r['config']} | {r['scene']} | " + " | ".join(cells) + f" | {r['report']['iteration']} |")
    return rows


SET_UP_STAGES = ("load_scene", "corrections", "weight_decay", "prior", "focal", "hash_kernel", "octree",
                 "pseudo_depth", "depth_target", "first_hit_cache")


def budget_rows(results: list[dict], scenes: list[str]) -> list[str]:
    """Per scene, the baseline run's seconds: set-up stages, compilation (first step), progress evaluations,
    training steps (less the first), final evaluation, and the whole command's wall clock."""
    rows = []
    for scene in scenes:
        run = next((r for r in results if r["scene"] == scene and r["config"] == BASELINE), None)
        if run is None or not run["report"].get("stages"):
            continue
        seconds = {st["name"]: st["seconds"] for st in run["report"]["stages"]}
        set_up = sum(seconds.get(name, 0.0) for name in SET_UP_STAGES)
        compile_s = seconds.get("compile", 0.0)
        steps = seconds.get("train", 0.0) - compile_s - seconds.get("progress_evals", 0.0)
        cells = [set_up, compile_s, seconds.get("progress_evals", 0.0), steps, seconds.get("final_eval", 0.0),
                 run["report"].get("wall_seconds") or 0.0]
        rows.append(f"| {scene} | " + " | ".join(f"{c:.1f}" for c in cells) + " |")
    return rows


def table(results: list[dict], scenes: list[str], synthetic: list[str], budget: float, command: str) -> str:
    head = ("| config | scenes | interp. mean | vs defaults | worst scene | scenes losing > 0.3 | extrap. mean | "
            "vs defaults | worst scene | scenes losing > 0.3 |\n| --- | --- | --- | --- | --- | --- | --- | --- | --- "
            "| --- |")
    parts = [f"Budget {budget:g} s of `voxnerf train` per run (everything included), one run at a time. Command:\n\n"
             f"    {command}\n"]
    for label, group in (("the synthetic rooms", synthetic), ("every scene, redkitchen included", scenes)):
        for metric, name in (("psnr", "PSNR (dB), all views"), ("half_psnr", "half-image PSNR (dB)")):
            rows = summary_rows(results, group, metric)
            if rows and group:
                parts.append(f"**{name}, mean over {label}** ({len(group)}):\n\n{head}\n" + "\n".join(rows) + "\n")
    spent = budget_rows(results, scenes)
    if spent:
        parts.append(f"**Where the budget went** (seconds, the `{BASELINE}` run of each scene):\n\n"
                     "| scene | set-up | compile (first step) | progress evaluations | training steps | "
                     "final evaluation | wall |\n| --- | --- | --- | --- | --- | --- | --- |\n"
                     + "\n".join(spent) + "\n")
    parts.append("**Every run** (PSNR / SSIM / LPIPS, half-image PSNR in brackets; steps):\n\n"
                 "| config | scene | interpolation | extrapolation | steps |\n| --- | --- | --- | --- | --- |\n"
                 + "\n".join(scene_rows(results, scenes)) + "\n")
    return "\n".join(parts)


def plot(results: list[dict], scenes: list[str], path: Path) -> bool:
    """PSNR change against ``defaults`` per configuration and scene, one panel per split (``path``, a PNG);
    False without matplotlib (the ``bench`` extra)."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        print("matplotlib not installed (the 'bench' extra): no plot", file=sys.stderr)
        return False
    by = {(r["scene"], r["config"]): split_scores(r["report"]["metrics"] or {}) for r in results}
    configs = [c for c in CONFIGS if c != BASELINE and any((s, c) in by for s in scenes)]
    fig, axes = plt.subplots(1, len(SPLITS), figsize=(6 * len(SPLITS), 0.45 * len(configs) + 1.5), sharey=True)
    width = 0.8 / max(len(scenes), 1)
    for ax, split in zip(axes, SPLITS, strict=True):
        for j, scene in enumerate(scenes):
            base = by.get((scene, BASELINE), {}).get(split, {}).get("psnr")
            deltas = [by.get((scene, c), {}).get(split, {}).get("psnr") for c in configs]
            values = [d - base if d is not None and base is not None else 0.0 for d in deltas]
            ax.barh([i + j * width for i in range(len(configs))], values, height=width, label=scene)
        ax.axvline(0.0, color="black", linewidth=0.8)
        ax.set_title(f"{split}: PSNR minus {BASELINE} (dB)")
        ax.set_yticks([i + 0.4 - width / 2 for i in range(len(configs))], configs)
        ax.invert_yaxis()
    axes[-1].legend(fontsize="small")
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return True


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--suite-dir", type=Path, help="where the suite's scenes are made (default OUT/scenes)")
    p.add_argument("--scenes", help="comma-separated suite scene names (default: all); 'redkitchen' among them "
                   "stands for the --redkitchen scene (alone: no synthetic room)")
    p.add_argument("--redkitchen", type=Path, help="the 7-Scenes redkitchen scene directory, added to the suite")
    p.add_argument("--configs", default=",".join(CONFIGS), help=f"comma-separated, from {', '.join(CONFIGS)}")
    p.add_argument("--budget", type=float, default=300.0, help="--max-seconds of every run")
    p.add_argument("--eval-at", default="", help="full evaluations inside each run, e.g. 120")
    p.add_argument("--quick", action="store_true", help="the quick suite, 5 eager steps per run (for tests)")
    p.add_argument("--table-only", action="store_true",
                   help="train nothing: the table of the runs already under --out (e.g. while a long run goes on)")
    p.add_argument("--write-docs", action="store_true", help="write the table into docs/benchmarks.md")
    args = p.parse_args(argv)
    unknown = [c for c in args.configs.split(",") if c not in CONFIGS]
    if unknown:
        p.error(f"unknown configs {unknown}; known: {', '.join(CONFIGS)}")
    if REDKITCHEN in (args.scenes or "").split(",") and args.redkitchen is None:
        p.error("--scenes names redkitchen: give its scene directory with --redkitchen")
    return args


def main(argv: list[str] | None = None) -> int:
    from voxnerf.synthetic.suite import QUICK_SUITE, SUITE, make_suite

    args = parse_args(argv)
    specs = QUICK_SUITE if args.quick else SUITE
    names = [n for n in args.scenes.split(",") if n != REDKITCHEN] if args.scenes else list(specs)
    configs = list(QUICK_CONFIGS) if args.quick and args.configs == ",".join(CONFIGS) else args.configs.split(",")
    scene_dirs = ({name: None for name in names} if args.table_only
                  else make_suite(args.suite_dir or args.out / "scenes", names=names, suite=specs))
    if args.redkitchen is not None:
        scene_dirs[REDKITCHEN] = args.redkitchen
    eval_at = [float(t) for t in args.eval_at.split(",") if t]
    extra = list(QUICK_TRAIN_ARGS) if args.quick else []
    for scene, scene_dir in [] if args.table_only else scene_dirs.items():
        for config in configs:  # a scene's configurations back to back: compared runs minutes apart
            print(f"{config} on {scene} ...", flush=True)
            run_one(scene, Path(scene_dir), config, args.out / "runs" / scene / config, args.budget, eval_at, extra)
    results = [json.loads(p.read_text()) for p in sorted((args.out / "runs").glob("*/*/suite-run.json"))]
    results = [r for r in results if r["config"] in CONFIGS and r["config"] in configs and r["scene"] in scene_dirs]
    scenes = list(dict.fromkeys([*scene_dirs, *(r["scene"] for r in results)]))
    synthetic = [s for s in scenes if s != REDKITCHEN]
    command = ".venv/bin/python benchmarks/suite.py " + shlex.join(sys.argv[1:] if argv is None else argv)
    text = table(results, scenes, synthetic, args.budget, command)
    publish(args.out, {"results": results, "command": command}, text, DOCS_PAGE, DOCS_SECTION, args.write_docs)
    plot(results, scenes, args.out / "suite.png")
    return 0


if __name__ == "__main__":
    sys.exit(main())
