"""Shared fixtures: the shared data directory, small synthetic scenes (generated once per session) and one run
trained on the small room that several test files read."""

from __future__ import annotations

import fcntl
import json
import os
import shutil
import sys
from collections.abc import Callable
from pathlib import Path

import pytest

SHARED_DATA = Path(__file__).resolve().parents[2] / "shared" / "data"


def built_once(tmp_path_factory: pytest.TempPathFactory, name: str, build: Callable[[Path], None]) -> Path:
    """``root/name``, made by ``build(path)`` once per test session even when pytest-xdist runs the session in
    several processes: they share the parent of their temporary folders and take turns under a file lock; the
    first to get it builds, the others read what it built. A build that raised is built again by the next."""
    root = tmp_path_factory.getbasetemp()
    if os.environ.get("PYTEST_XDIST_WORKER"):
        root = root.parent  # pytest-of-<user>/pytest-N, shared by the session's processes
    path, done = root / name, root / f"{name}.built"
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(root / f"{name}.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        if not done.is_file():
            shutil.rmtree(path, ignore_errors=True)
            build(path)
            done.touch()
    return path


@pytest.fixture(scope="session")
def shared_data() -> Path:
    if not SHARED_DATA.is_dir():
        pytest.skip("../shared/data is absent")
    return SHARED_DATA


@pytest.fixture(scope="session")
def small_room(tmp_path_factory) -> Path:
    """A 64x48 furnished room with a noisy point-cloud prior (sigma 2 cm) and interpolation/extrapolation splits."""
    from voxnerf.synthetic import RoomSpec, make_room_scene

    def build(out: Path) -> None:
        make_room_scene(out, RoomSpec(width=64, height=48, n_frames=120, train_every=6, gap_len=20,
                                      prior_max_points=100_000))

    return built_once(tmp_path_factory, "scenes/small_room", build)


@pytest.fixture(scope="session")
def captured_small_room(small_room, tmp_path_factory) -> Path:
    """``small_room`` as a user would write it: no ``synthetic`` key, so a run trains the corrections of a captured
    scan too (pose refinement, per-image appearance). The compiled step of this scene under the default config is
    the one test_pose_refinement.py, test_service_runtime.py and test_budget_share.py compile
    (``compiled_captured_step`` compiles it first)."""

    def build(scene: Path) -> None:
        shutil.copytree(small_room, scene)
        meta = json.loads((scene / "transforms.json").read_text())
        meta.pop("synthetic", None)
        (scene / "transforms.json").write_text(json.dumps(meta))

    return built_once(tmp_path_factory, "scenes/captured_small_room", build)


@pytest.fixture(scope="session")
def compiled_captured_step(captured_small_room, tmp_path_factory) -> Path:
    """A run of ``captured_small_room`` under the default config, compiled, for 8 steps (both graphs of a step
    that refines poses on every n-th one), made once per session under the file lock: afterwards the inductor
    cache holds the step that test_pose_refinement.py, test_service_runtime.py and test_budget_share.py compile,
    and each loads it instead of compiling it cold at the same moment as another (in a three-process run two of
    them compiled it side by side)."""
    from voxnerf.config import TrainConfig
    from voxnerf.training.run import train

    def build(run: Path) -> None:
        config = TrainConfig(max_iters=8, final_eval=False, device="cpu", checkpoint_every_s=1e9)
        train(captured_small_room, run, config, progress_bar=False)

    return built_once(tmp_path_factory, "runs/captured_compiled", build)


@pytest.fixture(scope="session")
def trained_small_room(small_room, tmp_path_factory) -> Path:
    """``small_room`` trained as ``voxnerf train --no-compile`` would (C kernel where available) for 500 steps
    of 1024 rays on the CPU, progress evaluations every 20 s and a final evaluation. Read by the end-to-end
    checks (tests/test_end_to_end.py) and the geometry export's (tests/inference/test_export.py); tests write
    nothing into it. Eager: compiling this step's graph on a cold cache took longer than its 500 steps, and the
    compiled step is covered by the runs that compile ``captured_small_room``'s."""
    from voxnerf.config import TrainConfig
    from voxnerf.training.run import train

    def build(run: Path) -> None:
        config = TrainConfig(max_iters=500, rays_per_batch=1024, device="cpu", eval_every_s=20.0, compile=False)
        train(small_room, run, config, progress_bar=False)

    return built_once(tmp_path_factory, "runs/small_room", build)


def pytest_configure(config: pytest.Config) -> None:
    """Under pytest-xdist (``make test`` runs three processes on two cores), torch computes in one thread per
    process: in the test processes and in every process they start (services' workers, ``voxnerf train``
    subprocesses), through ``OMP_NUM_THREADS`` unless it is set already. With torch's default of a thread per
    core, the test processes' OpenMP threads, and their services', spin for cores another process holds:
    the in-process training tests took nearly twice as long. Tests of multi-threaded code set their threads."""
    if os.environ.get("PYTEST_XDIST_WORKER"):
        os.environ.setdefault("OMP_NUM_THREADS", "1")  # torch reads it when it loads
        if "torch" in sys.modules:  # loaded already (by a plugin): set its threads directly
            sys.modules["torch"].set_num_threads(int(os.environ["OMP_NUM_THREADS"]))


def pytest_collection_modifyitems(session: pytest.Session, config: pytest.Config, items: list[pytest.Item]) -> None:
    """Test files in the order of their seconds in tests/file_seconds.json, longest first (a file's tests keep
    their order; a file the table lacks comes after those it lists). ``--dist loadfile --no-loadscope-reorder``
    hands files to the test processes in this order as each finishes one, so the session ends on short files
    instead of one process running a long one while the others wait."""
    table = Path(__file__).with_name("file_seconds.json")
    seconds = json.loads(table.read_text()) if table.is_file() else {}

    def longest_first(item: pytest.Item) -> float:
        return -seconds.get(item.nodeid.split("::")[0], -1)  # the node id starts with the file, from the root

    items.sort(key=longest_first)  # stable: the collection's order within a file and among equals
