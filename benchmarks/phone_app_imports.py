"""Import time and pose agreement of the LiDAR phone-app importers on redkitchen written in each app's layout.

For each app (Record3D, Polycam, Stray Scanner) the shared redkitchen frames are written in the app's export
layout exactly as the tests write them (``tests/phone_app_fixtures.py``: poses in the app's convention, depth
resampled to 256 x 192, confidence maps with low and medium regions; Stray's colour as an H.264 MP4), then
imported with ``voxnerf import <app>``. Only the import is timed. Reported per app: frames imported, frames with
depth, measured depth pixels dropped for low confidence, the largest pose difference from the source (against the
nearest rotation for the quaternion apps), and the import's wall time. With ``--train SECONDS`` each app is
imported with ``--splits paper`` and each imported scene, and the given scene cut to the same frames and splits,
trains for that long (``voxnerf train``, one after another; ``--train-args`` adds options such as ``--max-iters``);
their evaluation metrics join the table.

    python benchmarks/phone_app_imports.py [--frames N] [--stride K] [--train S] [--out DIR]
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
sys.path.insert(0, str(Path(__file__).resolve().parent))
from import_captures import given_subset, source_by_pose, train  # noqa: E402  (one definition of a training row)
from phone_app_fixtures import (  # noqa: E402  (the tests' export writers, one definition)
    REDKITCHEN,
    nearest_rigid,
    redkitchen_frames,
    write_polycam,
    write_record3d,
    write_stray,
)

from voxnerf.data.importers import PaperSplitRule  # noqa: E402
from voxnerf.data.importers.polycam import import_polycam  # noqa: E402
from voxnerf.data.importers.record3d import import_record3d  # noqa: E402
from voxnerf.data.importers.stray import import_stray  # noqa: E402

APPS = {
    "record3d": (write_record3d, import_record3d, True),
    "polycam": (write_polycam, import_polycam, False),
    "stray": (write_stray, import_stray, True),
}


def measure(app: str, frames: list[dict], work: Path, splits: PaperSplitRule | None = None) -> dict:
    write, run_import, quaternions = APPS[app]
    export = write(work / f"{app}_export", frames)
    start = time.perf_counter()
    summary = run_import(export, work / f"{app}_scene", splits)
    seconds = time.perf_counter() - start
    meta = json.loads((work / f"{app}_scene" / "transforms.json").read_text())
    error = 0.0
    for got, want in zip(meta["frames"], frames, strict=True):
        reference = np.asarray(want["transform_matrix"])
        reference = nearest_rigid(reference) if quaternions else reference
        error = max(error, float(np.abs(np.asarray(got["transform_matrix"]) - reference).max()))
    dropped = next((n for n in summary["notes"] if "measured depth pixels" in n), "")
    return {"app": app, "frames": summary["frames"], "depth_frames": summary["depth_frames"],
            "max_pose_difference": error, "import_seconds": round(seconds, 2),
            "depth_note": dropped.split("; ")[-1]}


def psnr_cell(row: dict) -> str:
    """``split imported / given; ...`` PSNR of the training runs, or "not run"."""
    if "train" not in row:
        return "not run"
    given = row["given_train"]["metrics"]
    return "; ".join(f"{split} {m['psnr']:.2f} / {given[split]['psnr']:.2f}"
                     for split, m in row["train"]["metrics"].items())


def table(rows: list[dict]) -> str:
    lines = ["| app | frames | with depth | largest pose difference | import time (s) | depth dropped | "
             "PSNR (imported / given) |", "| --- | --- | --- | --- | --- | --- | --- |"]
    lines += [f"| {r['app']} | {r['frames']} | {r['depth_frames']} | {r['max_pose_difference']:.1e} | "
              f"{r['import_seconds']:.1f} | {r['depth_note']} | {psnr_cell(r)} |" for r in rows]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=1000, help="redkitchen frames to write (default: all 1000)")
    parser.add_argument("--stride", type=int, default=1,
                        help="source frames between written frames (5: every frame has depth, as redkitchen's depth "
                        "is on every 5th)")
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results/phone_app_imports"))
    parser.add_argument("--train", type=float, default=0.0, metavar="SECONDS",
                        help="also train each imported scene and the given one this long (0: no training)")
    parser.add_argument("--train-args", default="", help="more `voxnerf train` options for every run")
    args = parser.parse_args(argv)
    if not (REDKITCHEN / "transforms.json").is_file():
        print(f"redkitchen not found at {REDKITCHEN}", file=sys.stderr)
        return 2
    frames = redkitchen_frames(args.frames * args.stride)[::args.stride]
    splits = PaperSplitRule() if args.train else None
    given_runs: dict[str, dict] = {}  # one run of the given scene per distinct frame set and splits
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        rows = []
        for app in APPS:
            row = measure(app, frames, tmp, splits)
            if args.train:
                scene, extra = tmp / f"{app}_scene", args.train_args.split()
                row["train"] = train(scene, tmp / f"{app}_run", args.train, extra)
                given = given_subset(REDKITCHEN, scene, source_by_pose(REDKITCHEN, scene), tmp / f"{app}_given")
                key = (given / "transforms.json").read_text()
                if key not in given_runs:
                    given_runs[key] = train(given, tmp / f"{app}_given_run", args.train, extra)
                row["given_train"] = given_runs[key]
            print(json.dumps(row), flush=True)
            rows.append(row)
    command = "python benchmarks/phone_app_imports.py " + " ".join(argv if argv is not None else sys.argv[1:])
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "results.json").write_text(json.dumps({"command": command, "results": rows}, indent=2) + "\n")
    (args.out / "table.md").write_text(f"`{command}`\n\n{table(rows)}\n")
    print(table(rows))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
