"""The embedded broker: kombu's filesystem transport with atomic publishing and atomic claiming.

kombu's stock filesystem channel writes a message file in place (a consumer polling at that moment can
read it half written: kombu issue #1551) and claims a message by moving it to the system temp directory
(a copy, not a rename, when that is another filesystem, so two consumers could both take it). Here a
message is written to a hidden temporary name and renamed into the queue folder, and a consumer claims
it by renaming it into a ``claimed`` folder beside the queue: one rename, one winner. kombu's channel also
binds a queue to a fanout exchange by testing whether the exchange's file exists and then truncating it
(processes that bind at the same moment, such as the workers of ``voxnerf serve``, lose each other's bindings
or leave the file unreadable, and a worker whose binding is lost never answers ``/healthz``). Here the file is
read and changed under one exclusive lock (a ``.lock`` file beside it) and the new table is renamed over the
old one, so a reader, or a binder killed while writing, never leaves or sees part of a table; an empty file is
an empty table. Message names, ordering and every other behaviour stay kombu's.

kombu's transport looks into the queue folder every ``polling_interval`` while it waits, a wake-up of an idle
worker 20 to 100 times a second, and a message waits up to one interval. Here, on Linux, a consumer that could
take a message waits on an inotify watch of the queue folder instead (app/core/folder_watch.py): it wakes when a
message is renamed in, and otherwise only when the caller's timeout ends. While one of its channels is full
(a task running to its prefetch limit) nothing in the folder says that the task ended, so it then polls at
``polling_interval`` as kombu does; without inotify (another system) it always does.
"""

from __future__ import annotations

import contextlib
import fcntl
import os
import uuid
from pathlib import Path
from queue import Empty
from time import monotonic, sleep

from kombu.transport import filesystem, virtual
from kombu.utils.encoding import bytes_to_str, str_to_bytes
from kombu.utils.json import dumps, loads

from app.core.folder_watch import FolderWatch
from voxnerf.data.image_io import write_atomic

Binding = filesystem.exchange_queue_t  # (routing_key, pattern, queue) of a queue bound to an exchange


class Channel(filesystem.Channel):
    """Filesystem channel whose ``_put``, ``_get`` and exchange bindings are atomic across processes."""

    @property
    def claimed_folder(self) -> str:
        return self.transport_options.get("claimed_folder", "claimed")

    def _put(self, queue, payload, **kwargs) -> None:
        name = f"{int(round(monotonic() * 1000))}_{uuid.uuid4()}.{queue}.msg"
        final = os.path.join(self.data_folder_out, name)
        tmp = os.path.join(self.data_folder_out, f".{name}.tmp")  # never matches a queue's ".msg" filter
        try:
            with open(tmp, "wb") as f:
                f.write(str_to_bytes(dumps(payload)))
                f.flush()
                os.fsync(f.fileno())
            os.replace(tmp, final)
        except OSError as exc:
            with contextlib.suppress(OSError):
                os.remove(tmp)
            raise filesystem.ChannelError(f"Cannot add file {final!r} to directory") from exc

    def _get(self, queue):
        wanted = f"{queue}.msg"
        for filename in sorted(os.listdir(self.data_folder_in)):
            if filename.partition(".")[2] != wanted:
                continue
            claimed = os.path.join(self.claimed_folder, f"{os.getpid()}-{filename}")
            try:
                os.rename(os.path.join(self.data_folder_in, filename), claimed)
            except FileNotFoundError:  # another consumer took it first
                continue
            try:
                with open(claimed, "rb") as f:
                    payload = f.read()
            finally:
                os.remove(claimed)
            return loads(bytes_to_str(payload))
        raise Empty()

    def get_table(self, exchange) -> list[Binding]:
        path = self._exchange_file(exchange)
        try:
            return _read_table(path)
        except OSError as exc:
            raise filesystem.ChannelError(f"Cannot open {path}") from exc

    def _queue_bind(self, exchange, routing_key, pattern, queue) -> None:
        binding = _binding(routing_key, pattern, queue)
        self._edit_table(exchange, lambda table: table if binding in table else [binding, *table])

    def _delete(self, queue, exchange, routing_key, pattern, *args, **kwargs) -> None:
        virtual.Channel._delete(self, queue, exchange, routing_key, pattern, *args, **kwargs)  # not kombu's file edit
        binding = _binding(routing_key, pattern, queue)
        self._edit_table(exchange, lambda table: [b for b in table if b != binding])

    def _edit_table(self, exchange, edit) -> None:
        """Replace the bindings of ``exchange`` by ``edit(bindings)``: read and edit under one exclusive lock, so
        no other process's change between the read and the write is lost, and write the new table whole
        (:func:`~voxnerf.data.image_io.write_atomic`: a temporary file renamed over the old one)."""
        path = self._exchange_file(exchange)
        self.control_folder.mkdir(parents=True, exist_ok=True)
        try:
            with open(f"{path}.lock", "ab") as lock:
                fcntl.flock(lock, fcntl.LOCK_EX)  # released by close
                table = _read_table(path)
                edited = edit(table)
                if edited != table:
                    write_atomic(path, str_to_bytes(dumps(edited)))
        except OSError as exc:
            raise filesystem.ChannelError(f"Cannot open {path}") from exc


