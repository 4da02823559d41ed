"""ZN-S register map: the shipped maps load, every kind of bad map gets its own message, values
survive encode → decode for every type, word order, scale and decimal-point variant."""
import math
import os

import pytest
import yaml

from conftest import ROOT
from drivers.meter.meter_map import DEFAULT_MAP_PATH, DecodeError, MapError, crc16_modbus, load_map, map_from_dict

MAPS = os.path.join(ROOT, "config", "meters")


def write(tmp_path, data, name="m.yaml"):
    p = tmp_path / name
    p.write_text(data if isinstance(data, str) else yaml.safe_dump(data, sort_keys=False))
    return str(p)


def base_map(**top):
    d = {"unit_id": 1, "baud": 115200, "parity": "N", "function": 3, "address_base": 0,
         "channels": {"ch1": {"address": 0, "type": "float32"},
                      "ch2": {"address": 2, "type": "float32"}}}
    d.update(top)
    return d


def test_shipped_default_map():
    m = load_map(os.path.join(MAPS, "zn-s.yaml"))
    assert os.path.samefile(DEFAULT_MAP_PATH, os.path.join(MAPS, "zn-s.yaml"))
    assert (m.unit_id, m.baud, m.parity, m.stopbits, m.bytesize, m.function) == (1, 115200, "N", 1, 8, 3)
    assert m.read_block == (3, 0, 4)
    assert (m.request_bytes, m.response_bytes) == (8, 13)
    assert m.turnaround_s == pytest.approx(0.002)
    # 21 characters × 11 bits at 115200 + 2 ms turnaround
    assert m.poll_time_s() == pytest.approx(21 * 11 / 115200 + 0.002)
    assert m.ch1.type == m.ch2.type == "float32" and m.ch1.word_order == "big"


@pytest.mark.parametrize("name", sorted(f for f in os.listdir(MAPS) if f.endswith(".yaml")))
def test_every_example_map_loads_and_round_trips(name):
    m = load_map(os.path.join(MAPS, name))
    regs = m.encode(0.512, 3.25)
    assert len(regs) == m.read_block[2]
    assert m.decode(regs) == pytest.approx((0.512, 3.25), abs=1e-9)


def test_poll_time_table():
    m = load_map(DEFAULT_MAP_PATH)
    ms = {b: m.with_overrides(baud=b).poll_time_s() * 1e3 for b in (9600, 19200, 38400, 115200)}
    assert ms[9600] == pytest.approx(26.06, abs=0.01) and ms[9600] > 20.0
    assert ms[19200] == pytest.approx(14.03, abs=0.01)
    assert ms[38400] == pytest.approx(8.02, abs=0.01)
    assert ms[115200] == pytest.approx(4.01, abs=0.01)


def test_overrides_are_validated():
    m = load_map(DEFAULT_MAP_PATH)
    o = m.with_overrides(baud=19200, unit_id=7, parity="e")
    assert (o.baud, o.unit_id, o.parity) == (19200, 7, "E")
    assert m.with_overrides() is m
    with pytest.raises(MapError, match=r"baud: 12345 is not allowed; one of .*115200"):
        m.with_overrides(baud=12345)
    with pytest.raises(MapError, match=r"unit_id: 0 is not allowed; an integer 1..247"):
        m.with_overrides(unit_id=0)
    with pytest.raises(MapError, match=r"parity: 'X' is not allowed; N, E or O"):
        m.with_overrides(parity="X")


