"""One virtual station in one process: the plant stepped in real time on the monotonic clock, a
virtual ZN-S meter sampling its tensions, a virtual STM32 driving its take-up motor, and the
scenario's fault timeline. Used by `hookwatch sim` (gateway/cli/sim.py).

Clock: plant time = ``time.monotonic() − t0`` (t0 = start of the station). The meter samples the
plant at the moment a request completes on the simulated wire, the STM32 commands it at the moment
a command frame completes; before either, the plant is advanced to that moment, so readings and
commands land on the right internal step. A background task advances it every 10 ms as well (trace,
wear onset event, truth file).
"""
from __future__ import annotations

import asyncio
import csv
import json
import logging
import math
import os
import re
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, TextIO

from .meter import VirtualMeter
from .plant import Plant
from .scenario import DEFAULT_SCENARIO, FaultSpec, Scenario, ScenarioError, load_scenario
from .twin_stm32 import Stm32Firmware, VirtualStm32

log = logging.getLogger("hookwatch.sim")

TICK_S = 0.01
#: the virtual STM32's firmware tick (watchdog, trips, idle-gap framing): 10 ms is 1/20 of the
#: shortest watchdog of the shipped scenarios and halves the simulator's wake-ups per station
STM32_TICK_S = 0.01


class LiveMotor:
    """The plant's motor as the virtual STM32 sees it: every access first brings the plant up to
    the current time, so a command takes effect at the step it was given."""

    def __init__(self, plant: Plant, now: Callable[[], float]):
        self.plant = plant
        self.now = now

    def _sync(self) -> None:
        self.plant.advance_to(self.now())

    def set_command(self, rpm: float) -> None:
        self._sync()
        self.plant.set_command(rpm)

    def enable(self, on: bool) -> None:
        self._sync()
        self.plant.enable(on)

    @property
    def speed_rpm(self) -> float:
        self._sync()
        return self.plant.speed_rpm

    @property
    def stalled(self) -> bool:
        return self.plant.stalled

    @property
    def enabled(self) -> bool:
        return self.plant.enabled

    @property
    def command_rpm(self) -> float:
        return self.plant.command_rpm


class EventLog:
    """JSON lines, one per event, flushed at once (``t`` = sim time in s)."""

    def __init__(self, stream: TextIO, close: bool):
        self.stream = stream
        self._close = close

    def write(self, t: float, event: str, **kw: Any) -> None:
        rec = {"t": round(t, 4), "event": event, **kw}
        try:
            self.stream.write(json.dumps(rec, default=str) + "\n")
            self.stream.flush()
        except (OSError, ValueError):
            pass

    def close(self) -> None:
        if self._close:
            try:
                self.stream.close()
            except OSError:
                pass


def _atomic_json(path: str, data: dict) -> None:
    tmp = f"{path}.tmp{os.getpid()}"
    with open(tmp, "w") as f:
        json.dump(data, f, indent=1, default=str)
        f.write("\n")
    os.replace(tmp, path)


