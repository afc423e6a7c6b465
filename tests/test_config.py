"""TrainConfig refuses absurd values with a ValidationError naming the field."""

from __future__ import annotations

import json
import math
import shutil
from pathlib import Path

import numpy as np
import pytest
from pydantic import ValidationError

from voxnerf.config import MAX_LR, TrainConfig


@pytest.mark.parametrize("lr", [0.0, -1e-3, math.nan, math.inf, -math.inf, 1.0000001, 10.0, 1e300])
def test_absurd_learning_rates_are_refused(lr: float) -> None:
    with pytest.raises(ValidationError) as caught:
        TrainConfig(lr=lr)
    (error,) = caught.value.errors()
    assert error["loc"] == ("schedule", "lr")
    assert "learning rate must be in (0, 1]" in str(caught.value) or "finite number" in str(caught.value)


@pytest.mark.parametrize("lr", [1e-6, 1e-2, MAX_LR])
def test_sane_learning_rates_are_kept(lr: float) -> None:
    assert TrainConfig(lr=lr).schedule.lr == lr


@pytest.mark.parametrize("field", ["max_seconds", "eval_every_s", "checkpoint_every_s", "lambda_depth"])
def test_nan_and_infinity_are_refused_in_every_number(field: str) -> None:
    for value in (math.nan, math.inf):
        with pytest.raises(ValidationError, match="finite number"):
            TrainConfig(**{field: value})
    with pytest.raises(ValidationError, match="finite number"):
        TrainConfig(eval_at=[10.0, math.inf])


# ------------------------------------------------------------------------------------ nested by component

def test_flat_dotted_and_nested_names_make_the_same_config():
    flat = TrainConfig(lr=0.02, n_importance=16, appearance="none")
    dotted = TrainConfig(**{"schedule.lr": 0.02, "sampling.n_importance": 16, "corrections.appearance": "none"})
    nested = TrainConfig(schedule={"lr": 0.02}, sampling={"n_importance": 16}, corrections={"appearance": "none"})
    assert flat == dotted == nested
    assert flat.schedule.lr == 0.02 and flat.sampling.n_importance == 16 and flat.corrections.appearance == "none"


def test_a_flat_or_dotted_name_wins_over_its_component_given_whole():
    cfg = TrainConfig(schedule={"lr": 0.02, "lr_final": 0.5}, lr=0.03)
    assert (cfg.schedule.lr, cfg.schedule.lr_final) == (0.03, 0.5)


@pytest.mark.parametrize("values", [{"no_such_setting": 1}, {"schedule.no_such_setting": 1},
                                    {"schedule": {"n_importance": 4}}, {"nope.lr": 0.1}])
def test_unknown_names_and_settings_in_the_wrong_component_are_refused(values):
    with pytest.raises(ValidationError):
        TrainConfig(**values)


def test_flat_round_trips_and_names_every_setting_once():
    from voxnerf.config import FIELD_SECTIONS, SECTIONS

    cfg = TrainConfig(preset="paper", lr=0.02, background=(0.1, 0.2, 0.3), eval_at=[5.0])
    flat = cfg.flat()
    assert TrainConfig(**flat) == cfg
    assert set(flat) == {"preset", *FIELD_SECTIONS}
    assert sum(len(section.model_fields) for section in SECTIONS.values()) == len(FIELD_SECTIONS)


def test_resolved_fills_the_preset_s_values_in_every_component_and_keeps_explicit_ones():
    from voxnerf.config import PRESETS

    cfg = TrainConfig(preset="paper", n_rest=7).resolved()
    for section, values in PRESETS["paper"].items():
        for name, value in values.items():
            expected = 7 if name == "n_rest" else value
            assert getattr(getattr(cfg, section), name) == expected, name
    assert cfg.sampling.samples_per_ray == 128 + 7


def test_model_copy_with_flat_names_updates_the_components_and_validates():
    cfg = TrainConfig().model_copy(update={"lr": 0.02, "sampling.n_rest": 3})
    assert cfg.schedule.lr == 0.02 and cfg.sampling.n_rest == 3 and "lr" not in cfg.__dict__
    with pytest.raises(ValidationError):
        TrainConfig().model_copy(update={"lr": 5.0})
    assert TrainConfig().model_copy(update={"preset": "paper"}).preset == "paper"


def test_updated_validates_the_new_values():
    cfg = TrainConfig()
    assert cfg.updated(focal_scale=1.1).corrections.focal_scale == 1.1 and cfg.corrections.focal_scale == "auto"
    with pytest.raises(ValidationError):
        cfg.updated(focal_scale=7.0)


def test_who_may_set_a_setting_is_said_where_it_is_defined():
    from voxnerf.config import audience, settings_for

    assert audience("max_seconds") == "job" and audience("device") == "worker" and audience("lr") == "internal"
    assert "preset" in settings_for("job") and "lr" not in settings_for("job")
    every = set(settings_for("job")) | set(settings_for("worker")) | set(settings_for("internal"))
    assert every == set(TrainConfig().flat())


OLD_RUN = Path(__file__).parent / "fixtures" / "run_v0_1"
# Settings added after OLD_RUN was written: its report lacks them, and they take their defaults.
ADDED_SINCE_OLD_RUN = {"octree_misses": "auto", "prior_file": True, "window_centre": "surface",
                       "window_width": 1.0, "pixel_jitter": False, "cone_radius": None,
                       "weight_average": 0.995, "render_background": "nearest_seen", "error_map": 0.0,
                       "error_map_weights": False, "antialias": True,
                       "nearest_seen_weight": 1.0}


