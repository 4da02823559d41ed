"""Scenario files for `hookwatch sim`: one virtual station (plant, meter, STM32) and a fault
timeline. Format and every key: docs/simulator.md. Loading validates everything and rejects
unknown keys; a :class:`ScenarioError` names the file, the key, the bad value and what is allowed.

Example::

    seed: 1
    meter: {map: ../meters/zn-s.yaml, baud: null}
    stm32: {watchdog_s: 0.2}
    plant: {grade: I, t_set: 0.5, time_scale: 150}
    method: {w_ss: 10, w_hold: 60, tau: 10}      # informational: what a station should run
    faults:
      - {at_s: 30, duration_s: 2, fault: meter_drop}
      - {at_s: 40, duration_s: 1, fault: meter_late, delay_ms: 40}
"""
from __future__ import annotations

import math
import os
from dataclasses import dataclass, field, fields, replace
from typing import Any

import gateway.plumbing.safeyaml as safeyaml

# the scenario's method and control sections are checked by gateway's pure core (the layer under
# the drivers: numbers in, numbers out, no I/O)
from gateway.core.control import ControlParams, NotchParams
from gateway.core.method.params import ParamError, build_params
from gateway.core.validation import Problem, ValidationError, did_you_mean, suggestion_text

from ..meter.meter_map import BAUDS, DEFAULT_MAP_PATH, MapError, load_map
from ..stm32.protocol import WATCHDOG_MS_MAX, WATCHDOG_MS_MIN
from .plant import GRADES, SECTIONS, PlantParams, params_from_dict

#: fault kind -> (extra keys allowed, extra keys required)
FAULT_KINDS: dict[str, tuple[tuple[str, ...], tuple[str, ...]]] = {
    "meter_drop": ((), ()),              # the meter receives requests and never answers
    "meter_bad_crc": ((), ()),           # replies go out with a wrong CRC
    "meter_late": (("delay_ms",), ("delay_ms",)),   # replies come delay_ms late
    "meter_port_vanish": ((), ()),       # the meter's device disappears, returns after duration
    "yarn_break": ((), ()),              # the yarn breaks: tension → 0 (rethreaded after duration)
    "saturation": ((), ()),              # both readings at full scale
    "swap_channels": ((), ()),           # ch1 and ch2 swapped on the wire
    "stm32_silent": ((), ()),            # the STM32 stops answering (keeps its watchdog)
    "stm32_port_vanish": ((), ()),       # the STM32's device disappears, returns after duration
    "motor_stall": ((), ()),             # the take-up motor stalls: speed → 0
}
FAULT_KEYS = ("at_s", "duration_s", "fault", "note")
TOP_KEYS = ("description", "seed", "duration_s", "meter", "stm32", "plant", "method", "control",
            "faults")
METER_KEYS = ("map", "baud", "unit_id", "echo", "latency_timer_ms")
STM32_KEYS = ("watchdog_s", "baud")
PLANT_TOP = ("grade", "t_set", "time_scale", "step_s", "theta_deg", "trace_every_s", "threaded")

#: (section, key) -> (lower bound, lower inclusive, upper bound or None); default for numbers: ≥ 0
BOUNDS: dict[tuple[str, str], tuple[float, bool, float | None]] = {
    ("", "t_set"): (0.0, False, 4.9),
    ("", "time_scale"): (0.0, False, None),
    ("", "step_s"): (0.0, False, 0.01),
    ("", "theta_deg"): (0.0, False, 360.0),
    ("", "trace_every_s"): (0.0, False, None),
    ("motor", "tau_s"): (0.0, True, None),
    ("motor", "accel_rpm_s"): (0.0, False, None),
    ("motor", "max_rpm"): (0.0, False, None),
    ("motor", "stall_decel_rpm_s"): (0.0, False, None),
    ("tension", "gain_n_per_rpm"): (0.0, False, None),
    ("tension", "mu_tension_coeff"): (-1.0, True, 1.0),
    ("tension", "dead_time_s"): (0.0, True, 2.0),
    ("drift", "sine_period_s"): (0.0, False, None),
    ("drift", "sine_amp"): (0.0, True, 0.5),
    ("drift", "walk_sigma"): (0.0, True, 0.5),
    ("ripple", "amplitude"): (0.0, True, 0.5),
    ("ripple", "ratio_i"): (0.0, False, None),
    ("ripple", "harmonic_h"): (1.0, True, None),
    ("sensor", "resolution_n"): (0.0, True, 1.0),
    ("sensor", "full_scale_n"): (0.0, False, None),
    ("sensor", "gain_ch1"): (0.0, False, 10.0),
    ("sensor", "gain_ch2"): (0.0, False, 10.0),
    ("sensor", "offset_ch1"): (-1.0, True, 1.0),
    ("sensor", "offset_ch2"): (-1.0, True, 1.0),
    ("tension", "slack_s"): (0.0, True, 600.0),
    ("wear", "mu_ss"): (0.0, False, 0.78),
    ("wear", "onset_s"): (0.0, False, None),
    ("wear", "run_in_tau_s"): (0.0, False, None),
    ("wear", "rise_a"): (0.0, False, None),
    ("wear", "rise_tau_s"): (0.0, False, None),
    ("wear", "rise_cap"): (0.3, False, 1.2),
}
INT_KEYS = {("ripple", "harmonic_h")}
NULLABLE = {("wear", "mu_ss"), ("wear", "onset_s")}

