"""Adding a finished scene to the service, for the API (an upload validated in :mod:`app.uploads`) and for the
workers (a capture import, :mod:`worker.imports`) alike: one ``os.replace`` of the scene directory into
``data_dir/scenes/<id>``, its copy in the object store when ``storage_url`` is set, then its row."""

from __future__ import annotations

import logging
import shutil
from dataclasses import dataclass
from pathlib import Path

from app.core import jobstore, storage
from app.core.settings import Settings

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class StoredScene:
    id: str
    size_bytes: int
    summary: dict


def tree_size(path: Path) -> int:
    """Bytes of the file at ``path``, or of every file under the folder at ``path``."""
    if not path.is_dir():
        return path.stat().st_size
    return sum(p.stat().st_size for p in path.rglob("*") if p.is_file())


class PublishFailed(Exception):
    """The object store refused the scene's copy (the API answers 503; an import fails naming it)."""


def commit_scene(settings: Settings, root: Path, name: str, summary: dict, size: int,
                 created_by: str | None = None) -> StoredScene:
    """Move the validated scene at ``root`` (on the data directory's filesystem) into ``scenes_dir`` under a new
    id, publish it to the object store and add its row (made by principal ``created_by``); on any failure the
    moved scene is removed again. Raises PublishFailed when the store refuses it."""
    scene_id = jobstore.new_id()
    final = settings.scenes_dir / scene_id
    root.replace(final)
    try:
        try:
            storage.publish_scene(settings, scene_id)
        except Exception as err:
            log.error("scene %s: upload to the object store failed", scene_id, exc_info=True)
            raise PublishFailed(f"the scene could not be copied to the object store ({type(err).__name__}: "
                                f"{err}); try again") from None
        jobstore.add_scene(settings, scene_id, name, summary, size, created_by)
    except BaseException:
        shutil.rmtree(final, ignore_errors=True)
        raise
    return StoredScene(scene_id, size, summary)
