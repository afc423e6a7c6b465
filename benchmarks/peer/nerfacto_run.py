"""Train nerfstudio's nerfacto on a VoxNeRF scene's training frames on CPU, rendering the held-out views at
fixed training times. Runs in the peer venv (``install_nerfstudio.sh``), never in the project's own.

    /work/peer/venv/bin/python benchmarks/peer/nerfacto_run.py SCENE --budget 300 --eval-at 60,120,300 --out OUT

The scene is a SCENE_FORMAT.md directory. Only ``train_filenames`` frames are given to nerfstudio, through a
filtered copy of transforms.json in ``OUT/train_transforms.json`` (absolute image paths, no split keys, the
dataparser's ``eval_mode`` "all"), so its pose normalisation sees the training cameras only. The configuration
is nerfstudio's ``nerfacto`` method config with what CPU forces:

- device ``cpu`` (mixed precision is then off, nerfstudio's own rule);
- ``VanillaDataManager`` instead of ``ParallelDataManager`` (same dataparser, pixel sampler and ray batch;
  no data-loading process is spawned);
- logging to tensorboard instead of the viewer (no web server);
- torchmetrics' LPIPS, built at model start-up for nerfstudio's own eval metrics, downloads AlexNet weights
  from download.pytorch.org; it is replaced by a module that refuses to run (this script never calls it).

Training clock: seconds spent in training iterations (data sampling, forward, backward, optimiser and
nerfstudio's training callbacks); set-up (image loading, model construction) and renders are excluded. After
the first iteration whose clock reaches each ``--eval-at`` time (and the budget, when not listed), every view
of each held-out split (``eval_splits`` and a non-empty ``test_filenames`` as ``test``) is rendered with the
split's own poses and intrinsics, mapped into nerfstudio's normalised frame with the dataparser's transform
and scale, to ``OUT/renders/<t>s/<split>/<image stem>.png``; ``OUT/timeline.csv`` gets one row per render
time: ``eval_at_s, seconds, iteration, rays_seen`` (seconds: the clock at that render).
``OUT/run.json`` records the configuration changes, the set-up and render times and the seconds per
iteration (mean, first, mean of the later ones).
"""

from __future__ import annotations

import argparse
import csv
import io
import json
import os
import shlex
import sys
import tempfile
import time
import warnings
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import torch

SPLIT_DIR_FORMAT = "{:g}s"
"""Render directory of one evaluation time, e.g. ``30s``."""
TRAIN_RAYS_PER_BATCH = 4096
"""nerfacto's default ray batch."""
POSE_TOLERANCE = 1e-4
"""Largest difference allowed between nerfstudio's training poses and ours mapped by its transform."""


def write_atomic(path: Path, data: bytes) -> None:
    """Write ``data`` to ``path`` through a temporary file in the same directory and ``os.replace``."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def load_scene(scene: Path) -> tuple[dict, list[dict], dict[str, list[dict]]]:
    """``(transforms.json, training frames, {held-out split: frames})`` of a SCENE_FORMAT directory."""
    meta = json.loads((scene / "transforms.json").read_text())
    by_path = {frame["file_path"]: frame for frame in meta["frames"]}
    if "train_filenames" not in meta:
        raise SystemExit(f"{scene / 'transforms.json'}: train_filenames is required (the benchmark's split)")
    named = {"train": meta["train_filenames"], **meta.get("eval_splits", {})}
    if meta.get("test_filenames"):
        named["test"] = meta["test_filenames"]
    splits = {}
    for name, paths in named.items():
        missing = [p for p in paths if p not in by_path]
        if missing:
            raise SystemExit(f"{scene / 'transforms.json'}: split {name!r} names files not in frames: {missing}")
        splits[name] = [by_path[p] for p in paths]
    for frames in splits.values():
        for frame in frames:
            if frame.get("camera_model", meta.get("camera_model", "PINHOLE")) != "PINHOLE":
                raise SystemExit(f"{scene / 'transforms.json'}: {frame['file_path']}: only PINHOLE is supported")
    train = splits.pop("train")
    return meta, train, {name: frames for name, frames in splits.items() if frames}


def write_train_transforms(scene: Path, meta: dict, train: list[dict], out: Path) -> Path:
    """A transforms.json holding only the training frames, with absolute image paths, for the dataparser."""
    intrinsics = ("fl_x", "fl_y", "cx", "cy", "w", "h", "camera_model")
    filtered = {key: meta[key] for key in intrinsics if key in meta}
    filtered["frames"] = [
        {**{k: v for k, v in frame.items() if k != "depth_file_path"},
         "file_path": str((scene / frame["file_path"]).resolve())}
        for frame in train
    ]
    path = out / "train_transforms.json"
    write_atomic(path, json.dumps(filtered, indent=1).encode())
    return path


def disable_lpips() -> None:
    """Replace torchmetrics' LPIPS (its constructor downloads AlexNet weights) by a module refusing to run."""
    import torchmetrics.image.lpip

    class LpipsDisabled(torch.nn.Module):
        """Stands in for ``LearnedPerceptualImagePatchSimilarity``; raises if nerfstudio ever evaluates it."""

        def __init__(self, **_: object) -> None:
            super().__init__()

        def forward(self, *_: torch.Tensor) -> torch.Tensor:
            raise RuntimeError("LPIPS is disabled in this benchmark (its weights would be downloaded)")

    torchmetrics.image.lpip.LearnedPerceptualImagePatchSimilarity = LpipsDisabled


