"""The VoxNeRF sampler's window checked against depth (voxnerf/training/window_check.py and the set-up stage
window_check): the counts on made-up rays, and the stage in a real run (report.json's window_check)."""

from __future__ import annotations

import json
import math
from dataclasses import replace

import numpy as np
import pytest
import trimesh
from synthetic_fixtures import MICRO, make_micro_scene, micro_config

from voxnerf.inference.render import load_model
from voxnerf.synthetic import make_room_scene
from voxnerf.training.run import REPORT, train
from voxnerf.training.window_check import (
    MAX_WRONG_FIRST_HITS,
    choose_sampler,
    first_hit_check,
    robust_spread,
    samples_near,
    share_outside,
)

NAN = float("nan")


def test_first_hits_are_sorted_into_miss_short_through_and_right():
    # Ten rays see a surface at 1.0 (normalised), one has no depth. Half-window 0.1; 2 normalised units per metre.
    true_t = np.array([1.0] * 10 + [NAN])
    hit_t = np.array([1.0, 1.05, 0.95, 1.09, 0.5, 0.85, 1.5, NAN, NAN, NAN, 0.2])
    hit = np.array([True] * 7 + [False] * 3 + [True])
    check = first_hit_check(hit_t, hit, true_t, half_window=0.1, scale=2.0)
    assert check["rays"] == 10 and check["half_window_m"] == pytest.approx(0.05)
    assert check["miss"] == pytest.approx(0.3)
    assert check["stop_short"] == pytest.approx(0.2)  # 0.5 and 0.85: more than 0.1 before the surface
    assert check["pass_through"] == pytest.approx(0.1)  # 1.5
    assert check["wrong_first_hit"] == pytest.approx(0.3)
    assert check["first_hit_offset_m"]["p50"] == pytest.approx(0.0)  # median of the 7 hits' offsets, metres
    assert check["prior_noise_m"] is None and check["window_over_noise"] is None and check["prior_sigma_m"] is None


def test_a_hit_as_far_as_the_half_window_is_still_inside():
    check = first_hit_check(np.array([0.9, 1.1]), np.array([True, True]), np.array([1.0, 1.0]), 0.1 + 1e-9, 1.0)
    assert check["stop_short"] == 0.0 and check["pass_through"] == 0.0


def test_the_priors_noise_is_measured_along_the_rays_against_the_depth():
    rng = np.random.default_rng(0)
    true_t = rng.uniform(1.0, 3.0, 20_000)
    prior_t = true_t + rng.normal(0.0, 0.04, true_t.size)  # 2 cm at 2 units per metre
    prior_t[:500] = NAN  # the prior is not seen there
    prior_t[500:700] += 1.0  # a few gross outliers do not move the robust spread
    check = first_hit_check(true_t, np.ones(true_t.size, bool), true_t, 0.2, 2.0, prior_t, prior_sigma=0.05)
    assert check["prior_noise_m"] == pytest.approx(0.02, rel=0.05)
    assert check["prior_sigma_m"] == pytest.approx(0.025)
    assert check["window_over_noise"] == pytest.approx(0.1 / 0.02, rel=0.05)


def test_no_ray_with_depth_gives_no_fractions_and_bad_input_is_refused():
    check = first_hit_check(np.array([1.0]), np.array([True]), np.array([NAN]), 0.1, 1.0)
    assert check["rays"] == 0 and check["miss"] is None and check["wrong_first_hit"] is None
    assert check["first_hit_offset_m"] is None
    with pytest.raises(ValueError, match="one shape"):
        first_hit_check(np.zeros(3), np.ones(2, bool), np.zeros(3), 0.1, 1.0)
    with pytest.raises(ValueError, match="positive"):
        first_hit_check(np.zeros(3), np.ones(3, bool), np.zeros(3), 0.0, 1.0)
    with pytest.raises(ValueError, match="positive"):
        first_hit_check(np.zeros(3), np.ones(3, bool), np.zeros(3), 0.1, NAN)
    assert robust_spread(np.array([NAN])) is None


def test_samples_near_the_surface_and_outside_the_window():
    mid = np.array([[0.95, 1.0, 1.5], [0.2, 0.3, 0.4], [0.1, 0.2, 0.3]])
    true_t = np.array([1.0, 0.3, NAN])
    assert samples_near(mid, true_t, 0.06) == pytest.approx(3 / 6)  # 0.95, 1.0 and 0.3
    assert samples_near(mid, np.array([NAN, NAN, NAN]), 0.06) is None
    hit_t, hit = np.array([1.0, NAN, 0.2]), np.array([True, False, True])
    # inside their window: 0.95 and 1.0 (ray 0), 0.2 (ray 2, 0.1 and 0.3 are 0.1 away); ray 1 has no hit
    assert share_outside(mid, hit_t, hit, 0.06) == pytest.approx(1 - 3 / 9)
    with pytest.raises(ValueError, match=r"\[R, S\]"):
        samples_near(mid[0], true_t, 0.1)


def _stage(report: dict, name: str) -> dict:
    return next(s for s in report["stages"] if s["name"] == name)


