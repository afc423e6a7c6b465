"""The tuning suite: named synthetic rooms, different in seed, size, field of view, resolution, camera path,
lighting, textures and prior (kind and noise), four of them capture-like (indirect light, soft shadows, sensor
noise, exposure drift, sensor-like depth).

``SUITE`` is what defaults are chosen on (with the real scans; ``benchmarks/suite.py`` splits them into a tuning
and a confirmation half); ``QUICK_SUITE`` holds tiny rooms that
render in seconds, for tests. :func:`make_suite` writes rooms into ``OUT_DIR/<name>`` beside their spec
``OUT_DIR/<name>.spec.json`` and reuses a room whose stored spec equals the wanted one.

``python -m voxnerf.synthetic.suite OUT_DIR [--names a,b] [--quick]`` writes (or reuses) them and prints what
each holds and how long it took.
"""

from __future__ import annotations

import argparse
import json
import shutil
import time
from collections.abc import Mapping
from dataclasses import asdict, replace
from pathlib import Path

from voxnerf.data.image_io import write_atomic
from voxnerf.synthetic.cameras import split_frames
from voxnerf.synthetic.writer import RoomSpec, make_room_scene, written_by_this_writer

# Splits: 18 training, 15 interpolation and 10 extrapolation views (n_frames 240, every 10th, 2 gaps of 30).
_SPLITS = dict(n_frames=240, train_every=10, n_gaps=2, gap_len=30)
# One long gap: 19 training, 17 interpolation and 9 extrapolation views, the extrapolation ones further from training.
_ONE_GAP = dict(n_frames=240, train_every=10, n_gaps=1, gap_len=50)
# A shorter path seen more densely: 17 training, 14 interpolation and 14 extrapolation views.
_DENSE = dict(n_frames=200, train_every=8, n_gaps=2, gap_len=32)
# Capture-like: indirect light with soft shadows, a dimmer ambient (the bounces light the shadows), and a sensor.
_CAPTURE = dict(ambient=0.03, light_radius_m=0.1, shadow_rays=4, noise_photons=400.0, noise_read_std=0.003,
                exposure_drift_ev=0.3, white_balance_drift_ev=0.05, vignetting=0.3, sensor_depth=True)

