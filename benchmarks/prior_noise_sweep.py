"""Prior-noise sweep: PSNR as the prior's true noise and its stated ``prior_sigma`` vary.

On the synthetic room, for each setting a point-cloud prior is sampled from the true mesh with Gaussian noise
of std ``true`` per axis (plus the synthetic generator's outliers and holes: ``voxnerf.synthetic.
sample_point_prior``) and written as a sibling scene stating ``prior_sigma = factor * true``; then one
``voxnerf train`` run (voxnerf sampler with the depth loss) per scene, same wall-clock budget. The default
settings grow the true noise with a correct statement, and state the middle noise level 3x too small and 3x
too large. Writes ``prior_noise.csv``, ``prior_noise.md`` and ``prior_noise_results.json`` under ``--out``.

    .venv/bin/python benchmarks/prior_noise_sweep.py --budget 300 --out OUT
    .venv/bin/python benchmarks/prior_noise_sweep.py --quick --out /tmp/noise    # CI-sized smoke run
"""

from __future__ import annotations

import argparse
import json
import shlex
from pathlib import Path

import numpy as np
from error_vs_runtime import (
    QUICK_BUDGET,
    QUICK_SAMPLES,
    QUICK_TRAIN_ARGS,
    eval_splits,
    final_psnr,
    make_scene,
    markdown_table,
    run_training,
    write_csv,
    write_results_json,
    write_text,
)
from make_priors import write_prior_scene

from voxnerf.errors import SceneError
from voxnerf.synthetic import build_room, sample_point_prior

DEFAULT_SETTINGS = "0.01:1,0.02:1,0.05:1,0.1:1,0.02:0.3333,0.02:3"
QUICK_SETTINGS = "0.05:1,0.05:3"


def parse_settings(text: str) -> list[tuple[float, float]]:
    """``"0.02:1,0.02:3"`` -> ``[(true noise m, stated factor), ...]``; ValueError unless all positive."""
    settings = []
    for item in (p for p in text.split(",") if p):
        try:
            true, factor = (float(v) for v in item.split(":"))
        except ValueError:
            raise ValueError(f"expected TRUE_NOISE:FACTOR pairs of numbers, got {item!r}") from None
        if not (np.isfinite([true, factor]).all() and true > 0 and factor > 0):
            raise ValueError(f"noise and factor must be positive and finite, got {item!r}")
        settings.append((true, factor))
    if not settings:
        raise ValueError("no TRUE_NOISE:FACTOR setting given")
    return settings


def noisy_prior_scene(scene: Path, out: Path, true: float, factor: float, max_points: int) -> Path:
    """``out/noise-<true>-stated-<stated>``: ``scene`` with a point prior of true noise ``true`` (m) stated
    as ``factor * true``. ``scene`` must be the synthetic room (its ``voxnerf_synthetic.seed`` rebuilds the
    true geometry); the noise is seeded by the setting, so reruns write the same prior."""
    meta = json.loads((scene / "transforms.json").read_text())
    synthetic = meta.get("voxnerf_synthetic")
    if not synthetic:
        raise SceneError(
            scene / "transforms.json",
            "the prior-noise sweep needs the synthetic room's ground truth",
            key="voxnerf_synthetic",
        )
    stated = true * factor
    dst = out / f"noise-{true:g}-stated-{stated:.4g}"
    if (dst / "transforms.json").is_file():
        return dst
    rng = np.random.default_rng([int(synthetic["seed"]), round(true * 1e6)])
    points, info = sample_point_prior(build_room(int(synthetic["seed"])), true, max_points, rng)
    info |= {"source": "prior_noise_sweep", "true_noise": true, "stated_factor": factor}
    return write_prior_scene(scene, dst, points, stated, info)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--scene", default="room", help="'room' (generated) or a synthetic room scene directory"
    )
    parser.add_argument(
        "--settings",
        help=f"TRUE_NOISE_M:STATED_FACTOR list (default {DEFAULT_SETTINGS}; --quick: {QUICK_SETTINGS})",
    )
    parser.add_argument("--budget", type=float, default=300.0, help="--max-seconds of every run")
    parser.add_argument("--max-points", type=int, default=300_000, help="cap on prior points per setting")
    parser.add_argument("--train-args", default="", help="extra `voxnerf train` flags")
    parser.add_argument(
        "--quick", action="store_true", help="smoke run: tiny room, 2 settings, 5 steps each, --no-compile"
    )
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args(argv)
    try:
        settings = parse_settings(args.settings or (QUICK_SETTINGS if args.quick else DEFAULT_SETTINGS))
    except ValueError as err:
        parser.error(str(err))
    if args.quick:
        args.budget, args.max_points = QUICK_BUDGET, 20_000
    args.out.mkdir(parents=True, exist_ok=True)
    scene = make_scene(args.scene, args.out, args.quick)
    extra = shlex.split(args.train_args) + ([*QUICK_TRAIN_ARGS, *QUICK_SAMPLES] if args.quick else [])
    results, rows = [], []
    try:
        variants = [noisy_prior_scene(scene, args.out, t, f, args.max_points) for t, f in settings]
    except SceneError as err:
        parser.error(str(err))
    for (true, factor), variant in zip(settings, variants, strict=True):
        res = run_training(
            variant.name,
            variant,
            args.out / "runs" / variant.name,
            args.budget,
            [],
            ["--sampler", "voxnerf", *extra],
        )
        results.append(res)
        rows.append(
            {
                "true_noise_m": true,
                "stated_sigma_m": round(true * factor, 6),
                "stated_factor": factor,
                "iterations": res["report"].get("iteration", 0),
            }
            | {f"psnr_{s}": round(v, 4) for s, v in final_psnr(res).items()}
        )
    splits = eval_splits(results[0])
    write_csv(rows, args.out / "prior_noise.csv")
    lines = markdown_table(
        ["true noise (m)", "stated sigma (m)", "stated / true", *(f"PSNR {s}" for s in splits), "iterations"],
        [
            [f"{r['true_noise_m']:g}", f"{r['stated_sigma_m']:.4g}", f"{r['stated_factor']:.3g}",
             *(f"{r[f'psnr_{s}']:.2f}" for s in splits), str(r["iterations"])]
            for r in rows
        ],
    )
    lines += [
        "",
        f"Final PSNR (dB) of runs with --max-seconds {args.budget:g} each (voxnerf sampler, depth loss; "
        "the commands below give every flag).",
        "",
        "Commands:",
        "",
    ] + [f"    {r['command']}" for r in results]
    table = "\n".join(lines)
    write_text(args.out / "prior_noise.md", table + "\n")
    write_results_json(results, args.out / "prior_noise_results.json", ("metrics",))
    print(table)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