def nerfacto_config(transforms: Path, out: Path, rays_per_batch: int):
    """nerfstudio's ``nerfacto`` TrainerConfig with the CPU changes listed in the module docstring."""
    from nerfstudio.configs.method_configs import method_configs
    from nerfstudio.data.datamanagers.base_datamanager import VanillaDataManagerConfig
    from nerfstudio.data.dataparsers.nerfstudio_dataparser import NerfstudioDataParserConfig

    config = method_configs["nerfacto"]
    default_dm = config.pipeline.datamanager
    config.pipeline.datamanager = VanillaDataManagerConfig(
        dataparser=NerfstudioDataParserConfig(data=transforms, eval_mode="all"),
        train_num_rays_per_batch=rays_per_batch,
        eval_num_rays_per_batch=default_dm.eval_num_rays_per_batch,
    )
    config.machine.device_type = "cpu"
    config.mixed_precision = False
    config.vis = "tensorboard"
    config.data = transforms
    config.output_dir = out / "nerfstudio"
    config.timestamp = "run"
    return config


def to_nerfstudio_frame(c2w: torch.Tensor, transform: torch.Tensor, scale: float) -> torch.Tensor:
    """Camera-to-world ``[N, 4, 4]`` (scene frame) as nerfstudio's ``[N, 3, 4]`` (dataparser frame)."""
    mapped = transform.to(c2w) @ c2w
    mapped[:, :3, 3] *= scale
    return mapped[:, :3, :4]


def check_pose_mapping(train: list[dict], outputs, transform: torch.Tensor, scale: float) -> None:
    """Fail unless our pose mapping reproduces the dataparser's own training cameras."""
    by_name = {Path(f["file_path"]).name: f for f in train}
    ours = torch.tensor(
        np.array([by_name[Path(p).name]["transform_matrix"] for p in outputs.image_filenames]), dtype=torch.float32
    )
    mapped = to_nerfstudio_frame(ours, transform, scale)
    error = float((mapped - outputs.cameras.camera_to_worlds).abs().max())
    if not error < POSE_TOLERANCE:
        raise RuntimeError(f"pose mapping differs from nerfstudio's training cameras by {error:g}")


def split_cameras(frames: list[dict], meta: dict, transform: torch.Tensor, scale: float):
    """nerfstudio ``Cameras`` of ``frames`` (per-frame intrinsics override the top level)."""
    from nerfstudio.cameras.cameras import Cameras, CameraType

    def column(key: str, dtype: torch.dtype) -> torch.Tensor:
        return torch.tensor([[frame.get(key, meta.get(key))] for frame in frames], dtype=dtype)

    c2w = torch.tensor(np.array([frame["transform_matrix"] for frame in frames]), dtype=torch.float32)
    return Cameras(
        camera_to_worlds=to_nerfstudio_frame(c2w, transform, scale),
        fx=column("fl_x", torch.float32),
        fy=column("fl_y", torch.float32),
        cx=column("cx", torch.float32),
        cy=column("cy", torch.float32),
        width=column("w", torch.int64),
        height=column("h", torch.int64),
        camera_type=CameraType.PERSPECTIVE,
    )


def render_splits(pipeline, cameras: dict, frames: dict[str, list[dict]], out_dir: Path) -> None:
    """Render every camera of every split to ``out_dir/<split>/<image stem>.png`` (8-bit RGB)."""
    pipeline.eval()
    for split, split_cameras_ in cameras.items():
        for i, frame in enumerate(frames[split]):
            rgb = pipeline.model.get_outputs_for_camera(split_cameras_[i : i + 1])["rgb"]
            if not bool(torch.isfinite(rgb).all()):
                raise RuntimeError(f"nerfacto rendered NaN/inf for {split}/{frame['file_path']}")
            image = (rgb.clamp(0.0, 1.0) * 255.0 + 0.5).to(torch.uint8).numpy()
            png = iio.imwrite("<bytes>", image, extension=".png")
            write_atomic(out_dir / split / f"{Path(frame['file_path']).stem}.png", png)
    pipeline.train()


