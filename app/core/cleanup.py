"""Start-up cleaning of what a crash left under ``data_dir``: staging directories (``upload-*``, ``fetch-*``,
``deleted-*``...) and scene directories that never got their database row (a crash between the rename into
``scenes/`` and the row) or lost it (a crash while deleting).

Other API and worker processes may share ``data_dir`` and be mid-upload or mid-fetch, so only leftovers in
which nothing changed for ``settings.leftover_age_s`` are removed; "changed" counts the change time too, which a
rename into ``scenes/`` refreshes.
"""

from __future__ import annotations

import logging
import os
import shutil
import time
from dataclasses import dataclass, field
from pathlib import Path

from app.core import jobstore
from app.core.settings import Settings

log = logging.getLogger(__name__)


@dataclass
class Cleaned:
    """What :func:`clean_leftovers` removed: entry names under ``staging_dir`` and scene ids."""

    staging: list[str] = field(default_factory=list)
    scenes: list[str] = field(default_factory=list)


def last_change(path: Path, deep: bool) -> float:
    """The latest modification or change time (seconds since the epoch) of ``path``, and with ``deep`` of
    everything under it; entries that vanish meanwhile are skipped."""
    paths = [path]
    if deep and path.is_dir() and not path.is_symlink():
        for folder, dirs, files in os.walk(path):
            paths.extend(Path(folder) / name for name in dirs + files)
    latest = 0.0
    for item in paths:
        try:
            info = item.lstat()
        except FileNotFoundError:
            continue
        latest = max(latest, info.st_mtime, info.st_ctime)
    return latest


def _remove(path: Path) -> None:
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path, ignore_errors=True)
    else:
        path.unlink(missing_ok=True)


def _stale(path: Path, cutoff: float, deep: bool) -> bool:
    return last_change(path, deep) <= cutoff


def clean_leftovers(settings: Settings, now: float | None = None) -> Cleaned:
    """Remove every entry of ``staging_dir`` and every entry of ``scenes_dir`` without a scene row, of those
    unchanged for ``leftover_age_s`` seconds before ``now`` (default: the current time); committed scenes
    (with a row) are never touched. Returns what was removed (also logged)."""
    cutoff = (time.time() if now is None else now) - settings.leftover_age_s
    cleaned = Cleaned()
    if settings.staging_dir.is_dir():
        for entry in sorted(settings.staging_dir.iterdir()):
            if _stale(entry, cutoff, deep=True):
                _remove(entry)
                cleaned.staging.append(entry.name)
    if settings.scenes_dir.is_dir():
        committed = {row.id for row in jobstore.list_scenes(settings)}
        for entry in sorted(settings.scenes_dir.iterdir()):
            if entry.name not in committed and _stale(entry, cutoff, deep=False):
                _remove(entry)
                cleaned.scenes.append(entry.name)
    if cleaned.staging or cleaned.scenes:
        log.warning("start-up: removed %d staging leftovers and %d scene directories without a row: %s",
                    len(cleaned.staging), len(cleaned.scenes), ", ".join(cleaned.staging + cleaned.scenes))
    return cleaned
