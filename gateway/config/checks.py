"""Feasibility and plausibility of a valid station configuration (``hookwatch check``).

Validation (:mod:`.loader`) says whether a file is well-formed; these checks say whether it can
work: does one poll of the meter fit in a sampling slot at the configured baud, are the wrap angle
and threshold physically sensible, do the ports and files it names exist here. Each check is a
function ``fn(cfg, ld, report)`` listed in :data:`CHECKS` with the sentence the docs print.
"""
from __future__ import annotations

import math
import os
from collections.abc import Callable
from dataclasses import dataclass

from drivers.stm32 import protocol as P

from . import sections as S
from .loader import Loaded, load_meter_map

#: share of the slot kept free for jitter, the method and the outputs
SLOT_SPARE = 0.2
#: STM32 reply latency assumed on top of the wire time (firmware answers from its UART interrupt)
STM32_LATENCY_S = 0.0005
#: physically sensible relative threshold increment δ (error outside, warning outside the soft range)
DELTA_HARD = (0.02, 1.0)
DELTA_SOFT = (0.05, 0.5)


@dataclass(frozen=True)
class Check:
    doc: str
    fn: Callable
    local: bool = False     # depends on the machine it runs on (skipped by --skip-local)


class _Rep:
    def __init__(self, ld: Loaded):
        self.ld = ld
        self.issues: list = []

    def error(self, path, msg, anchor=None):
        self.issues.append(self.ld.issue("error", path, msg, anchor))

    def warning(self, path, msg, anchor=None):
        self.issues.append(self.ld.issue("warning", path, msg, anchor))


def stm32_exchange_s(baud: int) -> float:
    """Wire time of one SET_SPEED request and its ACK (with status) at ``baud``, plus latency."""
    req = P.OVERHEAD + P.REQUEST_PAYLOAD[P.Cmd.SET_SPEED]
    rep = P.OVERHEAD + P.ACK_PAYLOAD
    return (req + rep) * P.BITS_PER_CHAR / float(baud) + STM32_LATENCY_S


def bus_budget(cfg) -> dict | None:
    """The numbers of one slot: meter poll, STM32 exchange, slot length (seconds), or None when the
    meter map cannot be read."""
    try:
        mm = load_meter_map(cfg)
    except Exception:
        return None
    ts = float(cfg.method["ts"])
    poll = mm.poll_time_s()
    stm = stm32_exchange_s(cfg.stm32.baud)
    out = {"ts": ts, "poll": poll, "stm32": stm, "baud": mm.baud, "map": mm,
           "request_bytes": mm.request_bytes, "response_bytes": mm.response_bytes,
           "turnaround": mm.turnaround_s}
    ok_bauds = [b for b in S.METER_BAUDS
                if mm.with_overrides(baud=b).poll_time_s() + stm <= ts * (1 - SLOT_SPARE)]
    out["min_baud"] = ok_bauds[0] if ok_bauds else None
    return out


def _ms(x: float) -> str:
    return f"{x * 1e3:.1f} ms"


def _hz(ts: float) -> str:
    return f"{1 / ts:g} Hz"


def budget_text(b: dict) -> str:
    return (f"meter {b['baud']} baud: poll {_ms(b['poll'])} + STM32 {_ms(b['stm32'])} "
            f"of a {_ms(b['ts'])} slot")


def _bus(cfg, ld, r):
    b = bus_budget(cfg)
    if b is None:
        return
    ts, poll, stm = b["ts"], b["poll"], b["stm32"]
    need = poll + stm
    where = ("meter", "baud")
    wire = (f"{b['baud']} baud: one poll takes {_ms(poll)} on the wire ({b['request_bytes']} B request "
            f"+ {_ms(b['turnaround'])} turnaround + {b['response_bytes']} B reply, 11 bits/char), "
            f"the STM32 exchange {_ms(stm)} at {cfg.stm32.baud} baud; the slot is {_ms(ts)}")
    fix = (f"; use ≥ {b['min_baud']} baud" if b["min_baud"] else
           "; no meter baud fits: lengthen method.ts or read fewer registers")
    if need > ts:
        r.error(where, f"{wire} — {_hz(ts)} is impossible{fix}", anchor=("meter",))
    elif need > ts * (1 - SLOT_SPARE):
        r.warning(where, f"{wire} — fits, but leaves {_ms(ts - need)} of the slot (less than "
                  f"{SLOT_SPARE:.0%}) for jitter and the method{fix}", anchor=("meter",))
    if cfg.meter.timeout_s < poll:
        r.error(("meter", "timeout_s"), f"{_ms(cfg.meter.timeout_s)} is shorter than one poll "
                f"({_ms(poll)} at {b['baud']} baud): every read would time out; allowed: ≥ "
                f"{math.ceil(poll * 1e4) / 1e4:g} s", anchor=("meter",))
    elif cfg.meter.timeout_s + stm > ts:
        r.warning(("meter", "timeout_s"), f"a timed-out read ({_ms(cfg.meter.timeout_s)}) plus the "
                  f"STM32 exchange ({_ms(stm)}) overruns the {_ms(ts)} slot", anchor=("meter",))
    if cfg.stm32.timeout_s < stm:
        r.error(("stm32", "timeout_s"), f"{_ms(cfg.stm32.timeout_s)} is shorter than one exchange "
                f"({_ms(stm)} at {cfg.stm32.baud} baud): every request would time out",
                anchor=("stm32",))


