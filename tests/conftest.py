"""Shared fixtures: the shared data directory and small synthetic scenes (generated once per session)."""

from __future__ import annotations

from pathlib import Path

import pytest

SHARED_DATA = Path(__file__).resolve().parents[2] / "shared" / "data"


@pytest.fixture(scope="session")
def shared_data() -> Path:
    if not SHARED_DATA.is_dir():
        pytest.skip("../shared/data is absent")
    return SHARED_DATA


@pytest.fixture(scope="session")
def small_room(tmp_path_factory) -> Path:
    """A 64x48 furnished room with a noisy point-cloud prior (sigma 2 cm) and interpolation/extrapolation splits."""
    from voxnerf.synthetic import RoomSpec, make_room_scene

    out = tmp_path_factory.mktemp("scenes") / "small_room"
    make_room_scene(out, RoomSpec(width=64, height=48, n_frames=120, train_every=6, gap_len=20,
                                  prior_max_points=100_000))
    return out
