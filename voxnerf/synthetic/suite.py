"""The tuning suite: named synthetic rooms, different in seed, size, field of view, lighting, textures and prior,
two of them capture-like (indirect light, soft shadows, sensor noise, exposure drift, sensor-like depth).

``SUITE`` is what defaults are chosen on (with the real redkitchen); ``QUICK_SUITE`` holds tiny rooms that
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
}
"""The full suite: 160 x 120 or 200 x 150 rooms; every room's splits are ``split_frames(**_SPLITS)``."""

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