def test_a_checkpoint_of_the_flat_config_loads_and_renders():
    from voxnerf.inference.render import load_model, render

    trained = load_model(OLD_RUN, "cpu")
    cfg = trained.model.config
    assert (cfg.model.hash_levels, cfg.model.hidden_dim, cfg.sampling.n_importance) == (2, 8, 4)
    assert cfg.corrections.appearance == "affine" and cfg.corrections.pose_refinement == "so3xr3"
    assert isinstance(cfg.model.background, tuple) and cfg.corrections.focal_scale == 1.0
    assert trained.model.appearance is not None and trained.model.pose_refinement is not None
    out = render(trained, np.eye(4))
    assert out["rgb"].shape == (trained.default_intrinsics.height, trained.default_intrinsics.width, 3)
    assert all(np.isfinite(v).all() for v in out.values())


def test_a_report_of_the_flat_config_names_the_settings_a_report_names_now():
    old = json.loads((OLD_RUN / "report.json").read_text())
    assert set(old["config"]) | set(ADDED_SINCE_OLD_RUN) == set(TrainConfig().flat())
    again = json.loads(json.dumps(TrainConfig(**old["config"]).flat()))
    assert again == old["config"] | ADDED_SINCE_OLD_RUN


def test_a_run_of_the_flat_config_resumes(tmp_path_factory, tmp_path):
    from synthetic_fixtures import MICRO

    from voxnerf.synthetic import make_room_scene
    from voxnerf.training.run import train

    scene = make_room_scene(tmp_path_factory.mktemp("old") / "scene", MICRO)
    meta = json.loads((scene / "transforms.json").read_text())
    meta.pop("voxnerf_synthetic")  # as the run was made: a captured-like scene
    (scene / "transforms.json").write_text(json.dumps(meta))
    run = tmp_path / "run"
    shutil.copytree(OLD_RUN, run)
    old = json.loads((OLD_RUN / "report.json").read_text())["config"]
    report = train(scene, run, TrainConfig(**(old | {"max_iters": 5})), progress_bar=False)
    assert report.status == "succeeded" and report.resumed_from_iteration == 3 and report.iteration == 5
    assert set(json.loads((run / "report.json").read_text())["config"]) == set(old) | set(ADDED_SINCE_OLD_RUN)


def test_a_checkpoint_keeps_the_model_s_own_config_and_rebuilds_it():
    import torch
    from tiny_run import tiny_model

    from voxnerf.config import MODEL_SETTINGS
    from voxnerf.model.voxnerf_model import VoxNeRFModel

    model = tiny_model(max_seconds=30.0, lr=0.02, focal_scale=1.1, n_importance=3)
    state = model.state_dict()
    kept = state["config"]
    assert set(kept) == set(MODEL_SETTINGS)
    assert "max_seconds" not in kept["run"] and "schedule" not in kept and kept["corrections"]["focal_scale"] == 1.1
    again = VoxNeRFModel.from_state_dict(state, torch.device("cpu"))
    assert again.config.model == model.config.model and again.config.sampling == model.config.sampling
    assert again.config.corrections.focal_scale == 1.1 and again.config.run.downscale == model.config.run.downscale


def test_docs_engine_lists_every_setting_in_its_component_with_who_may_set_it():
    import re

    from voxnerf.config import SECTIONS, audience

    text = (Path(__file__).parents[1] / "docs" / "engine.md").read_text()
    text = text[text.index("## Configuration"):]
    text = text[: text.index("\n## ", 1)]
    for name, section in SECTIONS.items():
        row = re.search(rf"^\| `{name}` \| (.*) \|$", text, re.M)
        assert row, f"docs/engine.md: no row for the component {name}"
        listed = re.findall(r"`(\w+)`(?: \((job|worker)\))?", row[1])
        assert [(field, who or "internal") for field, who in listed] == \
            [(field, audience(field)) for field in section.model_fields], name


@pytest.mark.parametrize("preset", ["cpu", "paper"])
def test_the_full_render_path_s_chunk_is_the_device_s_unless_set(preset):
    """eval_chunk left unset takes the rendering device's value (4,096 rays on a CPU, 32,768 on a GPU, for either
    preset: a checkpoint keeps it unset, so where it renders decides); a value set wins on every device."""
    from voxnerf.config import EVAL_CHUNKS

    evaluation = TrainConfig(preset=preset).resolved().evaluation
    assert evaluation.eval_chunk is None
    assert evaluation.chunk_on("cpu") == EVAL_CHUNKS["cpu"] == 4096
    assert evaluation.chunk_on("cuda") == EVAL_CHUNKS["cuda"] == 32_768
    model_config = TrainConfig(**TrainConfig(preset=preset).for_model())
    assert model_config.evaluation.chunk_on("cuda") == 32_768
    chosen = TrainConfig(preset=preset, eval_chunk=1000).evaluation
    assert chosen.chunk_on("cpu") == chosen.chunk_on("cuda") == 1000
    with pytest.raises(ValueError, match="no evaluation chunk for device type 'mps'"):
        evaluation.chunk_on("mps")