def write_csv(rows: list[dict], path: Path) -> None:
    """``rows`` as a CSV file with a header, written atomically."""
    text = io.StringIO()
    writer = csv.DictWriter(text, fieldnames=list(rows[0]))
    writer.writeheader()
    writer.writerows(rows)
    write_atomic(path, text.getvalue().encode())


def train(scene: Path, budget: float, eval_at: list[float], out: Path, rays_per_batch: int) -> dict:
    """Train nerfacto for ``budget`` training seconds, rendering the held-out splits at ``eval_at``."""
    from nerfstudio.engine.callbacks import TrainingCallbackLocation
    from nerfstudio.engine.trainer import Trainer

    meta, train_frames, held_out = load_scene(scene)
    if not held_out:
        raise SystemExit(f"{scene / 'transforms.json'}: no held-out split to render")
    out.mkdir(parents=True, exist_ok=True)
    transforms = write_train_transforms(scene, meta, train_frames, out)
    disable_lpips()
    config = nerfacto_config(transforms, out, rays_per_batch)

    setup_start = time.perf_counter()
    trainer = Trainer(config)
    trainer.setup()
    setup_s = time.perf_counter() - setup_start
    pipeline = trainer.pipeline
    outputs = pipeline.datamanager.train_dataparser_outputs
    transform, scale = outputs.dataparser_transform, float(outputs.dataparser_scale)
    check_pose_mapping(train_frames, outputs, transform, scale)
    cameras = {split: split_cameras(frames, meta, transform, scale) for split, frames in held_out.items()}

    times = sorted({t for t in eval_at if t <= budget} | {budget})
    clock, step, timeline, render_s, iteration_s = 0.0, 0, [], 0.0, []
    while times:
        start = time.perf_counter()
        pipeline.train()
        for callback in trainer.callbacks:
            callback.run_callback_at_location(step, location=TrainingCallbackLocation.BEFORE_TRAIN_ITERATION)
        loss, _, _ = trainer.train_iteration(step)
        for callback in trainer.callbacks:
            callback.run_callback_at_location(step, location=TrainingCallbackLocation.AFTER_TRAIN_ITERATION)
        iteration_s.append(time.perf_counter() - start)
        clock += iteration_s[-1]
        step += 1
        if not bool(torch.isfinite(loss)):
            raise RuntimeError(f"nerfacto's loss is {float(loss)} at iteration {step}")
        while times and clock >= times[0]:
            t = times.pop(0)
            render_start = time.perf_counter()
            render_splits(pipeline, cameras, held_out, out / "renders" / SPLIT_DIR_FORMAT.format(t))
            render_s += time.perf_counter() - render_start
            timeline.append(
                {"eval_at_s": t, "seconds": round(clock, 3), "iteration": step, "rays_seen": step * rays_per_batch}
            )
            write_csv(timeline, out / "timeline.csv")
            print(f"t={t:g}s: clock {clock:.1f} s, iteration {step}, loss {float(loss):.4f}", flush=True)
    run = {
        "command": shlex.join([sys.executable, *sys.argv]),
        "scene": str(scene.resolve()),
        "budget_s": budget,
        "nerfstudio_config": "nerfacto (method_configs), changed: device cpu, mixed precision off, "
        "VanillaDataManager, vis tensorboard, LPIPS metric disabled",
        "train_rays_per_batch": rays_per_batch,
        "train_frames": len(train_frames),
        "held_out": {split: len(frames) for split, frames in held_out.items()},
        "setup_s": round(setup_s, 2),
        "train_s": round(clock, 2),
        "render_s": round(render_s, 2),
        "iterations": step,
        "s_per_iteration": round(clock / step, 3),
        "first_iteration_s": round(iteration_s[0], 3),
        "later_s_per_iteration": round(float(np.mean(iteration_s[1:])), 3) if step > 1 else None,
        "torch_threads": torch.get_num_threads(),
    }
    write_atomic(out / "run.json", json.dumps(run, indent=1).encode())
    return run


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("scene", type=Path, help="SCENE_FORMAT directory")
    parser.add_argument("--budget", type=float, required=True, help="training seconds")
    parser.add_argument("--eval-at", default="", help="comma-separated training seconds to render at")
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--rays", type=int, default=TRAIN_RAYS_PER_BATCH, help="training rays per iteration")
    args = parser.parse_args(argv)
    # torch's deprecation notice on nerfstudio's camera indexing, repeated for every ray batch
    warnings.filterwarnings("ignore", message="Using a non-tuple sequence for multidimensional indexing")
    eval_at = [float(t) for t in args.eval_at.split(",") if t.strip()]
    if args.budget <= 0 or any(t <= 0 for t in eval_at):
        parser.error("--budget and --eval-at must be positive seconds")
    run = train(args.scene, args.budget, eval_at, args.out, args.rays)
    print(json.dumps(run), flush=True)
    return 0


if __name__ == "__main__":  # nerfstudio's data workers, when any, re-import this module
    sys.exit(main())
