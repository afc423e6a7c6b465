"""Samples-per-ray sweep: quality and training throughput of the surface-guided sampler per (N_imp, N_rest).

For each pair, one ``voxnerf train --sampler voxnerf --samples N_IMP,N_REST`` run with the same wall-clock
budget (runs one after the other). Reports the final PSNR per evaluation split, iterations, training rays/s
and samples/s (training steps only, compile excluded), and names the cheapest pair whose PSNR on every split
is within ``KEEP_DB`` of the best pair's: the candidate for the CPU preset. Writes ``samples.csv``,
``samples.md`` and ``samples_results.json`` under ``--out``.

    .venv/bin/python benchmarks/samples_sweep.py --scene room --budget 300 --out OUT
    .venv/bin/python benchmarks/samples_sweep.py --quick --out /tmp/samples    # CI-sized smoke run
"""

from __future__ import annotations

import argparse
import shlex
from pathlib import Path

from error_vs_runtime import (
    QUICK_BUDGET,
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

DEFAULT_PAIRS = "4:2,8:4,16:8,32:16,64:32"
QUICK_PAIRS = "4:2,8:4"
KEEP_DB = 0.5
"""A pair "keeps quality" when its PSNR on every split is within this many dB of the best pair's."""


def parse_pairs(text: str) -> list[tuple[int, int]]:
    """``"4:2,8:4"`` -> ``[(4, 2), (8, 4)]``; ValueError for anything that is not positive integer pairs."""
    pairs = []
    for item in (p for p in text.split(",") if p):
        parts = item.split(":")
        if len(parts) != 2 or not all(p.isdigit() and int(p) > 0 for p in parts):
            raise ValueError(f"expected N_IMP:N_REST pairs of positive integers, got {item!r}")
        pairs.append((int(parts[0]), int(parts[1])))
    if not pairs:
        raise ValueError("no (N_imp, N_rest) pair given")
    return pairs


def sweep_rows(results: list[dict], pairs: list[tuple[int, int]]) -> list[dict]:
    """One flat row per run: pair, samples per ray, PSNR per split, iterations, rays/s, samples/s."""
    rows = []
    for (n_imp, n_rest), res in zip(pairs, results, strict=True):
        rate = res["report"].get("throughput", {})
        row = {
            "n_importance": n_imp,
            "n_rest": n_rest,
            "samples_per_ray": n_imp + n_rest,
            "iterations": res["report"].get("iteration", 0),
        }
        row |= {f"psnr_{split}": round(value, 4) for split, value in final_psnr(res).items()}
        row |= {
            "rays_per_s": round(rate.get("rays_per_s", 0.0), 1),
            "samples_per_s": round(rate.get("samples_per_s", 0.0), 1),
        }
        rows.append(row)
    return rows


def cheapest_keeping_quality(rows: list[dict], splits: list[str]) -> dict | None:
    """The row with the fewest samples per ray whose PSNR on every split is within ``KEEP_DB`` of the best."""
    best = {s: max(r[f"psnr_{s}"] for r in rows) for s in splits}
    keep = [r for r in rows if all(r[f"psnr_{s}"] >= best[s] - KEEP_DB for s in splits)]
    return min(keep, key=lambda r: r["samples_per_ray"]) if keep else None


def markdown(rows: list[dict], splits: list[str], budget: float, commands: list[str]) -> str:
    lines = markdown_table(
        ["N_imp", "N_rest", "samples/ray", *(f"PSNR {s}" for s in splits), "iterations", "rays/s", "samples/s"],
        [
            [str(r["n_importance"]), str(r["n_rest"]), str(r["samples_per_ray"]),
             *(f"{r[f'psnr_{s}']:.2f}" for s in splits), str(r["iterations"]), f"{r['rays_per_s']:,.0f}",
             f"{r['samples_per_s']:,.0f}"]
            for r in rows
        ],
    )
    pick = cheapest_keeping_quality(rows, splits)
    lines += [
        "",
        f"Final PSNR (dB) of runs with --max-seconds {budget:g} each (the commands below give every flag); "
        "throughput over the training steps.",
        "",
        f"Cheapest pair within {KEEP_DB} dB of the best on every split: "
        + (f"({pick['n_importance']}, {pick['n_rest']})." if pick else "none."),
        "",
        "Commands:",
        "",
    ] + [f"    {c}" for c in commands]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--scene", default="room", help="'room' (synthetic) or a scene directory with a prior"
    )
    parser.add_argument(
        "--pairs", help=f"N_IMP:N_REST list (default {DEFAULT_PAIRS}; --quick: {QUICK_PAIRS})"
    )
    parser.add_argument("--budget", type=float, default=300.0, help="--max-seconds of every run")
    parser.add_argument(
        "--train-args", default="", help="extra `voxnerf train` flags, e.g. '--no-depth-loss'"
    )
    parser.add_argument(
        "--quick", action="store_true", help="smoke run: tiny room, 2 pairs, 5 steps each, --no-compile"
    )
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args(argv)
    try:
        pairs = parse_pairs(args.pairs or (QUICK_PAIRS if args.quick else DEFAULT_PAIRS))
    except ValueError as err:
        parser.error(str(err))
    if args.quick:
        args.budget = QUICK_BUDGET
    args.out.mkdir(parents=True, exist_ok=True)
    scene = make_scene(args.scene, args.out, args.quick)
    extra = shlex.split(args.train_args) + (list(QUICK_TRAIN_ARGS) if args.quick else [])
    results = [
        run_training(
            f"{n}:{m}",
            scene,
            args.out / "runs" / f"samples-{n}-{m}",
            args.budget,
            [],
            ["--sampler", "voxnerf", "--samples", f"{n},{m}", *extra],
        )
        for n, m in pairs
    ]
    rows = sweep_rows(results, pairs)
    splits = eval_splits(results[0])
    write_csv(rows, args.out / "samples.csv")
    table = markdown(rows, splits, args.budget, [r["command"] for r in results])
    write_text(args.out / "samples.md", table + "\n")
    write_results_json(results, args.out / "samples_results.json", ("metrics", "throughput"))
    print(table)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
