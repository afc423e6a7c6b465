"""Plain-C kernels of the CPU paths: compiled on first use, cached, loaded with ctypes.

Each kernel is one C source file beside this module (no Python or torch headers). It is compiled with the C
compiler that ``torch.compile`` already needs on the CPU, once per source version and flags, into
``$VOXNERF_CACHE`` (default ``~/.cache/voxnerf``). Where it cannot be built or loaded, :func:`load` says why in
one line and the callers keep their pure-PyTorch paths.
"""

from __future__ import annotations

import ctypes
import functools
import hashlib
import os
import shutil
import subprocess
import tempfile
from pathlib import Path

# -ffp-contract=off: no fused multiply-adds, so float arithmetic rounds as torch's separate operations do.
CFLAGS = ("-O3", "-std=c11", "-shared", "-fPIC", "-pthread", "-ffp-contract=off")


def cache_dir() -> Path:
    return Path(os.environ.get("VOXNERF_CACHE") or Path.home() / ".cache" / "voxnerf")


def _compiler() -> str | None:
    for name in (os.environ.get("CC"), "cc", "gcc", "clang"):
        if name and shutil.which(name):
            return name
    return None


def _build(compiler: str, source: Path, target: Path) -> None:
    """Compile ``source`` into ``target`` (written to a temporary name, then renamed)."""
    target.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.NamedTemporaryFile(dir=target.parent, suffix=".so", delete=False) as tmp:
        partial = Path(tmp.name)
    try:
        subprocess.run([compiler, *CFLAGS, str(source), "-o", str(partial)], check=True,
                       capture_output=True, text=True)
        os.replace(partial, target)
    finally:
        partial.unlink(missing_ok=True)


def loaded(library: functools._lru_cache_wrapper) -> bool:
    """Whether ``library`` (a cached loader of :func:`load`) has loaded its kernel in this process, without
    building or loading it."""
    return library.cache_info().currsize > 0 and not isinstance(library(), str)


def load(source: Path, signatures: dict[str, list]) -> ctypes.CDLL | str:
    """``source`` built (when not cached) and loaded, with each function of ``signatures`` (name -> ctypes
    argument types; they return void) declared; or a one-line reason why there is none."""
    digest = hashlib.sha256(source.read_bytes() + " ".join(CFLAGS).encode()).hexdigest()[:16]
    target = cache_dir() / f"{source.stem}-{digest}.so"
    if not target.is_file():
        compiler = _compiler()
        if compiler is None:
            return "no C compiler (cc, gcc or clang) on PATH"
        try:
            _build(compiler, source, target)
        except (OSError, subprocess.CalledProcessError) as exc:
            detail = (getattr(exc, "stderr", None) or str(exc)).strip()
            return f"building {source.name} failed: {detail.splitlines()[-1] if detail else exc}"
    try:
        lib = ctypes.CDLL(str(target))
    except OSError as exc:  # e.g. a cache on a noexec mount, or a library built for another machine
        return f"loading {target} failed: {exc}"
    for name, args in signatures.items():
        fn = getattr(lib, name)
        fn.argtypes, fn.restype = args, None
    return lib
