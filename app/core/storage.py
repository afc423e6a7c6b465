"""Scenes and runs in an object store (``VOXNERF_STORAGE_URL``: ``s3://bucket/prefix`` or any fsspec URL).

Unset, nothing here does anything: every process shares ``data_dir``. Set, the store is what connects the
machines and each process keeps only a local cache under its own ``data_dir``:

- the API publishes a scene once it is validated and stored (:func:`publish_scene`), and deletes it from the
  store with the scene (:func:`delete_scene`);
- a train worker fetches the scene if its cache lacks it (:func:`ensure_scene`), fetches the run's last
  uploaded checkpoint when its cache does not hold that one (:func:`ensure_run`, so a job redelivered to
  another machine resumes), and uploads the run after every checkpoint and at the end (:class:`RunPublisher`);
- a render worker fetches a run's checkpoint when it is not in its cache (:func:`ensure_run` without refresh).

Layout under the URL, for ``<kind>/<id>`` = ``scenes/<scene id>`` or ``runs/<job id>``::

    <kind>/<id>/<generation>/<files...>    one complete upload of the directory
    <kind>/<id>/current.json               the marker: {"generation": ..., "files": {path: bytes}}

:func:`put_dir` uploads every file under a fresh generation key, writes the marker last, then deletes older
generations; :func:`fetch_dir` reads the marker first and downloads only what it names. A reader therefore
sees a whole upload or none (a directory without a marker is not in the store), on any backend, including
those without atomic renames such as S3. Downloads land in a temporary directory under ``staging_dir`` and
are renamed into the cache, so a cache entry is complete too; it remembers its generation in
``.store-generation`` (never uploaded).

A worker machine's cache is bounded (``worker_cache_bytes``): before a task fetches, and after a training task,
the worker removes the least recently used scenes and runs from it until it fits (:func:`prune_cache`). A task
marks what it uses (:func:`cache_entry_in_use`: a shared ``flock`` on ``data_dir/cache-locks/<kind>-<id>.lock``,
whose modification time is the entry's last use), and the prune removes only an entry it can lock exclusively
and that the store holds as it is here (same generation, same files and sizes; a run's outputs each published),
so neither work in progress nor a run the store lacks is ever lost. The lock files stay (empty; removing one
while a task waits on it would let two tasks lock different files).
"""

from __future__ import annotations

import contextlib
import fcntl
import json
import logging
import os
import shutil
import tempfile
import threading
import uuid
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path, PurePosixPath
from types import TracebackType

import fsspec
from fsspec.core import url_to_fs

from app.core.disk_space import directory_bytes
from app.core.redact import mask_url
from app.core.settings import Settings
from voxnerf.errors import VoxNeRFError
from voxnerf.files import CHECKPOINT

MARKER = "current.json"
LOCAL_GENERATION = ".store-generation"
SCENES = "scenes"
RUNS = "runs"
RUN_OUTPUTS = "outputs"  # a run's output files (app.core.outputs.OUTPUTS_DIR), each published under its own key
CACHE_LOCKS = "cache-locks"
FETCH_ATTEMPTS = 3  # a fetch restarts when a newer upload deletes the generation it was reading

log = logging.getLogger(__name__)


class StorageError(VoxNeRFError):
    """A directory the store does not hold (never uploaded, upload unfinished, deleted) or holds damaged."""


@dataclass(frozen=True)
class Store:
    """An fsspec filesystem and the path of ``storage_url`` inside it (``bucket/prefix``, no trailing /)."""

    fs: fsspec.AbstractFileSystem
    root: str
    url: str

    def path(self, key: str) -> str:
        """The filesystem path of ``key`` (``scenes/<id>/current.json``...) under the store's root."""
        return f"{self.root}/{key}" if self.root else key

    def where(self, key: str) -> str:
        """``key`` as a URL, for messages (credentials masked)."""
        return mask_url(f"{self.url.rstrip('/')}/{key}")


