"""The colour camera's focal length for training: ``focal_scale`` ``auto``, checked against the prior.

``auto`` measures, on a captured scan with a mesh prior and one pinhole camera for its training images, how
well those images agree through the prior at scales of the stated focal length (:mod:`voxnerf.prior.focal_check`),
and takes the best scale when it removes at least ``MIN_GAIN`` of the stated focal length's error and lies
inside the scales tried; otherwise, and on a synthetic scene (exact intrinsics), the stated focal length stays.
A number is used as given. The scene that training, its evaluations and every later render of its views use
is :func:`voxnerf.data.scene.with_focal_scale` of the loaded one; the depth maps keep the stated camera.
"""

from __future__ import annotations

import time
from dataclasses import astuple, dataclass

import numpy as np
import torch

from voxnerf.cameras.rules import Intrinsics
from voxnerf.config import TrainConfig
from voxnerf.data.scene import Scene, with_focal_scale
from voxnerf.prior.focal_check import FocalCheck, check_focal
from voxnerf.prior.loading import GeometryPrior
from voxnerf.prior.pseudo_depth import MeshCaster
from voxnerf.training import setup_cache
from voxnerf.training.records import StageRecord

MIN_GAIN = 0.05  # the best scale must remove at least this fraction of the stated focal length's error
MIN_CHANGE = 0.01  # a measured scale closer to 1 than this leaves the stated focal length


@dataclass
class FocalStage:
    record: StageRecord
    cfg: TrainConfig  # ``cfg`` with a number in focal_scale
    scene: Scene  # the scene seen through that focal length (the loaded one when it is 1)


def focal_stage(cfg: TrainConfig, scene: Scene, prior: GeometryPrior | None) -> FocalStage:
    """Resolve ``auto`` in ``cfg.corrections.focal_scale`` on ``scene``'s (loaded) training images and ``prior`` (scene
    units), and apply the scale to the scene."""
    t0 = time.perf_counter()
    if cfg.corrections.focal_scale == "auto":
        scale, why = measured_scale(scene, prior, cfg.run.setup_cache)
    else:
        scale, why = float(cfg.corrections.focal_scale), "as configured"
    cfg = cfg.updated(focal_scale=scale)
    corrected = with_focal_scale(scene, scale)
    stated = scene.intrinsics(scene.train_indices[0]) if scene.train_indices else None
    if scale == 1.0:
        text = f"the stated focal length; {why}"
    else:
        at = "" if stated is None else f" ({stated.fl_x * scene.downscale:.1f} -> " \
                                       f"{stated.fl_x * scene.downscale * scale:.1f} px at full size)"
        text = f"the stated focal length x {scale:.4f}{at}; {why}"
    return FocalStage(StageRecord(name="focal", ran=scale != 1.0, why=text, seconds=time.perf_counter() - t0),
                      cfg, corrected)


def measured_scale(scene: Scene, prior: GeometryPrior | None, use_cache: bool = True) -> tuple[float, str]:
    """(scale, why) of ``auto``: the focal check's scale when it is clearly better, else 1 (the check's result
    comes from the set-up cache when an earlier run made it on the same images, poses and mesh)."""
    if scene.synthetic:
        return 1.0, "auto: a synthetic scene, whose intrinsics are exact"
    if prior is None or prior.mesh is None:
        return 1.0, "auto: not checked, it needs the prior as a mesh (a surface to match the images through)"
    train = scene.train_indices
    cameras = {scene.frames[i].intrinsics for i in train}
    if len(cameras) != 1:
        return 1.0, f"auto: not checked, the training images come from {len(cameras)} cameras"
    intr = scene.intrinsics(train[0])
    if intr.lens is not None:
        return 1.0, "auto: not checked, a lens model's intrinsics come from a calibration"
    if scene.images is None or len(train) < 2:
        return 1.0, "auto: not checked, it needs two training images"
    try:
        check, loaded = _cached_check([scene.images[i] for i in train], np.stack([scene.frames[i].c2w for i in train]),
                                      intr, prior, use_cache)
    except ValueError as err:
        return 1.0, f"auto: not checked, {err}"
    measured = (f"{check.pairs} pairs of neighbouring training images agree best through the prior at "
                f"{check.best:.3f} x the stated focal length (grey-level error {check.best_error:.4f} against "
                f"{check.stated_error:.4f} at the stated one, {check.points} points"
                f"{'; loaded from the set-up cache' if loaded else ''})")
    if not check.interior:
        return 1.0, f"auto: {measured}; not used: at the end of the scales tried"
    if check.gain < MIN_GAIN or abs(check.best - 1.0) < MIN_CHANGE:
        return 1.0, f"auto: {measured}; not used: within {MIN_GAIN:.0%} of the stated one's error or of 1"
    return check.best, f"auto: {measured}"


def _cached_check(images: list[np.ndarray], c2ws: np.ndarray, intr: Intrinsics, prior: GeometryPrior,
                  use_cache: bool) -> tuple[FocalCheck, bool]:
    """(:func:`check_focal` of the images through the prior's mesh, whether it came from the set-up cache)."""
    vertices, faces = np.asarray(prior.mesh.vertices), np.asarray(prior.mesh.faces)

    def compute() -> setup_cache.Entry:
        check = check_focal(MeshCaster(vertices, faces), images, c2ws, intr)
        return {"scales": torch.tensor(list(check.errors), dtype=torch.float64),
                "errors": torch.tensor(list(check.errors.values()), dtype=torch.float64),
                "best": torch.tensor([check.best], dtype=torch.float64),
                "counts": torch.tensor([check.pairs, check.points], dtype=torch.int64)}

    def fits(entry: setup_cache.Entry) -> bool:
        shapes = {k: tuple(v.shape) for k, v in entry.items()}
        return (set(shapes) == {"scales", "errors", "best", "counts"} and shapes["scales"] == shapes["errors"]
                and shapes["best"] == (1,) and shapes["counts"] == (2,) and 1.0 in entry["scales"].tolist())

    inputs = ["focal_check", images, c2ws, astuple(intr), vertices, faces]
    entry, loaded = setup_cache.cached("focal_check", inputs, torch.device("cpu"), compute, fits, use_cache)
    errors = dict(zip(entry["scales"].tolist(), entry["errors"].tolist(), strict=True))
    pairs, points = entry["counts"].tolist()
    return FocalCheck(errors=errors, best=float(entry["best"]), pairs=int(pairs), points=int(points)), loaded
