"""voxnerf.inference.render: loading a run and rendering a pose, on an untrained model written directly (no
training)."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from tiny_run import DEFAULT_INTRINSICS, DEPTH_UNIT_SCALE, write_tiny_run

from voxnerf.cameras.rules import Intrinsics, Lens, validate_pose
from voxnerf.errors import RenderStopped, RunError
from voxnerf.inference.encoding import OUTPUT_NAMES
from voxnerf.inference.render import (
    CHECKPOINT,
    OUTPUTS,
    PIXEL_RAYS,
    PixelSet,
    load_model,
    render,
    render_normalized,
    render_pixel_sets,
    render_pixels,
)


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    return load_model(write_tiny_run(tmp_path_factory.mktemp("tiny") / "run"), "cpu")


def _pose(z: float = 3.0) -> np.ndarray:
    pose = np.eye(4)
    pose[2, 3] = z  # looking along -Z at the box around the origin
    return pose


def test_load_model_reads_the_default_camera_and_depth_unit(trained):
    assert trained.default_intrinsics == DEFAULT_INTRINSICS
    assert trained.depth_unit_scale == DEPTH_UNIT_SCALE and trained.iteration == 0
    assert not trained.model.field.training


def test_missing_checkpoint_is_a_run_error(tmp_path):
    with pytest.raises(RunError, match="no checkpoint"):
        load_model(tmp_path, "cpu")


@pytest.mark.parametrize(
    "content",
    [b"", b"not a checkpoint at all", "list", "no_model", "no_intrinsics", "bad_weights"],
)
def test_unreadable_checkpoints_are_one_line_run_errors(tmp_path, content):
    path = tmp_path / CHECKPOINT
    if isinstance(content, bytes):
        path.write_bytes(content)
    else:
        write_tiny_run(tmp_path)
        state = torch.load(path, weights_only=False)
        if content == "list":
            state = [1, 2, 3]
        elif content == "no_model":
            del state["model"]
        elif content == "no_intrinsics":
            del state["default_intrinsics"]
        else:
            state["model"]["field"] = {"nonsense": torch.zeros(2)}
        torch.save(state, path)
    with pytest.raises(RunError) as info:
        load_model(tmp_path, "cpu")
    message = str(info.value)
    assert message.startswith(f"{path}: unreadable checkpoint") and "\n" not in message, message


def test_render_default_camera_gives_every_output(trained):
    out = render(trained, _pose())
    assert set(out) == set(OUTPUTS) == set(OUTPUT_NAMES)
    h, w = DEFAULT_INTRINSICS.height, DEFAULT_INTRINSICS.width
    assert out["rgb"].shape == (h, w, 3) and out["depth"].shape == (h, w) and out["opacity"].shape == (h, w)
    assert all(v.dtype == np.float32 for v in out.values())
    assert ((out["rgb"] >= 0) & (out["rgb"] <= 1)).all()
    assert ((out["opacity"] >= 0) & (out["opacity"] <= 1 + 1e-6)).all()
    # the box is [-2, 2]^3 in scene units and the camera 3 units from its centre: depth within [1, 5]
    assert np.isfinite(out["depth"]).all() and (out["depth"] >= 1 - 1e-4).all() and (out["depth"] <= 5).all()


def test_render_computes_only_the_outputs_asked_for(trained):
    intr = Intrinsics(fl_x=10.0, fl_y=10.0, cx=4.0, cy=3.0, width=8, height=6)
    out = render(trained, _pose(), intr, ("depth",))
    assert list(out) == ["depth"] and out["depth"].shape == (6, 8)


def test_render_accepts_a_tensor_pose_and_matches_the_array(trained):
    a = render(trained, _pose(), outputs=("rgb",))
    b = render(trained, torch.from_numpy(_pose()).float(), outputs=("rgb",))
    np.testing.assert_allclose(a["rgb"], b["rgb"], atol=1e-6)


def test_unknown_output_is_a_run_error(trained):
    with pytest.raises(RunError, match="unknown outputs"):
        render(trained, _pose(), outputs=("normals",))


@pytest.mark.parametrize(
    ("pose", "needle"),
    [
        (np.diag([2.0, 1, 1, 1]), "not a proper orthonormal"),  # refused by POST /render too
        (np.diag([-1.0, 1, 1, 1]), "det = -1"),
        (np.eye(4) * 2, "last row"),
        (np.eye(3), "4x4"),
        (np.full((4, 4), np.nan), "NaN or inf"),
        ([[True, False, False, False], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]], "numbers"),
    ],
)
def test_bad_poses_are_refused_like_the_rest_api_refuses_them(trained, pose, needle):
    with pytest.raises(RunError) as info:
        render(trained, pose)
    assert str(info.value).startswith("c2w: ") and needle in str(info.value), str(info.value)


def test_slightly_skewed_pose_renders_as_its_repaired_rotation(trained):
    skewed = _pose()
    skewed[0, 1] = 1e-3
    a = render(trained, skewed, outputs=("rgb",))
    b = render(trained, validate_pose(skewed), outputs=("rgb",))
    np.testing.assert_array_equal(a["rgb"], b["rgb"])


# ------------------------------------------------------------------------------------------------ lenses


@pytest.fixture(scope="module")
def trained_through_a_lens(tmp_path_factory):
    """The tiny run, its default camera an OPENCV lens (as a checkpoint of a distorted scene stores it)."""
    run = write_tiny_run(tmp_path_factory.mktemp("lens") / "run")
    state = torch.load(run / CHECKPOINT, weights_only=False)
    state["default_intrinsics"]["lens"] = {"model": "OPENCV", "k1": -0.3, "k2": 0.0, "k3": 0.0, "k4": 0.0,
                                           "p1": 0.01, "p2": 0.0}
    torch.save(state, run / CHECKPOINT)
    return run, load_model(run, "cpu")


def test_the_default_render_of_a_distorted_run_is_its_undistorted_pinhole_view(trained_through_a_lens, trained):
    _, lensed = trained_through_a_lens
    assert lensed.default_intrinsics == Intrinsics(**DEFAULT_INTRINSICS.as_dict(), lens=Lens("OPENCV", k1=-0.3,
                                                                                            p1=0.01))
    default = render(lensed, _pose(), outputs=("depth",))["depth"]
    pinhole = render(trained, _pose(), outputs=("depth",))["depth"]  # same weights (same seed), no lens
    np.testing.assert_array_equal(default, pinhole)
    through = render(lensed, _pose(), lensed.default_intrinsics, ("depth",))["depth"]
    assert np.abs(through - pinhole).max() > 1e-3  # the lens bends the corner rays: other z-depths


def test_the_cli_pose_file_asks_for_a_lens_as_post_render_does(trained_through_a_lens, tmp_path):
    from app.core.render_request import RenderRequest
    from voxnerf.cli import _read_pose

    run, lensed = trained_through_a_lens
    doc = {"transform_matrix": _pose().tolist(), "w": 8, "h": 6, "camera_model": "OPENCV", "k2": 0.05}
    (tmp_path / "pose.json").write_text(json.dumps(doc))
    _, cli = _read_pose(tmp_path / "pose.json", lensed.default_intrinsics)
    rest = RenderRequest(job_id="a" * 32, transform_matrix=doc["transform_matrix"], width=8, height=6,
                         camera_model="OPENCV", k2=0.05).intrinsics(lensed.default_intrinsics)
    assert cli == rest and cli.lens == Lens("OPENCV", k1=-0.3, k2=0.05, p1=0.01)
    (tmp_path / "bad.json").write_text(json.dumps({**doc, "camera_model": "OPENCV", "k4": 0.1}))
    with pytest.raises(RunError, match=r"bad.json: k4: OPENCV has no k4"):
        _read_pose(tmp_path / "bad.json", lensed.default_intrinsics)


def test_a_render_compiles_nothing_even_for_a_run_trained_compiled(tmp_path):
    trained = load_model(write_tiny_run(tmp_path / "run"), "cpu")
    trained.model.config.run.compile = True  # as a run trained with torch.compile records it
    render(trained, _pose(), outputs=("rgb",))
    assert not any("render_samples" in str(key) for key in trained.model._compiled)


@pytest.mark.parametrize("path", ["fast", "full"])
def test_a_render_stops_between_passes_once_should_stop_says_so(trained, path):
    """A render nobody waits for any more (issue #42: the API gave up with 504) stops at its next pass over the
    rays, and a render asked to stop never is the same image as one without the question."""
    camera = Intrinsics(20.0, 20.0, 32.0, 32.0, 64, 64)  # 4096 rays: four passes of 1024
    asked = []

    def stop_at_the_third_pass() -> bool:
        asked.append(len(asked))
        return len(asked) == 3

    with pytest.raises(RenderStopped, match="stopped after 2048 of 4096 rays"):
        render_normalized(trained.model, torch.eye(4), camera, ("rgb",), chunk=1024, path=path,
                          should_stop=stop_at_the_third_pass)
    assert len(asked) == 3  # nothing more was rendered once it said stop
    kept = render(trained, _pose(), camera, ("rgb",), path=path, should_stop=lambda: False)
    plain = render(trained, _pose(), camera, ("rgb",), path=path)
    np.testing.assert_array_equal(kept["rgb"], plain["rgb"])


def test_the_full_path_renders_in_passes_of_the_device_s_chunk_unless_the_config_sets_one(trained, monkeypatch):
    """On a CPU the full path's passes are EVAL_CHUNKS["cpu"] rays (4,096, as the cpu preset always had); a
    config's eval_chunk wins (the CUDA value is checked in tests/test_config.py)."""
    model = trained.model
    passes = []
    real = type(model).render_rays

    def counting(self, rays, *args, **kwargs):
        passes.append(len(rays))
        return real(self, rays, *args, **kwargs)

    monkeypatch.setattr(type(model), "render_rays", counting)
    camera = Intrinsics(40.0, 40.0, 40.0, 30.0, 80, 60)  # 4,800 rays
    assert model.config.evaluation.eval_chunk is None
    render_normalized(model, torch.eye(4), camera, ("rgb",), path="full", antialias=False)
    assert passes == [4096, 704]
    passes.clear()
    monkeypatch.setattr(model.config.evaluation, "eval_chunk", 3000)
    render_normalized(model, torch.eye(4), camera, ("rgb",), path="full", antialias=False)
    assert passes == [3000, 1800]


# ------------------------------------------------------------------------------------------- antialiasing


def test_the_rays_of_an_antialiased_pixel_start_at_its_centre_and_weigh_one_in_all():
    assert PIXEL_RAYS[0][:2] == (0.0, 0.0) and len(PIXEL_RAYS) == 5
    assert sum(weight for *_, weight in PIXEL_RAYS) == pytest.approx(1.0)
    assert all(abs(dx) < 0.5 and abs(dy) < 0.5 and weight > 0 for dx, dy, weight in PIXEL_RAYS)  # inside the pixel


@pytest.mark.parametrize("path", ["fast", "full"])
def test_an_antialiased_colour_is_the_weighted_mean_of_its_rays_and_depth_is_the_centre_s(trained, path):
    model = trained.model
    camera = Intrinsics(30.0, 30.0, 10.0, 7.5, 20, 15)
    assert model.config.model.antialias  # the default
    default = render_normalized(model, torch.eye(4), camera, OUTPUTS, path=path)
    centre = render_normalized(model, torch.eye(4), camera, OUTPUTS, path=path, antialias=False)
    expected = sum(weight * render_normalized(model, torch.eye(4), Intrinsics(30.0, 30.0, 10.0 - dx, 7.5 - dy, 20, 15),
                                              ("rgb",), path=path, antialias=False)["rgb"]
                   for dx, dy, weight in PIXEL_RAYS)
    torch.testing.assert_close(default["rgb"], expected)
    assert not torch.allclose(default["rgb"], centre["rgb"])
    for name in ("depth", "opacity"):
        torch.testing.assert_close(default[name], centre[name], rtol=0, atol=0)


def test_a_run_set_to_centre_rays_renders_them_and_a_render_without_colour_casts_no_more(trained, monkeypatch):
    import voxnerf.inference.render as render_module

    model = trained.model
    camera = Intrinsics(30.0, 30.0, 10.0, 7.5, 20, 15)
    passes = []
    real = render_module._render_chunks

    def counting(model, origins, dirs, outputs, *args):
        passes.append(tuple(outputs))
        return real(model, origins, dirs, outputs, *args)

    monkeypatch.setattr(render_module, "_render_chunks", counting)
    render_normalized(model, torch.eye(4), camera, ("rgb", "depth"))
    assert passes == [("rgb", "depth")] + [("rgb",)] * 4  # the centre's every output, the colour of four more
    passes.clear()
    render_normalized(model, torch.eye(4), camera, ("depth", "opacity"))
    assert passes == [("depth", "opacity")]
    passes.clear()
    centre = render_normalized(model, torch.eye(4), camera, ("rgb",), antialias=False)
    monkeypatch.setattr(model, "config", model.config.updated(antialias=False))
    torch.testing.assert_close(render_normalized(model, torch.eye(4), camera, ("rgb",))["rgb"], centre["rgb"])
    assert passes == [("rgb",)] * 2


# ------------------------------------------------------------------------------------------- some pixels


@pytest.mark.parametrize("path", ["fast", "full"])
@pytest.mark.parametrize("lensed", [False, True])
def test_some_pixels_render_as_they_do_in_the_whole_view(trained, trained_through_a_lens, path, lensed):
    """render_pixels (the progress evaluations' renders): the same rays, pose and colour as the whole image's."""
    model = (trained_through_a_lens[1] if lensed else trained).model
    camera = Intrinsics(20.0, 18.0, 16.5, 11.0, 32, 24, lens=Lens("OPENCV", k1=-0.3, p1=0.01) if lensed else None)
    c2w = torch.from_numpy(_pose()).float()
    whole = render_normalized(model, c2w, camera, OUTPUT_NAMES, path=path)
    pixels = torch.tensor([0, 5, 31, 32, 400, 767])
    some = render_pixels(model, c2w, camera, pixels, OUTPUT_NAMES, path=path)
    rows, cols = pixels // 32, pixels % 32
    for name in OUTPUT_NAMES:
        torch.testing.assert_close(some[name], whole[name][rows, cols], atol=1e-5, rtol=1e-5)
    assert render_pixels(model, c2w, camera, pixels[:0])["rgb"].shape == (0, 3)


@pytest.mark.parametrize("bad", [[-1, 3], [0, 768]])
def test_pixels_outside_the_image_are_a_run_error(trained, bad):
    with pytest.raises(RunError, match=r"pixel indices must lie in \[0, 768\) for a 32x24 image"):
        render_pixels(trained.model, torch.eye(4), Intrinsics(20.0, 20.0, 16.0, 12.0, 32, 24), torch.tensor(bad))


def test_the_pixels_of_several_views_render_in_one_pass_as_each_alone(trained_through_a_lens):
    model = trained_through_a_lens[1].model
    camera = Intrinsics(20.0, 18.0, 16.5, 11.0, 32, 24, lens=Lens("OPENCV", k1=-0.3, p1=0.01))
    other = Intrinsics(15.0, 15.0, 8.0, 6.0, 16, 12)
    near, far = torch.from_numpy(_pose(2.5)).float(), torch.from_numpy(_pose(3.5)).float()
    sets = [PixelSet(near, camera, torch.tensor([3, 700, 40])), PixelSet(far, other, torch.tensor([0, 191])),
            PixelSet(far, camera, torch.tensor([], dtype=torch.long))]
    together = render_pixel_sets(model, sets, OUTPUT_NAMES, path="full")
    for one, got in zip(sets, together, strict=True):
        alone = render_pixels(model, one.c2w, one.intrinsics, one.pixels, OUTPUT_NAMES, path="full")
        for name in OUTPUT_NAMES:
            torch.testing.assert_close(got[name], alone[name], atol=1e-5, rtol=1e-5)
    with pytest.raises(RunError, match=r"pixel indices must lie in \[0, 192\) for a 16x12 image"):
        render_pixel_sets(model, [sets[0], PixelSet(far, other, torch.tensor([192]))])
