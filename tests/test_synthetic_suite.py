"""voxnerf.synthetic's variety and capture-like rendering (RoomSpec's style fields, room.RoomStyle,
raycast.Shading, sensor) and the tuning suite (voxnerf.synthetic.suite): each field's validation, each effect on
a tiny render, determinism, the default room unchanged byte for byte, and make_suite's reuse and rebuild."""

from __future__ import annotations

import hashlib
import itertools
import json
import math
from dataclasses import asdict, replace
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import open3d as o3d
import pytest

from voxnerf.image_io import srgb_to_linear
from voxnerf.synthetic import RoomSpec, build_room, camera_path, make_room_scene
from voxnerf.synthetic.raycast import Shading, light_visibility, render_radiance
from voxnerf.synthetic.room import ROOM_SIZE_RANGE, RoomStyle, temperature_rgb
from voxnerf.synthetic.sensor import (
    DEPTH_MAX_M,
    CameraResponse,
    capture_linear,
    drift_walk,
    sensor_depth,
    vignette_gain,
)
from voxnerf.synthetic.suite import QUICK_SUITE, SUITE, main, make_suite, spec_json, split_sizes
from voxnerf.synthetic.textures import PATTERNS, Material
from voxnerf.synthetic.writer import WRITER_VERSION

# 24 x 18 pixels, 7 training, 5 interpolation and 3 extrapolation frames, no prior: renders in a fraction of a second.
TINY = RoomSpec(width=24, height=18, n_frames=36, train_every=4, n_gaps=1, gap_len=12, prior_kind="none")
# The default room's files as the generator wrote them before the style and capture fields existed.
DEFAULT_HASHES = {
    "b64f1c2d457357031d3b4018459d7bfc5ee4f09c67794cf9dbbe7fcf6bbe9600": RoomSpec(
        width=24, height=18, n_frames=40, train_every=4, n_gaps=0, gap_len=0, prior_max_points=3000),
    "a055918e6c33220329a0ed1cdca675d2632bb7aed020f3f08f725103a5b6a0e6": RoomSpec(
        width=20, height=16, n_frames=24, train_every=4, n_gaps=1, gap_len=12, prior_kind="mesh", seed=3,
        hfov_deg=80.0),
}


def _without_version_2_keys(text: str) -> bytes:
    """transforms.json as the writer wrote it before version 2 added ``synthetic`` and ``voxnerf_synthetic.writer``."""
    meta = json.loads(text)
    assert meta.pop("synthetic") is True and meta["voxnerf_synthetic"].pop("writer") == WRITER_VERSION
    return (json.dumps(meta, indent=2) + "\n").encode()


def _tree_hash(root: Path) -> str:
    """Every file's path and bytes; transforms.json as the writer before version 2 wrote it."""
    digest = hashlib.sha256()
    for path in sorted(root.rglob("*")):
        if path.is_file():
            digest.update(str(path.relative_to(root)).encode())
            is_meta = path.name == "transforms.json"
            digest.update(_without_version_2_keys(path.read_text()) if is_meta else path.read_bytes())
    return digest.hexdigest()


def _linear_images(scene: Path) -> dict[str, np.ndarray]:
    """Every image of ``scene`` as linear RGB float64 [h, w, 3], by file name."""
    return {p.name: srgb_to_linear(iio.imread(p) / 255.0) for p in sorted((scene / "images").glob("*.png"))}


def _meta(scene: Path) -> dict:
    return json.loads((scene / "transforms.json").read_text())


# --- validation -------------------------------------------------------------------------------------------------

BAD_VALUES = [
    ("room_size", (4.0, 4.0, 2.6)), ("room_size", (5.0, 4.0)), ("room_size", "big"), ("room_size", (5.0, 7.0, 2.6)),
    ("ambient", -0.1), ("ambient", math.nan), ("light_scale", 0.0), ("light_scale", True),
    ("light_temperature_k", 1000.0), ("light_temperature_k", "warm"), ("light_jitter_m", 0.6),
    ("texture_scale", 0.1), ("palette_shift", 1.5), ("light_radius_m", 0.2), ("shadow_rays", 0),
    ("shadow_rays", 1.5), ("gi_bounces", 3), ("gi_bounces", -1), ("gi_rays", 0), ("noise_photons", -1.0),
    ("noise_photons", math.inf), ("noise_read_std", 0.5), ("exposure_drift_ev", 3.0),
    ("white_balance_drift_ev", -0.1), ("vignetting", 1.5), ("sensor_depth", "yes"),
]


