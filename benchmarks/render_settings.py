"""What a render-time setting changes, side by side on the same trained fields: ``--setting render_background``
('colour', the background colour, the training images' mean by default, against 'nearest_seen', the colour the
training images show where the ray meets the prior, :mod:`voxnerf.model.colour_prior`), ``--setting
nearest_seen_weight`` ('nearest_seen', that colour alone, against 'shrunk', 3/4 of it and 1/4 of the background) or
``--setting antialias`` ('centre_ray', each pixel's colour from its centre ray, against 'antialiased', the weighted
mean of five rays through it, :data:`voxnerf.inference.render.PIXEL_RAYS`).

Such a setting acts only when rendering, so both choices are scored on one trained field per scene, without training
twice: each run's set-up is replayed on its scene (the engine's own set-up stages, resumed from the run's checkpoint,
up to the colour prior, so the field renders as the run would), and every evaluation view is rendered and scored
both ways (PSNR, SSIM, LPIPS over all views and by the half-image protocol, as report.json's). The runs are a suite
run's (:mod:`suite`): ``RUNS/runs/<scene>/<config>``.

    PYTHONPATH=. .venv/bin/python benchmarks/render_settings.py --setting antialias --runs /tmp/suite300 \
        --suite-dir /tmp/scenes --redkitchen ../shared/data/redkitchen --out /tmp/antialias

Writes ``OUT/results.json`` (every scene's metrics both ways) and ``OUT/table.md`` (per half: the means and the worst
scene of the second choice against the first; then every scene), with the command.
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

from voxnerf.config import ModelConfig, TrainConfig
from voxnerf.data.scene import load_scene
from voxnerf.inference.evaluation import evaluate_views
from voxnerf.inference.render import load_model, scene_as_trained
from voxnerf.training.checkpoint import load_previous
from voxnerf.training.eval_passes import eval_views_of
from voxnerf.training.records import TrainReport
from voxnerf.training.setup import SETUP_STAGES, SetupContext, run_setup

# Each setting's two choices, the baseline first: a label (results.json's keys, the table's columns) -> its value.
SETTINGS: dict[str, dict[str, object]] = {
    "render_background": {"colour": "colour", "nearest_seen": "nearest_seen"},
    "antialias": {"centre_ray": False, "antialiased": True},
    "nearest_seen_weight": {"nearest_seen": 1.0, "shrunk": 0.75},
}
# The set-up replayed for the colour prior: every stage up to it (prior rays only shape training).
REPLAYED = tuple(stage for stage in SETUP_STAGES if stage.name != "prior_rays")


def scene_dir_of(scene: str, suite_dir: Path, redkitchen: Path | None) -> Path:
    """Where a suite scene lives: redkitchen at ``--redkitchen``, the others under ``--suite-dir``."""
    if scene == "redkitchen":
        if redkitchen is None:
            raise SystemExit("render_settings: redkitchen's run needs --redkitchen")
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


def score_run(run_dir: Path, scene_dir: Path, device: str, setting: str = "render_background") -> dict:
    """Both choices' metrics of ``setting`` per evaluation split, and the colour prior stage's why. The field
    renders as today's defaults render it (the colour prior replayed, every render-time setting of :data:`SETTINGS`
    at its default, whatever the run's config said when it trained) but for ``setting``."""
    prior, why = colour_prior_of(run_dir, scene_dir, device)
    trained = load_model(run_dir, device)
    model = trained.model
    model.colour_prior = prior
    model.config = model.config.updated(**{name: ModelConfig.model_fields[name].default for name in SETTINGS})
    scene = scene_as_trained(load_scene(scene_dir, downscale=model.config.run.downscale), model)
    views = eval_views_of(scene, model.transform)
    out = {"run": str(run_dir), "setting": setting, "colour_prior": why}
    for choice, value in SETTINGS[setting].items():
        model.config = model.config.updated(**{setting: value})
        metrics = evaluate_views(model, views, model.config, half_image=True)
        out[choice] = {split: {key: m[key] for key in ("psnr", "ssim", "lpips", "half")}
                       for split, m in metrics.items()}
    return out


def _joined(values: list[float]) -> str:
    return " / ".join(f"{v:.2f}" for v in values)


