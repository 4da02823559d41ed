"""Store and forward: device data held while no primary host listens, replayed in order. Pure.

While no primary host is online (or no connection), device data goes to a :class:`Buffer` as DDATA
payloads whose metrics carry ``is_historical = true`` and their original timestamps; when the host
is online again, after NBIRTH and the DBIRTHs, :meth:`StoreAndForward.drain` replays them in order
(seq assigned at sending), and only then is data published live: the latest values that changed
meanwhile go out live when the replay ends, and the stations that stopped meanwhile get their
DDEATH then.
"""
from __future__ import annotations

from typing import Any, Protocol

from . import metrics as M
from .actions import Publish
from .devices import Device, DeviceTable
from .payloads import Outgoing


class Buffer(Protocol):
    """Store-and-forward of DDATA payloads (the runtime uses the SQLite outbox)."""

    def put(self, topic: str, payload: bytes, telemetry: bool) -> None: ...
    def peek(self, n: int) -> list[tuple[int, str, bytes]]: ...     # (key, topic, payload), oldest first
    def remove(self, keys: list[int]) -> None: ...
    def __len__(self) -> int: ...


class MemoryBuffer:
    """A Buffer in memory (tests, and the fallback when the outbox cannot be opened)."""

    def __init__(self) -> None:
        self.rows: list[tuple[int, str, bytes]] = []
        self._n = 0

    def put(self, topic: str, payload: bytes, telemetry: bool) -> None:
        self._n += 1
        self.rows.append((self._n, topic, payload))

    def peek(self, n: int) -> list[tuple[int, str, bytes]]:
        return self.rows[:n]

    def remove(self, keys: list[int]) -> None:
        ks = set(keys)
        self.rows = [r for r in self.rows if r[0] not in ks]

    def __len__(self) -> int:
        return len(self.rows)


class StoreAndForward:
    """The node's held device data and its replay (see the module docstring)."""

    def __init__(self, buffer: Buffer, devices: DeviceTable, outgoing: Outgoing, counters: dict[str, int],
                 batch: int = 50) -> None:
        self.buffer = buffer
        self.devices = devices
        self.outgoing = outgoing
        self.counters = counters
        self.batch = batch
        self.replaying = False
        #: per device, the metrics that changed during the replay (their latest values go out after it)
        self._dirty: dict[str, set[str]] = {}

    def hold(self, dev: Device, changed: dict[str, Any], now_ms: int) -> None:
        """Device data that cannot go out live now: into the buffer, historical."""
        telemetry = all(M.DEVICE_BY_NAME[k].telemetry for k in changed)
        self.buffer.put(self.outgoing.topics.topic("DDATA", dev.device_id),
                        self.outgoing.historical(dev, changed, now_ms), telemetry)
        self.counters["stored"] += 1

    def changed_during_replay(self, device_id: str, names: dict[str, Any]) -> None:
        self._dirty.setdefault(device_id, set()).update(names)

    def held(self) -> bool:
        """Data waits in the buffer (then the births include the stopped stations' DBIRTHs)."""
        return len(self.buffer) > 0

    def start(self, now_ms: int) -> list[Publish]:
        """The births went out: the replay starts, or — nothing held — the stopped stations are
        buried now."""
        self.replaying = len(self.buffer) > 0
        self._dirty = {}
        if not self.replaying:
            return self.bury_stopped(now_ms)
        return []

    def drain(self, now_ms: int) -> tuple[list[Publish], list[int]]:
        """The next batch of stored DDATA (oldest first, seq assigned now) and the buffer keys to
        remove once they are handed to the client. When the buffer is empty, the replay ends: the
        latest values that changed meanwhile go out live, stopped stations get their DDEATH."""
        rows = self.buffer.peek(self.batch)
        out: list[Publish] = []
        keys: list[int] = []
        for key, topic, payload in rows:
            dev_id = topic.rsplit("/", 1)[-1]
            dev = self.devices.get(dev_id)
            if dev is None:
                # stored before a restart, for a station not (yet) running here: birth it, so that
                # its history is not lost; buried at the end of the replay
                dev = self.devices.adopt(dev_id)
            if not dev.born:
                out.append(self.outgoing.dbirth(dev, now_ms))
            pub = self.outgoing.resend(dev_id, payload)
            keys.append(key)
            if pub is None:         # a damaged row: skipped, counted
                self.counters["ignored_commands"] += 1
                continue
            out.append(pub)
            self.counters["replayed"] += 1
        if len(rows) < self.batch and len(self.buffer) <= len(rows):
            self.replaying = False
            for dev_id, names in self._dirty.items():
                dev = self.devices.get(dev_id)
                if dev is None or not dev.born:
                    continue
                out.append(self.outgoing.ddata(dev, {k: dev.values.get(k) for k in names}, now_ms))
            self._dirty = {}
            out.extend(self.bury_stopped(now_ms))
        return out, keys

    def bury_stopped(self, now_ms: int) -> list[Publish]:
        """The stations that stopped while their data was held: DDEATH (when born), then gone."""
        out = []
        for dev in self.devices:
            if dev.stopped:
                if dev.born:
                    out.append(self.outgoing.ddeath(dev, now_ms))
                self.devices.remove(dev.device_id)
        return out
