"""Helpers for the console tests: a running fleet (`hookwatch sim` + `hookwatch run`) with the
console on a free loopback port, users made with `hookwatch user add`, and a small HTTP client."""
from __future__ import annotations

import contextlib
import http.cookiejar
import json
import subprocess
import urllib.error
import urllib.request

import yaml

from conftest import ROOT, hookwatch_cmd
from kit.e2e import fleet_dir, run_gateway, virtual_station

QUICK = "config/scenarios/quick.yaml"


def add_user(users_file, name, password):
    p = subprocess.run(hookwatch_cmd() + ["user", "add", name, "--file", str(users_file),
                                          "--password-stdin"], input=password + "\n",
                       capture_output=True, text=True, cwd=ROOT, timeout=60)
    assert p.returncode == 0, p.stderr
    return p


@contextlib.contextmanager
def console_fleet(tmp_path, names=("loom-a",), *, users=None, console=None, test=None, seed=1):
    """Yields (base_url, gateway Proc, {name: (sim Proc, links)})."""
    users_file = tmp_path / "users.json"
    for u, pw in (users or {}).items():
        add_user(users_file, u, pw)
    fleet = fleet_dir(tmp_path, control={"dead_band_n": 0.01},
                      test={"t_end_s": 70, "autostart": True, **(test or {})},
                      console={"enabled": True, "listen": ["127.0.0.1:0"],
                               "users_file": str(users_file), "lockout_attempts": 3,
                               "lockout_s": 60, **(console or {})})
    with contextlib.ExitStack() as stack:
        sims = {}
        for i, name in enumerate(names):
            sub = tmp_path / name
            sub.mkdir()
            sims[name] = stack.enter_context(virtual_station(sub, QUICK, seed=seed + i))
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
