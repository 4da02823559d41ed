"""Modbus TCP server for PLCs: live values in input registers, commands in holding registers.

One server per (host, port) in the process, shared by the stations configured on it; each station
answers on its own unit ID. The server is our own asyncio server in layers
(``gateway/outputs/plc/modbus_tcp``: MBAP framer, pure PDU codec, server with connection caps, idle
timeout and pacing; only the functions the register map documents) and runs on its own thread and
event loop, so PLC traffic never runs on a station's loop.

- Live values: each station's :class:`ModbusOutput` (a station output) encodes a complete input
  register image on the station's loop (about 10 times a second from slot records, and on every
  state change) and swaps it in with one reference assignment; a read returns a consistent
  snapshot. The heartbeat is advanced by that same loop: it stops when the station is stuck.
- Writes: refused with exception 01 unless the station's YAML enables them and the client's
  address is listed (an address or a network, e.g. ``10.10.5.0/24``); every value is checked against the
  register map and the shared command rules (gateway/core/command_rules.py) before anything changes
  (exception 03 when out of range); commands go to ``station.submit`` on the station's own loop
  (source ``plc:<address>``), a refused command answers the exception its reason code maps to
  (``registers.refusal_exception``: 06 busy, 03 refused value, 04 only when the station failed to
  answer) with the reason code in ``last_result``.
- The client address of a request is the connection's peer address.
"""
from __future__ import annotations

import asyncio
import ipaddress
import logging
import math
import os
import sys
import threading
import time
from dataclasses import dataclass
from typing import Any

from ... import __version__
from ...core import catalog
from ...core.command_intake import intake, rejected_event_data
from ...core.command_rules import CODE, Rejection, check_sample_id, reply_code
from ...core.ports import CommandSink, StationLimits, StationView
from ...core.records import Command, CommandKind, Event, EventType, SlotRecord, StationState, TestState
from ...core.slotwindow import SlotWindow
from ...plumbing.doors import DoorLimits
from ...plumbing.ratelog import RateLog, safe
from ...plumbing.threadloop import call_soon_on, submit_to
from . import registers as R
from .modbus_tcp.pdu import Exc as ExcCodes
from .modbus_tcp.tcp_server import ModbusTcpServer, Pacer, Store

log = logging.getLogger("hookwatch.modbus")

#: input registers served from the command status (not from the station's image)
CMD_BASE = R.IR["last_command"].address
CMD_REGS = 3
#: input registers after the command status (from the station's image again)
TAIL_BASE = CMD_BASE + CMD_REGS
STATUS_ADDR = R.IR["status"].address
WRITES_BIT = 1 << R.STATUS_BIT["writes_enabled"]
LIVE_UPDATE_S = 0.1
COMMAND_TIMEOUT_S = 5.0
SWITCH_INTERVAL_S = 0.0005
#: requests per second the server answers at most (all clients, all units together)
MAX_REQUESTS_PER_S = float(os.environ.get("HW_MODBUS_MAX_RPS", 4000.0))
#: the server thread's nice value above the process's
SERVER_NICE = 10



# ============================================================================ the datastore
class Unit:
    """One station's registers on a shared server."""

    def __init__(self, unit_id: int, owner: ModbusOutput):
        self.unit_id = unit_id
        self.owner = owner
        self.ir: list[int] = [0] * CMD_BASE
        self.hr: list[int] = [0] * R.HOLDING_SIZE
        self.cmd_regs: list[int] = [0] * CMD_REGS
        self.tail: list[int] = [0] * (R.INPUT_SIZE - TAIL_BASE)
        self.lock = asyncio.Lock()      # writes of one unit are applied one at a time

    def may_write(self, peer: str | None) -> bool:
        return self.owner.may_write(peer)

    def allowed(self, peer: str | None) -> bool:
        """``peer`` is in the station's allow-list (its connections always find room)."""
        return self.owner.allowed(peer)

    def write_policy(self) -> str:
        o = self.owner
        return ("writes allowed only from " + ", ".join(sorted(o.allowed_clients))
                if o.writes_enabled else "writes disabled")

    def input_image(self) -> list[int]:
        """The whole input table: the station's image with the command status in its place."""
        return self.ir + self.cmd_regs + self.tail

    def decorate_input(self, regs: list[int], address: int, peer: str | None) -> list[int]:
        """The status word's ``writes_enabled`` bit is per client."""
        if address <= STATUS_ADDR < address + len(regs) and self.may_write(peer):
            regs = list(regs)
            regs[STATUS_ADDR - address] |= WRITES_BIT
        return regs


