"""``voxnerf render``: pose files, output files, and one-line errors that leave nothing behind."""

from __future__ import annotations

import json

import imageio.v3 as iio
import numpy as np
import pytest
from synthetic_fixtures import make_micro_scene
from tiny_run import DEFAULT_INTRINSICS, DEPTH_UNIT_SCALE, write_tiny_run

from voxnerf.cli import MAX_RENDER_PIXELS, main
from voxnerf.data.image_io import decode_exr, read_png_header
from voxnerf.inference.encoding import encode_outputs
from voxnerf.inference.render import load_model, render


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    return write_tiny_run(tmp_path_factory.mktemp("tiny") / "run")


def _pose(z: float = 3.0) -> list[list[float]]:
    pose = np.eye(4)
    pose[2, 3] = z
    return pose.tolist()


def _render(run, tmp_path, pose_doc, out_name="view.png", *flags) -> int:
    pose_file = tmp_path / "pose.json"
    pose_file.write_text(pose_doc if isinstance(pose_doc, str) else json.dumps(pose_doc))
    return main(["render", str(run), "--pose", str(pose_file), "--out", str(tmp_path / "out" / out_name),
                 "--device", "cpu", *flags])


def test_png_render_writes_rgb_and_optionally_depth_and_gray_opacity(run, tmp_path, capsys):
    assert _render(run, tmp_path, {"transform_matrix": _pose()}, "view.png", "--depth", "--opacity") == 0
    out = tmp_path / "out"
    assert sorted(p.name for p in out.iterdir()) == ["view.png", "view_depth.png", "view_opacity.png"]
    h, w = DEFAULT_INTRINSICS.height, DEFAULT_INTRINSICS.width
    rgb = iio.imread(out / "view.png")
    assert rgb.shape == (h, w, 3) and rgb.dtype == np.uint8
    assert read_png_header(out / "view_depth.png")[2:] == (16, 0)  # 16-bit gray
    assert read_png_header(out / "view_opacity.png")[2:] == (8, 0)  # 8-bit gray, one channel
    assert iio.imread(out / "view_opacity.png").shape == (h, w)
    # the same bytes as the Python API's render encoded by voxnerf.inference.encoding
    images = render(load_model(run, "cpu"), np.asarray(_pose()))
    for name, file in (("rgb", "view.png"), ("depth", "view_depth.png"), ("opacity", "view_opacity.png")):
        assert (out / file).read_bytes() == encode_outputs(images, "png", [name], DEPTH_UNIT_SCALE), name
    printed = capsys.readouterr().out
    assert "view_depth.png" in printed and "view_opacity.png" in printed and f"({w}x{h})" in printed


def test_png_render_without_flags_writes_one_file(run, tmp_path):
    assert _render(run, tmp_path, {"transform_matrix": _pose()}) == 0
    assert [p.name for p in (tmp_path / "out").iterdir()] == ["view.png"]


def test_exr_render_holds_the_asked_channels_at_the_asked_size(run, tmp_path):
    doc = {"transform_matrix": _pose(), "w": 8, "h": 6}
    assert _render(run, tmp_path, doc, "view.exr", "--opacity") == 0
    channels = decode_exr((tmp_path / "out" / "view.exr").read_bytes())
    assert sorted(channels) == ["A", "B", "G", "R"] and channels["A"].shape == (6, 8)


def test_given_intrinsics_are_used(run, tmp_path):
    """Explicit fl/cx/cy (a negative cx included, as POST /render allows) at a new size."""
    doc = {"transform_matrix": _pose(), "w": 8, "h": 6, "fl_x": 5.0, "fl_y": 5.0, "cx": -2.0, "cy": 3.0}
    assert _render(run, tmp_path, doc, "view.png") == 0
    assert iio.imread(tmp_path / "out" / "view.png").shape == (6, 8, 3)


def test_slightly_skewed_pose_is_repaired_as_the_rest_api_does(run, tmp_path):
    pose = _pose()
    pose[0][1] = 1e-3
    assert _render(run, tmp_path, {"transform_matrix": pose}) == 0


