"""A camera and a depth sensor in front of the ray caster: exposure and white-balance drift along the path,
vignetting, Poisson-Gaussian noise in linear space, and Kinect-like depth (noise growing with z^2, disparity
quantisation, no measurement at grazing angles, beyond range or in random holes).

Everything random comes from the generator passed in, so a scene's seed and a frame's index fix every value.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

DEPTH_NOISE_AT_1M = 0.0015
"""Metres: the std of sensor depth noise at 1 m; it grows as ``z^2`` (Kinect-like)."""
DEPTH_DISPARITY_STEP = 0.0025
"""1 / metres: sensor depth is quantised in inverse depth, so its step is about ``DEPTH_DISPARITY_STEP * z^2``."""
DEPTH_MIN_COS = 0.2
"""A surface seen more obliquely than ``acos(DEPTH_MIN_COS)`` (78 degrees) gives no depth (0)."""
DEPTH_MAX_M = 6.0
"""Metres: farther surfaces give no depth (0)."""
DEPTH_HOLES = (1, 4)
DEPTH_HOLE_RADIUS = (0.015, 0.04)
"""Each sensor depth map loses ``DEPTH_HOLES`` (inclusive range) discs of these radii (fraction of the width)."""
DRIFT_SMOOTHING = 0.04
"""The exposure and white-balance walks are smoothed by a Gaussian of this fraction of the path (in frames)."""


@dataclass(frozen=True)
class CameraResponse:
    """What the camera does to linear radiance (the defaults do nothing).

    ``noise_photons``: photons collected at linear value 1 (Poisson shot noise, 0: none); ``noise_read_std``:
    Gaussian read noise (linear units); ``vignetting`` in [0, 1]: the gain is ``1 - v * (1 - cos^4 theta)``
    at ``theta`` off the optical axis.
    """

    noise_photons: float = 0.0
    noise_read_std: float = 0.0
    vignetting: float = 0.0

    @property
    def is_identity(self) -> bool:
        return self.noise_photons == 0.0 and self.noise_read_std == 0.0 and self.vignetting == 0.0


def drift_walk(n_frames: int, amplitude_ev: float, rng: np.random.Generator) -> np.ndarray:
    """A smooth random walk [n_frames] float64 in EV along the camera loop, zero-mean, peak ``|amplitude_ev|``.

    Gaussian steps summed along the path, closed into a loop (the path is one), then smoothed with a circular
    Gaussian of ``DRIFT_SMOOTHING * n_frames`` frames. All zeros when ``amplitude_ev == 0`` (nothing drawn).
    """
    if amplitude_ev == 0.0:
        return np.zeros(n_frames)
    walk = np.cumsum(rng.normal(size=n_frames))
    walk -= np.linspace(0.0, walk[-1], n_frames)
    sigma = max(DRIFT_SMOOTHING * n_frames, 0.5)
    offsets = np.arange(n_frames)
    distance = np.minimum(offsets, n_frames - offsets)
    kernel = np.exp(-0.5 * (distance / sigma) ** 2)
    smooth = np.real(np.fft.ifft(np.fft.fft(walk) * np.fft.fft(kernel / kernel.sum())))
    smooth -= smooth.mean()
    peak = np.abs(smooth).max()
    return smooth * (amplitude_ev / peak) if peak > 0 else smooth


def vignette_gain(w: int, h: int, fl: float, cx: float, cy: float, strength: float) -> np.ndarray:
    """Gain [h, w] float64 at pixel centres: ``1 - strength * (1 - cos^4 theta)``, ``theta`` off the axis."""
    y, x = np.meshgrid(np.arange(h) + 0.5 - cy, np.arange(w) + 0.5 - cx, indexing="ij")
    cos2 = fl**2 / (fl**2 + x**2 + y**2)
    return 1.0 - strength * (1.0 - cos2**2)


def capture_linear(
    radiance: np.ndarray, gain_rgb: np.ndarray, vignette: np.ndarray | None, response: CameraResponse,
    rng: np.random.Generator,
) -> np.ndarray:
    """What the sensor records [h, w, 3] float64 (linear, not clipped) from ``radiance`` [h, w, 3] linear.

    ``gain_rgb`` [3]: exposure times white balance; ``vignette`` [h, w] or None. Shot noise is Poisson in
    ``noise_photons * value`` photons, read noise Gaussian; nothing is drawn for a noise that is off.
    """
    signal = radiance * np.asarray(gain_rgb, np.float64)[None, None]
    if vignette is not None:
        signal = signal * vignette[..., None]
    signal = np.maximum(signal, 0.0)
    if response.noise_photons > 0:
        signal = rng.poisson(signal * response.noise_photons) / response.noise_photons
    if response.noise_read_std > 0:
        signal = signal + rng.normal(0.0, response.noise_read_std, signal.shape)
    return signal


def sensor_depth(depth: np.ndarray, cos_incidence: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """A Kinect-like depth map [h, w] float64 (metres, 0: no measurement) from true z-depth ``depth`` [h, w].

    ``cos_incidence`` [h, w]: |cos| of the angle between each pixel's ray and the surface normal. Noise of std
    ``DEPTH_NOISE_AT_1M * z^2``, quantised in inverse depth by ``DEPTH_DISPARITY_STEP``; 0 where the surface is
    grazing (``cos < DEPTH_MIN_COS``), beyond ``DEPTH_MAX_M``, missing (``depth == 0``) or inside a hole.
    """
    h, w = depth.shape
    noisy = depth + rng.normal(size=depth.shape) * DEPTH_NOISE_AT_1M * depth**2
    valid = (depth > 0) & (noisy > 0) & (depth <= DEPTH_MAX_M) & (cos_incidence >= DEPTH_MIN_COS)
    disparity = np.round(1.0 / np.where(valid, noisy, 1.0) / DEPTH_DISPARITY_STEP) * DEPTH_DISPARITY_STEP
    measured = np.where(valid, 1.0 / np.maximum(disparity, DEPTH_DISPARITY_STEP), 0.0)
    y, x = np.meshgrid(np.arange(h) + 0.5, np.arange(w) + 0.5, indexing="ij")
    for _ in range(int(rng.integers(DEPTH_HOLES[0], DEPTH_HOLES[1] + 1))):
        centre = rng.uniform([0.0, 0.0], [w, h])
        radius = rng.uniform(*DEPTH_HOLE_RADIUS) * w
        measured[(x - centre[0]) ** 2 + (y - centre[1]) ** 2 < radius**2] = 0.0
    return measured
