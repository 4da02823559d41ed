"""Test helpers for the northbound: a real Mosquitto broker and mosquitto_sub as processes."""
from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import threading
import time

from tools import free_port, require_tool


def wait_port(port: int, timeout: float = 20.0, host: str = "127.0.0.1") -> None:
    t_end = time.monotonic() + timeout
    while time.monotonic() < t_end:
        try:
            with socket.create_connection((host, port), timeout=0.5):
                return
        except OSError:
            time.sleep(0.05)
    raise AssertionError(f"nothing listens on {host}:{port} after {timeout} s")


def wait_for(cond, timeout: float = 20.0, interval: float = 0.05, what: str = "condition"):
    t_end = time.monotonic() + timeout
    while True:
        v = cond()
        if v:
            return v
        if time.monotonic() > t_end:
            raise AssertionError(f"timed out after {timeout} s waiting for {what}")
        time.sleep(interval)


class Broker:
    """Mosquitto on a free loopback port; ``persistent`` keeps sessions across restarts."""

    def __init__(self, tmp_path, persistent: bool = False, port: int | None = None):
        self.exe = require_tool("mosquitto")
        self.port = port or free_port()
        self.dir = tmp_path / f"broker-{self.port}"
        self.dir.mkdir(exist_ok=True)
        self.conf = self.dir / "mosquitto.conf"
        import getpass

        # as root, mosquitto would drop to user `mosquitto`, who may not write to the test folder
        lines = [f"user {getpass.getuser()}", f"listener {self.port} 127.0.0.1", "allow_anonymous true",
                 f"persistence {'true' if persistent else 'false'}",
                 f"persistence_location {self.dir}/", "autosave_interval 1",
                 "max_queued_messages 100000", "log_type error", "log_type warning",
                 f"log_dest file {self.dir}/mosquitto.log"]
        self.conf.write_text("\n".join(lines) + "\n")
        self.p: subprocess.Popen | None = None

    def start(self) -> "Broker":
        self.p = subprocess.Popen([self.exe, "-c", str(self.conf)], stdout=subprocess.DEVNULL,
                                  stderr=subprocess.DEVNULL)
        wait_port(self.port)
        return self

    def stop(self) -> None:
        if self.p is not None and self.p.poll() is None:
            self.p.send_signal(signal.SIGTERM)
            try:
                self.p.wait(10)
            except subprocess.TimeoutExpired:
                self.p.kill()
                self.p.wait()
        self.p = None

    def __enter__(self):
        return self.start()

    def __exit__(self, *exc):
        self.stop()


class Sub:
    """mosquitto_sub printing `retain<TAB>topic<TAB>payload` lines, collected by a thread."""

    def __init__(self, port: int, topic: str, *, qos: int = 1, client_id: str | None = None,
                 clean: bool = True, extra: list[str] | None = None):
        exe = require_tool("mosquitto_sub")
        argv = [exe, "-h", "127.0.0.1", "-p", str(port), "-t", topic, "-q", str(qos),
                "-F", "%r\t%t\t%p", "-k", "5"]
        if client_id:
            argv += ["-i", client_id]
        if not clean:
            argv += ["-c"]
        argv += extra or []
        self.p = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        self.lines: list[tuple[bool, str, str, float]] = []
        self._lock = threading.Lock()
        self._t = threading.Thread(target=self._read, daemon=True)
        self._t.start()

    def _read(self) -> None:
        for line in self.p.stdout:
            line = line.rstrip("\n")
            parts = line.split("\t", 2)
            if len(parts) == 3:
                with self._lock:
                    self.lines.append((parts[0] == "1", parts[1], parts[2], time.time()))

    def messages(self, suffix: str | None = None) -> list[tuple[bool, str, dict, float]]:
        with self._lock:
            lines = list(self.lines)
        out = []
        for r, t, p, ts in lines:
            if suffix is not None and not (t == suffix or t.endswith("/" + suffix)):
                continue
            try:
                out.append((r, t, json.loads(p), ts))
            except json.JSONDecodeError:
                out.append((r, t, {"_raw": p}, ts))
        return out

    def wait(self, cond, timeout: float = 20.0, what: str = "messages"):
        return wait_for(lambda: cond(self), timeout, what=what)

    def stop(self) -> None:
        if self.p.poll() is None:
            self.p.terminate()
            try:
                self.p.wait(5)
            except subprocess.TimeoutExpired:
                self.p.kill()
                self.p.wait()
        self._t.join(5)
        self.p.stdout.close()
        self.p.stderr.close()