BAD = [
    # (top-level changes, channel changes, expected message fragment)
    ({"bogus": 1}, None, r"bogus: unknown key; allowed keys: model, .*channels"),
    ({"unit_id": 300}, None, r"unit_id: 300 is not allowed; an integer 1..247"),
    ({"unit_id": True}, None, r"unit_id: True is not allowed"),
    ({"baud": 1000}, None, r"baud: 1000 is not allowed; one of 1200, .*230400"),
    ({"baud": "fast"}, None, r"baud: 'fast' is not allowed"),
    ({"parity": "X"}, None, r"parity: 'X' is not allowed; N, E or O"),
    ({"parity": False}, None, r"parity: False is not allowed; N, E or O \(quote it"),
    ({"stopbits": 3}, None, r"stopbits: 3 is not allowed; 1 or 2"),
    ({"bytesize": 7}, None, r"bytesize: 7 is not allowed; 8 \(Modbus RTU"),
    ({"function": 1}, None, r"function: 1 is not allowed; 3 \(holding registers\) or 4"),
    ({"address_base": 2}, None, r"address_base: 2 is not allowed; 0 .* or 1"),
    ({"turnaround_ms": -1}, None, r"turnaround_ms: -1 is not allowed; a number of milliseconds"),
    ({"turnaround_ms": "2ms"}, None, r"turnaround_ms: '2ms' is not allowed"),
    ({"channels": None}, None, r"channels: missing; give ch1 and ch2"),
    ({"channels": [1, 2]}, None, r"channels: \[1, 2\] is not allowed; a mapping with ch1 and ch2"),
    ({"channels": {"ch1": {"address": 0}}}, None, r"channels.ch2: missing"),
    ({"channels": {"ch1": {"address": 0}, "ch2": {"address": 2}, "ch3": {"address": 4}}}, None,
     r"channels.ch3: unknown channel; allowed: ch1, ch2"),
    (None, {"colour": "red"}, r"channels.ch1.colour: unknown key; allowed keys: address, type"),
    (None, {"address": None}, r"channels.ch1.address: None is not allowed"),
    (None, {"address": -1}, r"channels.ch1.address: -1 is not allowed; an integer 0..65535"),
    (None, {"type": "int64"}, r"channels.ch1.type: 'int64' is not allowed; one of int16, uint16, int32, float32"),
    (None, {"word_order": "middle"}, r"channels.ch1.word_order: 'middle' is not allowed; big .* or little"),
    (None, {"type": "int16", "word_order": "big", "scale": 0.001},
     r"channels.ch1.word_order: only applies to 32-bit types"),
    (None, {"type": "int16"}, r"channels.ch1: int16 needs scale .* or decimals_register"),
    (None, {"scale": 0}, r"channels.ch1.scale: 0 is not allowed; a positive number"),
    (None, {"scale": 0.001, "decimals_register": 4}, r"channels.ch1: give either scale or decimals_register, not both"),
    (None, {"decimals": 3}, r"channels.ch1.decimals: only with decimals_register"),
    (None, {"type": "int16", "decimals_register": 4, "decimals": 9},
     r"channels.ch1.decimals: 9 is not allowed; an integer 0..6"),
    (None, {"address": 1}, r"channels.ch2.address: register 2 overlaps channels.ch1.address"),
    (None, {"address": 200}, r"channels: the registers span 200 registers from 2; one read \(FC3\) covers at most 125"),
]


@pytest.mark.parametrize("top,ch1,msg", BAD)
def test_bad_maps_get_specific_messages(tmp_path, top, ch1, msg):
    d = base_map()
    if top:
        d.update(top)
    if ch1:
        d["channels"]["ch1"].update(ch1)
    p = write(tmp_path, d)
    with pytest.raises(MapError, match=msg) as ei:
        load_map(p)
    assert str(ei.value).startswith(p + ": ")


def test_missing_and_broken_files(tmp_path):
    with pytest.raises(MapError, match=r"nope.yaml: register map file not found"):
        load_map(str(tmp_path / "nope.yaml"))
    p = write(tmp_path, "unit_id: [1\n")
    with pytest.raises(MapError, match=r"m.yaml: not valid YAML \(line \d+, column \d+\)"):
        load_map(p)
    p = write(tmp_path, "- 1\n- 2\n", "list.yaml")
    with pytest.raises(MapError, match=r"list.yaml: expected a mapping of keys"):
        load_map(p)


def test_decimals_registers_must_agree(tmp_path):
    d = base_map(channels={"ch1": {"address": 0, "type": "int16", "decimals_register": 2, "decimals": 3},
                           "ch2": {"address": 1, "type": "int16", "decimals_register": 2, "decimals": 2}})
    with pytest.raises(MapError, match=r"channels.ch2.decimals: 2 differs from 3 for the shared"):
        load_map(write(tmp_path, d))


def test_address_base_one(tmp_path):
    d = base_map(address_base=1, channels={"ch1": {"address": 1}, "ch2": {"address": 3}})
    m = load_map(write(tmp_path, d))
    assert m.read_block == (3, 0, 4)
    d["channels"]["ch1"]["address"] = 0
    with pytest.raises(MapError,
                       match=r"channels.ch1.address: 0 is not allowed; an integer 1..65536 \(address_base is 1\)"):
        load_map(write(tmp_path, d))


