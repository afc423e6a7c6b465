"""Where a training step's time goes: the loop's phases (the batch with its sampling, the forward and backward
pass, the optimiser update) and each periodic duty, per configuration, side by side in one process.

Each configuration trains ``--warm`` (+ ``--trace``) + ``--steps`` steps of the real training run (set-up,
compiled step, callbacks as ``voxnerf train`` has them); only the last ``--steps`` are timed (the warm ones
compile the step's graphs). A device sync closes every phase, so a phase's time is its own even on a GPU,
where work is queued. The run's own ``throughput`` (also printed) has no syncs but counts every step, the
warm and traced ones too.
``--trace N`` records N steps after the warm ones with ``torch.profiler`` and keeps the operators (and CUDA
kernels) that took the most time; those steps are not timed. ``--count-syncs N`` (CUDA only) runs N steps after the
warm ones under ``torch.cuda.set_sync_debug_mode("warn")`` and counts, per phase, the operations that made the
host wait for the device (the divergence guard's read of the loss is one per step by design); those steps are not
timed either. Each row says how the voxnerf sampler filled the rays that missed its octree (``octree_misses``:
``--config NAME='{"octree_misses": "gather"}'`` runs the path with the host sync, ``"mask"`` the one without).

    .venv/bin/python benchmarks/step_profile.py SCENE [--downscale 2] [--steps 40] [--warm 8]
        [--config NAME=JSON ...] [--trace 5] [--count-syncs 4] [--json OUT.json]

``--config paper='{"preset": "paper"}'`` sets TrainConfig fields over the defaults (repeatable; default: the
``cpu`` and ``paper`` presets).
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
import warnings
from collections import defaultdict
from collections.abc import Callable
from pathlib import Path

import torch

import voxnerf.training.loop as training_loop
import voxnerf.training.run as training_run
from voxnerf.config import TrainConfig
from voxnerf.devices import resolve_device
from voxnerf.training.loop import Callback

DEFAULT_CONFIGS = {"cpu": {}, "paper": {"preset": "paper"}}


class PhaseClock:
    """Seconds per named phase on the steps after the first ``warm``, each phase closed by ``sync`` (a no-op
    on a CPU)."""

    def __init__(self, sync: Callable[[], None], warm: int) -> None:
        self.sync, self.warm = sync, warm
        self.steps = 0  # steps begun so far (the loop's batch counts them)
        self.seconds: dict[str, list[float]] = defaultdict(list)

    def timed(self, name: str, fn: Callable) -> Callable:
        """``fn`` timed under ``name`` on the steps after the warm ones."""
        def wrapper(*args, **kwargs):
            if self.steps <= self.warm:
                return fn(*args, **kwargs)
            self.sync()
            t0 = time.perf_counter()
            result = fn(*args, **kwargs)
            self.sync()
            self.seconds[name].append(time.perf_counter() - t0)
            return result
        return wrapper

    def milliseconds(self, steps: int) -> dict[str, float]:
        """Each phase's mean milliseconds per step (a duty that ran on some steps only, spread over all)."""
        return {name: 1000.0 * sum(times) / steps for name, times in self.seconds.items()}


class StepTrace:
    """``torch.profiler`` over the ``n`` steps after the warm ones: the top operators by self time."""

    def __init__(self, n: int, warm: int, device: torch.device) -> None:
        self.n, self.warm, self.cuda = n, warm, device.type == "cuda"
        self.profiler: torch.profiler.profile | None = None
        self.table = ""

    def at_batch(self, step: int) -> None:
        """Before step ``step``'s batch: start recording at the first step after the warm ones, stop after ``n``."""
        if self.n <= 0:
            return
        if step == self.warm + 1:
            activities = [torch.profiler.ProfilerActivity.CPU]
            if self.cuda:
                activities.append(torch.profiler.ProfilerActivity.CUDA)
            self.profiler = torch.profiler.profile(activities=activities)
            self.profiler.__enter__()
        elif step == self.warm + 1 + self.n and self.profiler is not None:
            self.finish()

    def finish(self) -> None:
        if self.profiler is None:
            return
        if self.cuda:
            torch.cuda.synchronize()
        self.profiler.__exit__(None, None, None)
        key = "self_device_time_total" if self.cuda else "self_cpu_time_total"
        self.table = self.profiler.key_averages().table(sort_by=key, row_limit=25, max_name_column_width=60)
        self.profiler = None


