"""The tuning suite: configurations of the trainer on every scene of the suite, side by side, one run at a time.

The suite is the synthetic rooms of :mod:`voxnerf.synthetic.suite` (varied layouts, sizes, fields of view,
lighting and priors, some rendered like captures) plus, with ``--redkitchen``, the real 7-Scenes kitchen at
``--downscale 2`` (``--scenes redkitchen`` runs it alone), and with ``--record3d-kitchen`` a capture importer's
scene made from it (:func:`make_record3d_kitchen`, also at ``--downscale 2``). Every scene belongs to one half
of a fixed split (:data:`HALVES`): the *tuning* half, on which a candidate configuration is chosen, and the
*confirmation* half, on which it must hold; each candidate's verdict against ``defaults`` (:func:`verdict`: "adopt"
only when it wins on the tuning half and no confirmation scene loses more than ``NOISE_DB``) is printed with both
halves side by side.

Every (scene, configuration) pair is one ``voxnerf train`` command with ``--max-seconds BUDGET`` (set-up,
compilation and the final evaluation included), run alone, one after the other, scene by scene: a scene's
configurations run back to back, so the runs compared on a scene are minutes apart on a machine whose speed
drifts over hours. A run whose report already holds the same command is reused, so rows can be added over
several invocations and the table always covers every run under ``--out``.

Each run's report gives, for every evaluation split: PSNR / SSIM / LPIPS over all views, and the same by the
half-image protocol (a colour gain and bias per channel fitted on each view's left half, scored on its right:
the honest score for runs that learn per-image exposure). ``--eval-at`` adds full evaluations inside the run
(their time is not charged to the budget); note that a schedule over the budget (``lr_schedule=budget``) is
mid-way at such a point, so only the final evaluation is what a run of that length gives.

``--tree NAME=DIR`` adds configuration NAME: the defaults of another source tree of VoxNeRF (e.g. ``git worktree
add DIR COMMIT`` of the commit an issue's targets were set on), its runs importing ``voxnerf`` from DIR; the record
keeps DIR's commit. A tree's ``voxnerf train`` runs as that tree's users ran it, whatever its ``--max-seconds``
charged then.

``--max-iters N`` bounds every run by N training steps as well (a fixed amount of work, so that runs on a machine
shared with other work still compare; the budget then only bounds the time).

Writes under ``--out``: ``runs/<scene>/<config>/`` (the runs), ``results.json`` and ``table.md`` (per half and
configuration: the mean and the worst scene against ``defaults``; each candidate's verdict; then every scene; the
``defaults`` runs' set-up check of the sampler's window, ``window_check`` in their report.json), ``suite.png``
(PSNR change against ``defaults`` per scene; needs matplotlib, the ``bench`` extra), and with ``--write-docs``
the table into docs/benchmarks.md.

    .venv/bin/python benchmarks/suite.py --out OUT --budget 120 --redkitchen ../shared/data/redkitchen \\
        --configs defaults,lr-budget,distortion
    .venv/bin/python benchmarks/suite.py --out OUT --budget 600 --max-iters 1000 \\
        --redkitchen ../shared/data/redkitchen --configs defaults,sampler-grid        # the sampler alone
    .venv/bin/python benchmarks/suite.py --quick --out /tmp/suite-quick    # CI-sized smoke run
"""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import os
import shlex
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from docs_section import publish
from error_vs_runtime import QUICK_TRAIN_ARGS, train_command

from voxnerf.data.image_io import write_atomic

