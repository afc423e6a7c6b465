"""Checkpoints cannot run code (issue #22, item 1): a checkpoint carrying a pickled callable is refused by
``load_model`` (``voxnerf render``, the render worker) and by a resumed ``train()`` before anything in it runs,
and saving refuses anything that ``weights_only`` loading would refuse."""

from __future__ import annotations

import io
import os
import pickle
import re
from pathlib import Path

import numpy as np
import pytest
import torch
from tiny_run import write_tiny_run

from voxnerf.cli import main
from voxnerf.config import TrainConfig
from voxnerf.errors import RunError
from voxnerf.files import CHECKPOINT
from voxnerf.inference.render import load_model
from voxnerf.training.checkpoint import check_plain, load_checkpoint, save_atomic_torch
from voxnerf.training.run import train


class WritesMarker:
    """Unpickling this calls ``open(marker, "w")``: the marker file appears if anything in the file runs."""

    def __init__(self, marker: Path) -> None:
        self.marker = marker

    def __reduce__(self):
        return (open, (str(self.marker), "w"))


def _poisoned_bytes(marker: Path, form: str) -> bytes:
    """A checkpoint-like dict whose "model" unpickles by calling ``open(marker, "w")``, as torch's zip file,
    torch's legacy format, or a bare pickle."""
    state = {"model": WritesMarker(marker), "iteration": 0}
    if form == "pickle":
        return pickle.dumps(state, protocol=2)  # torch.load reads protocol 2; 4 and up stop at their FRAME
    buffer = io.BytesIO()
    torch.save(state, buffer, _use_new_zipfile_serialization=form == "zip")
    return buffer.getvalue()


@pytest.fixture(params=["zip", "legacy", "pickle"])
def poisoned_run(request, tmp_path) -> tuple[Path, Path]:
    """(run_dir whose checkpoint carries the callable, marker path that must never appear)."""
    run, marker = tmp_path / "run", tmp_path / "marker"
    run.mkdir()
    (run / CHECKPOINT).write_bytes(_poisoned_bytes(marker, request.param))
    return run, marker


def _assert_refused(message: str, run: Path) -> None:
    assert message.startswith(f"{run / CHECKPOINT}: refused") and "\n" not in message.strip(), message
    assert "weights_only" not in message  # no advice to turn the protection off


def test_the_marker_payload_runs_when_unpickled_without_the_guard(tmp_path):
    """The payload is live: plain unpickling writes the marker (so its absence below means refusal)."""
    marker = tmp_path / "marker"
    pickle.loads(_poisoned_bytes(marker, "pickle"))
    assert marker.exists()


def test_load_model_refuses_a_checkpoint_carrying_a_callable(poisoned_run):
    run, marker = poisoned_run
    with pytest.raises(RunError) as info:
        load_model(run, "cpu")
    _assert_refused(str(info.value), run)
    assert not marker.exists()


def test_voxnerf_render_refuses_it_in_one_line(poisoned_run, capsys):
    run, marker = poisoned_run
    pose = run.parent / "pose.json"
    pose.write_text('{"transform_matrix": [[1,0,0,0],[0,1,0,0],[0,0,1,3],[0,0,0,1]]}')
    out = run.parent / "out" / "view.png"
    assert main(["render", str(run), "--pose", str(pose), "--out", str(out), "--device", "cpu"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("voxnerf: error: "), err
    _assert_refused(err.removeprefix("voxnerf: error: "), run)
    assert not marker.exists() and not out.parent.exists()


def test_resuming_refuses_it_before_training(poisoned_run, tmp_path):
    run, marker = poisoned_run
    config = TrainConfig(max_iters=1, device="cpu", compile=False)
    with pytest.raises(RunError) as info:
        train(tmp_path / "no-scene-needed", run, config, resume=True, progress_bar=False)
    _assert_refused(str(info.value), run)
    assert not marker.exists()


def test_a_checkpoint_that_is_not_a_dict_is_unreadable(tmp_path):
    path = tmp_path / CHECKPOINT
    torch.save([torch.zeros(2)], path)
    with pytest.raises(RunError, match=r"unreadable checkpoint \(holds a list, not a dict\)"):
        load_checkpoint(path)


def test_a_written_checkpoint_loads_with_weights_only(tmp_path):
    """The checkpoint format (model config, transform, octree, weights, intrinsics) is plain types only."""
    run = write_tiny_run(tmp_path / "run")
    state = torch.load(run / CHECKPOINT, weights_only=True)
    check_plain(state)
    assert load_model(run, "cpu").iteration == 0


@pytest.mark.parametrize(("value", "where"), [(np.zeros(2), "checkpoint/history[0]"),
                                              (Path("/x"), "checkpoint/history[0]"),
                                              (object(), "checkpoint/history[0]")])
def test_saving_refuses_what_loading_would_refuse(tmp_path, value, where):
    path = tmp_path / CHECKPOINT
    with pytest.raises(TypeError, match=rf"^{re.escape(where)}: a .* cannot go in a checkpoint"):
        save_atomic_torch({"iteration": 1, "history": [value]}, path)
    assert os.listdir(tmp_path) == []


FUZZ_INPUTS = 60


def test_damaged_checkpoints_are_run_errors_never_crashes(tmp_path):
    """Random byte flips and truncations of a real checkpoint: each loads or is a one-line RunError."""
    good = (write_tiny_run(tmp_path / "good") / CHECKPOINT).read_bytes()
    rng = np.random.default_rng(22)
    run = tmp_path / "run"
    run.mkdir()
    for i in range(FUZZ_INPUTS):
        data = bytearray(good[: int(rng.integers(1, len(good)))] if i % 3 == 0 else good)
        for at in rng.integers(0, len(data), size=int(rng.integers(1, 8))):
            data[at] = int(rng.integers(0, 256))
        (run / CHECKPOINT).write_bytes(bytes(data))
        try:
            load_model(run, "cpu")
        except RunError as err:
            assert str(err).startswith(str(run / CHECKPOINT)) and "\n" not in str(err), str(err)
