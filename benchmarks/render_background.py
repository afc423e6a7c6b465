"""What a rendered ray shows behind its last sample, side by side on the same trained fields: ``render_background``
'colour' (the background colour, the training images' mean by default) against 'nearest_seen' (the colour the
training images show where the ray meets the prior, :mod:`voxnerf.model.colour_prior`).

The setting acts only when rendering, so both are scored on one trained field per scene, without training twice:
each run's set-up is replayed on its scene (the engine's own set-up stages, resumed from the run's checkpoint, up to
the colour prior), and every evaluation view is rendered and scored both ways (PSNR, SSIM, LPIPS over all views and
by the half-image protocol, as report.json's). The runs are a suite run's (:mod:`suite`):
``RUNS/runs/<scene>/<config>``.

    PYTHONPATH=. .venv/bin/python benchmarks/render_background.py --runs /tmp/suite300 --suite-dir /tmp/scenes \\
        --redkitchen ../shared/data/redkitchen --out /tmp/render_background

Writes ``OUT/results.json`` (every scene's metrics both ways) and ``OUT/table.md`` (per half: the means and the worst
scene of 'nearest_seen' against 'colour'; then every scene), with the command.
"""

from __future__ import annotations

import argparse
import json
import shlex
import sys
import tempfile
from pathlib import Path

import torch
from suite import BASELINE, HALVES, NOISE_DB, verdict, verdict_rows

from voxnerf.config import TrainConfig
from voxnerf.data.scene import load_scene
from voxnerf.inference.evaluation import evaluate_views
from voxnerf.inference.render import load_model, scene_as_trained
from voxnerf.training.checkpoint import load_previous
from voxnerf.training.eval_passes import eval_views_of
from voxnerf.training.records import TrainReport
from voxnerf.training.setup import SETUP_STAGES, SetupContext, run_setup

CHOICES = ("colour", "nearest_seen")
# The set-up replayed for the colour prior: every stage up to it (prior rays only shape training).
REPLAYED = tuple(stage for stage in SETUP_STAGES if stage.name != "prior_rays")


def scene_dir_of(scene: str, suite_dir: Path, redkitchen: Path | None) -> Path:
    """Where a suite scene lives: redkitchen at ``--redkitchen``, the others under ``--suite-dir``."""
    if scene == "redkitchen":
        if redkitchen is None:
            raise SystemExit("render_background: redkitchen's run needs --redkitchen")
        return redkitchen
    return suite_dir / scene


def colour_prior_of(run_dir: Path, scene_dir: Path, device: str):
    """The colour prior the run's set-up makes under ``render_background`` 'nearest_seen' (None where the stage
    does not run, with its why), from the run's own config and checkpoint."""
    flat = json.loads((run_dir / "report.json").read_text())["config"]
    cfg = TrainConfig.model_validate(flat).updated(render_background="nearest_seen", device=device)
    previous = load_previous(run_dir / "checkpoint.pt", True)
    with tempfile.TemporaryDirectory() as scratch:  # the prior stage may write a fused prior there
        report = TrainReport(config=cfg.flat(), device=device)
        ctx = SetupContext(cfg, scene_dir, Path(scratch), torch.device(device), report, previous, lambda: None)
        records = {}
        run_setup(ctx, lambda record, _: records.__setitem__(record.name, record), lambda: None, REPLAYED)
    return ctx.built.model.colour_prior, records["colour_prior"].why


def score_run(run_dir: Path, scene_dir: Path, device: str) -> dict:
    """Both render backgrounds' metrics per evaluation split, and the colour prior stage's why."""
    prior, why = colour_prior_of(run_dir, scene_dir, device)
    trained = load_model(run_dir, device)
    model = trained.model
    model.colour_prior = prior
    scene = scene_as_trained(load_scene(scene_dir, downscale=model.config.run.downscale), model)
    views = eval_views_of(scene, model.transform)
    out = {"run": str(run_dir), "colour_prior": why}
    for choice in CHOICES:
        model.config = model.config.updated(render_background=choice)
        metrics = evaluate_views(model, views, model.config, half_image=True)
        out[choice] = {split: {key: m[key] for key in ("psnr", "ssim", "lpips", "half")}
                       for split, m in metrics.items()}
    return out


def _joined(values: list[float]) -> str:
    return " / ".join(f"{v:.2f}" for v in values)


def _change(by_choice: dict[str, list[float]]) -> str:
    return " / ".join(f"{b - a:+.2f}" for a, b in zip(by_choice["colour"], by_choice["nearest_seen"], strict=True))