# ============================================================================ shared servers
class SharedServer:
    """A Modbus TCP server on (host, port) in its own thread and loop, shared by stations."""

    RETRY_S = 5.0
    LINGER_S = 3.0

    def __init__(self, host: str, port: int, limits: DoorLimits | None = None):
        self.host, self.port = host, port
        self.limits = limits
        self.store = Store()
        self.pacer = Pacer(MAX_REQUESTS_PER_S)
        self.loop: asyncio.AbstractEventLoop | None = None
        self.server: ModbusTcpServer | None = None
        self.listening = threading.Event()
        self.error: str | None = None
        self._stop: asyncio.Event | None = None
        self._ready = threading.Event()
        self._thread = threading.Thread(target=self._main, name=f"modbus-{host}:{port}", daemon=True)
        self._linger: threading.Timer | None = None
        self._thread.start()
        self._ready.wait(10)

    def _main(self) -> None:
        asyncio.run(self._serve())

    async def _serve(self) -> None:
        # PLC traffic runs in this thread of the gateway process: a station thread woken by its
        # slot clock must get the interpreter within ~1 ms, not the default 5 ms switch interval
        if sys.getswitchinterval() > SWITCH_INTERVAL_S:
            sys.setswitchinterval(SWITCH_INTERVAL_S)
        # and on a busy box the OS runs the stations' threads before this one (Linux: per thread)
        try:
            os.setpriority(os.PRIO_PROCESS, threading.get_native_id(),
                           os.getpriority(os.PRIO_PROCESS, 0) + SERVER_NICE)
        except (OSError, AttributeError):
            pass
        self.loop = asyncio.get_running_loop()
        self._stop = asyncio.Event()
        self._ready.set()
        logged = False
        while not self._stop.is_set():
            server = ModbusTcpServer(self.store, self.pacer, limits=self.limits)
            try:
                await server.start(self.host, self.port)
            except Exception as e:  # address in use, permission
                await server.close()
                self.error = f"modbus_tcp {self.host}:{self.port}: cannot listen: {e}"
                if not logged:
                    log.error("%s; retrying every %.0f s", self.error, self.RETRY_S)
                    logged = True
                try:
                    await asyncio.wait_for(self._stop.wait(), self.RETRY_S)
                except TimeoutError:
                    pass
                continue
            self.server = server
            self.error = None
            self.listening.set()
            log.info("Modbus TCP server listening on %s:%d", self.host, self.port)
            await self._stop.wait()
        if self.server is not None:
            await self.server.close()
            self.server = None
        self.listening.clear()

    def register(self, unit: Unit) -> bool:
        if self._linger is not None:
            self._linger.cancel()
            self._linger = None
        other = self.store.units.get(unit.unit_id)
        if other is not None and other.owner is not unit.owner:
            log.error("modbus_tcp %s:%d: unit_id %d is already used by station %s; station %s is not "
                      "served", self.host, self.port, unit.unit_id, other.owner.station_id,
                      unit.owner.station_id)
            return False
        self.store.units = {**self.store.units, unit.unit_id: unit}
        return True

    def unregister(self, unit: Unit) -> None:
        if self.store.units.get(unit.unit_id) is unit:
            units = dict(self.store.units)
            del units[unit.unit_id]
            self.store.units = units
        if not self.store.units:
            self._linger = threading.Timer(self.LINGER_S, self._linger_done)
            self._linger.daemon = True
            self._linger.start()

    def _linger_done(self) -> None:
        with _REG_LOCK:
            if self.store.units:
                return
            if _SERVERS.get((self.host, self.port)) is self:
                del _SERVERS[(self.host, self.port)]
        self.shutdown()

    def shutdown(self, timeout: float = 5.0) -> None:
        if self.loop is not None and self._stop is not None:
            try:
                self.loop.call_soon_threadsafe(self._stop.set)
            except RuntimeError:
                pass
        self._thread.join(timeout)