SUITE: dict[str, RoomSpec] = {
    "studio": RoomSpec(
        **_SPLITS, seed=101, room_size=(4.6, 4.0, 2.5), hfov_deg=70.0, prior_kind="points", prior_sigma=0.02,
        ambient=0.25, light_scale=0.9, light_temperature_k=3200.0, light_jitter_m=0.3, texture_scale=0.8,
        palette_shift=0.3,
    ),
    "loft": RoomSpec(
        **_SPLITS, width=200, height=150, seed=102, room_size=(6.6, 5.4, 3.3), hfov_deg=80.0, prior_kind="mesh",
        prior_sigma=0.03, ambient=0.2, light_scale=1.5, light_temperature_k=7500.0, light_jitter_m=0.4,
        texture_scale=1.5, palette_shift=0.5,
    ),
    "den": RoomSpec(
        **_SPLITS, seed=103, room_size=(5.4, 4.3, 2.7), hfov_deg=60.0, prior_kind="points", prior_sigma=0.04,
        ambient=0.15, light_scale=1.2, light_temperature_k=4000.0, light_jitter_m=0.2, texture_scale=1.0,
        palette_shift=0.8,
    ),
    "office": RoomSpec(
        **_SPLITS, width=200, height=150, seed=104, room_size=(5.9, 4.6, 2.9), hfov_deg=90.0, prior_kind="mesh",
        prior_sigma=0.01, ambient=0.25, light_scale=0.95, light_temperature_k=5500.0, light_jitter_m=0.5,
        texture_scale=0.6, palette_shift=0.2,
    ),
    "capture_lounge": RoomSpec(
        **_SPLITS, seed=105, room_size=(5.2, 4.4, 2.7), hfov_deg=75.0, prior_kind="points", prior_sigma=0.025,
        light_scale=0.75, light_temperature_k=3000.0, light_jitter_m=0.3, texture_scale=1.2, palette_shift=0.4,
        gi_bounces=2, gi_rays=3, **_CAPTURE,
    ),
    "capture_kitchen": RoomSpec(
        **_SPLITS, width=200, height=150, seed=106, room_size=(4.8, 4.8, 2.5), hfov_deg=85.0, prior_kind="mesh",
        prior_sigma=0.015, light_scale=0.85, light_temperature_k=6000.0, light_jitter_m=0.4, texture_scale=0.7,
        palette_shift=0.6, gi_bounces=1, gi_rays=4, **_CAPTURE,
    ),
    # Issue #46: six more rooms, so that a tuning and a confirmation half each span the variety.
    "gallery": RoomSpec(
        **_ONE_GAP, width=200, height=150, seed=107, room_size=(7.0, 6.0, 3.5), hfov_deg=65.0, prior_kind="points",
        prior_sigma=0.05, ambient=0.3, light_scale=1.8, light_temperature_k=6500.0, light_jitter_m=0.2,
        texture_scale=2.0, palette_shift=0.1,
    ),
    "attic": RoomSpec(
        **_DENSE, width=176, height=132, seed=108, room_size=(4.4, 4.0, 2.4), hfov_deg=95.0, prior_kind="mesh",
        prior_sigma=0.042, ambient=0.1, light_scale=0.6, light_temperature_k=2400.0, light_jitter_m=0.1,
        texture_scale=0.5, palette_shift=0.9,
    ),
    "hall": RoomSpec(
        **_SPLITS, width=176, height=132, seed=109, room_size=(6.8, 4.2, 3.2), hfov_deg=100.0, prior_kind="mesh",
        prior_sigma=0.035, ambient=0.2, light_scale=1.3, light_temperature_k=8500.0, light_jitter_m=0.45,
        texture_scale=1.3, palette_shift=0.7,
    ),
    "library": RoomSpec(
        **_ONE_GAP, width=192, height=144, seed=110, room_size=(6.2, 5.0, 3.0), hfov_deg=55.0, prior_kind="points",
        prior_sigma=0.012, ambient=0.18, light_scale=1.1, light_temperature_k=9000.0, light_jitter_m=0.35,
        texture_scale=1.8, palette_shift=0.0,
    ),
    "capture_bedroom": RoomSpec(
        **_DENSE, width=192, height=144, seed=111, room_size=(4.5, 4.2, 2.6), hfov_deg=58.0, prior_kind="points",
        prior_sigma=0.045, light_scale=0.7, light_temperature_k=2700.0, light_jitter_m=0.25, texture_scale=0.9,
        palette_shift=0.25, gi_bounces=1, gi_rays=3,
        **(_CAPTURE | dict(noise_photons=250.0, exposure_drift_ev=0.5)),
    ),
    "capture_study": RoomSpec(
        **_SPLITS, seed=112, room_size=(5.0, 5.6, 2.8), hfov_deg=68.0, prior_kind="points", prior_sigma=0.038,
        light_scale=0.9, light_temperature_k=4500.0, light_jitter_m=0.15, texture_scale=1.1, palette_shift=0.15,
        gi_bounces=2, gi_rays=2, **(_CAPTURE | dict(vignetting=0.45, white_balance_drift_ev=0.1)),
    ),
}
"""The full suite: 160 x 120 to 200 x 150 rooms (4:3), 17-19 training views each (``_SPLITS``, ``_ONE_GAP``,
``_DENSE``); the first six rooms' specs are those of the measurements before issue #46 and stay as they are."""

_QUICK = dict(width=48, height=36, n_frames=36, train_every=4, n_gaps=1, gap_len=12, supersample=1,
              prior_max_points=5_000)
QUICK_SUITE: dict[str, RoomSpec] = {
    "quick_plain": replace(SUITE["studio"], **_QUICK),
    "quick_capture": replace(SUITE["capture_lounge"], **_QUICK, gi_bounces=1, gi_rays=2, shadow_rays=2),
}
"""Tiny rooms for tests, with the styles of ``studio`` and ``capture_lounge`` (one bounce of indirect light)."""