def storage_options(settings: Settings) -> dict:
    """fsspec options of the store: ``storage_options`` plus endpoint, key and secret for ``s3://`` URLs."""
    options = dict(settings.storage_options)
    key, secret = settings.storage_key, settings.storage_secret
    s3_fields = {  # s3fs option: (setting's environment variable, value)
        "endpoint_url": ("VOXNERF_STORAGE_ENDPOINT_URL", settings.storage_endpoint_url),
        "key": ("VOXNERF_STORAGE_KEY", key.get_secret_value() if key else None),
        "secret": ("VOXNERF_STORAGE_SECRET", secret.get_secret_value() if secret else None),
    }
    given = {option: value for option, (_, value) in s3_fields.items() if value is not None}
    protocol = (settings.storage_url or "").split("://", 1)[0]
    if given and protocol not in ("s3", "s3a"):
        names = ", ".join(s3_fields[option][0] for option in given)
        raise ValueError(f"{names} apply to s3:// stores only, not to {mask_url(settings.storage_url)!r}")
    options.update(given)
    return options


def open_store(settings: Settings) -> Store | None:
    """The configured store, or None when ``storage_url`` is unset (fsspec caches filesystems per process)."""
    if not settings.storage_url:
        return None
    fs, root = url_to_fs(settings.storage_url, **storage_options(settings))
    return Store(fs, root.rstrip("/"), settings.storage_url)


def check_store(settings: Settings) -> None:
    """Make sure the store's root exists (an S3 bucket is created if missing and allowed); no-op if unset.

    Meant for start-up (API and workers), so bad credentials or an unreachable endpoint stop the process at
    once rather than failing the first upload: raises StorageError naming the URL and the backend's error
    (ValueError for inconsistent storage settings).
    """
    store = open_store(settings)
    if store is None:
        return
    try:
        store.fs.makedirs(store.root, exist_ok=True)
    except Exception as err:  # each backend raises its own types (botocore, OSError, PermissionError...)
        raise StorageError(
            mask_url(f"the object store {store.url} (VOXNERF_STORAGE_URL) cannot be used: {type(err).__name__}: {err}")
        ) from err


def _local_files(local_dir: Path) -> dict[str, Path]:
    """Every regular file under ``local_dir`` by its POSIX path relative to it, except the generation record
    and the ``*.tmp`` files of atomic writes still in progress."""
    return {
        path.relative_to(local_dir).as_posix(): path
        for path in sorted(local_dir.rglob("*"))
        if path.is_file() and not path.name.startswith(LOCAL_GENERATION) and path.suffix != ".tmp"
    }


def read_marker(store: Store, key: str) -> dict | None:
    """The marker of directory ``key`` (``{"generation", "files"}``), or None when it is not in the store."""
    try:
        raw = store.fs.cat_file(store.path(f"{key}/{MARKER}"))
    except FileNotFoundError:
        return None
    try:
        marker = json.loads(raw)
        if not isinstance(marker["generation"], str) or not isinstance(marker["files"], dict):
            raise TypeError("generation must be a string and files an object")
        for name, size in marker["files"].items():
            path = PurePosixPath(name)
            if path.is_absolute() or ".." in path.parts or not isinstance(size, int):
                raise ValueError(f"file entry {name!r}: {size!r} is not a relative path and a byte count")
    except (ValueError, KeyError, TypeError) as err:
        raise StorageError(f"{store.where(f'{key}/{MARKER}')}: damaged marker ({err})") from None
    return marker


def _snapshot(local_dir: Path, into: Path) -> dict[str, Path]:
    """Hard-link (copy where links fail) every file of ``local_dir`` into ``into``, so that a file the
    trainer replaces meanwhile cannot change what is uploaded; returns the snapshot's files by name."""
    files = {}
    for name, path in _local_files(local_dir).items():
        target = into / name
        target.parent.mkdir(parents=True, exist_ok=True)
        try:
            os.link(path, target)
        except OSError:
            shutil.copy2(path, target)
        files[name] = target
    return files


def put_dir(store: Store, local_dir: Path, key: str) -> str:
    """Upload every file of ``local_dir`` as a new generation of ``key``; returns the generation.

    Uploads a snapshot of the directory (hard links in a temporary sibling directory); the marker is written
    after all files and older generations are deleted after the marker, so readers never see a partial or
    mixed upload. Records the generation in ``local_dir/.store-generation``.
    """
    generation = uuid.uuid4().hex
    snapshot = Path(tempfile.mkdtemp(prefix=".upload-", dir=local_dir.parent))
    try:
        files = _snapshot(local_dir, snapshot)
        names = list(files)
        remote = [store.path(f"{key}/{generation}/{name}") for name in names]
        store.fs.put([str(files[name]) for name in names], remote)
        sizes = {name: files[name].stat().st_size for name in names}
    finally:
        shutil.rmtree(snapshot, ignore_errors=True)
    marker = json.dumps({"generation": generation, "files": sizes}, indent=1).encode()
    store.fs.pipe_file(store.path(f"{key}/{MARKER}"), marker)
    _delete_other_generations(store, key, generation)
    _write_local_generation(local_dir, generation)
    return generation


