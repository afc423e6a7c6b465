"""The CPU hash-encoding kernel against the pure-PyTorch encoding: same features, same table gradient, one
registration that torch.compile and autograd accept, and a clear fallback where it cannot be built."""

import json

import pytest
import torch

from voxnerf.cli import main
from voxnerf.config import TrainConfig
from voxnerf.model import hash_kernel
from voxnerf.model.field import HashEncoding
from voxnerf.model.voxnerf_model import field_for
from voxnerf.training.run import train

pytestmark = pytest.mark.skipif(not hash_kernel.available(), reason="the hash kernel could not be built here")

ENCODINGS = [
    dict(levels=12, features=2, log2_size=17, base_resolution=16, max_resolution=1024),  # the cpu preset's
    dict(levels=6, features=1, log2_size=10, base_resolution=4, max_resolution=300),
    dict(levels=3, features=4, log2_size=12, base_resolution=2, max_resolution=64),
    dict(levels=1, features=3, log2_size=14, base_resolution=8, max_resolution=8),  # one dense level
]


def _positions(n: int = 4000) -> torch.Tensor:
    """Random points, the box's faces and corners, grid-aligned points and points outside (clamped)."""
    gen = torch.Generator().manual_seed(0)
    x = torch.rand(n, 3, generator=gen)
    x[:8] = torch.tensor([[a, b, c] for a in (0.0, 1.0) for b in (0.0, 1.0) for c in (0.0, 1.0)])
    x[8:200] = torch.randint(0, 65, (192, 3), generator=gen).float() / 64  # on cell boundaries of many levels
    x[200:260] = x[200:260] * 3 - 1  # outside [0, 1]
    x[260] = torch.tensor([float("inf"), -float("inf"), 0.5])
    return x


def _encoding(spec: dict) -> HashEncoding:
    torch.manual_seed(1)
    enc = HashEncoding(**spec)
    with torch.no_grad():
        enc.table.uniform_(-1.0, 1.0)
    return enc


@pytest.mark.parametrize("spec", ENCODINGS)
def test_kernel_features_equal_the_pytorch_encoding_bit_for_bit(spec):
    enc, x = _encoding(spec), _positions()
    assert enc.dense_levels >= 1
    reference = enc(x)
    enc.use_kernel = True
    assert torch.equal(enc(x), reference)


@pytest.mark.parametrize("spec", ENCODINGS)
def test_kernel_table_gradient_matches_autograd_of_the_pytorch_encoding(spec):
    enc, x = _encoding(spec), _positions()
    grad_out = torch.randn(x.shape[0], enc.out_dim, generator=torch.Generator().manual_seed(2))
    (reference,) = torch.autograd.grad(enc(x), enc.table, grad_out)
    enc.use_kernel = True
    (grad,) = torch.autograd.grad(enc(x), enc.table, grad_out)
    assert reference.abs().sum() > 0
    torch.testing.assert_close(grad, reference, rtol=1e-5, atol=1e-5)


@pytest.mark.parametrize("threads", [1, 2, 5, 64])
def test_kernel_result_does_not_depend_on_the_thread_count(threads):
    enc, x = _encoding(ENCODINGS[0]), _positions()
    enc.use_kernel = True
    grad_out = torch.randn(x.shape[0], enc.out_dim, generator=torch.Generator().manual_seed(3))
    before = torch.get_num_threads()
    try:
        torch.set_num_threads(1)
        out1 = enc(x)
        (g1,) = torch.autograd.grad(out1, enc.table, grad_out)
        torch.set_num_threads(threads)
        out = enc(x)
        (g,) = torch.autograd.grad(out, enc.table, grad_out)
    finally:
        torch.set_num_threads(before)
    assert torch.equal(out, out1) and torch.equal(g, g1)  # each level is one thread's, whatever the count


def test_kernel_ops_pass_torch_library_checks():
    enc, x = _encoding(ENCODINGS[1]), _positions(300)
    args = (x, enc.table, enc.resolution, enc.dense_levels)
    torch.library.opcheck(hash_kernel.hash_encode, args)
    grad_out = torch.randn(x.shape[0], enc.out_dim)
    table = enc.table.detach()  # its own gradient (a second derivative) is not defined
    torch.library.opcheck(hash_kernel.hash_encode_x_grad, (grad_out, x, table, enc.resolution, enc.dense_levels))


def test_kernel_inside_torch_compile_matches_eager():
    enc, x = _encoding(ENCODINGS[1]), _positions(512)
    enc.use_kernel = True

    def loss(p):
        return (enc(p) ** 2).sum()

    eager = loss(x)
    (g_eager,) = torch.autograd.grad(eager, enc.table)
    compiled = torch.compile(loss, dynamic=False, fullgraph=True)(x)
    (g_compiled,) = torch.autograd.grad(compiled, enc.table)
    torch.testing.assert_close(compiled, eager)
    torch.testing.assert_close(g_compiled, g_eager)


@pytest.mark.parametrize("spec", ENCODINGS)
def test_kernel_position_gradient_matches_autograd_of_the_pytorch_encoding(spec):
    enc, x = _encoding(spec), _positions()
    grad_out = torch.randn(x.shape[0], enc.out_dim, generator=torch.Generator().manual_seed(4))
    xr = x.clone().requires_grad_(True)
    reference, ref_table = torch.autograd.grad(enc(xr), (xr, enc.table), grad_out)
    enc.use_kernel = True
    xk = x.clone().requires_grad_(True)
    grad, grad_table = torch.autograd.grad(enc(xk), (xk, enc.table), grad_out)
    assert reference.abs().sum() > 0
    assert torch.equal(grad[200:261] == 0, reference[200:261] == 0)  # clamped axes (outside, infinite) get none
    torch.testing.assert_close(grad, reference, rtol=1e-4, atol=1e-3)
    torch.testing.assert_close(grad_table, ref_table, rtol=1e-5, atol=1e-5)


