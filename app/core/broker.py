"""The embedded broker: kombu's filesystem transport with atomic publishing and atomic claiming.

kombu's stock filesystem channel writes a message file in place (a consumer polling at that moment can
read it half written: kombu issue #1551) and claims a message by moving it to the system temp directory
(a copy, not a rename, when that is another filesystem, so two consumers could both take it). Here a
message is written to a hidden temporary name and renamed into the queue folder, and a consumer claims
it by renaming it into a ``claimed`` folder beside the queue: one rename, one winner. Message names,
ordering, fanout exchanges and every other behaviour stay kombu's.
"""

from __future__ import annotations

import contextlib
import os
import uuid
from queue import Empty
from time import monotonic

from kombu.transport import filesystem
from kombu.utils.encoding import bytes_to_str, str_to_bytes
from kombu.utils.json import dumps, loads


class Channel(filesystem.Channel):
    """Filesystem channel whose ``_put`` and ``_get`` are atomic across processes."""

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


class Transport(filesystem.Transport):
    """Selected by ``broker_transport = "app.core.broker:Transport"`` with ``broker_url = "filesystem://"``."""

    Channel = Channel
