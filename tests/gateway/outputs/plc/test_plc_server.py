"""Modbus TCP server: mbpoll reads the documented registers with live values from a running
station, validated writes (exception 03 for out-of-range, 01 for clients not allowed, 06 for a
command the running test refuses, 03 for one the station's state refuses), the running test's
sample and test ID in input registers, several stations on one port, and fuzzed frames never
stop it."""
import math
import os
import socket
import struct

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from conftest import ROOT
from gateway.core.records import TestState as TState
from gateway.outputs.plc import registers as R
from gateway.outputs.plc.server import ModbusOutput, ModbusSettings, shutdown_all
from kit.northbound import LoopThread, RunningStation, make_station, mbpoll
from kit.tools import free_port, require_tool, wait_for

IR, HR = R.IR, R.HR


@pytest.fixture(scope="module")
def plant(tmp_path_factory):
    """Two real stations (fake ports, 50 Hz slot loops) served on one port: unit 3 accepts writes
    from 127.0.0.1, unit 4 only from another address; unit 5 (little-endian words) no writes."""
    require_tool("mbpoll")
    tmp = tmp_path_factory.mktemp("modbus")
    port = free_port()
    lt = LoopThread()
    stations, runs = {}, []
    for name, unit, allowed, order, writes in (("st3", 3, ("127.0.0.1",), "big", True),
                                               ("st4", 4, ("10.9.9.9",), "big", True),
                                               ("st5", 5, (), "little", False)):
        s = make_station(tmp, [], station_id=name)
        s.outputs.append(ModbusOutput(ModbusSettings(name, port=port, unit_id=unit, word_order=order,
                                                     writes_enabled=writes, allowed_clients=allowed), s))
        stations[unit] = s
        runs.append(RunningStation(lt, s))
    for unit in (3, 4):
        wait_for(lambda unit=unit: mbpoll(port, "-t", "3:float", "-B", "-r", str(R.IR["t1"].address), unit=unit)[1]
                 .get(R.IR["t1"].address) == 0.4, 20, what="the server with live values")
    yield port, stations
    for r in runs:
        r.stop()
    lt.close()
    shutdown_all()


def _floats(port, unit, start, n, big=True):
    rc, vals, err = mbpoll(port, "-t", "3:float", *(["-B"] if big else []), "-r", str(start), "-c", str(n),
                           unit=unit)
    assert rc == 0, err
    return vals


def _live_floats(port, unit, start, n, big=True):
    """The latest slot's values: a slot the loop reached late is MISSING and reads NaN until the
    next slot (docs/registers.md), which a loaded box shows now and then; read again then."""
    def read():
        v = _floats(port, unit, start, n, big)
        return v if all(math.isfinite(x) for x in v.values()) else None
    return wait_for(read, 10, interval=0.02, what="a slot with a reading")


def test_mbpoll_reads_the_documented_registers_with_live_values(plant):
    port, stations = plant
    rc, v, err = mbpoll(port, "-t", "3", "-r", "0", "-c", str(IR["alarm"].address + 1), unit=3)
    assert rc == 0, err
    assert v[IR["map_version"].address] == R.MAP_VERSION
    assert v[IR["test_state"].address] == int(TState.IDLE)
    status = v[IR["status"].address]
    for bit in ("meter_ok", "stm32_ok", "writes_enabled"):
        assert status & (1 << R.STATUS_BIT[bit]), bit
    assert not status & (1 << R.STATUS_BIT["running"])
    f = _live_floats(port, 3, IR["t1"].address, 3)
    assert f == {IR["t1"].address: 0.4, IR["t2"].address: 0.6, IR["tension"].address: 0.5}
    # the heartbeat counts seconds, driven by the station's own loop
    h0 = v[IR["heartbeat"].address]
    wait_for(lambda: mbpoll(port, "-t", "3", "-r", "0", unit=3)[1].get(0, h0) >= h0 + 2, 20,
             what="the heartbeat to advance")
    # unit 4 on the same port is another station; its status does not show writes for us
    rc, v4, err = mbpoll(port, "-t", "3", "-r", str(IR["status"].address), unit=4)
    assert rc == 0 and not v4[IR["status"].address] & (1 << R.STATUS_BIT["writes_enabled"])
    # little-endian words on unit 5: mbpoll without -B
    assert _live_floats(port, 5, IR["t1"].address, 1, big=False) == {IR["t1"].address: 0.4}


