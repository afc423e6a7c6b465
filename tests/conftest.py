"""Shared fixtures: the shared data directory, small synthetic scenes (generated once per session) and one run
trained on the small room that several test files read."""

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


@pytest.fixture(scope="session")
def trained_small_room(small_room, tmp_path_factory) -> Path:
    """``small_room`` trained as ``voxnerf train`` would (compiled step, C kernel where available) for 500 steps
    of 1024 rays on the CPU, progress evaluations every 20 s and a final evaluation. Read by the end-to-end
    checks (tests/test_end_to_end.py) and the geometry export's (tests/inference/test_export.py); tests write
    nothing into it."""
    from voxnerf.config import TrainConfig
    from voxnerf.training.run import train

    run = tmp_path_factory.mktemp("runs") / "small_room"
    config = TrainConfig(max_iters=500, rays_per_batch=1024, device="cpu", eval_every_s=20.0)
    train(small_room, run, config, progress_bar=False)
    return run
