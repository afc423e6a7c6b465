"""Quick modes of the benchmark scripts, end to end (real `voxnerf train` runs on a tiny synthetic room).

Each test runs a script's ``--quick`` mode (5 training steps per run, eager mode, 32x24 pixels) and checks
its CSV, markdown table and plot. The scene is generated once and shared.
"""

from __future__ import annotations

import csv
import dataclasses
import importlib
import json
import math
import subprocess
import sys
from pathlib import Path

import pytest
import trimesh

from voxnerf.synthetic import make_room_scene

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
error_vs_runtime = importlib.import_module("error_vs_runtime")
samples_sweep = importlib.import_module("samples_sweep")
prior_noise_sweep = importlib.import_module("prior_noise_sweep")
docs_section = importlib.import_module("docs_section")
optimizer_step = importlib.import_module("optimizer_step")
depth_sources = importlib.import_module("depth_sources")
render_speed = importlib.import_module("render_speed")
suite = importlib.import_module("suite")
sample_placement = importlib.import_module("sample_placement")
suite_geometry = importlib.import_module("suite_geometry")
pose_views = importlib.import_module("pose_views")
step_profile = importlib.import_module("step_profile")
gpu_check = importlib.import_module("gpu_check")
service_speed = importlib.import_module("service_speed")
suite_rooms = importlib.import_module("voxnerf.synthetic.suite")

pytestmark = pytest.mark.timeout(300)


@pytest.fixture(scope="module")
def room(tmp_path_factory) -> Path:
    return make_room_scene(tmp_path_factory.mktemp("bench") / "room", error_vs_runtime.QUICK_ROOM)


def _read_csv(path: Path) -> list[dict]:
    with path.open() as f:
        return list(csv.DictReader(f))


def _finite_psnr(value: str) -> bool:
    return math.isfinite(float(value)) and 0.0 < float(value) < 100.0


def test_time_to_psnr_interpolates_and_reports_unreached() -> None:
    curve = [(10.0, 12.0), (20.0, 16.0), (30.0, 18.0)]
    assert error_vs_runtime.time_to_psnr(curve, 14.0) == pytest.approx(15.0)
    assert error_vs_runtime.time_to_psnr(curve, 11.0) == 10.0
    assert error_vs_runtime.time_to_psnr(curve, 18.5) is None


def test_ratio_table_against_both_baselines() -> None:
    def run(name: str, curve: list[tuple[float, float]]) -> dict:
        history = [{"elapsed_s": t, "psnr": {"interpolation": p}} for t, p in curve]
        return {"name": name, "report": {"history": history}}

    results = [
        run("voxnerf", [(10, 15.0), (20, 20.0)]),
        run("occgrid", [(10, 12.0), (40, 18.5)]),
        run("uniform", [(10, 10.0), (40, 12.5)]),
    ]
    text = "\n".join(error_vs_runtime.ratio_table(results, ["interpolation"]))
    # occgrid's target 18.0 dB: occgrid reaches it at 37.5 s, voxnerf at 16 s -> 2.36x
    assert "vs occgrid, interpolation (18.00 dB)" in text and "| voxnerf | 16 s, 2.36x |" in text
    assert "| uniform | not reached |" in text
    # uniform's target 12.0 dB: uniform at 34 s, voxnerf already above at its first evaluation (10 s): only a
    # bound, at least 3.40x; occgrid's target voxnerf meets between evaluations: an exact time
    assert "| voxnerf | 16 s, 2.36x | ≤10 s, ≥3.40x |" in text
    # occgrid meets uniform's target at its first evaluation while uniform needs 34 s: occgrid's ratio is a bound
    assert "| occgrid | 38 s, 1.00x | ≤10 s, ≥3.40x |" in text


def test_ratio_curves_keep_to_one_set_of_views() -> None:
    def run(name: str, progress: list, full: list) -> dict:
        history = [{"elapsed_s": t, "psnr": {"interpolation": p}} for t, p in progress]
        history += [{"elapsed_s": t, "psnr": {"interpolation": p}, "full": True} for t, p in full]
        history.sort(key=lambda e: e["elapsed_s"])
        return {"name": name, "report": {"history": history, "metrics": {"interpolation": {"psnr": full[-1][1]}}}}

    # 4-view progress evaluations score higher than all views: a target from one must not be met on the other
    with_progress = [
        run("occgrid", [(60, 20.0), (180, 24.0)], [(120, 19.0), (300, 20.0)]),
        run("voxnerf", [(60, 22.0), (180, 25.0)], [(120, 21.0), (300, 22.0)]),
        run("nerfacto", [], [(300, 19.0)]),
    ]
    text = "\n".join(error_vs_runtime.ratio_table(with_progress, ["interpolation"]))
    assert "on the 4-view progress evaluations" in text and "(23.50 dB)" in text
    assert "| voxnerf | 120 s, 1.38x |" in text and "| nerfacto | - |" in text
    # without progress evaluations (--eval-every beyond the budget) every curve is the full evaluations'
    full_only = [run("occgrid", [], [(120, 19.0), (300, 20.0)]), run("voxnerf", [], [(120, 21.0), (300, 22.0)])]
    text = "\n".join(error_vs_runtime.ratio_table(full_only, ["interpolation"]))
    assert "on the full evaluations (all views)" in text and "(19.50 dB)" in text
    assert "| voxnerf | ≤120 s, ≥1.75x |" in text


def test_progress_curve_reads_full_evaluations_through_their_progress_views() -> None:
    history = [
        {"elapsed_s": 60.0, "psnr": {"interpolation": 20.0}},
        {"elapsed_s": 120.0, "psnr": {"interpolation": 19.0}, "full": True, "progress_psnr": {"interpolation": 21.0}},
        {"elapsed_s": 150.0, "psnr": {"interpolation": 19.5}, "final": True},  # a run from before progress_psnr
    ]
    curve = error_vs_runtime.progress_curve({"report": {"history": history}}, "interpolation")
    assert curve == [(60.0, 20.0), (120.0, 21.0)]


