"""Gateway side of the STM32 link (docs/protocols/stm32.md): an asyncio client that never blocks
the event loop and never raises.

:class:`Stm32Link` is the client (the ``Stm32Port`` and ``Stm32PostingPort`` contracts of
``gateway/core/ports.py``) over three parts, layered as pymodbus layers its client over a transaction
manager, a framer and a transport:

- :class:`~drivers.stm32.wire.Stm32Wire` (``drivers/stm32/wire.py``): the port, opened with
  pyserial and served non-blocking, and the framing of what comes back;
- :class:`~drivers.stm32.exchange.Exchanges` (``drivers/stm32/exchange.py``): one exchange at a
  time, sequence numbers, timeouts and retries within ``budget_s``, posted SET_SPEEDs collected
  in the next slot without waking the process;
- :class:`~drivers.stm32.keepalive.KeepAlive` (``drivers/stm32/keepalive.py``): the background
  task that reopens a lost port every ``reopen_s`` and feeds the firmware watchdog while the drive
  is enabled, and the drive's enabled state.

Lean on the hot path (issue 16, ``bench/bench_slot_cpu.py``): the uncontended exchange takes no
lock object, a whole ACK read in one chunk is decoded straight from the bytes, a posted command's
ACK does not wake the process, and while commands flow the keep-alive's wake-up is pushed out from
the transmit path instead of waking the loop.

A vanished port (read/write error, hang-up) sets ``connected = False``; calls then return None at
once until the keep-alive task has the port open again. All counters are in one ``counters``
mapping, shared by the parts.
"""
from __future__ import annotations

import asyncio
import logging
import statistics

from gateway.core.ports import DriveStop

from .exchange import Exchanges
from .keepalive import KeepAlive
from .protocol import DEFAULT_BAUD, Cmd, Reply, Status, StopReason, speed_payload, watchdog_for, watchdog_payload
from .wire import Stm32Wire

log = logging.getLogger("hookwatch.stm32")


def stop_reason_code(reason: str | int | StopReason = "") -> StopReason:
    """The station's stop reason text → the code sent with STOP."""
    if isinstance(reason, int):
        try:
            return StopReason(int(reason))
        except ValueError:
            return StopReason.COMMAND
    r = (reason or "").lower()
    if "protection" in r:
        return StopReason.PROTECTION
    if r == "completed":
        return StopReason.TEST_END
    if r.startswith("gateway"):
        return StopReason.GATEWAY
    return StopReason.COMMAND