DEFAULT_SCENARIO = os.path.join(os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))),
                                "config", "scenarios", "demo.yaml")


class ScenarioError(ValidationError):
    """A scenario file that cannot be used; the message names file, key, value and what is
    allowed, and ``problem`` holds the same as data (file, key path, value, allowed)."""

    def __init__(self, text: str, problem: Problem | None = None):
        super().__init__(problem or Problem((), text), text=text)


@dataclass(frozen=True)
class FaultSpec:
    at_s: float
    duration_s: float | None        # None: until the end of the run
    fault: str
    delay_ms: float | None = None   # meter_late
    note: str | None = None

    @property
    def end_s(self) -> float:
        return math.inf if self.duration_s is None else self.at_s + self.duration_s

    def as_dict(self) -> dict[str, Any]:
        d = {"at_s": self.at_s, "duration_s": self.duration_s, "fault": self.fault}
        if self.delay_ms is not None:
            d["delay_ms"] = self.delay_ms
        return d


@dataclass(frozen=True)
class Scenario:
    path: str
    seed: int = 1
    description: str = ""
    duration_s: float | None = None
    meter_map: str | None = None        # path of the register map (None: the packaged default)
    baud: int | None = None
    unit_id: int | None = None
    echo: bool = False                  # the adapter hands our own request back (2-wire bus)
    latency_timer_ms: float = 0.0       # the adapter's latency timer (FTDI default 16; 0: a UART)
    watchdog_s: float = 0.2
    stm32_baud: int = 115200
    plant: PlantParams = field(default_factory=PlantParams)
    faults: tuple[FaultSpec, ...] = ()
    method: dict[str, Any] = field(default_factory=dict)    # informational (not used by the sim)
    control: dict[str, Any] = field(default_factory=dict)   # informational (not used by the sim)

    def load_meter_map(self, baud: int | None = None):
        """The meter's register map with this scenario's (or the caller's) overrides."""

        path = self.meter_map or DEFAULT_MAP_PATH
        try:
            m = load_map(path)
            b = baud if baud is not None else self.baud
            if b is not None or self.unit_id is not None:
                m = m.with_overrides(baud=b, unit_id=self.unit_id)
        except MapError as e:
            raise ScenarioError(f"{self.path}: meter.map: {e}",
                                Problem(("meter", "map"), str(e), value=path, file=self.path)) from None
        except OSError as e:
            raise ScenarioError(f"{self.path}: meter.map: {path}: {e.strerror}") from None
        return m


# ----------------------------------------------------------------------------------------------

def _bad(where: str, key: str, value: Any, allowed: str) -> ScenarioError:
    msg = f"{value!r} is not allowed; allowed: {allowed}"
    return ScenarioError(f"{where}: {key}: {msg}", Problem(_path(key), msg, value=value,
                                                           allowed=allowed, file=where))


def _fail(where: str, key: str, msg: str) -> ScenarioError:
    """A problem of ``key`` that is not one bad value (a missing key, a rule between keys)."""
    return ScenarioError(f"{where}: {key}: {msg}", Problem(_path(key), msg, file=where))


def _path(key: str) -> tuple:
    out: list = []
    for part in key.split("."):
        name, _, idx = part.partition("[")
        out.append(name)
        if idx:
            out.append(int(idx.rstrip("]")))
    return tuple(out)


def _mapping(where: str, key: str, v: Any) -> dict:
    if v is None:
        return {}
    if not isinstance(v, dict):
        raise _bad(where, key, v, "a mapping of keys to values")
    return v


def _unknown(where: str, prefix: str, d: dict, allowed) -> None:
    for k in d:
        if k not in allowed:
            sugg = did_you_mean(k, allowed)
            msg = f"unknown key; allowed: {', '.join(allowed)}" + suggestion_text(sugg)
            raise ScenarioError(f"{where}: {prefix}{k}: {msg}",
                                Problem(_path(prefix + str(k)), msg, value=k,
                                        allowed=", ".join(allowed), suggestion=sugg, file=where))