CHANNEL_VARIANTS = [
    ({"type": "float32", "word_order": "big"}, 1e-9),
    ({"type": "float32", "word_order": "little"}, 1e-9),
    ({"type": "float32", "scale": 0.5}, 1e-6),
    ({"type": "int32", "word_order": "big", "scale": 0.001}, 1e-9),
    ({"type": "int32", "word_order": "little", "scale": 0.001}, 1e-9),
    ({"type": "int16", "scale": 0.001}, 1e-9),
    ({"type": "uint16", "scale": 0.001}, 1e-9),
    ({"type": "int16", "decimals_register": 10, "decimals": 3}, 1e-9),
    ({"type": "uint16", "decimals_register": 10, "decimals": 2}, None),
    ({"type": "int32", "word_order": "little", "decimals_register": 10, "decimals": 3}, 1e-9),
]


@pytest.mark.parametrize("chan,tol", CHANNEL_VARIANTS)
def test_round_trip_each_type(chan, tol):
    c2 = dict(chan)
    m = map_from_dict(base_map(channels={"ch1": {"address": 0, **chan}, "ch2": {"address": 4, **c2}}))
    fc, start, count = m.read_block
    assert count == (11 if "decimals_register" in chan else 4 + m.ch2.width)
    for v1, v2 in [(0.0, 0.0), (0.5, 1.25), (0.4994, 4.9876), (2.0005, 0.001), (4.999, 3.333)]:
        regs = m.encode(v1, v2)
        assert all(0 <= r <= 0xFFFF for r in regs)
        d1, d2 = m.decode(regs)
        step = m.ch1.step_n
        assert d1 == pytest.approx(round(round(v1, 3) / step) * step, abs=tol or 1e-9)
        assert d2 == pytest.approx(round(round(v2, 3) / step) * step, abs=tol or 1e-9)


def test_word_order_layout():
    big = map_from_dict(base_map())
    little = map_from_dict(base_map(channels={"ch1": {"address": 0, "word_order": "little"},
                                              "ch2": {"address": 2, "word_order": "little"}}))
    rb = big.encode(1.5, 0.0)
    rl = little.encode(1.5, 0.0)
    assert rb[:2] == [0x3FC0, 0x0000]           # 1.5f = 0x3FC00000, high word first
    assert rl[:2] == [0x0000, 0x3FC0]
    i32 = map_from_dict(base_map(channels={"ch1": {"address": 0, "type": "int32", "scale": 0.001},
                                           "ch2": {"address": 2, "type": "int32", "word_order": "little",
                                                   "scale": 0.001}}))
    assert i32.encode(70.0, 70.0) == [0x0001, 0x1170, 0x1170, 0x0001]   # 70000 = 0x00011170


def test_quantise_and_clip():
    m = map_from_dict(base_map(channels={"ch1": {"address": 0, "type": "int16", "scale": 0.001},
                                         "ch2": {"address": 1, "type": "uint16", "scale": 0.01}}))
    assert m.decode(m.encode(40.0, -1.0)) == (32.767, 0.0)        # clipped to the type's range
    assert m.decode(m.encode(0.12345, 0.126)) == (0.123, 0.13)     # 1 mN, or the coarser 10 mN step
    assert m.decode(m.encode(math.inf, math.inf)) == (32.767, 655.35)
    with pytest.raises(ValueError, match="NaN"):
        m.encode(math.nan, 0.0)
    f = map_from_dict(base_map())
    a, b = f.decode(f.encode(0.12345678, math.nan))
    assert a == 0.123 and math.isnan(b)
    assert f.decode(f.encode(1e40, -1e40)) == pytest.approx((3.402823e38, -3.402823e38), rel=1e-6)


def test_decimal_point_register_is_read_live():
    m = map_from_dict(base_map(address_base=1,
                               channels={"ch1": {"address": 1, "type": "int16", "decimals_register": 5},
                                         "ch2": {"address": 2, "type": "int16", "decimals_register": 5}}))
    fc, start, count = m.read_block
    assert (start, count) == (0, 5)
    regs = m.encode(1.234, 0.5)
    assert regs == [1234, 500, 0, 0, 3]
    regs[4] = 1                                 # the meter was switched to one decimal
    assert m.decode(regs) == (123.4, 50.0)
    regs[4] = 0
    assert m.decode(regs) == (1234.0, 500.0)
    regs[4] = 9
    with pytest.raises(DecodeError, match=r"decimal-point register 4 holds 9; allowed 0..6"):
        m.decode(regs)
    with pytest.raises(DecodeError, match=r"expected 5 registers, got 4"):
        m.decode(regs[:4])


def test_crc16_modbus_known_vector():
    # read 4 holding registers from address 0 of unit 1: 01 03 00 00 00 04 | 44 09
    frame = bytes([1, 3, 0, 0, 0, 4])
    assert crc16_modbus(frame).to_bytes(2, "little") == bytes([0x44, 0x09])