def protocol_verdict(results: dict[str, dict]) -> dict:
    """The suite's verdict (:func:`suite.verdict`, issue #46's protocol) on 'nearest_seen' against 'colour' as the
    baseline, over the scenes of ``results`` that belong to a half."""
    runs = [{"scene": scene, "config": BASELINE if choice == "colour" else choice, "report": {"metrics": r[choice]}}
            for scene, r in results.items() for choice in CHOICES]
    return verdict(runs, {s: HALVES[s] for s in results if s in HALVES}, "nearest_seen")


def table(results: dict[str, dict], command: str) -> str:
    lines = ["PSNR (dB), all views, the same trained field rendered both ways; `nearest_seen` - `colour`. Command:", "",
             f"    {command}", "",
             "**The protocol's verdict** (`nearest_seen` against `colour`; benchmarks/suite.py's rule):", "",
             "| config | tuning scenes | interp. | extrap. | confirmation scenes | interp. | extrap. | "
             "worst confirmation scene | verdict |", "| --- | --- | --- | --- | --- | --- | --- | --- | --- |",
             *verdict_rows([protocol_verdict(results)]), ""]
    for half in dict.fromkeys(HALVES.values()):
        scenes = [s for s, h in HALVES.items() if h == half and s in results]
        if not scenes:
            continue
        lines += [f"**{half} half** ({', '.join(scenes)})", "",
                  "| split | colour | nearest_seen | change | worst scene | scenes losing > 0.3 |",
                  "| --- | --- | --- | --- | --- | --- |"]
        for split in dict.fromkeys(split for s in scenes for split in results[s]["colour"]):
            pairs = [(results[s]["colour"][split]["psnr"], results[s]["nearest_seen"][split]["psnr"])
                     for s in scenes if split in results[s]["colour"]]
            if not pairs:
                continue
            before = sum(a for a, _ in pairs) / len(pairs)
            after = sum(b for _, b in pairs) / len(pairs)
            worst = min(b - a for a, b in pairs)
            losing = sum(b - a < -NOISE_DB for a, b in pairs)
            lines.append(f"| {split} | {before:.2f} | {after:.2f} | {after - before:+.2f} | {worst:+.2f} | {losing} |")
        lines.append("")
    lines += ["**Every scene** (PSNR per split, e.g. interpolation / extrapolation; half-image PSNR; LPIPS)", "",
              "| scene | colour | nearest_seen | change | half-image change | LPIPS colour | LPIPS nearest_seen |",
              "| --- | --- | --- | --- | --- | --- | --- |"]
    for scene, r in results.items():
        splits = list(r["colour"])
        psnr = {c: [r[c][s]["psnr"] for s in splits] for c in CHOICES}
        half = {c: [r[c][s]["half"]["psnr"] for s in splits] for c in CHOICES}
        lpips = {c: ["-" if r[c][s]["lpips"] is None else f"{r[c][s]['lpips']:.3f}" for s in splits] for c in CHOICES}
        lines.append(f"| {scene} | {_joined(psnr['colour'])} | {_joined(psnr['nearest_seen'])} | "
                     f"{_change(psnr)} | {_change(half)} | {' / '.join(lpips['colour'])} | "
                     f"{' / '.join(lpips['nearest_seen'])} |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--runs", type=Path, required=True, help="a suite's --out: its runs/<scene>/<config>")
    p.add_argument("--suite-dir", type=Path, required=True, help="the suite's scenes")
    p.add_argument("--redkitchen", type=Path, help="the 7-Scenes redkitchen scene directory")
    p.add_argument("--config", default="defaults", help="which configuration's runs (default: defaults)")
    p.add_argument("--scenes", help="comma-separated (default: every scene with a run)")
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--device", default="cpu")
    args = p.parse_args(argv)
    available = sorted(d.name for d in (args.runs / "runs").iterdir() if (d / args.config / "checkpoint.pt").is_file())
    scenes = args.scenes.split(",") if args.scenes else available
    missing = [s for s in scenes if s not in available]
    if missing:
        p.error(f"no {args.config} run with a checkpoint under {args.runs / 'runs'} for {', '.join(missing)}")
    args.out.mkdir(parents=True, exist_ok=True)
    results_path = args.out / "results.json"
    results = json.loads(results_path.read_text()) if results_path.is_file() else {}
    for scene in scenes:
        run_dir = args.runs / "runs" / scene / args.config
        if results.get(scene, {}).get("run") == str(run_dir):
            continue
        print(f"{scene} ...", flush=True)
        results[scene] = score_run(run_dir, scene_dir_of(scene, args.suite_dir, args.redkitchen), args.device)
        results_path.write_text(json.dumps(results, indent=1))
    command = shlex.join(["PYTHONPATH=.", ".venv/bin/python", "benchmarks/render_background.py",
                          *(argv if argv is not None else sys.argv[1:])])
    text = table({s: results[s] for s in scenes}, command)
    (args.out / "table.md").write_text(text)
    print(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