def _number(where: str, key: str, v: Any, lo: float = 0.0, lo_incl: bool = True,
            hi: float | None = None, integer: bool = False, nullable: bool = False) -> Any:
    if v is None and nullable:
        return None
    rng = (f"{'≥' if lo_incl else '>'} {lo:g}" + (f" and ≤ {hi:g}" if hi is not None else ""))
    kind = "an integer" if integer else "a number"
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        raise _bad(where, key, v, f"{kind} {rng}" + (", or null" if nullable else ""))
    if integer and not (isinstance(v, int) or float(v).is_integer()):
        raise _bad(where, key, v, f"{kind} {rng}")
    f = float(v)
    if not math.isfinite(f) or (f < lo if lo_incl else f <= lo) or (hi is not None and f > hi):
        raise _bad(where, key, v, f"{kind} {rng}" + (", or null" if nullable else ""))
    return int(f) if integer else f


def _plant(where: str, d: dict) -> PlantParams:
    allowed = PLANT_TOP + tuple(SECTIONS)
    _unknown(where, "plant.", d, allowed)
    out: dict[str, Any] = {}
    defaults = PlantParams()
    for k, v in d.items():
        key = f"plant.{k}"
        if k == "grade":
            if not isinstance(v, str) or v not in GRADES:
                raise _bad(where, key, v, ", ".join(GRADES))
            out[k] = v
        elif k == "threaded":
            if not isinstance(v, bool):
                raise _bad(where, key, v, "true or false")
            out[k] = v
        elif k in SECTIONS:
            sec = _mapping(where, key, v)
            cls = SECTIONS[k]
            names = tuple(f.name for f in fields(cls))
            _unknown(where, f"plant.{k}.", sec, names)
            kw = {}
            for sk, sv in sec.items():
                lo, incl, hi = BOUNDS.get((k, sk), (0.0, True, None))
                kw[sk] = _number(where, f"plant.{k}.{sk}", sv, lo, incl, hi,
                                 integer=(k, sk) in INT_KEYS, nullable=(k, sk) in NULLABLE)
            out[k] = kw
        else:
            lo, incl, hi = BOUNDS.get(("", k), (0.0, True, None))
            out[k] = _number(where, key, v, lo, incl, hi)
    p = params_from_dict(out)
    if p.sensor.full_scale_n <= p.t_set:
        raise _fail(where, "plant.t_set", f"{p.t_set!r} is not allowed; allowed: below the "
                            f"sensor full scale ({p.sensor.full_scale_n:g} N)")
    if p.trace_every_s < p.step_s:
        raise _bad(where, "plant.trace_every_s", p.trace_every_s, f"≥ plant.step_s ({p.step_s:g})")
    del defaults
    return p


def _faults(where: str, v: Any) -> tuple[FaultSpec, ...]:
    if v is None:
        return ()
    if not isinstance(v, list):
        raise _bad(where, "faults", v, "a list of {at_s, duration_s, fault, ...}")
    out = []
    kinds = ", ".join(FAULT_KINDS)
    for i, item in enumerate(v):
        key = f"faults[{i}]"
        if not isinstance(item, dict):
            raise _bad(where, key, item, "a mapping {at_s, duration_s, fault, ...}")
        kind = item.get("fault")
        if kind not in FAULT_KINDS:
            raise _bad(where, f"{key}.fault", kind, kinds)
        extra_ok, extra_req = FAULT_KINDS[kind]
        _unknown(where, f"{key}.", item, FAULT_KEYS + extra_ok)
        for r in extra_req:
            if r not in item:
                raise _fail(where, f"{key}.{r}", f"missing; fault {kind} needs {', '.join(extra_req)}")
        if "at_s" not in item:
            raise _fail(where, f"{key}.at_s", "missing; the fault's start, s after the sim starts")
        at = _number(where, f"{key}.at_s", item["at_s"])
        dur = _number(where, f"{key}.duration_s", item.get("duration_s"), 0.0, False, nullable=True)
        delay = None
        if "delay_ms" in item:
            delay = _number(where, f"{key}.delay_ms", item["delay_ms"], 0.0, False, 10000.0)
        note = item.get("note")
        if note is not None and not isinstance(note, str):
            raise _bad(where, f"{key}.note", note, "a string")
        out.append(FaultSpec(at, dur, kind, delay, note))
    # the same kind must not overlap itself (clearing one would clear the other)
    for i, a in enumerate(out):
        for j, b in enumerate(out):
            if i < j and a.fault == b.fault and a.at_s < b.end_s and b.at_s < a.end_s:
                raise _fail(where, f"faults[{j}]", f"{b.fault} at {b.at_s:g} s overlaps "
                                    f"faults[{i}] ({a.at_s:g}–{a.end_s:g} s); allowed: one "
                                    f"{b.fault} at a time")
    return tuple(sorted(out, key=lambda f: f.at_s))


