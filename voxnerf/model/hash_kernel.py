"""The CPU hash-encoding kernel (``hashgrid.c``) as two torch custom ops, so ``torch.compile`` calls it.

Why: inductor's backward of the hash encoding zeroes the table's gradient and then makes one atomic float add
per sample, level, corner and feature. The kernel splits the work by level instead, so each thread adds into
its own slice of the gradient without atomics while that slice sits in cache (docs/performance.md, "Training
throughput and render time", measures both).

The kernel is plain C, built and loaded by :mod:`voxnerf.native`. Where it cannot be built (no compiler)
:func:`available` is False and the field keeps its pure-PyTorch path; it is never used on CUDA. Positions
that need a gradient go through it too (a third entry point, their gradient, for pose refinement).
"""

from __future__ import annotations

import ctypes
import functools
from pathlib import Path

import torch
from torch import Tensor

from voxnerf import native

SOURCE = Path(__file__).with_name("hashgrid.c")
_SIGNATURE = [ctypes.c_void_p, ctypes.c_int64, ctypes.c_void_p, ctypes.c_int, ctypes.c_int, ctypes.c_int64,
              ctypes.c_int, ctypes.c_void_p, ctypes.c_void_p, ctypes.c_int]
_SIGNATURE_X = [ctypes.c_void_p, ctypes.c_int64, ctypes.c_void_p, ctypes.c_void_p, ctypes.c_int, ctypes.c_int,
                ctypes.c_int64, ctypes.c_int, ctypes.c_void_p, ctypes.c_void_p, ctypes.c_int]


@functools.cache
def _library() -> ctypes.CDLL | str:
    """The loaded kernel, or a one-line reason why there is none."""
    return native.load(SOURCE, {"hash_encode_forward": _SIGNATURE, "hash_encode_backward": _SIGNATURE,
                                "hash_encode_backward_x": _SIGNATURE_X})


def available() -> bool:
    """Whether the kernel is built and loaded (building it on the first call)."""
    return not isinstance(_library(), str)


def loaded() -> bool:
    """Whether this process has loaded the kernel (nothing is built or loaded to answer)."""
    return native.loaded(_library)


def unavailable_reason() -> str | None:
    lib = _library()
    return lib if isinstance(lib, str) else None


def _lib() -> ctypes.CDLL:
    lib = _library()
    if isinstance(lib, str):
        raise RuntimeError(f"the CPU hash-encoding kernel is unavailable: {lib}")
    return lib


def _check(x: Tensor, table: Tensor, resolution: Tensor) -> None:
    for name, t in (("x", x), ("table", table), ("resolution", resolution)):
        if t.device.type != "cpu" or t.dtype != torch.float32:
            raise ValueError(f"hash kernel: {name} must be a float32 CPU tensor, got {t.dtype} on {t.device}")
    if x.dim() != 2 or x.shape[1] != 3:
        raise ValueError(f"hash kernel: x must be [N, 3], got {list(x.shape)}")
    if bool(torch.isnan(x).any()):  # infinities are clamped into the box, as by the PyTorch encoding
        raise ValueError(f"hash kernel: {int(torch.isnan(x).any(-1).sum())} of {x.shape[0]} positions are NaN")
    levels = resolution.shape[0]
    if table.dim() != 2 or table.shape[0] % levels:
        raise ValueError(f"hash kernel: table must be [levels * size, F], got {list(table.shape)} for {levels} levels")


@torch.library.custom_op("voxnerf::hash_encode", mutates_args=())
def hash_encode(x: Tensor, table: Tensor, resolution: Tensor, dense_levels: int) -> Tensor:
    """Features [N, L * F] of positions ``x`` [N, 3] in [0, 1] from ``table`` [L * T, F] (levels of resolution
    ``resolution`` [L], the first ``dense_levels`` indexed densely). Differentiable in ``table`` and ``x``."""
    _check(x, table, resolution)
    x, table, resolution = x.contiguous(), table.contiguous(), resolution.contiguous()
    levels, (rows, features) = resolution.shape[0], table.shape
    out = x.new_empty(x.shape[0], levels * features)
    _lib().hash_encode_forward(x.data_ptr(), x.shape[0], table.data_ptr(), levels, features, rows // levels,
                               dense_levels, resolution.data_ptr(), out.data_ptr(), torch.get_num_threads())
    return out


@hash_encode.register_fake
def _(x: Tensor, table: Tensor, resolution: Tensor, dense_levels: int) -> Tensor:
    return x.new_empty(x.shape[0], resolution.shape[0] * table.shape[1])


@torch.library.custom_op("voxnerf::hash_encode_table_grad", mutates_args=())
def hash_encode_table_grad(grad_out: Tensor, x: Tensor, resolution: Tensor, rows: int, dense_levels: int) -> Tensor:
    """The gradient [rows, F] of :func:`hash_encode`'s table, given the output's gradient [N, L * F]."""
    x, resolution = x.contiguous(), resolution.contiguous()
    levels = resolution.shape[0]
    features = grad_out.shape[1] // levels
    grad_out = grad_out.reshape(x.shape[0], levels, features).transpose(0, 1).contiguous()  # level-major
    grad = grad_out.new_empty(rows, features)
    _lib().hash_encode_backward(x.data_ptr(), x.shape[0], grad_out.data_ptr(), levels, features, rows // levels,
                                dense_levels, resolution.data_ptr(), grad.data_ptr(), torch.get_num_threads())
    return grad


@hash_encode_table_grad.register_fake
def _(grad_out: Tensor, x: Tensor, resolution: Tensor, rows: int, dense_levels: int) -> Tensor:
    return grad_out.new_empty(rows, grad_out.shape[1] // resolution.shape[0])


@torch.library.custom_op("voxnerf::hash_encode_x_grad", mutates_args=())
def hash_encode_x_grad(grad_out: Tensor, x: Tensor, table: Tensor, resolution: Tensor, dense_levels: int) -> Tensor:
    """The gradient [N, 3] of :func:`hash_encode`'s positions, given the output's gradient [N, L * F] (zero in an
    axis where the position lies outside [0, 1] and is clamped)."""
    x, table, resolution, grad_out = x.contiguous(), table.contiguous(), resolution.contiguous(), grad_out.contiguous()
    levels, (rows, features) = resolution.shape[0], table.shape
    grad = x.new_empty(x.shape[0], 3)
    _lib().hash_encode_backward_x(x.data_ptr(), x.shape[0], table.data_ptr(), grad_out.data_ptr(), levels,
                                  features, rows // levels, dense_levels, resolution.data_ptr(), grad.data_ptr(),
                                  torch.get_num_threads())
    return grad


@hash_encode_x_grad.register_fake
def _(grad_out: Tensor, x: Tensor, table: Tensor, resolution: Tensor, dense_levels: int) -> Tensor:
    return x.new_empty(x.shape[0], 3)


def _setup_context(ctx, inputs, output) -> None:
    x, table, resolution, dense_levels = inputs
    ctx.save_for_backward(x, table, resolution)
    ctx.rows, ctx.dense_levels = table.shape[0], dense_levels


def _backward(ctx, grad_out: Tensor):
    x, table, resolution = ctx.saved_tensors
    grad_x = grad_table = None
    if ctx.needs_input_grad[0]:
        grad_x = hash_encode_x_grad(grad_out, x, table, resolution, ctx.dense_levels)
    if ctx.needs_input_grad[1]:
        grad_table = hash_encode_table_grad(grad_out, x, resolution, ctx.rows, ctx.dense_levels)
    return grad_x, grad_table, None, None


hash_encode.register_autograd(_backward, setup_context=_setup_context)
