"""Shared test setup. Tests mirror the package tree (tests/gateway/..., tests/drivers/...); the
shared kit is tests/kit/ (process stop, Mosquitto, the virtual station and meter, fakes), offered
here as fixtures too."""
import os
import sys

import pytest

HERE = TESTS = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
VECTORS = os.path.join(HERE, "vectors")
VENV_BIN = os.path.join(ROOT, ".venv", "bin")

# the project before tests/ (tests/gateway must never shadow the gateway package), and tests/
# for `kit` and `conftest` from any depth
for _p in (HERE, ROOT):
    if _p in sys.path:
        sys.path.remove(_p)
    sys.path.insert(0, _p)


def hookwatch_cmd() -> list[str]:
    """The console command as a user runs it (the venv's, else the one on PATH)."""
    exe = os.path.join(os.path.dirname(sys.executable), "hookwatch")
    if os.path.exists(exe):
        return [exe]
    return [sys.executable, "-m", "gateway.cli"]


# ------------------------------------------------------------------------------------ fixtures


@pytest.fixture
def broker(tmp_path):
    """A running Mosquitto on a free loopback port (kit.broker.Broker), stopped after the test."""
    from kit.broker import Broker

    with Broker(tmp_path) as b:
        yield b


@pytest.fixture
def virtual_station(tmp_path):
    """Starts `hookwatch sim SCENARIO` (kit.e2e.virtual_station): call it with the scenario path;
    yields (process, links). Stopped after the test."""
    import contextlib

    from kit.e2e import virtual_station as _vs

    with contextlib.ExitStack() as stack:
        yield lambda scenario, **kw: stack.enter_context(_vs(tmp_path, scenario, **kw))


@pytest.fixture
def fake_meter():
    from kit.fakes import FakeMeter

    return FakeMeter()


@pytest.fixture
def fake_stm32():
    from kit.fakes import FakeStm32

    return FakeStm32()


@pytest.fixture
def loop_thread():
    """An asyncio loop in its own thread (kit.northbound.LoopThread), closed after the test."""
    from kit.northbound import LoopThread

    lt = LoopThread()
    yield lt
    lt.close()
