"""The embedded broker: kombu's filesystem transport with atomic publishing and atomic claiming.

kombu's stock filesystem channel writes a message file in place (a consumer polling at that moment can
read it half written: kombu issue #1551) and claims a message by moving it to the system temp directory
(a copy, not a rename, when that is another filesystem, so two consumers could both take it). Here a
message is written to a hidden temporary name and renamed into the queue folder, and a consumer claims
it by renaming it into a ``claimed`` folder beside the queue: one rename, one winner. kombu's channel also
binds a queue to a fanout exchange by testing whether the exchange's file exists and then truncating it
(processes that bind at the same moment, such as the workers of ``voxnerf serve``, lose each other's bindings
or leave the file unreadable, and a worker whose binding is lost never answers ``/healthz``). Here the file is
read, changed and rewritten under one exclusive lock, and an empty file is an empty table. Message names,
ordering and every other behaviour stay kombu's.
"""

from __future__ import annotations

import contextlib
import fcntl
import os
import uuid
from queue import Empty
from time import monotonic

from kombu.transport import filesystem, virtual
from kombu.utils.encoding import bytes_to_str, str_to_bytes
from kombu.utils.json import dumps, loads

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
            with open(path, "rb") as f:
                fcntl.flock(f, fcntl.LOCK_SH)  # released by close
                return _parse_table(f.read())
        except FileNotFoundError:
            return []
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
        """Replace the bindings of ``exchange`` by ``edit(bindings)``: read, edit and rewrite under one
        exclusive lock, so no other process's change between the read and the write is lost."""
        path = self._exchange_file(exchange)
        self.control_folder.mkdir(parents=True, exist_ok=True)
        try:
            with open(os.open(path, os.O_RDWR | os.O_CREAT, 0o644), "r+b") as f:  # never truncated unlocked
                fcntl.flock(f, fcntl.LOCK_EX)  # released by close
                table = _parse_table(f.read())
                edited = edit(table)
                if edited != table:
                    f.seek(0)
                    f.write(str_to_bytes(dumps(edited)))
                    f.truncate()
        except OSError as exc:
            raise filesystem.ChannelError(f"Cannot open {path}") from exc


def _binding(routing_key, pattern, queue) -> Binding:
    """A binding as kombu stores it (None as "")."""
    return Binding(routing_key or "", pattern or "", queue or "")


def _parse_table(data: bytes) -> list[Binding]:
    """The bindings stored in an exchange file; an empty file (created, not yet written) holds none."""
    return [Binding(*entry) for entry in loads(bytes_to_str(data))] if data.strip() else []


class Transport(filesystem.Transport):
    """Selected by ``broker_transport = "app.core.broker:Transport"`` with ``broker_url = "filesystem://"``."""

    Channel = Channel