def _theta(cfg, ld, r):
    th = cfg.method["theta_deg"]
    if not 0 < th <= 360:
        r.error(("method", "theta_deg"), f"{th:g}° is not a wrap angle around a needle hook; "
                "allowed: 0 < theta_deg ≤ 360 (the yarn wraps the hook less than one turn)",
                anchor=("method",))


def _delta(cfg, ld, r):
    d = cfg.method["delta"]
    lo, hi = DELTA_HARD
    slo, shi = DELTA_SOFT
    if not lo <= d <= hi:
        why = ("inside the scatter of a steady μ: noise alone would end the life" if d < lo else
               "μ would have to rise by more than 100 % over its baseline: the hook breaks first")
        r.error(("method", "delta"), f"{d:g} is outside physical sense ({why}); allowed: "
                f"{lo:g} ≤ delta ≤ {hi:g}", anchor=("method",))
    elif not slo <= d <= shi:
        r.warning(("method", "delta"), f"{d:g} is unusual (the method's default is 0.25; "
                  f"{slo:g} … {shi:g} is the usual range)", anchor=("method",))


def _setpoint(cfg, ld, r):
    m = cfg.method
    t_sat = m["sat_ratio"] * m["full_scale"]
    t = cfg.test.t_set_n
    if t >= t_sat:
        r.error(("test", "t_set_n"), f"{t:g} N is at or above the sensor's saturation T_sat = "
                f"sat_ratio · full_scale = {t_sat:g} N: every slot would be unsafe; allowed: "
                f"< {t_sat:g} N", anchor=("test",))
    elif t * 2 > t_sat:
        r.warning(("test", "t_set_n"), f"{t:g} N is more than half of T_sat ({t_sat:g} N): the "
                  "outgoing tension T2 = T1·e^(μθ) may saturate the sensor", anchor=("test",))


def _duration(cfg, ld, r):
    m = cfg.method
    if cfg.test.t_end_s <= m["w_hold"]:
        r.warning(("test", "t_end_s"), f"{cfg.test.t_end_s:g} s is not longer than method.w_hold "
                  f"({m['w_hold']:g} s): a test of this length ends before a baseline can be "
                  "established", anchor=("test",))


def _speeds(cfg, ld, r):
    if cfg.control.n_max_rpm > P.DEFAULT_MAX_RPM:
        r.warning(("control", "n_max_rpm"), f"{cfg.control.n_max_rpm:g} rpm is above the STM32 "
                  f"firmware's speed range (0 … {P.DEFAULT_MAX_RPM:g} rpm): commands above it are refused",
                  anchor=("control",))
    wd = cfg.stm32.watchdog_s
    if wd is None:
        return          # null: method.stop_after + the margin, as the design needs
    stop_after = float(cfg.method.get("stop_after", 1.0) or 0.0)
    need = P.watchdog_for(stop_after)
    if wd < stop_after:
        r.error(("stm32", "watchdog_s"), f"{wd:g} s is shorter than the protection stop "
                f"(method.stop_after = {stop_after:g} s): a stall of the gateway the method "
                "tolerates would stop the drive and end the test; allowed: ≥ "
                f"{stop_after:g} s (recommended: null = {need:g} s)", anchor=("stm32",))
    elif wd < need:
        r.warning(("stm32", "watchdog_s"), f"{wd:g} s leaves less than {P.WATCHDOG_MARGIN_S:g} s "
                  f"over the protection stop (method.stop_after = {stop_after:g} s): a stall "
                  "just shorter than it can still stop the drive (recommended: null = "
                  f"{need:g} s)", anchor=("stm32",))


