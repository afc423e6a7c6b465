"""What an upload's validation process does (:mod:`app.uploads.sandbox` runs it under memory and time limits).

Order of checks, each refusing with :class:`~app.uploads.rules.UploadError` (an HTTP status and a one-line
``detail``):

1. a zip's end-of-central-directory record (zip64's when present), read from the file's tail before the
   directory itself is parsed: more than ``2 * max_files`` entries, or a directory larger than those entries
   can need, is refused (``zipfile`` would build an object per entry: 10^6 entries are gigabytes);
2. the central directory, before anything is extracted: entry names that would escape the scene directory
   (``..``, absolute paths, drive letters, backslashes, NUL), symlinks and other special files, encrypted
   entries, unsupported compression or file types, duplicate names, too many files, a ``transforms.json``
   declared over ``max_transforms_bytes``, a total declared size over ``max_scene_bytes``, and compression
   ratios typical of zip bombs;
3. extraction into the staging directory, never writing more bytes than declared;
4. every file whose first bytes (or, failing that, its suffix) say PNG, JPEG, ``.npy`` or EXR, whatever its name:
   the width x height its header declares, before any pixel is decoded, against ``max_image_pixels``, and
   their sum over the scene against ``max_scene_pixels``;
   an archive without ``transforms.json`` holding a COLMAP model (``sparse/0/cameras.bin|txt``), a ScanNet
   export (``color/ pose/ intrinsic/``), a Record3D EXR + JPG export (``metadata.json rgb/ depth/``) or a
   Polycam raw export (``keyframes/``) is extracted beside the staging scene and written into it by the
   matching importer (:mod:`voxnerf.data.importers`), optionally with the paper's splits;
5. the size of ``transforms.json`` on disk against ``max_transforms_bytes``, then
   :func:`voxnerf.data.scene.inspect_scene`: the engine's own validation of transforms.json, images (sizes must
   match the intrinsics), depth maps and the prior.
"""

from __future__ import annotations

import logging
import lzma
import math
import shutil
import stat
import struct
import zipfile
import zlib
from dataclasses import dataclass
from pathlib import Path, PurePosixPath
from typing import BinaryIO

import numpy as np

from app.core.scene_store import tree_size
from app.core.settings import Settings
from app.uploads.rules import (
    IMPORT_SUFFIXES,
    MAX_PATH_BYTES,
    StagedUpload,
    UploadError,
    ValidatedScene,
    check_suffix,
    check_transforms_size,
    clip,
    copy_limited,
    ignored,
    safe_relpath,
)
from voxnerf.data.image_io import EXR_MAGIC, PNG_SIGNATURE, image_size
from voxnerf.data.importers import QUEUED_LAYOUTS, PaperSplitRule, detect_layout, run_import
from voxnerf.errors import SceneError
from voxnerf.files import TRANSFORMS

IMAGE_SUFFIXES = frozenset({".png", ".jpg", ".jpeg"})
JPEG_MAGIC = b"\xff\xd8\xff"
NPY_MAGIC = b"\x93NUMPY"
RAW_DIR = "raw"  # beside the staging scene: an import layout as uploaded, before its importer runs
SUPPORTED_COMPRESSION = frozenset(
    {zipfile.ZIP_STORED, zipfile.ZIP_DEFLATED, zipfile.ZIP_BZIP2, zipfile.ZIP_LZMA}
)
BOMB_MIN_BYTES = 1024 * 1024  # entries smaller than this may compress arbitrarily well
NPY_HEADER_READERS = {
    (1, 0): np.lib.format.read_array_header_1_0,
    (2, 0): np.lib.format.read_array_header_2_0,
}
# the end-of-central-directory records, as zipfile reads them (APPNOTE.TXT 4.3.14-4.3.16)
EOCD = struct.Struct("<4s4H2LH")  # signature, disk numbers, entries here and in all, directory size and offset
EOCD_SIGNATURE = b"PK\x05\x06"
ZIP64_LOCATOR = struct.Struct("<4sLQL")  # signature, disk of the zip64 record, its offset, number of disks
ZIP64_LOCATOR_SIGNATURE = b"PK\x06\x07"
ZIP64_EOCD = struct.Struct("<4sQ2H2L4Q")  # ..., entries here and in all, directory size and offset
ZIP64_EOCD_SIGNATURE = b"PK\x06\x06"
MAX_ZIP_COMMENT = 0xFFFF
# a directory record: 46 fixed bytes, the name, and room for extra fields and a comment
MAX_DIRECTORY_RECORD_BYTES = 46 + MAX_PATH_BYTES + 1024

log = logging.getLogger(__name__)


