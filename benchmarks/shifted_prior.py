"""The sampler on a prior registered in the wrong place: the VoxNeRF sampler against the prior-seeded occupancy grid
when the scene's prior is moved by a few to tens of centimetres (a SLAM mesh or TSDF cloud in a frame a little off
the images' poses), and what sampler ``auto`` chooses on each (issue #46: the sampler pays or steps aside).

Each case is a scene of the tuning suite (``--suite-dir``: suite.py's ``--suite-dir`` or its ``OUT/scenes``) with
its prior file moved by a vector (metres), written to ``OUT/scenes/<case>/`` (images and depth maps copied, the
true mesh left out). Each case is trained twice, alone, one after the other, ``--budget`` seconds each:

    voxnerf train OUT/scenes/CASE --out OUT/runs/CASE/voxnerf --max-seconds B --restart --eval-every 100000 \\
        --sampler voxnerf
    voxnerf train OUT/scenes/CASE --out OUT/runs/CASE/occgrid ... --sampler occgrid

A run whose report.json is there already is reused (``--table-only`` trains nothing). The table gives, per case,
the share of wrong first hits the voxnerf run's window check measured, the choice sampler ``auto`` makes from it
(:func:`voxnerf.training.window_check.choose_sampler`), both runs' PSNR and the grid minus the window sampler;
``table.md`` and ``results.json`` under ``--out``, and with ``--write-docs`` in docs/benchmarks.md.

    .venv/bin/python benchmarks/shifted_prior.py --suite-dir SCENES --out OUT --budget 300 \\
        --cases den:0.28,0.28,0 den:0.11,0.10,0 library:0,0.25,0.15 hall:0.2,-0.1,0.1
"""

from __future__ import annotations

import argparse
import json
import shlex
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import trimesh
from docs_section import publish
from error_vs_runtime import train_command

from voxnerf.training.window_check import choose_sampler

DOCS_PAGE = Path(__file__).resolve().parent.parent / "docs" / "benchmarks.md"
DOCS_SECTION = "shifted-prior"
SAMPLERS = ("voxnerf", "occgrid")
SPLITS = ("interpolation", "extrapolation")


def parse_case(text: str) -> tuple[str, np.ndarray]:
    """``SCENE:DX,DY,DZ`` -> (scene, shift in metres); SystemExit with the case named when malformed."""
    scene, _, vector = text.partition(":")
    try:
        shift = np.array([float(v) for v in vector.split(",")])
    except ValueError:
        shift = np.zeros(0)
    if not scene or shift.shape != (3,) or not np.isfinite(shift).all():
        raise SystemExit(f"shifted_prior.py: case {text!r}: expected SCENE:DX,DY,DZ (metres)")
    return scene, shift


def case_name(scene: str, shift: np.ndarray) -> str:
    return f"{scene}+{round(100 * float(np.linalg.norm(shift)))}cm"


def make_case(source: Path, shift: np.ndarray, out: Path) -> Path:
    """``source`` with its prior file moved by ``shift`` at ``out`` (made once: reused while its transforms.json
    is there)."""
    if (out / "transforms.json").is_file():
        return out
    if not (source / "transforms.json").is_file():
        raise SystemExit(f"shifted_prior.py: {source / 'transforms.json'}: no such scene (see --suite-dir)")
    meta = json.loads((source / "transforms.json").read_text())
    if not meta.get("prior_file_path"):
        raise SystemExit(f"shifted_prior.py: {source / 'transforms.json'}: no prior_file_path to move")
    partial = out.with_name(out.name + ".partial")
    shutil.rmtree(partial, ignore_errors=True)
    shutil.copytree(source, partial, ignore=shutil.ignore_patterns("gt_mesh.ply"))
    prior = partial / meta["prior_file_path"]
    geometry = trimesh.load(prior, process=False)
    moved = np.asarray(geometry.vertices) + shift
    if isinstance(geometry, trimesh.Trimesh):
        trimesh.Trimesh(moved, geometry.faces, process=False).export(prior)
    else:
        trimesh.PointCloud(moved).export(prior)
    meta.pop("gt_mesh_file_path", None)
    (partial / "transforms.json").write_text(json.dumps(meta))
    partial.rename(out)
    return out


