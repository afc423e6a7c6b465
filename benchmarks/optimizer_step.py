"""Time of one Adam step over the field's parameters: per-tensor loop, foreach and fused, side by side.

The hash table dominates the field's parameters (2^17 or 2^19 entries per level), and Adam touches every entry
every step, so its implementation matters on a CPU. Alternates the implementations in rounds so all see the
same machine load, and replaces the marked ``optimizer`` section of docs/performance.md.

    .venv/bin/python benchmarks/optimizer_step.py [--steps 20] [--repeats 3] [--out docs/performance.md]
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import torch
from docs_section import replace_section

from voxnerf.config import TrainConfig
from voxnerf.model.field import RadianceField
from voxnerf.model.voxnerf_model import field_for

IMPLEMENTATIONS = {"loop": {"foreach": False}, "foreach": {"foreach": True}, "fused": {"fused": True}}


def _step_ms(field: RadianceField, options: dict, steps: int) -> float:
    """Median milliseconds of ``optimizer.step()`` with dense random gradients (Adam's cost ignores values)."""
    params = list(field.parameters())
    for p in params:
        p.grad = torch.randn_like(p)
    optimizer = torch.optim.Adam(params, lr=1e-2, eps=1e-15, **options)
    for _ in range(3):
        optimizer.step()
    times = []
    for _ in range(steps):
        t0 = time.perf_counter()
        optimizer.step()
        times.append(time.perf_counter() - t0)
    return 1e3 * statistics.median(times)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=20)
    parser.add_argument("--repeats", type=int, default=3, help="alternating rounds per implementation")
    parser.add_argument("--out", type=Path, default=Path("docs/performance.md"))
    args = parser.parse_args()
    sizes = [("cpu", 17), ("cpu", 19), ("paper", 19)]
    fields = {size: field_for(TrainConfig(preset=size[0], hash_log2_size=size[1])) for size in sizes}
    ms: dict[tuple, list[float]] = {}
    for _ in range(args.repeats):
        for size, field in fields.items():
            for name, options in IMPLEMENTATIONS.items():
                ms.setdefault((size, name), []).append(_step_ms(field, options, args.steps))
    lines = [
        f"Measured {time.strftime('%Y-%m-%d')}, {torch.get_num_threads()} torch threads, torch {torch.__version__}. "
        f"Command: `.venv/bin/python {' '.join(sys.argv)}`",
        "",
        f"Median time of one `Adam.step()` over the whole field (median of {args.steps} steps, best of "
        f"{args.repeats} alternating rounds).",
        "",
        "| field | parameters | loop | foreach | fused | loop / fused |",
        "| --- | --- | --- | --- | --- | --- |",
    ]
    for size, field in fields.items():
        best = {name: min(ms[(size, name)]) for name in IMPLEMENTATIONS}
        n = sum(p.numel() for p in field.parameters())
        lines.append(
            f"| preset `{size[0]}`, 2^{size[1]} per level | {n / 1e6:.1f} M | {best['loop']:.1f} ms | "
            f"{best['foreach']:.1f} ms | {best['fused']:.1f} ms | {best['loop'] / best['fused']:.1f}x |"
        )
    replace_section(args.out, "optimizer", "\n".join(lines))
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
