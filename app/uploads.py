"""Scene uploads: inspect an archive (or multipart files) before unpacking, validate, then store atomically.

Order of checks, each refusing with :class:`UploadError` (an HTTP status and a one-line ``detail``):

1. the archive's central directory, before anything is extracted: entry names that would escape the
   scene directory (``..``, absolute paths, drive letters, backslashes, NUL), symlinks and other special
   files, encrypted entries, unsupported compression or file types, duplicate names, too many files, a
   total declared size over ``max_scene_bytes``, and compression ratios typical of zip bombs;
2. extraction into a private staging directory under ``data_dir``, never writing more bytes than declared;
3. every image and ``.npy`` header, before any pixel is decoded: declared width x height over
   ``max_image_pixels``;
   an archive without ``transforms.json`` holding a COLMAP model (``sparse/0/cameras.bin|txt``) or a ScanNet
   export (``color/ pose/ intrinsic/``) is extracted beside the staging scene and written into it by the
   matching importer (:mod:`voxnerf.importers`), optionally with the paper's splits (form field ``splits``);
4. :func:`voxnerf.scene.inspect_scene`: the engine's own validation of transforms.json, images (sizes
   must match the intrinsics), depth maps and the prior (imported when an upload is validated, so that the
   API process does not load torch until then);
5. only then one ``os.replace`` of the staging directory into ``data_dir/scenes/<id>``, and, when
   ``storage_url`` is set, its upload to the object store (:func:`app.core.storage.publish_scene`).

Any failure removes the staging directory, so a refused upload leaves nothing behind.
"""

from __future__ import annotations

import errno
import logging
import lzma
import math
import re
import shutil
import stat
import tempfile
import zipfile
import zlib
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path, PurePosixPath
from typing import BinaryIO

import numpy as np

from app.core import jobstore, storage
from app.core.settings import Settings
from voxnerf.errors import SceneError
from voxnerf.files import TRANSFORMS
from voxnerf.image_io import image_size
from voxnerf.importers import PaperSplitRule, detect_layout, run_import

ALLOWED_SUFFIXES = frozenset(
    {".json", ".png", ".jpg", ".jpeg", ".npy", ".ply", ".obj", ".mtl", ".glb", ".off"}
)
IMAGE_SUFFIXES = frozenset({".png", ".jpg", ".jpeg"})
IMPORT_SUFFIXES = frozenset({".txt", ".bin"})  # COLMAP models and ScanNet poses: only in an import layout
SPLIT_RULES = {"paper": PaperSplitRule()}
RAW_DIR = "raw"  # beside the staging scene: an import layout as uploaded, before its importer runs
SUPPORTED_COMPRESSION = frozenset(
    {zipfile.ZIP_STORED, zipfile.ZIP_DEFLATED, zipfile.ZIP_BZIP2, zipfile.ZIP_LZMA}
)
IGNORED_PREFIXES = ("__MACOSX/",)  # resource forks written by macOS's archiver
IGNORED_NAMES = frozenset({".DS_Store", "Thumbs.db"})
BOMB_MIN_BYTES = 1024 * 1024  # entries smaller than this may compress arbitrarily well
COPY_CHUNK = 1024 * 1024
MAX_PATH_BYTES = 1024  # a relative path inside a scene; with the staging prefix well under Linux's PATH_MAX
MAX_PATH_DEPTH = 32  # folders in such a path
_DRIVE = re.compile(r"^[A-Za-z]:")
NPY_HEADER_READERS = {
    (1, 0): np.lib.format.read_array_header_1_0,
    (2, 0): np.lib.format.read_array_header_2_0,
}

log = logging.getLogger(__name__)


class UploadError(Exception):
    """A refused upload: ``status_code`` (4xx) and a ``detail`` naming the entry and the reason."""

    def __init__(self, status_code: int, detail: str) -> None:
        self.status_code = status_code
        # a name echoed from hostile input may hold lone surrogates, which no JSON response can encode
        self.detail = detail.encode("utf-8", "backslashreplace").decode("utf-8")
        super().__init__(self.detail)


@dataclass(frozen=True)
class StoredScene:
    id: str
    size_bytes: int
    summary: dict


