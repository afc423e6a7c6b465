"""Tests of voxnerf.data.image_io: PNG/JPEG/depth reading, PNG/EXR encoding and atomic writes."""

from __future__ import annotations

import io
import struct
import zlib
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import OpenEXR
import pytest

from voxnerf.data.image_io import (
    decode_exr,
    encode_depth_png16,
    encode_exr,
    encode_png,
    image_size,
    read_depth,
    read_rgb,
    write_atomic,
)
from voxnerf.errors import SceneError


def _png_chunk(kind: bytes, payload: bytes) -> bytes:
    return struct.pack(">I", len(payload)) + kind + payload + struct.pack(">I", zlib.crc32(kind + payload))


def _png16(samples: np.ndarray) -> bytes:
    """A 16-bit PNG written by hand (Pillow cannot write 16-bit RGB), samples uint16 [H, W, C]."""
    height, width, channels = samples.shape
    color_type = {1: 0, 3: 2, 4: 6}[channels]
    rows = b"".join(b"\x00" + samples[y].astype(">u2").tobytes() for y in range(height))
    ihdr = struct.pack(">IIBBBBB", width, height, 16, color_type, 0, 0, 0)
    chunks = _png_chunk(b"IHDR", ihdr) + _png_chunk(b"IDAT", zlib.compress(rows)) + _png_chunk(b"IEND", b"")
    return b"\x89PNG\r\n\x1a\n" + chunks


# --- PNG colour -------------------------------------------------------------------------------------


def test_encode_png_round_trip_matches_rounded_values() -> None:
    rng = np.random.default_rng(0)
    rgb = rng.uniform(-0.2, 1.2, size=(23, 31, 3))
    rgb[0, 0, 0] = np.nan
    decoded = iio.imread(encode_png(rgb))
    expected = np.round(np.clip(np.nan_to_num(rgb, nan=0.0), 0, 1) * 255).astype(np.uint8)
    assert decoded.dtype == np.uint8 and decoded.shape == (23, 31, 3)
    np.testing.assert_array_equal(decoded, expected)
    assert decoded[0, 0, 0] == 0


def test_encode_png_rejects_wrong_shape() -> None:
    with pytest.raises(ValueError, match=r"\[H, W, 3\]"):
        encode_png(np.zeros((4, 4)))


def test_read_rgb_drops_alpha_and_expands_gray(tmp_path: Path) -> None:
    rng = np.random.default_rng(1)
    rgba = rng.integers(0, 256, size=(9, 13, 4), dtype=np.uint8)
    iio.imwrite(tmp_path / "rgba.png", rgba)
    np.testing.assert_array_equal(read_rgb(tmp_path / "rgba.png"), rgba[:, :, :3])

    gray = rng.integers(0, 256, size=(9, 13), dtype=np.uint8)
    iio.imwrite(tmp_path / "gray.png", gray)
    np.testing.assert_array_equal(read_rgb(tmp_path / "gray.png"), np.repeat(gray[:, :, None], 3, axis=2))


def test_read_rgb_jpeg_matches_imageio(tmp_path: Path) -> None:
    rng = np.random.default_rng(2)
    rgb = rng.integers(0, 256, size=(16, 24, 3), dtype=np.uint8)
    iio.imwrite(tmp_path / "x.jpg", rgb, quality=90)
    out = read_rgb(tmp_path / "x.jpg")
    assert out.dtype == np.uint8 and out.shape == (16, 24, 3) and out.flags.writeable
    np.testing.assert_array_equal(out, iio.imread(tmp_path / "x.jpg"))


@pytest.mark.parametrize("channels", [1, 3, 4])
def test_read_rgb_refuses_16_bit_png_naming_the_file(tmp_path: Path, channels: int) -> None:
    path = tmp_path / f"deep{channels}.png"
    samples = np.full((4, 5, channels), 40000, dtype=np.uint16)
    path.write_bytes(_png16(samples))
    # Pillow would silently truncate the 16-bit RGB file to 8 bits: make sure the file is what we think.
    assert iio.imread(path).shape[:2] == (4, 5)
    with pytest.raises(SceneError, match="16-bit") as info:
        read_rgb(path)
    assert info.value.file == str(path)
    assert str(path) in str(info.value)


