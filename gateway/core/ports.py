"""The contracts between a station and the parts plugged into it, in code.

- :class:`MeterPort` — a tension meter (``drivers/meter/driver.py`` is one); ``read()`` gives one
  :class:`MeterReading` per slot, or ``None`` (the slot is MISSING).
- :class:`Stm32Port` — a take-up motor controller (``drivers/stm32/driver.py``); replies are a
  :class:`Stm32Status`; one that can also say when the drive stopped on its own is a
  :class:`Stm32DriveStops` (a :class:`DriveStop`, with the sentence every door says it in).
- :class:`Output` — anything fed by the slot loop (recorder, MQTT, Modbus TCP, console). Called on
  the station's loop; each call must be O(1) and never block (an output that runs on another
  thread hands over through :class:`gateway.plumbing.threadloop.Mailbox`).
- :class:`CommandSink` — what a command source calls (a station's ``submit``);
  :class:`CommandSource` — a door commands come in by (MQTT, PLC), bound to a sink.
- :class:`StationLimits` — what commands are checked against, built once from the station's
  configuration (``StationLimits.from_config``); ``gateway.station.command_desk.validate`` uses it.
- :class:`StationView` — what an output may read of its station and call on it (a
  ``gateway.station.station.Station`` in the station's process, a
  ``gateway.supervisor.remote.RemoteStation`` in a fleet's supervisor).
- :class:`Runtime` — what ``hookwatch run``'s one main loop drives: the stations of this process
  (``gateway.station.fleet.Fleet``) or a worker process per station
  (``gateway.supervisor.supervisor.Supervisor``).

This module is pure (no I/O, no asyncio objects created) and is checked with ``mypy --strict``.
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, Protocol, runtime_checkable

from .records import AlarmRecord, Command, CommandReply, Event, RefusalData, SlotRecord, StationState

#: longest sample ID (also the size of the PLC's sample ID registers: 16 registers × 2 chars)
SAMPLE_ID_MAX = 32
#: longest planned test duration a command may ask for, s (30 days)
T_END_MAX_S = 30 * 24 * 3600
#: T_sat = sat_ratio · full_scale when the method section does not set sat_ratio
DEFAULT_SAT_RATIO = 0.98
DEFAULT_FULL_SCALE = 5.0
DEFAULT_GRADES: tuple[str, ...] = ("I", "II")


# ----------------------------------------------------------------------------- southbound
@dataclass(frozen=True, slots=True)
class MeterReading:
    """One poll of the meter: both channels, N, and the request → reply time."""
    ch1: float
    ch2: float
    rtt_s: float


@runtime_checkable
class Stm32Status(Protocol):
    """What the STM32 reports (``drivers.stm32.protocol.Status``, a frozen dataclass, is one):
    read-only to its users."""
    @property
    def actual_rpm(self) -> float: ...
    @property
    def command_rpm(self) -> float: ...
    @property
    def enabled(self) -> bool: ...


class MeterPort(Protocol):
    """A tension meter. ``read`` never raises: a lost port is ``connected = False`` and None."""
    connected: bool
    counters: dict[str, int]

    async def open(self) -> None: ...
    async def read(self) -> MeterReading | None: ...
    async def close(self) -> None: ...


@runtime_checkable
class MeterDiagnosis(Protocol):
    """A meter port that can say why its reads give no reading (``drivers/meter/driver.py``): one sentence
    naming the port and its settings. ``diagnosis``: the latest read's (None after a good one);
    ``failure_text``: the latest failed read's. The station says it in its once-a-second link
    check (a counted line) when reads fail."""

    def diagnosis(self) -> str | None: ...
    def failure_text(self) -> str | None: ...


class Stm32Port(Protocol):
    """The take-up motor controller. Calls never raise; None when there was no valid reply."""
    connected: bool
    counters: dict[str, int]

    async def open(self) -> None: ...
    async def enable(self) -> Stm32Status | None: ...
    async def set_speed(self, rpm: float) -> Stm32Status | None: ...
    async def stop(self, reason: str = "") -> Stm32Status | None: ...
    async def read_status(self) -> Stm32Status | None: ...
    async def close(self) -> None: ...


@runtime_checkable
class Stm32PostingPort(Protocol):
    """An STM32 port that can also post the per-slot speed command without waiting for its reply
    (``drivers/stm32/driver.py``): ``post_speed`` writes it now and never blocks (False: not sent);
    ``collect`` gives the reply's status later without waiting (None: none came, counted by the
    port). The station uses it when its STM32 port has it, otherwise awaited ``set_speed``."""

    def post_speed(self, rpm: float) -> bool: ...
    def collect(self) -> Stm32Status | None: ...


#: the STM32's own stop reasons (docs/protocols/stm32.md) and how the sentence names each
DRIVE_STOP_WORDS = {"WATCHDOG": "STM32 watchdog", "STALL": "STM32 stall trip: the take-up was blocked",
                    "OVERSPEED": "STM32 overspeed trip"}


@dataclass(frozen=True, slots=True)
class DriveStop:
    """The STM32 stopped the drive on its own while it ran (its watchdog, a stall or overspeed
    trip; docs/protocols/stm32.md), as its link saw it: the firmware's stop ``reason`` (the
    ``StopReason`` name), its ``flags``, its watchdog period and ``silence_s``, the longest time
    between two frames the gateway sent since the drive was enabled — measured by the link on
    its own clock, not guessed (None: not measured). The keep-alive promises a frame every half
    watchdog period at the latest, so a longer silence is the gateway's stall."""
    reason: str
    flags: str
    watchdog_s: float
    silence_s: float | None

    @property
    def gateway_stalled(self) -> bool:
        """The gateway itself fell silent for longer than its keep-alive allows (half the
        watchdog period): its process stalled (a frozen process, a starved CPU, a blocked loop)."""
        return self.silence_s is not None and self.silence_s > self.watchdog_s / 2.0

    def words(self) -> str:
        """The one sentence every door says it with (the event, the log, the console,
        result.json): ``the drive stopped on its own (STM32 watchdog, 1.5 s without the gateway):
        the gateway stalled 2512 ms``."""
        what = DRIVE_STOP_WORDS.get(self.reason, f"STM32 stop reason {self.reason}")
        if self.reason != "WATCHDOG":
            return f"the drive stopped on its own ({what})"
        head = f"the drive stopped on its own ({what}, {self.watchdog_s:g} s without the gateway)"
        if self.silence_s is None:
            return head
        ms = round(self.silence_s * 1000.0)
        if self.gateway_stalled:
            return f"{head}: the gateway stalled {ms} ms"
        return (f"{head}: the gateway's frames were at most {ms} ms apart, so they did not reach "
                "the STM32 (the serial line or its adapter)")

    def as_data(self) -> dict[str, Any]:
        """What the ``drive_stopped`` event and result.json carry."""
        return {"reason": self.reason, "flags": self.flags, "watchdog_s": self.watchdog_s,
                "silence_ms": None if self.silence_s is None else round(self.silence_s * 1000.0),
                "gateway_stalled": self.gateway_stalled, "why": self.words()}