def safe_relpath(name: str) -> PurePosixPath:
    """The relative path an archive entry or uploaded part names, or UploadError if it could escape."""
    if not name or "\x00" in name:
        raise UploadError(422, f"entry {_clip(name)}: empty name or NUL byte")
    if "\\" in name:
        raise UploadError(422, f"entry {_clip(name)}: backslash in name (use '/' separators)")
    if name.startswith("/") or _DRIVE.match(name):
        raise UploadError(422, f"entry {_clip(name)}: absolute path")
    parts = [p for p in name.split("/") if p not in ("", ".")]
    if ".." in parts:
        raise UploadError(422, f"entry {_clip(name)}: '..' would escape the scene directory")
    if not parts:
        raise UploadError(422, f"entry {_clip(name)}: names no file")
    if any(len(p.encode()) > 255 for p in parts):
        raise UploadError(422, f"entry {_clip(name)}: a path component is longer than 255 bytes")
    if len(parts) > MAX_PATH_DEPTH or len("/".join(parts).encode()) > MAX_PATH_BYTES:
        raise UploadError(
            422,
            f"entry {_clip(name)}: path deeper than {MAX_PATH_DEPTH} folders or longer than "
            f"{MAX_PATH_BYTES} bytes",
        )
    return PurePosixPath(*parts)


def _clip(name: str) -> str:
    """``repr(name)``, shortened when long (a hostile name can be megabytes)."""
    text = repr(name)
    return text if len(text) <= 100 else f"{text[:80]}...' ({len(name)} characters)"


def _ignored(name: str) -> bool:
    return name.startswith(IGNORED_PREFIXES) or PurePosixPath(name).name in IGNORED_NAMES


def _check_suffix(path: PurePosixPath, also: frozenset[str] = frozenset()) -> None:
    if path.suffix.lower() not in ALLOWED_SUFFIXES | also:
        raise UploadError(
            415,
            f"entry {_clip(str(path))}: unsupported file type {path.suffix or '(none)'!r}; "
            f"allowed: {', '.join(sorted(ALLOWED_SUFFIXES | also))}",
        )


def _layout_of(paths: list[PurePosixPath]) -> str | None:
    """``"colmap"`` or ``"scannet"`` for an archive to import, None for a scene (``.txt``/``.bin`` refused)."""
    layout = None if PurePosixPath(TRANSFORMS) in paths else detect_layout(paths)
    if layout is None:
        for path in paths:
            _check_suffix(path)
    return layout


def _strip_common_folder(paths: list[PurePosixPath]) -> list[PurePosixPath]:
    """Drop one top-level folder that holds everything (``room/transforms.json`` -> ``transforms.json``)."""
    if any(p == PurePosixPath(TRANSFORMS) for p in paths):
        return paths
    tops = {p.parts[0] for p in paths}
    if len(tops) == 1 and all(len(p.parts) > 1 for p in paths):
        return [PurePosixPath(*p.parts[1:]) for p in paths]
    return paths


def _plan_zip(
    archive: zipfile.ZipFile, settings: Settings
) -> tuple[list[tuple[zipfile.ZipInfo, PurePosixPath]], str | None]:
    """Which entries to extract where, and the layout to import (None: a scene); raises UploadError for anything
    unsafe. Reads only the directory."""
    infos = archive.infolist()
    if len(infos) > 2 * settings.max_files:
        raise UploadError(
            413, f"archive has {len(infos)} entries; at most {settings.max_files} files allowed"
        )
    planned = [(info, path) for info in infos if (path := _entry_path(info)) is not None]
    _check_archive_sizes([info for info, _ in planned], settings)
    targets = _strip_common_folder([path for _, path in planned])
    seen: set[PurePosixPath] = set()
    for target in targets:
        if target in seen:
            raise UploadError(422, f"entry {_clip(str(target))} appears twice")
        seen.add(target)
    plan = [(info, target) for (info, _), target in zip(planned, targets, strict=True)]
    return plan, _layout_of(targets)