def train(scene: Path, run: Path, sampler: str, budget: float, extra: list[str]) -> list[str]:
    """``voxnerf train`` of ``scene`` into ``run`` with ``sampler`` (skipped when ``run`` holds a finished report)."""
    cmd = train_command(scene, run, budget, [], ["--eval-every", "100000", "--sampler", sampler, *extra])
    report = run / "report.json"
    if not report.is_file() or json.loads(report.read_text()).get("status") != "succeeded":
        print(f"{sampler} on {scene.name} ...", flush=True)
        run.parent.mkdir(parents=True, exist_ok=True)
        log_path = run.parent / f"{sampler}.log"
        with open(log_path, "w") as log:  # its output and progress bar
            if subprocess.run(cmd, stdout=log, stderr=subprocess.STDOUT).returncode != 0:
                raise SystemExit(f"shifted_prior.py: {shlex.join(cmd[1:])} failed; its output: {log_path}")
    return cmd


def row(case: str, shift: np.ndarray, runs: Path) -> dict | None:
    """The case's two runs read back; None while either has no finished report."""
    reports = {}
    for sampler in SAMPLERS:
        path = runs / case / sampler / "report.json"
        if not path.is_file():
            return None
        reports[sampler] = json.loads(path.read_text())
    check = reports["voxnerf"].get("window_check")
    chosen, why = choose_sampler(check, has_octree=True)
    psnr = {s: {split: (reports[s]["metrics"].get(split) or {}).get("psnr") for split in SPLITS} for s in SAMPLERS}
    wrong = None if check is None else check["wrong_first_hit"]
    return {"case": case, "shift_m": shift.tolist(), "wrong_first_hit": wrong, "auto": chosen, "why": why,
            "psnr": psnr, "steps": {s: reports[s]["iteration"] for s in SAMPLERS}}


def table(rows: list[dict], command: str) -> str:
    lines = [f"Command:\n\n    {command}\n",
             "| case | prior moved | wrong first hits | `auto` chooses | voxnerf (interp. / extrap.) | occgrid | "
             "occgrid - voxnerf | steps (voxnerf / occgrid) |", "| --- | --- | --- | --- | --- | --- | --- | --- |"]
    for r in rows:
        v, g = r["psnr"]["voxnerf"], r["psnr"]["occgrid"]
        wrong = "n/a" if r["wrong_first_hit"] is None else f"{r['wrong_first_hit']:.1%}"
        lines.append(f"| {r['case']} | {100 * float(np.linalg.norm(r['shift_m'])):.0f} cm | {wrong} | {r['auto']} | "
                     f"{_pair(v, '.2f')} | {_pair(g, '.2f')} | "
                     f"{_pair({s: _minus(g[s], v[s]) for s in SPLITS}, '+.2f')} | "
                     f"{r['steps']['voxnerf']} / {r['steps']['occgrid']} |")
    return "\n".join(lines) + "\n"


def _minus(a: float | None, b: float | None) -> float | None:
    return None if a is None or b is None else a - b


def _pair(scores: dict[str, float | None], spec: str) -> str:
    """``interpolation / extrapolation`` (n/a for a split the scene lacks)."""
    return " / ".join("n/a" if scores[s] is None else format(scores[s], spec) for s in SPLITS)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--suite-dir", type=Path, required=True, help="the tuning suite's scenes (suite.py --suite-dir)")
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--budget", type=float, default=300.0, help="--max-seconds of each run")
    ap.add_argument("--cases", nargs="+", required=True, help="SCENE:DX,DY,DZ, the prior's shift in metres")
    ap.add_argument("--table-only", action="store_true", help="train nothing; table the runs under --out")
    ap.add_argument("--write-docs", action="store_true", help="the table into docs/benchmarks.md too")
    ap.add_argument("--train-args", default="", help="more `voxnerf train` flags for every run, one string: "
                    "--train-args=\"--no-compile --max-iters 2\"")
    args = ap.parse_args(argv)
    cases = [parse_case(c) for c in args.cases]
    rows = []
    for scene, shift in cases:
        case = case_name(scene, shift)
        if not args.table_only:
            scene_dir = make_case(args.suite_dir / scene, shift, args.out / "scenes" / case)
            for sampler in SAMPLERS:
                train(scene_dir, args.out / "runs" / case / sampler, sampler, args.budget, shlex.split(args.train_args))
        if (found := row(case, shift, args.out / "runs")) is not None:
            rows.append(found)
    command = ".venv/bin/python benchmarks/shifted_prior.py " + shlex.join(sys.argv[1:] if argv is None else argv)
    publish(args.out, {"command": command, "rows": rows}, table(rows, command), DOCS_PAGE, DOCS_SECTION,
            args.write_docs)
    return 0


if __name__ == "__main__":
    sys.exit(main())