@pytest.mark.parametrize(("name", "value"), BAD_VALUES)
def test_each_style_field_is_validated_by_name(name: str, value):
    with pytest.raises(ValueError, match=rf"RoomSpec\.{name} "):
        replace(TINY, **{name: value}).validate()


def test_make_room_scene_refuses_a_bad_style_before_writing(tmp_path: Path):
    with pytest.raises(ValueError, match=r"RoomSpec\.gi_rays"):
        make_room_scene(tmp_path / "room", replace(TINY, gi_rays=0))
    assert not (tmp_path / "room").exists()


# --- defaults and determinism -----------------------------------------------------------------------------------


@pytest.mark.parametrize("expected", sorted(DEFAULT_HASHES))
def test_default_rooms_are_byte_identical_to_before(tmp_path: Path, expected: str):
    assert _tree_hash(make_room_scene(tmp_path / "room", DEFAULT_HASHES[expected])) == expected


def test_capture_room_is_deterministic_and_seeded(tmp_path: Path):
    spec = QUICK_SUITE["quick_capture"]
    first, second = make_room_scene(tmp_path / "a", spec), make_room_scene(tmp_path / "b", spec)
    assert _tree_hash(first) == _tree_hash(second)
    other = make_room_scene(tmp_path / "c", replace(spec, seed=spec.seed + 1))
    assert _tree_hash(other) != _tree_hash(first)
    record = _meta(first)["voxnerf_synthetic"]
    assert record["spec"]["gi_bounces"] == spec.gi_bounces and record["room_size"] == list(spec.room_size)
    assert "gi_bounces" not in _meta(make_room_scene(tmp_path / "d", TINY))["voxnerf_synthetic"]["spec"]


# --- variety: size, lights, textures ----------------------------------------------------------------------------


@pytest.mark.parametrize("size", list(itertools.product(*ROOM_SIZE_RANGE)))
def test_resized_rooms_hold_their_furniture_and_a_clear_camera_path(size):
    W, D, H = size
    lo, hi = np.array([-W / 2, -D / 2, 0.0]) - 1e-9, np.array([W / 2, D / 2, H]) + 1e-9
    positions = camera_path(60, size)[:, :3, 3]
    for seed in (0, 7):
        geom = build_room(seed, RoomStyle(room_size=size))
        assert geom.room_size == size
        assert (geom.vertices >= lo).all() and (geom.vertices <= hi).all()
        assert (positions > lo + 0.5).all() and (positions < hi - 0.5).all()
        distance = geom.raycasting_scene.compute_distance(o3d.core.Tensor(positions.astype(np.float32))).numpy()
        assert distance.min() > 0.35
    shelf = build_room(0, RoomStyle(room_size=size)).object_named("shelf_back")
    assert shelf.bounds[0][0] == pytest.approx(-W / 2), "the shelf stays on the west wall"


def test_default_style_is_the_default_room():
    plain, styled = build_room(3), build_room(3, RoomStyle())
    np.testing.assert_array_equal(plain.vertices, styled.vertices)
    assert plain.objects == styled.objects and plain.lights == styled.lights


def test_light_style_scales_tints_and_jitters_lights():
    base = build_room(2)
    styled = build_room(2, RoomStyle(light_scale=2.0, light_temperature_k=2500.0, light_jitter_m=0.4))
    W, D, H = base.room_size
    for before, after in zip(base.lights, styled.lights, strict=True):
        tint = np.asarray(after.intensity) / (2.0 * np.asarray(before.intensity))
        np.testing.assert_allclose(tint, temperature_rgb(2500.0))
        assert tint[0] > tint[2], "a warm light is redder than it is blue"
        moved = np.asarray(after.position) - np.asarray(before.position)
        assert 0 < np.abs(moved).max() <= 0.4 + 1e-12 and moved[2] <= 0
        assert abs(after.position[0]) <= W / 2 - 0.3 and abs(after.position[1]) <= D / 2 - 0.3
    assert base.objects == styled.objects
    np.testing.assert_allclose(temperature_rgb(6500.0), (1.0, 1.0, 1.0))


def test_texture_style_scales_patterns_and_shifts_palettes_per_material():
    base = build_room(4)
    styled = build_room(4, RoomStyle(texture_scale=2.0, palette_shift=0.6))
    pairs = list(zip(base.objects, styled.objects, strict=True))
    for before, after in pairs:
        assert after.material.scale == pytest.approx(2.0 * before.material.scale) and after.bounds == before.bounds
    changed = [a.material.base != b.material.base for b, a in pairs if b.material.pattern != "sky"]
    assert sum(changed) > 0.8 * len(changed)
    assert styled.object_named("window_view").material.base == base.object_named("window_view").material.base
    legs = {styled.object_named(f"table_leg_{k}").material for k in range(4)} | {
        styled.object_named("table_top").material}
    assert len(legs) == 1, "parts sharing a material keep sharing it"


