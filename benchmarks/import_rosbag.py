"""``voxnerf import rosbag`` on redkitchen: the shared frames written as a robot's ROS 2 MCAP bag (JPEG colour,
16UC1 depth on every 5th frame, CameraInfo, a /tf chain map -> odom -> base_link over a static camera mount, as
the tests make it), imported with the default motion rule and with every frame; time to write and import, frames
kept, frames with depth, and the pose error against the given poses (rotation in degrees, camera centre as a
fraction of the trajectory's length; no similarity fit is needed, the bag carries metric poses in the source's
own world frame).

    python benchmarks/import_rosbag.py --frames 1000 --out /tmp/import_rosbag [--train S]

Writes ``results.json`` in ``--out`` beside the bag and the two scenes. With ``--train SECONDS`` both imports use
``--splits paper``, and each imported scene and the given scene cut to the same frames and splits train for that
long (``voxnerf train``, one after another; ``--train-args`` adds options); their metrics join the results.
"""

from __future__ import annotations

import argparse
import json
import math
import shutil
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
sys.path.insert(0, str(Path(__file__).resolve().parent))
from import_captures import REDKITCHEN, given_subset, source_by_pose, train  # noqa: E402  (one training row)
from rosbag_fixtures import BagSpec, make_frames, write_bag  # noqa: E402

from voxnerf.data.importers import PaperSplitRule, RosbagOptions, import_rosbag  # noqa: E402


def pose_errors(meta: dict, frames: list) -> tuple[float, float]:
    """Largest rotation error (degrees) and centre error (metres) of each imported frame against the source
    frame nearest to it (the motion rule keeps a subset, in capture order)."""
    source = np.stack([f.c2w_gl for f in frames])
    rot_err, centre_err = 0.0, 0.0
    for entry in meta["frames"]:
        m = np.asarray(entry["transform_matrix"])
        want = source[int(np.argmin(np.abs(source - m).reshape(len(frames), -1).max(axis=1)))]
        cos = (np.trace(want[:3, :3].T @ m[:3, :3]) - 1) / 2
        rot_err = max(rot_err, math.degrees(math.acos(min(1.0, max(-1.0, cos)))))
        centre_err = max(centre_err, float(np.linalg.norm(m[:3, 3] - want[:3, 3])))
    return rot_err, centre_err


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--frames", type=int, default=1000, help="redkitchen frames in the bag (at most 1000)")
    parser.add_argument("--stride", type=int, default=1, help="source frames between frames in the bag")
    parser.add_argument("--out", type=Path, required=True, help="folder for the bag, the scenes and results.json")
    parser.add_argument("--train", type=float, default=0.0, metavar="SECONDS",
                        help="also train each imported scene and the given one this long (0: no training)")
    parser.add_argument("--train-args", default="", help="more `voxnerf train` options for every run")
    parser.add_argument("--imports", default="by_motion,all_frames", help="which imports to make (comma-separated)")
    args = parser.parse_args()
    shutil.rmtree(args.out, ignore_errors=True)
    args.out.mkdir(parents=True)
    frames = make_frames(step=args.stride, n=args.frames)
    start = time.perf_counter()
    bag = write_bag(args.out / "redkitchen_bag", BagSpec(frames, colour="jpeg", scale=1), "mcap")
    results = {"frames": len(frames), "write_s": round(time.perf_counter() - start, 2),
               "bag_mb": round(sum(p.stat().st_size for p in bag.rglob("*")) / 1e6, 1)}
    centres = np.stack([f.c2w_gl[:3, 3] for f in frames])
    trajectory = float(np.linalg.norm(np.diff(centres, axis=0), axis=1).sum())
    splits = PaperSplitRule() if args.train else None
    imports = {"by_motion": RosbagOptions(), "all_frames": RosbagOptions(all_frames=True)}
    for name in args.imports.split(","):
        start = time.perf_counter()
        summary = import_rosbag(bag, args.out / name, splits, options=imports[name])
        seconds = time.perf_counter() - start
        meta = json.loads((args.out / name / "transforms.json").read_text())
        rot, centre = pose_errors(meta, frames)
        results[name] = {"import_s": round(seconds, 2), "kept": summary["frames"],
                         "depth_frames": summary["depth_frames"], "skipped": summary["skipped"],
                         "rotation_error_deg": rot, "centre_error_of_trajectory": centre / trajectory}
        if args.train:
            scene, extra = args.out / name, args.train_args.split()
            results[name]["train"] = train(scene, args.out / f"{name}_run", args.train, extra)
            given = given_subset(REDKITCHEN, scene, source_by_pose(REDKITCHEN, scene), args.out / f"{name}_given")
            results[name]["given_train"] = train(given, args.out / f"{name}_given_run", args.train, extra)
        print(name, json.dumps(results[name]), flush=True)
    results["command"] = "python benchmarks/import_rosbag.py " + " ".join(sys.argv[1:])
    (args.out / "results.json").write_text(json.dumps(results, indent=2) + "\n")
    print(json.dumps(results, indent=2))


if __name__ == "__main__":
    main()
