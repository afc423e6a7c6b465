"""Which real-scan corrections a run learns: ``auto`` for per-image appearance and pose refinement, per scene.

A captured scan carries the errors of its capture: poses from tracking or structure from motion drift along the
path, and auto-exposure and white balance change from frame to frame. Per-image appearance
(:mod:`voxnerf.model.appearance`) and pose refinement (:mod:`voxnerf.cameras.pose_refinement`) learn them. A
synthetic scene
(rendered images with exact poses, transforms.json ``"synthetic": true``) has no pose error, and refining its
poses only moves what was right. ``auto`` follows the tuning suite (docs/benchmarks.md): the pair paid on the
real scan, and on the synthetic rooms it cost: on two of them at 120 s, and on the mean of all six, on both
splits, at 300 s (the capture-like rooms with exposure drift included). So ``auto`` turns both on for a
captured scan and leaves them out for a synthetic one; a resumed run keeps what its checkpoint learnt, and a
value other than ``auto`` is used as given.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

from voxnerf.config import TrainConfig
from voxnerf.data.scene import Scene
from voxnerf.training.records import StageRecord

# What ``auto`` turns on, per config field (the field's name is also the checkpoint's key for its state).
CORRECTIONS = {"appearance": "affine", "pose_refinement": "so3xr3"}
# The corrections are held at zero mean over the training images: with fewer, there is nothing to correct.
MIN_IMAGES = 2


@dataclass
class CorrectionsStage:
    record: StageRecord
    cfg: TrainConfig  # ``cfg`` with no ``auto`` left in appearance and pose_refinement


def _chosen(cfg: TrainConfig, scene: Scene, previous: dict | None) -> tuple[dict[str, str], str]:
    """(values for the fields that are ``auto``, why)."""
    auto = [name for name in CORRECTIONS if getattr(cfg.corrections, name) == "auto"]
    if not auto:
        return {}, "as configured"
    if previous is not None:
        learnt = previous["model"]
        return ({name: CORRECTIONS[name] if learnt.get(name) is not None else "none" for name in auto},
                "auto: as the resumed checkpoint learnt them")
    if scene.synthetic:
        why = "auto: left out, transforms.json says the scene is synthetic (rendered, exact poses)"
        return dict.fromkeys(auto, "none"), why
    if len(scene.train_indices) < MIN_IMAGES:
        return dict.fromkeys(auto, "none"), f"auto: left out, fewer than {MIN_IMAGES} training images to correct"
    return ({name: CORRECTIONS[name] for name in auto},
            "auto: a captured scan (transforms.json does not say synthetic), whose poses and exposure drift")


def corrections_stage(cfg: TrainConfig, scene: Scene, previous: dict | None) -> CorrectionsStage:
    """Resolve ``auto`` in ``cfg.corrections.appearance`` and ``.pose_refinement`` for ``scene`` (and the checkpoint a
    resumed run continues from, ``previous``); the record names what runs and why."""
    t0 = time.perf_counter()
    values, why = _chosen(cfg, scene, previous)
    cfg = cfg.updated(**values)
    learnt = [f"{name} {getattr(cfg.corrections, name)}" for name in CORRECTIONS
              if getattr(cfg.corrections, name) != "none"]
    ran = bool(learnt)
    text = f"{', '.join(learnt) if ran else 'none'}; {why}"
    return CorrectionsStage(StageRecord(name="corrections", ran=ran, why=text, seconds=time.perf_counter() - t0),
                            cfg)
