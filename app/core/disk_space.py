"""Room on disk: the data directory's quota and the filesystem's free-space floor, checked before the service
accepts work that writes files (an upload, an output job); the API answers a refusal with 507.

- ``data_dir_quota_bytes`` (unset: none): what ``data_dir`` holds, every file under it counted once
  (:func:`directory_bytes`), plus what the request brings, may not pass it;
- ``min_free_bytes``: the free space of ``data_dir``'s filesystem, less what the request brings, may not fall
  under it, so the checkpoints of the jobs already running still fit.

What a request "brings" is the caller's estimate: an upload's declared ``Content-Length`` before its body is
read, nothing more once it is unpacked (its files are then in ``data_dir/staging`` and counted), nothing for an
output (its size is unknown until rendered: the free-space floor is the margin).
"""

from __future__ import annotations

import os
import shutil
import stat
from pathlib import Path

from app.core.settings import Settings

GiB = 1024**3


class InsufficientStorage(Exception):
    """The data directory has no room for the work asked for (HTTP 507); ``detail`` says which limit."""

    status_code = 507

    def __init__(self, detail: str) -> None:
        super().__init__(detail)
        self.detail = detail


def directory_bytes(root: Path) -> int:
    """Bytes of every regular file under ``root`` (symbolic links not followed, a file removed meanwhile
    skipped); 0 when ``root`` does not exist."""
    total = 0
    pending = [root]
    while pending:
        try:
            entries = os.scandir(pending.pop())
        except (FileNotFoundError, NotADirectoryError):
            continue
        with entries:
            for entry in entries:
                try:
                    info = entry.stat(follow_symlinks=False)
                except FileNotFoundError:
                    continue
                if stat.S_ISDIR(info.st_mode):
                    pending.append(Path(entry.path))
                elif stat.S_ISREG(info.st_mode):
                    total += info.st_size
    return total


def _size(n: int) -> str:
    return f"{n / GiB:.2f} GiB" if n >= GiB // 10 else f"{n / 1024**2:.1f} MiB"


def require_room(settings: Settings, incoming_bytes: int = 0, counted_apart: int = 0, what: str = "this") -> None:
    """Raise InsufficientStorage unless ``incoming_bytes`` more fit under the quota and above the free floor.

    ``counted_apart``: bytes already under ``data_dir`` that the request's result will not keep (an upload's
    zip once it is unpacked), left out of the quota's count. ``what`` names the work in the message.
    """
    free = shutil.disk_usage(settings.data_dir).free
    if free - incoming_bytes < settings.min_free_bytes:
        raise InsufficientStorage(
            f"not enough free disk space for {what}: {_size(free)} free, {_size(incoming_bytes)} needed, and "
            f"{_size(settings.min_free_bytes)} is kept free for running jobs (VOXNERF_MIN_FREE_BYTES); "
            "delete scenes or jobs, or free space on the server"
        )
    quota = settings.data_dir_quota_bytes
    if quota is not None:
        used = directory_bytes(settings.data_dir) - counted_apart
        if used + incoming_bytes > quota:
            raise InsufficientStorage(
                f"the data directory's quota is full for {what}: {_size(used)} used of {_size(quota)} "
                f"(VOXNERF_DATA_DIR_QUOTA_BYTES), {_size(incoming_bytes)} more needed; delete scenes or jobs first"
            )
