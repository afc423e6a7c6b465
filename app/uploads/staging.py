"""Scene uploads, on the API's side: stage the upload on disk, have it validated in a separate process, then
store it atomically.

1. ``POST /scenes`` takes at most ``max_concurrent_uploads`` uploads at once per API process (429 beyond,
   :mod:`app.routes.scenes`); the request body is cut off past ``max_upload_bytes`` while it streams in
   (:mod:`app.body_limit`) and the multipart parser spools file parts to disk;
2. the upload goes into a private staging directory under ``data_dir/staging``: a zip is copied there as it
   is; files sent as form parts are written under their (checked) names into the staging scene, after their
   count, duplicates, types and the size of ``transforms.json`` are checked;
3. a validation process unpacks and checks it under a memory and a time limit (:mod:`app.uploads.sandbox`
   runs :mod:`app.uploads.validation`, whose docstring lists its checks): the API process parses nothing the
   client sent and never imports torch;
4. the room on disk is checked again with the scene unpacked (:func:`app.core.disk_space.require_room`: the
   data directory's quota and the free-space floor; the route checked the declared size before the body was
   read), and a disk that fills up while the upload is written is answered the same way (507);
5. only then one ``os.replace`` of the staging scene into ``data_dir/scenes/<id>``, and, when ``storage_url``
   is set, its upload to the object store (:func:`app.core.scene_store.commit_scene`).

A capture whose import takes long (``QUEUED_LAYOUTS``: a ROS bag, sent as one file or as a zip of a ROS 2 bag
folder) is not imported here: the zip is unpacked under the same limits (3.) and the room checked (4.), the file
is copied as it is (recognised by its first bytes alone), and the raw capture is queued as an import job
(:func:`app.core.imports.create_import`); a worker writes and checks its scene.

Any failure removes the staging directory, so a refused upload leaves nothing behind.
"""

from __future__ import annotations

import errno
import logging
import shutil
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import BinaryIO

from app.core.disk_space import InsufficientStorage, require_room
from app.core.imports import create_import
from app.core.lease import QueueFull
from app.core.models import ImportRow
from app.core.scene_store import PublishFailed, StoredScene, commit_scene
from app.core.settings import Settings
from app.core.tokens import Principal
from app.uploads.rules import (
    StagedUpload,
    UploadError,
    check_suffix,
    check_transforms_size,
    clip,
    copy_limited,
    safe_relpath,
)
from app.uploads.sandbox import validate_in_child
from app.uploads.validation import RAW_DIR
from voxnerf.data.importers import CAPTURE_MAGIC_BYTES, capture_file_layout
from voxnerf.data.importers.splits import PaperSplitRule
from voxnerf.files import TRANSFORMS

__all__ = ["TRANSFORMS", "StoredScene", "UploadError", "capture_kind", "safe_relpath", "split_rule",
           "store_capture", "store_parts", "store_zip"]

SPLIT_RULES = {"paper": PaperSplitRule()}
SCENE_DIR = "scene"  # in an upload's staging directory: the scene being filled and validated
ARCHIVE_NAME = "upload.zip"  # in an upload's staging directory: the zip as it was sent

log = logging.getLogger(__name__)


def split_rule(value: object) -> PaperSplitRule | None:
    """The split rule the form field ``splits`` names (absent or empty: none); UploadError (422) otherwise."""
    if value is None or value == "":
        return None
    if not isinstance(value, str) or value not in SPLIT_RULES:
        raise UploadError(422, f"splits: expected one of {', '.join(SPLIT_RULES)}, got {clip(str(value))}")
    return SPLIT_RULES[value]


def _stream_size(source: BinaryIO) -> int:
    """Bytes from the current position of a seekable stream to its end (the position is kept)."""
    position = source.tell()
    size = source.seek(0, 2) - position
    source.seek(position)
    return size


def _write_parts(parts: list[tuple[str, BinaryIO]], root: Path, settings: Settings) -> None:
    """Write the form's file parts into ``root`` under their paths, after checking names, count and the size
    of ``transforms.json``; nothing is parsed here."""
    paths = [safe_relpath(name) for name, _ in parts]
    for path in paths:
        check_suffix(path)
    if len(paths) > settings.max_files:
        raise UploadError(413, f"{len(paths)} files uploaded; at most {settings.max_files} allowed")
    if len(set(paths)) != len(paths):
        raise UploadError(422, "the same file name was uploaded twice")
    for path, (_, source) in zip(paths, parts, strict=True):
        check_transforms_size(path, _stream_size(source), settings)
    total = 0
    for path, (_, source) in zip(paths, parts, strict=True):
        total += copy_limited(source, root / path, settings.max_scene_bytes - total, str(path))


def _commit(settings: Settings, root: Path, name: str, summary: dict, size: int,
            principal: Principal | None) -> StoredScene:
    """Move a validated scene into ``scenes_dir`` (:func:`app.core.scene_store.commit_scene`); 503 when the object
    store refuses its copy."""
    try:
        return commit_scene(settings, root, name, summary, size, created_by=principal and principal.name)
    except PublishFailed as err:
        raise UploadError(503, str(err)) from None