def _entry_path(info: zipfile.ZipInfo) -> PurePosixPath | None:
    """Where one archive entry goes in the scene; None for what is skipped (folders, macOS and Windows
    litter); UploadError for links, special files, encryption, unknown compression and unsupported types."""
    if _ignored(info.filename):
        return None
    path = safe_relpath(info.filename)
    mode = info.external_attr >> 16
    file_type = stat.S_IFMT(mode) if info.create_system == 3 else 0
    if file_type == stat.S_IFLNK:
        raise UploadError(422, f"entry {_clip(info.filename)}: symbolic links are not allowed")
    if info.is_dir() or file_type == stat.S_IFDIR:
        return None
    if file_type not in (0, stat.S_IFREG):
        raise UploadError(422, f"entry {_clip(info.filename)}: not a regular file (mode {oct(mode)})")
    if info.flag_bits & 0x1:
        raise UploadError(422, f"entry {_clip(info.filename)}: encrypted entries are not supported")
    if info.compress_type not in SUPPORTED_COMPRESSION:
        raise UploadError(
            422, f"entry {_clip(info.filename)}: unsupported compression method {info.compress_type}"
        )
    _check_suffix(path, IMPORT_SUFFIXES)  # .txt and .bin: refused by _layout_of unless the archive is imported
    return path


def _check_archive_sizes(infos: list[zipfile.ZipInfo], settings: Settings) -> None:
    """The files to extract: how many, their declared total, and compression ratios (zip bombs)."""
    if len(infos) > settings.max_files:
        raise UploadError(413, f"archive has {len(infos)} files; at most {settings.max_files} allowed")
    declared = sum(info.file_size for info in infos)
    if declared > settings.max_scene_bytes:
        raise UploadError(
            413, f"archive declares {declared} bytes uncompressed; the limit is {settings.max_scene_bytes}"
        )
    for info in infos:
        ratio = info.file_size / max(info.compress_size, 1)
        if info.file_size >= BOMB_MIN_BYTES and ratio > settings.max_compression_ratio:
            raise UploadError(
                422,
                f"entry {_clip(info.filename)}: compression ratio {ratio:.0f} exceeds "
                f"{settings.max_compression_ratio:.0f} (zip bomb?)",
            )
    compressed = sum(info.compress_size for info in infos)
    if declared >= BOMB_MIN_BYTES and declared > settings.max_compression_ratio * max(compressed, 1):
        raise UploadError(
            422,
            f"archive compression ratio {declared / max(compressed, 1):.0f} exceeds "
            f"{settings.max_compression_ratio:.0f} (zip bomb?)",
        )


def _read_chunk(src: BinaryIO, name: str) -> bytes:
    """The next chunk of an entry; a decompressor choking on corrupt data (bz2 raises OSError) is a 422."""
    try:
        return src.read(COPY_CHUNK)
    except OSError as err:
        raise UploadError(422, f"entry {_clip(name)}: corrupt compressed data ({err})") from None


def _copy_limited(src: BinaryIO, dst: Path, limit: int, name: str) -> int:
    """Copy at most ``limit`` bytes; more means the entry lied about its size."""
    written = 0
    try:
        dst.parent.mkdir(parents=True, exist_ok=True)
        with open(dst, "xb") as out:
            while chunk := _read_chunk(src, name):
                written += len(chunk)
                if written > limit:
                    raise UploadError(422, f"entry {_clip(name)}: larger than its declared size")
                out.write(chunk)
    except (FileExistsError, NotADirectoryError, IsADirectoryError):
        raise UploadError(
            422, f"entry {_clip(name)}: clashes with another entry (a file and a folder of one name)"
        ) from None
    except OSError as err:
        if err.errno not in (errno.ENAMETOOLONG, errno.EILSEQ):
            raise  # disk full, permissions: the server's problem, not the upload's
        raise UploadError(
            422, f"entry {_clip(name)}: the file system refuses this name ({err.strerror})"
        ) from None
    return written


def _extract_zip(source: BinaryIO, root: Path, settings: Settings) -> tuple[int, str | None]:
    """Bytes written and the layout to import: a scene goes to ``root``, an import layout beside it (RAW_DIR)."""
    try:
        with zipfile.ZipFile(source) as archive:
            plan, layout = _plan_zip(archive, settings)
            dest = root if layout is None else root.parent / RAW_DIR
            total = 0
            for info, target in plan:
                with archive.open(info) as src:
                    total += _copy_limited(src, dest / target, info.file_size, info.filename)
    except UploadError:
        raise
    except (
        zipfile.BadZipFile,
        zlib.error,
        lzma.LZMAError,
        EOFError,
        NotImplementedError,
        RuntimeError,
        ValueError,
    ) as err:
        raise UploadError(422, f"corrupt or unreadable zip archive: {err}") from None
    return total, layout


def _tree_size(root: Path) -> int:
    return sum(p.stat().st_size for p in root.rglob("*") if p.is_file())