class SimStation:
    def __init__(self, scenario: Scenario, *, link_dir: str, seed: int | None = None,
                 baud: int | None = None, truth_path: str | None = None,
                 trace_path: str | None = None, events: EventLog | None = None,
                 clock: Callable[[], float] = time.monotonic, name: str | None = None):
        self.scenario = scenario
        self.name = name                  # set when one process hosts several stations
        self.seed = scenario.seed if seed is None else int(seed)
        self.link_dir = link_dir
        self.meter_map = scenario.load_meter_map(baud)
        self.truth_path = truth_path
        self.trace_path = trace_path
        self.events = events
        self.clock = clock
        self.plant = Plant(scenario.plant, seed=self.seed)
        self.t0: float | None = None
        self.meter: Any = None      # VirtualMeter, made by start()
        self.stm32: Any = None      # VirtualStm32, made by start()
        self.active: dict[str, FaultSpec] = {}
        self.fired: list[dict] = []
        self._tasks: list[asyncio.Task] = []
        self._trace_f: Any = None
        self._trace_w: Any = None
        self._last_trace_flush = 0.0
        self._seen_first_run = False
        self._seen_onset = False

    # ------------------------------------------------------------------ time
    def now(self) -> float:
        """Sim time, s since start."""
        return self.clock() - (self.t0 if self.t0 is not None else self.clock())

    def _source(self) -> tuple[float, float]:
        self.plant.advance_to(self.now())
        return self.plant.tensions()

    # ------------------------------------------------------------------ lifecycle
    async def start(self, shared_tick: bool = False) -> None:
        """Start the devices and the background tasks. ``shared_tick``: no tasks of its own for
        the plant stepping and the STM32 firmware tick; the caller calls :meth:`tick` every
        ``TICK_S`` (run_fleet: one task for all stations, not 2 wake-ups per station)."""

        os.makedirs(self.link_dir, exist_ok=True)
        if self.trace_path:
            self._trace_f = open(self.trace_path, "w", newline="")
            self._trace_w = csv.writer(self._trace_f)
            self._trace_w.writerow(Plant.TRACE_COLUMNS)
            self.plant.trace_enabled = True
        self.t0 = self.clock()
        self.meter = VirtualMeter(self.meter_map, self._source, os.path.join(self.link_dir, "meter"))
        self.meter.adapter.echo = self.scenario.echo
        self.meter.adapter.latency_s = self.scenario.latency_timer_ms / 1000.0
        self.stm32 = VirtualStm32(Stm32Firmware(self.scenario.watchdog_s),
                                  LiveMotor(self.plant, self.now),
                                  os.path.join(self.link_dir, "stm32"),
                                  baud=self.scenario.stm32_baud, tick_s=STM32_TICK_S,
                                  on_drive=lambda rec: self._event("drive", **rec))
        await self.meter.start()
        await self.stm32.start(own_ticker=not shared_tick)
        self._write_truth()
        self._event("start", meter=self.meter.device, stm32=self.stm32.device,
                     link_dir=self.link_dir, seed=self.seed, scenario=self.scenario.path,
                     baud=self.meter_map.baud, t0_monotonic=self.t0)
        loop = asyncio.get_running_loop()
        if not shared_tick:
            self._tasks.append(loop.create_task(self._stepper()))
        if self.scenario.faults:
            self._tasks.append(loop.create_task(self._timeline()))

    async def stop(self) -> None:
        for t in self._tasks:
            t.cancel()
        for t in self._tasks:
            try:
                await t
            except asyncio.CancelledError:
                pass
            except Exception:                       # noqa: BLE001 — already logged by the task
                log.exception("sim task failed")
        self._tasks.clear()
        if self.t0 is not None:
            self.plant.advance_to(self.now())
            self._flush_trace(force=True)
        for name in list(self.active):
            self._clear(self.active[name], reason="stop")
        if self.stm32 is not None:
            await self.stm32.stop()
        if self.meter is not None:
            await self.meter.stop()
        if self._trace_f is not None:
            self._trace_f.close()
            self._trace_f = None
        if self.t0 is not None:
            self._event("stop", counters={"meter": dict(self.meter.counters) if self.meter else {},
                                          "stm32": dict(self.stm32.counters) if self.stm32 else {}},
                        meter_reply_lateness_ms=self.meter.lateness_summary_ms() if self.meter else {})
            self._write_truth()

    # ------------------------------------------------------------------ background
    async def _stepper(self) -> None:
        while True:
            self._step()
            await asyncio.sleep(TICK_S)

    def tick(self) -> None:
        """The shared-tick form of the background work (see :meth:`start`)."""
        self._step()
        if self.stm32 is not None:
            self.stm32.tick()

    def _step(self) -> None:
        self.plant.advance_to(self.now())
        p = self.plant
        if not self._seen_first_run and p.first_run_t is not None:
            self._seen_first_run = True
            self._event("yarn_running", at=p.first_run_t)
            self._write_truth()
        if not self._seen_onset and p.onset_t is not None:
            self._seen_onset = True
            self._event("wear_onset", at=p.onset_t, wear_s=p.profile.onset_s)
            self._write_truth()
        self._flush_trace()

    def _flush_trace(self, force: bool = False) -> None:
        if self._trace_w is None:
            return
        rows = self.plant.drain_trace()
        if rows:
            self._trace_w.writerows(rows)
        now = self.clock()
        if force or now - self._last_trace_flush > 1.0:
            self._last_trace_flush = now
            try:
                self._trace_f.flush()
            except OSError:
                pass

    async def _timeline(self) -> None:
        """Fire and clear the scenario's faults at their sim times."""
        actions: list[tuple[float, int, FaultSpec]] = []
        for f in self.scenario.faults:
            actions.append((f.at_s, 1, f))
            if f.duration_s is not None:
                actions.append((f.end_s, 0, f))
        actions.sort(key=lambda a: (a[0], a[1]))      # a clear before a fire at the same time
        for when, on, f in actions:
            delay = when - self.now()
            if delay > 0:
                await asyncio.sleep(delay)
            if on:
                self._fire(f)
            else:
                self._clear(f)

    # ------------------------------------------------------------------ faults
    def _set(self, f: FaultSpec, on: bool) -> dict[str, Any]:
        """Apply (on) or undo a fault; returns details for the event log."""
        self.plant.advance_to(self.now())
        kind = f.fault
        info: dict[str, Any] = {}
        if kind == "meter_drop":
            self.meter.faults.drop_replies = on
        elif kind == "meter_bad_crc":
            self.meter.faults.corrupt_crc = on
        elif kind == "meter_late":
            self.meter.faults.extra_delay_s = (f.delay_ms or 0.0) / 1000.0 if on else 0.0
            info["delay_ms"] = f.delay_ms
        elif kind == "meter_port_vanish":
            if on:
                self.meter.vanish()
            else:
                info["device"] = self.meter.restore()
        elif kind == "stm32_port_vanish":
            if on:
                self.stm32.vanish()
            else:
                info["device"] = self.stm32.restore()
        elif kind == "stm32_silent":
            self.stm32.faults.silent = on
        elif kind == "yarn_break":
            self.plant.faults.yarn_break = on
        elif kind == "saturation":
            self.plant.faults.saturate = on
        elif kind == "swap_channels":
            self.plant.faults.swap_channels = on
        elif kind == "motor_stall":
            self.plant.faults.stall = on
        else:                                   # the loader only lets known kinds through
            raise ValueError(f"unknown fault {kind!r}")
        return info

    def _fire(self, f: FaultSpec) -> None:
        info = self._set(f, True)
        self.active[f.fault] = f
        rec = {"fault": f.fault, "at_s": f.at_s, "duration_s": f.duration_s, **info}
        self.fired.append(rec)
        self._event("fault_on", **rec)

    def _clear(self, f: FaultSpec, reason: str = "scheduled") -> None:
        if self.active.get(f.fault) is not f:
            return
        info = self._set(f, False)
        del self.active[f.fault]
        self._event("fault_off", fault=f.fault, at_s=f.at_s, reason=reason, **info)

    # ------------------------------------------------------------------ output
    def _event(self, event: str, **kw: Any) -> None:
        if self.events is not None:
            if self.name is not None:
                kw = {"station": self.name, **kw}
            self.events.write(self.now(), event, **kw)

    def truth(self) -> dict[str, Any]:
        d = self.plant.truth()
        d.update({"scenario": self.scenario.path, "seed": self.seed, "t0_monotonic": self.t0,
                  "faults": [f.as_dict() for f in self.scenario.faults],
                  "meter_baud": self.meter_map.baud})
        return {k: (None if isinstance(v, float) and not math.isfinite(v) else v) for k, v in d.items()}

    def _write_truth(self) -> None:
        if not self.truth_path:
            return
        try:
            _atomic_json(self.truth_path, self.truth())
        except OSError as e:
            log.warning("truth file %s: %s", self.truth_path, e.strerror)