def _delete_other_generations(store: Store, key: str, keep: str) -> None:
    prefix = store.path(key)
    store.fs.invalidate_cache(prefix)
    for entry in store.fs.ls(prefix, detail=False):
        name = entry.rstrip("/").rsplit("/", 1)[-1]
        if name not in (keep, MARKER):
            store.fs.rm(entry, recursive=True)


def _write_local_generation(local_dir: Path, generation: str) -> None:
    record = local_dir / LOCAL_GENERATION
    temp = local_dir / f"{LOCAL_GENERATION}.{uuid.uuid4().hex}.tmp"
    temp.write_text(generation)
    os.replace(temp, record)


def local_generation(local_dir: Path) -> str | None:
    """The store generation a cached directory holds (None if it was never uploaded nor fetched)."""
    try:
        return (local_dir / LOCAL_GENERATION).read_text().strip() or None
    except FileNotFoundError:
        return None


def fetch_dir(store: Store, key: str, local_dir: Path, staging_dir: Path) -> str:
    """Download the current generation of ``key`` into ``local_dir`` (replacing it); returns the generation.

    Raises StorageError when the store has no marker for ``key`` or a file is missing or of the wrong size.
    The download goes to a temporary directory in ``staging_dir`` (same filesystem) and is renamed into place.
    """
    staging_dir.mkdir(parents=True, exist_ok=True)
    for _ in range(FETCH_ATTEMPTS):
        marker = read_marker(store, key)
        if marker is None:
            raise StorageError(
                f"{store.where(key)}: not in the store (no {MARKER}: never uploaded, upload unfinished, "
                "or deleted)"
            )
        generation, sizes = marker["generation"], marker["files"]
        temp = Path(tempfile.mkdtemp(prefix="fetch-", dir=staging_dir))
        try:
            names = list(sizes)
            for name in names:
                (temp / name).parent.mkdir(parents=True, exist_ok=True)
            try:
                remote = [store.path(f"{key}/{generation}/{name}") for name in names]
                store.fs.get(remote, [str(temp / name) for name in names])
            except FileNotFoundError:
                if (read_marker(store, key) or {}).get("generation") != generation:
                    continue  # a newer upload replaced this generation while we read it: start again
                raise StorageError(
                    f"{store.where(f'{key}/{generation}')}: a file the marker lists is missing"
                ) from None
            for name, size in sizes.items():
                got = (temp / name).stat().st_size if (temp / name).is_file() else None
                if got != size:
                    where = store.where(f"{key}/{generation}/{name}")
                    raise StorageError(f"{where}: {got} bytes, the marker says {size}")
            _write_local_generation(temp, generation)
            _replace_dir(temp, local_dir, staging_dir)
            return generation
        finally:
            shutil.rmtree(temp, ignore_errors=True)
    raise StorageError(f"{store.where(key)}: changed {FETCH_ATTEMPTS} times while being fetched")


def _replace_dir(new: Path, target: Path, staging_dir: Path) -> None:
    """Rename ``new`` to ``target``; an existing ``target`` is first renamed away into ``staging_dir``."""
    target.parent.mkdir(parents=True, exist_ok=True)
    if target.exists():
        doomed = Path(tempfile.mkdtemp(prefix="replaced-", dir=staging_dir))
        target.replace(doomed / "old")
        new.replace(target)
        shutil.rmtree(doomed, ignore_errors=True)
    else:
        new.replace(target)


def delete_prefix(store: Store, key: str) -> None:
    """Delete directory ``key`` from the store: the marker first (readers stop seeing it), then the files."""
    marker = store.path(f"{key}/{MARKER}")
    if store.fs.exists(marker):
        store.fs.rm_file(marker)
    store.fs.invalidate_cache(store.path(key))
    if store.fs.exists(store.path(key)):
        store.fs.rm(store.path(key), recursive=True)


def publish_scene(settings: Settings, scene_id: str) -> None:
    """Upload ``scenes/<id>`` (after the API validated and stored it); no-op without a store."""
    store = open_store(settings)
    if store is not None:
        put_dir(store, settings.scenes_dir / scene_id, f"{SCENES}/{scene_id}")