def test_kernel_position_gradient_alone_leaves_the_table_out():
    enc, x = _encoding(ENCODINGS[1]), _positions(300).clamp(0, 1)
    enc.use_kernel = True
    enc.table.requires_grad_(False)
    x.requires_grad_(True)
    enc(x).sum().backward()
    assert x.grad is not None and x.grad.abs().sum() > 0 and enc.table.grad is None


@pytest.mark.parametrize("threads", [1, 3, 64])
def test_kernel_position_gradient_does_not_depend_on_the_thread_count(threads):
    enc, x = _encoding(ENCODINGS[0]), _positions(1000)
    enc.use_kernel = True
    grad_out = torch.randn(x.shape[0], enc.out_dim, generator=torch.Generator().manual_seed(5))
    before = torch.get_num_threads()
    try:
        torch.set_num_threads(1)
        g1 = hash_kernel.hash_encode_x_grad(grad_out, x, enc.table, enc.resolution, enc.dense_levels)
        torch.set_num_threads(threads)
        g = hash_kernel.hash_encode_x_grad(grad_out, x, enc.table, enc.resolution, enc.dense_levels)
    finally:
        torch.set_num_threads(before)
    assert torch.equal(g, g1)  # each point is one thread's, its sum over levels in one order


def test_nan_positions_are_refused_with_a_clear_error():
    enc = _encoding(ENCODINGS[1])
    enc.use_kernel = True
    x = _positions()[:100].clone()
    x[5, 1] = float("nan")
    with pytest.raises(ValueError, match="1 of 100 positions are NaN"):
        enc(x)


def test_wrong_inputs_are_refused():
    enc = _encoding(ENCODINGS[1])
    with pytest.raises(ValueError, match="float32"):
        hash_kernel.hash_encode(torch.rand(4, 3, dtype=torch.float64), enc.table, enc.resolution, 1)
    with pytest.raises(ValueError, match=r"\[N, 3\]"):
        hash_kernel.hash_encode(torch.rand(4, 2), enc.table, enc.resolution, 1)


def test_the_config_switch_and_the_field_factory():
    assert field_for(TrainConfig()).encoding.use_kernel
    assert not field_for(TrainConfig(hash_kernel=False)).encoding.use_kernel


def test_without_a_compiler_the_kernel_is_unavailable_and_says_why(tmp_path, monkeypatch):
    monkeypatch.setenv("VOXNERF_CACHE", str(tmp_path))  # an empty cache: it would have to be built
    monkeypatch.setenv("PATH", str(tmp_path))
    monkeypatch.delenv("CC", raising=False)
    hash_kernel._library.cache_clear()
    try:
        assert not hash_kernel.available()
        assert "no C compiler" in hash_kernel.unavailable_reason()
        assert not field_for(TrainConfig()).encoding.use_kernel
    finally:
        hash_kernel._library.cache_clear()
    monkeypatch.undo()
    assert hash_kernel.available()


def test_a_failed_build_leaves_nothing_in_the_cache(tmp_path, monkeypatch):
    compiler = tmp_path / "cc"
    compiler.write_text("#!/bin/sh\necho 'cc: fatal error: out of disk' >&2\nexit 1\n")
    compiler.chmod(0o755)
    monkeypatch.setenv("VOXNERF_CACHE", str(tmp_path / "cache"))
    monkeypatch.setenv("CC", str(compiler))
    hash_kernel._library.cache_clear()
    try:
        assert "out of disk" in hash_kernel.unavailable_reason()
        assert list((tmp_path / "cache").iterdir()) == []
    finally:
        hash_kernel._library.cache_clear()


def test_the_report_says_whether_the_kernel_ran(small_room, tmp_path):
    """The default run reports the kernel's stage as run; ``voxnerf train --no-hash-kernel`` as disabled."""
    report = train(small_room, tmp_path / "kernel", TrainConfig(max_iters=2, compile=False, downscale=4,
                   final_eval=False), resume=False, progress_bar=False)
    stage = next(s for s in report.stages if s.name == "hash_kernel")
    assert stage.ran and "C kernel" in stage.why
    assert main(["train", str(small_room), "--out", str(tmp_path / "torch"), "--max-iters", "2", "--no-compile",
                 "--downscale", "4", "--no-hash-kernel"]) == 0
    report = json.loads((tmp_path / "torch" / "report.json").read_text())
    stage = next(s for s in report["stages"] if s["name"] == "hash_kernel")
    assert not stage["ran"] and "disabled (--no-hash-kernel)" in stage["why"]
    assert report["config"]["hash_kernel"] is False


def test_a_cached_library_that_does_not_load_is_reported_not_raised(tmp_path, monkeypatch):
    monkeypatch.setenv("VOXNERF_CACHE", str(tmp_path / "built"))
    hash_kernel._library.cache_clear()
    try:
        assert hash_kernel.available()  # builds into tmp_path / "built" (and stays loaded: never overwrite it)
        (built,) = (tmp_path / "built").glob("hashgrid-*.so")
        corrupt = tmp_path / "corrupt" / built.name
        corrupt.parent.mkdir()
        corrupt.write_bytes(b"not a shared library")  # where the cache would find it, so nothing is built
        monkeypatch.setenv("VOXNERF_CACHE", str(corrupt.parent))
        hash_kernel._library.cache_clear()
        reason = hash_kernel.unavailable_reason()
        assert reason.startswith("loading ") and built.name in reason
        assert not field_for(TrainConfig()).encoding.use_kernel
    finally:
        hash_kernel._library.cache_clear()