@runtime_checkable
class Stm32DriveStops(Protocol):
    """An STM32 port that says when the drive stopped on its own (``drivers/stm32/driver.py``):
    ``take_drive_stop`` gives the newest such stop not taken yet, once (None: none)."""

    def take_drive_stop(self) -> DriveStop | None: ...


# ----------------------------------------------------------------------------- outputs
class Output(Protocol):
    """Fed by the slot loop, on the station's loop. ``on_*`` are O(1) and never block; an
    exception is caught and counted by the station (an output never stops the station)."""

    async def start(self) -> None: ...
    def on_record(self, rec: SlotRecord) -> None: ...
    def on_event(self, ev: Event) -> None: ...
    def on_state(self, st: StationState) -> None: ...
    async def stop(self) -> None: ...


# ----------------------------------------------------------------------------- commands
class CommandSink(Protocol):
    """Where every door's commands go (MQTT, Sparkplug, the console, the PLC, the CLI and the
    supervisor's channel): a station's command desk (one at a time, a repeated request_id once,
    one validation, a rate per source, one set of bounded events) or a worker's proxy.
    ``submit`` a command the intake made; ``refused`` a request the intake refused (``command``,
    ``source``, ``reason``, ``code``), counted in the sink's ``command_rejected`` events.
    Both on the sink's own loop (from another thread: ``submit_to``/``call_soon_on``)."""

    async def submit(self, cmd: Command) -> CommandReply: ...
    def refused(self, data: RefusalData) -> None: ...


class CommandSource(Protocol):
    """A door for commands (MQTT ``cmd/…`` topics, PLC holding registers). It builds
    :class:`Command` objects with its ``source`` name and hands them to its sink."""
    source: str

    def bind(self, sink: CommandSink) -> None: ...


@dataclass(frozen=True, slots=True)
class StationLimits:
    """What a command may ask of one station (built once, from its configuration)."""
    full_scale: float = DEFAULT_FULL_SCALE       # N, the meter's full scale (method.full_scale)
    sat_ratio: float = DEFAULT_SAT_RATIO         # method.sat_ratio: T_sat = sat_ratio · full_scale
    grades: tuple[str, ...] = DEFAULT_GRADES
    sample_id_max: int = SAMPLE_ID_MAX
    t_end_max_s: int = T_END_MAX_S
    t_end_default_s: float = 36000.0             # test.t_end_s: a start without t_end

    @property
    def t_set_range(self) -> tuple[float, float]:
        """Open interval of allowed setpoints, N: (0, T_sat)."""
        return 0.0, self.sat_ratio * self.full_scale

    @classmethod
    def from_values(cls, method: dict[str, Any], grades: tuple[str, ...] = DEFAULT_GRADES,
                    t_end_default_s: float = 36000.0) -> StationLimits:
        """From the method values (``full_scale``, ``sat_ratio``; defaults for missing ones)."""
        fs = method.get("full_scale")
        sr = method.get("sat_ratio")
        return cls(full_scale=DEFAULT_FULL_SCALE if fs is None else float(fs),
                   sat_ratio=DEFAULT_SAT_RATIO if sr is None else float(sr),
                   grades=tuple(grades), t_end_default_s=float(t_end_default_s))


