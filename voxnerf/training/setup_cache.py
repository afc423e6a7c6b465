"""A cache of the set-up's per-pixel ray casts, shared by the runs of one scene.

The pseudo-depth and first-hit stages cast a ray through every training pixel (seconds on a real scan). A second
run on the same scene with the same prior (a re-run, the next configuration of a sweep) loads their results
instead. The key is a hash of everything a cast reads, not of file names or dates:

- the training rays: poses, intrinsics, lens, image size (:class:`voxnerf.training.pixels.TrainingPixels`), the
  scene box;
- what the rays are cast against (the prior's points and mesh, the octree) and any hint;
- the engine's own source (every ``.py`` and ``.c`` file of the package), torch's version and the device type:
  a code change misses instead of loading a result the new code would not give.

Entries live in ``$VOXNERF_CACHE/setup`` (:func:`voxnerf.native.cache_dir`) as ``<key>.pt`` (written atomically);
beyond :data:`MAX_BYTES` the least recently used are removed. A missing, unreadable or mismatched entry is cast
again and rewritten. ``TrainConfig.setup_cache=False`` bypasses the cache.
"""

from __future__ import annotations

import contextlib
import functools
import hashlib
import io
import os
from collections.abc import Callable, Iterable
from pathlib import Path

import numpy as np
import torch

from voxnerf import native
from voxnerf.image_io import write_atomic

MAX_BYTES = 2 * 1024**3
PerPixel = tuple[torch.Tensor, torch.Tensor]  # t float32 [N, H, W] (NaN where invalid), ok bool [N, H, W]


def cache_dir() -> Path:
    return native.cache_dir() / "setup"


@functools.cache
def engine_fingerprint() -> str:
    """sha256 of the package's source files (``.py`` and ``.c``, by relative path), torch's version."""
    root = Path(__file__).resolve().parents[1]
    h = hashlib.sha256(torch.__version__.encode())
    for path in sorted(p for p in root.rglob("*") if p.suffix in (".py", ".c") and p.is_file()):
        h.update(str(path.relative_to(root)).encode() + b"\0" + path.read_bytes() + b"\0")
    return h.hexdigest()


def cache_key(name: str, inputs: Iterable, device: torch.device) -> str:
    """sha256 of ``name``, the engine, the device type and ``inputs`` (tensors, arrays, numbers, strings, None,
    and lists / tuples / dicts of them; a tensor by dtype, shape and values)."""
    h = hashlib.sha256(f"{name}\0{engine_fingerprint()}\0{device.type}\0".encode())
    for item in inputs:
        _update(h, item)
    return h.hexdigest()


def _update(h, item) -> None:
    if isinstance(item, torch.Tensor):
        item = item.detach().cpu().contiguous().numpy()
    if isinstance(item, np.ndarray):
        array = np.ascontiguousarray(item)
        h.update(f"a{array.dtype.str}{array.shape}".encode())
        h.update(array.tobytes())
    elif isinstance(item, (list, tuple)):
        h.update(f"l{len(item)}".encode())
        for value in item:
            _update(h, value)
    elif isinstance(item, dict):
        h.update(f"d{len(item)}".encode())
        for key in sorted(item):
            _update(h, key)
            _update(h, item[key])
    elif item is None or isinstance(item, (str, int, float, bool)):
        h.update(f"{type(item).__name__}:{item!r}\0".encode())
    else:
        raise TypeError(f"cannot key the set-up cache on a {type(item).__name__}")


def cached_per_pixel(name: str, inputs: Iterable, shape: tuple[int, int, int], device: torch.device,
                     compute: Callable[[], PerPixel], enabled: bool = True) -> tuple[PerPixel, bool]:
    """``compute()``'s (t, ok), or the same loaded from the cache -> ((t, ok) on ``device``, whether loaded).

    ``shape`` is (N, H, W) of both; an entry of another shape or dtype counts as missing."""
    if not enabled:
        return compute(), False
    path = cache_dir() / f"{cache_key(name, inputs, device)}.pt"
    loaded = _load(path, shape)
    if loaded is not None:
        return (loaded[0].to(device), loaded[1].to(device)), True
    t, ok = compute()
    _store(path, t, ok)
    return (t, ok), False


def _load(path: Path, shape: tuple[int, int, int]) -> PerPixel | None:
    try:
        entry = torch.load(path, map_location="cpu", weights_only=True)
        t, ok = entry["t"], entry["ok"]
    except Exception:  # absent, truncated or not ours (torch.load raises many kinds): cast again
        return None
    if not (isinstance(t, torch.Tensor) and isinstance(ok, torch.Tensor) and tuple(t.shape) == tuple(ok.shape)
            == tuple(shape) and t.dtype == torch.float32 and ok.dtype == torch.bool):
        return None
    with contextlib.suppress(OSError):
        os.utime(path)  # recently used: evicted last
    return t, ok


def _store(path: Path, t: torch.Tensor, ok: torch.Tensor) -> None:
    """Write the entry (atomically) and evict; a cache that cannot be written is no error."""
    buffer = io.BytesIO()
    torch.save({"t": t.detach().cpu(), "ok": ok.detach().cpu()}, buffer)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        write_atomic(path, buffer.getvalue())
        evict(path.parent, MAX_BYTES)
    except OSError:
        pass


def evict(directory: Path, max_bytes: int) -> None:
    """Remove the least recently used ``*.pt`` entries of ``directory`` until they total at most ``max_bytes``."""
    entries = []
    for path in directory.glob("*.pt"):
        try:
            stat = path.stat()
        except OSError:
            continue
        entries.append((stat.st_mtime_ns, stat.st_size, path))
    total = sum(size for _, size, _ in entries)
    for _, size, path in sorted(entries, key=lambda e: e[0]):
        if total <= max_bytes:
            break
        path.unlink(missing_ok=True)
        total -= size