DOCS_PAGE = Path(__file__).resolve().parent.parent / "docs" / "benchmarks.md"
DOCS_SECTION = "suite"
REDKITCHEN = "redkitchen"
REDKITCHEN_DOWNSCALE = 2
RECORD3D = "record3d_kitchen"
RECORD3D_FRAMES, RECORD3D_STRIDE = 100, 5
"""The Record3D-like scene: every 5th of redkitchen's first 500 frames (each has depth), as
benchmarks/phone_app_imports.py's training rows."""
REAL_SCANS = (REDKITCHEN, RECORD3D)
NOISE_DB = 0.3
"""A per-scene change smaller than this is read as noise (the issue's bar for "loses")."""
TUNING, CONFIRMATION = "tuning", "confirmation"
HALVES: dict[str, str] = {
    "studio": TUNING, "office": TUNING, "capture_lounge": TUNING, "gallery": TUNING, "hall": TUNING,
    "capture_bedroom": TUNING, REDKITCHEN: TUNING,
    "loft": CONFIRMATION, "den": CONFIRMATION, "capture_kitchen": CONFIRMATION, "attic": CONFIRMATION,
    "library": CONFIRMATION, "capture_study": CONFIRMATION, RECORD3D: CONFIRMATION,
}
"""The fixed split of the suite's scenes (issue #46). The six rooms measured before it keep the roles they had
(studio, office, capture_lounge tuned on; loft, den, capture_kitchen checked a choice); redkitchen is tuning, since
the defaults were chosen on it; the six new rooms are dealt so that each half holds both prior kinds (points and
mesh), prior noise from 1 to 5 cm, fields of view from under 60 to 95-100 degrees, 160 x 120 to 200 x 150 pixels,
two capture-like rooms and each kind of camera path (two gaps, one long gap, a dense path). The Record3D-like
import is confirmation: other frames, other splits and the phone's depth, though of the kitchen the tuning half
holds (a weak check of a choice made on redkitchen, and a cheap one)."""
QUICK_HALVES: dict[str, str] = {"quick_plain": TUNING, "quick_capture": CONFIRMATION,
                                **{scan: HALVES[scan] for scan in REAL_SCANS}}
"""The quick suite's split (for tests): one tiny room per half, the real scans where they always are."""

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
    "previous-defaults": {"train_background": "fixed", "background": [0.0, 0.0, 0.0], "octree_carving": False,
                          "window_centre": "entry", "weight_average": 0.0}
    | NO_CORRECTIONS | NO_DECAY | STATED_FOCAL,
    "stated-focal": STATED_FOCAL,
    "pixel-jitter": {"pixel_jitter": True},
    "error-map": {"error_map": 0.5},
    "error-map-weighted": {"error_map": 0.5, "error_map_weights": True},
    "cone": {"cone_radius": "auto"},
    "no-carving": {"octree_carving": False},
    "background-mean": {"train_background": "fixed", "background": "training_mean"},
    "background-gray": {"train_background": "fixed", "background": [0.5, 0.5, 0.5]},
    "render-black": {"background": [0.0, 0.0, 0.0]},
    "render-background-colour": {"render_background": "colour"},
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
    # The sampler alone: the defaults (depth loss, corrections, budget) with the prior-seeded occupancy grid in place
    # of the VoxNeRF sampler; the occgrid-* rows below also turn the depth loss off (the paper's Table II).
    "sampler-grid": {"sampler": "occgrid"},
    # The VoxNeRF sampler's window centred on its first leaf's entry (the paper's z; the default before issue #46's
    # window measurement), and the default window at half the paper's width.
    "window-entry": {"window_centre": "entry"},
    "window-half": {"window_width": 0.5},
    # Renders and checkpoints from the field's last-step parameters: the default before the moving average of its
    # parameters (a lag of 200 steps) won issue #46's protocol at 300 s.
    "no-weight-average": {"weight_average": 0.0},
    # The settings of the defaults when issue #46 was filed (the window on its first leaf's entry, no weight average,
    # the VoxNeRF sampler) on today's engine: beside ``--tree`` of that commit it tells the settings' share of a
    # change from the engine's.
    "issue-46-settings": {"window_centre": "entry", "weight_average": 0.0, "sampler": "voxnerf"},
    "occgrid-seeded": {"sampler": "occgrid", "depth_loss": False},
    "occgrid-density": {"sampler": "occgrid", "occgrid_seed": False, "depth_loss": False},
    "paper-preset": {"preset": "paper"},  # the paper's GPU setting (config.PRESETS); for a CUDA machine
}
"""Configuration name -> TrainConfig fields (``voxnerf train --set``) over the defaults."""
BASELINE = "defaults"
TREES: dict[str, Path] = {}
"""Configuration name -> a source tree whose defaults it runs (``--tree``, filled by :func:`main`)."""
QUICK_CONFIGS = ("defaults", "distortion")


