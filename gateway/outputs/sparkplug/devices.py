"""The node's devices (one per station) and their metric/alias table. Pure: no I/O, no clock.

A device's metrics are :data:`.metrics.DEVICE_METRICS`; their aliases are a block per device:
``alias_base + index`` (tck-id-payloads-alias-uniqueness), the base from the CRC-32 of the
device ID (:func:`.metrics.device_alias_base`), moved to the next free block when two device IDs
clash. A device keeps the latest value of each metric and when it was set (a DBIRTH carries them),
whether its DBIRTH went out in this session, and whether its station stopped while data of it
still waits in the store-and-forward buffer (then it is buried after the replay).
"""
from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import Any

from . import metrics as M
from .namespace import valid_id

#: a device metric's index in DEVICE_METRICS (its alias is the device's alias_base + index)
DEVICE_INDEX = {d.name: i for i, d in enumerate(M.DEVICE_METRICS)}
_MISSING = object()


@dataclass
class Device:
    device_id: str
    alias_base: int
    values: dict[str, Any] = field(default_factory=dict)
    stamps: dict[str, int] = field(default_factory=dict)
    born: bool = False
    stopped: bool = False          # its station stopped while data of it waits in the buffer

    def names_by_alias(self) -> dict[int, str]:
        """Alias → metric name, for commands that name their metrics by alias."""
        return {self.alias_base + i: d.name for i, d in enumerate(M.DEVICE_METRICS)}


class DeviceTable:
    """The devices of one edge node by device ID, in the order they came up."""

    def __init__(self) -> None:
        self._by_id: dict[str, Device] = {}

    def __getitem__(self, device_id: str) -> Device:
        return self._by_id[device_id]

    def __contains__(self, device_id: object) -> bool:
        return device_id in self._by_id

    def __iter__(self) -> Iterator[Device]:
        return iter(list(self._by_id.values()))

    def get(self, device_id: str) -> Device | None:
        return self._by_id.get(device_id)

    def up(self, device_id: str, values: dict[str, Any], now_ms: int) -> Device:
        """A station (re)starts as this device: its alias block (a CRC clash between two station
        IDs takes the next free block) and its current values. ValueError for a bad device ID."""
        if not valid_id(device_id):
            raise ValueError(f"sparkplug device id {device_id!r}: must be non-empty without '/', '+' or '#'")
        base = M.device_alias_base(device_id)
        taken = {d.alias_base for k, d in self._by_id.items() if k != device_id}
        while base in taken:       # a CRC clash between two station IDs: the next free block
            base += 1 << 12
        dev = self._by_id.get(device_id)
        if dev is None or dev.alias_base != base:
            dev = Device(device_id, base)
            self._by_id[device_id] = dev
        dev.stopped = False
        for k, v in values.items():
            if k in M.DEVICE_BY_NAME:
                dev.values[k] = v
                dev.stamps[k] = int(now_ms)
        return dev

    def adopt(self, device_id: str) -> Device:
        """A device whose data was stored before a restart and whose station does not run here
        (yet): known for its replay, buried after it."""
        dev = Device(device_id, M.device_alias_base(device_id), stopped=True)
        self._by_id[device_id] = dev
        return dev

    def remove(self, device_id: str) -> None:
        del self._by_id[device_id]

    @staticmethod
    def update(dev: Device, values: dict[str, Any], now_ms: int) -> dict[str, Any]:
        """New values of a device's metrics (unknown names ignored): the ones to send, i.e.
        every telemetry value and the other values that changed."""
        changed = {}
        for k, v in values.items():
            d = M.DEVICE_BY_NAME.get(k)
            if d is None:
                continue
            if d.telemetry or dev.values.get(k, _MISSING) != v:
                changed[k] = v
            dev.values[k] = v
            dev.stamps[k] = int(now_ms)
        return changed

    def running(self) -> int:
        """Devices whose station runs (the NBIRTH's Properties/Devices)."""
        return sum(1 for x in self._by_id.values() if not x.stopped)

    def all_unborn(self) -> None:
        """The session ended: every device needs its DBIRTH again."""
        for d in self._by_id.values():
            d.born = False
