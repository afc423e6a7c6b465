"""Captures without poses on redkitchen: import time, images registered and pose error of ``voxnerf import images``
and ``voxnerf import video``, and optionally the PSNR of a run on each imported scene beside the same run on the
scene as given.

- **photos**: ``--frames`` redkitchen colour frames ``--stride`` apart (native 640 x 480 JPEGs, copied), posed by
  ``import_images``;
- **video**: every redkitchen frame over the same span encoded as an H.264 MP4 at ``--fps`` (imageio-ffmpeg),
  imported by ``import_video`` keeping ``--frames`` frames (the sharpest of each time window).

Pose error: the imported camera-to-world poses against the given ones after the similarity fit of
:mod:`voxnerf.data.importers.alignment` (rotation in degrees; centre error as a fraction of the trajectory's
length). The given poses are KinectFusion's for the depth camera; 7-Scenes does not register the colour camera
to it, so part of the error is the data's. With ``--train SECONDS`` each imported scene (``--splits paper``) and
the given scene restricted to the same frames and splits train for that long (``voxnerf train``, one after
another) and their evaluation metrics join the table.

    python benchmarks/import_captures.py --out benchmarks/results/import_captures [--train 300]
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from voxnerf.data.importers import PaperSplitRule, import_images, import_video  # noqa: E402
from voxnerf.data.importers.alignment import pose_errors  # noqa: E402

REDKITCHEN = ROOT.parent / "shared" / "data" / "redkitchen"
SPLIT_KEYS = ("train_filenames", "eval_splits")


def source_frames(redkitchen: Path) -> list[dict]:
    return json.loads((redkitchen / "transforms.json").read_text())["frames"]


def write_photos(redkitchen: Path, frames: list[dict], indices: list[int], dst: Path, scale: float) -> None:
    """The frames ``indices`` as photos: copied, or scaled by ``scale`` (Lanczos, JPEG quality 95)."""
    from PIL import Image

    dst.mkdir(parents=True)
    for i in indices:
        src, name = redkitchen / frames[i]["file_path"], Path(frames[i]["file_path"]).name
        if scale == 1:
            shutil.copyfile(src, dst / name)
            continue
        with Image.open(src) as im:
            size = (round(im.width * scale), round(im.height * scale))
            im.convert("RGB").resize(size, Image.LANCZOS).save(dst / name, quality=95)


def write_video(redkitchen: Path, frames: list[dict], indices: list[int], path: Path, fps: float) -> None:
    import imageio_ffmpeg
    from PIL import Image

    with Image.open(redkitchen / frames[indices[0]]["file_path"]) as im:
        size = im.size
    writer = imageio_ffmpeg.write_frames(str(path), size, fps=fps, codec="libx264", quality=8, macro_block_size=1,
                                         ffmpeg_log_level="error")
    writer.send(None)
    for i in indices:
        with Image.open(redkitchen / frames[i]["file_path"]) as im:
            writer.send(np.ascontiguousarray(np.asarray(im.convert("RGB"))))
    writer.close()


def measure(name: str, scene: Path, summary: dict, seconds: float, given_pose_of) -> dict:
    meta = json.loads((scene / "transforms.json").read_text())
    estimated = np.array([f["transform_matrix"] for f in meta["frames"]])
    given = np.array([given_pose_of(f["file_path"]) for f in meta["frames"]])
    errors = pose_errors(estimated, given)
    sfm = summary["sfm"]
    width, height = (meta["w"], meta["h"]) if "w" in meta else (meta["frames"][0]["w"], meta["frames"][0]["h"])
    row = {"importer": name, "size": [width, height], "import_s": seconds, "images": sfm["images"],
           "registered": sfm["registered"],
           "matching": sfm["matching"], "cameras": sfm["cameras"], "reconstructions": sfm["reconstructions"],
           "reprojection_px": sfm["mean_reprojection_error_px"], "points": sfm["points"],
           "focal_px": meta.get("fl_x"), "pose_error": errors.as_dict()}
    print(name, json.dumps(row), flush=True)
    return row


def given_subset(redkitchen: Path, imported: Path, source_name_of, out: Path) -> Path:
    """The given scene restricted to ``imported``'s frames (same split keys, renamed to the source's files),
    with hard links to the source's images, depth maps and prior."""
    meta = json.loads((redkitchen / "transforms.json").read_text())
    imported_meta = json.loads((imported / "transforms.json").read_text())
    by_path = {f["file_path"]: f for f in meta["frames"]}
    rename = {f["file_path"]: source_name_of(f["file_path"]) for f in imported_meta["frames"]}
    meta["frames"] = [by_path[rename[f["file_path"]]] for f in imported_meta["frames"]]
    meta["train_filenames"] = [rename[p] for p in imported_meta["train_filenames"]]
    meta["eval_splits"] = {k: [rename[p] for p in v] for k, v in imported_meta["eval_splits"].items()}
    meta.pop("test_filenames", None)
    needed = {f["file_path"] for f in meta["frames"]} | {f["depth_file_path"] for f in meta["frames"]
                                                           if f.get("depth_file_path")}
    needed |= {meta[k] for k in ("ply_file_path", "prior_file_path") if meta.get(k)}
    for rel in needed:
        (out / rel).parent.mkdir(parents=True, exist_ok=True)
        try:
            os.link(redkitchen / rel, out / rel)
        except OSError:
            shutil.copy2(redkitchen / rel, out / rel)
    (out / "transforms.json").write_text(json.dumps(meta))
    return out


