"""StationLimits: what commands are checked against, built once from the station's configuration.

The regression: a station with ``method.full_scale: 10`` loads with ``test.t_set_n: 6``, yet a start
with t_set 6.0 was refused "allowed: (0, 4.9) N" (the limits fell back to a default full scale)."""
import struct

import pytest

from gateway.config import load_station
from gateway.core.control import ControlParams
from gateway.core.ports import StationLimits
from gateway.core.records import Command, CommandKind, StationState
from gateway.core.records import TestState as TState
from gateway.outputs.plc import registers as R
from gateway.outputs.plc.server import ModbusOutput, ModbusSettings, shutdown_all
from gateway.station.build import method_values, station_limits
from gateway.station.command_desk import validate
from gateway.station.station import Station, TestPlan
from kit.fakes import FakeMeter, FakeStm32
from kit.northbound import LoopThread, RunningStation, mbpoll
from kit.tools import free_port, require_tool, wait_for

YAML = """station: {id: fs10}
meter: {port: /dev/a-meter}
stm32: {port: /dev/a-stm32}
grades: [A, B, C]
method: {full_scale: 10}
test: {t_set_n: 6, t_end_s: 900}
"""


@pytest.fixture
def cfg(tmp_path):
    p = tmp_path / "fs10.yaml"
    p.write_text(YAML)
    return load_station(str(p))


def _start(t_set, **kw):
    return Command(CommandKind.START, "mqtt", {"sample_id": "S-1", "t_set": t_set, **kw})


def test_limits_come_from_the_configuration(cfg):
    lim = station_limits(cfg, method_values(cfg))
    assert lim == StationLimits(full_scale=10.0, sat_ratio=0.98, grades=("A", "B", "C"),
                                t_end_default_s=900.0)
    assert lim.t_set_range == (0.0, pytest.approx(9.8))
    idle = StationState(station="fs10")
    assert validate(_start(6.0), lim, idle) is None
    r = validate(_start(9.9), lim, idle)
    assert r is not None and r.code == 5 and "allowed: (0, 9.8) N" in r.reason
    r = validate(_start(1.0, grade="I"), lim, idle)
    assert r is not None and r.code == 6 and "allowed: A, B, C" in r.reason
    running = StationState(station="fs10", state=TState.MONITORING)
    assert validate(_start(6.0), lim, running).code == 1


def test_defaults_match_the_old_fixed_rule():
    lim = StationLimits()
    assert lim.t_set_range == (0.0, pytest.approx(4.9)) and lim.grades == ("I", "II")
    r = validate(_start(6.0), lim, StationState(station="x"))
    assert r is not None and "allowed: (0, 4.9) N" in r.reason


def _sample_regs(text):
    return list(struct.unpack(">16H", text.encode().ljust(32, b"\0")))


def test_a_plc_starts_a_test_at_6_n_on_a_10_n_meter(cfg, tmp_path):
    """Through the real PLC path: mbpoll writes the setpoint 6.0 N and the start command."""
    require_tool("mbpoll")
    port = free_port()
    mv = method_values(cfg)
    st = Station(station_id="fs10", method=mv, control=ControlParams(), meter=FakeMeter(5.9, 6.1),
                 stm32=FakeStm32(), records_dir=str(tmp_path / "rec"),
                 default_plan=TestPlan("S-0", None, 6.0, 900.0), limits=station_limits(cfg, mv))
    st.outputs.append(ModbusOutput(ModbusSettings("fs10", port=port, unit_id=7, writes_enabled=True,
                                                  allowed_clients=("127.0.0.1",)), st))
    lt = LoopThread()
    run = RunningStation(lt, st)
    try:
        wait_for(lambda: mbpoll(port, "-t", "3", "-r", "0", unit=7)[0] == 0, 20, what="the server")
        hr = R.HR
        assert mbpoll(port, "-t", "4", "-r", str(hr["sample_id"].address), unit=7,
                      values=_sample_regs("PLC-6N"))[0] == 0
        rc, _, err = mbpoll(port, "-t", "4:float", "-B", "-r", str(hr["t_set"].address), unit=7,
                            values=[6.0])
        assert rc == 0, err
        rc, _, err = mbpoll(port, "-t", "4", "-r", str(hr["command"].address), unit=7, values=[1])
        assert rc == 0, err
        assert st.plan is not None and (st.plan.sample_id, st.plan.t_set) == ("PLC-6N", 6.0)
        # 9.9 N is beyond T_sat = 9.8 N: exception 03, nothing changes
        rc, _, err = mbpoll(port, "-t", "4:float", "-B", "-r", str(hr["t_set"].address), unit=7,
                            values=[9.9])
        assert rc != 0
    finally:
        run.stop()
        lt.close()
        shutdown_all()
