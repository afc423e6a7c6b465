"""Reading scene images and depth maps; encoding renders as PNG and EXR; atomic file writes.

Array contracts (numpy):
- colour images: uint8 ``[H, W, 3]`` when read, float ``[H, W, 3]`` in [0, 1] when encoded;
- depth maps: float32 ``[H, W]`` in metres (scene units), NaN where a pixel has no valid depth;
- EXR channels: float32 ``[H, W]`` per channel name (``R G B`` linear colour, ``Z`` depth, ``A`` opacity).

Decoding goes through Pillow (the codec imageio uses), because only its lazy header access tells the
pixel format apart before decoding; EXR goes through the OpenEXR package (imageio's ``.exr`` writer
silently writes TIFF bytes).
"""

from __future__ import annotations

import io
import os
import shutil
import struct
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import NamedTuple, TypeVar

import imageio.v3 as iio
import numpy as np
import OpenEXR
from PIL import Image

from voxnerf.errors import SceneError

T = TypeVar("T")

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
EXR_MAGIC = b"\x76\x2f\x31\x01"  # 0x762f3101, stored little-endian as the first 4 bytes of every EXR file

_RGB_FORMATS = ("PNG", "JPEG", "MPO")  # MPO: multi-picture JPEG written by many phone cameras
_MODES_WITHOUT_ALPHA = ("1", "L", "P", "RGB")
_MODES_WITH_ALPHA = ("LA", "PA", "RGBA")
_PNG_GRAYSCALE = 0  # PNG colour type of a single-channel image
PNG_DEPTH_INVALID_MAX = 65535  # the 16-bit maximum: no measurement, like 0


class PngHeader(NamedTuple):
    """The fields of a PNG's IHDR chunk that decide how it may be read."""

    width: int
    height: int
    bit_depth: int  # bits per sample: 1, 2, 4, 8 or 16
    color_type: int  # 0 gray, 2 RGB, 3 palette, 4 gray+alpha, 6 RGBA


def read_png_header(path: Path) -> PngHeader | None:
    """The IHDR fields of a PNG file, or None when ``path`` is not a PNG. Reads 29 bytes, decodes nothing."""
    try:
        with open(path, "rb") as f:
            head = f.read(29)
    except OSError as err:
        raise SceneError(path, f"cannot read file: {err.strerror or err}") from err
    if not head.startswith(PNG_SIGNATURE):
        return None
    if len(head) < 29 or head[12:16] != b"IHDR":
        raise SceneError(path, "corrupt PNG: the IHDR chunk is missing")
    width, height, bit_depth, color_type = struct.unpack(">IIBB", head[16:26])
    return PngHeader(width, height, bit_depth, color_type)


def image_size(path: Path) -> tuple[int, int]:
    """``(width, height)`` declared in an image's header, without decoding its pixels.

    Lets a caller refuse huge declared sizes before decompressing anything. PNG headers are parsed
    directly; other formats go through Pillow's lazy open.
    """
    header = read_png_header(path)
    if header is not None:
        return header.width, header.height
    try:
        with Image.open(path) as im:
            return im.size
    except Image.DecompressionBombError as err:
        raise SceneError(path, f"declared image size is too large: {err}") from err
    except OSError as err:  # includes PIL.UnidentifiedImageError
        raise SceneError(path, f"cannot read image header: {err}") from err


def read_rgb(path: Path) -> np.ndarray:
    """An 8-bit PNG or JPEG as uint8 ``[H, W, 3]``: alpha is dropped, grayscale and palette expanded to RGB.

    Raises SceneError naming the file when it is unreadable, not PNG/JPEG, 16 bits per sample, or in a
    pixel format that is not gray/RGB (with or without alpha), e.g. CMYK.
    """
    header = read_png_header(path)
    if header is not None and header.bit_depth > 8:
        raise SceneError(path, f"{header.bit_depth}-bit PNG is not supported for colour images: use 8 bits")
    try:
        with Image.open(path) as im:
            if im.format not in _RGB_FORMATS:
                raise SceneError(path, f"unsupported image format {im.format}: expected PNG or JPEG")
            if im.mode not in _MODES_WITHOUT_ALPHA + _MODES_WITH_ALPHA:
                raise SceneError(path, f"unsupported pixel format {im.mode}: expected 8-bit gray, RGB or RGBA")
            rgb = np.array(im.convert("RGB"))
    except Image.DecompressionBombError as err:
        raise SceneError(path, f"declared image size is too large: {err}") from err
    except OSError as err:  # unreadable, truncated, or not an image (PIL.UnidentifiedImageError)
        raise SceneError(path, f"cannot decode image: {err}") from err
    if rgb.dtype != np.uint8 or rgb.ndim != 3 or rgb.shape[2] != 3:
        raise SceneError(path, f"decoded to {rgb.dtype} {rgb.shape}, expected uint8 [H, W, 3]")
    return rgb