def test_plaster_gradient_spans_the_rooms_own_height():
    material = Material("plaster", (0.9, 0.1, 0.1), (0.1, 0.1, 0.9), 0.5)
    ceiling, up = np.array([[0.3, 0.2, 2.6]]), np.array([[0.0, 0.0, 1.0]])
    low = PATTERNS["plaster"](ceiling, up, material, 1)
    tall = PATTERNS["plaster"](ceiling, up, material, 1, room_height=5.2)
    assert low[0, 2] > 5 * low[0, 0], "the default room's ceiling is the accent colour"
    np.testing.assert_allclose(tall[0, 0], tall[0, 2], rtol=1e-9, err_msg="half-way up a 5.2 m room: an even mix")


# --- capture-like rendering -------------------------------------------------------------------------------------


def _view(shading: Shading, index: int = 24, rng_seed: int = 0):
    geom = build_room(0)
    fl = 24 / math.tan(math.radians(65) / 2)
    return render_radiance(geom, camera_path(36)[index], fl, 24, 18, 48, 36, 1, None, shading,
                           np.random.default_rng(rng_seed))


def test_indirect_light_brightens_shadowed_points():
    direct = _view(Shading(ambient=0.0)).radiance.sum(axis=-1)
    indirect = _view(Shading(ambient=0.0, gi_bounces=1, gi_rays=8)).radiance.sum(axis=-1)
    shadowed = direct == 0
    assert shadowed.sum() >= 5
    assert (indirect[shadowed] > 0).mean() > 0.9 and indirect[shadowed].mean() > 0.02
    assert indirect.mean() > direct.mean()


def test_shading_with_random_rays_needs_a_generator():
    with pytest.raises(ValueError, match="rng"):
        render_radiance(build_room(0), camera_path(8)[0], 20.0, 8, 6, 16, 12, 1, None, Shading(gi_bounces=1))


def test_area_lights_cast_penumbras():
    geom = build_room(0)
    x, y = np.meshgrid(np.linspace(-2.4, 2.4, 60), np.linspace(-1.9, 1.9, 48))
    floor = np.stack([x.ravel(), y.ravel(), np.full(x.size, 0.013)], axis=1)
    lit = np.ones(len(floor), bool)
    light = geom.lights[0].position
    hard = light_visibility(geom, floor, lit, light, Shading(), None)
    soft = light_visibility(geom, floor, lit, light, Shading(light_radius_m=0.12, shadow_rays=16),
                            np.random.default_rng(0))
    assert set(np.unique(hard)) == {0.0, 1.0}
    penumbra = (soft > 0) & (soft < 1)
    assert penumbra.sum() >= 20 and abs(soft.mean() - hard.mean()) < 0.05


def test_shot_and_read_noise_have_the_expected_spread():
    clean = _view(Shading()).radiance
    response = CameraResponse(noise_photons=400.0, noise_read_std=0.01)
    noisy = capture_linear(clean, np.ones(3), None, response, np.random.default_rng(1))
    expected = np.sqrt(clean / 400.0 + 0.01**2)
    ratio = np.std((noisy - clean) / expected)
    assert 0.9 < ratio < 1.1
    np.testing.assert_array_equal(capture_linear(clean, np.ones(3), None, CameraResponse(), None), clean)


def test_noisy_scene_differs_from_the_clean_one_by_the_noise(tmp_path: Path):
    clean = _linear_images(make_room_scene(tmp_path / "clean", TINY))
    noisy = _linear_images(make_room_scene(tmp_path / "noisy", replace(TINY, noise_photons=300.0)))
    for name, image in clean.items():
        keep = image < 0.8
        spread = np.std((noisy[name] - image)[keep] / np.sqrt(np.maximum(image[keep], 0.02) / 300.0))
        assert 0.7 < spread < 1.4, name