def config_names() -> list[str]:
    """Every configuration a run may name, in table order: :data:`CONFIGS`, then the ``--tree`` ones."""
    return [*CONFIGS, *TREES]


def tree_commit(tree: Path) -> str | None:
    """The commit checked out at ``tree`` (None where it is not a git checkout)."""
    proc = subprocess.run(["git", "-C", str(tree), "rev-parse", "HEAD"], capture_output=True, text=True)
    return proc.stdout.strip() if proc.returncode == 0 else None


def config_flags(overrides: dict) -> list[str]:
    """``--set FIELD=VALUE`` flags (values as JSON) for ``overrides``."""
    return [arg for name, value in overrides.items() for arg in ("--set", f"{name}={json.dumps(value)}")]


def scene_flags(scene: str) -> list[str]:
    return ["--downscale", str(REDKITCHEN_DOWNSCALE)] if scene in REAL_SCANS else []


def make_record3d_kitchen(out: Path) -> Path:
    """The Record3D-like capture of redkitchen at ``out``, made once (reused while it holds a transforms.json):
    :data:`RECORD3D_FRAMES` of the shared redkitchen's frames written in Record3D's export layout by the tests'
    writer (``tests/phone_app_fixtures.py``: poses as quaternions, depth resampled to the phone's 256 x 192) and
    imported with the paper's splits (``voxnerf import record3d --splits paper``)."""
    if (out / "transforms.json").is_file():
        return out
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
    from phone_app_fixtures import redkitchen_frames, write_record3d

    from voxnerf.data.importers import PaperSplitRule
    from voxnerf.data.importers.record3d import import_record3d

    frames = redkitchen_frames(RECORD3D_FRAMES * RECORD3D_STRIDE)[::RECORD3D_STRIDE]
    with tempfile.TemporaryDirectory() as tmp:
        import_record3d(write_record3d(Path(tmp) / "export", frames), out, PaperSplitRule())
    return out


def run_one(scene: str, scene_dir: Path, config: str, run: Path, budget: float, eval_at: list[float],
            extra: list[str]) -> dict:
    """Train (or reuse a finished run of the same command) -> ``{"scene", "config", "command", "report"}``.

    A two-step run of the same scene and flags comes first (not timed): it fills the inductor cache (both
    graphs of a step that refines poses on every n-th step only), so the timed run loads its compiled step as
    a user's second run does, instead of every new configuration paying a cold compilation inside its
    budget."""
    tree = TREES.get(config)
    flags = [*scene_flags(scene), "--eval-every", "100000", *extra, *config_flags(CONFIGS.get(config, {}))]
    if tree is not None:  # a tree's run starts in the tree
        scene_dir, run = scene_dir.resolve(), run.resolve()
    cmd = train_command(scene_dir, run, budget, eval_at, flags)
    command = ("" if tree is None else f"PYTHONPATH={tree} ") + "voxnerf " + shlex.join(cmd[3:])
    done = run / "suite-run.json"
    if (finished := _finished(done)) is not None and finished.get("command") == command:
        return finished
    if "--no-compile" not in extra:
        _run(train_command(scene_dir, run.parent / f".warm-{config}", budget, [],
                           [*flags, "--max-iters", "2", "--set", "final_eval=false"]), tree)
    t0 = time.perf_counter()
    _run(cmd, tree)
    report = json.loads((run / "report.json").read_text())
    keep = {k: report.get(k) for k in REPORT_KEYS}
    result = {"scene": scene, "config": config, "command": command, "wall_s": time.perf_counter() - t0,
              "report": keep}
    if tree is not None:
        result["tree"] = {"path": str(tree), "commit": tree_commit(tree)}
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