def test_ratio_bounds_when_the_baseline_starts_above_its_target() -> None:
    assert error_vs_runtime._ratio_cell(30.0, 10.0, False, True) == "30 s, ≤0.33x"
    assert error_vs_runtime._ratio_cell(10.0, 10.0, True, True) == "≤10 s, -"
    assert error_vs_runtime._ratio_cell(25.0, 50.0, False, False) == "25 s, 2.00x"


def test_the_benchmark_room_is_rendered_again_when_an_older_writer_cached_it(tmp_path: Path) -> None:
    scene = error_vs_runtime.make_scene("room", tmp_path, quick=True)
    stamp = (scene / "transforms.json").stat().st_mtime_ns
    assert error_vs_runtime.make_scene("room", tmp_path, quick=True) == scene
    assert (scene / "transforms.json").stat().st_mtime_ns == stamp  # reused
    meta = json.loads((scene / "transforms.json").read_text())
    del meta["synthetic"], meta["voxnerf_synthetic"]["writer"]  # as the writer before version 2 wrote it
    (scene / "transforms.json").write_text(json.dumps(meta))
    error_vs_runtime.make_scene("room", tmp_path, quick=True)
    assert json.loads((scene / "transforms.json").read_text())["synthetic"] is True


def test_the_benchmark_room_is_rendered_again_when_its_spec_changed(tmp_path: Path, monkeypatch) -> None:
    scene = error_vs_runtime.make_scene("room", tmp_path, quick=True)
    sigma = json.loads((tmp_path / "scene.spec.json").read_text())["prior_sigma"]
    other = dataclasses.replace(error_vs_runtime.QUICK_ROOM, prior_sigma=sigma / 2)
    monkeypatch.setattr(error_vs_runtime, "QUICK_ROOM", other)  # as a full room would differ from a quick one
    assert error_vs_runtime.make_scene("room", tmp_path, quick=True) == scene
    assert json.loads((tmp_path / "scene.spec.json").read_text())["prior_sigma"] == sigma / 2
    assert json.loads((scene / "transforms.json").read_text())["prior_sigma"] == sigma / 2


