"""voxnerf.synthetic.writer: docs/scene-format.md compliance of the written room, determinism, refused output."""

from __future__ import annotations

import json
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import pytest
from synthetic_fixtures import TINY, make_tiny_scene, meta_of

from voxnerf.synthetic import RoomSpec, make_room_scene
from voxnerf.synthetic.writer import WRITER_VERSION, written_by_this_writer


@pytest.fixture(scope="module")
def tiny_scene(tmp_path_factory) -> Path:
    return make_tiny_scene(tmp_path_factory)


def test_scene_follows_scene_format(tiny_scene: Path):
    meta = meta_of(tiny_scene)
    for key in ("fl_x", "fl_y", "cx", "cy", "w", "h", "frames"):
        assert key in meta
    assert (meta["w"], meta["h"]) == (TINY.width, TINY.height)
    assert (meta["cx"], meta["cy"]) == (TINY.width / 2, TINY.height / 2)
    hfov = 2 * np.degrees(np.arctan(meta["w"] / 2 / meta["fl_x"]))
    assert 60 <= hfov <= 70
    assert meta["depth_unit_scale_factor"] == 0.001
    assert meta["prior_file_path"] == "prior.ply" and meta["prior_sigma"] == TINY.prior_sigma

    frame_paths = [f["file_path"] for f in meta["frames"]]
    assert len(frame_paths) == len(set(frame_paths))
    for frame in meta["frames"]:
        c2w = np.asarray(frame["transform_matrix"])
        assert c2w.shape == (4, 4)
        np.testing.assert_allclose(c2w[3], [0, 0, 0, 1])
        np.testing.assert_allclose(c2w[:3, :3] @ c2w[:3, :3].T, np.eye(3), atol=1e-6)
        assert np.linalg.det(c2w[:3, :3]) == pytest.approx(1.0, abs=1e-6)
        rgb = iio.imread(tiny_scene / frame["file_path"])
        assert rgb.shape == (TINY.height, TINY.width, 3) and rgb.dtype == np.uint8
        assert rgb.std() > 10, "images should carry texture"
        depth = iio.imread(tiny_scene / frame["depth_file_path"])
        assert depth.shape == (TINY.height, TINY.width) and depth.dtype == np.uint16
        assert depth.min() > 0, "the closed room leaves no pixel without depth"

    splits = {"train": meta["train_filenames"], "test": meta["test_filenames"], **meta["eval_splits"]}
    assert set(meta["eval_splits"]) == {"interpolation", "extrapolation"}
    assert meta["test_filenames"] == meta["eval_splits"]["interpolation"]
    for name, files in splits.items():
        assert files, name
        assert set(files) <= set(frame_paths), name
    assert not set(splits["train"]) & (set(splits["interpolation"]) | set(splits["extrapolation"]))
    assert set(frame_paths) == set().union(*splits.values()), "only frames a split uses are written"
    on_disk = sorted(p.name for p in (tiny_scene / "images").iterdir())
    assert on_disk == sorted(Path(p).name for p in frame_paths)
    assert (tiny_scene / "gt_mesh.ply").is_file()
    assert meta["voxnerf_synthetic"]["seed"] == TINY.seed
    assert meta["voxnerf_synthetic"]["room_size"] == [5.0, 4.0, 2.6]


def test_generation_is_deterministic(tiny_scene: Path, tmp_path: Path):
    again = make_room_scene(tmp_path / "again", TINY)
    files = sorted(p.relative_to(tiny_scene) for p in tiny_scene.rglob("*") if p.is_file())
    assert files == sorted(p.relative_to(again) for p in again.rglob("*") if p.is_file())
    for rel in files:
        assert (tiny_scene / rel).read_bytes() == (again / rel).read_bytes(), rel


def test_no_prior_and_refused_output(tmp_path: Path):
    spec = RoomSpec(width=32, height=24, n_frames=40, train_every=4, gap_len=10, prior_kind="none", seed=3)
    out = make_room_scene(tmp_path / "none", spec)
    meta = meta_of(out)
    assert "prior_file_path" not in meta and "prior_sigma" not in meta and not (out / "prior.ply").exists()
    with pytest.raises(FileExistsError, match="none"):
        make_room_scene(out, spec)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["none"], "no temporary directory is left behind"
    with pytest.raises(ValueError, match="prior_kind"):
        make_room_scene(tmp_path / "bad", RoomSpec(prior_kind="tsdf"))


def test_a_scene_says_it_is_synthetic_and_which_writer_wrote_it(tiny_scene: Path, tmp_path: Path):
    meta = meta_of(tiny_scene)
    assert meta["synthetic"] is True and meta["voxnerf_synthetic"]["writer"] == WRITER_VERSION
    assert written_by_this_writer(tiny_scene)
    assert not written_by_this_writer(tmp_path / "absent")
    for written in ({**meta, "voxnerf_synthetic": {}}, {**meta, "voxnerf_synthetic": [1]}, [meta]):
        (tmp_path / "transforms.json").write_text(json.dumps(written))
        assert not written_by_this_writer(tmp_path)
    (tmp_path / "transforms.json").write_text("{")
    assert not written_by_this_writer(tmp_path)
