"""Helpers for the console tests: a running fleet (`hookwatch sim` + `hookwatch run`) with the
console on a free loopback port, users made with `hookwatch user add`, and a small HTTP client."""
from __future__ import annotations

import contextlib
import http.cookiejar
import json
import math
import os
import subprocess
import urllib.error
import urllib.request

import yaml

from conftest import ROOT, hookwatch_cmd
from gateway.core import records as R
from gateway.core.records import StationState
from gateway.outputs.console import auth
from gateway.outputs.console.app import ConsoleServer
from gateway.outputs.console.feed import ConsoleOutput
from gateway.outputs.console.settings import ConsoleSettings
from kit.e2e import QUICK_END, QUICK_METHOD, fleet_dir, quick_scenario, run_gateway, virtual_station

QUICK = "config/scenarios/quick.yaml"


def add_user(users_file, name, password):
    p = subprocess.run(hookwatch_cmd() + ["user", "add", name, "--file", str(users_file),
                                          "--password-stdin"], input=password + "\n",
                       capture_output=True, text=True, cwd=ROOT, timeout=60)
    assert p.returncode == 0, p.stderr
    return p


@contextlib.contextmanager
def console_fleet(tmp_path, names=("loom-a",), *, users=None, console=None, test=None, seed=1,
                  quick=False):
    """Yields (base_url, gateway Proc, {name: (sim Proc, links)}). Each station runs the one-minute
    life (quick.yaml: the end of life ≈ 53 s after slot 0, the planned end at 70 s); ``quick``: the
    kit's twice-compressed one (QUICK_*: the end of life ≈ 23 s after slot 0, the planned end at
    QUICK_END)."""
    users_file = tmp_path / "users.json"
    for u, pw in (users or {}).items():
        add_user(users_file, u, pw)
    life = {"method": QUICK_METHOD} if quick else {}
    fleet = fleet_dir(tmp_path, control={"dead_band_n": 0.01}, **life,
                      test={"t_end_s": QUICK_END if quick else 70, "autostart": True, **(test or {})},
                      console={"enabled": True, "listen": ["127.0.0.1:0"],
                               "users_file": str(users_file), "lockout_attempts": 3,
                               "lockout_s": 60, **(console or {})})
    with contextlib.ExitStack() as stack:
        sims = {}
        for i, name in enumerate(names):
            sub = tmp_path / name
            sub.mkdir()
            sc = quick_scenario(sub, "quick.yaml") if quick else QUICK
            sims[name] = stack.enter_context(virtual_station(sub, sc, seed=seed + i))
            _p, links = sims[name]
            (fleet / "stations" / f"{name}.yaml").write_text(yaml.safe_dump({
                "station": {"id": name}, "meter": {"port": links["meter"]},
                "stm32": {"port": links["stm32"]}, "test": {"sample_id": f"S-{name}"}}))
        gw = run_gateway(tmp_path, str(fleet))
        try:
            url = gw.readline_until("console:", timeout=30)
            yield url.rstrip("/"), gw, sims
        finally:
            gw.stop()


class Client:
    """A browser-like HTTP client: cookies kept, JSON in and out, errors returned not raised."""

    def __init__(self, base: str):
        self.base = base
        self.jar = http.cookiejar.CookieJar()
        self.opener = urllib.request.build_opener(urllib.request.HTTPCookieProcessor(self.jar))
        self.csrf = None

    def request(self, method, path, body=None, headers=None, raw: bytes | None = None):
        data = raw if raw is not None else (None if body is None else json.dumps(body).encode())
        h = {"Content-Type": "application/json", **(headers or {})}
        req = urllib.request.Request(self.base + path, data=data, method=method, headers=h)
        try:
            # a bound against a hang, not a speed goal: a campaign report on a loaded machine
            # (other workers' stations on the same cores) can take minutes
            with self.opener.open(req, timeout=180) as r:
                return r.status, _json(r.read()), r.headers
        except urllib.error.HTTPError as e:
            return e.code, _json(e.read()), e.headers

    def get(self, path):
        return self.request("GET", path)

    def post(self, path, body=None, csrf=True, **kw):
        h = {"X-CSRF-Token": self.csrf} if csrf and self.csrf else {}
        return self.request("POST", path, body, headers=h, **kw)

    def login(self, user, password):
        st, data, _ = self.request("POST", "/api/login", {"user": user, "password": password})
        if st == 200:
            self.csrf = data["csrf"]
        return st, data


def _json(b: bytes):
    try:
        return json.loads(b.decode())
    except ValueError:
        return {"raw": b[:200]}


# ------------------------------------------------ a console fed with constructed station states
CONSOLE_PW = "a long password"
START = "2026-11-26T06:00:00.000Z"
INJECT = '=HYPERLINK("http://evil.example","x")'