def _frozen():
    """The addresses of the map as shipped, from the golden file (not from the map in the code)."""
    out = {}
    with open(os.path.join(ROOT, R.GOLDEN), encoding="utf-8") as f:
        for line in f:
            c = line.rstrip("\n").split("\t")
            if c[0] in ("input", "holding"):
                out[c[0], c[6]] = int(c[2])
            elif c[0] == "bit":
                out[c[1], c[3]] = int(c[2])
    return out


def test_mbpoll_reads_the_same_values_at_the_frozen_addresses(plant):
    """Issue 35 items 3 and 6: a PLC program written against the frozen map (the golden file's
    addresses) reads the live values from a running station: the whole first read, the floats,
    the staged plan in the holding registers of unit 5 (which no client may write)."""
    port, _ = plant
    fz = _frozen()
    rc, v, err = mbpoll(port, "-t", "3", "-r", "0", "-c", str(fz["input", "map_minor"] + 1), unit=3)
    assert rc == 0, err
    assert (v[fz["input", "map_version"]], v[fz["input", "map_minor"]]) == (R.MAP_VERSION, R.MAP_MINOR)
    assert v[fz["input", "test_state"]] == int(TState.IDLE)
    assert v[fz["input", "status"]] & (1 << fz["status", "meter_ok"]) and v[fz["input", "command_count"]] >= 0
    t1, t2, ten = fz["input", "t1"], fz["input", "t2"], fz["input", "tension"]
    assert _live_floats(port, 3, t1, 3) == {t1: 0.4, t2: 0.6, ten: 0.5}
    rc, h, err = mbpoll(port, "-t", "4:float", "-r", str(fz["holding", "t_set"]), unit=5)
    assert rc == 0 and h == {fz["holding", "t_set"]: 0.5}, err
    sid = fz["holding", "sample_id"]
    rc, h, err = mbpoll(port, "-t", "4", "-r", str(sid), "-c", "16", unit=5)
    assert rc == 0, err
    assert R.decode_sample_id(struct.pack(">16H", *(h[sid + i] for i in range(16)))) == "S-0"


def _write(port, unit, reg, values, typ="4"):
    return mbpoll(port, "-t", typ, *(["-B"] if typ.endswith("float") else []), "-r", str(reg),
                  unit=unit, values=values)


def _hr(port, unit, name, typ="4"):
    rc, v, err = mbpoll(port, "-t", typ, *(["-B"] if typ.endswith("float") else []), "-r", str(HR[name].address),
                        unit=unit)
    assert rc == 0, err
    return v[HR[name].address]


def _cmd_status(port, unit):
    rc, v, err = mbpoll(port, "-t", "3", "-r", str(IR["last_command"].address), "-c", "3", unit=unit)
    assert rc == 0, err
    a = IR["last_command"].address
    return v[a], v[a + 1], v[a + 2]


def _sample_regs(text):
    raw = text.encode().ljust(32, b"\0")
    return list(struct.unpack(">16H", raw))


