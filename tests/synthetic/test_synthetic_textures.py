"""voxnerf.synthetic.textures: every procedural pattern gives a deterministic, seed-dependent, varied colour."""

from __future__ import annotations

import numpy as np
import pytest

from voxnerf.synthetic.textures import PATTERNS, Material, _fbm, _value_noise


def _points(n: int = 2000) -> tuple[np.ndarray, np.ndarray]:
    """Points spread over the room with axis-aligned normals (as on its boxes and walls)."""
    rng = np.random.default_rng(7)
    points = rng.uniform([-2.5, -2.0, 0.0], [2.5, 2.0, 2.6], (n, 3))
    normals = np.eye(3)[rng.integers(3, size=n)] * rng.choice([-1.0, 1.0], size=(n, 1))
    return points, normals


@pytest.mark.parametrize("pattern", sorted(PATTERNS))
def test_pattern_is_deterministic_seeded_and_varied(pattern: str):
    material = Material(pattern, (0.6, 0.4, 0.3), (0.2, 0.3, 0.5), 0.2)
    points, normals = _points()
    colour = PATTERNS[pattern](points, normals, material, 11)
    assert colour.shape == (len(points), 3) and np.isfinite(colour).all()
    assert colour.min() >= 0.0 and colour.max() <= 1.5  # near [0, 1]; shading clips albedo to it
    np.testing.assert_array_equal(colour, PATTERNS[pattern](points, normals, material, 11))
    assert colour.std(axis=0).max() > 0.01, "a pattern is not a flat colour"
    if pattern not in ("fabric",):  # plaid stripes and weave do not depend on the seed
        assert not np.array_equal(colour, PATTERNS[pattern](points, normals, material, 12))


def test_value_noise_is_smooth_and_in_unit_range():
    points, _ = _points(5000)
    noise = _value_noise(points * 3.0, 5)
    assert noise.min() >= 0.0 and noise.max() <= 1.0 and noise.std() > 0.05
    nearby = _value_noise(points * 3.0 + 1e-4, 5)
    assert np.abs(noise - nearby).max() < 1e-2, "value noise is continuous"
    fbm = _fbm(points, 5)
    assert fbm.min() >= 0.0 and fbm.max() <= 1.0
    np.testing.assert_allclose(_value_noise(points, 5), _value_noise(points + 64.0, 5), atol=1e-9)  # period 64