def spec_json(spec: RoomSpec) -> dict:
    """``spec`` as the JSON object stored in ``<name>.spec.json`` (tuples become lists)."""
    return json.loads(json.dumps(asdict(spec)))


def _stored_spec(path: Path) -> dict | None:
    """The spec stored at ``path``; None when it is missing or not a JSON object (the room is then rebuilt)."""
    try:
        stored = json.loads(path.read_text())
    except (OSError, ValueError):
        return None
    return stored if isinstance(stored, dict) else None


def make_suite(
    out_dir: Path, names: list[str] | None = None, suite: Mapping[str, RoomSpec] | None = None
) -> dict[str, Path]:
    """Write the rooms ``names`` (default: all) of ``suite`` (default: :data:`SUITE`) into ``out_dir/<name>``.

    A room is reused when ``out_dir/<name>.spec.json`` equals its spec and ``out_dir/<name>`` holds a scene of
    this writer's version (:func:`~voxnerf.synthetic.writer.written_by_this_writer`); otherwise both are removed
    and the room is rendered again (the scene appears whole, its spec file after it). Every spec is validated
    before anything is written. Returns ``{name: room directory}``.
    """
    suite = SUITE if suite is None else suite
    names = list(suite) if names is None else list(names)
    _check_names(names, suite)
    for name in names:
        try:
            suite[name].validate()
        except ValueError as err:
            raise ValueError(f"suite room {name!r}: {err}") from None
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    return {name: _make_room(out_dir, name, suite[name]) for name in names}


def _check_names(names: list[str], suite: Mapping[str, RoomSpec]) -> None:
    unknown = [n for n in names if n not in suite]
    if unknown:
        raise ValueError(f"unknown suite room(s) {unknown}; rooms: {sorted(suite)}")


def _make_room(out_dir: Path, name: str, spec: RoomSpec) -> Path:
    room, spec_path = out_dir / name, out_dir / f"{name}.spec.json"
    wanted = spec_json(spec)
    if _stored_spec(spec_path) == wanted and written_by_this_writer(room):
        return room
    spec_path.unlink(missing_ok=True)
    if room.is_dir() and not room.is_symlink():
        shutil.rmtree(room)
    elif room.exists() or room.is_symlink():
        room.unlink()
    make_room_scene(room, spec)
    write_atomic(spec_path, (json.dumps(wanted, indent=2, sort_keys=True) + "\n").encode())
    return room


def split_sizes(spec: RoomSpec) -> dict[str, int]:
    """Frames per split of ``spec``'s room: ``{"train", "interpolation", "extrapolation"}``."""
    splits = split_frames(spec.n_frames, spec.train_every, spec.n_gaps, spec.gap_len)
    return {k: len(v) for k, v in asdict(splits).items()}


def main(argv: list[str] | None = None) -> int:
    """``python -m voxnerf.synthetic.suite OUT_DIR [--names a,b] [--quick]``: write the rooms, print a summary."""
    parser = argparse.ArgumentParser(prog="python -m voxnerf.synthetic.suite", description=__doc__.split("\n\n")[0])
    parser.add_argument("out_dir", type=Path)
    parser.add_argument("--names", help="comma-separated room names (default: every room)")
    parser.add_argument("--quick", action="store_true", help="the tiny QUICK_SUITE rooms instead")
    args = parser.parse_args(argv)
    suite = QUICK_SUITE if args.quick else SUITE
    names = [n.strip() for n in args.names.split(",") if n.strip()] if args.names else list(suite)
    try:
        _check_names(names, suite)
        for name in names:
            start = time.perf_counter()
            room = make_suite(args.out_dir, [name], suite)[name]
            spec = suite[name]
            print(json.dumps({
                "room": name, "path": str(room), "seconds": round(time.perf_counter() - start, 1),
                "size": f"{spec.width}x{spec.height}", "splits": split_sizes(spec),
            }), flush=True)
    except ValueError as err:
        parser.exit(2, f"error: {err}\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