class Stm32Link:
    """The STM32 take-up controller over its serial link: the wire, the exchanges and the
    keep-alive composed; a ``Stm32Port``, a ``Stm32PostingPort`` and a ``Stm32DriveStops``."""

    def __init__(self, port: str, baud: int = DEFAULT_BAUD, timeout_s: float = 0.01,
                 retries: int = 1, watchdog_s: float = 0.2, *, budget_s: float = 0.018,
                 reopen_s: float = 0.5, keepalive: bool = True):
        self.port = port
        self.baud = int(baud)
        self.timeout_s = float(timeout_s)
        self.retries = max(0, int(retries))
        self.watchdog_s = float(watchdog_s)
        self.budget_s = max(float(budget_s), self.timeout_s)
        self.reopen_s = float(reopen_s)
        self.keepalive_enabled = keepalive
        self.counters: dict[str, int] = {
            "sent": 0, "acked": 0, "naks": 0, "timeouts": 0, "crc_errors": 0, "retries": 0,
            "port_lost": 0, "reopened": 0, "stale": 0, "bad_replies": 0, "keepalives": 0,
            "failed": 0, "drive_stops": 0}
        self.last_status: Status | None = None
        self.wire = Stm32Wire(port, self.baud, self.reopen_s, self.counters, self)
        self.keep = KeepAlive(self)
        self.exchanges = Exchanges(self.wire, self.counters, timeout_s=self.timeout_s,
                                   retries=self.retries, budget_s=self.budget_s,
                                   accept=self._accept_status, sent=self.keep.sent)

    @classmethod
    def from_config(cls, cfg, *, watchdog_s: float | None = None) -> Stm32Link:
        """``watchdog_s``: the period to set at enable (the station's, derived from its
        protection stop when ``stm32.watchdog_s`` is null); else the section's, else the one
        for the method's default protection stop (1 s + WATCHDOG_MARGIN_S)."""
        def get(name, default):
            v = getattr(cfg, name, None)
            return default if v is None else v
        if watchdog_s is None:
            watchdog_s = float(get("watchdog_s", watchdog_for(1.0)))
        return cls(cfg.port, baud=int(get("baud", DEFAULT_BAUD)),
                   timeout_s=float(get("timeout_s", 0.01)), retries=int(get("retries", 1)),
                   watchdog_s=watchdog_s,
                   budget_s=float(get("budget_s", 0.018)))

    # ------------------------------------------------------------------ port
    @property
    def connected(self) -> bool:
        return self.wire.connected

    @connected.setter
    def connected(self, value: bool) -> None:
        self.wire.connected = value

    @property
    def low_latency(self) -> bool:
        """The kernel took low-latency mode for the port."""
        return self.wire.low_latency

    @property
    def busy(self) -> bool:
        """An exchange holds the link."""
        return self.exchanges.busy

    async def open(self) -> None:
        loop = asyncio.get_running_loop()
        self.wire.bind(loop)
        self.exchanges.bind(loop)
        self.wire.open()
        self.keep.start(loop)

    def reopen(self) -> bool:
        """The port open again (the keep-alive task's call while it is lost)."""
        return self.wire.open()

    async def close(self) -> None:
        await self.keep.stop()
        self.exchanges.abort()
        self.wire.release()
        self.wire.connected = False

    # ------------------------------------------------------------------ what the wire hands up
    def reply(self, rep: Reply) -> None:
        self.exchanges.take(rep)

    def damaged(self) -> None:
        self.exchanges.damaged()

    def lost(self) -> None:
        self.exchanges.abort()
        self.keep.poke()

    # ------------------------------------------------------------------ posted speed commands
    def post_speed(self, rpm: float) -> bool:
        """SET_SPEED without waiting for the ACK (:meth:`Exchanges.post_speed`); never blocks,
        never raises. False (not sent) while another exchange holds the link, the port is gone,
        the speed is not a finite number or the write would block."""
        if not self.wire.connected or self.exchanges.busy:
            return False
        payload = self._speed_payload(rpm)
        return payload is not None and self.exchanges.post_speed(payload)

    def collect(self) -> Status | None:
        """The status from the ACK of the command :meth:`post_speed` sent, read from the port
        without waiting; None if nothing is posted or no valid ACK has come (counted)."""
        return self.exchanges.collect()

    # ------------------------------------------------------------------ status
    async def _status(self, cmd: Cmd, payload: bytes = b"", attempts: int = 1) -> Status | None:
        """The status from the ACK, or None. ``attempts`` > 1 repeats the call (a new SEQ each
        time) when it got no answer at all — for ENABLE and STOP, whose effect matters."""
        rep = None
        for _ in range(max(1, attempts)):
            try:
                rep = await self.exchanges.exchange(cmd, payload)
            except Exception:   # never raise into the station
                log.exception("stm32 %s: %s failed", self.port, cmd.name)
                return None
            if rep is not None:
                break
            if not self.connected:
                return None
        if rep is None or not rep.ok or rep.status is None:    # an ACK always carries a status
            return None
        return self._accept_status(rep.status)

    def _accept_status(self, st: Status | None) -> Status | None:
        if st is None:
            return None
        self.last_status = st
        self.keep.accept(st)
        return st

    # ------------------------------------------------------------------ API
    async def enable(self) -> Status | None:
        """Set the firmware watchdog to the configured period (unless it already has it), then
        ENABLE (speed command 0). Up to 3 calls if there is no answer at all."""
        self.keep.want_enabled = True
        want = int(round(self.watchdog_s * 1000))
        st = self.last_status
        if st is None or st.watchdog_ms != want:
            await self._status(Cmd.SET_WATCHDOG, watchdog_payload(self.watchdog_s), attempts=2)
        st = await self._status(Cmd.ENABLE, attempts=3)
        if st is not None and st.watchdog_ms != want:
            # the SET_WATCHDOG before went unanswered (or the firmware restarted since): the
            # drive now runs on the firmware's period, so set ours (allowed while enabled)
            st = await self._status(Cmd.SET_WATCHDOG, watchdog_payload(self.watchdog_s),
                                    attempts=2) or st
        return st

    async def disable(self) -> Status | None:
        self.keep.want_enabled = False          # no keep-alive from now on, whatever the answer
        return await self._status(Cmd.DISABLE, attempts=3)

    def _speed_payload(self, rpm: float) -> bytes | None:
        try:
            return speed_payload(float(rpm))
        except (TypeError, ValueError):
            self.counters["failed"] += 1
            log.warning("stm32 %s: set_speed(%r) not sent: not a finite number", self.port, rpm)
            return None

    async def set_speed(self, rpm: float) -> Status | None:
        payload = self._speed_payload(rpm)
        if payload is None:
            return None
        return await self._status(Cmd.SET_SPEED, payload)

    async def stop(self, reason: str | int = "") -> Status | None:
        """STOP with the reason code (up to 3 calls if unanswered). The keep-alive ends at once,
        so even a STOP that never arrives stops the motor by the firmware watchdog."""
        self.keep.want_enabled = False
        return await self._status(Cmd.STOP, bytes((int(stop_reason_code(reason)),)), attempts=3)

    async def read_status(self) -> Status | None:
        return await self._status(Cmd.READ_STATUS)

    def take_drive_stop(self) -> DriveStop | None:
        """The newest stop of the drive on its own not taken yet (once), with the gateway's
        longest silence on the line before it (:class:`gateway.core.ports.Stm32DriveStops`)."""
        ds, self.keep.drive_stop = self.keep.drive_stop, None
        return ds

    async def ping(self) -> Status | None:
        return await self._status(Cmd.PING)

    async def set_watchdog(self, seconds: float) -> Status | None:
        return await self._status(Cmd.SET_WATCHDOG, watchdog_payload(seconds))

    # ------------------------------------------------------------------ keep-alive
    @property
    def keepalive_interval_s(self) -> float:
        return self.keep.interval_s

    @property
    def armed(self) -> bool:
        """Keep-alive wanted: enable() was called (no stop()/disable() since) and the firmware
        last reported the drive enabled."""
        return self.keep.armed

    async def keepalive(self) -> Status | None:
        """PING if the firmware is enabled and nothing went out for half the watchdog period."""
        return await self.keep.keepalive()

    # ------------------------------------------------------------------ figures
    @property
    def last_nak(self) -> Reply | None:
        return self.exchanges.last_nak

    @property
    def last_rtt_s(self) -> float:
        return self.exchanges.last_rtt_s

    def rtt_summary(self) -> dict[str, float]:
        r = sorted(self.exchanges.rtts)
        if not r:
            return {"n": 0}
        return {"n": len(r), "median_ms": statistics.median(r) * 1e3,
                "p90_ms": r[int(0.9 * (len(r) - 1))] * 1e3, "max_ms": r[-1] * 1e3}
