"""The PLC's holding-register writes, decided purely (no socket, no server): the register map and
the station's command rules give the Modbus exception or the staged image."""
import os
import struct
import subprocess
import sys

import pytest

from conftest import ROOT
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


# ----------------------------------------------------------------------------- addresses never move
def _golden():
    with open(os.path.join(ROOT, R.GOLDEN), encoding="utf-8") as f:
        return f.read()


def test_the_map_keeps_every_frozen_address():
    """Issue 35 item 3: the map as shipped (tests/golden/plc_register_map.txt, made from map 4 before
    blocks existed) is served unchanged: every register keeps its table, block, address, count,
    type and unit, every bit and command code its number; every addition is frozen too."""
    problems = R.frozen_problems(_golden())
    assert problems == [], "\n".join(problems)


def test_a_moved_register_fails_with_the_rule_for_the_developer(monkeypatch):
    specs = R.input_specs()
    specs["live"][0], specs["live"][1] = specs["live"][1], specs["live"][0]     # t2 before t1
    monkeypatch.setattr(R, "INPUT_REGS", R._layout(R.INPUT_BLOCKS, specs))
    problems = R.frozen_problems(_golden())
    assert any("input register `t1` (block live, address 8) changed: address 8 → 10" in p for p in problems)
    assert all("never before an existing register" in p for p in problems)
    with pytest.raises(ValueError, match="changed: address 8 → 10"):
        R.freeze(_golden())


def test_a_reused_or_vanished_address_fails(monkeypatch):
    specs = R.input_specs()
    specs["reasons"] = [R._reason_reg(n) for n in ("MISSING", "SATURATED", "LOW_TENSION", "WOBBLE",
                                                   "RATIO_LOW", "RATIO_HIGH")]
    monkeypatch.setattr(R, "INPUT_REGS", R._layout(R.INPUT_BLOCKS, specs))
    problems = "\n".join(R.frozen_problems(_golden()))
    assert "`count_jump` (block reasons, address 42) is gone" in problems
    assert "`count_wobble` at 42 reuses the frozen address of `count_jump`" in problems
    bits = list(R.STATUS_BITS)
    bits[13], bits[14] = (13, "hook_due", ""), (14, "disk_ok", "")
    monkeypatch.setattr(R, "STATUS_BITS", tuple(bits))
    problems = "\n".join(R.frozen_problems(_golden()))
    assert "status bit `hook_due` (14) moved to 13" in problems


def test_a_full_block_refuses_an_insertion_at_import():
    """A new method reason inserted among the map 4 counters would shift every later address: the
    block `reasons` has no room, so the map fails to build (at import) and says where values go."""
    specs = R.input_specs()
    specs["reasons"].insert(3, R._reason_reg("WOBBLE"))
    with pytest.raises(ValueError, match="block reasons needs 14 registers, it has 12.*new block"):
        R._layout(R.INPUT_BLOCKS, specs)
    with pytest.raises(ValueError, match="overlaps block"):
        R._layout((R.Block("a", "input", 0, 10, ""), R.Block("b", "input", 9, 2, "")), {})
    with pytest.raises(ValueError, match="more than one read"):
        R._layout((R.Block("a", "input", 0, 126, ""),), {})


def test_a_new_method_reason_and_a_new_value_are_added_without_moving_anything(monkeypatch):
    """A reason the method adds after map 4.0 is counted in block `reasons_more`, a new value
    goes to block `more`: nothing frozen moves; the additions must be frozen under a new minor
    (freezing refuses until MAP_MINOR is bumped), then the map matches the golden file again."""
    free = {b.name: max((r.address + r.count for r in R.INPUT_REGS if r.block == b.name), default=b.base)
            for b in R.INPUT_BLOCKS}          # the first reserved address of each block
    specs = R.input_specs()
    specs["reasons_more"] = specs.get("reasons_more", []) + [R._reason_reg("WOBBLE")]
    specs["more"] = specs.get("more", []) + [("t3", "float32", "N", "a third tension")]
    monkeypatch.setattr(R, "INPUT_REGS", R._layout(R.INPUT_BLOCKS, specs))
    regs = {r.name: r for r in R.INPUT_REGS}
    wobble, t3 = free["reasons_more"], free["more"]
    assert (regs["count_wobble"].address, regs["t3"].address) == (wobble, t3) and (wobble, t3) >= (128, 200)
    problems = R.frozen_problems(_golden())
    assert len(problems) == 1 and f"not frozen yet: input reasons_more {wobble} 2 uint32 slots count_wobble" \
        in problems[0] and "--freeze tests/golden/plc_register_map.txt" in problems[0]
    with pytest.raises(ValueError, match=f"bump MAP_MINOR past {R.MAP_MINOR}"):
        R.freeze(_golden())
    monkeypatch.setattr(R, "MAP_MINOR", R.MAP_MINOR + 1)
    added = R.freeze(_golden())
    assert added.splitlines()[0] == f"# map_version {R.MAP_VERSION}.{R.MAP_MINOR} added"
    assert R.frozen_problems(_golden() + added) == []


def test_blocks_fit_one_read_and_hold_their_registers():
    for blocks, regs in ((R.INPUT_BLOCKS, R.INPUT_REGS), (R.HOLDING_BLOCKS, R.HOLDING_REGS)):
        for b in blocks:
            mine = [r for r in regs if r.block == b.name]
            assert b.size <= 125 and all(b.base <= r.address and r.address + r.count <= b.end for r in mine)
            assert [r.address for r in mine] == sorted(r.address for r in mine)
    # the map as shipped (0–122) and the minor version still fit the first read of 125 registers
    # (what is added later goes to the blocks above: `reasons_more`, `more`)
    assert R.IR["map_minor"].address == 123 and R.HOLDING_SIZE <= 125
    assert all(b.end <= 125 for b in R.INPUT_BLOCKS if b.base < 125)
    assert {r.block for r in R.INPUT_REGS if r.address + r.count > 125} <= {"reasons_more", "more"}


def test_freeze_appends_only(tmp_path):
    path = tmp_path / "golden.txt"
    path.write_text(_golden())
    r = subprocess.run([sys.executable, "-m", "gateway.outputs.plc.registers", "--freeze", str(path)],
                       capture_output=True, text=True, timeout=60, cwd=ROOT)
    assert r.returncode == 0 and r.stdout == "nothing to freeze\n" and path.read_text() == _golden()
    path.write_text(_golden().replace("input\tlive\t8\t2\tfloat32\tN\tt1", "input\tlive\t8\t2\tfloat32\tmN\tt1"))
    r = subprocess.run([sys.executable, "-m", "gateway.outputs.plc.registers", "--freeze", str(path)],
                       capture_output=True, text=True, timeout=60, cwd=ROOT)
    assert r.returncode == 1 and "unit mN → N" in r.stderr and "new major version" in r.stderr