SYNC_WARNING = "synchronizing CUDA operation"  # what torch's sync debug mode says of each host sync


class SyncCount:
    """On CUDA, the host syncs of each phase over the ``n`` steps after the first ``start`` (under
    ``torch.cuda.set_sync_debug_mode("warn")``, which warns at every operation that waits for the device);
    nothing elsewhere."""

    def __init__(self, n: int, start: int, device: torch.device) -> None:
        self.n, self.start, self.cuda = n, start, device.type == "cuda"
        self.step = 0  # steps begun so far
        self.counts: dict[str, int] = defaultdict(int)

    @property
    def active(self) -> bool:
        return self.cuda and self.start < self.step <= self.start + self.n

    def counted(self, name: str, fn: Callable) -> Callable:
        """``fn`` with its host syncs counted under ``name`` on the counted steps."""
        def wrapper(*args, **kwargs):
            if not self.active:
                return fn(*args, **kwargs)
            with warnings.catch_warnings(record=True) as caught:
                warnings.simplefilter("always")
                torch.cuda.set_sync_debug_mode("warn")
                try:
                    return fn(*args, **kwargs)
                finally:
                    torch.cuda.set_sync_debug_mode("default")
                    self.counts[name] += sum(SYNC_WARNING in str(w.message) for w in caught)
        return wrapper

    def per_step(self) -> dict[str, float] | None:
        """Host syncs per step by phase (None where nothing was counted: no CUDA, or no counted steps)."""
        if not self.cuda or self.n <= 0:
            return None
        return {name: count / self.n for name, count in self.counts.items()}


def instrumented_loop(clock: PhaseClock, trace: StepTrace, syncs: SyncCount) -> Callable:
    """``run_loop`` with the step's phases and every callback hook timed by ``clock`` and their host syncs
    counted by ``syncs`` (the divergence guard's too)."""
    real_loop = training_run.run_loop

    def phase(name: str, fn: Callable) -> Callable:
        return clock.timed(name, syncs.counted(name, fn))

    def run_loop(step, state, callbacks, limits):
        timed_batch = phase("batch (rays, sampling)", step.batch)

        def batch():  # a step begins: count it, start or stop the trace, then draw (and time) the batch
            clock.steps += 1
            syncs.step = clock.steps
            trace.at_batch(clock.steps)
            return timed_batch()

        step.batch = batch
        step.losses = phase("forward + backward", step.losses)
        step.apply = phase("optimiser update", step.apply)
        for callback in callbacks:
            for hook in ("before_step", "after_step"):
                if getattr(type(callback), hook) is not getattr(Callback, hook):  # as the loop picks its hooks
                    setattr(callback, hook, phase(type(callback).__name__, getattr(callback, hook)))
        real_guard = training_loop.divergence_guard
        training_loop.divergence_guard = syncs.counted("divergence guard", real_guard)  # not timed: one float()
        try:
            return real_loop(step, state, callbacks, limits)
        finally:
            training_loop.divergence_guard = real_guard
            trace.finish()

    return run_loop