def _method(where: str, d: dict, t_set: float) -> dict[str, Any]:

    if "t_set" in d:
        raise _fail(where, "method.t_set", "set the tension in plant.t_set")
    try:
        build_params({**d, "t_set": t_set}, source=f"{where}: method")
    except ParamError as e:
        pr = e.problem
        raise ScenarioError(str(e), replace(pr, path=("method",) + pr.path, file=where,
                                            related=tuple(("method",) + r for r in pr.related))) from None
    return dict(d)


def _control(where: str, d: dict) -> dict[str, Any]:

    names = tuple(f.name for f in fields(ControlParams) if f.name != "ts")
    _unknown(where, "control.", d, names)
    nnames = tuple(f.name for f in fields(NotchParams))
    if "notch" in d:
        _unknown(where, "control.notch.", _mapping(where, "control.notch", d["notch"]), nnames)
    return dict(d)


def scenario_from_dict(data: Any, path: str = "<scenario>") -> Scenario:
    where = path
    if data is None:
        data = {}
    if not isinstance(data, dict):
        raise ScenarioError(f"{where}: the file must be a mapping with keys {', '.join(TOP_KEYS)}")
    _unknown(where, "", data, TOP_KEYS)
    base = os.path.dirname(os.path.abspath(path)) if path != "<scenario>" else os.getcwd()
    seed = data.get("seed", 1)
    if isinstance(seed, bool) or not isinstance(seed, int) or seed < 0:
        raise _bad(where, "seed", seed, "an integer ≥ 0")
    desc = data.get("description", "") or ""
    if not isinstance(desc, str):
        raise _bad(where, "description", desc, "a string")
    duration = _number(where, "duration_s", data.get("duration_s"), 0.0, False, nullable=True)
    meter = _mapping(where, "meter", data.get("meter"))
    _unknown(where, "meter.", meter, METER_KEYS)
    mpath = meter.get("map")
    if mpath is not None:
        if not isinstance(mpath, str) or not mpath:
            raise _bad(where, "meter.map", mpath, "a path to a register map (relative to this file)")
        mpath = mpath if os.path.isabs(mpath) else os.path.normpath(os.path.join(base, mpath))
        if not os.path.isfile(mpath):
            raise _fail(where, "meter.map", f"{meter['map']!r}: no such file ({mpath})")
    baud = meter.get("baud")
    if baud is not None:
        if isinstance(baud, bool) or baud not in BAUDS:
            raise _bad(where, "meter.baud", baud, ", ".join(map(str, BAUDS)) + ", or null")
    unit = meter.get("unit_id")
    if unit is not None:
        unit = _number(where, "meter.unit_id", unit, 1.0, True, 247.0, integer=True)
    echo = meter.get("echo", False)
    if not isinstance(echo, bool):
        raise _bad(where, "meter.echo", echo, "true or false")
    latency = _number(where, "meter.latency_timer_ms", meter.get("latency_timer_ms", 0.0), 0.0, True, 255.0)
    stm = _mapping(where, "stm32", data.get("stm32"))
    _unknown(where, "stm32.", stm, STM32_KEYS)
    wd = _number(where, "stm32.watchdog_s", stm.get("watchdog_s", 0.2), WATCHDOG_MS_MIN / 1000.0,
                 True, WATCHDOG_MS_MAX / 1000.0)
    sbaud = _number(where, "stm32.baud", stm.get("baud", 115200), 1200.0, True, 4000000.0,
                    integer=True)
    plant = _plant(where, _mapping(where, "plant", data.get("plant")))
    method = _method(where, _mapping(where, "method", data.get("method")), plant.t_set)
    control = _control(where, _mapping(where, "control", data.get("control")))
    faults = _faults(where, data.get("faults"))
    return Scenario(path=path, seed=seed, description=desc, duration_s=duration, meter_map=mpath,
                    baud=baud, unit_id=unit, echo=echo, latency_timer_ms=latency,
                    watchdog_s=wd, stm32_baud=sbaud, plant=plant, faults=faults,
                    method=method, control=control)


def load_scenario(path: str | os.PathLike | None = None) -> Scenario:
    """Read and validate a scenario file (None: the packaged demo)."""
    path = os.fspath(path) if path is not None else DEFAULT_SCENARIO
    try:
        data = safeyaml.read(path, limits=safeyaml.CONFIG).data
    except FileNotFoundError:
        raise ScenarioError(f"{path}: no such scenario file") from None
    except IsADirectoryError:
        raise ScenarioError(f"{path}: is a folder, not a scenario file") from None
    except OSError as e:
        raise ScenarioError(f"{path}: cannot read: {e.strerror}") from None
    except safeyaml.YamlError as e:
        raise ScenarioError(f"{path}: {e.detail()}") from None
    return scenario_from_dict(data, path)
