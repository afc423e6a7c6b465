"""Hash encoding and field: shapes, interpolation, dense/hash levels, bounded density."""

import math

import pytest
import torch

from voxnerf.model import hash_kernel
from voxnerf.model.field import HashEncoding, RadianceField, spherical_harmonics_deg4, trunc_exp


def test_hash_encoding_interpolates_trilinearly_on_dense_level():
    enc = HashEncoding(levels=1, features=1, log2_size=12, base_resolution=4, max_resolution=4)
    assert not bool(enc.use_hash[0])
    with torch.no_grad():
        # Table value = x-index of the grid point: interpolation must reproduce x * res.
        idx = torch.arange(enc.table.shape[0])
        enc.table[:, 0] = (idx % 5).float()
    x = torch.rand(100, 3)
    torch.testing.assert_close(enc(x)[:, 0], x[:, 0] * 4, rtol=1e-5, atol=1e-5)


def test_hash_encoding_shapes_and_gradients():
    enc = HashEncoding(levels=8, features=2, log2_size=10, base_resolution=4, max_resolution=256)
    assert bool(enc.use_hash.any()) and not bool(enc.use_hash.all())
    x = torch.rand(50, 3)
    out = enc(x)
    assert out.shape == (50, 16)
    out.sum().backward()
    assert enc.table.grad is not None and enc.table.grad.abs().sum() > 0
    edge = enc(torch.tensor([[0.0, 0.0, 0.0], [1.0, 1.0, 1.0]]))
    assert torch.isfinite(edge).all()


def test_trunc_exp_is_bounded_with_useful_gradient():
    x = torch.tensor([-100.0, 0.0, 15.0, 1e6], requires_grad=True)
    y = trunc_exp(x)
    assert torch.isfinite(y).all() and float(y[-1].detach()) == float(torch.exp(torch.tensor(15.0)))
    y.sum().backward()
    assert torch.isfinite(x.grad).all() and float(x.grad[-1]) > 0


def test_spherical_harmonics_orthonormal_on_sphere():
    torch.manual_seed(0)
    d = torch.nn.functional.normalize(torch.randn(200_000, 3, dtype=torch.float64), dim=-1)
    sh = spherical_harmonics_deg4(d)
    gram = sh.T @ sh * (4 * torch.pi / d.shape[0])
    torch.testing.assert_close(gram, torch.eye(16, dtype=torch.float64), atol=0.03, rtol=0)


def test_field_outputs():
    field = RadianceField(levels=4, log2_size=12, max_resolution=64, hidden_dim=16)
    density, rgb = field(torch.rand(10, 3) * 2 - 1, torch.nn.functional.normalize(torch.randn(10, 3), dim=-1))
    assert density.shape == (10,) and rgb.shape == (10, 3)
    assert torch.all(density >= 0) and torch.all((rgb >= 0) & (rgb <= 1))


def test_level_weights_scale_each_levels_features_on_both_paths():
    enc = HashEncoding(levels=6, features=2, log2_size=10, base_resolution=4, max_resolution=128)
    with torch.no_grad():
        enc.table.uniform_(-1, 1)
    x = torch.rand(64, 3)
    full = enc.encode(x)
    enc.set_active_levels(2.5)
    expected = full.view(64, 6, 2) * torch.tensor([1.0, 1.0, 0.5, 0.0, 0.0, 0.0])[None, :, None]
    for use_kernel in (False, True):
        enc.use_kernel = use_kernel and hash_kernel.available()
        torch.testing.assert_close(enc(x), expected.reshape(64, 12))
    enc.use_kernel = False
    xg = x.clone().requires_grad_(True)  # the PyTorch path: no gradient reaches a switched-off level
    enc(xg).sum().backward()
    grad = enc.table.grad.view(6, -1, 2)
    assert grad[3:].abs().sum() == 0 and grad[:2].abs().sum() > 0
    enc.set_active_levels(6.0)
    torch.testing.assert_close(enc(x), full)


def test_footprint_weights_fall_with_the_footprint_and_the_level_and_a_point_keeps_every_level():
    enc = HashEncoding(levels=6, features=2, log2_size=10, base_resolution=4, max_resolution=128)
    radii = torch.tensor([0.0, 1e-3, 1e-2, 1e-1])
    w = enc.footprint_weights(radii).view(4, 6, 2)
    torch.testing.assert_close(w[0], torch.ones(6, 2))  # a point
    assert torch.all(w[:, :, 0] == w[:, :, 1])  # one weight per level
    assert torch.all(w[1:, 1:, 0] <= w[1:, :-1, 0]) and torch.all(w[3, 1:, 0] < w[3, :-1, 0])  # finer levels less
    assert torch.all(w[2:, :, 0] <= w[1:-1, :, 0]) and torch.all(w[3, :, 0] < w[2, :, 0])  # and wider footprints
    # Zip-NeRF's erf(1 / sqrt(8 r^2 n^2)): a footprint of 1/10 at the finest level (n = 127) keeps about 3 %
    n = float(enc.resolution[-1])
    assert n == 127 and abs(float(w[3, 5, 0]) - math.erf(1.0 / math.sqrt(8 * (0.1 * n) ** 2))) < 1e-6
    assert float(w[3, 5, 0]) < 0.035 and float(w[1, 0, 0]) > 0.999


def test_the_field_read_over_footprints_scales_the_features_on_both_paths_and_passes_gradients():
    field = RadianceField(levels=4, log2_size=12, max_resolution=64, hidden_dim=16)
    with torch.no_grad():
        field.encoding.table.uniform_(-1, 1)
    x = torch.rand(32, 3) * 2 - 1
    radii = torch.rand(32) * 0.05  # normalised units: the encoding's [0, 1] radii are half of these
    expected = field.encoding.encode((x + 1) * 0.5) * field.encoding.footprint_weights(radii * 0.5)
    for use_kernel in (False, True):
        field.encoding.use_kernel = use_kernel and hash_kernel.available()
        torch.testing.assert_close(field.features(x, radii), expected)
        torch.testing.assert_close(field.features(x), field.encoding.encode((x + 1) * 0.5))
    dirs = torch.nn.functional.normalize(torch.randn(32, 3), dim=-1)
    density, _ = field(x, dirs, radii)
    torch.testing.assert_close(density, field.density(x, radii))
    torch.testing.assert_close(field.geometry(x, radii)[0], density)
    density.sum().backward()
    assert field.encoding.table.grad.abs().sum() > 0


@pytest.mark.parametrize("bands", [1, 2, 3, 4])
def test_fewer_sh_bands_shrink_the_colour_input_and_bands_1_ignores_the_direction(bands):
    field = RadianceField(levels=4, log2_size=12, max_resolution=64, hidden_dim=16, sh_bands=bands)
    assert field.color_mlp[0].in_features == bands * bands + field.GEO_FEATURES
    positions = torch.rand(8, 3) * 2 - 1
    d1 = torch.nn.functional.normalize(torch.randn(8, 3), dim=-1)
    _, rgb1 = field(positions, d1)
    _, rgb2 = field(positions, -d1)
    assert torch.equal(rgb1, rgb2) == (bands == 1)
    # the inference split (direction part once per ray) gives forward's colour
    _, geo = field.geometry(positions)
    torch.testing.assert_close(field.color(geo, field.direction_features(d1)), rgb1)


def test_sh_bands_outside_one_to_four_are_refused():
    with pytest.raises(ValueError, match="sh_bands must be 1-4"):
        RadianceField(levels=4, log2_size=12, max_resolution=64, hidden_dim=16, sh_bands=5)