def pub(port: int, topic: str, payload: str, *, retain: bool = False, qos: int = 1) -> None:
    exe = require_tool("mosquitto_pub")
    argv = [exe, "-h", "127.0.0.1", "-p", str(port), "-t", topic, "-m", payload, "-q", str(qos)]
    if retain:
        argv.append("-r")
    subprocess.run(argv, check=True, timeout=20)


def env_with_root() -> dict:
    from conftest import ROOT
    env = dict(os.environ)
    env["PYTHONPATH"] = ROOT + os.pathsep + env.get("PYTHONPATH", "")
    return env


# ------------------------------------------------------------------ an in-process station
class Reading:
    def __init__(self, ch1, ch2, rtt_s=0.004):
        self.ch1, self.ch2, self.rtt_s = ch1, ch2, rtt_s


class FakeMeter:
    """The smallest meter port: constant tensions (None → no reply). For tests of the command path
    that do not need a plant; end-to-end tests use `hookwatch sim` instead."""

    def __init__(self, ch1=0.40, ch2=0.60):
        self.connected = True
        self.counters = {}
        self.value = (ch1, ch2)

    async def open(self):
        pass

    async def read(self):
        await __import__("asyncio").sleep(0.002)
        return Reading(*self.value) if self.value else None

    async def close(self):
        pass


class FakeStm32:
    def __init__(self):
        self.connected = True
        self.counters = {}
        self.calls = []

    async def open(self):
        pass

    async def enable(self):
        self.calls.append("enable")

    async def set_speed(self, rpm):
        return None

    async def stop(self, reason=""):
        self.calls.append(f"stop:{reason}")

    async def read_status(self):
        return None

    async def close(self):
        pass


class LoopThread:
    """An asyncio loop in its own thread, like a StationRunner's."""

    def __init__(self):
        import asyncio

        self.loop = asyncio.new_event_loop()
        self.t = threading.Thread(target=self.loop.run_forever, daemon=True)
        self.t.start()

    def call(self, coro, timeout: float = 20.0):
        import asyncio

        return asyncio.run_coroutine_threadsafe(coro, self.loop).result(timeout)

    def close(self):
        import asyncio

        async def _cancel_all():
            for t in asyncio.all_tasks():
                if t is not asyncio.current_task():
                    t.cancel()

        try:
            self.call(_cancel_all(), 5)
        except Exception:
            pass
        self.loop.call_soon_threadsafe(self.loop.stop)
        self.t.join(5)
        self.loop.run_until_complete(self.loop.shutdown_default_executor())
        self.loop.close()


#: a fake meter is no plant (its tension is there with the motor off and does not follow the
#: setpoint): no zero check, and a start settles on any tension near T_set (METHOD.md §3a)
FAKE_PLANT_START = {"zero_check": False, "settle_band": 0.5, "settle_time": 0.2}


def make_station(tmp_path, outputs, station_id="st1", **kw):
    from gateway.control import ControlParams
    from gateway.station.station import Station, TestPlan

    return Station(station_id=station_id, method=dict(FAKE_PLANT_START), control=ControlParams(),
                   meter=FakeMeter(),
                   stm32=FakeStm32(), records_dir=str(tmp_path / "records"), outputs=outputs,
                   default_plan=TestPlan("S-0", "I", 0.5, 600.0), **kw)


class RunningStation:
    """A real Station running its slot loop on a LoopThread (with the fake ports above)."""

    def __init__(self, lt: LoopThread, station):
        import asyncio

        self.lt, self.station = lt, station

        async def _mk():
            return asyncio.Event()

        self.stop_evt = lt.call(_mk())
        self.fut = asyncio.run_coroutine_threadsafe(station.run(self.stop_evt), lt.loop)

    def stop(self, timeout: float = 30.0) -> None:
        self.lt.loop.call_soon_threadsafe(self.stop_evt.set)
        self.fut.result(timeout)


def mbpoll(port: int, *args, unit: int = 1, values=(), timeout: float = 20.0):
    """Run mbpoll once against 127.0.0.1:port (0-based addresses). Returns (rc, {addr: value}, stderr)."""
    import re

    exe = require_tool("mbpoll")
    argv = [exe, "-m", "tcp", "-p", str(port), "-a", str(unit), "-0", "-1", "-o", "2", *args,
            "127.0.0.1", *(["--"] if any(float(v) < 0 for v in values) else []), *[str(v) for v in values]]
    r = subprocess.run(argv, capture_output=True, text=True, timeout=timeout)
    vals = {}
    for m in re.finditer(r"^\[(\d+)\]:\s+(\S+)", r.stdout, re.M):
        v = m.group(2)
        try:
            vals[int(m.group(1))] = int(v)
        except ValueError:
            vals[int(m.group(1))] = float(v)
    return r.returncode, vals, r.stderr.strip()
