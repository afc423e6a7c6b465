"""A cache of the set-up's per-pixel ray casts, shared by the runs of one scene.

The pseudo-depth and first-hit stages cast a ray through every training pixel, and the octree carving traces
millions of measured rays (seconds on a real scan). A second run on the same scene with the same prior (a re-run,
the next configuration of a sweep) loads their results instead. The key is a hash of everything a stage reads,
not of file names or dates:

- the training rays: poses, intrinsics, lens, image size (:class:`voxnerf.training.pixels.TrainingPixels`), the
  scene box;
- what the rays are cast against (the prior's points and mesh, the octree), any hint, the measured depths;
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
from voxnerf.data.image_io import write_atomic

MAX_BYTES = 2 * 1024**3
PerPixel = tuple[torch.Tensor, torch.Tensor]  # t float32 [N, H, W] (NaN where invalid), ok bool [N, H, W]
Entry = dict[str, torch.Tensor]  # one stage's result, by name


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


def cached(name: str, inputs: Iterable, device: torch.device, compute: Callable[[], Entry],
           fits: Callable[[Entry], bool], enabled: bool = True) -> tuple[Entry, bool]:
    """``compute()``'s tensors (by name), or the same loaded from the cache -> (tensors on ``device``, whether
    loaded). An entry that ``fits`` refuses (or that is not a dict of tensors) counts as missing."""
    if not enabled:
        return compute(), False
    path = cache_dir() / f"{cache_key(name, inputs, device)}.pt"
    loaded = _load(path, fits)
    if loaded is not None:
        return {key: value.to(device) for key, value in loaded.items()}, True
    entry = compute()
    _store(path, entry)
    return entry, False


def cached_per_pixel(name: str, inputs: Iterable, shape: tuple[int, int, int], device: torch.device,
                     compute: Callable[[], PerPixel], enabled: bool = True) -> tuple[PerPixel, bool]:
    """:func:`cached` for a per-pixel cast: (t, ok) -> ((t, ok) on ``device``, whether loaded).

    ``shape`` is (N, H, W) of both; an entry of another shape or dtype counts as missing."""

    def fits(entry: Entry) -> bool:
        t, ok = entry.get("t"), entry.get("ok")
        return (isinstance(t, torch.Tensor) and isinstance(ok, torch.Tensor) and tuple(t.shape) == tuple(ok.shape)
                == tuple(shape) and t.dtype == torch.float32 and ok.dtype == torch.bool)

    entry, loaded = cached(name, inputs, device, lambda: dict(zip(("t", "ok"), compute(), strict=True)), fits,
                           enabled)
    return (entry["t"], entry["ok"]), loaded


def _load(path: Path, fits: Callable[[Entry], bool]) -> Entry | None:
    try:
        entry = torch.load(path, map_location="cpu", weights_only=True)
    except Exception:  # absent, truncated or not ours (torch.load raises many kinds): compute again
        return None
    if not (isinstance(entry, dict) and all(isinstance(v, torch.Tensor) for v in entry.values()) and fits(entry)):
        return None
    with contextlib.suppress(OSError):
        os.utime(path)  # recently used: evicted last
    return entry


def _store(path: Path, entry: Entry) -> None:
    """Write the entry (atomically) and evict; a cache that cannot be written is no error."""
    buffer = io.BytesIO()
    torch.save({key: value.detach().cpu() for key, value in entry.items()}, buffer)
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