def _change(by_choice: dict[str, list[float]], base: str, other: str) -> str:
    return " / ".join(f"{b - a:+.2f}" for a, b in zip(by_choice[base], by_choice[other], strict=True))


def protocol_verdict(results: dict[str, dict], setting: str) -> dict:
    """The suite's verdict (:func:`suite.verdict`, issue #46's protocol) on ``setting``'s second choice against its
    first as the baseline, over the scenes of ``results`` that belong to a half."""
    base, other = SETTINGS[setting]
    runs = [{"scene": scene, "config": BASELINE if choice == base else choice, "report": {"metrics": r[choice]}}
            for scene, r in results.items() for choice in (base, other)]
    return verdict(runs, {s: HALVES[s] for s in results if s in HALVES}, other)


def table(results: dict[str, dict], command: str, setting: str) -> str:
    base, other = SETTINGS[setting]
    lines = [f"PSNR (dB), all views, the same trained field rendered both ways (`{setting}`); `{other}` - `{base}`. "
             "Command:", "", f"    {command}", "",
             f"**The protocol's verdict** (`{other}` against `{base}`; benchmarks/suite.py's rule):", "",
             "| config | tuning scenes | interp. | extrap. | confirmation scenes | interp. | extrap. | "
             "worst confirmation scene | verdict |", "| --- | --- | --- | --- | --- | --- | --- | --- | --- |",
             *verdict_rows([protocol_verdict(results, setting)]), ""]
    for half in dict.fromkeys(HALVES.values()):
        scenes = [s for s, h in HALVES.items() if h == half and s in results]
        if not scenes:
            continue
        lines += [f"**{half} half** ({', '.join(scenes)})", "",
                  f"| split | {base} | {other} | change | worst scene | scenes losing > 0.3 |",
                  "| --- | --- | --- | --- | --- | --- |"]
        for split in dict.fromkeys(split for s in scenes for split in results[s][base]):
            pairs = [(results[s][base][split]["psnr"], results[s][other][split]["psnr"])
                     for s in scenes if split in results[s][base]]
            if not pairs:
                continue
            before = sum(a for a, _ in pairs) / len(pairs)
            after = sum(b for _, b in pairs) / len(pairs)
            worst = min(b - a for a, b in pairs)
            losing = sum(b - a < -NOISE_DB for a, b in pairs)
            lines.append(f"| {split} | {before:.2f} | {after:.2f} | {after - before:+.2f} | {worst:+.2f} | {losing} |")
        lines.append("")
    lines += ["**Every scene** (PSNR per split, e.g. interpolation / extrapolation; half-image PSNR; LPIPS)", "",
              f"| scene | {base} | {other} | change | half-image change | LPIPS {base} | LPIPS {other} |",
              "| --- | --- | --- | --- | --- | --- | --- |"]
    for scene, r in results.items():
        splits = list(r[base])
        psnr = {c: [r[c][s]["psnr"] for s in splits] for c in (base, other)}
        half = {c: [r[c][s]["half"]["psnr"] for s in splits] for c in (base, other)}
        lpips = {c: ["-" if r[c][s]["lpips"] is None else f"{r[c][s]['lpips']:.3f}" for s in splits]
                 for c in (base, other)}
        lines.append(f"| {scene} | {_joined(psnr[base])} | {_joined(psnr[other])} | "
                     f"{_change(psnr, base, other)} | {_change(half, base, other)} | {' / '.join(lpips[base])} | "
                     f"{' / '.join(lpips[other])} |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--setting", choices=list(SETTINGS), default="render_background",
                   help="the render-time setting compared (default: render_background)")
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
        if results.get(scene, {}).get("run") == str(run_dir) and results[scene].get("setting") == args.setting:
            continue
        print(f"{scene} ...", flush=True)
        results[scene] = score_run(run_dir, scene_dir_of(scene, args.suite_dir, args.redkitchen), args.device,
                                   args.setting)
        results_path.write_text(json.dumps(results, indent=1))
    command = shlex.join(["PYTHONPATH=.", ".venv/bin/python", "benchmarks/render_settings.py",
                          *(argv if argv is not None else sys.argv[1:])])
    text = table({s: results[s] for s in scenes}, command, args.setting)
    (args.out / "table.md").write_text(text)
    print(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