def test_read_rgb_refuses_unreadable_files(tmp_path: Path) -> None:
    garbage = tmp_path / "garbage.png"
    garbage.write_bytes(b"this is not an image")
    missing = tmp_path / "missing.png"
    truncated = tmp_path / "truncated.png"
    truncated.write_bytes(encode_png(np.random.default_rng(3).random((64, 64, 3)))[:200])
    bmp = tmp_path / "image.bmp"
    iio.imwrite(bmp, np.zeros((4, 4, 3), dtype=np.uint8))
    for path in (garbage, missing, truncated, bmp):
        with pytest.raises(SceneError) as info:
            read_rgb(path)
        assert info.value.file == str(path)


# --- depth ------------------------------------------------------------------------------------------


def test_read_depth_converts_millimetres_and_marks_zero_and_saturation_invalid(tmp_path: Path) -> None:
    raw = np.array([[0, 1000, 1234], [65535, 1, 65534]], dtype=np.uint16)
    iio.imwrite(tmp_path / "d.png", raw)
    depth = read_depth(tmp_path / "d.png", unit_scale=0.001)
    assert depth.dtype == np.float32 and depth.shape == (2, 3)
    assert np.isnan(depth[0, 0]) and np.isnan(depth[1, 0])  # 0 and the 16-bit maximum: no measurement
    np.testing.assert_allclose(depth[0, 1:], [1.0, 1.234], rtol=1e-7)
    np.testing.assert_allclose(depth[1, 1:], [0.001, 65.534], rtol=1e-7)


def test_read_depth_npy_float_metres(tmp_path: Path) -> None:
    values = np.array([[0.5, 0.0], [np.inf, np.nan]], dtype=np.float64)
    np.save(tmp_path / "d.npy", values)
    depth = read_depth(tmp_path / "d.npy", unit_scale=0.001)  # the scale only applies to PNG
    assert depth.dtype == np.float32
    assert depth[0, 0] == 0.5 and np.isnan(depth[0, 1]) and np.isnan(depth[1]).all()
    np.save(tmp_path / "d1.npy", values[:, :, None])
    assert read_depth(tmp_path / "d1.npy", 1.0).shape == (2, 2)


@pytest.mark.filterwarnings("error::RuntimeWarning")  # an expected overflow, not a warning to the user
def test_read_depth_beyond_float32_range_is_invalid_not_inf(tmp_path: Path) -> None:
    iio.imwrite(tmp_path / "d.png", np.array([[1, 0]], dtype=np.uint16))
    depth = read_depth(tmp_path / "d.png", unit_scale=1e300)
    assert np.isnan(depth).all()
    np.save(tmp_path / "d.npy", np.array([[1e300, 2.0]]))
    depth = read_depth(tmp_path / "d.npy", unit_scale=1.0)
    assert np.isnan(depth[0, 0]) and depth[0, 1] == 2.0


def test_read_depth_refuses_bad_files(tmp_path: Path) -> None:
    np.save(tmp_path / "int.npy", np.ones((3, 3), dtype=np.int32))
    np.save(tmp_path / "rgb.npy", np.ones((3, 3, 3), dtype=np.float32))
    np.save(tmp_path / "neg.npy", -np.ones((3, 3), dtype=np.float32))
    iio.imwrite(tmp_path / "d8.png", np.ones((3, 3), dtype=np.uint8))
    (tmp_path / "d.jpg").write_bytes(b"\xff\xd8\xff\xe0 not really")
    for name, message in [
        ("int.npy", "dtype int32"),
        ("rgb.npy", r"\[H, W\]"),
        ("neg.npy", "negative"),
        ("d8.png", "16-bit"),
        ("d.jpg", "16-bit PNG or a .npy"),
    ]:
        with pytest.raises(SceneError, match=message) as info:
            read_depth(tmp_path / name, 0.001)
        assert info.value.file == str(tmp_path / name)
    with pytest.raises(SceneError) as info:
        read_depth(tmp_path / "int.npy", 0.0)
    assert info.value.key == "depth_unit_scale_factor"


def test_depth_png16_round_trip_within_half_unit(tmp_path: Path) -> None:
    rng = np.random.default_rng(4)
    scale = 0.001
    depth = rng.uniform(0.01, 60.0, size=(17, 19))
    depth[0, 0] = np.nan
    depth[0, 1] = 100.0  # beyond 65535 units: stored as 65535, read back as no measurement
    depth[0, 2] = -1.0  # negative: stored as 0 (no depth)
    data = encode_depth_png16(depth, scale)
    assert data[24] == 16 and data[25] == 0  # IHDR: 16-bit grayscale
    path = tmp_path / "d.png"
    path.write_bytes(data)
    back = read_depth(path, scale)
    valid = np.ones_like(depth, dtype=bool)
    valid[0, :3] = False
    assert np.all(np.abs(back[valid] - depth[valid]) <= scale / 2 + 1e-6)
    assert np.isnan(back[0, 0]) and np.isnan(back[0, 1]) and np.isnan(back[0, 2])