def validate_upload(upload: StagedUpload, settings: Settings) -> ValidatedScene:
    """Unpack ``upload.archive`` (if any) into ``upload.root`` and validate the scene there.

    Returns its size and summary; raises UploadError for a refused upload. Writes only under the staging
    directory that holds ``upload.root``.
    """
    imported = None
    if upload.archive is not None:
        imported = _unpack(upload.archive, upload.root, settings, upload.splits)
    if isinstance(imported, str):  # a layout imported as queued work: the worker checks the scene it writes
        raw = upload.root.parent / RAW_DIR
        return ValidatedScene(tree_size(raw), {}, queued_layout=imported)
    summary = _validate_staged(upload.root, settings)
    if imported is not None:
        summary["imported"] = imported
    return ValidatedScene(tree_size(upload.root), summary)


# ------------------------------------------------------------------------------------------------ the archive


@dataclass(frozen=True)
class DirectoryExtent:
    """What a zip's end-of-central-directory record (zip64's when present) declares of its central directory."""

    entries: int
    size_bytes: int


def read_directory_extent(source: BinaryIO) -> DirectoryExtent:
    """The end-of-central-directory record ``zipfile`` would use, found as it finds it (at the very end, else
    the last signature in the final 64 KiB), with zip64's record when its locator precedes it. Reads at most
    64 KiB + 98 bytes; 422 when there is no such record."""
    source.seek(0, 2)
    file_size = source.tell()
    tail_start = max(file_size - EOCD.size - MAX_ZIP_COMMENT, 0)
    source.seek(tail_start)
    tail = source.read()
    at = _end_record_offset(tail)
    if at is None:
        raise UploadError(422, "corrupt or unreadable zip archive: no end-of-central-directory record")
    _, _, _, _, entries, size, _, _ = EOCD.unpack_from(tail, at)
    zip64 = _zip64_extent(source, tail_start + at)
    return zip64 or DirectoryExtent(entries, size)


def _end_record_offset(tail: bytes) -> int | None:
    """Where in ``tail`` the end-of-central-directory record starts (zipfile's rule), or None."""
    last = len(tail) - EOCD.size
    if last >= 0 and tail[last:].startswith(EOCD_SIGNATURE) and tail.endswith(b"\0\0"):
        return last
    at = tail.rfind(EOCD_SIGNATURE)
    return at if 0 <= at <= last else None


def _zip64_extent(source: BinaryIO, end_record_at: int) -> DirectoryExtent | None:
    """The zip64 end-of-central-directory record just before the zip64 locator that precedes the classic
    record at ``end_record_at``, as zipfile reads it; None when there is none."""
    if end_record_at < ZIP64_LOCATOR.size + ZIP64_EOCD.size:
        return None
    source.seek(end_record_at - ZIP64_LOCATOR.size)
    signature, disk, _, disks = ZIP64_LOCATOR.unpack(source.read(ZIP64_LOCATOR.size))
    if signature != ZIP64_LOCATOR_SIGNATURE:
        return None
    if disk != 0 or disks > 1:
        raise UploadError(422, "corrupt or unreadable zip archive: archives spanning several disks are not supported")
    source.seek(end_record_at - ZIP64_LOCATOR.size - ZIP64_EOCD.size)
    fields = ZIP64_EOCD.unpack(source.read(ZIP64_EOCD.size))
    if fields[0] != ZIP64_EOCD_SIGNATURE:
        return None
    return DirectoryExtent(entries=fields[7], size_bytes=fields[8])


def check_directory_extent(extent: DirectoryExtent, settings: Settings) -> None:
    """413 for more entries than a scene may hold (files, folders and archiver litter: ``2 * max_files``) or a
    directory larger than that many records can need: zipfile reads the whole directory and makes an object
    per record, whatever the entry count says."""
    max_entries = 2 * settings.max_files
    if extent.entries > max_entries:
        raise UploadError(
            413,
            f"archive declares {extent.entries} entries in its end-of-central-directory record; at most "
            f"{settings.max_files} files allowed (VOXNERF_MAX_FILES)",
        )
    max_size = max_entries * MAX_DIRECTORY_RECORD_BYTES
    if extent.size_bytes > max_size:
        raise UploadError(
            413,
            f"archive's central directory is {extent.size_bytes} bytes; {max_entries} entries need at most "
            f"{max_size} (VOXNERF_MAX_FILES)",
        )