def waiting_payloads(queue_folder: Path, queue: str) -> list[dict]:
    """The messages (kombu payloads) waiting in ``queue`` of the filesystem broker whose queue folder is
    ``queue_folder``: those no consumer has taken yet, oldest first. One a consumer takes while they are read is
    left out; one a killed consumer took (left in the ``claimed`` folder) is not waiting: nothing delivers it."""
    wanted = f"{queue}.msg"
    found = []
    for filename in sorted(os.listdir(queue_folder)):
        if filename.partition(".")[2] != wanted:
            continue
        try:
            data = (Path(queue_folder) / filename).read_bytes()
        except FileNotFoundError:  # a consumer took it meanwhile
            continue
        found.append(loads(bytes_to_str(data)))
    return found


def _binding(routing_key, pattern, queue) -> Binding:
    """A binding as kombu stores it (None as "")."""
    return Binding(routing_key or "", pattern or "", queue or "")


def _read_table(path) -> list[Binding]:
    """The bindings stored in the exchange file ``path``; a missing or empty file holds none."""
    try:
        data = Path(path).read_bytes()
    except FileNotFoundError:
        return []
    return [Binding(*entry) for entry in loads(bytes_to_str(data))] if data.strip() else []


class Transport(filesystem.Transport):
    """Selected by ``broker_transport = "app.core.broker:Transport"`` with ``broker_url = "filesystem://"``."""

    Channel = Channel
    _watch: FolderWatch | None = None
    _watch_pid: int | None = None

    def drain_events(self, connection, timeout=None):
        """kombu's loop (take a message from any consumed queue, else wait and look again), waiting on the queue
        folder's watch while every channel could take a message, for ``polling_interval`` otherwise."""
        started = monotonic()
        watch = self._folder_watch()  # before the first look: a message that arrives after it wakes the wait
        while True:
            try:
                self.cycle.get(self._deliver, timeout=timeout)
                return
            except Empty:
                pass
            left = None if timeout is None else timeout - (monotonic() - started)
            if left is not None and left <= 0:
                raise TimeoutError  # socket.timeout: what kombu and Celery catch
            if watch is None or any(ch._consumers and not ch.qos.can_consume() for ch in self.channels):
                sleep(self.polling_interval if left is None else min(self.polling_interval, left))
            else:
                watch.wait(IDLE_WAIT_S if left is None else min(IDLE_WAIT_S, left))
                if watch.woken:  # the worker is stopping (folder_watch.wake_all): back to Celery's loop at once
                    raise TimeoutError

    def _folder_watch(self) -> FolderWatch | None:
        """This process's watch of the queue folder (a forked child makes its own), made on its first wait."""
        if self._watch_pid != os.getpid():
            folder = self.client.transport_options.get("data_folder_in")
            self._watch = FolderWatch.open(folder) if folder else None
            self._watch_pid = os.getpid()
        return self._watch

    def close_connection(self, connection):
        if self._watch is not None and self._watch_pid == os.getpid():
            self._watch.close()
            self._watch, self._watch_pid = None, None
        super().close_connection(connection)


IDLE_WAIT_S = 5.0
"""The longest wait on the queue folder's watch without a look into the folder (a safety net: a message whose
event was lost, e.g. on a folder another host writes into, is still taken within this time)."""