REPORT_KEYS = ("history", "metrics", "throughput", "iteration", "stages", "train_seconds", "wall_seconds",
               "window_check", "budget")
"""What a run's record keeps of its report.json."""


def load_result(path: Path) -> dict:
    """A run's record (``suite-run.json``); a record made before it kept the report's ``budget`` takes it from the
    run's report.json beside it, when that is there (:func:`budget_rows` needs it to read the ``train`` stage)."""
    result = json.loads(path.read_text())
    report = result.get("report") or {}
    if "budget" not in report:
        with contextlib.suppress(OSError, ValueError):
            report["budget"] = json.loads((path.parent / "report.json").read_text()).get("budget")
    return result


def _finished(path: Path) -> dict | None:
    """A finished run's record, or None (absent or unreadable: the run is made again)."""
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError):
        return None


def _run(cmd: list[str], tree: Path | None = None) -> None:
    """Run ``cmd``; with ``tree``, in that directory with ``PYTHONPATH`` naming it (``python -m`` puts the working
    directory first on the path, so the tree's ``voxnerf`` is the one imported)."""
    env = None if tree is None else os.environ | {"PYTHONPATH": str(tree)}
    proc = subprocess.run(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, env=env, cwd=tree)
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
    configs = [c for c in config_names() if any((s, c) in by for s in scenes)]
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


def scene_changes(results: list[dict], scenes: list[str], config: str,
                  metric: str = "psnr") -> dict[str, dict[str, float]]:
    """``{scene: {split: change}}``: ``config``'s ``metric`` minus the baseline's on each of ``scenes`` where both
    ran and scored every split (finite values only)."""
    by = {(r["scene"], r["config"]): split_scores(r["report"]["metrics"] or {}) for r in results}
    changes = {}
    for scene in scenes:
        ours, base = by.get((scene, config)), by.get((scene, BASELINE))
        if ours is None or base is None:
            continue
        pairs = {split: (ours.get(split, {}).get(metric), base.get(split, {}).get(metric)) for split in SPLITS}
        if all(v is not None and b is not None and math.isfinite(v) and math.isfinite(b) for v, b in pairs.values()):
            changes[scene] = {split: v - b for split, (v, b) in pairs.items()}
    return changes


def verdict(results: list[dict], halves: dict[str, str], config: str) -> dict:
    """Whether ``config`` should replace the baseline, by the suite's protocol (issue #46), from PSNR over all views.

    It *wins on the tuning half* when the half's mean change, summed over interpolation and extrapolation, is
    positive and neither split's mean falls by more than ``NOISE_DB``; it *holds on the confirmation half* when no
    scene of that half loses more than ``NOISE_DB`` on either split. "adopt" needs both and a run of ``config`` and
    of the baseline on every scene of both halves ("keep" otherwise, the reason in ``why``). ``halves`` maps each
    scene of the invocation to its half. Returns ``{"config", "tuning": {...}, "confirmation": {...}, "verdict",
    "why"}``, each half with its scene count, the scenes lacking a run, the mean change per split, and the
    confirmation half its worst scene (``{"scene", "split", "change"}``)."""
    summary: dict = {"config": config}
    for half in (TUNING, CONFIRMATION):
        scenes = [s for s, h in halves.items() if h == half]
        changes = scene_changes(results, scenes, config)
        part = {"scenes": len(changes), "missing": [s for s in scenes if s not in changes]}
        part |= {split: _mean([c[split] for c in changes.values()]) for split in SPLITS}
        if half == CONFIRMATION and changes:
            scene, split = min(((s, sp) for s in changes for sp in SPLITS), key=lambda k: changes[k[0]][k[1]])
            part["worst"] = {"scene": scene, "split": split, "change": changes[scene][split]}
        summary[half] = part
    tuning, confirmation = summary[TUNING], summary[CONFIRMATION]
    missing = [s for half in (tuning, confirmation) for s in half["missing"]]
    if not tuning["scenes"] or not confirmation["scenes"] or missing:
        lacking = f"no run on {', '.join(missing)}" if missing else "a half has no scene in this run"
        return summary | {"verdict": "keep", "why": f"incomplete: {lacking}"}
    gain = tuning["interpolation"] + tuning["extrapolation"]
    means = f"{tuning['interpolation']:+.2f} / {tuning['extrapolation']:+.2f} dB"
    if gain <= 0 or min(tuning["interpolation"], tuning["extrapolation"]) < -NOISE_DB:
        return summary | {"verdict": "keep", "why": f"does not win on the tuning half ({means})"}
    worst = confirmation["worst"]
    if worst["change"] < -NOISE_DB:
        return summary | {"verdict": "keep", "why": f"wins on the tuning half ({means}) but {worst['scene']} loses "
                                                    f"{-worst['change']:.2f} dB of {worst['split']}"}
    return summary | {"verdict": "adopt", "why": f"wins on the tuning half ({means}) and no confirmation scene loses "
                                                  f"more than {NOISE_DB:g} dB"}


