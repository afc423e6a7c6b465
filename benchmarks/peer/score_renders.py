"""Score a peer's renders (``nerfacto_run.py``'s output) against the scene's held-out images with the
engine's own metrics (``voxnerf.inference.metrics``: PSNR, SSIM), in ``error_vs_runtime.py``'s CSV layout.

    .venv/bin/python benchmarks/peer/score_renders.py SCENE --out PEER_OUT [--config nerfacto]

Reads ``PEER_OUT/timeline.csv`` (``eval_at_s, seconds, iteration, rays_seen``) and, for each row, the renders
``PEER_OUT/renders/<eval_at_s>s/<split>/<image stem>.png`` of every evaluation split of the scene
(``eval_splits`` first, then ``test``). Writes ``PEER_OUT/evaluations.csv`` with the columns
``config, elapsed_s, iteration, split, psnr, ssim, final`` (split means over its views; ``final`` marks the
last training time), so the rows merge into error_vs_runtime's table and plot.
"""

from __future__ import annotations

import argparse
import csv
import io
import sys
from pathlib import Path

import torch

from voxnerf.data.image_io import read_rgb, write_atomic
from voxnerf.data.scene import Scene, load_scene
from voxnerf.errors import SceneError
from voxnerf.inference.metrics import evaluate_images

RENDER_DIR_FORMAT = "{:g}s"
"""Render directory of one evaluation time, as nerfacto_run.py names it."""
COLUMNS = ("config", "elapsed_s", "iteration", "split", "psnr", "ssim", "final")
"""error_vs_runtime.py's evaluations.csv columns."""


def read_timeline(path: Path) -> list[dict]:
    """Rows of a peer's timeline.csv as ``{"eval_at_s", "seconds": float, "iteration", "rays_seen": int}``."""
    if not path.is_file():
        raise SceneError(path, "timeline missing: run nerfacto_run.py first")
    with open(path, newline="") as f:
        rows = list(csv.DictReader(f))
    if not rows:
        raise SceneError(path, "timeline has no rows")
    try:
        return [
            {"eval_at_s": float(r["eval_at_s"]), "seconds": float(r["seconds"]),
             "iteration": int(r["iteration"]), "rays_seen": int(r["rays_seen"])}
            for r in rows
        ]
    except (KeyError, TypeError, ValueError) as err:
        raise SceneError(path, f"malformed row: {err}", key="eval_at_s,seconds,iteration,rays_seen") from err


def as_unit_float(rgb) -> torch.Tensor:
    """uint8 ``[H, W, 3]`` as float ``[H, W, 3]`` in [0, 1]."""
    return torch.from_numpy(rgb).float() / 255.0


def score_split(scene: Scene, split: str, render_dir: Path) -> dict[str, float]:
    """Mean PSNR (dB) and SSIM of the renders in ``render_dir/<split>`` against the scene's images."""
    preds, gts = [], []
    for index in scene.splits[split]:
        frame = scene.frames[index]
        path = render_dir / split / f"{Path(frame.file_path).stem}.png"
        if not path.is_file():
            raise SceneError(path, f"render of {frame.file_path} missing")
        pred, gt = read_rgb(path), read_rgb(frame.image_path)
        if pred.shape != gt.shape:
            raise SceneError(path, f"render is {pred.shape[1]}x{pred.shape[0]}, the image {gt.shape[1]}x{gt.shape[0]}")
        preds.append(as_unit_float(pred))
        gts.append(as_unit_float(gt))
    return evaluate_images(preds, gts, lpips_model=None)["mean"]


def evaluations(scene: Scene, peer_out: Path, config: str) -> list[dict]:
    """One row per (timeline row, evaluation split), in error_vs_runtime's layout."""
    timeline = read_timeline(peer_out / "timeline.csv")
    rows = []
    for i, entry in enumerate(timeline):
        render_dir = peer_out / "renders" / RENDER_DIR_FORMAT.format(entry["eval_at_s"])
        for split in scene.eval_split_names:
            mean = score_split(scene, split, render_dir)
            rows.append({
                "config": config, "elapsed_s": entry["seconds"], "iteration": entry["iteration"], "split": split,
                "psnr": mean["psnr"], "ssim": mean["ssim"], "final": i == len(timeline) - 1,
            })
    return rows


def write_csv(rows: list[dict], path: Path) -> None:
    """``rows`` as a CSV file with ``COLUMNS`` as header, written atomically."""
    text = io.StringIO()
    writer = csv.DictWriter(text, fieldnames=list(COLUMNS))
    writer.writeheader()
    writer.writerows(rows)
    write_atomic(path, text.getvalue().encode())


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("scene", type=Path, help="the SCENE_FORMAT directory the peer trained on")
    parser.add_argument("--out", type=Path, required=True, help="the peer run's output directory")
    parser.add_argument("--config", default="nerfacto", help="configuration name in the CSV")
    args = parser.parse_args(argv)
    scene = load_scene(args.scene, load_images=False)
    rows = evaluations(scene, args.out, args.config)
    write_csv(rows, args.out / "evaluations.csv")
    for row in rows:
        print(f"{row['config']} {row['elapsed_s']:8.1f} s  it {row['iteration']:6d}  {row['split']:14s} "
              f"PSNR {row['psnr']:6.2f}  SSIM {row['ssim']:.3f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