def profile_config(scene: Path, run_dir: Path, overrides: dict, downscale: int | None, steps: int, warm: int,
                   trace_steps: int, device: str, sync_steps: int = 0) -> dict:
    """Train ``warm + sync_steps + trace_steps + steps`` steps of ``overrides``, the last ``steps`` timed -> the
    profile's row (``sync_steps`` counted for host syncs on CUDA, ``trace_steps`` traced, after the warm ones)."""
    scale = {} if downscale is None else {"downscale": downscale}
    cfg = TrainConfig(**overrides | scale, max_iters=warm + sync_steps + trace_steps + steps, final_eval=False,
                      eval_every_s=1e9, checkpoint_every_s=1e9, device=device)
    torch_device = resolve_device(device)
    sync = torch.cuda.synchronize if torch_device.type == "cuda" else (lambda: None)
    clock = PhaseClock(sync, warm + sync_steps + trace_steps)
    syncs = SyncCount(sync_steps, warm, torch_device)
    trace = StepTrace(trace_steps, warm + sync_steps, torch_device)
    real_loop = training_run.run_loop
    training_run.run_loop = instrumented_loop(clock, trace, syncs)
    try:
        report = training_run.train(scene, run_dir, cfg, resume=False, progress_bar=False)
    finally:
        training_run.run_loop = real_loop
    ms = clock.milliseconds(max(1, clock.steps - clock.warm))
    calls = {name: len(times) for name, times in clock.seconds.items()}
    runtime = report.runtime or {}
    return {"config": report.config, "device": report.device, "octree_misses": runtime.get("octree_misses"),
            "phases_ms": ms, "phase_calls": calls, "step_ms": sum(ms.values()), "host_syncs_per_step": syncs.per_step(),
            "throughput": report.throughput, "trace": trace.table,
            "stages": {s.name: s.seconds for s in report.stages}}


def _config_arg(text: str) -> tuple[str, dict]:
    name, _, value = text.partition("=")
    if not name or not value:
        raise argparse.ArgumentTypeError(f"--config {text!r}: expected NAME=JSON")
    try:
        overrides = json.loads(value)
    except json.JSONDecodeError as exc:
        raise argparse.ArgumentTypeError(f"--config {name}: {exc}") from None
    if not isinstance(overrides, dict):
        raise argparse.ArgumentTypeError(f"--config {name}: expected a JSON object")
    return name, overrides


def print_rows(rows: dict[str, dict]) -> None:
    for name, row in rows.items():
        t = row["throughput"]
        print(f"\n## {name} on {row['device']} (octree misses: {row['octree_misses']}): {row['step_ms']:.1f} ms per "
              f"step with a sync after each phase; the run's own rate over all its steps, compilation left out: "
              f"{t.get('samples_per_s', 0) / 1e6:.2f} M samples/s, {t.get('rays_per_s', 0) / 1e3:.1f} K rays/s")
        for phase, ms in sorted(row["phases_ms"].items(), key=lambda kv: -kv[1]):
            print(f"  {phase:28s} {ms:8.2f} ms")
        if row["host_syncs_per_step"] is not None:
            print("  host syncs per step: " + ", ".join(f"{phase} {n:g}" for phase, n in
                                                       sorted(row["host_syncs_per_step"].items())))
        if row["trace"]:
            print(row["trace"])


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("scene", type=Path)
    p.add_argument("--downscale", type=int)
    p.add_argument("--steps", type=int, default=40, help="timed steps per configuration")
    p.add_argument("--warm", type=int, default=8, help="steps before the timed ones (compilation)")
    p.add_argument("--config", type=_config_arg, action="append", help="NAME=JSON of TrainConfig fields")
    p.add_argument("--trace", type=int, default=0, help="steps recorded with torch.profiler")
    p.add_argument("--count-syncs", type=int, default=0, help="steps whose host syncs are counted (CUDA)")
    p.add_argument("--device", default="auto")
    p.add_argument("--json", type=Path, help="write the rows here too")
    args = p.parse_args(argv)
    configs = dict(args.config) if args.config else DEFAULT_CONFIGS
    rows = {}
    with tempfile.TemporaryDirectory() as tmp:
        for name, overrides in configs.items():
            rows[name] = profile_config(args.scene, Path(tmp) / name, overrides, args.downscale, args.steps,
                                        args.warm, args.trace, args.device, args.count_syncs)
            print_rows({name: rows[name]})
            if args.json is not None:
                args.json.write_text(json.dumps({"command": " ".join(sys.argv), "rows": rows}, indent=1,
                                                default=str))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
