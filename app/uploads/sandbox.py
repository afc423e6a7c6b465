"""An upload's validation in a child process under a memory and a time limit: a hostile file costs a 4xx, never
the API process.

:func:`validate_in_child` hands a :class:`StagedUpload` (files already on disk under ``data_dir/staging``) to a
child that unpacks and checks it (:func:`app.uploads.validation.validate_upload`) and answers with a
:class:`ValidatedScene` or a refusal. Children are forked from a multiprocessing *forkserver* that imported the
validator (and with it the engine's scene checks and torch) once: the API process itself never imports torch,
and a validation starts in milliseconds instead of importing torch anew. Each child, before it reads a byte:

* caps its address space (``RLIMIT_AS``) at what it starts with plus ``upload_validation_memory_bytes``: an
  allocation past it raises MemoryError, answered 413 naming the setting;
* caps its CPU time (``RLIMIT_CPU``) a little past ``upload_validation_timeout_s``, which ends it even if the
  API is gone.

The API waits at most ``upload_validation_timeout_s`` (wall clock), then kills the child: 422. A child killed
by a signal (a decoder crashing on hostile bytes, the kernel's OOM killer) is a 422 too; an unexpected
exception in the validator (a bug, a full disk) is the server's error (RuntimeError, a 500).
"""

from __future__ import annotations

import logging
import math
import multiprocessing
import resource
import signal
import sys
from multiprocessing.connection import Connection, wait

from app.core.settings import Settings
from app.uploads.rules import StagedUpload, UploadError, ValidatedScene

log = logging.getLogger(__name__)

# imported once by the forkserver, so that each child starts with them loaded (open3d: a prior's sigma estimate)
VALIDATOR_MODULES = ["app.uploads.validation", "voxnerf.data.scene", "voxnerf.prior.loading", "open3d"]


def _preload() -> list[str]:
    """What the forkserver imports: the validator's modules and the program's main module, which each child
    would otherwise import again (a script must guard its start with ``if __name__ == "__main__":``; a module
    run with ``-m``, e.g. ``python -m app.serve``, is preloaded by name, so a child re-runs only its own
    lines)."""
    spec = getattr(sys.modules["__main__"], "__spec__", None)
    by_name = [spec.name] if spec is not None and not spec.name.endswith("__main__") else []
    return ["__main__", *by_name, *VALIDATOR_MODULES]


_CONTEXT = multiprocessing.get_context("forkserver")
_CONTEXT.set_forkserver_preload(_preload())
REAP_TIMEOUT_S = 10.0  # how long to wait for a child that was killed or has answered to exit
CPU_GRACE_S = 5  # CPU seconds past the wall-clock timeout: the API's kill comes first; this ends an orphan


def validate_in_child(upload: StagedUpload, settings: Settings) -> ValidatedScene:
    """Validate ``upload`` in a fresh child process (see the module's docstring); UploadError for a refusal."""
    receiver, sender = _CONTEXT.Pipe(duplex=False)
    child = _CONTEXT.Process(
        target=_child_main, args=(upload, settings, sender), name="voxnerf-upload-validation", daemon=True
    )
    child.start()
    sender.close()  # the child holds the only sending end: its death reads as EOF here
    try:
        outcome = _await_outcome(child, receiver, settings.upload_validation_timeout_s)
    finally:
        receiver.close()
        if child.is_alive():
            child.kill()
        child.join(REAP_TIMEOUT_S)
    return _answer(outcome, child.exitcode, settings)


def _await_outcome(child, receiver: Connection, timeout_s: float) -> tuple | None:
    """The child's message; ``("timeout",)`` when none came within ``timeout_s``; None when it died first."""
    ready = wait([receiver, child.sentinel], timeout_s)
    if not ready:
        return ("timeout",)
    if receiver in ready or receiver.poll():
        try:
            return receiver.recv()
        except EOFError:
            pass
    child.join(REAP_TIMEOUT_S)
    return None


def _answer(outcome: tuple | None, exitcode: int | None, settings: Settings) -> ValidatedScene:
    """The ValidatedScene of an ``("ok", scene)`` outcome; UploadError or RuntimeError for any other."""
    if outcome is not None and outcome[0] == "ok":
        return outcome[1]
    if outcome is not None and outcome[0] == "refused":
        raise UploadError(outcome[1], outcome[2])
    if outcome is not None and outcome[0] == "timeout":
        raise UploadError(
            422,
            f"validating the upload took longer than {settings.upload_validation_timeout_s:g} s "
            "(VOXNERF_UPLOAD_VALIDATION_TIMEOUT_S)",
        )
    if outcome is not None:  # ("error", text): the validator's own failure, logged by the child
        raise RuntimeError(f"upload validation failed: {outcome[1]}")
    if exitcode is not None and exitcode < 0:
        name = signal.Signals(-exitcode).name if -exitcode in signal.valid_signals() else str(-exitcode)
        log.warning("an upload's validation process was killed by %s", name)
        raise UploadError(422, f"the upload could not be validated: its validation process was killed by {name}")
    raise RuntimeError(f"upload validation process exited with status {exitcode} without an answer")


def _child_main(upload: StagedUpload, settings: Settings, sender: Connection) -> None:
    """In the child: apply the limits, validate, send one outcome tuple."""
    _limit_resources(settings)
    from app.uploads.validation import validate_upload  # preloaded by the forkserver: no import happens here

    try:
        outcome: tuple = ("ok", validate_upload(upload, settings))
    except UploadError as err:
        outcome = ("refused", err.status_code, err.detail)
    except MemoryError:
        outcome = ("refused", 413, _memory_detail(settings))
    except Exception as err:  # reported to the API as a server error; the traceback goes to this log
        log.exception("upload validation failed")
        outcome = ("error", f"{type(err).__name__}: {err}")
    try:
        sender.send(outcome)
    except MemoryError:  # the answer itself did not fit
        sender.send(("refused", 413, _memory_detail(settings)))
    sender.close()


def _memory_detail(settings: Settings) -> str:
    return (
        f"validating the upload needs more than {settings.upload_validation_memory_bytes // 2**20} MiB of "
        "memory (VOXNERF_UPLOAD_VALIDATION_MEMORY_BYTES)"
    )


def _limit_resources(settings: Settings) -> None:
    """This process's address space capped at its current size plus the budget; its CPU time at the timeout."""
    limit_child(settings.upload_validation_memory_bytes, settings.upload_validation_timeout_s)


def limit_child(memory_bytes: int, timeout_s: float) -> None:
    """The limits of a child that reads untrusted or large files (an upload's validation, a scene read for the
    viewer): its address space capped at its current size plus ``memory_bytes`` (past it: MemoryError), its CPU
    time a little past ``timeout_s`` (ends it even if the API is gone), torch on one thread."""
    _lower_limit(resource.RLIMIT_AS, _address_space_bytes() + memory_bytes)
    _lower_limit(resource.RLIMIT_CPU, math.ceil(timeout_s) + CPU_GRACE_S)
    torch = sys.modules.get("torch")  # loaded by the forkserver; one thread keeps the address space small
    if torch is not None:
        torch.set_num_threads(1)


def _lower_limit(kind: int, soft: int) -> None:
    _, hard = resource.getrlimit(kind)
    resource.setrlimit(kind, (soft if hard == resource.RLIM_INFINITY else min(soft, hard), hard))


def _address_space_bytes() -> int:
    """This process's virtual memory size (``/proc/self/statm``: pages)."""
    with open("/proc/self/statm") as statm:
        pages = int(statm.read().split()[0])
    return pages * resource.getpagesize()