# --- image_size ---------------------------------------------------------------------------------------


def test_image_size_reads_header(tmp_path: Path) -> None:
    iio.imwrite(tmp_path / "a.png", np.zeros((23, 37, 3), dtype=np.uint8))
    assert image_size(tmp_path / "a.png") == (37, 23)
    iio.imwrite(tmp_path / "a.jpg", np.zeros((23, 37, 3), dtype=np.uint8))
    assert image_size(tmp_path / "a.jpg") == (37, 23)
    # A header declaring 100000 x 80000 pixels with no pixel data: the size comes back without decoding.
    huge = tmp_path / "huge.png"
    ihdr = struct.pack(">IIBBBBB", 100000, 80000, 8, 2, 0, 0, 0)
    huge.write_bytes(b"\x89PNG\r\n\x1a\n" + _png_chunk(b"IHDR", ihdr))
    assert image_size(huge) == (100000, 80000)
    with pytest.raises(SceneError):
        image_size(tmp_path / "missing.png")


# --- EXR ----------------------------------------------------------------------------------------------


def test_exr_round_trip_is_exact_float32() -> None:
    rng = np.random.default_rng(5)
    channels = {name: rng.random((13, 21)).astype(np.float32) for name in "RGBA"}
    z = rng.uniform(0.5, 8.0, size=(13, 21)).astype(np.float32)
    z[0, 0], z[0, 1], z[0, 2] = 1e4, 1e-4, 3.0e-38
    channels["Z"] = z
    data = encode_exr(channels)
    assert data[:4] == bytes.fromhex("762f3101")
    assert int.from_bytes(data[:4], "little") == 0x01312F76
    decoded = decode_exr(data)
    assert set(decoded) == set("RGBZA")
    for name, values in channels.items():
        assert decoded[name].dtype == np.float32
        np.testing.assert_array_equal(decoded[name], values)
    # Every channel is stored with 32-bit FLOAT pixels (not HALF).
    stored = OpenEXR.File(io.BytesIO(data), separate_channels=True).channels()
    assert all(ch.type() == OpenEXR.FLOAT for ch in stored.values())


def test_exr_handles_non_contiguous_and_float64_input() -> None:
    transposed = (np.arange(6 * 8, dtype=np.float64).reshape(8, 6) / 7.0).T  # Fortran-ordered [6, 8]
    strided = np.arange(12 * 8, dtype=np.float32).reshape(12, 8)[::2]  # every other row [6, 8]
    decoded = decode_exr(encode_exr({"R": transposed, "G": strided}))
    np.testing.assert_array_equal(decoded["R"], transposed.astype(np.float32))
    np.testing.assert_array_equal(decoded["G"], strided)


def test_exr_refuses_bad_input() -> None:
    with pytest.raises(ValueError, match="NaN or inf"):
        encode_exr({"Z": np.array([[1.0, np.nan]], dtype=np.float32)})
    with pytest.raises(ValueError, match="shape"):
        encode_exr({"R": np.zeros((2, 2)), "G": np.zeros((2, 3))})
    with pytest.raises(ValueError, match="magic"):
        decode_exr(encode_png(np.zeros((2, 2, 3))))


# --- write_atomic -------------------------------------------------------------------------------------


def test_write_atomic_replaces_and_leaves_no_temp_files(tmp_path: Path) -> None:
    target = tmp_path / "render.png"
    write_atomic(target, b"first")
    assert target.read_bytes() == b"first"
    write_atomic(target, b"second version")
    assert target.read_bytes() == b"second version"
    assert [p.name for p in tmp_path.iterdir()] == ["render.png"]


def test_write_atomic_failure_keeps_old_file(tmp_path: Path) -> None:
    target = tmp_path / "render.png"
    write_atomic(target, b"good")
    with pytest.raises(TypeError):
        write_atomic(target, "not bytes")  # type: ignore[arg-type]
    assert target.read_bytes() == b"good"
    assert [p.name for p in tmp_path.iterdir()] == ["render.png"]
    with pytest.raises(FileNotFoundError):
        write_atomic(tmp_path / "no_such_dir" / "x.png", b"x")
