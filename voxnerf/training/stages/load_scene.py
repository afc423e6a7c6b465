"""Stage load_scene: the scene, loaded and checked (sensor depth where the config asks for it)."""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

from voxnerf.config import TrainConfig
from voxnerf.data.scene import Scene, load_scene
from voxnerf.errors import SceneError
from voxnerf.files import TRANSFORMS
from voxnerf.training.records import StageRecord
from voxnerf.training.stages.common import stage_record


@dataclass
class SceneStage:
    record: StageRecord
    scene: Scene


def load_scene_stage(scene_dir: str | Path, cfg: TrainConfig) -> SceneStage:
    t0 = time.perf_counter()
    scene = load_scene(scene_dir, downscale=cfg.run.downscale)
    check_sensor_depth(cfg, scene)  # before any set-up work, not after it
    why = f"{len(scene.frames)} frames, {len(scene.train_indices)} for training" + training_sizes_note(scene)
    return SceneStage(stage_record("load_scene", True, why, t0), scene)


def training_sizes_note(scene: Scene) -> str:
    """For training images of several sizes: how many of each, and how much of the grid they share
    (:class:`voxnerf.training.pixels.TrainingPixels`) is padding; "" for one size."""
    sizes = [(scene.intrinsics(i).width, scene.intrinsics(i).height) for i in scene.train_indices]
    counts: dict[tuple[int, int], int] = {}
    for size in sizes:
        counts[size] = counts.get(size, 0) + 1
    if len(counts) < 2:
        return ""
    grid_w, grid_h = max(w for w, _ in sizes), max(h for _, h in sizes)
    padding = 1.0 - sum(w * h for w, h in sizes) / (len(sizes) * grid_w * grid_h)
    listed = ", ".join(f"{w}x{h}: {n}" for (w, h), n in counts.items())
    return (f"; training images of {len(counts)} sizes ({listed}) on a {grid_w}x{grid_h} grid, "
            f"{padding:.0%} of it padding")


def check_sensor_depth(cfg: TrainConfig, scene: Scene) -> None:
    """SceneError when ``depth_source`` 'sensor' is asked for and no training frame has a depth map."""
    wants_sensor = cfg.loss.depth_loss and cfg.loss.depth_source == "sensor"
    if wants_sensor and all(scene.depths[i] is None for i in scene.train_indices):
        raise SceneError(scene.root / TRANSFORMS, "depth_source 'sensor' needs depth maps, and no training frame "
                         "has one", key="depth_file_path")