def test_exposure_and_white_balance_drift_follow_the_recorded_gains(tmp_path: Path):
    clean = _linear_images(make_room_scene(tmp_path / "clean", TINY))
    scene = make_room_scene(tmp_path / "drift", replace(TINY, exposure_drift_ev=0.5, white_balance_drift_ev=0.2))
    drifted, capture = _linear_images(scene), _meta(scene)["voxnerf_synthetic"]["capture_ev"]
    exposure, red = np.array(capture["exposure"]), np.array(capture["red"])
    assert np.abs(exposure).max() <= 0.5 + 1e-6 and exposure.std() > 0.1 and np.abs(red).max() > 0
    for k, name in enumerate(clean):
        gain = 2.0 ** exposure[k]
        keep = clean[name][..., 1] * gain < 0.8
        measured = drifted[name][..., 1][keep].sum() / clean[name][..., 1][keep].sum()
        assert math.log2(measured) == pytest.approx(exposure[k], abs=0.03), name
        keep_red = clean[name][..., 0] * 2.0 ** (exposure[k] + red[k]) < 0.8
        measured_red = drifted[name][..., 0][keep_red].sum() / clean[name][..., 0][keep_red].sum()
        assert math.log2(measured_red) == pytest.approx(exposure[k] + red[k], abs=0.05), name


def test_drift_walk_is_smooth_zero_mean_and_bounded():
    walk = drift_walk(200, 0.3, np.random.default_rng(0))
    assert np.abs(walk).max() == pytest.approx(0.3) and abs(walk.mean()) < 1e-9
    assert np.abs(np.diff(walk)).max() < 0.05, "consecutive frames change little"
    assert not np.any(drift_walk(50, 0.0, np.random.default_rng(0)))


def test_vignetting_darkens_toward_the_corners():
    gain = vignette_gain(40, 30, 30.0, 20.0, 15.0, 0.5)
    assert gain[15, 20] == pytest.approx(1.0, abs=1e-3)
    corner_cos2 = 30.0**2 / (30.0**2 + 19.5**2 + 14.5**2)
    assert gain[0, 0] == pytest.approx(1 - 0.5 * (1 - corner_cos2**2))
    assert gain[15, 20] > gain[15, 30] > gain[15, 39] and (gain > 0).all()


def test_sensor_depth_noise_grows_with_depth_and_holes_are_zero():
    errors = {}
    for z in (1.0, 3.0):
        depth = np.full((60, 80), z)
        measured = sensor_depth(depth, np.ones_like(depth), np.random.default_rng(2))
        valid = measured > 0
        assert 0.8 < valid.mean() < 1.0, "a few holes, the rest measured"
        errors[z] = np.std(measured[valid] - z)
    assert errors[1.0] < 0.004 and errors[3.0] > 5 * errors[1.0]
    depth = np.full((10, 10), 2.0)
    grazing = np.full_like(depth, 0.1)
    assert not sensor_depth(depth, grazing, np.random.default_rng(0)).any()
    assert not sensor_depth(np.full_like(depth, DEPTH_MAX_M + 0.5), np.ones_like(depth), np.random.default_rng(0)).any()


def test_sensor_depth_scene_keeps_the_true_mesh(tmp_path: Path):
    true = make_room_scene(tmp_path / "true", TINY)
    scene = make_room_scene(tmp_path / "sensor", replace(TINY, sensor_depth=True))
    assert (true / "gt_mesh.ply").read_bytes() == (scene / "gt_mesh.ply").read_bytes()
    for path in sorted((true / "depth").glob("*.png")):
        exact, measured = iio.imread(path).astype(float), iio.imread(scene / "depth" / path.name).astype(float)
        valid = measured > 0
        assert valid.mean() < 1.0 and valid.mean() > 0.5
        assert np.median(np.abs(measured - exact)[valid]) < 30, "millimetres"
        assert not np.array_equal(measured, exact)


# --- the suite --------------------------------------------------------------------------------------------------


def test_suite_rooms_differ_and_two_look_like_captures():
    assert len(SUITE) >= 6
    for field in ("seed", "room_size", "hfov_deg", "light_temperature_k", "texture_scale", "palette_shift",
                  "prior_sigma"):
        values = [getattr(spec, field) for spec in SUITE.values()]
        assert len(set(values)) == len(values), field
    assert {spec.prior_kind for spec in SUITE.values()} == {"points", "mesh"}
    capture_like = [name for name, s in SUITE.items() if s.gi_bounces > 0 and s.light_radius_m > 0
                    and s.noise_photons > 0 and s.exposure_drift_ev > 0 and s.sensor_depth]
    assert len(capture_like) >= 2
    for name, spec in SUITE.items():
        spec.validate()
        assert (spec.width, spec.height) in {(160, 120), (200, 150)}, name
        assert 0.01 <= spec.prior_sigma <= 0.04, name
        sizes = split_sizes(spec)
        assert 16 <= sizes["train"] <= 24 and sizes["interpolation"] > 0 and sizes["extrapolation"] > 0, name


