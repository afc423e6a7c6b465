"""The rules an uploaded file's name and size must meet, the bounded copy, and what the API process (which stages
an upload) and the validation process (which unpacks and checks it, :mod:`app.uploads.validation`) hand each other:
:class:`StagedUpload` in, :class:`ValidatedScene` out.

:class:`UploadError` is a refusal: an HTTP status (4xx) and a one-line ``detail`` naming the entry at fault.
Nothing here interprets a file's contents.
"""

from __future__ import annotations

import errno
import re
from dataclasses import dataclass
from pathlib import Path, PurePosixPath
from typing import BinaryIO

from app.core.settings import Settings
from voxnerf.data.importers.splits import PaperSplitRule
from voxnerf.files import TRANSFORMS


@dataclass(frozen=True)
class StagedUpload:
    """An upload on disk, as the API process hands it to the validation process."""

    root: Path  # the scene directory to fill (from ``archive``) and validate: ``<staging>/scene``
    archive: Path | None  # a zip to unpack into ``root`` first; None: the files are in ``root`` already
    splits: PaperSplitRule | None = None  # for an archive to import: write the paper's splits


@dataclass(frozen=True)
class ValidatedScene:
    """What the validation process answers for a valid scene."""

    size_bytes: int  # of the files in ``root``
    summary: dict  # the engine's summary (``voxnerf.data.scene.inspect_scene``), with ``imported`` for an import
    queued_layout: str | None = None  # an import to queue (QUEUED_LAYOUTS): unpacked beside ``root``, not imported


ALLOWED_SUFFIXES = frozenset(
    {".json", ".png", ".jpg", ".jpeg", ".npy", ".ply", ".obj", ".mtl", ".glb", ".off"}
)
# only in an import layout: COLMAP models and ScanNet poses, Record3D depth, a Stray Scanner recording's video and
# odometry, a ROS 2 bag folder's metadata and storage
IMPORT_SUFFIXES = frozenset({".txt", ".bin", ".exr", ".mp4", ".csv", ".yaml", ".db3", ".mcap"})
IGNORED_PREFIXES = ("__MACOSX/",)  # resource forks written by macOS's archiver
IGNORED_NAMES = frozenset({".DS_Store", "Thumbs.db"})
MAX_PATH_BYTES = 1024  # a relative path inside a scene; with the staging prefix well under Linux's PATH_MAX
MAX_PATH_DEPTH = 32  # folders in such a path
COPY_CHUNK = 1024 * 1024
_DRIVE = re.compile(r"^[A-Za-z]:")


class UploadError(Exception):
    """A refused upload: ``status_code`` (4xx) and a ``detail`` naming the entry and the reason."""

    def __init__(self, status_code: int, detail: str) -> None:
        self.status_code = status_code
        # a name echoed from hostile input may hold lone surrogates, which no JSON response can encode
        self.detail = detail.encode("utf-8", "backslashreplace").decode("utf-8")
        super().__init__(self.detail)


def safe_relpath(name: str) -> PurePosixPath:
    """The relative path an archive entry or uploaded part names, or UploadError if it could escape."""
    if not name or "\x00" in name:
        raise UploadError(422, f"entry {clip(name)}: empty name or NUL byte")
    if "\\" in name:
        raise UploadError(422, f"entry {clip(name)}: backslash in name (use '/' separators)")
    if name.startswith("/") or _DRIVE.match(name):
        raise UploadError(422, f"entry {clip(name)}: absolute path")
    parts = [p for p in name.split("/") if p not in ("", ".")]
    if ".." in parts:
        raise UploadError(422, f"entry {clip(name)}: '..' would escape the scene directory")
    if not parts:
        raise UploadError(422, f"entry {clip(name)}: names no file")
    if any(len(p.encode()) > 255 for p in parts):
        raise UploadError(422, f"entry {clip(name)}: a path component is longer than 255 bytes")
    if len(parts) > MAX_PATH_DEPTH or len("/".join(parts).encode()) > MAX_PATH_BYTES:
        raise UploadError(
            422,
            f"entry {clip(name)}: path deeper than {MAX_PATH_DEPTH} folders or longer than "
            f"{MAX_PATH_BYTES} bytes",
        )
    return PurePosixPath(*parts)


def clip(name: str) -> str:
    """``repr(name)``, shortened when long (a hostile name can be megabytes)."""
    text = repr(name)
    return text if len(text) <= 100 else f"{text[:80]}...' ({len(name)} characters)"


def ignored(name: str) -> bool:
    """Archive litter that is skipped rather than extracted (macOS resource forks, Finder and Explorer files)."""
    return name.startswith(IGNORED_PREFIXES) or PurePosixPath(name).name in IGNORED_NAMES


def check_suffix(path: PurePosixPath, also: frozenset[str] = frozenset()) -> None:
    """415 unless ``path`` has one of the scene's file types (or one of ``also``)."""
    if path.suffix.lower() not in ALLOWED_SUFFIXES | also:
        raise UploadError(
            415,
            f"entry {clip(str(path))}: unsupported file type {path.suffix or '(none)'!r}; "
            f"allowed: {', '.join(sorted(ALLOWED_SUFFIXES | also))}",
        )


def check_transforms_size(path: PurePosixPath, size: int, settings: Settings) -> None:
    """413 when ``path`` is the scene's ``transforms.json`` and ``size`` (bytes: declared by an archive, sent
    in a form part, or on disk) is over ``max_transforms_bytes``; called before the file is parsed."""
    if path == PurePosixPath(TRANSFORMS) and size > settings.max_transforms_bytes:
        raise UploadError(
            413,
            f"{TRANSFORMS} is {size} bytes; the limit is {settings.max_transforms_bytes} "
            "(VOXNERF_MAX_TRANSFORMS_BYTES)",
        )


def _read_chunk(src: BinaryIO, name: str) -> bytes:
    """The next chunk of an entry; a decompressor choking on corrupt data (bz2 raises OSError) is a 422."""
    try:
        return src.read(COPY_CHUNK)
    except OSError as err:
        raise UploadError(422, f"entry {clip(name)}: corrupt compressed data ({err})") from None


def copy_limited(src: BinaryIO, dst: Path, limit: int, name: str) -> int:
    """Copy ``src`` into the new file ``dst`` (its folders made), at most ``limit`` bytes: more means the entry
    lied about its size (422). Returns the bytes written; memory stays at one chunk."""
    written = 0
    try:
        dst.parent.mkdir(parents=True, exist_ok=True)
        with open(dst, "xb") as out:
            while chunk := _read_chunk(src, name):
                written += len(chunk)
                if written > limit:
                    raise UploadError(422, f"entry {clip(name)}: larger than its declared size")
                out.write(chunk)
    except (FileExistsError, NotADirectoryError, IsADirectoryError):
        raise UploadError(
            422, f"entry {clip(name)}: clashes with another entry (a file and a folder of one name)"
        ) from None
    except OSError as err:
        if err.errno not in (errno.ENAMETOOLONG, errno.EILSEQ):
            raise  # disk full, permissions: the server's problem, not the upload's
        raise UploadError(
            422, f"entry {clip(name)}: the file system refuses this name ({err.strerror})"
        ) from None
    return written