def delete_scene(settings: Settings, scene_id: str) -> None:
    """Delete a scene from the store; no-op without a store."""
    store = open_store(settings)
    if store is not None:
        delete_prefix(store, f"{SCENES}/{scene_id}")


def delete_keys(settings: Settings, keys: list[str]) -> None:
    """Delete directories ``keys`` (e.g. ``runs/<job id>``) from the store; no-op without a store."""
    store = open_store(settings)
    if store is not None:
        for key in keys:
            delete_prefix(store, key)


def ensure_scene(settings: Settings, scene_id: str) -> Path:
    """The local directory of a scene, fetched from the store if this machine's cache lacks it.

    Scenes never change once stored, so a cached copy is used as is. Raises StorageError if the store does
    not hold the scene.
    """
    local = settings.scenes_dir / scene_id
    store = open_store(settings)
    if store is not None and not local.is_dir():
        fetch_dir(store, f"{SCENES}/{scene_id}", local, settings.staging_dir)
    return local


def ensure_run(settings: Settings, job_id: str, refresh: bool = True) -> Path:
    """The local run directory of a job, brought up to date with the store.

    ``refresh`` (training): fetch the last uploaded run unless the cache holds that very generation (then the
    cache is as new or newer), so a job redelivered to another machine resumes from its last uploaded
    checkpoint; a run the store does not hold yet starts empty. Without ``refresh`` (rendering a finished
    job): fetch only when the cache has no checkpoint, and raise StorageError if the store has no run.
    """
    local = settings.runs_dir / job_id
    store = open_store(settings)
    if store is None:
        return local
    key = f"{RUNS}/{job_id}"
    if not refresh:
        if not (local / CHECKPOINT).is_file():
            fetch_dir(store, key, local, settings.staging_dir)
        return local
    marker = read_marker(store, key)
    if marker is not None and marker["generation"] != local_generation(local):
        log.info("run %s: fetching generation %s from %s", job_id, marker["generation"], store.where(key))
        fetch_dir(store, key, local, settings.staging_dir)
    return local


# ------------------------------------------------------------------------------------------------ worker cache


def _lock_path(settings: Settings, kind: str, entry_id: str) -> Path:
    return settings.data_dir / CACHE_LOCKS / f"{kind}-{entry_id}.lock"


@contextlib.contextmanager
def cache_entry_in_use(settings: Settings, kind: str, entry_id: str) -> Iterator[None]:
    """Hold cache entry ``<kind>/<id>`` (``scenes`` or ``runs``) for a task: :func:`prune_cache` leaves it alone
    meanwhile, and its last use is when the block ends. Enter it before the entry is fetched (a prune in
    progress on it is waited for). Does nothing without a store (then ``data_dir`` is not a cache)."""
    if not settings.storage_url:
        yield
        return
    path = _lock_path(settings, kind, entry_id)
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "ab") as lock:
        fcntl.flock(lock, fcntl.LOCK_SH)
        os.utime(path)
        try:
            yield
        finally:
            os.utime(path)
            fcntl.flock(lock, fcntl.LOCK_UN)


def _last_use(settings: Settings, kind: str, local: Path) -> float:
    """When a task last held the entry (its lock file's time), else when the directory last changed."""
    for path in (_lock_path(settings, kind, local.name), local):
        with contextlib.suppress(FileNotFoundError):
            return path.stat().st_mtime
    return 0.0


def held_by_store(store: Store, kind: str, local: Path) -> bool:
    """Whether the store holds cache entry ``local`` as it is here: the generation the entry records is the
    store's current one, with every file (a run's outputs aside) there at its size, and each of a run's outputs
    published (it records a generation). False when the store cannot say."""
    generation = local_generation(local)
    try:
        marker = read_marker(store, f"{kind}/{local.name}")
    except StorageError:
        return False
    if generation is None or marker is None or marker["generation"] != generation:
        return False
    for name, path in _local_files(local).items():
        if name.split("/", 1)[0] == RUN_OUTPUTS and kind == RUNS:
            continue
        if marker["files"].get(name) != path.stat().st_size:
            return False
    outputs = local / RUN_OUTPUTS if kind == RUNS else None
    return outputs is None or not outputs.is_dir() or all(
        local_generation(output) is not None for output in outputs.iterdir() if output.is_dir())


