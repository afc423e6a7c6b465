"""Upload sessions: one file sent in parts (``/uploads``), for scans past what one request may carry and for
connections that drop; completed, the file takes the path a one-request upload takes (:mod:`app.routes.scenes`).

A session lives in ``upload_sessions_dir/<id>/`` and needs no database row:

- ``session.json``: what :func:`create` was told and chose (file name, size, SHA-256, part size, the token
  that opened it), written once;
- ``parts/<n>.<sha256>``: each part received, renamed there whole once its size and hash are checked, so a part
  is either absent or complete (a dropped connection leaves only a temporary file, removed at once);
- ``lock``: taken (``flock``) while a part is added or the session is completed or removed, so two requests for
  one session (from one API process or several sharing ``data_dir``) never interleave.

The session directory's modification time is its last activity: touched on every part received, and a session
idle for ``upload_session_expiry_s`` is expired (410 until the API's sweeper, :func:`remove_expired`, removes it).
Parts are numbered from 0; every part has ``part_bytes`` bytes but the last, which has the rest.
"""

from __future__ import annotations

import contextlib
import fcntl
import hashlib
import json
import os
import re
import secrets
import shutil
import tempfile
import threading
import time
from collections.abc import Iterator
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import BinaryIO

from app.core.disk_space import require_room
from app.core.settings import Settings
from app.uploads.rules import UploadError, clip

SESSION_FILE = "session.json"
PARTS_DIR = "parts"
INCOMING_DIR = "incoming"
LOCK_FILE = "lock"
SHA256_RE = re.compile(r"^[0-9a-f]{64}$")
SESSION_ID_RE = re.compile(r"^[0-9a-f]{32}$")
MAX_FILENAME_CHARS = 255
_PART_NAME = re.compile(r"^(\d{6})\.([0-9a-f]{64})$")
_creating = threading.Lock()  # one creation at a time in this process, so the open-session count holds


