"""Errors the engine raises for bad input, each naming the file and the field at fault."""

from __future__ import annotations

from pathlib import Path


class VoxNeRFError(Exception):
    """Base class of every error the engine raises on purpose."""


class SceneError(VoxNeRFError, ValueError):
    """A scene (transforms.json, an image, a depth map or a prior) is malformed.

    ``str(err)`` is one line: ``<file>: <key>: <message>`` (key omitted when the whole file is at fault).
    """

    def __init__(self, file: str | Path, message: str, key: str | None = None) -> None:
        self.file = str(file)
        self.key = key
        self.message = message
        where = f"{self.file}: {key}" if key else self.file
        super().__init__(f"{where}: {message}")


class TrainingDiverged(VoxNeRFError, RuntimeError):
    """The loss or the parameters became NaN/inf; the last good checkpoint was kept."""


class RenderStopped(VoxNeRFError):
    """A render was stopped between two passes over its rays because its caller's ``should_stop`` said so (nobody
    waits for it any more); it returns nothing."""


class RunError(VoxNeRFError, ValueError):
    """A run directory or a render request is unusable (missing checkpoint, bad pose file...)."""