def _layout_of(paths: list[PurePosixPath]) -> str | None:
    """``"colmap"`` or ``"scannet"`` for an archive to import, None for a scene (``.txt``/``.bin`` refused)."""
    layout = None if PurePosixPath(TRANSFORMS) in paths else detect_layout(paths)
    if layout is None:
        for path in paths:
            check_suffix(path)
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
    targets = _strip_common_folder([path for _, path in planned])
    seen: set[PurePosixPath] = set()
    for target in targets:
        if target in seen:
            raise UploadError(422, f"entry {clip(str(target))} appears twice")
        seen.add(target)
    plan = [(info, target) for (info, _), target in zip(planned, targets, strict=True)]
    for info, target in plan:
        check_transforms_size(target, info.file_size, settings)
    _check_archive_sizes([info for info, _ in planned], settings)
    return plan, _layout_of(targets)


def _entry_path(info: zipfile.ZipInfo) -> PurePosixPath | None:
    """Where one archive entry goes in the scene; None for what is skipped (folders, macOS and Windows
    litter); UploadError for links, special files, encryption, unknown compression and unsupported types."""
    if ignored(info.filename):
        return None
    path = safe_relpath(info.filename)
    mode = info.external_attr >> 16
    file_type = stat.S_IFMT(mode) if info.create_system == 3 else 0
    if file_type == stat.S_IFLNK:
        raise UploadError(422, f"entry {clip(info.filename)}: symbolic links are not allowed")
    if info.is_dir() or file_type == stat.S_IFDIR:
        return None
    if file_type not in (0, stat.S_IFREG):
        raise UploadError(422, f"entry {clip(info.filename)}: not a regular file (mode {oct(mode)})")
    if info.flag_bits & 0x1:
        raise UploadError(422, f"entry {clip(info.filename)}: encrypted entries are not supported")
    if info.compress_type not in SUPPORTED_COMPRESSION:
        raise UploadError(
            422, f"entry {clip(info.filename)}: unsupported compression method {info.compress_type}"
        )
    check_suffix(path, IMPORT_SUFFIXES)  # .txt and .bin: refused by _layout_of unless the archive is imported
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
                f"entry {clip(info.filename)}: compression ratio {ratio:.0f} exceeds "
                f"{settings.max_compression_ratio:.0f} (zip bomb?)",
            )
    compressed = sum(info.compress_size for info in infos)
    if declared >= BOMB_MIN_BYTES and declared > settings.max_compression_ratio * max(compressed, 1):
        raise UploadError(
            422,
            f"archive compression ratio {declared / max(compressed, 1):.0f} exceeds "
            f"{settings.max_compression_ratio:.0f} (zip bomb?)",
        )


def _extract_zip(path: Path, root: Path, settings: Settings) -> str | None:
    """Extract the zip at ``path``; returns the layout to import: a scene goes to ``root``, an import layout
    beside it (RAW_DIR)."""
    try:
        with open(path, "rb") as source:
            check_directory_extent(read_directory_extent(source), settings)
            with zipfile.ZipFile(source) as archive:
                plan, layout = _plan_zip(archive, settings)
                dest = root if layout is None else root.parent / RAW_DIR
                for info, target in plan:
                    with archive.open(info) as src:
                        copy_limited(src, dest / target, info.file_size, info.filename)
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
        struct.error,
    ) as err:
        raise UploadError(422, f"corrupt or unreadable zip archive: {err}") from None
    return layout


def _import_layout(layout: str, root: Path, settings: Settings, rule: PaperSplitRule | None) -> dict:
    """Write the extracted ``layout`` (in RAW_DIR beside ``root``) into ``root`` with its importer.

    Returns the importer's summary; UploadError (422) naming the file at fault.
    """
    raw = root.parent / RAW_DIR
    check_declared_sizes(raw, settings)
    try:
        imported = run_import(layout, raw, root, rule)
    except SceneError as err:
        raise UploadError(422, f"{layout} import: {_hide_staging(str(err), raw)}") from None
    except MemoryError:
        raise
    except Exception as err:  # a reader deep in pycolmap or Pillow choked on hostile bytes: the upload's fault
        log.warning("%s import refused by an unexpected %s", layout, type(err).__name__, exc_info=True)
        raise UploadError(422, _hide_staging(f"{layout} import failed: {type(err).__name__}: {err}", raw)) from None
    shutil.rmtree(raw, ignore_errors=True)
    return imported


def _unpack(archive: Path, root: Path, settings: Settings, rule: PaperSplitRule | None) -> dict | str | None:
    """Extract the zip into ``root``, or import it there when it holds a COLMAP model or a ScanNet export
    (then the importer's summary, else None); a layout imported as queued work (``QUEUED_LAYOUTS``, a ROS 2 bag
    folder) is only extracted beside ``root`` (RAW_DIR) and its name returned."""
    layout = _extract_zip(archive, root, settings)
    if layout is None:
        if rule is not None:
            raise UploadError(
                422, "splits: only an upload to import takes splits; a transforms.json scene names its own"
            )
        return None
    if layout in QUEUED_LAYOUTS:
        check_declared_sizes(root.parent / RAW_DIR, settings)
        return layout
    return _import_layout(layout, root, settings, rule)