@dataclass(frozen=True)
class Session:
    """What ``session.json`` holds."""

    id: str
    filename: str  # the file's name as the client gave it (its stem is the scene's default name)
    name: str | None  # the scene's display name, as the form field ``name`` of POST /scenes
    splits: str | None  # as the form field ``splits`` of POST /scenes
    total_bytes: int
    part_bytes: int
    sha256: str | None  # of the whole file, checked at completion when given
    created_at: float
    # the token that opened it, the only one but an admin that may use it (None: opened before sessions had
    # owners, the admin's)
    created_by: str | None = None

    @property
    def part_count(self) -> int:
        return max(1, -(-self.total_bytes // self.part_bytes))

    def part_size(self, number: int) -> int:
        """Bytes part ``number`` must have."""
        return self.part_bytes if number < self.part_count - 1 else self.total_bytes - number * self.part_bytes


@dataclass(frozen=True)
class SessionState:
    """A session and what it has received: what a client needs to resume."""

    session: Session
    received: dict[int, str]  # part number -> its SHA-256
    received_bytes: int
    expires_at: float


class SessionGone(UploadError):
    """An upload session that does not exist (404) or has expired (410)."""


def _dir(settings: Settings, session_id: str) -> Path:
    if not SESSION_ID_RE.match(session_id):
        raise SessionGone(404, f"no upload session {clip(session_id)}")
    return settings.upload_sessions_dir / session_id


def _read(path: Path) -> Session:
    return Session(**json.loads((path / SESSION_FILE).read_text()))


def _expires_at(settings: Settings, path: Path) -> float:
    return path.stat().st_mtime + settings.upload_session_expiry_s


@contextlib.contextmanager
def _locked(settings: Settings, session_id: str) -> Iterator[tuple[Path, Session]]:
    """The session's directory and description, its lock held; SessionGone when it is absent or has expired."""
    path = _dir(settings, session_id)
    try:
        lock = open(path / LOCK_FILE, "rb")  # noqa: SIM115 - closed below
    except FileNotFoundError:
        raise SessionGone(404, f"no upload session {session_id} (completed, deleted or expired)") from None
    with lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        if not (path / SESSION_FILE).is_file():  # removed while this request waited for the lock
            raise SessionGone(404, f"no upload session {session_id} (completed, deleted or expired)")
        if time.time() > _expires_at(settings, path):
            raise SessionGone(410, f"upload session {session_id} expired: no part arrived for "
                                   f"{settings.upload_session_expiry_s:.0f} s (VOXNERF_UPLOAD_SESSION_EXPIRY_S); "
                                   "start a new one")
        yield path, _read(path)


def _received(path: Path) -> dict[int, str]:
    found = {}
    for entry in os.listdir(path / PARTS_DIR):
        if match := _PART_NAME.match(entry):
            found[int(match[1])] = match[2]
    return found


def _open_sessions(settings: Settings) -> int:
    now = time.time()
    count = 0
    for entry in settings.upload_sessions_dir.iterdir():
        with contextlib.suppress(FileNotFoundError):
            if (entry / SESSION_FILE).is_file() and now <= _expires_at(settings, entry):
                count += 1
    return count


def part_size_for(settings: Settings, total_bytes: int) -> int:
    """The part size of a file of ``total_bytes``: ``upload_part_bytes``, larger when that would take more than
    ``max_upload_parts`` parts."""
    return max(settings.upload_part_bytes, -(-total_bytes // settings.max_upload_parts))


def check_sha256(value: str | None, what: str) -> str | None:
    """``value`` as 64 lowercase hex digits (None stays None); UploadError 422 otherwise."""
    if value is None:
        return None
    text = value.strip().lower()
    if not SHA256_RE.match(text):
        raise UploadError(422, f"{what}: expected a SHA-256 as 64 hex digits, got {clip(value)}")
    return text


def create(settings: Settings, filename: str, total_bytes: int, sha256: str | None, name: str | None,
           splits: str | None, created_by: str | None) -> SessionState:
    """Open a session for a file of ``total_bytes``, owned by the token named ``created_by``: 413 past
    ``max_upload_session_bytes``, 429 when ``max_upload_sessions`` are open, 507 when the disk has no room for the
    file."""
    if total_bytes > settings.max_upload_session_bytes:
        raise UploadError(413, f"total_bytes: {total_bytes} bytes is more than the {settings.max_upload_session_bytes}"
                               " an upload session takes (VOXNERF_MAX_UPLOAD_SESSION_BYTES)")
    require_room(settings, total_bytes, what=f"an upload of {total_bytes} bytes")
    settings.make_dirs()
    with _creating:
        if _open_sessions(settings) >= settings.max_upload_sessions:
            raise UploadError(429, f"{settings.max_upload_sessions} upload sessions are open "
                                   "(VOXNERF_MAX_UPLOAD_SESSIONS): complete or delete one, or wait for one to expire")
        session = Session(secrets.token_hex(16), filename, name, splits, total_bytes,
                          part_size_for(settings, total_bytes), sha256, time.time(), created_by)
        staging = Path(tempfile.mkdtemp(prefix=".new-", dir=settings.upload_sessions_dir))
        try:
            (staging / PARTS_DIR).mkdir()
            (staging / INCOMING_DIR).mkdir()
            (staging / LOCK_FILE).touch()
            (staging / SESSION_FILE).write_text(json.dumps(asdict(session)))
            staging.chmod(0o755)
            staging.rename(settings.upload_sessions_dir / session.id)
        except BaseException:
            shutil.rmtree(staging, ignore_errors=True)
            raise
    return state(settings, session.id)


def owner(settings: Settings, session_id: str) -> str | None:
    """The token that opened the session (None: opened before sessions had owners), expired or not;
    SessionGone 404 when there is none."""
    try:
        return _read(_dir(settings, session_id)).created_by
    except FileNotFoundError:
        raise SessionGone(404, f"no upload session {session_id} (completed, deleted or expired)") from None


def state(settings: Settings, session_id: str) -> SessionState:
    """The session and its received parts; SessionGone when it is absent or expired."""
    with _locked(settings, session_id) as (path, session):
        received = _received(path)
        done = sum(session.part_size(n) for n in received)
        return SessionState(session, received, done, _expires_at(settings, path))


def _check_number(session: Session, number: int) -> None:
    if not 0 <= number < session.part_count:
        raise UploadError(404, f"part {number}: this session has parts 0 to {session.part_count - 1}")


def incoming_file(settings: Settings, session_id: str, number: int) -> tuple[Session, BinaryIO]:
    """An open temporary file for the bytes of part ``number`` as they arrive (the caller closes it and hands it
    to :func:`add_part`, or removes it), after checking the session and the part number and the room on disk."""
    with _locked(settings, session_id) as (path, session):
        _check_number(session, number)
    require_room(settings, session.part_size(number), what=f"part {number} ({session.part_size(number)} bytes)")
    return session, tempfile.NamedTemporaryFile(dir=path / INCOMING_DIR, prefix=f"{number:06d}-", delete=False)


def add_part(settings: Settings, session_id: str, number: int, temp: Path, size: int, digest: str,
             declared: str) -> bool:
    """Keep the part received in ``temp`` (``size`` bytes hashing to ``digest``; the client declared
    ``declared``) as part ``number``. True when it is new, False when the same bytes were there already; 422 for a
    wrong size or hash, 409 for other bytes than the part already received. ``temp`` is gone afterwards."""
    try:
        with _locked(settings, session_id) as (path, session):
            _check_number(session, number)
            expected = session.part_size(number)
            if size != expected:
                raise UploadError(422, f"part {number}: {size} bytes received, {expected} expected (part size "
                                       f"{session.part_bytes}, the last part has the rest)")
            if digest != declared:
                raise UploadError(422, f"part {number}: the bytes received hash to {digest}, not to the "
                                       f"X-Content-SHA256 sent ({declared}); send the part again")
            existing = _received(path).get(number)
            if existing is not None:
                if existing != digest:
                    raise UploadError(409, f"part {number} was received already with other bytes (SHA-256 "
                                           f"{existing}); a received part cannot change: delete the session to "
                                           "start again")
                return False
            temp.rename(path / PARTS_DIR / f"{number:06d}.{digest}")
            os.utime(path)  # the session's last activity
            return True
    finally:
        temp.unlink(missing_ok=True)


def assemble(settings: Settings, session_id: str, into: Path) -> Session:
    """Join the session's parts, in order, into the file ``into`` (each part removed once copied), check the
    whole file's SHA-256 when the session has one, and remove the session. 409 with the missing parts' numbers
    when some are missing (the session is kept); 422 when the whole-file hash differs (the session is removed:
    its parts cannot change)."""
    with _locked(settings, session_id) as (path, session):
        received = _received(path)
        missing = [n for n in range(session.part_count) if n not in received]
        if missing:
            listed = ", ".join(map(str, missing[:20])) + (" ..." if len(missing) > 20 else "")
            raise UploadError(409, f"{len(missing)} of {session.part_count} parts not received yet: {listed}; "
                                   f"GET /uploads/{session_id} lists what arrived")
        require_room(settings, session.part_bytes, what="joining the upload's parts")
        digest = hashlib.sha256()
        try:
            with open(into, "wb") as out:
                for number in range(session.part_count):
                    part = path / PARTS_DIR / f"{number:06d}.{received[number]}"
                    with open(part, "rb") as source:
                        while chunk := source.read(1024 * 1024):
                            digest.update(chunk)
                            out.write(chunk)
                    part.unlink()
            if session.sha256 is not None and digest.hexdigest() != session.sha256:
                raise UploadError(422, f"the file joined from the parts hashes to {digest.hexdigest()}, not to "
                                       f"the sha256 given when the session was created ({session.sha256}); "
                                       "the session is removed, upload the file again")
        except BaseException:
            into.unlink(missing_ok=True)
            raise
        finally:
            _remove(path)
        return session


def _remove(path: Path) -> None:
    """Remove a session directory: its description first, so a request waiting for its lock finds it gone."""
    (path / SESSION_FILE).unlink(missing_ok=True)
    doomed = path.with_name(f".deleted-{path.name}")
    with contextlib.suppress(FileNotFoundError):
        path.rename(doomed)
    shutil.rmtree(doomed, ignore_errors=True)


def delete(settings: Settings, session_id: str) -> None:
    """Remove a session and its parts (an expired one too); SessionGone 404 when there is none."""
    try:
        with _locked(settings, session_id) as (path, _session):
            _remove(path)
    except SessionGone as gone:
        if gone.status_code != 410:
            raise
        _remove(_dir(settings, session_id))


def remove_expired(settings: Settings) -> list[str]:
    """Remove every expired session (and what a crash left half-made); the ids removed. The API's sweeper
    calls it every round."""
    removed = []
    if not settings.upload_sessions_dir.is_dir():
        return removed
    now = time.time()
    for entry in sorted(settings.upload_sessions_dir.iterdir()):
        try:
            idle = now - entry.stat().st_mtime
        except FileNotFoundError:
            continue
        if idle <= settings.upload_session_expiry_s:
            continue
        if SESSION_ID_RE.match(entry.name):
            with contextlib.suppress(SessionGone):
                delete(settings, entry.name)
            removed.append(entry.name)
        else:  # a session being created or removed when a process died
            shutil.rmtree(entry, ignore_errors=True)
    return removed