async def run_station(station: SimStation, stop: asyncio.Event, duration_s: float | None,
                      on_ready: Callable[[SimStation], None] | None = None) -> None:
    """Start, call on_ready, run until ``stop`` is set or ``duration_s`` passed, stop."""
    await run_fleet([station], stop, duration_s,
                    (lambda sts: on_ready(sts[0])) if on_ready is not None else None)


async def run_fleet(stations: list[SimStation], stop: asyncio.Event, duration_s: float | None,
                    on_ready: Callable[[list[SimStation]], None] | None = None) -> None:
    """Several virtual stations on one event loop (one process): start them all, call on_ready,
    run until ``stop`` is set or ``duration_s`` passed, stop them all (also after a failed start).
    The meters share one reply-writer thread (drivers/sim/meter.py)."""
    started: list[SimStation] = []
    shared = len(stations) > 1
    ticker = None
    try:
        for st in stations:
            await st.start(shared_tick=shared)
            started.append(st)
        if shared:
            ticker = asyncio.get_running_loop().create_task(_tick_all(stations))
        if on_ready is not None:
            on_ready(stations)
        if duration_s is not None:
            try:
                await asyncio.wait_for(stop.wait(), timeout=duration_s)
            except TimeoutError:
                pass
        else:
            await stop.wait()
    finally:
        if ticker is not None:
            ticker.cancel()
            try:
                await ticker
            except asyncio.CancelledError:
                pass
        for st in reversed(started):
            await st.stop()