_SERVERS: dict[tuple[str, int], SharedServer] = {}
_REG_LOCK = threading.Lock()


def shared_server(host: str, port: int, limits: DoorLimits | None = None) -> SharedServer:
    """The server on (host, port), started by the first station that names it (with its
    ``modbus_tcp`` door limits)."""
    with _REG_LOCK:
        s = _SERVERS.get((host, port))
        if s is None or not s._thread.is_alive():
            s = _SERVERS[(host, port)] = SharedServer(host, port, limits)
        if s._linger is not None:
            s._linger.cancel()
            s._linger = None
        return s


def shutdown_all() -> None:
    """Stop every server of this process (tests)."""
    with _REG_LOCK:
        servers = list(_SERVERS.values())
        _SERVERS.clear()
    for s in servers:
        if s._linger is not None:
            s._linger.cancel()
        s.shutdown()


# ============================================================================ the station output
@dataclass
class ModbusSettings:
    station_id: str
    host: str = "127.0.0.1"
    port: int = 5020
    unit_id: int = 1
    word_order: str = "big"
    writes_enabled: bool = False
    allowed_clients: tuple[str, ...] = ()
    grades: tuple[str, ...] = ("I", "II")
    live_update_s: float = LIVE_UPDATE_S
    #: connection cap, request deadline, idle timeout of the port (the first station's win)
    door: DoorLimits | None = None


#: the latest slot before the first: no reading, speed command 0
_NO_SLOT = SlotRecord(-1, 0.0, False, math.nan, math.nan, 0, 0, None, None, math.nan, 0.0, math.nan, False)