def test_error_vs_runtime_quick(room: Path, tmp_path: Path) -> None:
    out = tmp_path / "evr"
    assert error_vs_runtime.main(["--quick", "--scene", str(room), "--out", str(out)]) == 0
    rows = _read_csv(out / "evaluations.csv")
    configs = ["voxnerf", "occgrid", "uniform"]
    assert {r["config"] for r in rows} == set(configs)
    for config in configs:
        final = [r for r in rows if r["config"] == config and r["final"] == "True"]
        assert {r["split"] for r in final} == {"interpolation", "extrapolation"}, config
        assert all(_finite_psnr(r["psnr"]) for r in final), config
    table = (out / "table.md").read_text()
    assert "Time-to-PSNR ratios against occgrid and uniform" in table
    for config in configs:
        assert f"| {config} |" in table
    assert "vs occgrid, interpolation" in table and "vs uniform, extrapolation" in table
    results = json.loads((out / "results.json").read_text())
    assert [r["name"] for r in results] == configs
    assert all("--no-compile" in r["command"] for r in results)
    assert (out / "psnr_vs_time.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    # --retable rebuilds the same table from results.json alone
    (out / "table.md").unlink()
    assert error_vs_runtime.main(["--retable", "--eval-at", "3", "--out", str(out)]) == 0
    assert (out / "table.md").read_text() == table
    (out / "results.json").write_text("[{}]")
    with pytest.raises(SystemExit):
        error_vs_runtime.main(["--retable", "--out", str(out)])


def test_samples_sweep_quick(room: Path, tmp_path: Path) -> None:
    out = tmp_path / "samples"
    assert samples_sweep.main(["--quick", "--scene", str(room), "--out", str(out)]) == 0
    rows = _read_csv(out / "samples.csv")
    assert [(int(r["n_importance"]), int(r["n_rest"])) for r in rows] == [(4, 2), (8, 4)]
    for r in rows:
        assert int(r["samples_per_ray"]) == int(r["n_importance"]) + int(r["n_rest"])
        assert _finite_psnr(r["psnr_interpolation"]) and _finite_psnr(r["psnr_extrapolation"])
        assert float(r["rays_per_s"]) > 0
        # samples/s counts every sample of every training ray
        expected = float(r["rays_per_s"]) * int(r["samples_per_ray"])
        assert float(r["samples_per_s"]) == pytest.approx(expected, rel=1e-3)
    table = (out / "samples.md").read_text()
    assert "| 4 | 2 | 6 |" in table and "| 8 | 4 | 12 |" in table and "Cheapest pair" in table


def test_prior_noise_sweep_quick(room: Path, tmp_path: Path) -> None:
    out = tmp_path / "noise"
    assert prior_noise_sweep.main(["--quick", "--scene", str(room), "--out", str(out)]) == 0
    rows = _read_csv(out / "prior_noise.csv")
    assert [(float(r["true_noise_m"]), float(r["stated_sigma_m"])) for r in rows] == [
        (0.05, 0.05),
        (0.05, 0.15),
    ]
    assert all(_finite_psnr(r["psnr_interpolation"]) for r in rows)
    for r in rows:
        variant = out / f"noise-{float(r['true_noise_m']):g}-stated-{float(r['stated_sigma_m']):.4g}"
        meta = json.loads((variant / "transforms.json").read_text())
        assert meta["prior_sigma"] == pytest.approx(float(r["stated_sigma_m"]))
        assert meta["voxnerf_prior"]["true_noise"] == pytest.approx(0.05)
    table = (out / "prior_noise.md").read_text()
    assert "| 0.05 | 0.15 | 3 |" in table


def test_sweep_arguments_are_checked() -> None:
    assert samples_sweep.parse_pairs("4:2,64:32") == [(4, 2), (64, 32)]
    assert prior_noise_sweep.parse_settings("0.02:0.3333") == [(0.02, 0.3333)]
    for bad in ("4:0", "4,2", "a:b", ""):
        with pytest.raises(ValueError):
            samples_sweep.parse_pairs(bad)
    for bad in ("0.02:-1", "0:1", "x", "nan:1"):
        with pytest.raises(ValueError):
            prior_noise_sweep.parse_settings(bad)


def test_generated_prior_configs_need_ground_truth(room: Path, tmp_path: Path, capsys) -> None:
    bare = tmp_path / "bare"
    make_priors = importlib.import_module("make_priors")
    points = trimesh.load(room / "gt_mesh.ply", process=False, force="mesh").vertices
    make_priors.write_prior_scene(room, bare, points, 0.05, {"source": "test"})
    (bare / "gt_mesh.ply").unlink()
    with pytest.raises(SystemExit) as exc:
        error_vs_runtime.main(
            ["--scene", str(bare), "--configs", "voxnerf-slam", "--out", str(tmp_path / "o")]
        )
    assert exc.value.code == 2 and "gt_mesh.ply" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        error_vs_runtime.main(["--scene", str(room), "--configs", "voxnerf,nerfacto", "--out", str(tmp_path)])
    assert "unknown configs ['nerfacto']" in capsys.readouterr().err


def _fake_peer_run(scene_dir: Path, out: Path) -> None:
    """A peer's output as benchmarks/peer/nerfacto_run.py writes it: renders at two times (flat grey, then the
    held-out images themselves), timeline.csv and run.json."""
    import numpy as np

    from voxnerf.data.image_io import encode_png, read_rgb, write_atomic
    from voxnerf.data.scene import load_scene

    scene = load_scene(scene_dir, load_images=False)
    for t in ("30", "60"):
        for split in scene.eval_split_names:
            for index in scene.splits[split]:
                frame = scene.frames[index]
                gt = read_rgb(frame.image_path) / 255.0
                image = np.full_like(gt, 0.5) if t == "30" else gt
                path = out / "renders" / f"{t}s" / split / f"{Path(frame.file_path).stem}.png"
                path.parent.mkdir(parents=True, exist_ok=True)
                write_atomic(path, encode_png(image))
    (out / "timeline.csv").write_text("eval_at_s,seconds,iteration,rays_seen\n30,31.5,2,8192\n60,62.0,4,16384\n")
    (out / "run.json").write_text(json.dumps({"command": "nerfacto_run.py ...", "scene": str(scene_dir),
                                              "train_s": 62.0, "iterations": 4}))


def test_peer_results_join_the_table(room: Path, tmp_path: Path) -> None:
    score_renders = importlib.import_module("peer.score_renders")
    peer = tmp_path / "peer"
    _fake_peer_run(room, peer)
    assert score_renders.main([str(room), "--out", str(peer)]) == 0
    rows = _read_csv(peer / "evaluations.csv")
    late = {r["split"]: float(r["psnr"]) for r in rows if r["elapsed_s"] == "62.0"}
    early = {r["split"]: float(r["psnr"]) for r in rows if r["elapsed_s"] == "31.5"}
    assert set(late) == set(early) == {"interpolation", "extrapolation", "test"}
    assert all(late[s] > 60 and 5 < early[s] < 25 for s in late)  # exact images score ~inf (capped), grey low

    out = tmp_path / "evr"
    with pytest.raises(SystemExit):  # a wrong peer directory fails before any training
        error_vs_runtime.main(["--quick", "--scene", str(room), "--configs", "occgrid", "--out", str(out),
                               "--peer", f"nerfacto={tmp_path / 'missing'}"])
    assert not (out / "runs").exists()
    assert error_vs_runtime.main(["--quick", "--scene", str(room), "--configs", "occgrid", "--out", str(out),
                                  "--peer", f"nerfacto={peer}"]) == 0
    table = (out / "table.md").read_text()
    assert "| nerfacto |" in table and "| occgrid |" in table
    assert {r["config"] for r in _read_csv(out / "evaluations.csv")} == {"occgrid", "nerfacto"}
    assert [r["name"] for r in json.loads((out / "results.json").read_text())] == ["occgrid", "nerfacto"]


def test_docs_section_replaces_only_its_marked_text(tmp_path):
    page = tmp_path / "page.md"
    begin, end = docs_section.markers("throughput")
    page.write_text(f"# Title\n\n{begin}\nold table\n{end}\n\nhand-written notes\n")
    docs_section.replace_section(page, "throughput", "new table\n")
    assert page.read_text() == f"# Title\n\n{begin}\nnew table\n{end}\n\nhand-written notes\n"
    with pytest.raises(ValueError, match="page.md.*load-test:begin"):
        docs_section.replace_section(page, "load-test", "x")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["page.md"]


def test_optimizer_step_benchmark_fills_its_section(tmp_path, monkeypatch):
    page = tmp_path / "performance.md"
    begin, end = docs_section.markers("optimizer")
    page.write_text(f"notes\n{begin}\nold\n{end}\n")
    monkeypatch.setattr(sys, "argv", ["optimizer_step.py", "--steps", "1", "--repeats", "1", "--out", str(page)])
    assert optimizer_step.main() == 0
    rows = [line for line in page.read_text().splitlines() if line.startswith("| preset")]
    assert len(rows) == 3 and all(line.endswith("x |") for line in rows)
    assert "old" not in page.read_text() and page.read_text().startswith("notes\n")


def test_depth_sources_variants_drop_the_prior_and_the_depth_without_copying(room: Path, tmp_path: Path) -> None:
    plain = depth_sources.variant_scene(room, tmp_path / "plain", prior=False, depth=False)
    meta = json.loads((plain / "transforms.json").read_text())
    assert not any(key in meta for key in depth_sources.PRIOR_KEYS)
    assert not any("depth_file_path" in f for f in meta["frames"]) and not list(plain.glob("*.ply"))
    image = meta["frames"][0]["file_path"]
    assert (plain / image).stat().st_ino == (room / image).stat().st_ino  # a hard link, not a copy
    kept = json.loads((depth_sources.variant_scene(room, tmp_path / "kept", True, True) / "transforms.json")
                      .read_text())
    assert kept == json.loads((room / "transforms.json").read_text())


def test_depth_sources_quick(room: Path, tmp_path: Path) -> None:
    out = tmp_path / "ds"
    args = [str(room), "--seconds", "120", "--downscale", "1", "--out", str(out), "--train-args",
            "--no-compile --max-iters 3"]
    assert depth_sources.main(args) == 0
    results = json.loads((out / "results.json").read_text())["results"]
    assert list(results) == list(depth_sources.VARIANTS)
    assert "from nerfstudio" not in results["a_prior_file"]["prior"]
    assert results["b_fused_prior"]["prior"].startswith("no prior file; ")
    assert results["c_fused_prior_sensor"]["depth_target"].startswith("depth_source 'sensor'")
    assert results["d_plain"]["prior"].startswith("the scene has no prior and no training frame has a depth map")
    assert all(r["iterations"] == 3 for r in results.values())
    table = (out / "table.md").read_text()
    assert all(f"| {name} | 3 |" in table for name in depth_sources.VARIANTS)


def test_render_speed_table_states_both_paths_their_ratio_and_the_psnr_gap():
    timing = {"fast": {"n": 3, "p50_ms": 100.0, "p95_ms": 120.0}, "full": {"n": 3, "p50_ms": 250.0, "p95_ms": 300.0}}
    results = {
        "environment": {"date": "2026-11-24", "machine": "Linux", "cpus": 2, "torch": "2", "load": "0.1"},
        "poses": 3, "renders": 4, "room_seconds": 60.0,
        "service": {"fast-0": {"n": 4, "p50_ms": 200.0, "p95_ms": 220.0}, "full-1": {"n": 4, "p50_ms": 500.0,
                    "p95_ms": 600.0}, "fast-2": {"n": 4, "p50_ms": 300.0, "p95_ms": 330.0}},
        "scenes": {"room 60 s": {"frame_times": {"320x240": timing}, "psnr": {
            "fast": {"test": 25.1, "seconds": 1.0}, "full": {"test": 25.2, "seconds": 2.0}}}},
    }
    text = render_speed.markdown(results, "cmd")
    assert "| room 60 s | 320x240 in process | 100 / 120 ms | 250 / 300 ms | 2.50x |" in text
    assert "200 / 220 ms then 300 / 330 ms | 500 / 600 ms | 2.00x |" in text  # against the mean of the fast rounds
    assert "| room 60 s | test | 25.100 dB | 25.200 dB | -0.100 dB |" in text and "cmd" in text


def test_service_speed_table_names_the_device_and_says_when_videos_were_left_out():
    def run(rate: float) -> dict:
        return {"steps": 10, "rays_per_s": rate, "psnr": {"interpolation": 20.0, "extrapolation": 15.0},
                "runtime": {"omp_wait_policy": None}, "render_s": [0.2], "overhead_s": [0.05],
                "in_process_render_s": [0.14]}
    results = {
        "environment": {"date": "2026-11-28", "machine": "Linux", "cpus": 16, "load": "0.1", "device": "NVIDIA H200"},
        "rounds": 1, "renders": 1, "video_frames": 0,
        "scenes": [{"label": "room", "paths": {"cli": [run(100.0)], "embedded": [run(95.0)], "redis": [run(90.0)]}}],
    }
    text = service_speed.markdown(results, "cmd")
    assert "device NVIDIA H200" in text and "| room | service, Redis | 10 | 90 | 0.90x |" in text
    assert "| room | embedded | 200 ms | 50 ms | 150 ms | 140 ms | not measured | not measured |" in text


def test_publish_writes_results_and_table_and_the_docs_section_only_when_asked(tmp_path):
    page = tmp_path / "page.md"
    page.write_text("intro\n<!-- s:begin -->\nold\n<!-- s:end -->\n")
    docs_section.publish(tmp_path / "out", {"a": 1}, "| t |", page, "s", write_docs=False)
    assert json.loads((tmp_path / "out" / "results.json").read_text()) == {"a": 1}
    assert (tmp_path / "out" / "table.md").read_text() == "| t |\n" and "old" in page.read_text()
    docs_section.publish(tmp_path / "out", {"a": 1}, "| t |", page, "s", write_docs=True)
    assert "| t |" in page.read_text() and "old" not in page.read_text()


def test_suite_quick_runs_every_config_on_every_room_and_reuses_finished_runs(tmp_path: Path) -> None:
    out = tmp_path / "suite"
    assert suite.main(["--quick", "--out", str(out)]) == 0
    results = json.loads((out / "results.json").read_text())["results"]
    pairs = {(r["scene"], r["config"]) for r in results}
    assert pairs == {(s, c) for s in suite_rooms.QUICK_SUITE for c in suite.QUICK_CONFIGS}
    for r in results:
        assert "--set" in r["command"] or r["config"] == "defaults"
        for split in ("interpolation", "extrapolation"):
            scores = suite.split_scores(r["report"]["metrics"])[split]
            assert _finite_psnr(str(scores["psnr"])) and _finite_psnr(str(scores["half_psnr"]))
    table = (out / "table.md").read_text()
    assert "| distortion | 1 |" in table and "mean over the tuning half** (quick_plain)" in table
    assert "mean over the confirmation half** (quick_capture)" in table and "| distortion | 1 | " in table
    written = json.loads((out / "results.json").read_text())
    assert written["halves"] == {"quick_plain": "tuning", "quick_capture": "confirmation"}
    assert [v["config"] for v in written["verdicts"]] == ["distortion"]
    said = written["verdicts"][0]["verdict"]
    assert said in ("adopt", "keep") and f"| **{said}**: " in table
    placement_table = out / "placement.md"
    assert sample_placement.main(["--runs", str(out / "runs"), "--scene", "quick_plain", "--scene-dir",
                                  str(out / "scenes" / "quick_plain"), "--configs", "defaults,distortion",
                                  "--max-views", "2", "--out", str(placement_table)]) == 0
    rows = [line for line in placement_table.read_text().splitlines() if line.startswith("| d")]
    assert [r.split(" | ")[0] for r in rows] == ["| defaults", "| distortion"] and "%" in rows[0]
    assert ("| rays stopping short | their share of the colour error | rays passing their surface | their share "
            "of the error |") in placement_table.read_text()
    stop_short, _, passing, _ = rows[0].split(" | ")[-4:]
    assert stop_short.endswith("%") and passing.endswith("%")  # voxnerf sampler's runs: where first hits fall
    geometry_table = out / "geometry.md"
    assert suite_geometry.main(["--runs", str(out / "runs"), "--scene", "quick_plain", "--scene-dir",
                                str(out / "scenes" / "quick_plain"), "--configs", "defaults,no-such-config",
                                "--max-views", "1", "--voxel-size", "0.05", "--out", str(geometry_table)]) == 0
    cells = geometry_table.read_text().splitlines()[-1].split(" | ")
    assert cells[0] == "| defaults" and 0.0 <= float(cells[1]) <= 1.0 and all(float(c) >= 0 for c in cells[2:-1])
    stamp = (out / "runs" / "quick_plain" / "defaults" / "suite-run.json").stat().st_mtime_ns
    assert suite.main(["--quick", "--out", str(out), "--configs", "defaults"]) == 0  # reused, not trained again
    assert (out / "runs" / "quick_plain" / "defaults" / "suite-run.json").stat().st_mtime_ns == stamp


def test_suite_summary_compares_with_defaults_and_counts_losing_scenes() -> None:
    def run(scene, config, interp, extrap):
        metrics = {"interpolation": {"psnr": interp, "ssim": 0.5}, "extrapolation": {"psnr": extrap, "ssim": 0.5}}
        return {"scene": scene, "config": config, "report": {"metrics": metrics, "iteration": 1}}

    results = [run("a", "defaults", 30.0, 20.0), run("b", "defaults", 25.0, 18.0),
               run("a", "distortion", 31.0, 20.1), run("b", "distortion", 24.0, 18.5)]
    rows = suite.summary_rows(results, ["a", "b"], "psnr")
    assert rows[0] == "| defaults | 2 | 27.50 | +0.00 | +0.00 | 0 | 19.00 | +0.00 | +0.00 | 0 |"
    assert rows[1] == "| distortion | 2 | 27.50 | +0.00 | -1.00 | 1 | 19.30 | +0.30 | +0.10 | 0 |"


def test_the_suite_split_is_fixed_and_each_half_spans_the_variety() -> None:
    rooms = suite_rooms.SUITE
    assert set(suite.HALVES) == {*rooms, suite.REDKITCHEN, suite.RECORD3D}
    assert suite.HALVES == {
        "studio": "tuning", "office": "tuning", "capture_lounge": "tuning", "gallery": "tuning", "hall": "tuning",
        "capture_bedroom": "tuning", "redkitchen": "tuning",
        "loft": "confirmation", "den": "confirmation", "capture_kitchen": "confirmation", "attic": "confirmation",
        "library": "confirmation", "capture_study": "confirmation", "record3d_kitchen": "confirmation"}
    for half in (suite.TUNING, suite.CONFIRMATION):
        specs = [rooms[name] for name, h in suite.HALVES.items() if h == half and name in rooms]
        assert len(specs) >= 6, half
        assert {s.prior_kind for s in specs} == {"points", "mesh"}, half
        assert sum(s.gi_bounces > 0 and s.noise_photons > 0 for s in specs) >= 2, half
        sigmas = [s.prior_sigma for s in specs]
        assert min(sigmas) <= 0.015 and max(sigmas) >= 0.04, half
        fovs = [s.hfov_deg for s in specs]
        assert min(fovs) < 60 and max(fovs) >= 95, half
        assert {s.width for s in specs} >= {176, 192, 200}, half
    assert set(suite.QUICK_HALVES) == {*suite_rooms.QUICK_SUITE, *suite.REAL_SCANS}
    assert set(suite.QUICK_HALVES.values()) == {suite.TUNING, suite.CONFIRMATION}


def _made_up(changes: dict[str, tuple[float, float]], config: str = "candidate") -> list[dict]:
    """Runs of ``defaults`` (30 / 20 dB) and of ``config`` (changed by ``changes[scene]``) on each scene."""
    def run(scene, name, interp, extrap):
        metrics = {split: {"psnr": psnr, "ssim": 0.5, "half": {"psnr": psnr - 1.0, "ssim": 0.5}}
                   for split, psnr in (("interpolation", interp), ("extrapolation", extrap))}
        return {"scene": scene, "config": name, "report": {"metrics": metrics, "iteration": 1}}

    return [r for scene, (di, de) in changes.items()
            for r in (run(scene, "defaults", 30.0, 20.0), run(scene, config, 30.0 + di, 20.0 + de))]


HALVES = {"t1": "tuning", "t2": "tuning", "c1": "confirmation", "c2": "confirmation"}


def test_the_verdict_adopts_only_a_tuning_win_that_holds_on_every_confirmation_scene() -> None:
    wins = {"t1": (0.4, 0.6), "t2": (0.2, -0.1)}
    adopt = suite.verdict(_made_up(wins | {"c1": (0.1, 0.5), "c2": (-0.29, 0.2)}), HALVES, "candidate")
    assert adopt["verdict"] == "adopt" and adopt["why"].startswith("wins on the tuning half (+0.30 / +0.25 dB)")
    assert adopt["tuning"]["interpolation"] == pytest.approx(0.3) and adopt["tuning"]["scenes"] == 2
    assert adopt["confirmation"]["worst"] == {"scene": "c2", "split": "interpolation",
                                              "change": pytest.approx(-0.29)}
    loses = suite.verdict(_made_up(wins | {"c1": (0.1, 0.55), "c2": (0.3, -0.31)}), HALVES, "candidate")
    assert loses["verdict"] == "keep" and loses["why"].endswith("but c2 loses 0.31 dB of extrapolation")
    assert loses["confirmation"]["extrapolation"] == pytest.approx(0.12)  # a good mean does not save it
    no_win = suite.verdict(_made_up({"t1": (0.5, -0.6), "t2": (0.0, 0.0), "c1": (1, 1), "c2": (1, 1)}), HALVES,
                           "candidate")
    assert no_win["verdict"] == "keep" and no_win["why"] == "does not win on the tuning half (+0.25 / -0.30 dB)"
    split_loses = suite.verdict(_made_up({"t1": (2.0, -0.8), "t2": (2.0, -0.8), "c1": (1, 1), "c2": (1, 1)}),
                                HALVES, "candidate")
    assert split_loses["verdict"] == "keep"  # a gain on one split does not buy a loss beyond the noise on the other
    missing = suite.verdict(_made_up(wins | {"c1": (0.1, 0.5)}), HALVES, "candidate")
    assert missing["verdict"] == "keep" and missing["why"] == "incomplete: no run on c2"
    rows = suite.verdict_rows([loses])
    assert rows == ["| candidate | 2 | +0.30 | +0.25 | 2 | +0.20 | +0.12 | c2 extrap. -0.31 | **keep**: wins on the "
                    "tuning half (+0.30 / +0.25 dB) but c2 loses 0.31 dB of extrapolation |"]


def test_the_docs_table_leaves_every_run_to_table_md(tmp_path: Path) -> None:
    results = _made_up({"t1": (0.4, 0.6), "c1": (0.1, 0.5)}, config="sampler-grid")
    halves = {"t1": "tuning", "c1": "confirmation"}
    full = suite.table(results, ["t1", "c1"], halves, 300, None, "CMD")
    short = suite.table(results, ["t1", "c1"], halves, 300, None, "CMD", every_run=False)
    assert "**Every run**" in full and "| sampler-grid | c1 |" in full
    assert "**Every run**" not in short and "| sampler-grid | c1 |" not in short
    assert short.endswith("`table.md` in the command's `--out`.\n")
    assert "half-image PSNR (dB), mean" in full and "half-image PSNR (dB), mean" not in short
    head, kept = short.split("The half-image PSNR means")[0].split("\n\n", 1)
    assert "as the budget table of `table.md` shows" in head and "as the budget table shows" in full
    assert "PSNR (dB), all views, mean over the confirmation half" in kept and "**Verdicts" in kept
    assert all(block in full for block in kept.split("\n\n"))  # the same all-view means and verdicts
    page = tmp_path / "page.md"
    page.write_text("<!-- s:begin -->\n<!-- s:end -->\n")
    docs_section.publish(tmp_path / "out", {}, full, page, "s", write_docs=True, docs_text=short)
    assert (tmp_path / "out" / "table.md").read_text() == full + "\n"
    assert page.read_text() == "<!-- s:begin -->\n" + short.strip("\n") + "\n<!-- s:end -->\n"


def test_suite_geometry_needs_a_true_mesh(tmp_path: Path, capsys) -> None:
    assert suite_geometry.main(["--runs", str(tmp_path), "--scene", "x", "--scene-dir", str(tmp_path)]) == 2
    assert "gt_mesh.ply: no true mesh" in capsys.readouterr().err


def test_suite_runs_scene_by_scene_and_redkitchen_by_name(tmp_path: Path, monkeypatch) -> None:
    calls, extras = [], []

    def fake_run_one(scene, scene_dir, config, run, budget, eval_at, extra):
        calls.append((scene, config))
        extras.append(extra)
        metrics = {s: {"psnr": 20.0, "ssim": 0.5} for s in ("interpolation", "extrapolation")}
        run.mkdir(parents=True)
        (run / "suite-run.json").write_text(json.dumps({"scene": scene, "config": config, "command": "c",
                                                        "report": {"metrics": metrics, "iteration": 1}}))

    monkeypatch.setattr(suite, "run_one", fake_run_one)
    kitchen = tmp_path / "kitchen"
    out = tmp_path / "out"
    argv = ["--quick", "--out", str(out), "--redkitchen", str(kitchen), "--configs", "previous-defaults,defaults"]
    assert suite.main([*argv, "--scenes", "quick_plain,redkitchen"]) == 0
    assert calls == [("quick_plain", "previous-defaults"), ("quick_plain", "defaults"),
                     ("redkitchen", "previous-defaults"), ("redkitchen", "defaults")]  # a scene's runs together
    calls.clear()
    assert suite.main([*argv, "--out", str(tmp_path / "alone"), "--scenes", "redkitchen"]) == 0
    assert calls == [("redkitchen", "previous-defaults"), ("redkitchen", "defaults")]  # no synthetic room
    results = json.loads((tmp_path / "alone" / "results.json").read_text())["results"]
    assert {r["scene"] for r in results} == {"redkitchen"}
    assert "incomplete: a half has no scene in this run" in (tmp_path / "alone" / "table.md").read_text()
    calls.clear()  # the real scans' flags given, a --scenes list that names neither: neither runs
    assert suite.main([*argv, "--out", str(tmp_path / "rooms"), "--record3d-kitchen", "--scenes", "quick_plain"]) == 0
    assert calls == [("quick_plain", "previous-defaults"), ("quick_plain", "defaults")]
    extras.clear()
    assert suite.main([*argv, "--out", str(tmp_path / "steps"), "--scenes", "redkitchen", "--max-iters", "7"]) == 0
    assert extras and all(extra[-2:] == ["--max-iters", "7"] for extra in extras)
    assert "or 7 steps, whichever comes first" in (tmp_path / "steps" / "table.md").read_text()


FAKE_VOXNERF_MAIN = """
import json, pathlib, sys
argv = sys.argv[1:]
with open(pathlib.Path(__file__).parent / "calls.txt", "a") as f:
    f.write(" ".join(argv) + "\\n")
run = pathlib.Path(argv[argv.index("--out") + 1])
run.mkdir(parents=True, exist_ok=True)
metrics = {s: {"psnr": 11.5, "ssim": 0.5} for s in ("interpolation", "extrapolation")}
(run / "report.json").write_text(json.dumps({"metrics": metrics, "iteration": 77}))
"""


def test_a_tree_runs_its_own_voxnerf_and_its_record_names_the_commit(tmp_path: Path) -> None:
    tree = tmp_path / "tree"
    (tree / "voxnerf").mkdir(parents=True)
    (tree / "voxnerf" / "__init__.py").write_text("")
    (tree / "voxnerf" / "__main__.py").write_text(FAKE_VOXNERF_MAIN)
    git = ["git", "-C", str(tree), "-c", "user.name=t", "-c", "user.email=t@t"]
    for cmd in (["init", "-q"], ["add", "voxnerf"], ["commit", "-q", "-m", "old"]):
        subprocess.run([*git, *cmd], check=True)
    commit = subprocess.run([*git, "rev-parse", "HEAD"], check=True, capture_output=True, text=True).stdout.strip()
    out = tmp_path / "out"
    argv = ["--out", str(out), "--scenes", "redkitchen", "--redkitchen", str(tmp_path / "kitchen"),
            "--configs", "old", "--tree", f"old={tree}"]
    assert suite.main(argv) == 0
    calls = (tree / "voxnerf" / "calls.txt").read_text().splitlines()
    assert len(calls) == 2 and "--max-iters 2" in calls[0] and "--max-iters" not in calls[1]  # warm-up, then timed
    record = json.loads((out / "runs" / "redkitchen" / "old" / "suite-run.json").read_text())
    assert record["report"]["iteration"] == 77  # the tree's voxnerf wrote it, not this checkout's
    assert record["command"].startswith(f"PYTHONPATH={tree} voxnerf train ")
    assert record["tree"] == {"path": str(tree), "commit": commit}
    assert "| old | redkitchen | 11.50 / 0.500" in (out / "table.md").read_text()
    assert suite.tree_commit(tmp_path / "kitchen") is None  # not a git checkout


@pytest.mark.parametrize(("tree", "message"), [
    ("old", "--tree wants NAME=DIR, got 'old'"),
    ("defaults=.", "--tree defaults: the name is taken; give the tree another"),
    ("old=/nonexistent", "--tree old: /nonexistent holds no voxnerf package (voxnerf/__init__.py)"),
])
def test_suite_refuses_a_bad_tree(tree: str, message: str, capsys) -> None:
    with pytest.raises(SystemExit):
        suite.main(["--out", "/nonexistent", "--tree", tree])
    assert message in capsys.readouterr().err


def test_suite_needs_the_redkitchen_directory_when_its_scenes_name_it(capsys) -> None:
    with pytest.raises(SystemExit):
        suite.main(["--out", "/nonexistent", "--scenes", "studio,redkitchen"])
    assert "--scenes names redkitchen: give its scene directory with --redkitchen" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        suite.main(["--out", "/nonexistent", "--scenes", "studio,record3d_kitchen"])
    assert "--scenes names record3d_kitchen: add --record3d-kitchen" in capsys.readouterr().err


def test_suite_refuses_unknown_configs(capsys) -> None:
    with pytest.raises(SystemExit):
        suite.main(["--out", "/nonexistent", "--configs", "defaults,warp-drive"])
    assert "unknown configs ['warp-drive']" in capsys.readouterr().err


@pytest.mark.parametrize("name", sorted(suite.CONFIGS))
def test_every_suite_row_is_a_valid_training_config(name: str) -> None:
    from voxnerf.config import TrainConfig

    overrides = suite.CONFIGS[name]
    cfg = TrainConfig(**overrides)  # a misspelt field or a refused value raises
    # JSON, as `--set` passes them (tuples: lists)
    kept = {name: value for name, value in json.loads(json.dumps(cfg.flat())).items() if name in overrides}
    assert kept == json.loads(json.dumps(overrides))


def test_pose_views_scores_held_out_views_at_given_and_moved_poses(room: Path, tmp_path: Path, capsys) -> None:
    from voxnerf.config import TrainConfig
    from voxnerf.training.run import train

    cfg = TrainConfig(max_iters=8, compile=False, device="cpu", rays_per_batch=256, hash_levels=4,
                      hash_log2_size=10, hidden_dim=16, final_eval=False, pose_refinement="so3xr3", pose_lr=0.01)
    train(room, tmp_path / "run", cfg, progress_bar=False)
    out = tmp_path / "pose_views.json"
    assert pose_views.main([str(tmp_path / "run"), str(room), "--every", "4", "--out", str(out)]) == 0
    splits = json.loads(out.read_text())["splits"]
    assert set(splits) == {"interpolation", "extrapolation"}
    for r in splits.values():
        assert r["views"] >= 1 and 0 < r["given"] < 100 and 0 < r["moved"] < 100 and r["given"] != r["moved"]
    assert "at the moved poses" in capsys.readouterr().out
    train(room, tmp_path / "plain", cfg.model_copy(update={"pose_refinement": "none"}), progress_bar=False)
    assert pose_views.main([str(tmp_path / "plain"), str(room)]) == 2
    assert "did not refine its poses" in capsys.readouterr().err


def test_step_profile_times_every_phase_and_traces_the_steps_after_the_warm_ones(room: Path, tmp_path: Path,
                                                                                 capsys) -> None:
    out = tmp_path / "profile.json"
    args = [str(room), "--steps", "2", "--warm", "1", "--trace", "1", "--json", str(out),
            "--config", 'eager={"compile": false, "rays_per_batch": 64}']
    assert step_profile.main(args) == 0
    row = json.loads(out.read_text())["rows"]["eager"]
    phases = row["phases_ms"]
    assert {"batch (rays, sampling)", "forward + backward", "optimiser update"} <= set(phases)
    assert all(ms >= 0 for ms in phases.values()) and phases["forward + backward"] > 0
    assert row["step_ms"] == pytest.approx(sum(phases.values()))
    core = ("batch (rays, sampling)", "forward + backward", "optimiser update")
    assert [row["phase_calls"][name] for name in core] == [2, 2, 2]  # the two timed steps, no warm or traced one
    assert row["config"]["rays_per_batch"] == 64 and row["config"]["max_iters"] == 4
    assert row["octree_misses"] == "gather" and row["host_syncs_per_step"] is None  # a CPU: nothing counted
    assert "Self CPU" in row["trace"] and "## eager on cpu (octree misses: gather)" in capsys.readouterr().out


def test_gpu_check_measures_both_sampler_paths_side_by_side(room: Path, tmp_path: Path) -> None:
    """The GPU check's dry run on a CPU (scripts/gpu_check.sh runs it on a GPU): step profile and throughput of
    each octree-miss path, render latency of each size in passes of the device's chunk, all in its JSON and
    tables."""
    out = tmp_path / "check"
    args = [str(room), "--out", str(out), "--device", "cpu", "--downscale", "1", "--steps", "1", "--warm", "1",
            "--train-seconds", "4", "--renders", "1", "--presets", "cpu", "--overrides", '{"compile": false}']
    assert gpu_check.main(args) == 0
    results = json.loads((out / "gpu_check.json").read_text())
    assert list(results["step_profile"]) == list(results["throughput"]) == ["cpu, gather", "cpu, mask"]
    assert [row["octree_misses"] for row in results["step_profile"].values()] == ["gather", "mask"]
    assert [row["octree_misses"] for row in results["throughput"].values()] == ["gather", "mask"]
    assert list(results["render"]) == ["cpu, 320x240, chunk 4096", "cpu, 640x480, chunk 4096"]  # a CPU: one chunk
    assert all(row["path"] == "fast" and row["median_ms"] > 0 for row in results["render"].values())
    table = (out / "gpu_check.md").read_text()
    assert "| cpu, mask |" in table and "| cpu, 640x480, chunk 4096 | fast |" in table


def test_step_profile_refuses_a_config_that_is_not_a_json_object(capsys) -> None:
    with pytest.raises(SystemExit):
        step_profile.main(["scene", "--config", "paper=[1]"])
    assert "expected a JSON object" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        step_profile.main(["scene", "--config", "paper"])
    assert "expected NAME=JSON" in capsys.readouterr().err


def test_the_budget_table_counts_the_steps_as_the_report_charges_them():
    stages = [{"name": "load_scene", "seconds": 1.0}, {"name": "octree", "seconds": 4.0},
              {"name": "compile", "seconds": 5.0}, {"name": "progress_evals", "seconds": 6.0},
              {"name": "train", "seconds": 291.6}, {"name": "final_eval", "seconds": 14.0}]
    budget = {"seconds": {"training": 291.6, "progress_evals": 6.0, "checkpoints": 2.4, "compile": 5.0}}
    run = {"scene": "office", "config": suite.BASELINE, "report": {"stages": stages, "budget": budget,
                                                                   "wall_seconds": 331.0}}
    (row,) = suite.budget_rows([run], ["office"])
    assert row == "| office | 5.0 | 5.0 | 6.0 | 291.6 | 14.0 | 331.0 |"  # not 291.6 - 5 - 6 again
    older = {**run, "report": {"stages": [*stages[:4], {"name": "train", "seconds": 302.6}, stages[5]],
                               "wall_seconds": 331.0}}  # before budget.seconds: train held compile and evals
    assert suite.budget_rows([older], ["office"]) == [row]


def test_a_record_made_before_it_kept_the_budget_takes_it_from_its_report(tmp_path):
    record = tmp_path / "suite-run.json"
    record.write_text(json.dumps({"scene": "office", "config": "defaults", "report": {"stages": []}}))
    assert suite.load_result(record)["report"] == {"stages": []}  # no report.json beside it: as it was
    (tmp_path / "report.json").write_text(json.dumps({"budget": {"seconds": {"training": 291.6}}}))
    assert suite.load_result(record)["report"]["budget"] == {"seconds": {"training": 291.6}}
    assert "budget" in suite.REPORT_KEYS  # and a new record keeps it
