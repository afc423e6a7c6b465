"""The trained models a worker process keeps loaded for renders and outputs (:func:`model_cache`), and how a task
gets a job's model through it (:func:`job_model`)."""

from __future__ import annotations

import logging
import os
from collections import OrderedDict
from functools import lru_cache
from pathlib import Path

from app.core import storage
from app.core.settings import Settings, get_settings
from voxnerf.errors import RunError
from voxnerf.files import CHECKPOINT
from voxnerf.inference.render import TrainedModel, load_model

log = logging.getLogger(__name__)
CheckpointKey = tuple[str, int, int, int, int]  # path, device, inode, size, modification time (ns)


def checkpoint_key(path: Path, stat: os.stat_result) -> CheckpointKey:
    """The identity of the checkpoint file at ``path``. The trainer writes each checkpoint to a new file and
    renames it over the old one (:func:`voxnerf.data.image_io.write_atomic`), so every checkpoint it saves has a
    new inode (and time): a key that still matches is the very file that was loaded."""
    return str(path), stat.st_dev, stat.st_ino, stat.st_size, stat.st_mtime_ns


class ModelCache:
    """The ``size`` most recently used trained models of this process, keyed by their checkpoint file's identity
    (:func:`checkpoint_key`).

    A render of an unchanged checkpoint costs one ``stat``. When a running job's trainer has saved a newer
    checkpoint, the next request loads it (from the file it opened and identified, never a half-written one: the
    trainer's checkpoints appear by rename) and drops the older model of the same run, so a job being viewed
    while it trains holds one model here, not one per checkpoint. ``loads`` counts the checkpoints loaded.
    """

    def __init__(self, size: int) -> None:
        self.size = size
        self.loads = 0
        self._models: OrderedDict[CheckpointKey, TrainedModel] = OrderedDict()

    def get(self, run_dir: Path, device: str) -> TrainedModel:
        checkpoint = run_dir / CHECKPOINT
        try:
            key = checkpoint_key(checkpoint, checkpoint.stat())
        except FileNotFoundError:
            raise RunError(f"job {run_dir.name} has no checkpoint") from None
        if key in self._models:
            self._models.move_to_end(key)
            return self._models[key]
        try:
            with open(checkpoint, "rb") as opened:  # a newer checkpoint renamed over it meanwhile leaves this one
                key = checkpoint_key(checkpoint, os.fstat(opened.fileno()))
                model = load_model(run_dir, device, opened)
        except FileNotFoundError:
            raise RunError(f"job {run_dir.name} has no checkpoint") from None
        self.loads += 1
        log.info("model cache: loaded run %s, checkpoint of iteration %d", run_dir.name, model.iteration)
        for older in [other for other in self._models if other[0] == key[0]]:  # the same run's earlier checkpoint
            del self._models[older]
        self._models[key] = model
        while len(self._models) > self.size:
            self._models.popitem(last=False)
        return model

    def held(self) -> int:
        """How many models this cache holds."""
        return len(self._models)


@lru_cache(maxsize=1)
def model_cache() -> ModelCache:
    """This process's model cache, built on first use (``render_cache_size`` models)."""
    return ModelCache(get_settings().render_cache_size)


def job_model(settings: Settings, job_id: str, checkpoint_iteration: int | None) -> TrainedModel:
    """Job ``job_id``'s model, through this process's cache. With an object store the run is fetched when this
    machine's cache has no checkpoint of it, and fetched again when the cached checkpoint is older than
    ``checkpoint_iteration`` (the job row's last checkpoint) and the store holds another upload: so a machine that
    rendered a job while it trained picks up its later checkpoints, and its final one. A machine that trains the
    job itself always holds the newest checkpoint and never fetches."""
    trained = model_cache().get(storage.ensure_run(settings, job_id, refresh=False), settings.device)
    stale = checkpoint_iteration is not None and trained.iteration < checkpoint_iteration
    if stale and storage.open_store(settings) is not None:
        trained = model_cache().get(storage.ensure_run(settings, job_id, refresh=True), settings.device)
    return trained
