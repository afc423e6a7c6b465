"""voxnerf.inference.encoding: every format and output encoded, then decoded back and compared."""

from __future__ import annotations

import imageio.v3 as iio
import numpy as np
import pytest

from voxnerf.data.image_io import decode_exr, read_png_header, srgb_to_linear
from voxnerf.inference.encoding import (
    FORMATS,
    MEDIA_TYPES,
    OUTPUT_NAMES,
    encode_files,
    encode_outputs,
    format_of,
    output_path,
    write_files,
)

H, W = 6, 10
SCALE = 0.001  # metres per stored depth unit


@pytest.fixture
def images() -> dict[str, np.ndarray]:
    rng = np.random.default_rng(0)
    return {
        "rgb": rng.uniform(0, 1, (H, W, 3)).astype(np.float32),
        "depth": rng.uniform(0.5, 6.0, (H, W)).astype(np.float32),
        "opacity": rng.uniform(0, 1, (H, W)).astype(np.float32),
    }


def test_names_and_media_types():
    assert OUTPUT_NAMES == ("rgb", "depth", "opacity")
    assert MEDIA_TYPES == {"png": "image/png", "exr": "image/x-exr"} and FORMATS == ("png", "exr")


def test_rgb_png_is_8bit_colour(images):
    data = encode_outputs(images, "png", ["rgb"], SCALE)
    decoded = iio.imread(data)
    assert decoded.dtype == np.uint8 and decoded.shape == (H, W, 3)
    np.testing.assert_array_equal(decoded, np.round(images["rgb"] * 255).astype(np.uint8))


def test_depth_png_is_16bit_gray_in_depth_units(images):
    data = encode_outputs(images, "png", ["depth"], SCALE)
    decoded = iio.imread(data)
    assert decoded.dtype == np.uint16 and decoded.shape == (H, W)
    np.testing.assert_array_equal(decoded, np.round(images["depth"].astype(np.float64) / SCALE).astype(np.uint16))
    coarse = iio.imread(encode_outputs(images, "png", ["depth"], 0.01))
    np.testing.assert_allclose(coarse * 0.01, images["depth"], atol=0.005 + 1e-6)


def test_opacity_png_is_8bit_single_channel_gray(images):
    data = encode_outputs(images, "png", ["opacity"], SCALE)
    decoded = iio.imread(data)
    assert decoded.dtype == np.uint8 and decoded.shape == (H, W)
    np.testing.assert_array_equal(decoded, np.round(images["opacity"] * 255).astype(np.uint8))
    assert (data[24], data[25]) == (8, 0)  # IHDR bit depth 8, colour type 0 (gray)


def test_png_values_are_clipped_and_nan_is_zero():
    images = {
        "rgb": np.array([[[-1.0, 2.0, np.nan]]], dtype=np.float32),
        "opacity": np.array([[np.nan, 1.5]], dtype=np.float32),
        "depth": np.array([[np.nan, 1e9]], dtype=np.float32),
    }
    assert iio.imread(encode_outputs(images, "png", ["rgb"], SCALE)).tolist() == [[[0, 255, 0]]]
    assert iio.imread(encode_outputs(images, "png", ["opacity"], SCALE)).tolist() == [[0, 255]]
    assert iio.imread(encode_outputs(images, "png", ["depth"], SCALE)).tolist() == [[0, 65535]]


@pytest.mark.parametrize(
    ("outputs", "channels"),
    [
        (["rgb", "depth", "opacity"], ["A", "B", "G", "R", "Z"]),
        (["rgb"], ["B", "G", "R"]),
        (["depth"], ["Z"]),
        (["opacity"], ["A"]),
        (["depth", "opacity"], ["A", "Z"]),
    ],
)
def test_exr_holds_float32_channels(images, outputs, channels):
    decoded = decode_exr(encode_outputs(images, "exr", outputs, SCALE))
    assert sorted(decoded) == channels
    for name, array in decoded.items():
        assert array.dtype == np.float32 and array.shape == (H, W), name
    linear = srgb_to_linear(images["rgb"])
    expected = {"R": linear[..., 0], "G": linear[..., 1], "B": linear[..., 2],
                "Z": images["depth"], "A": images["opacity"]}
    for name in channels:
        np.testing.assert_array_equal(decoded[name], expected[name])