def source_by_pose(redkitchen: Path, imported: Path):
    """``file_path -> source file_path`` for an imported scene whose poses are the source's own (phone apps, bags):
    each imported frame is matched to the source frame with the nearest camera-to-world matrix."""
    source = source_frames(redkitchen)
    matrices = np.array([f["transform_matrix"] for f in source])
    names = {}
    for entry in json.loads((imported / "transforms.json").read_text())["frames"]:
        gap = np.abs(matrices - np.asarray(entry["transform_matrix"])).reshape(len(source), -1).max(axis=1)
        names[entry["file_path"]] = source[int(np.argmin(gap))]["file_path"]
    if len(set(names.values())) != len(names):
        raise SystemExit(f"{imported}: two imported frames match one source frame; poses are not the source's")
    return names.__getitem__


def train(scene: Path, run: Path, seconds: float, extra: list[str]) -> dict:
    cmd = [sys.executable, "-m", "voxnerf", "train", str(scene), "--out", str(run), "--max-seconds", str(seconds),
           "--restart", *extra]
    subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    report = json.loads((run / "report.json").read_text())
    return {"iterations": report["iteration"],
            "metrics": {split: {k: m.get(k) for k in ("psnr", "ssim", "lpips")}
                        for split, m in report["metrics"].items()}}


def table(rows: list[dict]) -> str:
    header = ["importer", "size", "matching", "import s", "registered", "rotation deg (max / median)",
              "centre / trajectory (max / median)", "reprojection px", "PSNR (imported / given)"]
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    for r in rows:
        e = r["pose_error"]
        psnr = "not run"
        if "train" in r:
            psnr = "; ".join(f"{split} {m['psnr']:.2f} / {r['given_train']['metrics'][split]['psnr']:.2f}"
                             for split, m in r["train"]["metrics"].items())
        centre = f"{100 * e['centre_error_max_fraction']:.1f} % / {100 * e['centre_error_median_fraction']:.1f} %"
        lines.append(f"| {r['importer']} | {r['size'][0]}x{r['size'][1]} | {r['matching']} | {r['import_s']:.0f} | "
                     f"{r['registered']} / {r['images']} | "
                     f"{e['rotation_deg_max']:.2f} / {e['rotation_deg_median']:.2f} | {centre} | "
                     f"{r['reprojection_px']:.2f} | {psnr} |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--redkitchen", type=Path, default=REDKITCHEN)
    parser.add_argument("--frames", type=int, default=100, help="photos, and frames kept from the video")
    parser.add_argument("--stride", type=int, default=5, help="source frames between photos (the video has all)")
    parser.add_argument("--fps", type=float, default=30.0, help="the video's frame rate (Kinect v1: 30)")
    parser.add_argument("--importers", default="photos,video")
    parser.add_argument("--scale", type=float, default=1.0,
                        help="photos scaled by this (2: 1280 x 960, about the 1 MP of a phone photo set)")
    parser.add_argument("--matching", default="auto", choices=["auto", "exhaustive", "sequential"],
                        help="the photos' matching (the video's is sequential)")
    parser.add_argument("--out", type=Path, required=True, help="results folder (results.json, table.md)")
    parser.add_argument("--train", type=float, default=0.0, metavar="SECONDS",
                        help="also train each imported scene and the given one this long (0: no training)")
    parser.add_argument("--train-args", default="", help="more `voxnerf train` options for every run")
    args = parser.parse_args(argv)
    frames = source_frames(args.redkitchen)
    span = args.frames * args.stride
    if span > len(frames):
        parser.error(f"--frames x --stride = {span} is more than the {len(frames)} redkitchen frames")
    photo_indices = list(range(0, span, args.stride))
    pose_of_name = {Path(f["file_path"]).name: f["transform_matrix"] for f in frames}
    splits = PaperSplitRule() if args.train else None
    rows = []
    args.out.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        for importer in args.importers.split(","):
            if importer == "photos":
                write_photos(args.redkitchen, frames, photo_indices, tmp / "photos", args.scale)
                started = time.perf_counter()
                summary = import_images(tmp / "photos", tmp / "photos_scene", splits, matching=args.matching)
                seconds = time.perf_counter() - started

                def source_of(file_path: str) -> str:
                    return f"images/{Path(file_path).name}"
            elif importer == "video":
                write_video(args.redkitchen, frames, list(range(span)), tmp / "capture.mp4", args.fps)
                started = time.perf_counter()
                summary = import_video(tmp / "capture.mp4", tmp / "video_scene", args.frames, splits)
                seconds = time.perf_counter() - started
                index_of = {p["file"]: p["frame"] for p in summary["video"]["picked"]}

                def source_of(file_path: str, index_of=index_of) -> str:
                    return frames[index_of[file_path]]["file_path"]
            else:
                parser.error(f"unknown importer {importer!r} (photos, video)")
            scene = tmp / f"{importer}_scene"
            row = measure(importer, scene, summary, seconds, lambda p: pose_of_name[Path(source_of(p)).name])
            if args.train:
                extra = args.train_args.split()
                row["train"] = train(scene, tmp / f"{importer}_run", args.train, extra)
                given = given_subset(args.redkitchen, scene, source_of, tmp / f"{importer}_given")
                row["given_train"] = train(given, tmp / f"{importer}_given_run", args.train, extra)
            rows.append(row)
    command = "python benchmarks/import_captures.py " + " ".join(argv if argv is not None else sys.argv[1:])
    (args.out / "results.json").write_text(json.dumps({"command": command, "results": rows}, indent=2))
    (args.out / "table.md").write_text(f"`{command}`\n\n{table(rows)}\n")
    print(table(rows))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