# ----------------------------------------------------------------------------- what outputs see
class AlarmExpiries(Protocol):
    """The part of a station's alarm store an output reads: when a shelving runs out."""

    def shelved_until(self, name: str) -> float | None: ...


class PlanView(Protocol):
    """A test plan as outputs read it (``gateway.station.session.TestPlan``)."""

    @property
    def sample_id(self) -> str: ...
    @property
    def grade(self) -> str | None: ...
    @property
    def t_set(self) -> float: ...
    @property
    def t_end(self) -> float: ...


class StationView(CommandSink, Protocol):
    """What an output may read of its station and call on it, and nothing more: the station in
    its own process and its proxy in a fleet's supervisor both are one. Reads are of the
    station's own loop (an output on another thread reads ``state``, a copy, or hands over)."""

    @property
    def id(self) -> str: ...
    @property
    def ts(self) -> float: ...
    @property
    def limits(self) -> StationLimits: ...
    @property
    def default_plan(self) -> PlanView | None: ...
    @property
    def state(self) -> StationState: ...
    @property
    def alarms(self) -> AlarmExpiries: ...
    @property
    def outputs(self) -> Sequence[Output]: ...


class AlarmStoreView(AlarmExpiries, Protocol):
    """A station's persisted alarm store (``gateway.station.alarm_store.AlarmStore``) as the MQTT
    output publishes from it: the end-of-life alarm and the wear warning as they stand."""

    @property
    def record(self) -> AlarmRecord: ...
    @property
    def warning(self) -> AlarmRecord: ...


class PortLink(Protocol):
    """A southbound port's health as the metrics read it (a :class:`MeterPort`, a
    :class:`Stm32Port`): whether it is connected, and its counters."""

    @property
    def connected(self) -> bool: ...
    @property
    def counters(self) -> dict[str, int]: ...


#: a JSON object (an event's data, a disk's details): what outputs report back with
JsonObject = dict[str, object]


class StationLinks(StationView, Protocol):
    """A station in this process as its own outputs see it: its view plus what they report
    back on the station's loop (their uplink, their disk), its alarm store itself, which the
    MQTT output publishes from, and its southbound ports' health, which the metrics report."""

    @property
    def alarms(self) -> AlarmStoreView: ...
    @property
    def meter(self) -> PortLink: ...
    @property
    def stm32(self) -> PortLink: ...

    def set_uplink(self, name: str, ok: bool) -> None: ...
    def set_disk(self, store: str, ok: bool, info: JsonObject | None = None) -> None: ...
    def site_lives(self, tests: tuple[object, ...]) -> None:
        """The other stations' lives of the site (``gateway.core.method.prior.PastTest``), as the
        MQTT output last received them (METHOD.md §7a)."""


@runtime_checkable
class WorkerHooks(Protocol):
    """The hooks an output may take besides :class:`Output`'s, from a fleet's supervisor (its
    station proxy, ``gateway.supervisor.remote.RemoteStation``): the station's worker process
    came up or went down (``on_worker``), ``n`` slot records were lost before they reached the
    output (``on_lost``), the worker's metrics snapshot (``on_metrics``). The fan-out calls them
    on the outputs that are one (``Fanout.worker``/``lost``/``metrics``)."""

    def on_worker(self, up: bool, restarts: int = 0) -> None: ...
    def on_lost(self, n: int) -> None: ...
    def on_metrics(self, snap: JsonObject) -> None: ...


# ----------------------------------------------------------------------------- the runtime
class Runtime(Protocol):
    """What ``hookwatch run`` drives in its one main loop, as gunicorn's arbiter drives its
    workers: ``start`` once, ``tick`` every 0.2 s (restarts, watchdogs, the test bookkeeping),
    ``healthy`` for systemd's watchdog, ``reload`` on SIGHUP, ``stop`` once; ``report`` gives
    each station's figures, results and failed starts at the end."""

    def start(self) -> object: ...
    def tick(self, now: float) -> None: ...
    def alive(self) -> bool: ...
    def ready(self) -> bool: ...
    def healthy(self) -> bool: ...
    def status(self) -> str: ...
    def tests_done(self) -> bool: ...
    def reload(self) -> None: ...
    def stop(self) -> None: ...
    def report(self) -> dict[str, dict[str, Any] | None]: ...