def read_depth(path: Path, unit_scale: float) -> np.ndarray:
    """A sensor depth map as float32 ``[H, W]`` in metres; NaN marks pixels without depth.

    ``.npy``: float depth in metres, ``[H, W]`` or ``[H, W, 1]``. Anything else must be a single-channel
    16-bit PNG whose values are multiplied by ``unit_scale`` (``depth_unit_scale_factor``, e.g. 0.001
    for millimetres). Zero, the 16-bit maximum (65535) and non-finite values become NaN; a negative depth is an
    error.
    """
    path = Path(path)
    if not (np.isfinite(unit_scale) and unit_scale > 0):
        raise SceneError(path, f"must be positive, got {unit_scale!r}", key="depth_unit_scale_factor")
    depth = _read_npy_depth(path) if path.suffix.lower() == ".npy" else _read_png_depth(path, unit_scale)
    if np.any(depth < 0):  # NaN compares False, so only finite and -inf negatives count
        raise SceneError(path, f"negative depth values (min {np.nanmin(depth):.4g}): depth must be >= 0")
    with np.errstate(over="ignore"):  # values beyond float32's range become inf here, and NaN below: no warning
        depth = depth.astype(np.float32)
    depth[~np.isfinite(depth) | (depth == 0)] = np.nan
    return depth


def _read_npy_depth(path: Path) -> np.ndarray:
    try:
        depth = np.load(path, allow_pickle=False)
    except (OSError, ValueError, EOFError) as err:
        raise SceneError(path, f"cannot read .npy depth: {err}") from err
    if depth.dtype.kind != "f":
        raise SceneError(path, f"depth .npy must hold floats in metres, got dtype {depth.dtype}")
    if depth.ndim == 3 and depth.shape[2] == 1:
        depth = depth[:, :, 0]
    if depth.ndim != 2:
        raise SceneError(path, f"depth .npy must have shape [H, W], got {list(depth.shape)}")
    return depth.astype(np.float64)


def _read_png_depth(path: Path, unit_scale: float) -> np.ndarray:
    header = read_png_header(path)
    if header is None:
        raise SceneError(path, "depth must be a 16-bit PNG or a .npy of float metres")
    if header.bit_depth != 16 or header.color_type != _PNG_GRAYSCALE:
        raise SceneError(
            path,
            f"depth PNG must be 16-bit grayscale, got {header.bit_depth}-bit colour type {header.color_type}",
        )
    try:
        raw = iio.imread(path)
    except (OSError, ValueError) as err:
        raise SceneError(path, f"cannot decode depth PNG: {err}") from err
    if raw.ndim != 2:
        raise SceneError(path, f"depth PNG decoded to shape {list(raw.shape)}, expected [H, W]")
    depth = raw.astype(np.float64) * unit_scale
    depth[raw == PNG_DEPTH_INVALID_MAX] = np.nan  # sensors write their saturation value for "no return"
    return depth


def encode_png(rgb: np.ndarray) -> bytes:
    """8-bit PNG bytes of a float ``[H, W, 3]`` image in [0, 1] (clipped; NaN becomes 0)."""
    rgb = np.asarray(rgb, dtype=np.float64)
    if rgb.ndim != 3 or rgb.shape[2] != 3:
        raise ValueError(f"encode_png expects [H, W, 3], got {list(rgb.shape)}")
    u8 = np.round(np.clip(np.nan_to_num(rgb, nan=0.0), 0.0, 1.0) * 255.0).astype(np.uint8)
    return iio.imwrite("<bytes>", u8, extension=".png")


def encode_gray_png8(values: np.ndarray) -> bytes:
    """8-bit single-channel (gray) PNG bytes of a float ``[H, W]`` map in [0, 1] (clipped; NaN becomes 0)."""
    values = np.asarray(values, dtype=np.float64)
    if values.ndim != 2:
        raise ValueError(f"encode_gray_png8 expects [H, W], got {list(values.shape)}")
    u8 = np.round(np.clip(np.nan_to_num(values, nan=0.0), 0.0, 1.0) * 255.0).astype(np.uint8)
    return iio.imwrite("<bytes>", u8, extension=".png")