def test_plc_starts_and_stops_a_test_through_the_command_path(plant):
    port, stations = plant
    s = stations[3]
    assert _write(port, 3, HR["sample_id"].address, _sample_regs("PLC-77"))[0] == 0
    assert _write(port, 3, HR["grade"].address, [2])[0] == 0
    assert _write(port, 3, HR["t_set"].address, [0.45], "4:float")[0] == 0
    assert s.default_plan.t_set == pytest.approx(0.45)
    n0 = _cmd_status(port, 3)[2]
    rc, _, err = _write(port, 3, HR["command"].address, [1])
    assert rc == 0, err
    wait_for(lambda: s.monitor is not None, 10, what="slot 0 after the start sequence (§3a)")
    assert (s.plan.sample_id, s.plan.grade, s.plan.t_set) == ("PLC-77", "II", 0.45)
    assert _cmd_status(port, 3) == (1, 0, (n0 + 1) & 0xFFFF)
    wait_for(lambda: mbpoll(port, "-t", "3", "-r", str(IR["test_state"].address), unit=3)[1]
             .get(IR["test_state"].address) == int(TState.BASELINE_SEARCH), 10, what="test state")
    wait_for(lambda: (mbpoll(port, "-t", "3:int", "-B", "-r", str(IR["slots"].address), unit=3)[1]
                      .get(IR["slots"].address, 0)) > 20, 10, what="slot counter")
    f = _floats(port, 3, IR["t_set"].address, 2)
    assert f[IR["t_set"].address] == pytest.approx(0.45) and f[IR["valid_ratio"].address] > 0.5
    # the running test's sample ID and test ID, read by mbpoll (and pymodbus as the oracle)
    assert _text(port, 3, "run_sample_id") == "PLC-77"
    assert s.test_id and _text(port, 3, "run_test_id") == s.test_id
    assert _pymodbus_text(port, 3, "run_test_id") == s.test_id
    # a second start is refused by the station: exception 06 (busy), reason code BUSY in last_result
    rc, _, err = _write(port, 3, HR["command"].address, [1])
    assert rc != 0 and "busy" in err.lower(), err
    assert _cmd_status(port, 3)[:2] == (1, 1)
    assert _pymodbus_write_exception(port, 3, HR["command"].address, [1]) == 6
    # the setpoint of a running test cannot change: 06 too, and the register keeps its value
    rc, _, err = _write(port, 3, HR["t_set"].address, [0.6], "4:float")
    assert rc != 0 and "busy" in err.lower(), err
    assert _cmd_status(port, 3)[:2] == (4, 8)
    assert _hr(port, 3, "t_set", "4:float") == pytest.approx(0.45)
    rc, _, err = _write(port, 3, HR["command"].address, [2])
    assert rc == 0, err
    # the last test's IDs stay readable after it ended
    assert _text(port, 3, "run_sample_id") == "PLC-77"
    # a stop without a running test: a refusal for the station's state (03), NOT_RUNNING in last_result
    rc, _, err = _write(port, 3, HR["command"].address, [2])
    assert rc != 0 and "illegal data value" in err.lower(), err
    assert _cmd_status(port, 3)[:2] == (2, 2)
    assert _pymodbus_write_exception(port, 3, HR["command"].address, [2]) == 3
    assert s.monitor is None and s.results[-1]["end_reason"] == "stopped by command"
    ev = [e for e in _events(s) if e["type"] == "test_ended"]
    assert ev and ev[-1]["source"] == "plc:127.0.0.1"


def _text(port, unit, name):
    r = IR[name]
    rc, v, err = mbpoll(port, "-t", "3", "-r", str(r.address), "-c", str(r.count), unit=unit)
    assert rc == 0, err
    raw = struct.pack(f">{r.count}H", *(v[r.address + i] for i in range(r.count)))
    return raw.rstrip(b"\0").decode("ascii")


def _pymodbus_client(port):
    from pymodbus.client import ModbusTcpClient

    c = ModbusTcpClient("127.0.0.1", port=port, timeout=3)
    assert c.connect()
    return c


def _pymodbus_text(port, unit, name):
    r = IR[name]
    c = _pymodbus_client(port)
    try:
        rr = c.read_input_registers(r.address, count=r.count, device_id=unit)
        assert not rr.isError(), rr
        return struct.pack(f">{r.count}H", *rr.registers).rstrip(b"\0").decode("ascii")
    finally:
        c.close()


def _pymodbus_write_exception(port, unit, address, values):
    c = _pymodbus_client(port)
    try:
        rr = c.write_registers(address, values, device_id=unit)
        assert rr.isError(), rr
        return rr.exception_code
    finally:
        c.close()


def _events(station):
    import glob
    import json

    out = []
    for p in sorted(glob.glob(f"{station.station_dir}/*/events.jsonl")):
        with open(p) as f:
            out += [json.loads(line) for line in f if line.strip()]
    return out


@pytest.mark.parametrize("name,values,typ", [
    ("t_set", [9.0], "4:float"), ("t_set", [0.0], "4:float"), ("t_set", [-1.0], "4:float"),
    ("grade", [7], "4"), ("command", [99], "4"), ("command", [0], "4"),
    ("t_end", [0x0FFF, 0xFFFF], "4"), ("sample_id", [0x0101], "4"), ("sample_id", [0x4100, 0x4141], "4"),
])
def test_out_of_range_writes_get_exception_03_and_change_nothing(plant, name, values, typ):
    port, stations = plant
    s = stations[3]
    before_hr = mbpoll(port, "-t", "4", "-r", "0", "-c", str(R.HOLDING_SIZE), unit=3)[1]
    plan = s.default_plan
    n0 = _cmd_status(port, 3)
    rc, _, err = _write(port, 3, HR[name].address, values, typ)
    assert rc != 0 and "illegal data value" in err.lower(), err
    assert mbpoll(port, "-t", "4", "-r", "0", "-c", str(R.HOLDING_SIZE), unit=3)[1] == before_hr
    assert s.default_plan == plan and s.monitor is None
    assert _cmd_status(port, 3) == n0