def _ports(cfg, ld, r):
    for sec in ("meter", "stm32"):
        p = getattr(cfg, sec).port
        if "://" in p:
            continue
        if not os.path.exists(p):
            r.warning((sec, "port"), f"{p!r} does not exist here (adapter unplugged, udev rule "
                      "missing, or checked on another machine)", anchor=(sec,))


def _writable(path: str) -> bool:
    p = os.path.abspath(path)
    while not os.path.exists(p):
        parent = os.path.dirname(p)
        if parent == p:
            return False
        p = parent
    return os.path.isdir(p) and os.access(p, os.W_OK | os.X_OK)


def _files(cfg, ld, r):
    if not _writable(cfg.recorder.dir):
        r.warning(("recorder", "dir"), f"{cfg.recorder.dir!r} is not writable by this user "
                  f"(the station runs as the user of its unit, normally 'hookwatch')",
                  anchor=("recorder",))
    m = cfg.mqtt
    if not m.enabled:
        return
    if m.password_env and m.password_env not in os.environ:
        r.warning(("mqtt", "password_env"), f"${m.password_env} is not set in this environment "
                  "(the unit sets it with EnvironmentFile=)", anchor=("mqtt",))
    if m.password_file:
        if not os.path.isfile(m.password_file):
            r.warning(("mqtt", "password_file"), f"{m.password_file!r} does not exist here", anchor=("mqtt",))
        elif os.stat(m.password_file).st_mode & 0o077:
            r.warning(("mqtt", "password_file"), f"{m.password_file!r} is readable by others; "
                      "chmod 600 it", anchor=("mqtt",))
    if m.tls.enabled:
        for k in ("ca_file", "cert_file", "key_file"):
            v = getattr(m.tls, k)
            if v and not os.path.isfile(v):
                r.warning(("mqtt", "tls", k), f"{v!r} does not exist here", anchor=("mqtt",))


def _name(cfg, ld, r):
    stem = os.path.splitext(os.path.basename(ld.path))[0]
    if os.path.basename(os.path.dirname(os.path.abspath(ld.path))) == "stations" and stem != cfg.station.id:
        r.warning(("station", "id"), f"{cfg.station.id!r} differs from the file name {stem!r}: the "
                  f"unit hookwatch@{stem} would run station {cfg.station.id}", anchor=("station",))


CHECKS: tuple[Check, ...] = (
    Check("One meter poll (request + turnaround + reply at the configured baud, 11 bits a "
          "character) plus the STM32 exchange fits in the sampling slot `method.ts` (error), with "
          f"{SLOT_SPARE:.0%} of the slot to spare (warning); `meter.timeout_s` is not shorter than a "
          "poll and `stm32.timeout_s` not shorter than an exchange (error).", _bus),
    Check("`method.theta_deg` is a wrap angle around a hook: 0 < θ ≤ 360 (error).", _theta),
    Check(f"`method.delta` is within {DELTA_HARD[0]:g} … {DELTA_HARD[1]:g} (error) and "
          f"{DELTA_SOFT[0]:g} … {DELTA_SOFT[1]:g} (warning).", _delta),
    Check("`test.t_set_n` is below the saturation `sat_ratio · full_scale` (error) and at most "
          "half of it (warning).", _setpoint),
    Check("`test.t_end_s` is longer than `method.w_hold` (warning).", _duration),
    Check("`control.n_max_rpm` within the STM32 firmware's range (warning); `stm32.watchdog_s` "
          "not shorter than `method.stop_after` (error) and at least "
          f"`stop_after` + {P.WATCHDOG_MARGIN_S:g} s (warning).", _speeds),
    Check("The serial ports exist here (warning).", _ports, local=True),
    Check("`recorder.dir` is writable; the MQTT password variable/file and TLS files exist "
          "(warnings).", _files, local=True),
    Check("A file in `stations/` is named after its `station.id` (warning).", _name),
)


def feasibility(ld: Loaded, local: bool = True) -> list:
    """Issues of the checks above for one valid station (``ld.cfg`` not None); ``local=False``
    skips the checks that depend on this machine."""
    r = _Rep(ld)
    for c in CHECKS:
        if local or not c.local:
            c.fn(ld.cfg, ld, r)
    return r.issues
