"""A station's links and stores: its two serial ports, its uplinks (MQTT) and its disks.

Each reaches the outputs through the station's state (``meter_ok``, ``stm32_ok``, ``mqtt_ok``,
``disk_ok``, written through the :class:`~.status.StatusBoard`) and, for a port or a disk, as a
pair of events per transition (``port_lost``/``port_back``, ``disk_full``/``disk_ok``). Called on
the station's own loop (others hand over through ``gateway.plumbing.threadloop``).
"""
from __future__ import annotations

import asyncio
import logging
from typing import Any

from ..core.ports import MeterDiagnosis, MeterPort, Stm32Port
from ..core.records import EventType
from ..plumbing.ratelog import RateLog
from ..plumbing.threadloop import call_soon_on
from .recorder import TestRecorder
from .status import StatusBoard

__all__ = ["Health"]

log = logging.getLogger("hookwatch.station")

#: the meter's counters of reads that gave no reading, by the cause they name
_METER_FAILURES = ("timeouts", "crc_errors", "garbage", "modbus_exceptions", "decode_errors",
                   "stale_replies", "not_connected", "errors")


class Health:
    def __init__(self, board: StatusBoard, meter: MeterPort, stm32: Stm32Port) -> None:
        self.board = board
        self.ports: tuple[tuple[str, MeterPort | Stm32Port], ...] = (("meter", meter), ("stm32", stm32))
        #: the ports' last seen state and loss count (:meth:`check_links`)
        self._port_seen: dict[str, bool | None] = {"meter": None, "stm32": None}
        self._port_lost_seen: dict[str, int] = {}
        self._uplinks: dict[str, bool] = {}
        self._disks: dict[str, bool] = {}
        self.meter = meter
        self._diagnosis = meter if isinstance(meter, MeterDiagnosis) else None
        #: failing meter reads: one line per cause a window, with the count (RateLog)
        self.meter_log = RateLog(log)
        self._meter_seen: dict[str, int] = {}

    def set_uplink(self, name: str, ok: bool) -> None:
        """An uplink (MQTT) reports its connection; it reaches every output through the state
        (``StationState.mqtt_ok``), e.g. the PLC's status."""
        if self._uplinks.get(name) == ok:
            return
        self._uplinks[name] = ok
        self.board.update(mqtt_ok=bool(self._uplinks.get("mqtt", False)), push=True)

    def set_disk(self, store: str, ok: bool, info: dict[str, Any] | None = None) -> None:
        """A store (``records``: the running test's recorder; ``outbox``: the MQTT outbox) reports
        that its disk can (not) be written. One ``disk_full``/``disk_ok`` event per transition of
        a store; ``StationState.disk_ok`` is False while any store cannot write."""
        if self._disks.get(store, True) == ok:
            return
        self._disks[store] = ok
        info = dict(info or {})
        data: dict[str, Any] = {"store": store, "reason": info.get("reason")}
        if ok:
            data.update({k: info[k] for k in ("duration_s", "lost_rows") if k in info})
        self.board.emit(EventType.DISK_OK if ok else EventType.DISK_FULL, **data)
        self.board.update(disk_ok=all(self._disks.values()), push=True)

    def watch_recorder(self, rec: TestRecorder) -> None:
        """The running test's recorder reports its disk state here (on this loop)."""
        loop = asyncio.get_running_loop()

        # called from inside the recorder's writes (within the fan-out): decided on the next turn
        def on_disk_state(ok: bool, info: dict[str, Any]) -> None:
            call_soon_on(loop, self.set_disk, "records", ok, info)
        rec.on_disk_state = on_disk_state
        self.set_disk("records", rec.disk_ok, {"reason": "the test folder cannot be written"}
                      if not rec.disk_ok else {})

    def check_links(self) -> None:
        """Port state to events and the station state, checked once a second. A port lost and back
        between two checks (a meter gone for 0.5 s) still gives its ``port_lost``/``port_back``
        pair: the drivers count every loss (``counters["port_lost"]``)."""
        changed = False
        emit = self.board.emit
        for port, drv in self.ports:
            ok = bool(drv.connected)
            was = self._port_seen.get(port)
            lost_n = int(drv.counters.get("port_lost", 0))
            lost_before = self._port_lost_seen.get(port, lost_n)
            if was is not None:
                if ok != was:
                    emit(EventType.PORT_BACK if ok else EventType.PORT_LOST, port=port)
                elif ok and lost_n > lost_before:    # lost and back since the last check
                    emit(EventType.PORT_LOST, port=port, brief=True, times=lost_n - lost_before)
                    emit(EventType.PORT_BACK, port=port, brief=True)
            if ok != was:
                changed = True
            self._port_seen[port] = ok
            self._port_lost_seen[port] = lost_n
        self.board.update(meter_ok=bool(self._port_seen["meter"]),
                          stm32_ok=bool(self._port_seen["stm32"]), push=changed)
        self.check_meter_reads()

    def check_meter_reads(self) -> None:
        """Reads that gave no reading since the last check, said in one counted line per cause
        (the driver's own sentence: port, settings and why), whatever the cause — a silent
        meter, a wrong unit ID, replies that fail their CRC or come sooner than the wire can
        carry them. The counts of every cause are in the meter's counters (metrics)."""
        c = self.meter.counters
        now = {k: int(c.get(k, 0)) for k in ("reads", "reads_ok", *_METER_FAILURES)}
        before, self._meter_seen = self._meter_seen, now
        if not before:
            before = {k: 0 for k in now}
        d = {k: now[k] - before.get(k, 0) for k in now}
        polls = d["reads"] + d["not_connected"]
        failed = polls - d["reads_ok"]
        if failed <= 0:
            return
        causes = ", ".join(f"{d[k]} {k}" for k in _METER_FAILURES if d[k] > 0) or "no cause counted"
        why = self._diagnosis.failure_text() if self._diagnosis is not None else None
        kind = max(_METER_FAILURES, key=lambda k: d[k])
        self.meter_log.warning(("meter", kind), "meter: %d of %d reads since the last check gave no "
                               "reading (%s): %s", failed, polls, causes,
                               why or "see the meter's counters")
