"""Training pixels and batches (voxnerf/training/pixels.py)."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
import torch

from voxnerf.config import TrainConfig
from voxnerf.training.pixels import TrainingPixels, per_pixel, rays_in_chunks, sample_batch, training_pixels


def _pixels(n: int = 3, h: int = 6, w: int = 7) -> TrainingPixels:
    return TrainingPixels(torch.zeros(n, h, w, 3, dtype=torch.uint8), torch.eye(4).expand(n, 4, 4).clone(),
                          torch.tensor([[5.0, 5.0, w / 2, h / 2]] * n))


def test_random_pixels_come_from_the_generator_alone():
    cfg = TrainConfig(max_iters=1, rays_per_batch=64)
    pixels = _pixels()
    a = sample_batch(pixels, cfg, False, torch.Generator().manual_seed(5))
    torch.manual_seed(0)  # the global generator plays no part
    b = sample_batch(pixels, cfg, False, torch.Generator().manual_seed(5))
    assert all(torch.equal(x, y) for x, y in zip(a, b, strict=True)) and all(len(x) == 64 for x in a)
    img, py, px = a
    assert int(img.max()) < 3 and int(py.max()) < 6 and int(px.max()) < 7


def test_patches_follow_the_random_pixels_as_whole_squares_of_one_image():
    cfg = TrainConfig(max_iters=1, rays_per_batch=10, smooth_patches=2, patch_size=3)
    img, py, px = sample_batch(_pixels(), cfg, True, torch.Generator().manual_seed(1))
    assert len(img) == 10 + 2 * 9
    for p in range(2):
        sl = slice(10 + 9 * p, 10 + 9 * (p + 1))
        assert len(set(img[sl].tolist())) == 1
        ys, xs = py[sl].view(3, 3), px[sl].view(3, 3)
        assert torch.equal(ys - ys[0, 0], torch.arange(3)[:, None].expand(3, 3))
        assert torch.equal(xs - xs[0, 0], torch.arange(3)[None, :].expand(3, 3))


def test_a_patch_never_exceeds_a_small_image():
    cfg = TrainConfig(max_iters=1, rays_per_batch=4, smooth_patches=1, patch_size=8)
    img, py, px = sample_batch(_pixels(h=5, w=6), cfg, True, torch.Generator().manual_seed(1))
    assert len(img) == 4 + 25 and int(py.max()) < 5 and int(px.max()) < 6


def test_rays_of_a_pixel_start_at_its_camera():
    pixels = _pixels()
    pixels.c2w[1, :3, 3] = torch.tensor([1.0, 2.0, 3.0])
    origins, dirs = pixels.rays(torch.tensor([1]), torch.tensor([3]), torch.tensor([3]))
    assert torch.allclose(origins, torch.tensor([[1.0, 2.0, 3.0]])) and origins.shape == dirs.shape == (1, 3)


@pytest.mark.parametrize("chunk", [5, 1000])
def test_per_pixel_maps_every_pixel_in_chunks_with_nan_where_invalid(chunk):
    pixels = _pixels(n=2, h=3, w=4)
    model = SimpleNamespace(ray_bundle=lambda origins, dirs: SimpleNamespace(origins=origins, dirs=dirs))

    def fn(rays, index):
        assert len(rays.origins) == len(index)
        return index.float(), index % 2 == 0

    t, ok = per_pixel(pixels, model, fn, chunk=chunk)
    flat = torch.arange(24).view(2, 3, 4)
    assert torch.equal(ok, flat % 2 == 0)
    assert torch.equal(t[ok], flat[ok].float()) and torch.isnan(t[~ok]).all()


@pytest.mark.parametrize("chunk", [3, 1000])
def test_rays_in_chunks_are_the_rays_of_the_pixels_asked_for(chunk):
    pixels = _pixels(n=2, h=3, w=4)
    pixels.c2w[1, :3, 3] = torch.tensor([1.0, 2.0, 3.0])
    flat = torch.tensor([23, 0, 5, 12, 13, 7, 19])  # any order, across images
    parts = list(rays_in_chunks(pixels, flat, chunk))
    assert len(parts) == -(-len(flat) // chunk)
    f, img, origins, dirs = (torch.cat(column) for column in zip(*parts, strict=True))
    assert torch.equal(f, flat) and torch.equal(img, flat // 12)
    want = pixels.rays(flat // 12, flat % 12 // 4, flat % 4)
    torch.testing.assert_close(origins, want[0])
    torch.testing.assert_close(dirs, want[1])
    assert not list(rays_in_chunks(pixels, torch.zeros(0, dtype=torch.int64), chunk))


def test_training_images_of_different_sizes_are_refused():
    scene = SimpleNamespace(train_indices=[0, 1], images=[np.zeros((4, 5, 3)), np.zeros((5, 4, 3))])
    with pytest.raises(ValueError, match="differ in size"):
        training_pixels(scene, None, torch.device("cpu"))


def test_lens_rays_from_the_direction_table_equal_the_inverse_model():
    """Frames with lenses look their rays up in a table of each distinct camera (two here, three frames)."""
    from voxnerf.cameras.lens import LensBatch
    from voxnerf.cameras.rules import Lens
    from voxnerf.training.pixels import direction_table

    n, h, w = 3, 12, 16
    intr = torch.tensor([[14.0, 15.0, 8.2, 5.9]] * n)
    lenses = [Lens("OPENCV", k1=-0.2, k2=0.03, p1=0.002), Lens("OPENCV_FISHEYE", k1=0.05, k2=-0.01),
              Lens("OPENCV", k1=-0.2, k2=0.03, p1=0.002)]
    lens = LensBatch.of(lenses)
    g = torch.Generator().manual_seed(1)
    c2w = torch.linalg.qr(torch.randn(n, 3, 3, generator=g))[0]
    poses = torch.eye(4).repeat(n, 1, 1)
    poses[:, :3, :3], poses[:, :3, 3] = c2w, torch.randn(n, 3, generator=g)
    table = direction_table(intr, lens, h, w)
    assert table.dirs.shape == (2, h, w, 3) and table.camera.tolist()[0] == table.camera.tolist()[2]
    img = torch.randint(0, n, (500,), generator=g)
    py, px = torch.randint(0, h, (500,), generator=g), torch.randint(0, w, (500,), generator=g)
    images = torch.zeros(n, h, w, 3, dtype=torch.uint8)
    looked_up = TrainingPixels(images, poses, intr, lens, directions=table).rays(img, py, px)
    computed = TrainingPixels(images, poses, intr, lens).rays(img, py, px)
    for a, b in zip(looked_up, computed, strict=True):
        torch.testing.assert_close(a, b, atol=2e-6, rtol=0)
    assert direction_table(intr, None, h, w) is None


def test_a_direction_table_past_its_memory_bound_is_not_built(monkeypatch):
    from voxnerf.cameras.lens import LensBatch
    from voxnerf.cameras.rules import Lens
    from voxnerf.training import pixels

    monkeypatch.setattr(pixels, "MAX_DIRECTION_TABLE_BYTES", 2 * 12 * 16 * 3 * 4 - 1)  # one byte short of two
    intr = torch.tensor([[14.0, 15.0, 8.0, 6.0], [14.0, 15.0, 8.5, 6.0]])
    lens = LensBatch.of([Lens("OPENCV", k1=-0.1)] * 2)
    assert pixels.direction_table(intr, lens, 12, 16) is None
    assert pixels.direction_table(intr[:1], LensBatch.of([Lens("OPENCV", k1=-0.1)]), 12, 16) is not None