def test_a_run_checks_its_window_at_set_up_and_reports_it(tmp_path_factory, tmp_path):
    room = make_micro_scene(tmp_path_factory, "window-check")
    train(room, tmp_path / "run", micro_config(max_iters=1, final_eval=False), progress_bar=False)
    report = json.loads((tmp_path / "run" / REPORT).read_text())
    stage = _stage(report, "window_check")
    assert stage["ran"] and "training rays with depth" in stage["why"]
    check = report["window_check"]
    assert check["rays"] > 1000 and check["half_window_m"] > 0
    parts = (check["miss"], check["stop_short"], check["pass_through"])
    assert all(0.0 <= p <= 1.0 for p in parts) and sum(parts) <= 1.0
    # The micro room's depth is exact and its prior a 2 cm point cloud: the prior's noise is measured near that.
    assert 0.005 < check["prior_noise_m"] < 0.06 and check["prior_sigma_m"] == pytest.approx(0.02)
    samples = check["samples"]
    assert samples["rays"] > 0 and 0.0 <= samples["outside_window"] <= 1.0
    near = samples["near_surface"]
    assert all(math.isfinite(near[k]) and 0.0 <= near[k] <= 1.0 for k in ("voxnerf", "occupancy_grid"))


def test_the_check_says_why_it_did_not_run(tmp_path_factory, tmp_path):
    room = make_micro_scene(tmp_path_factory, "window-check-grid")
    train(room, tmp_path / "grid", micro_config(max_iters=1, final_eval=False, sampler="occgrid"), progress_bar=False)
    report = json.loads((tmp_path / "grid" / REPORT).read_text())
    assert _stage(report, "window_check") == {**_stage(report, "window_check"), "ran": False,
                                              "why": "sampler 'occgrid' has no window"}
    assert "window_check" not in report
    no_depth = make_room_scene(tmp_path_factory.mktemp("no-depth") / "room", replace(MICRO, write_depth=False))
    train(no_depth, tmp_path / "no-depth", micro_config(max_iters=1, final_eval=False), progress_bar=False)
    report = json.loads((tmp_path / "no-depth" / REPORT).read_text())
    assert _stage(report, "window_check")["why"] == ("no sensor depth to check the window against; sampler 'auto': "
                                                     "voxnerf, no depth to check the window against: the VoxNeRF "
                                                     "sampler, as the paper")
    assert "window_check" not in report and report["config"]["sampler"] == "voxnerf"


def test_sampler_auto_keeps_the_window_unless_too_many_first_hits_are_wrong():
    assert choose_sampler(None, has_octree=False)[0] == "occgrid"
    assert choose_sampler({"wrong_first_hit": 0.0}, has_octree=False)[0] == "occgrid"  # no octree, no window
    assert choose_sampler(None, has_octree=True)[0] == "voxnerf"  # nothing to check against: the paper's sampler
    assert choose_sampler({"wrong_first_hit": None}, has_octree=True)[0] == "voxnerf"
    assert choose_sampler({"wrong_first_hit": 0.047}, has_octree=True) == (
        "voxnerf", "the first hit is wrong on 4.7% of the rays with depth (at most 6%): the VoxNeRF sampler")
    assert choose_sampler({"wrong_first_hit": MAX_WRONG_FIRST_HITS}, has_octree=True)[0] == "voxnerf"
    name, why = choose_sampler({"wrong_first_hit": 0.491}, has_octree=True)
    assert name == "occgrid"
    assert why.startswith("the first hit is wrong on 49.1% of the rays with depth (more than 6%)")


@pytest.mark.parametrize(("shift_m", "chosen"), [(0.0, "voxnerf"), (0.5, "occgrid")])
def test_a_run_on_sampler_auto_chooses_at_set_up_and_trains_renders_and_reports_its_choice(
        tmp_path_factory, tmp_path, shift_m, chosen):
    """The micro room as given, and with its prior moved by half a metre (a prior registered in another frame):
    the window check finds the first hits right, or wrong on most rays, and the run samples with its choice."""
    room = make_micro_scene(tmp_path_factory, "window-auto")
    meta = json.loads((room / "transforms.json").read_text())
    prior = room / meta["prior_file_path"]
    cloud = trimesh.load(prior)
    trimesh.PointCloud(np.asarray(cloud.vertices) + [shift_m, shift_m, 0.0]).export(prior)
    run = tmp_path / "run"
    train(room, run, micro_config(final_eval=False), progress_bar=False)
    report = json.loads((run / REPORT).read_text())
    assert report["status"] == "succeeded" and report["config"]["sampler"] == chosen
    check = report["window_check"]
    assert (check["wrong_first_hit"] > MAX_WRONG_FIRST_HITS) == (chosen == "occgrid")
    assert check["sampler"]["chosen"] == chosen and check["sampler"]["why"] in _stage(report, "window_check")["why"]
    assert f"sampler 'auto': {chosen}, " in _stage(report, "window_check")["why"]
    assert _stage(report, "octree")["ran"]  # built for the check whatever the choice
    trained = load_model(run, "cpu")
    assert trained.model.config.sampling.sampler == chosen  # the checkpoint keeps the choice: renders follow it
    sampler = trained.model.sampler()
    assert type(sampler).__name__ == ("OccGridSampler" if chosen == "occgrid" else "VoxNeRFSampler")