@pytest.mark.parametrize(
    ("doc", "where", "needle"),
    [
        ("{not json", "", "cannot read pose JSON"),
        ([1, 2], "transform_matrix", "missing"),
        ({"w": 8}, "transform_matrix", "missing"),
        ({"transform_matrix": np.diag([2.0, 1, 1, 1]).tolist()}, "transform_matrix", "not a proper orthonormal"),
        ({"transform_matrix": np.diag([-1.0, 1, 1, 1]).tolist()}, "transform_matrix", "det = -1"),
        ({"transform_matrix": (np.eye(4) * 2).tolist()}, "transform_matrix", "last row"),
        ({"transform_matrix": np.eye(3).tolist()}, "transform_matrix", "4x4"),
        ({"transform_matrix": "eye"}, "transform_matrix", "4x4"),
        ({"transform_matrix": [[True, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]}, "transform_matrix",
         "numbers"),
        ('{"transform_matrix": [[NaN, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]}', "transform_matrix",
         "NaN or inf"),
        ({"transform_matrix": _pose(), "w": 8}, "w, h", "together"),
        ({"transform_matrix": _pose(), "h": 6}, "w, h", "together"),
        ({"transform_matrix": _pose(), "w": 8.5, "h": 6}, "w", "positive integer"),
        ({"transform_matrix": _pose(), "w": 8, "h": 0}, "h", "positive integer"),
        ({"transform_matrix": _pose(), "w": 8, "h": True}, "h", "positive integer"),
        ({"transform_matrix": _pose(), "fl_x": -3}, "fl_x", "positive finite"),
        ({"transform_matrix": _pose(), "fl_y": "20"}, "fl_y", "positive finite"),
        ({"transform_matrix": _pose(), "cx": [1]}, "cx", "finite number"),
        ('{"transform_matrix": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]], "cy": Infinity}', "cy",
         "finite number"),
        ({"transform_matrix": _pose(), "w": 10_000, "h": 10_000}, "w, h", f"limit of {MAX_RENDER_PIXELS}"),
    ],
)
def test_bad_pose_files_are_one_line_naming_file_and_field_and_write_nothing(run, tmp_path, capsys, doc, where,
                                                                             needle):
    assert _render(run, tmp_path, doc, "view.png", "--depth") == 2
    err = capsys.readouterr().err
    pose_file = tmp_path / "pose.json"
    prefix = f"voxnerf: error: {pose_file}: {where + ': ' if where else ''}"
    assert err.count("\n") == 1 and err.startswith(prefix), err
    assert needle in err, err
    assert not (tmp_path / "out").exists()


def test_bad_output_name_is_refused_before_anything_runs(tmp_path, capsys):
    assert main(["render", str(tmp_path / "no-run"), "--pose", "p.json", "--out", str(tmp_path / "x.jpg")]) == 2
    err = capsys.readouterr().err
    assert err == f"voxnerf: error: {tmp_path / 'x.jpg'}: output must end in .png or .exr\n"


def test_unreadable_checkpoint_is_one_line(tmp_path, capsys):
    (tmp_path / "run").mkdir()
    (tmp_path / "run" / "checkpoint.pt").write_bytes(b"garbage")
    assert main(["render", str(tmp_path / "run"), "--pose", "p.json", "--out", str(tmp_path / "o" / "x.png")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "checkpoint.pt: unreadable checkpoint" in err
    assert not (tmp_path / "o").exists()


def test_train_config_takes_the_flags_and_set_by_flat_or_dotted_name_over_them(tmp_path):
    from voxnerf.cli import build_parser, train_config

    args = build_parser().parse_args([
        "train", str(tmp_path), "--out", str(tmp_path / "r"), "--max-iters", "3", "--samples", "8,4",
        "--set", "lr_schedule=budget", "--set", "model.sh_bands=2", "--set", "sampling.n_importance=6",
        "--set", "eval_at=[5, 10]",
    ])
    cfg = train_config(args)
    assert cfg.run.max_iters == 3 and cfg.schedule.lr_schedule == "budget" and cfg.model.sh_bands == 2
    assert (cfg.sampling.n_importance, cfg.sampling.n_rest) == (6, 4)  # --set wins over --samples
    assert cfg.evaluation.eval_at == [5.0, 10.0]


def test_a_set_of_an_unknown_dotted_name_is_a_one_line_error(tmp_path, capsys):
    from voxnerf.cli import main

    code = main(["train", str(tmp_path), "--out", str(tmp_path / "r"), "--max-iters", "1", "--set", "model.lr=0.1"])
    assert code == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "model.lr" in err


def test_train_prints_the_set_up_decisions_with_the_sampler_auto_chose(tmp_path_factory, tmp_path, capsys):
    scene = make_micro_scene(tmp_path_factory, "cli_train")
    small = ["--set", "hash_levels=4", "--set", "hash_log2_size=10", "--set", "hidden_dim=16"]
    assert main(["train", str(scene), "--out", str(tmp_path / "r"), "--max-iters", "2", "--no-compile",
                 "--device", "cpu", "--eval-every", "100000", *small]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert any(line.startswith("prior: ") for line in lines)
    check = [line for line in lines if line.startswith("window_check: ")]
    assert len(check) == 1 and "sampler 'auto': voxnerf" in check[0]
    chosen = json.loads((tmp_path / "r" / "report.json").read_text())["window_check"]["sampler"]["chosen"]
    assert chosen == "voxnerf"


def test_synth_with_too_few_frames_is_a_one_line_error_writing_nothing(tmp_path, capsys):
    assert main(["synth", str(tmp_path / "room"), "--frames", "24"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("voxnerf: error: voxnerf synth --frames 24: only 0 training frame")
    assert not (tmp_path / "room").exists()