def _import_layout(layout: str, root: Path, settings: Settings, rule: PaperSplitRule | None) -> tuple[int, dict]:
    """Write the extracted ``layout`` (in RAW_DIR beside ``root``) into ``root`` with its importer.

    Returns the scene's size and the importer's summary; UploadError (422) naming the file at fault.
    """
    raw = root.parent / RAW_DIR
    _check_declared_sizes(raw, settings)
    try:
        imported = run_import(layout, raw, root, rule)
    except SceneError as err:
        raise UploadError(422, f"{layout} import: {_hide_staging(str(err), raw)}") from None
    except Exception as err:  # a reader deep in pycolmap or Pillow choked on hostile bytes: the upload's fault
        log.warning("%s import refused by an unexpected %s", layout, type(err).__name__, exc_info=True)
        raise UploadError(422, _hide_staging(f"{layout} import failed: {type(err).__name__}: {err}", raw)) from None
    shutil.rmtree(raw, ignore_errors=True)
    return _tree_size(root), imported


def _unpack(source: BinaryIO, root: Path, settings: Settings, rule: PaperSplitRule | None) -> int | tuple[int, dict]:
    """Extract the zip into ``root``, or import it there when it holds a COLMAP model or a ScanNet export."""
    total, layout = _extract_zip(source, root, settings)
    if layout is None:
        if rule is not None:
            raise UploadError(
                422, "splits: only a COLMAP or ScanNet upload takes splits; a transforms.json scene names its own"
            )
        return total
    return _import_layout(layout, root, settings, rule)


def split_rule(value: object) -> PaperSplitRule | None:
    """The split rule the form field ``splits`` names (absent or empty: none); UploadError (422) otherwise."""
    if value is None or value == "":
        return None
    if not isinstance(value, str) or value not in SPLIT_RULES:
        raise UploadError(422, f"splits: expected one of {', '.join(SPLIT_RULES)}, got {_clip(str(value))}")
    return SPLIT_RULES[value]


def _write_parts(parts: Iterable[tuple[str, BinaryIO]], root: Path, settings: Settings) -> int:
    paths: list[PurePosixPath] = []
    sources: list[BinaryIO] = []
    for name, source in parts:
        path = safe_relpath(name)
        _check_suffix(path)
        paths.append(path)
        sources.append(source)
    if len(paths) > settings.max_files:
        raise UploadError(413, f"{len(paths)} files uploaded; at most {settings.max_files} allowed")
    if len(set(paths)) != len(paths):
        raise UploadError(422, "the same file name was uploaded twice")
    total = 0
    for path, source in zip(paths, sources, strict=True):
        total += _copy_limited(source, root / path, settings.max_scene_bytes - total, str(path))
    return total


def _npy_size(path: Path) -> tuple[int, int]:
    """``(width, height)`` a depth ``.npy`` declares (``[H, W]`` or ``[H, W, C]``; elements past H x W are
    folded into the width), from its header alone: ``np.load`` would allocate the whole array first."""
    try:
        with open(path, "rb") as f:
            version = np.lib.format.read_magic(f)
            if version not in NPY_HEADER_READERS:
                raise SceneError(path, f".npy format version {version} is not supported (1.0 or 2.0)")
            shape, _, _ = NPY_HEADER_READERS[version](f)
    except (ValueError, OSError, EOFError) as err:
        raise SceneError(path, f"cannot read .npy header: {err}") from None
    if len(shape) < 2:
        raise SceneError(path, f"depth .npy must have shape [H, W], got {list(shape)}")
    return math.prod(shape[1:]), shape[0]


def _check_declared_sizes(root: Path, settings: Settings) -> None:
    """Every image and .npy header, before anything is decoded: width x height within the limit."""
    for path in sorted(root.rglob("*")):
        suffix = path.suffix.lower()
        if suffix not in IMAGE_SUFFIXES | {".npy"} or not path.is_file():
            continue
        rel = path.relative_to(root)
        try:
            width, height = _npy_size(path) if suffix == ".npy" else image_size(path)
        except SceneError as err:
            raise UploadError(422, f"{rel}: {err.message}") from None
        if width * height > settings.max_image_pixels:
            raise UploadError(
                422,
                f"{rel}: declared image size {width}x{height} ({width * height} pixels) exceeds the "
                f"limit of {settings.max_image_pixels} pixels",
            )