def test_exr_colour_is_linear_light_decoded_from_the_srgb_the_model_renders():
    rgb = np.array([[[0.0, 0.04045, 0.5]], [[1.0, 0.2, 0.8]]], dtype=np.float32)  # [2, 1, 3]
    decoded = decode_exr(encode_outputs({"rgb": rgb}, "exr", ["rgb"], SCALE))
    assert decoded["R"][0, 0] == 0.0 and decoded["R"][1, 0] == pytest.approx(1.0)
    assert decoded["G"][0, 0] == pytest.approx(0.04045 / 12.92)  # the linear toe
    assert decoded["B"][0, 0] == pytest.approx(0.21404, abs=1e-5)  # sRGB 0.5 is about 21% of the light
    assert decoded["G"][1, 0] < 0.2 and decoded["B"][1, 0] < 0.8  # decoding darkens every mid-tone


def test_exr_depth_is_in_scene_units_whatever_the_depth_unit(images):
    a = decode_exr(encode_outputs(images, "exr", ["depth"], 0.001))
    b = decode_exr(encode_outputs(images, "exr", ["depth"], 1.0))
    np.testing.assert_array_equal(a["Z"], b["Z"])


@pytest.mark.parametrize(
    ("fmt", "outputs", "needle"),
    [
        ("jpg", ["rgb"], "unknown format"),
        ("png", ["rgb", "depth"], "one output"),
        ("png", [], "at least one"),
        ("exr", [], "at least one"),
        ("exr", ["normals"], "at least one"),
    ],
)
def test_bad_requests_raise_value_error(images, fmt, outputs, needle):
    with pytest.raises(ValueError, match=needle):
        encode_outputs(images, fmt, outputs, SCALE)


def test_missing_image_is_a_value_error(images):
    del images["depth"]
    with pytest.raises(ValueError, match="depth"):
        encode_outputs(images, "exr", ["rgb", "depth"], SCALE)


def test_nan_depth_cannot_go_to_exr(images):
    images["depth"][0, 0] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        encode_outputs(images, "exr", ["depth"], SCALE)


# ------------------------------------------------------------------------------------------------ CLI files


def test_format_and_paths(tmp_path):
    assert format_of(tmp_path / "a.PNG") == "png" and format_of("x/b.exr") == "exr"
    for bad in ("a.jpg", "a", "a.png.tmp"):
        with pytest.raises(ValueError, match=r"\.png or \.exr"):
            format_of(bad)
    out = tmp_path / "view.png"
    assert output_path(out, "rgb") == out
    assert output_path(out, "depth") == tmp_path / "view_depth.png"
    assert output_path(out, "opacity") == tmp_path / "view_opacity.png"


def test_png_render_is_one_file_per_output(tmp_path, images):
    out = tmp_path / "view.png"
    files = encode_files(out, images, ["rgb", "depth", "opacity"], SCALE)
    assert list(files) == [out, tmp_path / "view_depth.png", tmp_path / "view_opacity.png"]
    assert write_files(files) == list(files)
    assert iio.imread(out).shape == (H, W, 3)
    assert read_png_header(tmp_path / "view_depth.png")[2:] == (16, 0)
    assert read_png_header(tmp_path / "view_opacity.png")[2:] == (8, 0)
    for name in ("rgb", "depth", "opacity"):
        assert files[output_path(out, name)] == encode_outputs(images, "png", [name], SCALE)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["view.png", "view_depth.png", "view_opacity.png"]


def test_exr_render_is_one_file(tmp_path, images):
    out = tmp_path / "view.exr"
    files = encode_files(out, images, ["rgb", "opacity"], SCALE)
    assert list(files) == [out]
    write_files(files)
    assert sorted(decode_exr(out.read_bytes())) == ["A", "B", "G", "R"]


def test_encoding_failure_writes_nothing(tmp_path, images):
    images["depth"][0, 0] = np.inf
    with pytest.raises(ValueError):
        encode_files(tmp_path / "view.exr", images, ["rgb", "depth"], SCALE)
    assert list(tmp_path.iterdir()) == []
