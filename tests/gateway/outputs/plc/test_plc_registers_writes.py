"""The PLC's holding-register writes, decided purely (no socket, no server): the register map and
the station's command rules give the Modbus exception or the staged image."""
import struct

from gateway.core.ports import StationLimits
from gateway.core.records import CommandKind
from gateway.outputs.plc import registers as R

HR = R.HR
LIM = StationLimits(full_scale=10.0, grades=("A", "B"))


def _blank():
    return [0] * R.HOLDING_SIZE


def _f32(x):
    return list(struct.unpack(">2H", struct.pack(">f", x)))


def test_a_setpoint_within_the_station_limits_is_staged_until_accepted():
    hr = _blank()
    p = R.plan_write(hr, HR["t_set"].address, _f32(6.0), "big", LIM)
    assert p.exception is None and p.value("t_set") == 6.0
    a = HR["t_set"].address
    assert list(p.staged[a:a + 2]) == [0, 0] and list(p.new[a:a + 2]) == _f32(6.0)
    assert R.apply_register(hr, p.new, "t_set")[a:a + 2] == _f32(6.0)


def test_out_of_range_values_and_addresses_are_refused_before_anything_changes():
    hr = _blank()
    p = R.plan_write(hr, HR["t_set"].address, _f32(9.9), "big", LIM)
    assert p.exception == R.EXC_ILLEGAL_VALUE and "allowed: (0, 9.8) N" in p.reason
    assert R.plan_write(hr, HR["t_set"].address + 1, [0], "big", LIM).exception == R.EXC_ILLEGAL_ADDRESS
    assert R.plan_write(hr, R.HOLDING_SIZE, [0], "big", LIM).exception == R.EXC_ILLEGAL_ADDRESS
    assert R.plan_write(hr, HR["grade"].address, [3], "big", LIM).exception == R.EXC_ILLEGAL_VALUE
    assert R.plan_write(hr, HR["command"].address, [99], "big", LIM).exception == R.EXC_ILLEGAL_VALUE
    assert R.plan_write(hr, HR["sample_id"].address, [0x0101], "big", LIM).exception == R.EXC_ILLEGAL_VALUE


def test_start_arguments_come_from_the_staged_registers():
    hr = _blank()
    raw = list(struct.unpack(">16H", b"S-42".ljust(32, b"\0")))
    hr[HR["sample_id"].address:HR["sample_id"].address + 16] = raw
    hr[HR["grade"].address] = 2
    hr[HR["t_set"].address:HR["t_set"].address + 2] = _f32(6.0)
    p = R.plan_write(hr, HR["command"].address, [1], "big", LIM)
    assert p.exception is None and R.COMMAND_KINDS[p.value("command")] == CommandKind.START
    assert R.start_args(p.new, "big", LIM.grades) == {"sample_id": "S-42", "t_set": 6.0, "grade": "B"}