def _hide_staging(text: str, root: Path) -> str:
    """A message with the private staging path cut down to a path inside the scene."""
    for prefix in (str(root.resolve()), str(root)):
        text = text.replace(prefix + "/", "").replace(prefix, ".")
    return text


def _publish(settings: Settings, scene_id: str) -> None:
    """Copy the stored scene to the object store, if one is configured; 503 when the store fails."""
    try:
        storage.publish_scene(settings, scene_id)
    except Exception as err:
        log.error("scene %s: upload to the object store failed", scene_id, exc_info=True)
        raise UploadError(
            503, f"the scene could not be copied to the object store ({type(err).__name__}: {err}); try again"
        ) from None


def _validate_staged(root: Path, settings: Settings, name: str) -> dict:
    """The engine's summary of the staged scene at ``root``; UploadError (422) when it is not a valid scene.

    The engine's scene checks are imported here, when an upload is validated, rather than when the API starts:
    they import torch, which the API process otherwise never needs.
    """
    from voxnerf.scene import inspect_scene

    if not (root / TRANSFORMS).is_file():
        raise UploadError(
            422,
            f"{TRANSFORMS} not found at the top of the scene (or inside one top-level folder), nor a COLMAP "
            "model (sparse/0/cameras.bin|txt) or a ScanNet export (color/, pose/, intrinsic/) to import",
        )
    _check_declared_sizes(root, settings)
    try:
        return inspect_scene(root)
    except SceneError as err:
        raise UploadError(422, _hide_staging(str(err), root)) from None
    except Exception as err:  # a parser deep in the engine choked on hostile bytes: still the upload's fault
        log.warning("upload %r refused by an unexpected %s", name, type(err).__name__, exc_info=True)
        detail = _hide_staging(f"the scene could not be read: {type(err).__name__}: {err}", root)
        raise UploadError(422, detail) from None


def _commit(settings: Settings, root: Path, name: str, summary: dict, size: int) -> StoredScene:
    """Move a validated scene into ``scenes_dir``, publish it to the store and add its row (or undo the move)."""
    scene_id = jobstore.new_id()
    final = settings.scenes_dir / scene_id
    root.replace(final)
    try:
        _publish(settings, scene_id)
        jobstore.add_scene(settings, scene_id, name, summary, size)
    except BaseException:
        shutil.rmtree(final, ignore_errors=True)
        raise
    return StoredScene(scene_id, size, summary)


def store_scene(settings: Settings, name: str, fill: Callable[[Path], int | tuple[int, dict]]) -> StoredScene:
    """Stage a scene with ``fill(root) -> bytes written`` (or ``(bytes, importer's summary)`` for an import),
    validate it, and move it into ``scenes_dir``; the importer's summary is the scene summary's ``imported``.

    Returns the new scene (its row added to the job store); raises UploadError leaving nothing stored.
    """
    settings.make_dirs()
    staging = Path(tempfile.mkdtemp(prefix="upload-", dir=settings.staging_dir))
    root = staging / "scene"
    root.mkdir()
    try:
        filled = fill(root)
        size, imported = filled if isinstance(filled, tuple) else (filled, None)
        summary = _validate_staged(root, settings, name)
        if imported is not None:
            summary["imported"] = imported
        return _commit(settings, root, name, summary, size)
    finally:
        shutil.rmtree(staging, ignore_errors=True)


def store_zip(settings: Settings, name: str, source: BinaryIO, splits: PaperSplitRule | None = None) -> StoredScene:
    """Store the scene in a zip archive (a seekable binary file): a scene directory, or a COLMAP model or
    ScanNet export to import (with ``splits``, the paper's splits; see :func:`split_rule`)."""
    return store_scene(settings, name, lambda root: _unpack(source, root, settings, splits))


def store_parts(settings: Settings, name: str, parts: list[tuple[str, BinaryIO]]) -> StoredScene:
    """Store a scene uploaded as files, each named by its path inside the scene (``images/0001.png``)."""
    return store_scene(settings, name, lambda root: _write_parts(parts, root, settings))


def remove_scene_files(settings: Settings, scene_id: str) -> None:
    """Delete ``scenes/<id>``: renamed into staging first, so it disappears at once even if rmtree is slow."""
    path = settings.scenes_dir / scene_id
    if not path.exists():
        return
    doomed = Path(tempfile.mkdtemp(prefix="deleted-", dir=settings.staging_dir)) / scene_id
    path.replace(doomed)
    shutil.rmtree(doomed.parent, ignore_errors=True)
