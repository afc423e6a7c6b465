"""The radiance field (paper III-B): multi-resolution hash encoding, a density MLP and a colour MLP.

Positions are in normalised units inside ``[-1, 1]^3`` (the canonical box); the field maps them to
``[0, 1]^3`` itself. Pure PyTorch, vectorised across levels, on CPU and CUDA alike (tiny-cuda-nn is not
integrated: it could not be built or tested here). On the CPU the encoding may instead run through
:mod:`voxnerf.model.hash_kernel` (``HashEncoding.use_kernel``), a C kernel with the same arithmetic and a cheaper
backward; the PyTorch path stays the reference and the fallback.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor, nn

from voxnerf.model.hash_kernel import hash_encode

# Spatial-hash primes of instant-ngp (Teschner et al.); the first axis uses 1.
HASH_PRIMES = (1, 2654435761, 805459861)
# Density activation ceiling: exp(15) ~ 3.3e6 per normalised unit, far beyond opaque for any step size.
MAX_LOG_DENSITY = 15.0


def trunc_exp(x: Tensor) -> Tensor:
    """``exp(min(x, 15))`` whose gradient is ``exp(min(x, 15))`` everywhere (instant-ngp's truncated exp).

    The straight-through form keeps a useful gradient above the ceiling and cannot overflow.
    """
    clamped = x - (x - x.clamp(max=MAX_LOG_DENSITY)).detach()
    return torch.exp(clamped)


class HashEncoding(nn.Module):
    """Multi-resolution hash grid (Mueller et al. 2022) with trilinear interpolation.

    Level ``l`` has resolution ``floor(base * growth**l)``; the coarse levels whose ``(res+1)^3`` grid fits in
    the table are indexed densely, the fine ones through the spatial hash. All levels live in one table
    ``[levels * 2**log2_size, features]`` so one gather serves them all. Index arithmetic is int32 (the hash
    multiplies wrap modulo 2^32 exactly like instant-ngp's uint32 hash; only the low ``log2_size`` bits are
    kept).
    """

    def __init__(
        self,
        levels: int = 16,
        features: int = 2,
        log2_size: int = 17,
        base_resolution: int = 16,
        max_resolution: int = 1024,
    ) -> None:
        super().__init__()
        if log2_size > 30:
            raise ValueError("log2_size must be <= 30 (int32 indices)")
        self.levels, self.features, self.table_size = levels, features, 2**log2_size
        growth = math.exp((math.log(max_resolution) - math.log(base_resolution)) / max(levels - 1, 1))
        res = [int(math.floor(base_resolution * growth**lvl)) for lvl in range(levels)]
        # Resolutions grow with the level, so the dense levels come first.
        self.dense_levels = sum((r + 1) ** 3 <= self.table_size for r in res)
        self.register_buffer("resolution", torch.tensor(res, dtype=torch.float32), persistent=False)
        self.register_buffer("max_cell", torch.tensor(res, dtype=torch.int32) - 1, persistent=False)
        strides = torch.tensor([[1, r + 1, (r + 1) ** 2] for r in res[: self.dense_levels]], dtype=torch.int32)
        self.register_buffer("dense_strides", strides.view(1, -1, 3, 1), persistent=False)
        primes = torch.tensor([HASH_PRIMES[0], HASH_PRIMES[1] - 2**32, HASH_PRIMES[2]], dtype=torch.int32)
        self.register_buffer("hash_primes", primes.view(1, 1, 3, 1), persistent=False)  # int32: wraps as uint32
        offsets = torch.arange(levels, dtype=torch.int32) * self.table_size
        self.register_buffer("level_offset", offsets.view(1, -1, 1, 1, 1), persistent=False)
        self.register_buffer("upper", torch.tensor([0, 1], dtype=torch.int32), persistent=False)
        self.table = nn.Parameter(torch.empty(levels * self.table_size, features).uniform_(-1e-4, 1e-4))
        # [levels * features] weight of each level's features (coarse-to-fine training ramps it up; all ones
        # otherwise, and always in a saved model: it is not part of the state dict).
        self.register_buffer("level_weight", torch.ones(levels * features), persistent=False)
        # Set by voxnerf.model.voxnerf_model.field_for where voxnerf.model.hash_kernel is available: CPU float32
        # positions then go
        # through its C kernel (the same features; a cheaper backward into the table, and the positions' own).
        self.use_kernel = False

    @property
    def use_hash(self) -> Tensor:
        """[levels] bool: which levels go through the hash."""
        return torch.arange(self.levels) >= self.dense_levels

    @property
    def out_dim(self) -> int:
        return self.levels * self.features

    def forward(self, x: Tensor, radii: Tensor | None = None) -> Tensor:
        """[N, 3] positions in [0, 1] -> [N, levels * features] features; with ``radii`` [N] (each position's
        footprint radius, same units) each level's features scaled by :meth:`footprint_weights`.

        Separable form: each axis contributes its lower/upper grid coordinate once ([N, L, 3, 2]); the 8 corner
        indices are their sums (dense levels) or XORs (hashed levels), and the trilinear blend is three lerps.
        """
        if self.use_kernel and x.device.type == "cpu" and x.dtype == torch.float32:
            features = hash_encode(x, self.table, self.resolution, self.dense_levels) * self.level_weight
        else:
            features = self.encode(x) * self.level_weight
        return features if radii is None else features * self.footprint_weights(radii)

    def footprint_weights(self, radii: Tensor) -> Tensor:
        """[N] footprint radii in [0, 1] units -> [N, levels * features] weights in (0, 1]: Zip-NeRF's feature
        downweighting, ``erf(1 / sqrt(8 r^2 n^2))`` for a level of resolution ``n``: about 1 where a level's cells
        are wider than the footprint, towards 0 where many cells fall inside it (their mean over an isotropic
        Gaussian of that radius is about zero). A zero radius gives 1 (a point)."""
        scaled = radii[:, None] * self.resolution[None, :] * math.sqrt(8.0)
        weight = torch.erf(1.0 / scaled.clamp_min(1e-12))
        return weight.repeat_interleave(self.features, dim=1)

    def set_active_levels(self, active: float) -> None:
        """Coarse-to-fine: weight 1 for levels below ``floor(active)``, a smooth ramp (1 - cos) / 2 of the fraction
        for the next, 0 above; ``active >= levels`` restores every level."""
        ramp = (torch.arange(self.levels, dtype=torch.float32) - active).neg().clamp(0.0, 1.0)
        weight = 0.5 * (1.0 - torch.cos(math.pi * ramp))
        self.level_weight.copy_(weight.repeat_interleave(self.features).to(self.level_weight.device))

    def encode(self, x: Tensor) -> Tensor:
        """The unweighted encoding in PyTorch (the reference of the C kernel)."""
        n = x.shape[0]
        pos = x.clamp(0.0, 1.0)[:, None, :] * self.resolution[None, :, None]  # [N, L, 3]
        cell = torch.minimum(pos.floor(), self.max_cell[None, :, None].to(pos.dtype))
        frac = pos - cell
        ends = cell.int()[..., None] + self.upper  # [N, L, 3, 2]
        nd = self.dense_levels
        d = ends[:, :nd] * self.dense_strides
        h = ends[:, nd:] * self.hash_primes
        dense_index = d[:, :, 0, :, None, None] + d[:, :, 1, None, :, None] + d[:, :, 2, None, None, :]
        hash_index = (h[:, :, 0, :, None, None] ^ h[:, :, 1, None, :, None] ^ h[:, :, 2, None, None, :]) & (
            self.table_size - 1
        )
        index = torch.cat([dense_index, hash_index], dim=1) + self.level_offset  # [N, L, 2, 2, 2]
        f = self.table.index_select(0, index.reshape(-1)).view(*index.shape, self.features)
        fx, fy, fz = frac.unbind(-1)  # [N, L] each
        f = f[:, :, :, :, 0] + (f[:, :, :, :, 1] - f[:, :, :, :, 0]) * fz[:, :, None, None, None]
        f = f[:, :, :, 0] + (f[:, :, :, 1] - f[:, :, :, 0]) * fy[:, :, None, None]
        f = f[:, :, 0] + (f[:, :, 1] - f[:, :, 0]) * fx[:, :, None]
        return f.reshape(n, -1)


def spherical_harmonics(d: Tensor, bands: int) -> Tensor:
    """The first ``bands`` bands (``bands^2`` coefficients) of :func:`spherical_harmonics_deg4` [N, bands^2]."""
    return spherical_harmonics_deg4(d)[:, : bands * bands]


def spherical_harmonics_deg4(d: Tensor) -> Tensor:
    """Real spherical harmonics up to degree 4 (16 coefficients) of unit directions [N, 3] -> [N, 16]."""
    x, y, z = d.unbind(-1)
    xx, yy, zz = x * x, y * y, z * z
    return torch.stack(
        [
            torch.full_like(x, 0.28209479177387814),
            -0.48860251190291987 * y,
            0.48860251190291987 * z,
            -0.48860251190291987 * x,
            1.0925484305920792 * x * y,
            -1.0925484305920792 * y * z,
            0.94617469575755997 * zz - 0.31539156525251999,
            -1.0925484305920792 * x * z,
            0.54627421529603959 * (xx - yy),
            0.59004358992664352 * y * (-3.0 * xx + yy),
            2.8906114426405538 * x * y * z,
            0.45704579946446572 * y * (1.0 - 5.0 * zz),
            0.3731763325901154 * z * (5.0 * zz - 3.0),
            0.45704579946446572 * x * (1.0 - 5.0 * zz),
            1.4453057213202769 * z * (xx - yy),
            0.59004358992664352 * x * (-xx + 3.0 * yy),
        ],
        dim=-1,
    )


def _mlp(in_dim: int, hidden: int, out_dim: int, layers: int) -> nn.Sequential:
    mods: list[nn.Module] = []
    dim = in_dim
    for _ in range(layers - 1):
        mods += [nn.Linear(dim, hidden), nn.ReLU(inplace=True)]
        dim = hidden
    mods.append(nn.Linear(dim, out_dim))
    return nn.Sequential(*mods)


class RadianceField(nn.Module):
    """sigma, h = MLP_pos(hash(x)); c = MLP_view(h, SH(d)) -- the paper's field (SH of ``sh_bands`` bands: 4, the
    paper's 16 coefficients; 1, a constant, leaves the colour independent of the direction).

    ``forward(positions [N, 3] normalised, dirs [N, 3] unit) -> (density [N] per normalised unit, rgb [N, 3])``.
    Every reading takes optional ``radii`` [N]: each position's footprint radius in normalised units (a pixel's
    cone at the sample's distance); None reads points. See :meth:`HashEncoding.footprint_weights`.
    """

    GEO_FEATURES = 15

    def __init__(
        self,
        levels: int = 16,
        features: int = 2,
        log2_size: int = 17,
        max_resolution: int = 1024,
        hidden_dim: int = 64,
        sh_bands: int = 4,
    ) -> None:
        super().__init__()
        if not 1 <= sh_bands <= 4:
            raise ValueError(f"sh_bands must be 1-4, got {sh_bands}")
        self.sh_bands = sh_bands
        self.encoding = HashEncoding(levels, features, log2_size, 16, max_resolution)
        self.density_mlp = _mlp(self.encoding.out_dim, hidden_dim, 1 + self.GEO_FEATURES, 2)
        self.color_mlp = _mlp(sh_bands * sh_bands + self.GEO_FEATURES, hidden_dim, 3, 3)

    def features(self, positions: Tensor, radii: Tensor | None = None) -> Tensor:
        """[N, 3] normalised positions (and footprint radii [N], normalised units) -> the encoding's features."""
        return self.encoding((positions + 1.0) * 0.5, None if radii is None else radii * 0.5)

    def density(self, positions: Tensor, radii: Tensor | None = None) -> Tensor:
        """[N, 3] normalised positions -> [N] densities (per normalised unit of length)."""
        h = self.density_mlp(self.features(positions, radii))
        return trunc_exp(h[:, 0])

    def forward(self, positions: Tensor, dirs: Tensor, radii: Tensor | None = None) -> tuple[Tensor, Tensor]:
        h = self.density_mlp(self.features(positions, radii))
        density = trunc_exp(h[:, 0])
        sh = spherical_harmonics(dirs, self.sh_bands)
        rgb = torch.sigmoid(self.color_mlp(torch.cat([sh, h[:, 1:]], dim=-1)))
        return density, rgb

    # The same field split for inference (voxnerf.inference.fast_path): the colour MLP's first layer is linear in
    # cat([SH(d), geo]), so its direction part is computed once per ray instead of once per sample.

    def geometry(self, positions: Tensor, radii: Tensor | None = None) -> tuple[Tensor, Tensor]:
        """[N, 3] normalised positions -> (density [N], geometry features [N, GEO_FEATURES])."""
        h = self.density_mlp(self.features(positions, radii))
        return trunc_exp(h[:, 0]), h[:, 1:]

    def direction_features(self, dirs: Tensor) -> Tensor:
        """[R, 3] unit directions -> [R, hidden]: the direction part of the colour MLP's first layer, bias
        included."""
        first = self.color_mlp[0]
        n_sh = first.in_features - self.GEO_FEATURES
        return nn.functional.linear(spherical_harmonics(dirs, self.sh_bands), first.weight[:, :n_sh], first.bias)

    def color(self, geo: Tensor, direction_features: Tensor) -> Tensor:
        """Colour [N, 3] in [0, 1] from geometry features [N, GEO_FEATURES] and the direction features [N, hidden]
        of each sample's ray: ``forward``'s colour, up to float rounding."""
        first = self.color_mlp[0]
        n_sh = first.in_features - self.GEO_FEATURES
        x = torch.addmm(direction_features, geo, first.weight[:, n_sh:].t()).relu_()
        for layer in self.color_mlp[2:-1]:
            x = layer(x)
        return torch.sigmoid(self.color_mlp[-1](x))
