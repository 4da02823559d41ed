"""Northbound test helpers: a real Station on its own loop thread (with the fake ports), and
mbpoll as the PLC. The broker is kit.broker."""
from __future__ import annotations

import os
import subprocess
import threading

from conftest import ROOT
from kit.fakes import FakeMeter, FakeStm32
from kit.tools import require_tool


def env_with_root() -> dict:
    env = dict(os.environ)
    env["PYTHONPATH"] = ROOT + os.pathsep + env.get("PYTHONPATH", "")
    return env


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


def make_station(tmp_path, outputs, station_id="st1", stm32=None, **kw):
    from gateway.core.control import ControlParams
    from gateway.station.station import Station, TestPlan

    return Station(station_id=station_id, method=dict(FAKE_PLANT_START), control=ControlParams(),
                   meter=FakeMeter(), stm32=stm32 or FakeStm32(), records_dir=str(tmp_path / "records"),
                   outputs=outputs,
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