def test_a_write_covering_half_a_float_is_an_address_error(plant):
    port, _ = plant
    rc, _, err = _write(port, 3, HR["t_set"].address + 1, [0])
    assert rc != 0 and "illegal data address" in err.lower(), err


def test_writes_from_a_client_not_listed_or_when_disabled_are_refused(plant):
    port, stations = plant
    for unit in (4, 5):
        before = mbpoll(port, "-t", "4", "-r", "0", "-c", str(R.HOLDING_SIZE), unit=unit)[1]
        rc, _, err = _write(port, unit, HR["command"].address, [1])
        assert rc != 0 and "illegal function" in err.lower(), err
        rc, _, err = _write(port, unit, HR["t_set"].address, [0.4], "4:float")
        assert rc != 0 and "illegal function" in err.lower(), err
        assert mbpoll(port, "-t", "4", "-r", "0", "-c", str(R.HOLDING_SIZE), unit=unit)[1] == before
        assert stations[unit].monitor is None


def test_unknown_unit_and_addresses(plant):
    port, _ = plant
    rc, _, err = mbpoll(port, "-t", "3", "-r", "0", unit=9)
    assert rc != 0 and "target device" in err.lower(), err
    rc, _, err = mbpoll(port, "-t", "3", "-r", str(R.INPUT_SIZE - 1), "-c", "2", unit=3)
    assert rc != 0 and "illegal data address" in err.lower(), err
    rc, _, err = mbpoll(port, "-t", "0", "-r", "0", unit=3)
    assert rc != 0 and "illegal function" in err.lower(), err


# ------------------------------------------------------------------ robustness
def _read_ok(port):
    from pymodbus.client import ModbusTcpClient

    c = ModbusTcpClient("127.0.0.1", port=port, timeout=3)
    try:
        assert c.connect()
        r = c.read_input_registers(IR["map_version"].address, count=1, device_id=3)
        return not r.isError() and r.registers == [R.MAP_VERSION]
    finally:
        c.close()


def _send(port, payload: bytes, wait_reply: bool = False):
    with socket.create_connection(("127.0.0.1", port), timeout=2) as s:
        s.sendall(payload)
        if wait_reply:
            s.settimeout(0.01)
            try:
                s.recv(512)
            except (TimeoutError, ConnectionError):
                pass


def _mbap(tid, unit, pdu, length=None):
    return struct.pack(">HHHB", tid & 0xFFFF, 0, (len(pdu) + 1) if length is None else length, unit) + pdu


frames = st.one_of(
    st.binary(min_size=0, max_size=300),                                        # noise
    st.builds(lambda t, u, p: _mbap(t, u, p), st.integers(0, 65535), st.integers(0, 255),
              st.binary(min_size=0, max_size=260)),                             # random PDU
    st.builds(lambda t, u, fc, body: _mbap(t, u, bytes([fc]) + body), st.integers(0, 65535),
              st.sampled_from([0, 3, 4, 5, 9]),
              st.sampled_from([1, 2, 3, 4, 5, 6, 8, 15, 16, 17, 22, 23, 43, 0x80 | 3, 255]),
              st.binary(min_size=0, max_size=40)),                              # plausible functions
    st.builds(lambda t, u, p, n: _mbap(t, u, p, n), st.integers(0, 65535), st.integers(0, 255),
              st.binary(max_size=20), st.integers(0, 65535)),                   # lying lengths
)


@settings(max_examples=2500, deadline=None, suppress_health_check=list(HealthCheck), derandomize=True)
@given(payload=st.one_of(frames, st.lists(frames, min_size=2, max_size=6).map(b"".join)), reply=st.booleans())
def test_malformed_frames_never_stop_the_server(plant, payload, reply):
    port, stations = plant
    _send(port, payload, reply)
    _counter[0] += 1
    if _counter[0] % 500 == 0:
        assert _read_ok(port)


_counter = [0]


def test_server_alive_after_fuzzing_and_no_write_got_through(plant):
    port, stations = plant
    assert _read_ok(port)
    # random PDUs may contain well-formed writes: units 4 and 5 must still be untouched
    assert stations[4].monitor is None and stations[5].monitor is None
    rc, v, err = mbpoll(port, "-t", "3", "-r", "0", "-c", "3", unit=3)
    assert rc == 0, err
