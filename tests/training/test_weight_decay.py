"""``field_weight_decay`` ``auto`` (voxnerf/training/stages/weight_decay.py): a decay in proportion to the training
images' noise, resolved once per run and said in the report."""

from __future__ import annotations

import json
import shutil
from pathlib import Path
from types import SimpleNamespace

import imageio.v3 as iio
import numpy as np
import pytest
import torch
from synthetic_fixtures import make_micro_scene, micro_config

from voxnerf.data.image_noise import images_noise_sigma
from voxnerf.data.scene import load_scene
from voxnerf.training.run import train
from voxnerf.training.stages import model_stage
from voxnerf.training.stages.weight_decay import NOISE_DECAY, NOISE_FLOOR, weight_decay_stage


@pytest.fixture(scope="module")
def room(tmp_path_factory) -> Path:
    return make_micro_scene(tmp_path_factory, "decay")


def _noisy_copy(room: Path, tmp_path: Path, sigma: float) -> Path:
    """``room`` with Gaussian noise of ``sigma`` (8-bit levels) added to every image."""
    copy = tmp_path / "noisy"
    shutil.copytree(room, copy)
    rng = np.random.default_rng(0)
    for frame in json.loads((copy / "transforms.json").read_text())["frames"]:
        path = copy / frame["file_path"]
        image = iio.imread(path).astype(np.float32)
        noisy = image + rng.normal(0.0, sigma, image.shape[:2] + (1,))
        iio.imwrite(path, np.clip(np.round(noisy), 0, 255).astype(np.uint8))
    return copy


def test_auto_decays_in_proportion_to_the_training_images_noise(room: Path, tmp_path: Path):
    clean, noisy = load_scene(room), load_scene(_noisy_copy(room, tmp_path, 8.0))
    decays = []
    for scene in (clean, noisy):
        stage = weight_decay_stage(micro_config(), scene)
        sigma = images_noise_sigma([scene.images[i] for i in scene.train_indices])
        expected = NOISE_DECAY * sigma**2 if sigma >= NOISE_FLOOR else 0.0
        assert stage.cfg.schedule.field_weight_decay == pytest.approx(expected)
        assert stage.record.name == "weight_decay" and f"{sigma * 255:.2f}/255" in stage.record.why
        decays.append(stage.cfg.schedule.field_weight_decay)
    assert decays[1] > 2 * decays[0]  # the micro room's tiny textured images read as a little noisy themselves


def test_clean_images_get_no_decay_at_all():
    y, x = np.mgrid[0:60, 0:80].astype(np.float32)
    ramp = np.repeat((40.0 + x + y)[..., None], 3, axis=-1)
    rng = np.random.default_rng(3)
    images = [np.round(ramp + rng.normal(0.0, s, ramp.shape[:2] + (1,))).astype(np.uint8) for s in (0.5, 4.0)]
    for image, decays in zip(images, (False, True), strict=True):
        scene = SimpleNamespace(images=[image, image], train_indices=[0, 1])
        stage = weight_decay_stage(micro_config(), scene)
        assert (stage.cfg.schedule.field_weight_decay > 0) is decays and stage.record.ran is decays
        assert ("clean" in stage.record.why) is not decays
    assert images_noise_sigma([images[0]]) < NOISE_FLOOR < images_noise_sigma([images[1]])


@pytest.mark.parametrize(("value", "ran", "why"), [(0.0, False, "none; as configured"),
                                                   (2e-7, True, "2e-07 on the field's parameters; as configured")])
def test_a_number_is_used_as_given(room: Path, value, ran, why):
    stage = weight_decay_stage(micro_config(field_weight_decay=value), load_scene(room, load_images=False))
    assert stage.cfg.schedule.field_weight_decay == value and stage.record.ran is ran and stage.record.why == why


def test_a_run_reports_the_decay_it_used(room: Path, tmp_path: Path):
    report = train(room, tmp_path / "run", micro_config(max_iters=2), progress_bar=False)
    record = next(s for s in report.stages if s.name == "weight_decay")
    assert isinstance(report.config["field_weight_decay"], float) and "auto: the training images' noise" in record.why


def test_auto_is_refused_before_it_is_resolved(room: Path):
    with pytest.raises(ValueError, match="resolve 'auto' field_weight_decay"):
        model_stage(micro_config(appearance="none", pose_refinement="none"), load_scene(room), None,
                    torch.device("cpu"), None)


@pytest.mark.parametrize("value", [-1e-7, 0.1, "sometimes", None, float("nan")])
def test_a_decay_that_is_neither_auto_nor_a_small_non_negative_number_is_refused(value):
    from pydantic import ValidationError

    from voxnerf.config import TrainConfig

    with pytest.raises(ValidationError, match="field_weight_decay"):
        TrainConfig(max_iters=1, field_weight_decay=value)


def test_a_large_scan_is_measured_on_a_bounded_sample_of_its_images():
    from voxnerf.training.stages.weight_decay import NOISE_IMAGES

    image = np.full((8, 8, 3), 100, np.uint8)
    scene = SimpleNamespace(images=[image] * 100, train_indices=list(range(100)))
    stage = weight_decay_stage(micro_config(), scene)
    assert f"median of {len(range(0, 100, 4))} images" in stage.record.why and len(range(0, 100, 4)) <= NOISE_IMAGES
