"""The multipart form of ``POST /scenes``, read with every file part on disk as it streams in.

Starlette's parser keeps each file part of up to 1 MiB in memory (a SpooledTemporaryFile) and gives each larger
one a temporary file of its own: 2 GiB of 1 MiB parts would be 2 GiB of the API's memory, 20 000 larger parts
20 000 open files. Here every file part is appended to one unlinked temporary file in ``staging_dir`` (one
descriptor per upload) and read back through its own :class:`SpoolSlice`, so the API process holds at most a
chunk of the body whatever the form holds. Form fields (``name``, ``splits``) stay small strings
(``max_part_size``).

:func:`read_form` is Starlette's ``request.form()`` with that change; it subclasses Starlette's
``MultiPartParser`` and replaces the file of each file part as the part's headers end.
"""

from __future__ import annotations

import contextlib
import os
import tempfile
from collections.abc import AsyncIterator
from pathlib import Path
from typing import BinaryIO

from starlette.datastructures import FormData
from starlette.exceptions import HTTPException
from starlette.formparsers import MultiPartException, MultiPartParser
from starlette.requests import Request

from app.core.settings import Settings

MAX_FIELD_BYTES = 64 * 1024  # a form field that is not a file: the display name, the split rule


class Spool:
    """One unlinked temporary file that the file parts of a form are appended to, one part after another."""

    def __init__(self, directory: Path) -> None:
        self.file: BinaryIO = tempfile.TemporaryFile(dir=directory)  # noqa: SIM115 - closed by close()
        self.end = 0  # bytes written so far

    def close(self) -> None:
        self.file.close()


class SpoolSlice:
    """The bytes of one file part in a :class:`Spool`: written once, in order, then read like a file (``read``,
    ``seek``, ``tell``) at a position of its own."""

    def __init__(self, spool: Spool) -> None:
        self._spool = spool
        self._start: int | None = None  # where its first byte went: parts are written strictly one after another
        self._size = 0
        self._position = 0
        self.closed = False

    def write(self, data: bytes) -> int:
        spool = self._spool
        if self._start is None:
            self._start = spool.end
        if self._start + self._size != spool.end:
            raise RuntimeError("a file part was written after the next part began")
        view = memoryview(data)
        while view:
            written = os.pwrite(spool.file.fileno(), view, spool.end)
            spool.end += written
            self._size += written
            view = view[written:]
        return len(data)

    def read(self, size: int = -1) -> bytes:
        remaining = self._size - self._position
        count = remaining if size is None or size < 0 else min(size, remaining)
        if count <= 0:
            return b""
        data = os.pread(self._spool.file.fileno(), count, self._start + self._position)
        self._position += len(data)
        return data

    def seek(self, offset: int, whence: int = os.SEEK_SET) -> int:
        base = {os.SEEK_SET: 0, os.SEEK_CUR: self._position, os.SEEK_END: self._size}[whence]
        if base + offset < 0:
            raise ValueError(f"negative seek position {base + offset}")
        self._position = base + offset
        return self._position

    def tell(self) -> int:
        return self._position

    def readable(self) -> bool:
        return True

    def close(self) -> None:
        self.closed = True


class _SpoolingParser(MultiPartParser):
    """Starlette's multipart parser with each file part's data sent to a :class:`SpoolSlice` of ``spool``."""

    def __init__(self, request: Request, spool: Spool, max_files: int) -> None:
        super().__init__(
            request.headers, request.stream(), max_files=max_files, max_fields=8, max_part_size=MAX_FIELD_BYTES
        )
        self._spool = spool

    def on_headers_finished(self) -> None:
        super().on_headers_finished()
        upload = self._current_part.file
        if upload is not None:  # a file part: its SpooledTemporaryFile (still empty, no descriptor) is replaced
            upload.file.close()
            upload.file = SpoolSlice(self._spool)


@contextlib.asynccontextmanager
async def read_form(request: Request, settings: Settings) -> AsyncIterator[FormData]:
    """The request's form: a multipart one with its file parts spooled to disk (at most ``max_files + 1``),
    anything else as ``request.form()`` reads it. 400 for a malformed multipart body; the spool is removed on
    leaving."""
    media_type = request.headers.get("content-type", "").split(";", 1)[0].strip().lower()
    if media_type != "multipart/form-data":
        form = await request.form(max_files=0, max_fields=8, max_part_size=MAX_FIELD_BYTES)
        try:
            yield form
        finally:
            await form.close()
        return
    spool = Spool(settings.staging_dir)
    try:
        try:
            form = await _SpoolingParser(request, spool, settings.max_files + 1).parse()
        except MultiPartException as err:
            raise HTTPException(400, err.message) from None
        try:
            yield form
        finally:
            await form.close()
    finally:
        spool.close()