def prune_cache(settings: Settings) -> list[str]:
    """Remove the least recently used scenes and runs from this machine's cache until it holds at most
    ``worker_cache_bytes``; the keys (``runs/<id>``...) it removed. Entries a task holds
    (:func:`cache_entry_in_use`) and entries the store does not hold as they are here (:func:`held_by_store`)
    stay, even when the cache is then still over its size. No-op without a store."""
    store = open_store(settings)
    if store is None:
        return []
    entries = [(kind, path) for kind, parent in ((SCENES, settings.scenes_dir), (RUNS, settings.runs_dir))
               if parent.is_dir() for path in parent.iterdir() if path.is_dir() and not path.name.startswith(".")]
    sizes = {path: directory_bytes(path) for _, path in entries}
    total = sum(sizes.values())
    removed: list[str] = []
    for kind, local in sorted(entries, key=lambda entry: _last_use(settings, *entry)):
        if total <= settings.worker_cache_bytes:
            break
        if _remove_if_idle(settings, store, kind, local):
            total -= sizes[local]
            removed.append(f"{kind}/{local.name}")
    if removed:
        log.info("worker cache: removed %d least recently used entries (%s); %d bytes left", len(removed),
                 ", ".join(removed), total)
    return removed


def _remove_if_idle(settings: Settings, store: Store, kind: str, local: Path) -> bool:
    """Remove cache entry ``local`` if no task holds it and the store holds it as it is; whether it did."""
    path = _lock_path(settings, kind, local.name)
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "ab") as lock:
        try:
            fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            return False  # a task uses it
        try:
            if not local.is_dir():
                return False
            try:
                held = held_by_store(store, kind, local)
            except Exception:  # the store is unreachable: keep the entry, it may be the only copy
                log.warning("worker cache: cannot ask the store about %s/%s; kept", kind, local.name, exc_info=True)
                return False
            if not held:
                return False
            doomed = Path(tempfile.mkdtemp(prefix="pruned-", dir=settings.staging_dir))
            local.replace(doomed / local.name)
            shutil.rmtree(doomed, ignore_errors=True)
            return True
        finally:
            fcntl.flock(lock, fcntl.LOCK_UN)


class RunPublisher:
    """Uploads a training run while it trains: after every new checkpoint and once more at the end.

    A side thread looks at ``run_dir/checkpoint.pt`` every ``storage_sync_interval_s`` and uploads the run
    when the file changed (the trainer replaces it atomically, so an upload reads one whole checkpoint).
    Leaving the context uploads the final run (checkpoint, report.json, evaluation renders); an upload error
    there propagates unless the block already raised. Does nothing without a store. ``may_upload()`` (a
    worker's lease: :meth:`worker.lease.Lease.still_owned`) is asked before every upload, so an attempt that
    lost its job never overwrites its successor's run in the store.
    """

    def __init__(self, settings: Settings, job_id: str, run_dir: Path,
                 may_upload: Callable[[], bool] = lambda: True) -> None:
        self.store = open_store(settings)
        self.may_upload = may_upload
        self.key = f"{RUNS}/{job_id}"
        self.run_dir = run_dir
        self.interval_s = settings.storage_sync_interval_s
        self._uploaded: int | None = self._checkpoint_stamp()
        self._done = threading.Event()
        self._thread = threading.Thread(target=self._run, name=f"publish-{job_id}", daemon=True)

    def _checkpoint_stamp(self) -> int | None:
        try:
            return (self.run_dir / CHECKPOINT).stat().st_mtime_ns
        except FileNotFoundError:
            return None

    def upload_if_changed(self) -> bool:
        """Upload the run if its checkpoint changed since the last upload; True if it uploaded."""
        stamp = self._checkpoint_stamp()
        if self.store is None or stamp is None or stamp == self._uploaded or not self.may_upload():
            return False
        put_dir(self.store, self.run_dir, self.key)
        self._uploaded = stamp
        return True

    def _run(self) -> None:
        while not self._done.wait(self.interval_s):
            try:
                self.upload_if_changed()
            except Exception:  # the store is briefly unreachable: keep training, retry at the next look
                log.warning("run %s: checkpoint upload failed", self.key, exc_info=True)

    def __enter__(self) -> RunPublisher:
        if self.store is not None:
            self._thread.start()
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        if self.store is None:
            return
        self._done.set()
        self._thread.join()
        if not self.run_dir.is_dir() or not self.may_upload():
            return
        try:
            put_dir(self.store, self.run_dir, self.key)
        except Exception:
            if exc_type is None:
                raise
            log.exception("run %s: final upload after a failed training failed too", self.key)