def encode_depth_png16(depth: np.ndarray, unit_scale: float) -> bytes:
    """16-bit PNG bytes of a float depth map ``[H, W]`` in metres.

    Stored value = round(depth / unit_scale), clipped to [0, 65535]; non-finite depth is stored as 0 and depth
    beyond the range as 65535, the two "no depth" values that :func:`read_depth` turns back into NaN.
    """
    if not (np.isfinite(unit_scale) and unit_scale > 0):
        raise ValueError(f"unit_scale must be a positive number, got {unit_scale!r}")
    depth = np.asarray(depth, dtype=np.float64)
    if depth.ndim != 2:
        raise ValueError(f"encode_depth_png16 expects [H, W], got {list(depth.shape)}")
    units = np.where(np.isfinite(depth), depth / unit_scale, 0.0)
    u16 = np.round(np.clip(units, 0.0, 65535.0)).astype(np.uint16)
    return iio.imwrite("<bytes>", u16, extension=".png")


def srgb_to_linear(values: np.ndarray) -> np.ndarray:
    """sRGB-encoded values in [0, 1] (what images and the model's colour hold) -> linear light, float32, by the
    sRGB transfer function of IEC 61966-2-1 (values outside [0, 1] are clipped first)."""
    v = np.clip(np.asarray(values, dtype=np.float32), 0.0, 1.0)
    return np.where(v <= 0.04045, v / 12.92, ((v + 0.055) / 1.055) ** 2.4).astype(np.float32)


def encode_exr(channels: dict[str, np.ndarray]) -> bytes:
    """Single-part scanline EXR bytes (ZIP compressed) with one FLOAT (32-bit) channel per name.

    Every array must be finite and ``[H, W]`` of the same shape. Raises ValueError otherwise.
    """
    if not channels:
        raise ValueError("encode_exr needs at least one channel")
    pixels: dict[str, np.ndarray] = {}
    shape = None
    for name, values in channels.items():
        # OpenEXR reads the raw buffer: a non-contiguous view would be written scrambled.
        array = np.ascontiguousarray(values, dtype=np.float32)
        if array.ndim != 2 or (shape is not None and array.shape != shape):
            raise ValueError(f"EXR channel {name!r} has shape {list(array.shape)}: need one [H, W] for all")
        if not np.all(np.isfinite(array)):
            raise ValueError(f"EXR channel {name!r} holds NaN or inf")
        shape = array.shape
        pixels[name] = array
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    buffer = io.BytesIO()
    OpenEXR.File(header, pixels).write(buffer)
    data = buffer.getvalue()
    if not data.startswith(EXR_MAGIC):
        raise RuntimeError("OpenEXR produced bytes without the EXR magic number")
    return data


def decode_exr(data: bytes) -> dict[str, np.ndarray]:
    """Channels of an EXR file's first part, each as float32 ``[H, W]``, keyed by channel name."""
    if not data.startswith(EXR_MAGIC):
        raise ValueError("not an EXR file (magic number 0x762f3101 missing)")
    try:
        exr = OpenEXR.File(io.BytesIO(data), separate_channels=True)
        return {name: np.array(ch.pixels, dtype=np.float32) for name, ch in exr.channels().items()}
    except (RuntimeError, OSError) as err:
        raise ValueError(f"cannot decode EXR: {err}") from err


def build_dir_atomic(out: Path, fill: Callable[[Path], T], check: Callable[[Path], None]) -> T:
    """Build a directory with ``fill(tmp)`` in a fresh directory beside ``out`` and rename it to ``out``.

    ``check(out)`` raises unless ``out`` may be written (e.g. absent or empty); it runs before and again just
    before the rename. When anything raises, the temporary directory is removed and ``out`` left as it was.
    Returns what ``fill`` returns.
    """
    out = Path(out)
    check(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.tmp-", dir=out.parent))
    try:
        result = fill(tmp)
        check(out)
        if out.exists():
            out.rmdir()
        os.replace(tmp, out)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return result


def write_atomic(path: Path, data: bytes) -> None:
    """Write ``data`` to ``path`` so that readers see the old file or the complete new one, never a part.

    The bytes go to a temporary file in the same directory, are flushed to disk (fsync), then moved over
    ``path`` with ``os.replace``, and the directory is fsynced so the rename itself survives a power cut.
    The temporary file is removed if anything fails.
    """
    path = Path(path)
    fd, tmp_name = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.chmod(tmp_name, 0o644)
        os.replace(tmp_name, path)
    except BaseException:
        Path(tmp_name).unlink(missing_ok=True)
        raise
    fsync_dir(path.parent)


def fsync_dir(directory: Path) -> None:
    """Flush ``directory``'s entries to disk (after a rename into it). A no-op where a directory cannot be
    opened (Windows) or fsynced (some network filesystems answer EINVAL)."""
    try:
        fd = os.open(directory, os.O_RDONLY | getattr(os, "O_DIRECTORY", 0))
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)