#: station → (line, area)
PLACES = {"loom-a": ("line-1", "hall-1"), "loom-b": ("line-1", "hall-2"),
          "loom-c": ("line-2", "hall-1"), "loom-d": ("line-2", "hall-2")}


def fleet_states() -> dict[str, StationState]:
    """Four stations: a, b projected (b sooner and due), c past its end of life (with a stale
    projection that must not be shown), d idle."""
    a = StationState(station="loom-a", state=R.TestState.MONITORING, test_id="20261126T060000Z-A",
                     sample_id=INJECT, grade="+G1", test_started_utc=START, headroom=0.6,
                     end_p10=3600.0, end_p50=5400.0, end_p90=7200.0, p_end=0.12, t_cross=5400.0,
                     elapsed_s=1200.0, prior_mean=5400.0, prior_sd=600.0,
                     prior_source="history:3 (the site: 6 tests from 2 stations (0 of this station; b 4, c 2))",
                     prior_n=3, prior_n_censored=2, prior_n_early=1)
    b = StationState(station="loom-b", state=R.TestState.MONITORING, test_id="20261126T060000Z-B",
                     sample_id="S-B", grade="@G2", test_started_utc=START, headroom=0.2,
                     end_p10=1500.0, end_p50=1800.0, end_p90=2400.0, p_end=0.71, due=True,
                     warn_reasons=["headroom", "trend"], wear_warning=True,
                     warning_alarm="unacknowledged", t_cross=1800.0, elapsed_s=1200.0)
    c = StationState(station="loom-c", state=R.TestState.END_OF_LIFE, test_id="20261126T060000Z-C",
                     sample_id="-S-C", grade="G3", test_started_utc=START, headroom=-0.1,
                     t_life=1000.0, end_p10=900.0, end_p50=1000.0, end_p90=1100.0, p_end=0.99,
                     due=True, t_cross=950.0, alarm="unacknowledged", elapsed_s=1200.0)
    d = StationState(station="loom-d")
    return {"loom-a": a, "loom-b": b, "loom-c": c, "loom-d": d}


#: cells a spreadsheet in some locale would read as a formula
HOSTILE_IDS = ("x;=1+1;y", "\t=cmd", '"=1"', "a\t@SUM(1)", " +1;-2", "x,=1")


def hostile_states() -> dict[str, StationState]:
    """The four stations with every figure ±Infinity or NaN and formula-hiding IDs (issue 27)."""
    a = StationState(station="loom-a", state=R.TestState.MONITORING, test_id="20261126T060000Z-A",
                     sample_id=HOSTILE_IDS[0], grade="=G1", test_started_utc=START, t_set=0.5,
                     mu_ss=math.nan, mu_th=math.inf, k_b=7, headroom=-math.inf, t_cross=math.inf, end_p10=math.inf,
                     end_p50=math.inf, end_p90=math.nan, p_end=math.nan, prior_mean=1e308 * 10, prior_sd=math.nan,
                     lead_s=math.inf, p_due=math.nan, elapsed_s=1200.0)
    b = StationState(station="loom-b", state=R.TestState.MONITORING, test_id="20261126T060000Z-B",
                     sample_id=HOSTILE_IDS[1], grade=HOSTILE_IDS[2], test_started_utc=START,
                     headroom=math.nan, end_p10=-math.inf, end_p50=1800.0, end_p90=math.inf, p_end=math.inf, due=True,
                     t_cross=-math.inf, elapsed_s=1200.0)
    c = StationState(station="loom-c", state=R.TestState.END_OF_LIFE, test_id="20261126T060000Z-C",
                     sample_id=HOSTILE_IDS[3], grade=HOSTILE_IDS[4], test_started_utc=START,
                     t_life=math.inf, mu_ss=0.2, mu_th=math.nan, due=True, elapsed_s=1200.0)
    d = StationState(station="loom-d", sample_id=HOSTILE_IDS[5], t_life=math.nan, elapsed_s=1200.0)
    return {"loom-a": a, "loom-b": b, "loom-c": c, "loom-d": d}


def start_console(tmp_path, states=None, **kw):
    """A console with the four stations; their states handed over as a station would."""
    users = str(tmp_path / "users.json")
    if not os.path.exists(users):
        auth.add_user(users, "alice", CONSOLE_PW)
    dirs = {n: str(tmp_path / "records" / n) for n in PLACES}
    for d in dirs.values():
        os.makedirs(d, exist_ok=True)
    srv = ConsoleServer(ConsoleSettings(listen=("127.0.0.1:0",), users_file=users, **kw), dirs,
                        places=PLACES)
    outs = {n: ConsoleOutput(srv.feeds[n]) for n in PLACES}
    for n, st in (states or fleet_states()).items():
        outs[n].on_state(st)
    url = srv.start()[0].rstrip("/")
    return srv, url, outs, dirs
