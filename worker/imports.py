"""The work of capture imports (queued on the ``train`` queue): turn an uploaded raw capture (a ROS bag) into a
scene with the engine's importer, check it as an upload is checked, and add it to the service. Loads the engine;
the Celery task is :func:`worker.tasks.run_capture_import`.

The task holds the import (:func:`worker.lease.hold`: claimed in the job store, fenced by its attempt, its lease
renewed every ``heartbeat_s`` and its cancel flag turned into ``should_stop``, read between the stages). Stages:
``importing`` (the importer writes the scene into a fresh directory under ``staging_dir``), ``checking``
(:func:`voxnerf.data.scene.inspect_scene`, the upload's full validation), ``storing``
(:func:`app.core.scene_store.commit_scene`: the scene's directory renamed into ``scenes_dir``, published to the
object store, its row added) and then ``done`` with ``scene_id``. A refusal (the importer's or the check's
one-line SceneError) fails the import naming the file at fault, and nothing is stored; an import that ends in any
state removes its raw capture, and a requeued one starts again from it.
"""

from __future__ import annotations

import logging
import shutil
import tempfile
import time
from pathlib import Path

from app.core.imports import IMPORTS, elapsed_eta, raw_dir, remove_raw
from app.core.models import ImportRow
from app.core.redact import public_error
from app.core.scene_store import PublishFailed, commit_scene, tree_size
from app.core.settings import Settings
from voxnerf.data.importers import ImportCancelled, ImportMonitor, PaperSplitRule, run_import
from voxnerf.data.scene import inspect_scene
from voxnerf.errors import VoxNeRFError
from worker.disk_full import disk_full_message
from worker.lease import Lease

log = logging.getLogger(__name__)
SPLIT_RULES = {"paper": PaperSplitRule()}
SCENE_DIR = "scene"  # in the import's staging directory: the scene the importer writes
STAGE_PROGRESS = {"importing": 0.05, "checking": 0.8, "storing": 0.95}  # how far the import is when each begins
STEP_WRITE_PERIOD_S = 1.0  # an importer's own progress is written at most this often


class Stopped(Exception):
    """The import was cancelled, or its lease lost, between two stages (or inside an importer that watches for
    it: ImportCancelled)."""


def _capture(settings: Settings, row: ImportRow) -> Path:
    """The raw capture of an import: the one file or folder in its :func:`app.core.imports.raw_dir`."""
    entries = list(raw_dir(settings, row.id).iterdir()) if raw_dir(settings, row.id).is_dir() else []
    if len(entries) != 1:
        raise VoxNeRFError(f"import {row.id}: its raw capture is missing (found {len(entries)} entries)")
    return entries[0]


class Stages:
    """Writes each stage and its progress (with an ETA from the time so far) and stops a cancelled import."""

    def __init__(self, settings: Settings, row: ImportRow, lease: Lease) -> None:
        self.settings, self.row, self.lease = settings, row, lease
        self._started = time.monotonic()

    def enter(self, stage: str) -> None:
        """Begin ``stage``; Stopped when the import was cancelled or its lease lost (before ``storing``, the
        store is asked: a scene is added only by the attempt that owns the import)."""
        if self.lease.should_stop() or (stage == "storing" and not self.lease.still_owned()):
            raise Stopped(stage)
        progress = STAGE_PROGRESS[stage]
        IMPORTS.record_progress(self.settings, self.row.id, self.row.attempt, stage, progress,
                                elapsed_eta(self._started, progress))

    def monitor(self) -> ImportMonitor:
        """The importing stage's monitor: the importer's steps written (at most every STEP_WRITE_PERIOD_S) as
        progress between the importing and checking stages, and the lease's stop request."""
        low, high = STAGE_PROGRESS["importing"], STAGE_PROGRESS["checking"]
        last_write = 0.0

        def report(step: str, fraction: float) -> None:
            nonlocal last_write
            if time.monotonic() - last_write < STEP_WRITE_PERIOD_S:
                return
            last_write = time.monotonic()
            progress = low + (high - low) * fraction
            IMPORTS.record_progress(self.settings, self.row.id, self.row.attempt, "importing", progress,
                                    elapsed_eta(self._started, progress), step)

        return ImportMonitor(report=report, should_stop=self.lease.should_stop)


def import_capture(settings: Settings, row: ImportRow, lease: Lease) -> dict:
    """Import a claimed capture; the final row values: ``state`` succeeded (``scene_id``, ``summary``),
    cancelled, or failed (``error``)."""
    stages = Stages(settings, row, lease)
    settings.make_dirs()
    staging = Path(tempfile.mkdtemp(prefix=f"import-{row.id}-", dir=settings.staging_dir))
    scene = staging / SCENE_DIR
    try:
        stages.enter("importing")
        summary = run_import(row.layout, _capture(settings, row), scene, SPLIT_RULES.get(row.params.get("splits")),
                             stages.monitor())
        stages.enter("checking")
        checked = inspect_scene(scene)
        stages.enter("storing")
        stored = commit_scene(settings, scene, row.name, {**checked, "imported": summary}, tree_size(scene),
                              created_by=row.created_by)  # the scene is the import's maker's
    except (Stopped, ImportCancelled):
        return {"state": "cancelled"}
    except Exception as err:
        return {"state": "failed", "error": public_error(_why_failed(row, err), settings)}
    finally:
        shutil.rmtree(staging, ignore_errors=True)
    return {"state": "succeeded", "scene_id": stored.id, "summary": summary}


def _why_failed(row: ImportRow, err: Exception) -> str:
    """A failed import's error: a full disk said as such, a refusal (the importer's or the check's one line) as
    it is, anything else an internal error (logged with its traceback)."""
    if (full := disk_full_message(err, "the scene was written")) is not None:
        log.warning("import %s failed: %s", row.id, full)
        return f"{full}: nothing was stored and the capture is removed; free space and upload it again"
    if isinstance(err, (VoxNeRFError, PublishFailed)):
        log.warning("import %s failed: %s", row.id, err)
        return str(err)
    log.exception("import %s crashed", row.id)
    return f"internal error: {type(err).__name__}: {err}"


def remove_capture(settings: Settings, row: ImportRow, state: str) -> None:
    """An import that ended (in any state) leaves no raw capture behind."""
    remove_raw(settings, row.id)