# ------------------------------------------------------------------------------------------------ the files


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


def _exr_size(path: Path) -> tuple[int, int]:
    """``(width, height)`` of an EXR's data window (a phone app's depth map), from its header alone."""
    import OpenEXR

    try:
        window = OpenEXR.File(str(path), header_only=True).header()["dataWindow"]
        (x0, y0), (x1, y1) = (int(v) for v in window[0]), (int(v) for v in window[1])
    except (RuntimeError, OSError, KeyError, TypeError, ValueError) as err:
        raise SceneError(path, f"cannot read EXR header: {err}") from None
    return max(x1 - x0 + 1, 0), max(y1 - y0 + 1, 0)


def _pixel_kind(path: Path) -> str | None:
    """``"image"`` (PNG, JPEG), ``"npy"`` or ``"exr"`` by the file's first bytes, else by its suffix (a ``.png``
    that is no image is then refused by the header reader); None for any other file."""
    with open(path, "rb") as f:
        head = f.read(len(PNG_SIGNATURE))
    suffix = path.suffix.lower()
    if head.startswith((PNG_SIGNATURE, JPEG_MAGIC)) or suffix in IMAGE_SUFFIXES:
        return "image"
    if head.startswith(NPY_MAGIC) or suffix == ".npy":
        return "npy"
    if head.startswith(EXR_MAGIC) or suffix == ".exr":
        return "exr"
    return None


def _declared_pixels(path: Path, rel: Path, settings: Settings) -> int:
    """Width x height the header of an image or ``.npy`` declares (0 for other files); 422 past
    ``max_image_pixels`` or for a header that cannot be read."""
    kind = _pixel_kind(path)
    if kind is None:
        return 0
    try:
        width, height = {"npy": _npy_size, "exr": _exr_size}.get(kind, image_size)(path)
    except SceneError as err:
        raise UploadError(422, f"{rel}: {err.message}") from None
    if width * height > settings.max_image_pixels:
        raise UploadError(
            422,
            f"{rel}: declared image size {width}x{height} ({width * height} pixels) exceeds the "
            f"limit of {settings.max_image_pixels} pixels",
        )
    return width * height


def check_declared_sizes(root: Path, settings: Settings) -> None:
    """Every image and ``.npy`` under ``root``, known by its content whatever its name, before anything is
    decoded: its declared width x height within ``max_image_pixels``, their sum within ``max_scene_pixels``."""
    total = 0
    for path in sorted(root.rglob("*")):
        if path.is_symlink() or not path.is_file():
            continue
        total += _declared_pixels(path, path.relative_to(root), settings)
        if total > settings.max_scene_pixels:
            raise UploadError(
                413,
                f"the scene's images and depth maps declare more than {settings.max_scene_pixels} pixels in all "
                f"(VOXNERF_MAX_SCENE_PIXELS; over the limit at {path.relative_to(root)})",
            )


def _hide_staging(text: str, root: Path) -> str:
    """A message with the private staging path cut down to a path inside the scene."""
    for prefix in (str(root.resolve()), str(root)):
        text = text.replace(prefix + "/", "").replace(prefix, ".")
    return text


def _validate_staged(root: Path, settings: Settings) -> dict:
    """The engine's summary of the staged scene at ``root``; UploadError (4xx) when it is not a valid scene."""
    from voxnerf.data.scene import inspect_scene  # imports torch: preloaded by the validation processes' forkserver

    transforms = root / TRANSFORMS
    if not transforms.is_file():
        raise UploadError(
            422,
            f"{TRANSFORMS} not found at the top of the scene (or inside one top-level folder), nor a COLMAP "
            "model (sparse/0/cameras.bin|txt), a ScanNet export (color/, pose/, intrinsic/), a Record3D export "
            "(metadata.json, rgb/, depth/), a Polycam export (keyframes/), a Stray Scanner recording (rgb.mp4, "
            "odometry.csv), a ROS 2 bag folder (metadata.yaml) or photos alone (.jpg, .png) to import",
        )
    check_transforms_size(PurePosixPath(TRANSFORMS), transforms.stat().st_size, settings)
    check_declared_sizes(root, settings)
    try:
        return inspect_scene(root)
    except SceneError as err:
        raise UploadError(422, _hide_staging(str(err), root)) from None
    except MemoryError:
        raise
    except Exception as err:  # a parser deep in the engine choked on hostile bytes: still the upload's fault
        log.warning("upload refused by an unexpected %s", type(err).__name__, exc_info=True)
        detail = _hide_staging(f"the scene could not be read: {type(err).__name__}: {err}", root)
        raise UploadError(422, detail) from None
