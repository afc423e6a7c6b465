"""Training pixels and batches (voxnerf/training/pixels.py)."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
import torch

from voxnerf.config import TrainConfig
from voxnerf.training.pixels import (
    TrainingPixels,
    per_pixel,
    rays_in_chunks,
    sample_batch,
    sensor_ray_distance,
    training_pixels,
)


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


def _mixed_scene():
    """A landscape 4x5 and a portrait 6x3 training image (values 1 and 2), pinhole cameras at the origin."""
    from voxnerf.cameras.rules import Intrinsics
    from voxnerf.data.scene import SceneTransform

    images = [np.full((4, 5, 3), 1, np.uint8), np.full((6, 3, 3), 2, np.uint8)]
    cameras = [Intrinsics(4.0, 4.0, 2.5, 2.0, 5, 4), Intrinsics(4.0, 4.0, 1.5, 3.0, 3, 6)]
    frames = [SimpleNamespace(c2w=np.eye(4)) for _ in images]
    scene = SimpleNamespace(train_indices=[0, 1], images=images, frames=frames, intrinsics=lambda i: cameras[i])
    return scene, SceneTransform((0.0, 0.0, 0.0), 1.0)


def test_training_images_of_different_sizes_share_the_largest_grid():
    scene, transform = _mixed_scene()
    pixels = training_pixels(scene, transform, torch.device("cpu"))
    assert pixels.shape == (2, 6, 5) and pixels.sizes.tolist() == [[4, 5], [6, 3]]
    assert pixels.pixel_count == 20 + 18 and pixels.smallest_side == (4, 3)
    assert int(pixels.images[0, 4:].max()) == 0 and int(pixels.images[1, :, 3:].max()) == 0  # padding
    assert pixels.inside().sum() == 38 and len(pixels.real_pixels()) == 38
    torch.testing.assert_close(pixels.mean_colour(), torch.full((3,), (20 * 1 + 18 * 2) / 38 / 255))
    same = training_pixels(SimpleNamespace(**{**vars(scene), "images": [scene.images[0]] * 2,
                                             "intrinsics": lambda i: scene.intrinsics(0)}), transform, "cpu")
    assert same.sizes is None and same.inside() is None and same.pixel_count == 40


def test_batches_of_mixed_sizes_cover_every_image_pixel_uniformly_and_never_the_padding():
    scene, transform = _mixed_scene()
    pixels = training_pixels(scene, transform, torch.device("cpu"))
    cfg = TrainConfig(max_iters=1, rays_per_batch=38_000, smooth_patches=50, patch_size=3)
    img, py, px = sample_batch(pixels, cfg, True, torch.Generator().manual_seed(3))
    assert bool((pixels.images[img, py, px] > 0).all())  # every ray hits an image pixel
    counts = torch.zeros(2, 6, 5).index_put_((img[:38_000], py[:38_000], px[:38_000]), torch.ones(38_000),
                                             accumulate=True)
    assert int((counts > 0).sum()) == 38 and float(counts[counts > 0].min()) > 800  # ~1000 each
    for p in range(50):  # whole 3x3 squares inside their own image
        sl = slice(38_000 + 9 * p, 38_000 + 9 * (p + 1))
        assert len(set(img[sl].tolist())) == 1
    flat = pixels.random_pixels(5000, torch.Generator().manual_seed(4))
    assert bool(pixels.inside().view(-1)[flat].all())


def test_per_pixel_caches_of_mixed_sizes_are_nan_on_the_padding():
    scene, transform = _mixed_scene()
    pixels = training_pixels(scene, transform, torch.device("cpu"))
    model = SimpleNamespace(ray_bundle=lambda origins, dirs: SimpleNamespace(origins=origins, dirs=dirs))
    t, ok = per_pixel(pixels, model, lambda rays, index: (torch.ones(len(index)), torch.ones(len(index)) > 0))
    inside = pixels.inside()
    assert torch.equal(ok, inside) and bool((t[inside] == 1).all()) and bool(torch.isnan(t[~inside]).all())
    z = torch.ones(2, 6, 5)
    sensor_t = sensor_ray_distance(pixels, z, 1.0)
    assert bool(torch.isfinite(sensor_t[inside]).all()) and bool(torch.isnan(sensor_t[~inside]).all())
    assert pixels.fraction(torch.isfinite(sensor_t)) == 1.0


def test_a_point_seen_only_past_a_smaller_image_edge_is_not_seen():
    """seen_by bounds each view by its own size: the padding of a portrait view does not see."""
    from voxnerf.training.prior_rays import seen_by

    intr = torch.tensor([[4.0, 4.0, 1.5, 3.0]])
    depth_t = torch.full((1, 6, 5), float("nan"))
    point = torch.tensor([[3.5 / 4.0, 0.0, -1.0]])  # projects to pixel (row 2, column 4): past a 3-wide image
    assert bool(seen_by(point, torch.eye(4)[None], intr, depth_t, 0.1)[0])  # as if 5 wide: seen
    assert not bool(seen_by(point, torch.eye(4)[None], intr, depth_t, 0.1, sizes=torch.tensor([[6, 3]]))[0])


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


def test_direction_tables_of_mixed_sizes_equal_the_inverse_model_inside_each_image():
    """Two frames share intrinsics and lens but not their size: two tables, each filled up to its own size."""
    from voxnerf.cameras.lens import LensBatch
    from voxnerf.cameras.rules import Lens
    from voxnerf.training.pixels import direction_table

    intr = torch.tensor([[14.0, 15.0, 8.2, 5.9]] * 3)
    lens = LensBatch.of([Lens("OPENCV", k1=-0.2, k2=0.03, p1=0.002)] * 3)
    sizes = torch.tensor([[12, 16], [11, 16], [12, 16]])
    table = direction_table(intr, lens, 12, 16, sizes)
    assert table.dirs.shape == (2, 12, 16, 3) and table.camera.tolist() == [1, 0, 1]
    assert bool((table.dirs[0, 11] == 0).all())  # the 11-row camera's padding row
    poses = torch.eye(4).repeat(3, 1, 1)
    images = torch.zeros(3, 12, 16, 3, dtype=torch.uint8)
    g = torch.Generator().manual_seed(2)
    img = torch.randint(0, 3, (400,), generator=g)
    py = (torch.rand(400, generator=g) * sizes[img, 0]).long()
    px = torch.randint(0, 16, (400,), generator=g)
    looked_up = TrainingPixels(images, poses, intr, lens, directions=table, sizes=sizes).rays(img, py, px)
    computed = TrainingPixels(images, poses, intr, lens, sizes=sizes).rays(img, py, px)
    for a, b in zip(looked_up, computed, strict=True):
        torch.testing.assert_close(a, b, atol=2e-6, rtol=0)


def test_an_offset_moves_a_pinhole_ray_to_that_point_of_its_pixel():
    from voxnerf.cameras.rays import camera_rays

    pixels = _pixels()
    img, py, px = torch.tensor([0, 2]), torch.tensor([1, 4]), torch.tensor([2, 6])
    offset = torch.tensor([[0.25, -0.4], [-0.5, 0.49]])
    _, dirs = pixels.rays(img, py, px, offset)
    k = pixels.intr[img]
    _, expected, _ = camera_rays(pixels.c2w[img], k[:, 0], k[:, 1], k[:, 2], k[:, 3], px + offset[:, 1],
                                 py + offset[:, 0])
    torch.testing.assert_close(dirs, expected)
    _, centre = pixels.rays(img, py, px, torch.zeros(2, 2))
    torch.testing.assert_close(centre, pixels.rays(img, py, px)[1])
    assert not torch.allclose(dirs, centre)


@pytest.mark.parametrize("sizes", [None, torch.tensor([[12, 16], [11, 13]])])
def test_an_offset_through_a_direction_table_follows_the_lens_between_pixel_centres(sizes):
    """The table's bilinear mix at a point between centres is the lens's own ray there (within a small angle),
    and an offset past an image's last centre stays inside that image's table."""
    from voxnerf.cameras.lens import LensBatch
    from voxnerf.cameras.rules import Lens
    from voxnerf.training.pixels import direction_table

    n, h, w = 2, 12, 16
    intr = torch.tensor([[14.0, 15.0, 8.2, 5.9], [14.0, 15.0, 8.2, 5.9]])
    lens = LensBatch.of([Lens("OPENCV", k1=-0.2, k2=0.03, p1=0.002), Lens("OPENCV_FISHEYE", k1=0.05, k2=-0.01)])
    table = direction_table(intr, lens, h, w, sizes)
    images, poses = torch.zeros(n, h, w, 3, dtype=torch.uint8), torch.eye(4).repeat(n, 1, 1)
    g = torch.Generator().manual_seed(3)
    img = torch.randint(0, n, (300,), generator=g)
    rows = torch.full((300,), h) if sizes is None else sizes[img, 0]
    cols = torch.full((300,), w) if sizes is None else sizes[img, 1]
    py, px = (torch.rand(300, generator=g) * rows).long(), (torch.rand(300, generator=g) * cols).long()
    offset = torch.rand(300, 2, generator=g) - 0.5
    _, looked_up = TrainingPixels(images, poses, intr, lens, directions=table, sizes=sizes).rays(img, py, px, offset)
    _, computed = TrainingPixels(images, poses, intr, lens, sizes=sizes).rays(img, py, px, offset)
    inside = ((py + offset[:, 0] >= 0) & (py + offset[:, 0] <= rows - 1) & (px + offset[:, 1] >= 0)
              & (px + offset[:, 1] <= cols - 1))
    cos = (looked_up * computed).sum(-1)
    assert torch.isfinite(looked_up).all() and bool(inside.any()) and bool((~inside).any())
    assert float(cos[inside].min()) > np.cos(np.radians(0.2))  # bilinear between centres: a small angle
    assert float(cos.min()) > np.cos(np.radians(3.0))  # clamped at the image's edge: the edge centre's ray


def test_pixel_jitter_draws_training_rays_through_their_pixels_not_their_centres():
    from voxnerf.training.step import pixel_offsets

    pixels = _pixels(n=2, h=9, w=11)
    k = pixels.intr[0]

    def pixel_of(dirs):  # where a ray through the camera at the origin (identity pose) crosses the image
        return (dirs[:, 1] / dirs[:, 2] * k[1] + k[3] - 0.5, -dirs[:, 0] / dirs[:, 2] * k[0] + k[2] - 0.5)

    for jitter in (False, True):
        cfg = TrainConfig(max_iters=1, rays_per_batch=256, pixel_jitter=jitter)
        img, py, px = sample_batch(pixels, cfg, False, torch.Generator().manual_seed(4))
        _, dirs = pixels.rays(img, py, px, pixel_offsets(cfg, len(img), torch.Generator().manual_seed(4)))
        y, x = pixel_of(dirs)
        dy, dx = y - py, x - px.float()
        assert float(dy.abs().max()) <= 0.5 + 1e-4 and float(dx.abs().max()) <= 0.5 + 1e-4
        assert (float(dx.abs().max()) > 0.3) == jitter and (float(dy.std()) > 0.1) == jitter


def test_index_of_undoes_the_flat_index_of_the_grid():
    pixels = _pixels(n=3, h=6, w=7)
    img, py, px = torch.tensor([0, 2, 1]), torch.tensor([5, 0, 3]), torch.tensor([6, 1, 4])
    flat = (img * 6 + py) * 7 + px
    assert all(torch.equal(a, b) for a, b in zip(pixels.index_of(flat), (img, py, px), strict=True))