class ModbusOutput:
    """Station output serving one station on a shared Modbus TCP server."""

    def __init__(self, settings: ModbusSettings, station: StationView | None = None):
        self.s = settings
        self.station_id = settings.station_id
        self.station = station
        #: where commands go (a CommandSource bound to its CommandSink: the station)
        self.sink: CommandSink | None = station
        self.writes_enabled = bool(settings.writes_enabled)
        self.allowed_clients = frozenset(str(a) for a in settings.allowed_clients)
        self._allowed_nets = _networks(self.allowed_clients)
        self.word_order = settings.word_order
        self.limits: StationLimits = (station.limits if station is not None
                                      else StationLimits(grades=tuple(settings.grades)))
        self.grades = self.limits.grades
        self.loop: asyncio.AbstractEventLoop | None = None
        self.server: SharedServer | None = None
        self.unit: Unit | None = None
        self._t0 = time.monotonic()
        self._last_update = 0.0
        self._state = StationState(station=settings.station_id)
        self._sw = R.software_version(__version__)
        # live values (station loop): the latest slot record (none yet: no reading, speed 0)
        self._rec = _NO_SLOT
        self._mu = math.nan
        self._mu_t = -1e9
        self._sat_t = -1e9
        self._in_test = False
        self._elapsed = 0.0
        #: the running test's slots (its valid ratio and reason counts), opened at each test start
        self._test = SlotWindow()
        #: refused writes and commands: one log line per kind per minute, with the count
        self.refusal_log = RateLog(log)
        #: the state's values this output serves, by register (the catalog's rows with one)
        self.catalog_regs = R.CATALOG_REGS
        #: the slot records' values it serves, by register (the catalog's slot rows with one; a
        #: row with neither a latest-slot nor a test-window source is filled here: `mu`)
        self.slot_regs = R.SLOT_REGS

    source = "plc"

    def bind(self, sink: CommandSink) -> None:
        """Send the PLC's commands to ``sink`` (gateway.core.ports.CommandSource)."""
        self.sink = sink

    def may_write(self, peer: str | None) -> bool:
        """Writes enabled and ``peer`` inside one of ``allowed_clients`` (addresses or networks)."""
        return self.writes_enabled and self.allowed(peer)

    def allowed(self, peer: str | None) -> bool:
        """``peer`` inside one of ``allowed_clients`` (writes enabled or not)."""
        if not peer:
            return False
        try:
            ip = ipaddress.ip_address(peer)
        except ValueError:
            return False
        if isinstance(ip, ipaddress.IPv6Address) and ip.ipv4_mapped is not None:   # ::ffff:a.b.c.d
            ip = ip.ipv4_mapped
        return any(ip in n for n in self._allowed_nets if n.version == ip.version)

    # -- output protocol (station loop)
    async def start(self) -> None:
        self.loop = asyncio.get_running_loop()
        self.server = await self.loop.run_in_executor(None, shared_server, self.s.host, int(self.s.port),
                                                  self.s.door)
        unit = Unit(int(self.s.unit_id), self)
        unit.hr = self._initial_holding()
        self.unit = unit
        self._update(force=True)
        if not self.server.register(unit):
            self.unit = None

    async def stop(self) -> None:
        if self.server is not None and self.unit is not None:
            self.server.unregister(self.unit)
        self.unit = None
        self.refusal_log.close()        # the counts of the last window, and no timer after

    def on_record(self, rec: SlotRecord) -> None:
        now = time.monotonic()
        self._rec = rec
        if rec.q and rec.mu is not None:
            self._mu, self._mu_t = rec.mu, now
        if rec.saturated:
            self._sat_t = now
        if self._in_test:
            self._test.add(rec)
            self._elapsed = rec.t
        if now - self._last_update >= self.s.live_update_s:
            self._update(now=now)

    def on_event(self, ev: Event) -> None:
        if ev.type == EventType.TEST_STARTED:
            self._in_test = True
            self._test = SlotWindow()
            self._elapsed = 0.0
        elif ev.type == EventType.TEST_ENDED and ev.test_id is not None:
            self._in_test = False

    def on_state(self, st: StationState) -> None:
        self._state = st
        if st.state in (TestState.BASELINE_SEARCH, TestState.MONITORING, TestState.END_OF_LIFE):
            self._elapsed = max(self._elapsed, float(st.elapsed_s))
        self._update(force=True)

    # -- register image
    def values(self, now: float | None = None) -> dict[str, Any]:
        now = time.monotonic() if now is None else now
        st = self._state
        w = self._test
        running = st.state in (TestState.BASELINE_SEARCH, TestState.MONITORING, TestState.END_OF_LIFE)
        flags = {
            "running": running, "baseline_found": st.mu_ss is not None,
            "end_of_life": st.t_life is not None,
            "alarm_unacknowledged": st.alarm in ("unacknowledged", "rtn_unacknowledged"),
            "mqtt_connected": bool(st.mqtt_ok), "saturation": now - self._sat_t <= 1.0,
            "starting": st.state == TestState.STARTING,
            # the flags of the state: the catalog's rows with a status bit (gateway/core/catalog.py)
            **{name: bool(row.source(st)) for name, row in R.STATUS_FLAGS.items()},
        }
        v: dict[str, Any] = {
            "heartbeat": int(now - self._t0) & 0xFFFF, "map_version": R.MAP_VERSION, "map_minor": R.MAP_MINOR,
            "sw_major": self._sw[0], "sw_minor": self._sw[1], "sw_patch": self._sw[2],
            "status": R.status_word(flags),
            "mu": self._mu if now - self._mu_t <= 1.0 else math.nan,
            "elapsed": self._elapsed,
        }
        # the values of the slot records: the catalog's slot rows (the latest slot, the test's window)
        rec = self._rec
        for name, srow in self.slot_regs.items():
            if srow.latest is not None:
                v[name] = srow.latest(rec)
            elif srow.plc_test is not None:
                v[name] = srow.plc_test(w)
        for name, c in w.reason_counts().items():
            v[f"count_{name.lower()}"] = c
        # the values of the station's state: the catalog's rows (gateway/core/catalog.py)
        for name, row in self.catalog_regs.items():
            v[name] = catalog.plc_number(row, st)
        return v

    def _update(self, now: float | None = None, force: bool = False) -> None:
        now = time.monotonic() if now is None else now
        self._last_update = now
        u = self.unit
        if u is None:
            return
        img = R.encode_table(R.INPUT_REGS, R.INPUT_SIZE, self.values(now), self.word_order)
        u.ir, u.tail = img[:CMD_BASE], img[TAIL_BASE:]

    def _initial_holding(self) -> list[int]:
        plan = self.station.default_plan if self.station is not None else None
        v: dict[str, Any] = {"command": 0, "t_end": 0}
        if plan is not None:
            v["t_set"] = plan.t_set
            v["sample_id"] = plan.sample_id if plan.sample_id and not check_sample_id(plan.sample_id) else ""
            v["grade"] = self.grades.index(plan.grade) + 1 if plan.grade in self.grades else 0
        else:
            v["t_set"] = math.nan
        return R.encode_table(R.HOLDING_REGS, R.HOLDING_SIZE, v, self.word_order)

    # -- writes (server loop)
    async def handle_write(self, u: Unit, address: int, values: list[int], peer: str) -> ExcCodes | None:
        plan = R.plan_write(u.hr, address, values, self.word_order, self.limits)
        if plan.exception is not None:
            if plan.decoded:
                (name, val), = plan.decoded
                self.refusal_log.info(("write", name, int(plan.exception)), "%s: PLC %s wrote %s=%s: %s",
                                      self.station_id, peer, name, safe(val), plan.reason)
            return ExcCodes(plan.exception)
        # staging values first, then the setpoint, then the command
        u.hr = list(plan.staged)
        if plan.wrote("t_set"):
            t_set = float(f"{plan.value('t_set'):.7g}")
            reply = await self._submit(intake(CommandKind.SETPOINT.value, {"t_set": t_set}, f"plc:{peer}"),
                                       R.COMMAND_CODE["setpoint"], u)
            if not reply:
                return ExcCodes(R.refusal_exception(u.cmd_regs[1]))
            u.hr = R.apply_register(u.hr, plan.new, "t_set")
        if plan.wrote("command"):
            code = int(plan.value("command"))   # the command register reads 0 (docs/registers.md)
            kind = R.COMMAND_KINDS[code]
            args = R.command_args(kind, u.hr, self.word_order, self.grades)
            if not await self._submit(intake(kind.value, args, f"plc:{peer}"), code, u):
                return ExcCodes(R.refusal_exception(u.cmd_regs[1]))
        return None

    async def _submit(self, cmd: Command | Rejection, code: int, u: Unit) -> bool:
        """``cmd`` as the intake made it (gateway/core/command_intake.py) to the station through
        its refusal gate; the result code goes to ``last_result``. A refusal is logged once per
        kind per minute with the count (and the station's ``command_rejected`` events likewise)."""
        st, loop = self.sink, self.loop
        result = CODE["NO_STATION"]
        ok = False
        name = next((n for c, n, _ in R.COMMAND_CODES if c == code), "command")
        if isinstance(cmd, Rejection):
            if st is not None and loop is not None:
                call_soon_on(loop, st.refused, rejected_event_data(name, cmd, "plc"))
            fut = None
            result = int(cmd.code)
            self.refusal_log.info(("command", name, result), "%s: PLC command %s refused: %s",
                                  self.station_id, name, cmd.reason)
        else:
            fut = submit_to(loop, st.submit(cmd)) if st is not None else None
        if fut is not None and isinstance(cmd, Command):
            try:
                reply = await asyncio.wait_for(asyncio.wrap_future(fut), COMMAND_TIMEOUT_S)
                ok = bool(reply.ok)
                result = reply_code(reply)
                if not ok:
                    self.refusal_log.info(("command", cmd.kind.value, result),
                                          "%s: PLC command %s from %s refused: %s", self.station_id,
                                          cmd.kind.value, cmd.source, reply.reason)
            except (TimeoutError, RuntimeError, Exception) as e:
                self.refusal_log.log(("no_answer", cmd.kind.value), logging.ERROR,
                                     "%s: PLC command %s: station did not answer (%s)", self.station_id,
                                     cmd.kind.value, type(e).__name__)
        n = (u.cmd_regs[2] + 1) & 0xFFFF
        u.cmd_regs = [code, result, n]
        return ok


def _networks(items) -> tuple:
    """``allowed_clients`` entries as networks (an address is a /32 or /128); entries that are
    neither are ignored here (``hookwatch check`` reports them)."""
    out = []
    for a in items:
        try:
            out.append(ipaddress.ip_network(str(a).strip(), strict=False))
        except ValueError:
            log.error("modbus_tcp.writes.allowed_clients: %r is not an address or network; ignored", a)
    return tuple(out)