def verdict_rows(verdicts: list[dict]) -> list[str]:
    """One markdown row per candidate: each half's mean change per split, the confirmation half's worst scene, the
    verdict and why."""
    rows = []
    for v in verdicts:
        t, c = v[TUNING], v[CONFIRMATION]
        worst = c.get("worst")
        worst_text = "-" if worst is None else f"{worst['scene']} {worst['split'][:6]}. {worst['change']:+.2f}"
        rows.append(f"| {v['config']} | {t['scenes']} | {_signed(t['interpolation'])} | "
                    f"{_signed(t['extrapolation'])} | {c['scenes']} | {_signed(c['interpolation'])} | "
                    f"{_signed(c['extrapolation'])} | {worst_text} | **{v['verdict']}**: {v['why']} |")
    return rows


def scene_rows(results: list[dict], scenes: list[str]) -> list[str]:
    """Per configuration and scene: PSNR / SSIM / LPIPS per split, half-image PSNR, steps."""
    rows, order = [], config_names()
    for r in sorted(results, key=lambda r: (order.index(r["config"]), scenes.index(r["scene"])
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
                 "pseudo_depth", "depth_target", "octree_carving", "first_hit_cache", "window_check")


def budget_rows(results: list[dict], scenes: list[str]) -> list[str]:
    """Per scene, the baseline run's seconds: set-up stages, compilation (first step), progress evaluations,
    training steps (less the first), final evaluation, and the whole command's wall clock. The steps are the
    report's ``budget.seconds.training`` where it has one (its ``train`` stage then holds the steps alone); an
    older report's ``train`` stage also held the compilation and the progress evaluations, which are taken off."""
    rows = []
    for scene in scenes:
        run = next((r for r in results if r["scene"] == scene and r["config"] == BASELINE), None)
        if run is None or not run["report"].get("stages"):
            continue
        seconds = {st["name"]: st["seconds"] for st in run["report"]["stages"]}
        set_up = sum(seconds.get(name, 0.0) for name in SET_UP_STAGES)
        compile_s = seconds.get("compile", 0.0)
        charged = (run["report"].get("budget") or {}).get("seconds") or {}
        if "training" in charged:
            steps = charged["training"]
        else:
            steps = seconds.get("train", 0.0) - compile_s - seconds.get("progress_evals", 0.0)
        cells = [set_up, compile_s, seconds.get("progress_evals", 0.0), steps, seconds.get("final_eval", 0.0),
                 run["report"].get("wall_seconds") or 0.0]
        rows.append(f"| {scene} | " + " | ".join(f"{c:.1f}" for c in cells) + " |")
    return rows


def window_rows(results: list[dict], scenes: list[str], halves: dict[str, str]) -> list[str]:
    """Per scene, the set-up check of the VoxNeRF sampler's window in its ``defaults`` run (``window_check`` of
    report.json, :mod:`voxnerf.training.window_check`)."""
    rows = []
    for scene in scenes:
        run = next((r for r in results if r["scene"] == scene and r["config"] == BASELINE), None)
        check = (run or {}).get("report", {}).get("window_check")
        if not check:
            continue
        samples = check.get("samples") or {}
        near = samples.get("near_surface") or {}

        def pct(value: float | None) -> str:
            return "-" if value is None else f"{100 * value:.1f}%"

        def cm(value: float | None) -> str:
            return "-" if value is None else f"{100 * value:.1f}"

        rows.append(f"| {scene} | {halves.get(scene, '-')} | {check['rays']} | {pct(check['miss'])} | "
                    f"{pct(check['stop_short'])} | {pct(check['pass_through'])} | {cm(check['half_window_m'])} | "
                    f"{cm(check.get('prior_noise_m'))} ({cm(check.get('prior_sigma_m'))}) | "
                    f"{_fmt(check.get('window_over_noise'), 1)} | {pct(samples.get('outside_window'))} | "
                    f"{pct(near.get('voxnerf'))} / {pct(near.get('occupancy_grid'))} |")
    return rows


def table(results: list[dict], scenes: list[str], halves: dict[str, str], budget: float, max_iters: int | None,
          command: str, every_run: bool = True) -> str:
    """The markdown table of the runs: each half's means, the verdicts, the window check, where the budget went and
    each run's scores. Without ``every_run`` (docs/benchmarks.md's form): each half's all-view PSNR means and the
    verdicts, then a line saying that ``table.md`` of ``--out`` has the rest."""
    head = ("| config | scenes | interp. mean | vs defaults | worst scene | scenes losing > 0.3 | extrap. mean | "
            "vs defaults | worst scene | scenes losing > 0.3 |\n| --- | --- | --- | --- | --- | --- | --- | --- | --- "
            "| --- |")
    bound = f"{budget:g} s" + (f" or {max_iters} steps, whichever comes first," if max_iters else "")
    budget_table = "the budget table" if every_run else "the budget table of `table.md`"
    parts = [f"Budget {bound} of training per `voxnerf train` run (`--max-seconds`; set-up, compilation and the "
             f"final evaluation come on top, as {budget_table} shows), one run at a time. Command:\n\n"
             f"    {command}\n"]
    for half in (TUNING, CONFIRMATION):
        group = [s for s in scenes if halves.get(s) == half]
        metrics = (("psnr", "PSNR (dB), all views"), ("half_psnr", "half-image PSNR (dB)"))
        for metric, name in metrics if every_run else metrics[:1]:
            rows = summary_rows(results, group, metric)
            if rows and group:
                parts.append(f"**{name}, mean over the {half} half** ({', '.join(group)}):\n\n{head}\n"
                             + "\n".join(rows) + "\n")
    ran = {r["config"] for r in results}
    verdicts = [verdict(results, halves, c) for c in config_names() if c != BASELINE and c in ran]
    if verdicts:
        parts.append(f"**Verdicts against `{BASELINE}`** (PSNR change, all views, dB: interpolation / extrapolation; "
                     "\"adopt\" only when a configuration wins on the tuning half and no confirmation scene loses "
                     f"more than {NOISE_DB:g} dB):\n\n"
                     "| config | tuning scenes | interp. | extrap. | confirmation scenes | interp. | extrap. | "
                     "worst confirmation scene | verdict |\n| --- | --- | --- | --- | --- | --- | --- | --- | --- |\n"
                     + "\n".join(verdict_rows(verdicts)) + "\n")
    if not every_run:
        parts.append("The half-image PSNR means, the sampler's window checked at set-up, where the budget went and "
                     "every run's PSNR, SSIM, LPIPS and steps: `table.md` in the command's `--out`.\n")
        return "\n".join(parts)
    window = window_rows(results, scenes, halves)
    if window:
        parts.append(f"**The VoxNeRF sampler's window, checked at set-up** (the `{BASELINE}` run of each scene, "
                     "training pixels with depth: rays whose octree first hit misses every leaf, stops short of the "
                     "depth or passes it by more than the window's half-width; the half-width against the prior's "
                     "noise along the ray, measured against the depth (stated sigma in brackets); the share of the "
                     "sampler's samples outside its window; the share of samples within the half-width of the depth, "
                     "VoxNeRF sampler / the prior-seeded occupancy grid at set-up):\n\n"
                     "| scene | half | rays | miss | stop short | pass through | half-window (cm) | prior noise (cm) | "
                     "window / noise | samples outside window | samples near the surface |\n"
                     "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |\n" + "\n".join(window) + "\n")
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


def plot(results: list[dict], scenes: list[str], halves: dict[str, str], path: Path) -> bool:
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
    configs = [c for c in config_names() if c != BASELINE and any((s, c) in by for s in scenes)]
    height = 0.18 * len(configs) * max(len(scenes), 3) + 1.5  # a bar per scene and configuration
    fig, axes = plt.subplots(1, len(SPLITS), figsize=(6 * len(SPLITS), height), sharey=True)
    width = 0.8 / max(len(scenes), 1)
    for ax, split in zip(axes, SPLITS, strict=True):
        for j, scene in enumerate(scenes):
            base = by.get((scene, BASELINE), {}).get(split, {}).get("psnr")
            deltas = [by.get((scene, c), {}).get(split, {}).get("psnr") for c in configs]
            values = [d - base if d is not None and base is not None else 0.0 for d in deltas]
            ax.barh([i + j * width for i in range(len(configs))], values, height=width,
                    label=f"{scene} ({halves.get(scene, '-')})", hatch="//" if halves.get(scene) == CONFIRMATION
                    else None)
        ax.axvline(0.0, color="black", linewidth=0.8)
        ax.set_title(f"{split}: PSNR minus {BASELINE} (dB)")
        ax.set_yticks([i + 0.4 - width / 2 for i in range(len(configs))], configs)
        ax.invert_yaxis()
    axes[-1].legend(fontsize="small", loc="center left", bbox_to_anchor=(1.02, 0.5))
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
    p.add_argument("--redkitchen", type=Path, help="the 7-Scenes redkitchen scene directory, added to the suite "
                   "(to a --scenes list only where it names redkitchen)")
    p.add_argument("--record3d-kitchen", action="store_true",
                   help=f"add {RECORD3D}: the shared redkitchen written as a Record3D export and imported (made once "
                   "under the suite directory; confirmation half; to a --scenes list only where it names it)")
    p.add_argument("--configs", default=",".join(CONFIGS), help=f"comma-separated, from {', '.join(CONFIGS)}")
    p.add_argument("--tree", action="append", default=[], metavar="NAME=DIR",
                   help="also run configuration NAME: the defaults of the VoxNeRF source tree at DIR (e.g. a git "
                   "worktree of an earlier commit)")
    p.add_argument("--budget", type=float, default=300.0, help="--max-seconds of every run")
    p.add_argument("--max-iters", type=int, help="also bound every run by this many training steps (a fixed amount "
                   "of work: runs on a shared machine still compare)")
    p.add_argument("--eval-at", default="", help="full evaluations inside each run, e.g. 120")
    p.add_argument("--quick", action="store_true", help="the quick suite, 5 eager steps per run (for tests)")
    p.add_argument("--table-only", action="store_true",
                   help="train nothing: the table of the runs already under --out (e.g. while a long run goes on)")
    p.add_argument("--write-docs", action="store_true", help="write the table into docs/benchmarks.md")
    args = p.parse_args(argv)
    args.trees = {}
    for text in args.tree:
        name, sep, tree = text.partition("=")
        if not sep or not name or not tree:
            p.error(f"--tree wants NAME=DIR, got {text!r}")
        if name in CONFIGS or name in args.trees:
            p.error(f"--tree {name}: the name is taken; give the tree another")
        if not (Path(tree) / "voxnerf" / "__init__.py").is_file():
            p.error(f"--tree {name}: {tree} holds no voxnerf package (voxnerf/__init__.py)")
        args.trees[name] = Path(tree).resolve()
    unknown = [c for c in args.configs.split(",") if c not in CONFIGS and c not in args.trees]
    if unknown:
        p.error(f"unknown configs {unknown}; known: {', '.join(CONFIGS)}")
    if REDKITCHEN in (args.scenes or "").split(",") and args.redkitchen is None:
        p.error("--scenes names redkitchen: give its scene directory with --redkitchen")
    if RECORD3D in (args.scenes or "").split(",") and not args.record3d_kitchen:
        p.error(f"--scenes names {RECORD3D}: add --record3d-kitchen")
    if args.max_iters is not None and args.max_iters < 1:
        p.error(f"--max-iters must be a positive number of steps, got {args.max_iters}")
    return args


def main(argv: list[str] | None = None) -> int:
    from voxnerf.synthetic.suite import QUICK_SUITE, SUITE, make_suite

    args = parse_args(argv)
    specs = QUICK_SUITE if args.quick else SUITE
    halves = QUICK_HALVES if args.quick else HALVES
    named = args.scenes.split(",") if args.scenes else None
    names = [n for n in named if n not in REAL_SCANS] if named is not None else list(specs)
    TREES.clear()
    TREES.update(args.trees)
    configs = list(QUICK_CONFIGS) if args.quick and args.configs == ",".join(CONFIGS) else args.configs.split(",")
    configs += [name for name in TREES if name not in configs]
    scene_dirs = ({name: None for name in names} if args.table_only
                  else make_suite(args.suite_dir or args.out / "scenes", names=names, suite=specs))
    # a real scan's flag adds it to the whole suite, or to a --scenes list that names it
    if args.redkitchen is not None and (named is None or REDKITCHEN in named):
        scene_dirs[REDKITCHEN] = args.redkitchen
    if args.record3d_kitchen and (named is None or RECORD3D in named):
        suite_dir = args.suite_dir or args.out / "scenes"
        scene_dirs[RECORD3D] = suite_dir / RECORD3D if args.table_only else make_record3d_kitchen(suite_dir / RECORD3D)
    eval_at = [float(t) for t in args.eval_at.split(",") if t]
    extra = list(QUICK_TRAIN_ARGS) if args.quick else []
    if args.max_iters is not None:
        extra += ["--max-iters", str(args.max_iters)]
    for scene, scene_dir in [] if args.table_only else scene_dirs.items():
        for config in configs:  # a scene's configurations back to back: compared runs minutes apart
            print(f"{config} on {scene} ...", flush=True)
            run_one(scene, Path(scene_dir), config, args.out / "runs" / scene / config, args.budget, eval_at, extra)
    results = [load_result(p) for p in sorted((args.out / "runs").glob("*/*/suite-run.json"))]
    results = [r for r in results if r["config"] in configs and r["scene"] in scene_dirs]
    scenes = list(dict.fromkeys([*scene_dirs, *(r["scene"] for r in results)]))
    in_run = {scene: halves[scene] for scene in scenes}
    command = ".venv/bin/python benchmarks/suite.py " + shlex.join(sys.argv[1:] if argv is None else argv)
    text = table(results, scenes, in_run, args.budget, args.max_iters, command)
    verdicts = [verdict(results, in_run, c) for c in configs if c != BASELINE]
    publish(args.out, {"results": results, "command": command, "halves": in_run, "verdicts": verdicts}, text,
            DOCS_PAGE, DOCS_SECTION, args.write_docs,
            docs_text=table(results, scenes, in_run, args.budget, args.max_iters, command, every_run=False))
    plot(results, scenes, in_run, args.out / "suite.png")
    return 0


if __name__ == "__main__":
    sys.exit(main())
