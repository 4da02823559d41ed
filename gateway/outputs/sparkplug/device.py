"""A station's Sparkplug device on an edge node of a fleet's supervisor (the output registry's
``sparkplug`` row builds it for a station proxy, ``gateway.supervisor.remote.RemoteStation``)."""
from __future__ import annotations

import asyncio
import threading
import time
from typing import Any

from ...core.ports import StationView
from ...core.records import SlotRecord, StationState
from . import runtime as sparkplug_client
from .output import SparkplugOutput, state_values

__all__ = ["SparkplugDevice"]


class SparkplugDevice(SparkplugOutput):
    """A station proxy's Sparkplug device on an edge node of the supervisor (see the module doc).

    The same output as in one process (metric set, aggregation, commands through the station's
    ``submit``), with one difference: the device lives while its WORKER does. ``start`` attaches
    the station to its node (one :class:`~gateway.outputs.sparkplug.runtime.NodeRuntime` per
    broker, group and edge node in the supervisor: stations sharing a node share its session,
    its bdSeq and its Will) without a device; ``on_worker(True)`` (HELLO) brings the device up —
    a DBIRTH with the station's current values once the node is born — and ``on_worker(False)``
    (its worker crashed, was killed or is restarting) takes it down: a DDEATH, the node and the
    other stations' devices going on. Nothing of a down worker is published (no stale values)."""

    def __init__(self, settings: Any, station: StationView | None = None) -> None:
        super().__init__(settings, station)
        self.up = False
        self._up_lock = threading.Lock()

    async def start(self) -> None:
        self.loop = asyncio.get_running_loop()
        self.rt = sparkplug_client.attach(self.s, self)     # the device is born with its worker

    async def stop(self) -> None:
        with self._up_lock:
            self.up = False
        await super().stop()

    def on_worker(self, up: bool, restarts: int = 0) -> None:
        with self._up_lock:
            if bool(up) == self.up or self.rt is None:
                return
            self.up = bool(up)
            if up:
                self._agg = None
                self._last = state_values(self.station.state) if self.station is not None else {}
                self.rt.post(("up", self.s.device_id, dict(self._last)))
            else:
                self._flush(time.monotonic())
                self._agg = None
                self.rt.post(("down", self.s.device_id))

    def on_lost(self, n: int) -> None:
        pass        # a device reports the slots it is given; a lost span is not published

    def on_metrics(self, snap: dict[str, Any]) -> None:
        pass        # the worker's figures go to the metrics endpoint, not to the device

    def on_record(self, rec: SlotRecord) -> None:
        if self.up:
            super().on_record(rec)

    def on_state(self, st: StationState) -> None:
        if self.up:
            super().on_state(st)

    def on_event(self, ev: Any) -> None:
        if self.up:
            super().on_event(ev)
