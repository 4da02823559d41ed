"""The station's fan-out: every slot record, event and state change goes to every output, in order.

Like python-can's ``Notifier`` with its ``Listener`` objects: the slot loop hands each item to
:class:`Fanout` once, and the fan-out calls each output (:class:`gateway.core.ports.Output`). One
failing output never stops the station or the other outputs: its first failure is logged with
its traceback, later ones are only counted (:attr:`Fanout.failures`), and the count is logged
when the station stops.
"""
from __future__ import annotations

import logging
from collections import Counter
from collections.abc import Sequence

from ..core.ports import JsonObject, Output, WorkerHooks
from ..core.records import Event, SlotRecord, StationState

log = logging.getLogger("hookwatch.station")


class Fanout:
    """Calls ``head`` (the station's own listeners, e.g. its recorder) then ``outputs`` (a list
    that may grow until the station starts)."""

    def __init__(self, station_id: str, outputs: list[Output], head: Sequence[Output] = ()) -> None:
        self.station_id = station_id
        self.outputs = outputs
        self.head = tuple(head)
        self.failures: Counter[str] = Counter()
        #: the outputs whose ``start()`` returned (only these are stopped)
        self.started: list[Output] = []

    def all(self) -> list[Output]:
        return [*self.head, *self.outputs]

    def _failed(self, o: object, what: str) -> None:
        key = f"{type(o).__name__}.{what}"
        self.failures[key] += 1
        if self.failures[key] == 1:
            log.exception("%s: output %r failed on %s (an output never stops the station; further "
                          "failures are counted)", self.station_id, o, what)

    def record(self, rec: SlotRecord) -> None:
        for o in (*self.head, *self.outputs):
            try:
                o.on_record(rec)
            except Exception:
                self._failed(o, "record")

    def event(self, ev: Event) -> None:
        for o in (*self.head, *self.outputs):
            try:
                o.on_event(ev)
            except Exception:
                self._failed(o, "event")

    def state(self, st: StationState) -> None:
        for o in (*self.head, *self.outputs):
            try:
                o.on_state(st)
            except Exception:
                self._failed(o, "state")

    def _hooked(self) -> list[WorkerHooks]:
        """The outputs that take a fleet proxy's hooks (:class:`gateway.core.ports.WorkerHooks`)."""
        return [o for o in (*self.head, *self.outputs) if isinstance(o, WorkerHooks)]

    def worker(self, up: bool, restarts: int = 0) -> None:
        """The station's worker process came up or went down (``WorkerHooks.on_worker``)."""
        for o in self._hooked():
            try:
                o.on_worker(up, restarts)
            except Exception:
                self._failed(o, "on_worker")

    def lost(self, n: int) -> None:
        """``n`` slot records were lost before the fan-out (``WorkerHooks.on_lost``)."""
        for o in self._hooked():
            try:
                o.on_lost(n)
            except Exception:
                self._failed(o, "on_lost")

    def metrics(self, snap: JsonObject) -> None:
        """A worker's metrics snapshot (``WorkerHooks.on_metrics``)."""
        for o in self._hooked():
            try:
                o.on_metrics(snap)
            except Exception:
                self._failed(o, "on_metrics")

    async def start(self) -> None:
        """Start every output. An output that cannot start raises: the station does not run
        half-wired (its supervisor logs it and restarts the station after a back-off)."""
        for o in self.all():
            await o.start()
            self.started.append(o)

    async def stop(self) -> None:
        """Stop every output that started (also when a later one failed to start), each once."""
        started, self.started = self.started, []
        for o in started:
            try:
                await o.stop()
            except Exception:
                self._failed(o, "stop")
        if self.failures:
            log.error("%s: output failures: %s", self.station_id,
                      ", ".join(f"{k} ×{n}" for k, n in sorted(self.failures.items())))
