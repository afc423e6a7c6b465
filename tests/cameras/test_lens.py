"""Lens distortion (voxnerf/cameras/lens.py): the forward models against OpenCV, the Newton inverses against
``cv2.undistortPoints``, round trips, finiteness on extreme input; rays through a lens; and the synthetic room
rendered through a lens, whose rays (as training builds them) hit the surface points the renderer saw."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from voxnerf.cameras.lens import (
    LensBatch,
    distort,
    distort_fisheye,
    distort_opencv,
    fisheye_theta,
    lens_directions,
    undistort,
)
from voxnerf.cameras.rays import camera_rays, image_rays
from voxnerf.cameras.rules import Intrinsics, Lens
from voxnerf.data.scene import SceneTransform, load_scene
from voxnerf.synthetic import RoomSpec, build_room, make_room_scene
from voxnerf.synthetic.raycast import _cast
from voxnerf.training.pixels import training_pixels

FL, CX, CY, W, H = 500.0, 321.5, 238.0, 640, 480
K = np.array([[FL, 0, CX], [0, FL, CY], [0, 0, 1.0]])
PHONE = Lens("OPENCV", k1=-0.12, k2=0.04, k3=-0.005, p1=0.001, p2=-0.0007)  # a wide-angle phone lens
GOPRO = Lens("OPENCV_FISHEYE", k1=0.05, k2=-0.02, k3=0.01, k4=-0.002)  # a GoPro-like fisheye
LENSES = [PHONE, GOPRO]
CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-15)


def _pixel_grid() -> np.ndarray:
    """[N, 2] pixels over the whole image, its corners included."""
    py, px = np.meshgrid(np.linspace(0, H, 31), np.linspace(0, W, 41), indexing="ij")
    return np.stack([px.ravel(), py.ravel()], axis=-1)


def _cv_coeffs(lens: Lens) -> np.ndarray:
    if lens.model == "OPENCV":
        return np.array([lens.k1, lens.k2, lens.p1, lens.p2, lens.k3])
    return np.array([lens.k1, lens.k2, lens.k3, lens.k4])


def _cv_project(lens: Lens, xy: np.ndarray) -> np.ndarray:
    """Pixels of undistorted normalised points ``xy`` [N, 2] by OpenCV."""
    points = np.concatenate([xy, np.ones((len(xy), 1))], axis=1)[:, None]
    module = cv2 if lens.model == "OPENCV" else cv2.fisheye
    return module.projectPoints(points, np.zeros(3), np.zeros(3), K, _cv_coeffs(lens))[0][:, 0]


def _cv_undistort(lens: Lens, pixels: np.ndarray) -> np.ndarray:
    """Undistorted normalised points of ``pixels`` [N, 2] by OpenCV, iterated to convergence."""
    module = cv2 if lens.model == "OPENCV" else cv2.fisheye
    out = module.undistortPoints(pixels[:, None].astype(np.float64), K, _cv_coeffs(lens), R=np.eye(3), P=np.eye(3),
                                 criteria=CRITERIA)
    return out[:, 0]


def _coeffs(lens: Lens, dtype=torch.float32) -> torch.Tensor:
    return torch.tensor(lens.coefficients, dtype=dtype)


@pytest.mark.parametrize("lens", LENSES, ids=lambda lens: lens.model)
def test_forward_model_matches_opencv_project_points(lens):
    rng = np.random.default_rng(0)
    xy = rng.uniform(-0.8, 0.8, (500, 2))
    ours = distort(torch.from_numpy(xy), _coeffs(lens, torch.float64), lens.model).numpy() * FL + [CX, CY]
    np.testing.assert_allclose(ours, _cv_project(lens, xy), atol=1e-6)
    ours32 = distort(torch.from_numpy(xy).float(), _coeffs(lens), lens.model).numpy() * FL + [CX, CY]
    np.testing.assert_allclose(ours32, _cv_project(lens, xy), atol=1e-3)


@pytest.mark.parametrize("lens", LENSES, ids=lambda lens: lens.model)
def test_inverse_matches_opencv_undistort_points_to_a_thousandth_of_a_pixel(lens):
    pixels = _pixel_grid()
    uv = torch.from_numpy((pixels - [CX, CY]) / FL).float()
    ours = undistort(uv, _coeffs(lens), lens.model).double().numpy()
    assert np.abs(ours - _cv_undistort(lens, pixels)).max() * FL < 1e-3
    assert np.abs(ours - uv.double().numpy()).max() * FL > 20  # the lens does move the corners


@pytest.mark.parametrize("lens", LENSES, ids=lambda lens: lens.model)
def test_distort_of_undistort_is_the_identity(lens):
    pixels = _pixel_grid()
    uv = torch.from_numpy((pixels - [CX, CY]) / FL).float()
    back = distort(undistort(uv, _coeffs(lens), lens.model), _coeffs(lens), lens.model)
    assert (back - uv).abs().max().item() * FL < 1e-3
    np.testing.assert_allclose(_cv_project(lens, undistort(uv, _coeffs(lens), lens.model).double().numpy()), pixels,
                               atol=1e-3)


@pytest.mark.parametrize("model", ["OPENCV", "OPENCV_FISHEYE"])
def test_extreme_coefficients_and_points_stay_finite(model):
    rng = np.random.default_rng(1)
    coeffs = torch.from_numpy(rng.normal(0, 5, (2000, 6))).float()
    uv = torch.from_numpy(rng.normal(0, 1, (2000, 2)) * 10.0 ** rng.uniform(-8, 4, (2000, 1))).float()
    uv[:4] = torch.tensor([[0.0, 0.0], [1e-30, 0.0], [1e6, -1e6], [3.2, 0.0]])
    assert torch.isfinite(undistort(uv, coeffs, model)).all()
    assert torch.isfinite(distort(uv.clamp(-1e3, 1e3), coeffs, model)).all()
    codes = torch.full((2000,), 1 if model == "OPENCV" else 2)
    dirs = lens_directions(uv, LensBatch(coeffs, codes, (int(codes[0]),)))
    assert torch.isfinite(dirs).all()
    torch.testing.assert_close(torch.linalg.vector_norm(dirs, dim=-1), torch.ones(2000))


def test_fisheye_directions_reach_past_ninety_degrees():
    """A fisheye pixel whose distorted radius is beyond pi/2 looks backwards; theta is never above pi."""
    coeffs = torch.zeros(6)
    theta = fisheye_theta(torch.tensor([[2.0, 0.0], [0.0, 4.0]]), coeffs)
    torch.testing.assert_close(theta, torch.tensor([2.0, torch.pi]))
    dirs = lens_directions(torch.tensor([[2.0, 0.0]]), LensBatch(coeffs[None], torch.tensor([2]), (2,)))
    torch.testing.assert_close(dirs, torch.tensor([[np.sin(2.0), 0.0, np.cos(2.0)]], dtype=torch.float32))
    assert distort_fisheye(torch.zeros(1, 2), coeffs).abs().max() == 0


def test_a_batch_of_mixed_lenses_gives_each_ray_its_own_model():
    batch = LensBatch.of([None, PHONE, GOPRO])
    assert batch.models == (0, 1, 2) and LensBatch.of([None, None]) is None
    uv = torch.tensor([[0.5, 0.3]] * 3)
    dirs = lens_directions(uv, batch.select(torch.tensor([0, 1, 2])))
    for row, lens in zip(dirs[1:], LENSES, strict=True):
        xy = undistort(uv[:1], _coeffs(lens), lens.model)[0]
        torch.testing.assert_close(row[:2] / row[2], xy, atol=1e-5, rtol=0)
    torch.testing.assert_close(dirs[0], torch.tensor([0.5, 0.3, 1.0]) / np.sqrt(1.34))
    torch.testing.assert_close(distort_opencv(uv, torch.zeros(6)), uv)


@pytest.mark.parametrize("lens", LENSES, ids=lambda lens: lens.model)
def test_image_rays_through_a_lens_project_back_to_their_pixels(lens):
    """Points along each ray, projected by OpenCV, land on the pixel centre the ray came from."""
    intr = Intrinsics(FL / 8, FL / 8, CX / 8, CY / 8, W // 8, H // 8, lens)
    c2w = torch.eye(4)
    origins, dirs, z_per_t = image_rays(c2w, intr)
    points = (origins + 3.0 * dirs).double().numpy() * [1, -1, -1]  # OpenGL -> OpenCV camera axes
    k = np.array([[intr.fl_x, 0, intr.cx], [0, intr.fl_y, intr.cy], [0, 0, 1.0]])
    module = cv2 if lens.model == "OPENCV" else cv2.fisheye
    pixels = module.projectPoints(points[:, None], np.zeros(3), np.zeros(3), k, _cv_coeffs(lens))[0][:, 0]
    py, px = np.meshgrid(np.arange(intr.height) + 0.5, np.arange(intr.width) + 0.5, indexing="ij")
    np.testing.assert_allclose(pixels, np.stack([px.ravel(), py.ravel()], -1), atol=1e-3)
    np.testing.assert_allclose(z_per_t.numpy(), -dirs[:, 2].numpy(), atol=1e-6)


def test_camera_rays_without_a_lens_are_unchanged():
    c2w = torch.eye(4)[None].expand(3, 4, 4)
    px, py = torch.tensor([0, 4, 7]), torch.tensor([1, 3, 5])
    pinhole = camera_rays(c2w, 10.0, 12.0, 4.0, 3.0, px, py)
    zero_lens = camera_rays(c2w, 10.0, 12.0, 4.0, 3.0, px, py, LensBatch.of([Lens("OPENCV")] * 3).select(
        torch.tensor([0, 1, 2])))
    for a, b in zip(pinhole, zero_lens, strict=True):
        torch.testing.assert_close(a, b)


# ------------------------------------------------------------------------------------------------ the room

ROOM_LENS = {"camera_model": "OPENCV", "k1": -0.15, "k2": 0.02, "p1": 0.001, "p2": -0.001}


@pytest.fixture(scope="module")
def lens_room(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("lens_room") / "room"
    return make_room_scene(out, RoomSpec(width=64, height=48, n_frames=16, train_every=4, n_gaps=0, gap_len=0,
                                         prior_kind="none", supersample=1, lens=ROOM_LENS))


def test_the_room_through_a_lens_writes_its_coefficients(lens_room):
    meta = json.loads((lens_room / "transforms.json").read_text())
    assert meta["camera_model"] == "OPENCV" and meta["k1"] == -0.15 and meta["k3"] == 0.0 and "k4" not in meta
    assert meta["voxnerf_synthetic"]["spec"]["lens"] == ROOM_LENS
    scene = load_scene(lens_room)
    assert scene.summary()["camera_models"] == {"OPENCV (camera_model)": len(scene.frames)}
    assert scene.intrinsics(0).lens == Lens("OPENCV", k1=-0.15, k2=0.02, p1=0.001, p2=-0.001)


def _hit_error(scene, geom, with_lens: bool) -> np.ndarray:
    """|ray distance to the room x z_per_t - the rendered depth| (metres) at every pixel of training frame 0."""
    frame = scene.frames[scene.train_indices[0]]
    intr = frame.intrinsics if with_lens else frame.intrinsics.undistorted()
    c2w = torch.from_numpy(frame.c2w).float()
    origins, dirs, z_per_t = image_rays(c2w, intr)
    t, _, _ = _cast(geom, origins.double().numpy(), dirs.double().numpy())
    depth = scene.depths[scene.train_indices[0]].ravel()
    return np.abs(t * z_per_t.double().numpy() - depth)


def test_rays_of_a_distorted_frame_hit_the_surface_the_renderer_saw(lens_room):
    """Rays built as training builds them (through the lens) meet the room at the z-depth the synthetic renderer
    wrote for each pixel; the same pixels read as a pinhole miss it near the corners."""
    scene = load_scene(lens_room)
    geom = build_room(0)
    pixels = training_pixels(scene, SceneTransform((0.0, 0.0, 0.0), 1.0), torch.device("cpu"))
    assert pixels.lens is not None and pixels.lens.models == (1,)
    through_lens = _hit_error(scene, geom, True)
    as_pinhole = _hit_error(scene, geom, False)
    assert np.median(through_lens) < 1e-3 and np.percentile(through_lens, 95) < 5e-3
    assert np.percentile(as_pinhole, 95) > 10 * np.percentile(through_lens, 95)
    # training's rays (TrainingPixels.rays) are image_rays' rays
    h, w = scene.images[0].shape[:2]
    py, px = torch.meshgrid(torch.arange(h), torch.arange(w), indexing="ij")
    origins, dirs = pixels.rays(torch.zeros(h * w, dtype=torch.long), py.reshape(-1), px.reshape(-1))
    frame = scene.frames[scene.train_indices[0]]
    expected = image_rays(torch.from_numpy(frame.c2w).float(), frame.intrinsics)
    torch.testing.assert_close(dirs, expected[1], atol=1e-5, rtol=0)
