"""A disk that fills up under a worker: the ``ENOSPC`` / ``EDQUOT`` error behind whatever a write raised."""

from __future__ import annotations

import errno

DISK_FULL_ERRNOS = (errno.ENOSPC, errno.EDQUOT)
DISK_FULL = "the disk filled up"
"""How a worker's error message begins when the data disk filled up under it."""


def disk_full_cause(err: BaseException) -> OSError | None:
    """The ``ENOSPC``/``EDQUOT`` OSError behind ``err`` (itself, or its cause or context, however deep), or None."""
    seen: set[int] = set()
    current: BaseException | None = err
    while current is not None and id(current) not in seen:
        if isinstance(current, OSError) and current.errno in DISK_FULL_ERRNOS:
            return current
        seen.add(id(current))
        current = current.__cause__ or current.__context__
    return None


def disk_full_message(err: BaseException, writing: str) -> str | None:
    """``"the disk filled up while <writing> (No space left on device)"`` when ``err`` comes from a full disk,
    else None."""
    cause = disk_full_cause(err)
    return None if cause is None else f"{DISK_FULL} while {writing} ({cause.strerror})"
