"""Images of different sizes on real data: redkitchen as given beside redkitchen with its images cut to three sizes.

The frames of redkitchen's splits (``../shared/data/redkitchen``) are written again under ``OUT/mixed`` with every
third frame kept at 640x480, every third cropped to 640x474 (three rows off the top and the bottom, as COLMAP's
undistortion crops a photo) and every third to a 360x480 portrait (140 columns off each side); each depth map is
cropped as its image, each frame's ``w h cx cy`` follow the crop, and the poses, splits and prior are the scene's.
Both scenes are trained with the same config and iteration count; the final PSNR of each evaluation split is
printed and written to ``OUT/mixed_sizes.json``. The cropped scene has less of the room in its images, so its
PSNR is not expected to equal the given scene's; what it shows is that a scene of mixed sizes trains through
every set-up stage and evaluates each view at its own size.

    .venv/bin/python benchmarks/mixed_sizes.py --out /tmp/mixed_sizes
    .venv/bin/python benchmarks/mixed_sizes.py --out /tmp/mixed_sizes --iters 300 --downscale 2
"""

from __future__ import annotations

import argparse
import json
import shutil
import time
from pathlib import Path

import imageio.v3 as iio

from voxnerf.config import TrainConfig
from voxnerf.training.run import train

REDKITCHEN = Path(__file__).resolve().parents[2] / "shared" / "data" / "redkitchen"
CROPS = (None, ("rows", 3, 477), ("cols", 140, 500))  # frame k gets CROPS[k % 3]


def _crop(array, crop):
    if crop is None:
        return array
    axis, start, stop = crop
    return array[start:stop] if axis == "rows" else array[:, start:stop]


def make_mixed_scene(out: Path, source: Path = REDKITCHEN) -> Path:
    """``source``'s split frames, cropped to three sizes, written as a scene at ``out`` (which must not exist)."""
    meta = json.loads((source / "transforms.json").read_text())
    used = set(meta.get("train_filenames", [])) | set(meta.get("test_filenames", []))
    for files in (meta.get("eval_splits") or {}).values():
        used |= set(files)
    frames = []
    for k, frame in enumerate(f for f in meta["frames"] if f["file_path"] in used):
        crop, entry = CROPS[k % 3], dict(frame)
        for key in ("file_path", "depth_file_path"):
            (out / frame[key]).parent.mkdir(parents=True, exist_ok=True)
            iio.imwrite(out / frame[key], _crop(iio.imread(source / frame[key]), crop))
        if crop is not None:
            h, w = iio.imread(out / frame["file_path"]).shape[:2]
            cx = meta["cx"] - (crop[1] if crop[0] == "cols" else 0)
            cy = meta["cy"] - (crop[1] if crop[0] == "rows" else 0)
            entry.update(w=w, h=h, cx=cx, cy=cy)
        frames.append(entry)
    shutil.copyfile(source / meta["prior_file_path"], out / meta["prior_file_path"])
    (out / "transforms.json").write_text(json.dumps({**meta, "frames": frames}))
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--iters", type=int, default=300)
    parser.add_argument("--downscale", type=int, default=4)
    parser.add_argument("--device", default="auto")
    args = parser.parse_args()
    mixed = args.out / "mixed"
    if not (mixed / "transforms.json").is_file():
        shutil.rmtree(mixed, ignore_errors=True)
        make_mixed_scene(mixed)
    results = {}
    for name, scene in (("given", REDKITCHEN), ("mixed", mixed)):
        cfg = TrainConfig(max_iters=args.iters, downscale=args.downscale, device=args.device, compile=False)
        run = args.out / f"run_{name}"
        shutil.rmtree(run, ignore_errors=True)
        t0 = time.perf_counter()
        report = train(scene, run, cfg, progress_bar=False).to_json_dict()
        load_scene = next(s for s in report["stages"] if s["name"] == "load_scene")
        results[name] = {"status": report["status"], "iterations": report["iteration"],
                         "seconds": round(time.perf_counter() - t0, 1), "image_sizes": report["scene"]["image_sizes"],
                         "load_scene": load_scene["why"],
                         "psnr": {split: m["psnr"] for split, m in (report["metrics"] or {}).items()}}
        print(name, json.dumps(results[name]))
    (args.out / "mixed_sizes.json").write_text(json.dumps(results, indent=2) + "\n")


if __name__ == "__main__":
    main()