async def _tick_all(stations: list[SimStation]) -> None:
    """One task ticks every station of a fleet each TICK_S (plant stepping, STM32 firmware)."""
    loop = asyncio.get_running_loop()
    t = loop.time()
    while True:
        t += TICK_S
        await asyncio.sleep(max(0.0, t - loop.time()))
        for st in stations:
            try:
                st.tick()
            except Exception:                       # noqa: BLE001 — one station, not the fleet
                log.exception("sim station %s: tick failed", st.name)
        if loop.time() - t > 10 * TICK_S:
            t = loop.time()                         # fell far behind (host stalled): no burst


# ---------------------------------------------------------------------------------- fleets
@dataclass(frozen=True)
class FleetEntry:
    """One virtual station of a fleet file (or of ``--count N``)."""
    name: str
    scenario: Scenario
    seed: int | None = None
    baud: int | None = None


MAX_FLEET = 64
_NAME_RE = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,63}$")


def is_fleet_file(data: Any) -> bool:
    return isinstance(data, dict) and "stations" in data


def fleet_from_dict(data: dict, path: str) -> list[FleetEntry]:
    """A fleet file: ``stations:`` a list of ``{name, scenario, seed, baud}`` (scenario relative to
    the file; default the packaged demo). Errors name the file, the entry and the key."""
    unknown = sorted(set(data) - {"stations", "description"})
    if unknown:
        raise ScenarioError(f"{path}: {unknown[0]}: unknown key; allowed: stations, description")
    items = data["stations"]
    if not isinstance(items, list) or not items:
        raise ScenarioError(f"{path}: stations: expected a list of 1 to {MAX_FLEET} stations")
    if len(items) > MAX_FLEET:
        raise ScenarioError(f"{path}: stations: {len(items)} stations; allowed: at most {MAX_FLEET}")
    base = os.path.dirname(os.path.abspath(path))
    out: list[FleetEntry] = []
    seen: set[str] = set()
    for i, it in enumerate(items):
        where = f"{path}: stations[{i}]"
        if not isinstance(it, dict):
            raise ScenarioError(f"{where}: expected a mapping with name, scenario, seed, baud")
        bad = sorted(set(it) - {"name", "scenario", "seed", "baud"})
        if bad:
            raise ScenarioError(f"{where}: {bad[0]}: unknown key; allowed: name, scenario, seed, baud")
        name = it.get("name", f"sim{i + 1:02d}")
        if not isinstance(name, str) or not _NAME_RE.match(name):
            raise ScenarioError(f"{where}: name: {name!r} is not allowed; allowed: letters, digits, "
                                f"_ . - (a folder name, at most 64 characters)")
        if name in seen:
            raise ScenarioError(f"{where}: name: {name!r} is used twice")
        seen.add(name)
        sp = it.get("scenario")
        if sp is None:
            sp = DEFAULT_SCENARIO
        elif not isinstance(sp, str) or not sp:
            raise ScenarioError(f"{where}: scenario: {sp!r} is not allowed; allowed: a path")
        elif not os.path.isabs(sp):
            sp = os.path.normpath(os.path.join(base, sp))
        for key in ("seed", "baud"):
            v = it.get(key)
            if v is not None and (isinstance(v, bool) or not isinstance(v, int) or v < 0):
                raise ScenarioError(f"{where}: {key}: {v!r} is not allowed; allowed: an integer ≥ 0")
        sc = load_scenario(sp)
        if it.get("baud") is not None:
            sc.load_meter_map(it["baud"])        # checks the override
        out.append(FleetEntry(name, sc, it.get("seed"), it.get("baud")))
    return out


def fleet_of_count(scenario: Scenario, count: int, seed: int | None = None) -> list[FleetEntry]:
    """``--count N``: N copies of one scenario named sim01…simNN, seeds seed, seed+1, … (so the
    first station is the one a single-station run with that seed gives)."""
    s0 = scenario.seed if seed is None else seed
    return [FleetEntry(f"sim{i + 1:02d}", scenario, s0 + i) for i in range(count)]