@pytest.fixture(scope="module")
def quick_suite(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("suite")
    make_suite(out, suite=QUICK_SUITE)
    return out


def test_quick_suite_renders_with_both_held_out_splits(quick_suite: Path):
    for name in QUICK_SUITE:
        meta = _meta(quick_suite / name)
        assert set(meta["eval_splits"]) == {"interpolation", "extrapolation"} and meta["train_filenames"]
        assert json.loads((quick_suite / f"{name}.spec.json").read_text()) == spec_json(QUICK_SUITE[name])


def test_make_suite_reuses_a_room_whose_spec_is_unchanged(quick_suite: Path):
    stamp = (quick_suite / "quick_plain" / "transforms.json").stat().st_mtime_ns
    rooms = make_suite(quick_suite, ["quick_plain"], QUICK_SUITE)
    assert rooms == {"quick_plain": quick_suite / "quick_plain"}
    assert (quick_suite / "quick_plain" / "transforms.json").stat().st_mtime_ns == stamp


def test_make_suite_rebuilds_a_room_whose_spec_changed(tmp_path: Path):
    spec = QUICK_SUITE["quick_plain"]
    make_suite(tmp_path, suite={"room": spec})
    make_suite(tmp_path, suite={"room": replace(spec, seed=spec.seed + 1)})
    assert _meta(tmp_path / "room")["voxnerf_synthetic"]["seed"] == spec.seed + 1
    assert json.loads((tmp_path / "room.spec.json").read_text())["seed"] == spec.seed + 1
    (tmp_path / "room.spec.json").write_text("{not json")
    make_suite(tmp_path, suite={"room": spec})
    assert _meta(tmp_path / "room")["voxnerf_synthetic"]["seed"] == spec.seed


def test_make_suite_rebuilds_a_room_an_older_writer_wrote(tmp_path: Path):
    spec = QUICK_SUITE["quick_plain"]
    make_suite(tmp_path, suite={"room": spec})
    assert _meta(tmp_path / "room")["voxnerf_synthetic"]["writer"] == WRITER_VERSION
    old = _meta(tmp_path / "room")
    del old["synthetic"], old["voxnerf_synthetic"]["writer"]  # what the writer before version 2 wrote
    (tmp_path / "room" / "transforms.json").write_text(json.dumps(old))
    make_suite(tmp_path, suite={"room": spec})
    assert _meta(tmp_path / "room")["synthetic"] is True
    (tmp_path / "room" / "transforms.json").write_text("[]")
    make_suite(tmp_path, suite={"room": spec})
    assert _meta(tmp_path / "room")["voxnerf_synthetic"]["writer"] == WRITER_VERSION


def test_make_suite_refuses_unknown_rooms_and_bad_specs_before_writing(tmp_path: Path):
    with pytest.raises(ValueError, match="unknown suite room"):
        make_suite(tmp_path / "a", ["nowhere"])
    bad = {"good": QUICK_SUITE["quick_plain"], "bad": replace(QUICK_SUITE["quick_plain"], vignetting=2.0)}
    with pytest.raises(ValueError, match=r"suite room 'bad': RoomSpec\.vignetting"):
        make_suite(tmp_path / "b", suite=bad)
    assert not (tmp_path / "a").exists() and not (tmp_path / "b").exists()


def test_cli_writes_named_quick_rooms_and_refuses_unknown_names(tmp_path: Path, capsys):
    assert main([str(tmp_path), "--quick", "--names", "quick_plain"]) == 0
    line = json.loads(capsys.readouterr().out.strip())
    assert line["room"] == "quick_plain" and line["splits"] == split_sizes(QUICK_SUITE["quick_plain"])
    assert sorted(p.name for p in tmp_path.iterdir()) == ["quick_plain", "quick_plain.spec.json"]
    with pytest.raises(SystemExit) as exit_info:
        main([str(tmp_path), "--quick", "--names", "quick_plain,nowhere"])
    assert exit_info.value.code == 2 and "unknown suite room" in capsys.readouterr().err


def test_spec_json_round_trips_the_spec():
    spec = SUITE["capture_kitchen"]
    stored = spec_json(spec)
    assert RoomSpec(**{**stored, "room_size": tuple(stored["room_size"])}) == spec
    assert stored == json.loads(json.dumps(asdict(spec)))
