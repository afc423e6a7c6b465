"""The trained models a worker process keeps loaded for renders and outputs (:func:`model_cache`)."""

from __future__ import annotations

from collections import OrderedDict
from functools import lru_cache
from pathlib import Path

from app.core.settings import get_settings
from voxnerf.errors import RunError
from voxnerf.files import CHECKPOINT
from voxnerf.inference.render import TrainedModel, load_model


class ModelCache:
    """The ``size`` most recently used trained models of this process, keyed by checkpoint file and mtime."""

    def __init__(self, size: int) -> None:
        self.size = size
        self._models: OrderedDict[tuple[str, int], TrainedModel] = OrderedDict()

    def get(self, run_dir: Path, device: str) -> TrainedModel:
        checkpoint = run_dir / CHECKPOINT
        try:
            key = (str(checkpoint), checkpoint.stat().st_mtime_ns)
        except FileNotFoundError:
            raise RunError(f"job {run_dir.name} has no checkpoint") from None
        if key in self._models:
            self._models.move_to_end(key)
            return self._models[key]
        model = load_model(run_dir, device)
        self._models[key] = model
        while len(self._models) > self.size:
            self._models.popitem(last=False)
        return model


@lru_cache(maxsize=1)
def model_cache() -> ModelCache:
    """This process's model cache, built on first use (``render_cache_size`` models)."""
    return ModelCache(get_settings().render_cache_size)