def _queue_import(settings: Settings, raw: Path, name: str, layout: str,
                  splits: PaperSplitRule | None, principal: Principal | None) -> ImportRow:
    """Queue the import of the raw capture at ``raw`` (moved out of staging); 429 when the queue is full."""
    params = {"splits": next((key for key, rule in SPLIT_RULES.items() if rule == splits), None)}
    try:
        return create_import(settings, raw, name, layout, params, principal)
    except QueueFull as full:
        raise UploadError(429, str(full)) from None


def store_scene(settings: Settings, name: str, stage: Callable[[Path], StagedUpload],
                principal: Principal | None = None) -> StoredScene | ImportRow:
    """Stage an upload with ``stage(root) -> StagedUpload`` (``root``: an empty scene directory in a fresh
    staging directory, which ``stage`` may also write beside), validate it in a validation process, and move
    the scene into ``scenes_dir``.

    Returns the new scene (its row added to the job store), or the queued import of a capture whose import
    takes long, each recorded as made by ``principal`` (None: outside the API); raises UploadError leaving nothing
    stored.
    """
    settings.make_dirs()
    staging = Path(tempfile.mkdtemp(prefix="upload-", dir=settings.staging_dir))
    root = staging / SCENE_DIR
    root.mkdir()
    try:
        upload = stage(root)
        validated = validate_in_child(upload, settings)
        archive_bytes = upload.archive.stat().st_size if upload.archive is not None else 0
        require_room(settings, counted_apart=archive_bytes, what=f"the scene ({validated.size_bytes} bytes unpacked)")
        if validated.queued_layout is not None:
            return _queue_import(settings, staging / RAW_DIR, name, validated.queued_layout, upload.splits,
                                 principal)
        return _commit(settings, upload.root, name, validated.summary, validated.size_bytes, principal)
    except OSError as err:
        if err.errno in (errno.ENOSPC, errno.EDQUOT):
            raise InsufficientStorage(f"the server's disk filled up while the upload was stored ({err.strerror}); "
                                      "nothing was kept: free space, then upload again") from None
        raise
    finally:
        shutil.rmtree(staging, ignore_errors=True)


def _place(settings: Settings, source: BinaryIO | Path, target: Path) -> None:
    """Put an upload's file at ``target``: a stream (a request's body) is copied, at most ``max_upload_bytes``;
    a file (an upload session's, bounded by ``max_upload_session_bytes`` as its parts arrived) is moved."""
    if isinstance(source, Path):
        source.replace(target)
        return
    source.seek(0)
    copy_limited(source, target, settings.max_upload_bytes, "file")


def capture_kind(source: BinaryIO) -> tuple[str, str] | None:
    """``(layout, suffix)`` of a capture sent as one file (a ROS bag) from its first bytes, None for anything
    else (:func:`voxnerf.data.importers.capture_file_layout`); the stream is left at its start."""
    source.seek(0)
    head = source.read(CAPTURE_MAGIC_BYTES)
    source.seek(0)
    return capture_file_layout(head)


def store_capture(settings: Settings, name: str, source: BinaryIO | Path, kind: tuple[str, str],
                  splits: PaperSplitRule | None = None, principal: Principal | None = None) -> ImportRow:
    """Queue the import of a capture sent as one file of ``kind`` (:func:`capture_kind`): placed as it is
    (:func:`_place`) and moved into the imports directory; nothing of it is parsed here."""
    layout, suffix = kind
    settings.make_dirs()
    staging = Path(tempfile.mkdtemp(prefix="upload-", dir=settings.staging_dir))
    try:
        capture = staging / f"capture{suffix}"
        _place(settings, source, capture)
        return _queue_import(settings, capture, name, layout, splits, principal)
    finally:
        shutil.rmtree(staging, ignore_errors=True)


def store_zip(
    settings: Settings, name: str, source: BinaryIO | Path, splits: PaperSplitRule | None = None,
    principal: Principal | None = None,
) -> StoredScene | ImportRow:
    """Store the scene in a zip archive (a binary file): a scene directory, or a COLMAP model or ScanNet export
    to import (with ``splits``, the paper's splits; see :func:`split_rule`), or a ROS 2 bag folder whose import
    is queued."""

    def stage(root: Path) -> StagedUpload:
        archive = root.parent / ARCHIVE_NAME
        _place(settings, source, archive)
        return StagedUpload(root, archive, splits)

    return store_scene(settings, name, stage, principal)


def store_parts(settings: Settings, name: str, parts: list[tuple[str, BinaryIO]],
                principal: Principal | None = None) -> StoredScene:
    """Store a scene uploaded as files, each named by its path inside the scene (``images/0001.png``)."""

    def stage(root: Path) -> StagedUpload:
        _write_parts(parts, root, settings)
        return StagedUpload(root, None)

    return store_scene(settings, name, stage, principal)


def remove_scene_files(settings: Settings, scene_id: str) -> None:
    """Delete ``scenes/<id>``: renamed into staging first, so it disappears at once even if rmtree is slow."""
    path = settings.scenes_dir / scene_id
    if not path.exists():
        return
    doomed = Path(tempfile.mkdtemp(prefix="deleted-", dir=settings.staging_dir)) / scene_id
    path.replace(doomed)
    shutil.rmtree(doomed.parent, ignore_errors=True)
