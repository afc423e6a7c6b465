"""benchmarks/import_captures.py on a few redkitchen frames: its table and results, and the given scene it trains
beside an imported one (same frames, same splits, the source's files)."""

from __future__ import annotations

import importlib
import json
import os
import sys
from pathlib import Path

import pytest
from capture_fixtures import REDKITCHEN, needs_redkitchen

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
import_captures = importlib.import_module("import_captures")

pytestmark = [pytest.mark.timeout(600), needs_redkitchen]


def test_photos_and_video_rows(tmp_path, capsys):
    out = tmp_path / "results"
    assert import_captures.main(["--redkitchen", str(REDKITCHEN), "--frames", "12", "--stride", "10", "--scale",
                                 "0.5", "--out", str(out)]) == 0
    rows = json.loads((out / "results.json").read_text())["results"]
    assert [r["importer"] for r in rows] == ["photos", "video"]
    photos, video = rows
    assert photos["size"] == [320, 240] and video["size"] == [640, 480]
    for row in rows:
        assert row["images"] == 12 and row["registered"] >= 10 and row["matching"] in ("exhaustive", "sequential")
        error = row["pose_error"]
        assert 0 < error["rotation_deg_max"] < 10 and 0 < error["centre_error_max_fraction"] < 0.25
        assert error["trajectory_length"] > 0.3
    table = (out / "table.md").read_text()
    assert table.count("| photos | 320x240 | exhaustive |") == 1 and "| video | 640x480 | sequential |" in table
    assert "not run" in table


def test_given_subset_keeps_the_imported_frames_and_splits_with_the_source_files(tmp_path):
    imported = tmp_path / "imported"
    imported.mkdir()
    frames = [{"file_path": f"images/frame_{k:05d}.jpg", "transform_matrix": []} for k in range(4)]
    (imported / "transforms.json").write_text(json.dumps({
        "frames": frames, "train_filenames": ["images/frame_00000.jpg", "images/frame_00002.jpg"],
        "eval_splits": {"interpolation": ["images/frame_00001.jpg"], "extrapolation": ["images/frame_00003.jpg"]}}))
    source = {f"images/frame_{k:05d}.jpg": f"images/frame-{10 * k:06d}.jpg" for k in range(4)}
    given = import_captures.given_subset(REDKITCHEN, imported, source.__getitem__, tmp_path / "given")
    meta = json.loads((given / "transforms.json").read_text())
    assert [f["file_path"] for f in meta["frames"]] == list(source.values())
    assert meta["train_filenames"] == ["images/frame-000000.jpg", "images/frame-000020.jpg"]
    assert meta["eval_splits"] == {"interpolation": ["images/frame-000010.jpg"],
                                   "extrapolation": ["images/frame-000030.jpg"]}
    source_meta = json.loads((REDKITCHEN / "transforms.json").read_text())
    assert meta["frames"][1] == source_meta["frames"][10] and meta["fl_x"] == source_meta["fl_x"]
    linked = given / "images" / "frame-000010.jpg"
    assert linked.is_file() and not linked.is_symlink()
    assert os.path.samefile(linked, REDKITCHEN / "images" / "frame-000010.jpg") or \
        linked.read_bytes() == (REDKITCHEN / "images" / "frame-000010.jpg").read_bytes()
    assert (given / "depth" / "frame-000000.png").is_file()  # every 5th source frame has depth
    prior = source_meta.get("ply_file_path") or source_meta.get("prior_file_path")
    assert prior is None or (given / prior).is_file()
