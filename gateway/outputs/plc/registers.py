"""The one definition of the PLC register map (Modbus TCP): addresses, types, units, meaning.

The Modbus TCP server (``gateway/outputs/plc/server.py``) encodes and decodes registers
with the functions here, ``docs/registers.md`` is generated from the same tables (``python -m
gateway.outputs.plc.registers > docs/registers.md``; a test checks it is current) and
``hookwatch regmap STATION.yaml`` prints them for one station.

**Addresses never move.** Each table is cut into :class:`Block` s, each at a fixed base address
with a fixed size (used + reserved registers, at most one read). A register's address is its
block's base plus the registers before it *in its block*: a new value is appended at the end of a
block with reserved space (or in a new block), never inserted before an existing one. The shipped
map is frozen in ``tests/golden/plc_register_map.txt``; a test refuses any register that moved,
changed type or unit, vanished, or reuses a frozen address, and any addition not frozen yet
(``python -m gateway.outputs.plc.registers --freeze tests/golden/plc_register_map.txt`` appends it,
after :data:`MAP_MINOR` was bumped). :data:`MAP_VERSION` (input register 1) is the *major* version:
it changes only when an address moves or a meaning changes, which never happens within a major;
:data:`MAP_MINOR` (input register 123) counts the additions in reserved space within the major.
"""
from __future__ import annotations

import math
import re
import struct
import sys
from dataclasses import dataclass
from typing import Any

from ...core import catalog
from ...core.alarms import ALARMS, SHELVE_MAX_S
from ...core.command_rules import REJECT_CODES, SAMPLE_ID_MAX, check_sample_id, check_t_end, check_t_set
from ...core.method.rules import REASONS
from ...core.ports import StationLimits
from ...core.records import CommandKind
from ...plumbing import safeout
from .modbus_tcp.pdu import MAX_READ

#: major version of the register map (input register 1): changes only when an existing address,
#: type or meaning changes (a PLC program must then be changed): never within a major
MAP_VERSION = 4    # 4: the §5b forecast (end_p10/50/90_left, p_end, warn_reasons), status bit 14
#                    hook_due; `hook_replaced` takes sample_id/grade (registers added only)
#                  3: alarm enums in ISA-18.2 states (0–5), command codes 5–7, status bit 13 disk_ok
#                    2: headroom, t_cross, warning_alarm, status bits 10–12, test state 6 starting
#: minor version within the major (input register `map_minor`): counts additions in reserved space
MAP_MINOR = 1      # 1: `map_minor` itself; blocks with reserved space (reason counters of new
#                    method reasons in block `reasons_more`)
#                  0: the map 4 as shipped (tests/golden/plc_register_map.txt)

INPUT = "input"
HOLDING = "holding"
#: characters of the input register `test_id` (a test ID is UTC time, sample name ≤ 48, "-n": ≤ 73)
TEST_ID_REG_CHARS = 80

#: register counts of each type
SIZES = {"uint16": 1, "enum": 1, "bits": 1, "uint32": 2, "float32": 2, "string": SAMPLE_ID_MAX // 2,
         "string80": TEST_ID_REG_CHARS // 2}


@dataclass(frozen=True)
class Reg:
    name: str
    table: str          # input | holding
    address: int        # 0-based PDU address
    type: str           # uint16 | enum | bits | uint32 | float32 | string | string80
    unit: str
    doc: str
    allowed: str = ""   # holding registers: values a write may carry
    block: str = ""       # the Block it sits in

    @property
    def count(self) -> int:
        return SIZES[self.type]

    @property
    def reference(self) -> int:
        """Traditional 1-based reference (3xxxx input, 4xxxx holding)."""
        return (30001 if self.table == INPUT else 40001) + self.address


@dataclass(frozen=True)
class Block:
    """A fixed range of one table: ``size`` registers from ``base``, the used ones first, the rest
    reserved for values added later in the same major map version."""
    name: str
    table: str
    base: int
    size: int
    doc: str

    @property
    def end(self) -> int:
        return self.base + self.size


def _layout(blocks: tuple[Block, ...], specs: dict[str, list[tuple[Any, ...]]]) -> tuple[Reg, ...]:
    """The registers of ``blocks``, each block's laid out from its base in the order given. A map
    that breaks the rules fails here, at import: a block over its size or over one read, blocks
    that overlap, registers of a block that does not exist."""
    regs: list[Reg] = []
    unknown = set(specs) - {b.name for b in blocks}
    if unknown:
        raise ValueError(f"register map: registers in unknown blocks {sorted(unknown)}")
    for b, after in zip(blocks, blocks[1:]):
        if after.base < b.end:
            raise ValueError(f"register map: block {after.name} at {after.base} overlaps block "
                             f"{b.name} ({b.base}–{b.end - 1})")
    for b in blocks:
        if b.size > MAX_READ:
            raise ValueError(f"register map: block {b.name} has {b.size} registers, more than one "
                             f"read ({MAX_READ})")
        addr = b.base
        for name, typ, unit, doc, *rest in specs.get(b.name, []):
            regs.append(Reg(name, b.table, addr, typ, unit, doc, rest[0] if rest else "", b.name))
            addr += SIZES[typ]
        if addr > b.end:
            raise ValueError(
                f"register map: block {b.name} needs {addr - b.base} registers, it has {b.size}. "
                "Never grow a block into the next one or shift an address: put the new value in "
                "another block's reserved space or in a new block (docs/registers.md, Versioning)")
    return tuple(regs)


def reserved(blocks: tuple[Block, ...], regs: tuple[Reg, ...]) -> list[tuple[Block, int, int]]:
    """The reserved range (block, first, last address) at the end of each block that has one."""
    out = []
    for b in blocks:
        used = max((r.address + r.count for r in regs if r.block == b.name), default=b.base)
        if used < b.end:
            out.append((b, used, b.end - 1))
    return out


#: the status bits (input register `status`) of the door's own: composites of the state, the slot
#: records and the client; the flags of the state are the catalog's rows with a bit
_OWN_STATUS_BITS: tuple[tuple[int, str, str], ...] = (
    (0, "running", "a test is running (baseline search, monitoring or end of life)"),
    (1, "baseline_found", "the baseline μ_ss of the current test is established"),
    (2, "end_of_life", "end of life latched for the current / last test (until a new test starts)"),
    (3, "alarm_unacknowledged", "the end-of-life alarm is unacknowledged or rtn_unacknowledged (ISA-18.2)"),
    (7, "mqtt_connected", "the gateway is connected to the MQTT broker"),
    (8, "saturation", "the control output was clamped during the last second"),
    (9, "writes_enabled", "this client may write the holding registers"),
    (12, "starting", "a start is in progress: zero check or spin-up before slot 0 (METHOD.md §3a)"),
)


def status_bits(values: tuple[catalog.Value, ...] = catalog.CATALOG) -> tuple[tuple[int, str, str], ...]:
    """The status bits in bit order: the door's own and each catalog row's (a bit taken twice
    fails here, at import)."""
    bits = list(_OWN_STATUS_BITS) + [(v.plc_bit.bit, v.plc_bit.name, v.plc_bit.doc)
                                     for v in values if v.plc_bit is not None]
    taken = [b for b, _, _ in bits]
    if len(set(taken)) != len(taken):
        raise ValueError(f"register map: a status bit taken twice in {sorted(taken)}")
    return tuple(sorted(bits))


#: status bits (input register `status`)
STATUS_BITS = status_bits()
#: the catalog's flags by their status bit's name
STATUS_FLAGS = {v.plc_bit.name: v for v in catalog.CATALOG if v.plc_bit is not None}
#: bits of the input register `warn_reasons`: the early warning's reasons (§5b) once it fired
WARN_REASON_BITS: tuple[tuple[int, str, str], ...] = (
    (0, "headroom", "the headroom stayed under `h_warn` for `n_warn` windows (§5a)"),
    (1, "prior", "the chance of the end within the lead reached `p_due` (the life prior, §7a)"),
    (2, "trend", "the recent trend reaches μ_th within the lead (§5a t_cross)"),
)
WARN_REASON_BIT = {name: bit for bit, name, _ in WARN_REASON_BITS}
if tuple(n for _, n, _ in WARN_REASON_BITS) != catalog.WARN_REASONS:
    raise ValueError("register map: the warn_reasons bits are not the catalog's reasons in their order")
STATUS_BIT = {name: bit for bit, name, _ in STATUS_BITS}

ALARM_STATES = catalog.ALARM_STATES

#: command codes (holding register `command`, input register `last_command`)
COMMAND_CODES: tuple[tuple[int, str, str], ...] = (
    (0, "none", "no command yet"),
    (1, "start", "start a test with `sample_id`, `grade`, `t_set`, `t_end` from the holding registers"),
    (2, "stop", "stop the running test (it ends as aborted)"),
    (3, "ack", "acknowledge the active alarms (end of life and wear warning)"),
    (4, "setpoint", "(input register only) the last command was a write of `t_set`"),
    (5, "hook_replaced", "the worn hook was replaced: ends the running test, closes its alarms "
     "(ISA-18.2 `normal`), logs it (hooks.jsonl); the new hook's `sample_id` and `grade` from the "
     "holding registers (empty / the old one: `<old>-R<n>`)"),
    (6, "out_of_service", "both alarms out of service while a needle is being changed"),
    (7, "in_service", "return the alarms to service"),
    (8, "shelve", "shelve the alarm in `alarm_select` for `shelve_duration` s (ISA-18.2; only an "
     "annunciated alarm: unacknowledged, acknowledged or rtn_unacknowledged)"),
    (9, "unshelve", "end the shelving of the alarm in `alarm_select`"),
)
COMMAND_CODE = {name: code for code, name, _ in COMMAND_CODES}
#: values of the holding register `alarm_select`: 0 none, then the alarms of gateway.core.alarms.ALARMS
ALARM_SELECT: tuple[str, ...] = tuple(ALARMS)

#: the method reasons counted in block `reasons` (map 4.0), in their address order; a reason the
#: method adds later is counted in block `reasons_more`, appended in the method's order (REASONS)
REASONS_MAP4 = ("MISSING", "SATURATED", "LOW_TENSION", "JUMP", "RATIO_LOW", "RATIO_HIGH")


#: the catalog's rows by their input register (gateway/core/catalog.py): the values the station's
#: state fills
CATALOG_REGS = {v.plc.name: v for v in catalog.CATALOG if v.plc is not None}


def _cat(name: str) -> tuple[str, str, str, str]:
    """The input register of the catalog's row whose register is ``name``, placed here among
    the registers of its block (its address frozen)."""
    p = CATALOG_REGS[name].plc
    assert p is not None
    return (p.name, p.type, p.unit, p.doc)


#: the slot records' values this map serves, by register: the catalog's slot rows with one
SLOT_REGS = {v.plc.name: v for v in catalog.SLOT_CATALOG if v.plc is not None}


def _slot(name: str) -> tuple[str, str, str, str]:
    """The input register of the catalog's slot records' row whose register is ``name``, placed
    here among the registers of its block (its address frozen)."""
    p = SLOT_REGS[name].plc
    assert p is not None
    return (p.name, p.type, p.unit, p.doc)


def _reason_reg(name: str) -> tuple[str, str, str, str]:
    return (f"count_{name.lower()}", "uint32", "slots", f"slots of the current / last test with reason {name}")


INPUT_BLOCKS = (
    Block("status", INPUT, 0, 8, "liveness, map and software versions, test state, status bits, alarm"),
    Block("live", INPUT, 8, 28, "the latest slot and the figures of the current / last test"),
    Block("reasons", INPUT, 36, 12, "slots per method reason (the reasons of map 4.0)"),
    Block("wear", INPUT, 48, 5, "wear headroom, projected crossing, wear-warning alarm (§5a)"),
    Block("command", INPUT, 53, 3, "the outcome of the last command"),
    Block("run", INPUT, 56, 56, "sample ID and test ID of the current / last test"),
    Block("forecast", INPUT, 112, 11, "the end forecast of the running test (§5b)"),
    Block("map", INPUT, 123, 2, "the map's minor version; reserved space in the first 125 registers"),
    Block("reasons_more", INPUT, 128, 64, "slots per method reason added after map 4.0, in the "
          "method's order (32 counters)"),
    Block("more", INPUT, 200, 100, "input values added in a later 4.x map, in the order added"),
)

#: the registers of each input block, in address order: append, never insert
INPUT_SPECS: dict[str, list[tuple[Any, ...]]] = {
    "status": [
        ("heartbeat", "uint16", "s", "seconds since the station started, wrapping at 65535; updated "
         "by the station's own loop: a value that stops changing means the station is stuck"),
        ("map_version", "uint16", "", f"major version of this register map ({MAP_VERSION}): "
         "addresses never move within a major (see Versioning)"),
        ("sw_major", "uint16", "", "gateway software version, major"),
        ("sw_minor", "uint16", "", "gateway software version, minor"),
        ("sw_patch", "uint16", "", "gateway software version, patch"),
        _cat("test_state"),
        ("status", "bits", "", "status bits, see the table below"),
        _cat("alarm"),
    ],
    "live": [
        _slot("t1"), _slot("t2"), _slot("tension"), _slot("mu"),
        _cat("mu_ss"),
        _cat("mu_th"),
        _cat("t_set"),
        _slot("valid_ratio"), _slot("speed_cmd"), _slot("speed_act"),
        _cat("t_life"),
        ("elapsed", "uint32", "s", "time since the start of the current / last test"),
        _slot("slots"), _slot("valid_slots"),
    ],
    "reasons": [_reason_reg(n) for n in REASONS_MAP4],
    "wear": [_cat("headroom"), _cat("t_cross"), _cat("warning_alarm")],
    "command": [
        ("last_command", "enum", "", "last command carried out or refused: "
         + ", ".join(f"{c} {n}" for c, n, _ in COMMAND_CODES)),
        ("last_result", "uint16", "", "result of the last command: 0 ok, else the rejection code (table below)"),
        ("command_count", "uint16", "", "commands processed (accepted or refused), wrapping at 65535"),
    ],
    "run": [_cat("run_sample_id"), _cat("run_test_id")],
    "forecast": [_cat("end_p10_left"), _cat("end_p50_left"), _cat("end_p90_left"), _cat("p_end"),
                 _cat("warn_reasons"), _cat("lead")],
    "map": [
        ("map_minor", "uint16", "", f"minor version of this register map within the major `map_version` "
         f"({MAP_MINOR}): counts the registers added in reserved space; addresses never move within a major"),
    ],
    "reasons_more": [_reason_reg(n) for _, n in REASONS if n not in REASONS_MAP4],
}


def input_specs(values: tuple[catalog.Value, ...] = catalog.CATALOG,
                slots: tuple[catalog.SlotValue, ...] = catalog.SLOT_CATALOG) -> dict[str, list[tuple[Any, ...]]]:
    """The registers of each input block in address order: :data:`INPUT_SPECS`, then each catalog
    row's register that they do not place (the state's rows, then the slot records'), appended at
    the end of its block in the catalog's order (in the block's reserved space: no existing
    address moves)."""
    specs = {b: list(rows) for b, rows in INPUT_SPECS.items()}
    placed = {row[0] for rows in specs.values() for row in rows}
    for p in [v.plc for v in values] + [s.plc for s in slots]:
        if p is not None and p.name not in placed:
            specs.setdefault(p.block, []).append((p.name, p.type, p.unit, p.doc))
    return specs


def input_layout(values: tuple[catalog.Value, ...] = catalog.CATALOG,
                 slots: tuple[catalog.SlotValue, ...] = catalog.SLOT_CATALOG) -> tuple[Reg, ...]:
    """The input registers of :func:`input_specs` at their addresses (a block without room for
    them fails here, at import)."""
    return _layout(INPUT_BLOCKS, input_specs(values, slots))


INPUT_REGS = input_layout()

#: command codes a PLC may write (all but 0 none and 4 setpoint, which is a write of `t_set`)
_WRITABLE_CODES = [(c, n) for c, n, _ in COMMAND_CODES if n not in ("none", "setpoint")]

HOLDING_BLOCKS = (
    Block("command", HOLDING, 0, 1, "the command to carry out"),
    Block("next_test", HOLDING, 1, 21, "the setpoint and the plan of the next test"),
    Block("shelve", HOLDING, 22, 3, "the alarm and duration of the next shelve command"),
    Block("more", HOLDING, 25, 100, "holding values added in a later 4.x map, in the order added"),
)

#: the registers of each holding block, in address order: append, never insert
HOLDING_SPECS: dict[str, list[tuple[Any, ...]]] = {
    "command": [
        ("command", "uint16", "", "write a command code to execute it ("
         + ", ".join(f"{c} {n}" for c, n in _WRITABLE_CODES) + ", see Command codes); reads 0",
         ", ".join(str(c) for c, _ in _WRITABLE_CODES)),
    ],
    "next_test": [
        ("t_set", "float32", "N", "tension setpoint of the next test; writing it is the `setpoint` command "
         "(refused while a test runs); `start` uses it", "(0, 0.98 · meter full scale) N"),
        ("grade", "uint16", "", "needle grade of the next test: 0 none, i = the station's i-th grade "
         "(see `hookwatch regmap STATION.yaml`)", "0 … number of grades"),
        ("t_end", "uint32", "s", "planned duration of the next test; 0 = the station's default",
         "0 … 2592000"),
        ("sample_id", "string", "", f"sample ID of the next test, up to {SAMPLE_ID_MAX} ASCII characters, "
         "two per register (first character in the high byte), padded with 0", "printable ASCII, 0-padded"),
    ],
    "shelve": [
        ("alarm_select", "enum", "", "the alarm the next `shelve` / `unshelve` command acts on: 0 none, "
         + ", ".join(f"{i} {n}" for i, n in enumerate(ALARM_SELECT, 1)),
         "0 … " + str(len(ALARM_SELECT))),
        ("shelve_duration", "uint32", "s", "how long the next `shelve` command shelves the alarm, s "
         f"(at most {SHELVE_MAX_S:.0f}: one 12 h shift)", f"0 … {SHELVE_MAX_S:.0f}"),
    ],
}
HOLDING_REGS = _layout(HOLDING_BLOCKS, HOLDING_SPECS)

#: registers served per table: up to the last register used (reserved registers before it read 0,
#: addresses after it answer exception 02)
INPUT_SIZE = max(r.address + r.count for r in INPUT_REGS)
HOLDING_SIZE = max(r.address + r.count for r in HOLDING_REGS)
BLOCKS = INPUT_BLOCKS + HOLDING_BLOCKS
REG = {(r.table, r.name): r for r in INPUT_REGS + HOLDING_REGS}
IR = {r.name: r for r in INPUT_REGS}
HR = {r.name: r for r in HOLDING_REGS}


# ----------------------------------------------------------------------------- encoding
def software_version(v: str) -> tuple[int, int, int]:
    m = re.match(r"(\d+)(?:\.(\d+))?(?:\.(\d+))?", v or "")
    if not m:
        return 0, 0, 0
    return tuple(min(65535, int(x or 0)) for x in m.groups())  # type: ignore[return-value]


def _words32(b: bytes, word_order: str) -> tuple[int, int]:
    hi, lo = struct.unpack(">HH", b)
    return (hi, lo) if word_order == "big" else (lo, hi)


def encode_value(reg: Reg, value: Any, word_order: str = "big") -> list[int]:
    """Registers of one value (None → NaN for floats, 0 otherwise; integers clamped)."""
    t = reg.type
    if t == "float32":
        v = math.nan if value is None else float(value)
        if not math.isfinite(v) or abs(v) > 3.4028234e38:
            v = math.nan
        return list(_words32(struct.pack(">f", v), word_order))
    if t == "uint32":
        v = 0 if value is None or (isinstance(value, float) and not math.isfinite(value)) else int(round(value))
        return list(_words32(struct.pack(">I", min(max(v, 0), 0xFFFFFFFF)), word_order))
    if t in ("string", "string80"):
        n = 2 * reg.count
        raw = ("" if value is None else str(value)).encode("ascii", "replace")[:n]
        raw = raw.ljust(n, b"\0")
        return list(struct.unpack(f">{reg.count}H", raw))
    v = 0 if value is None else int(value)
    return [min(max(v, 0), 0xFFFF)]


def decode_value(reg: Reg, regs: list[int], word_order: str = "big") -> Any:
    t = reg.type
    if t in ("float32", "uint32"):
        a, b = regs[0], regs[1]
        hi, lo = (a, b) if word_order == "big" else (b, a)
        raw = struct.pack(">HH", hi, lo)
        return struct.unpack(">f" if t == "float32" else ">I", raw)[0]
    if t in ("string", "string80"):
        raw = struct.pack(f">{len(regs)}H", *regs)
        return raw
    return regs[0]


def decode_sample_id(raw: bytes) -> str | None:
    """The sample ID in its registers: ASCII, 0-padded; None if malformed (a 0 inside, not ASCII)."""
    s = raw.rstrip(b"\0")
    if b"\0" in s:
        return None
    try:
        text = s.decode("ascii")
    except UnicodeDecodeError:
        return None
    return text


def encode_table(regs: tuple[Reg, ...], size: int, values: dict[str, Any], word_order: str) -> list[int]:
    out = [0] * size
    for r in regs:
        if r.name in values:
            out[r.address:r.address + r.count] = encode_value(r, values[r.name], word_order)
    return out


def status_word(flags: dict[str, bool]) -> int:
    w = 0
    for name, on in flags.items():
        if on:
            w |= 1 << STATUS_BIT[name]
    return w


# ----------------------------------------------------------------------------- writes (pure)
#: Modbus exception codes a write can get before anything changes
EXC_ILLEGAL_ADDRESS = 2
EXC_ILLEGAL_VALUE = 3
#: … and after the station was asked (Modbus Application Protocol 1.1b3, 7)
EXC_DEVICE_FAILURE = 4
EXC_DEVICE_BUSY = 6

#: rejection codes (``last_result``) a PLC may retry later unchanged: the station is busy with a
#: running test, or the source sent more commands than its rate allows (Modbus 06 SERVER DEVICE BUSY)
BUSY_REJECTIONS = ("BUSY", "SETPOINT_LOCKED", "RATE_LIMITED")
#: rejection codes that are no refusal but a failure: the station did not answer (04)
FAILURE_REJECTIONS = ("NO_STATION",)
_REJECTION_NAME = {code: name for code, name, _ in REJECT_CODES}


def refusal_exception(code: int) -> int:
    """The Modbus exception a command refused with rejection ``code`` answers: 06 while a test
    keeps the station busy, 04 only when the station failed to answer, 03 for every other refusal
    (a value, or a command the station's state does not allow: retrying it unchanged cannot
    help). The detailed code stays in ``last_result``."""
    name = _REJECTION_NAME.get(code)
    if name in BUSY_REJECTIONS:
        return EXC_DEVICE_BUSY
    if name is None or name in FAILURE_REJECTIONS:
        return EXC_DEVICE_FAILURE
    return EXC_ILLEGAL_VALUE

#: the command codes that are commands (holding register ``command``)
COMMAND_KINDS = {COMMAND_CODE["start"]: CommandKind.START, COMMAND_CODE["stop"]: CommandKind.STOP,
                 COMMAND_CODE["ack"]: CommandKind.ACK, COMMAND_CODE["hook_replaced"]: CommandKind.HOOK_REPLACED,
                 COMMAND_CODE["out_of_service"]: CommandKind.OUT_OF_SERVICE,
                 COMMAND_CODE["in_service"]: CommandKind.IN_SERVICE,
                 COMMAND_CODE["shelve"]: CommandKind.SHELVE, COMMAND_CODE["unshelve"]: CommandKind.UNSHELVE}


def check_holding(name: str, val: Any, limits: StationLimits) -> str | None:
    """Is ``val`` (decoded) allowed in holding register ``name``? None if yes, else why not."""
    if name == "command":
        allowed = ", ".join(f"{c} {COMMAND_CODES[c][1]}" for c in sorted(COMMAND_KINDS))
        return None if val in COMMAND_KINDS else f"command code {val}; allowed: {allowed}"
    if name == "t_set":
        return check_t_set(val, limits)
    if name == "grade":
        n = len(limits.grades)
        return None if 0 <= val <= n else f"grade {val}; allowed: 0 … {n}"
    if name == "t_end":
        return None if val == 0 else check_t_end(val, limits.t_end_max_s)
    if name == "alarm_select":
        n = len(ALARM_SELECT)
        return None if 0 <= val <= n else f"alarm_select {val}; allowed: 0 … {n}"
    if name == "shelve_duration":
        return None if 0 <= val <= SHELVE_MAX_S else f"shelve_duration {val} s; allowed: 0 … {SHELVE_MAX_S:.0f}"
    if name == "sample_id":
        text = decode_sample_id(val)
        if text is None:
            return "sample_id: not 0-padded printable ASCII"
        return None if text == "" else check_sample_id(text, limits.sample_id_max)
    return f"{name} is not writable"


@dataclass(frozen=True)
class WritePlan:
    """What a write to the holding registers does, decided before anything changes.

    ``exception`` set: refuse the write with it (nothing changes; ``reason`` says why). Otherwise
    ``staged`` is the image to show at once (every register written except ``t_set`` and
    ``command``, which change only when the station accepts them), ``new`` the image once all is
    accepted, ``decoded`` the written registers' values."""
    exception: int | None
    reason: str = ""
    staged: tuple[int, ...] = ()
    new: tuple[int, ...] = ()
    decoded: tuple[tuple[str, Any], ...] = ()

    def value(self, name: str) -> Any:
        return dict(self.decoded)[name]

    def wrote(self, name: str) -> bool:
        return any(n == name for n, _ in self.decoded)


def plan_write(hr: list[int] | tuple[int, ...], address: int, values: list[int], word_order: str,
               limits: StationLimits) -> WritePlan:
    """Check a write of ``values`` at ``address`` against the register map and the command rules."""
    end = address + len(values)
    if address < 0 or end > HOLDING_SIZE or not values:
        return WritePlan(EXC_ILLEGAL_ADDRESS, f"registers {address}…{end - 1} outside 0…{HOLDING_SIZE - 1}")
    if any(not 0 <= v <= 0xFFFF for v in values):
        return WritePlan(EXC_ILLEGAL_VALUE, "a register value outside 0…65535")
    new = list(hr)
    new[address:end] = values
    touched = [r for r in HOLDING_REGS if r.address < end and address < r.address + r.count]
    for r in touched:
        if r.count == 2 and not (address <= r.address and r.address + r.count <= end):
            return WritePlan(EXC_ILLEGAL_ADDRESS, f"{r.name}: half of a 32-bit value")
    decoded: list[tuple[str, Any]] = []
    for r in touched:
        val = decode_value(r, new[r.address:r.address + r.count], word_order)
        err = check_holding(r.name, val, limits)
        if err:
            return WritePlan(EXC_ILLEGAL_VALUE, err, decoded=((r.name, val),))
        decoded.append((r.name, val))
    staged = list(new)
    for n in ("t_set", "command"):
        a, c = HR[n].address, HR[n].count
        staged[a:a + c] = hr[a:a + c]
    return WritePlan(None, "", tuple(staged), tuple(new), tuple(decoded))


def apply_register(hr: list[int] | tuple[int, ...], new: tuple[int, ...], name: str) -> list[int]:
    """``hr`` with holding register ``name`` taken from ``new`` (once the station accepted it)."""
    a, c = HR[name].address, HR[name].count
    out = list(hr)
    out[a:a + c] = new[a:a + c]
    return out


def start_args(hr: list[int] | tuple[int, ...], word_order: str, grades: tuple[str, ...]) -> dict[str, Any]:
    """The arguments of a start command from the staged holding registers."""
    def get(n: str) -> Any:
        r = HR[n]
        return decode_value(r, list(hr[r.address:r.address + r.count]), word_order)
    sid = decode_sample_id(get("sample_id")) or ""
    g = int(get("grade"))
    t_set = float(get("t_set"))
    t_end = int(get("t_end"))
    args: dict[str, Any] = {"sample_id": sid,
                            "t_set": float(f"{t_set:.7g}") if math.isfinite(t_set) else t_set}
    if 1 <= g <= len(grades):
        args["grade"] = grades[g - 1]
    if t_end:
        args["t_end"] = float(t_end)
    return args


def command_args(kind: CommandKind, hr: list[int] | tuple[int, ...], word_order: str,
                 grades: tuple[str, ...]) -> dict[str, Any]:
    """The arguments of command ``kind`` from the staged holding registers (the keys of
    gateway.station.command_desk.COMMAND_KEYS; its ``validate`` judges them like any other source's)."""
    if kind == CommandKind.START:
        return start_args(hr, word_order, grades)
    args: dict[str, Any] = {}
    if kind == CommandKind.HOOK_REPLACED:
        # the new hook's sample id and grade, when staged (the station derives `<old>-R<n>`
        # when the sample id is empty or still the old hook's)
        r = HR["sample_id"]
        sid = decode_sample_id(decode_value(r, list(hr[r.address:r.address + r.count]), word_order))
        if sid:
            args["sample_id"] = sid
        g = int(hr[HR["grade"].address])
        if 1 <= g <= len(grades):
            args["grade"] = grades[g - 1]
        return args
    if kind in (CommandKind.SHELVE, CommandKind.UNSHELVE):
        sel = int(hr[HR["alarm_select"].address])
        if 1 <= sel <= len(ALARM_SELECT):
            args["alarm"] = ALARM_SELECT[sel - 1]
        if kind == CommandKind.SHELVE:
            r = HR["shelve_duration"]
            args["duration_s"] = float(decode_value(r, list(hr[r.address:r.address + r.count]), word_order))
    return args


# ----------------------------------------------------------------------------- docs
EXCEPTIONS = (
    (1, "ILLEGAL FUNCTION", "a write when the station's YAML does not allow writes "
     "(`modbus_tcp.writes.enabled: false`, the default) or from a client address not in "
     "`modbus_tcp.writes.allowed_clients`; also coils / discrete inputs (not served)"),
    (2, "ILLEGAL DATA ADDRESS", "a register outside the map, or a write covering only part of a "
     "32-bit value"),
    (3, "ILLEGAL DATA VALUE", "a write of a value out of its allowed range (nothing changes); or a "
     "command the station refused for its value or because its state does not allow it (rejection "
     "codes " + ", ".join(f"{c} {n}" for c, n, _ in REJECT_CODES
                           if c and n not in BUSY_REJECTIONS + FAILURE_REJECTIONS)
     + " in `last_result`)"),
    (4, "SERVER DEVICE FAILURE", "only a real failure: the station did not answer the command in "
     "time (rejection code " + ", ".join(f"{c} {n}" for c, n, _ in REJECT_CODES if n in FAILURE_REJECTIONS)
     + " in `last_result`), or the server failed to serve the request"),
    (6, "SERVER DEVICE BUSY", "a valid command the station cannot take while a test runs (rejection "
     "codes " + ", ".join(f"{c} {n}" for c, n, _ in REJECT_CODES if n in BUSY_REJECTIONS)
     + " in `last_result`): retry once the test has ended"),
    (11, "GATEWAY TARGET FAILED TO RESPOND", "a unit ID no station on this port has"),
)


def _type_doc(r: Reg) -> str:
    return {"string": f"string ({r.count} registers)", "string80": f"string ({r.count} registers)",
            "enum": "uint16 (enum)",
            "bits": "uint16 (bits)"}.get(r.type, r.type)


def _span(first: int, last: int) -> str:
    return f"{first}" if first == last else f"{first}–{last}"


def _n_regs(n: int) -> str:
    return f"{n} register" + ("s" if n != 1 else "")


def _ref(table: str, address: int) -> int:
    return (30001 if table == INPUT else 40001) + address


def _with_reserved(blocks: tuple[Block, ...], regs: tuple[Reg, ...]) -> list[Reg | tuple[Block, int, int]]:
    """The registers in address order with each block's reserved range (block, first, last) after them."""
    out: list[Reg | tuple[Block, int, int]] = []
    free = {b.name: (b, first, last) for b, first, last in reserved(blocks, regs)}
    for b in blocks:
        out += [r for r in regs if r.block == b.name]
        if b.name in free:
            out.append(free[b.name])
    return out


def _versioning() -> list[str]:
    return [
        "## Versioning: addresses never move",
        "",
        "For PLC engineers: a PLC program written for map version "
        f"{MAP_VERSION}.x keeps reading the right values from every later {MAP_VERSION}.y.",
        "",
        f"- **Major** (`map_version`, input register {IR['map_version'].address}): changes only when "
        "an existing register moves, changes its type, unit or meaning, or is removed. That never "
        "happens within a major version. A PLC program may check `map_version` once at start-up "
        "and refuse to run on another major.",
        f"- **Minor** (`map_minor`, input register {IR['map_minor'].address}): counts additions within "
        "the major: a new value goes into the reserved space at the end of a block (or into a new "
        "block at addresses no block uses), never before an existing register. A register a PLC "
        "program does not know is simply not read; a register of a later minor reads 0 on an "
        "earlier gateway, or answers exception 02 beyond the table's last register. Status bits, "
        "warning-reason bits and command codes follow the same rule: a new one takes a free "
        "number, an existing one keeps its number.",
        "- A register that loses its value keeps its address (it then reads 0, or NaN as a float).",
        "- Each block fits one read (at most 125 registers), so a PLC program can read a whole "
        "block with one request. The first 125 input registers (0–124) hold the map as shipped "
        "with map 4.0 and can still be read in one request.",
        "- The gateway's tests compare the map with the frozen map of every released version "
        "(`tests/golden/plc_register_map.txt`) and fail on any moved, re-typed or reused address.",
        "",
    ]


def _blocks_doc() -> list[str]:
    out = ["## Blocks", "", "| table | block | addresses | used | reserved | holds |", "|---|---|---|---|---|---|"]
    for blocks, regs in ((INPUT_BLOCKS, INPUT_REGS), (HOLDING_BLOCKS, HOLDING_REGS)):
        free = {b.name: last - first + 1 for b, first, last in reserved(blocks, regs)}
        for b in blocks:
            used = b.size - free.get(b.name, 0)
            out.append(f"| {b.table} | `{b.name}` | {_span(b.base, b.end - 1)} | {used} | "
                       f"{free.get(b.name, 0)} | {b.doc} |")
    out += ["", "Addresses outside every block are not assigned; a later minor version may place a "
            "new block there.", ""]
    return out


def rows(station: dict[str, Any] | None = None) -> list[dict[str, Any]]:
    """The map as rows (csv / md), for one station if given."""
    out = []
    pre = ({"station": station["id"], "unit_id": station["unit_id"], "word_order": station["word_order"]}
           if station else {})
    for r in INPUT_REGS + HOLDING_REGS:
        out.append({**pre, "table": r.table, "block": r.block, "address": r.address, "reference": r.reference,
                    "count": r.count, "name": r.name, "type": r.type, "unit": r.unit, "allowed": r.allowed,
                    "meaning": r.doc})
    return out


def render(station: dict[str, Any] | None = None) -> str:
    """Markdown of the register map; with ``station`` (unit id, host, port, word order, writes,
    grades) the header describes that station."""
    out = ["# PLC register map (Modbus TCP)", ""]
    if station is None:
        out += ["Generated from `gateway/outputs/plc/registers.py` (`python -m "
                "gateway.outputs.plc.registers > docs/registers.md`); do not edit by hand. "
                "`hookwatch regmap STATION.yaml [--format md|csv]` prints it for one station.", ""]
    out += [f"Register map version **{MAP_VERSION}.{MAP_MINOR}**: major {MAP_VERSION} in input register "
            f"{IR['map_version'].address} (`map_version`), minor {MAP_MINOR} in input register "
            f"{IR['map_minor'].address} (`map_minor`). Addresses never move within a major version "
            "(see Versioning).", ""]
    if station is not None:
        md = safeout.md_text           # the configuration's strings, shown as text
        out += [f"Station **{md(station['id'])}**: Modbus TCP server {md(station['host'])}:{station['port']}, "
                f"unit ID **{station['unit_id']}**, {md(station['word_order'])}-endian word order, writes "
                + (f"allowed from {md(', '.join(station['allowed_clients'])) or 'no client'}"
                   if station['writes'] else "disabled") + ".", ""]
        grades = station.get("grades") or []
        if grades:
            out += ["Grades (holding register `grade`): 0 none, " +
                    ", ".join(f"{i} {md(g)}" for i, g in enumerate(grades, 1)) + ".", ""]
    out += [
        "## Conventions",
        "",
        "- Addresses are 0-based PDU addresses (mbpoll `-0`); the reference column is the "
        "traditional 1-based number (3xxxx input, 4xxxx holding; mbpoll without `-0` uses "
        "address + 1).",
        "- 32-bit values (float32 IEEE 754, uint32) take two registers. Word order is configurable "
        "per station (`modbus_tcp.word_order`): `big` (default) puts the high word first "
        "(mbpoll `-B`), `little` the low word first. Bytes within a register are always "
        "big-endian.",
        "- A value that is not known is NaN (float32) or 0 (integers).",
        "- Each table is cut into blocks (see Blocks): a register's block and address never change "
        "within a major map version.",
        "- Several stations on one box share a server (one host:port) and each answers on its own "
        "unit ID (`modbus_tcp.unit_id`).",
        "- Live values are refreshed by the station's loop about 10 times a second and on every "
        "state change; the heartbeat counts seconds.",
        "- The server answers at most 4000 requests per second in total (all clients and units "
        "together); requests beyond that wait a few milliseconds. It runs in its own thread at a "
        "lower OS priority than the stations: PLC polling never delays a slot.",
        "",
        *_versioning(),
        *_blocks_doc(),
        "## Input registers (function 04, read only)",
        "",
        "| block | address | reference | name | type | unit | meaning |",
        "|---|---|---|---|---|---|---|",
    ]
    for r in _with_reserved(INPUT_BLOCKS, INPUT_REGS):
        if not isinstance(r, Reg):
            b, first, last = r
            out.append(f"| {b.name} | {_span(first, last)} | {_ref(INPUT, first)} | *reserved* | | | "
                       f"{_n_regs(last - first + 1)} for values added within major {MAP_VERSION} |")
        else:
            out.append(f"| {r.block} | {_span(r.address, r.address + r.count - 1)} | {r.reference} | "
                       f"`{r.name}` | {_type_doc(r)} | {r.unit} | {r.doc} |")
    out += ["", "### Status bits (`status`)", "", "| bit | name | meaning |", "|---|---|---|"]
    for bit, name, doc in STATUS_BITS:
        out.append(f"| {bit} | `{name}` | {doc} |")
    out += ["", "### Early-warning reasons (`warn_reasons`)", "", "| bit | reason | meaning |",
            "|---|---|---|"]
    for bit, name, doc in WARN_REASON_BITS:
        out.append(f"| {bit} | `{name}` | {doc} |")
    out += [
        "",
        "## Holding registers (functions 03 read, 06 / 16 / 23 write)",
        "",
        "| block | address | reference | name | type | unit | allowed on write | meaning |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in _with_reserved(HOLDING_BLOCKS, HOLDING_REGS):
        if not isinstance(r, Reg):
            b, first, last = r
            out.append(f"| {b.name} | {_span(first, last)} | {_ref(HOLDING, first)} | *reserved* | | | | "
                       f"{_n_regs(last - first + 1)} for values added within major {MAP_VERSION} |")
        else:
            out.append(f"| {r.block} | {_span(r.address, r.address + r.count - 1)} | {r.reference} | "
                       f"`{r.name}` | {_type_doc(r)} | {r.unit} | {r.allowed} | {r.doc} |")
    out += [
        "",
        "Writes are off unless the station's YAML allows them (`modbus_tcp.writes.enabled: true`) "
        "and then only from the client addresses in `modbus_tcp.writes.allowed_clients`. Every "
        "value of a write is checked before anything changes; a multi-register write is applied "
        "in address order with the `command` register last. Commands from a PLC go through the "
        "same validation and the same command path as MQTT commands (source `plc:<address>`), "
        "with the same events.",
        "",
        "A register write has no request id: **each write of the `command` register is one "
        "command, carried out once** (the register reads 0 again). A Modbus TCP retry of a write "
        "whose answer was lost is a second command: before resending, read `command_count` (it "
        "counts every command processed) and `last_command`/`last_result` — if the count moved "
        "past the value read before the write, the write arrived. A repeated command cannot do "
        "harm twice: a second stop finds no test (2 NOT_RUNNING), a second start a running one "
        "(1 BUSY), a second hook replaced with the `sample_id` still staged (now the station's own) no "
        "alarm and no test (3 NO_ALARM). A stop written here names no test: it ends the test "
        "running when it arrives (`run_test_id`); MQTT, Sparkplug and the console can name the "
        "test a stop means (`test_id`: a stop for a test that already ended is refused, 15 "
        "WRONG_TEST). More than 20 commands at once or 60 a minute from one PLC address, carried "
        "out or refused alike, are refused (14 RATE_LIMITED, exception 06).",
        "",
        "To start a test: write `sample_id`, `grade`, `t_end` (optional) and `t_set`, then 1 to "
        "`command`. Read `last_command`, `last_result` and `command_count` to see the outcome.",
        "",
        "When a hook is replaced: write the new hook's `sample_id` (and `grade`), then 5 to "
        "`command`: the running test ends, the alarms close and the replacement is logged.",
        "",
        "To shelve an alarm (ISA-18.2): write `alarm_select` (1 end_of_life, 2 wear_warning) and "
        "`shelve_duration` (s), then 8 to `command`; 9 with `alarm_select` unshelves it. The alarm "
        "states are in `alarm` and `warning_alarm` (4 shelved); the shelving ends by itself at its "
        "expiry. A refused shelve (no alarm selected: 11, duration 0 or too long: 12, an alarm "
        "that is not annunciated: 13) answers exception 03 and leaves the code in `last_result`.",
        "",
        "## Command codes",
        "",
        "| code | command | meaning |",
        "|---|---|---|",
    ]
    for code, name, doc in COMMAND_CODES:
        out.append(f"| {code} | {name} | {doc} |")
    out += ["", "## Rejection codes (`last_result`)", "", "| code | name | meaning |", "|---|---|---|"]
    for code, name, doc in REJECT_CODES:
        out.append(f"| {code} | {name} | {doc} |")
    out += ["", "## Exception responses", "", "| code | name | when |", "|---|---|---|"]
    for code, name, doc in EXCEPTIONS:
        out.append(f"| {code:02d} | {name} | {doc} |")
    out += [
        "",
        "## Examples (mbpoll)",
        "",
        "```sh",
        "# heartbeat, map version, software version, test state, status, alarm",
        "mbpoll -m tcp -p 5020 -a 1 -0 -t 3 -r 0 -c 8 -1 127.0.0.1",
        "# T1, T2, tension, mu, mu_ss, mu_th as float32 (big-endian words)",
        f"mbpoll -m tcp -p 5020 -a 1 -0 -t 3:float -B -r {IR['t1'].address} -c 6 -1 127.0.0.1",
        "# set the setpoint of the next test to 0.5 N, then start it",
        f"mbpoll -m tcp -p 5020 -a 1 -0 -t 4:float -B -r {HR['t_set'].address} 127.0.0.1 0.5",
        f"mbpoll -m tcp -p 5020 -a 1 -0 -t 4 -r {HR['command'].address} 127.0.0.1 1",
        "# shelve the wear warning (alarm_select 2) for one hour",
        f"mbpoll -m tcp -p 5020 -a 1 -0 -t 4 -r {HR['alarm_select'].address} 127.0.0.1 2",
        f"mbpoll -m tcp -p 5020 -a 1 -0 -t 4:int -B -r {HR['shelve_duration'].address} 127.0.0.1 3600",
        f"mbpoll -m tcp -p 5020 -a 1 -0 -t 4 -r {HR['command'].address} 127.0.0.1 8",
        "```",
        "",
    ]
    return "\n".join(out)


def render_csv(station: dict[str, Any] | None = None) -> str:
    """The register map as CSV, every cell defused against spreadsheet formulas (gateway.plumbing.safeout)."""
    rs = rows(station)
    keys = list(rs[0].keys())
    ident = ({"station": station["id"], "unit_id": station["unit_id"],
              "word_order": station["word_order"]} if station else {})
    bits = [{**ident, "table": f"input.{reg}", "block": IR[reg].block, "address": IR[reg].address,
             "reference": IR[reg].reference, "count": 1, "name": f"bit{bit}:{name}", "type": "bit", "unit": "",
             "allowed": "", "meaning": doc}
            for reg, table in (("status", STATUS_BITS), ("warn_reasons", WARN_REASON_BITS))
            for bit, name, doc in table]
    return safeout.csv_text([keys, *([r.get(k) for k in keys] for r in [*rs, *bits])], line_end="\n")


# ----------------------------------------------------------------------------- the frozen map
#: where the shipped map is frozen (tests/golden/plc_register_map.txt, relative to the tree)
GOLDEN = "tests/golden/plc_register_map.txt"
_RULE = ("addresses never move within a major map version: add a value at the end of a block with "
         "reserved space or in a new block, never before an existing register (docs/registers.md, "
         "Versioning). Changing a frozen register is a new major version, agreed with the PLC "
         "engineers, with a new golden file")


def golden_lines(input_regs: tuple[Reg, ...] | None = None) -> list[str]:
    """The current map as the lines of the golden file: one per register (table, block, address,
    count, type, unit, name), per bit (``bit``, register, bit, name), per command code."""
    out = ["\t".join((r.table, r.block, str(r.address), str(r.count), r.type, r.unit or "-", r.name))
           for r in (INPUT_REGS if input_regs is None else input_regs) + HOLDING_REGS]
    out += [f"bit\t{reg}\t{b}\t{n}" for reg, table in (("status", STATUS_BITS), ("warn_reasons", WARN_REASON_BITS))
            for b, n, _ in table]
    out += [f"code\tcommand\t{c}\t{n}" for c, n, _ in COMMAND_CODES]
    return out


def _parse(lines: list[str]) -> tuple[dict[tuple[str, str], list[str]], dict[tuple[str, str, str], str]]:
    regs, marks = {}, {}
    for line in lines:
        f = line.rstrip("\n").split("\t")
        if line.startswith("#") or not line.strip():
            continue
        if f[0] in (INPUT, HOLDING) and len(f) == 7:
            regs[(f[0], f[6])] = f
        elif len(f) == 4:
            marks[(f[0], f[1], f[3])] = f[2]
    return regs, marks


def _compare(golden: str, input_regs: tuple[Reg, ...] | None = None
             ) -> tuple[list[str], list[str], list[tuple[int, int]]]:
    """(problems with the frozen entries, current lines not frozen yet, the frozen versions)."""
    versions = [(int(v.partition(".")[0]), int(v.partition(".")[2] or 0))
                for v in (ln.split()[2] for ln in golden.splitlines() if ln.startswith("# map_version "))]
    regs, marks = _parse(golden.splitlines())
    lines = golden_lines(input_regs)
    cur, cur_marks = _parse(lines)
    problems = []
    for key, g in regs.items():
        c = cur.get(key)
        label = f"{g[0]} register `{g[6]}` (block {g[1]}, address {g[2]})"
        if c is None:
            problems.append(f"{label} is gone: a frozen register keeps its place (0 / NaN when it has no value)")
        elif c != g:
            what = ", ".join(f"{n} {g[i]} → {c[i]}" for i, n in enumerate(("", "block", "address", "count",
                                                                            "type", "unit"))
                             if i and g[i] != c[i])
            problems.append(f"{label} changed: {what}")
    taken = {(g[0], a): g[6] for g in regs.values() for a in range(int(g[2]), int(g[2]) + int(g[3]))}
    new = []
    for key, c in cur.items():
        if key in regs:
            continue
        hits = sorted({taken[(c[0], a)] for a in range(int(c[2]), int(c[2]) + int(c[3])) if (c[0], a) in taken})
        if hits:
            problems.append(f"{c[0]} register `{c[6]}` at {c[2]} reuses the frozen address of "
                            + ", ".join(f"`{h}`" for h in hits))
        else:
            new.append("\t".join(c))
    numbers = {(k[0], k[1], n): k[2] for k, n in marks.items()}
    for (kind, reg, name), n in marks.items():
        now = cur_marks.get((kind, reg, name))
        label = f"{reg} {kind} `{name}` ({n})"
        if now is None:
            problems.append(f"{label} is gone: a frozen {kind} keeps its number")
        elif now != n:
            problems.append(f"{label} moved to {now}")
    for (kind, reg, name), n in cur_marks.items():
        if (kind, reg, name) in marks:
            continue
        if (kind, reg, n) in numbers:
            problems.append(f"{reg} {kind} {n} `{name}` reuses the frozen {kind} of `{numbers[(kind, reg, n)]}`")
        else:
            new.append(f"{kind}\t{reg}\t{n}\t{name}")
    if {m for m, _ in versions} != {MAP_VERSION}:
        problems.append(f"map_version is {MAP_VERSION}, the golden file freezes map "
                        f"{sorted({m for m, _ in versions})}")
    return problems, new, versions


def frozen_problems(golden: str, input_regs: tuple[Reg, ...] | None = None) -> list[str]:
    """What keeps the current map (or one with ``input_regs``) from the frozen one (the golden
    file's text): moved, re-typed, vanished or reused registers, bits and codes; additions not
    frozen yet; a minor version that does not match. Empty when the map keeps every frozen address."""
    problems, new, versions = _compare(golden, input_regs)
    out = [f"PLC register map: {p}. {_RULE}" for p in problems]
    last = max((n for _, n in versions), default=0)
    if new:
        added = "; ".join(n.replace("\t", " ") for n in new)
        out.append(f"PLC register map: not frozen yet: {added}. Once final, bump MAP_MINOR past {last} and "
                   f"append them: python -m gateway.outputs.plc.registers --freeze {GOLDEN}")
    elif MAP_MINOR != last:
        out.append(f"PLC register map: MAP_MINOR is {MAP_MINOR}, the golden file's last frozen minor is {last}")
    return out


def freeze(golden: str) -> str:
    """The lines to append to the golden file: the additions, under their minor version. Refuses
    (ValueError) when a frozen entry changed or MAP_MINOR was not bumped past the last frozen."""
    problems, new, versions = _compare(golden)
    if problems:
        raise ValueError("; ".join(problems) + ". " + _RULE)
    last = max((n for _, n in versions), default=0)
    if not new:
        return ""
    if MAP_MINOR <= last:
        raise ValueError(f"bump MAP_MINOR past {last} first (the additions are map {MAP_VERSION}.{last + 1})")
    return f"# map_version {MAP_VERSION}.{MAP_MINOR} added\n" + "".join(ln + "\n" for ln in new)


def _main(argv: list[str]) -> int:
    if argv[:1] == ["--freeze"] and len(argv) == 2:
        with open(argv[1], encoding="utf-8") as f:
            text = f.read()
        try:
            add = freeze(text)
        except ValueError as e:
            print(f"not frozen: {e}", file=sys.stderr)
            return 1
        with open(argv[1], "a", encoding="utf-8") as f:
            f.write(add)
        print(add or "nothing to freeze", end="" if add else "\n")
        return 0
    if argv:
        print("usage: python -m gateway.outputs.plc.registers [--freeze GOLDEN]", file=sys.stderr)
        return 2
    print(render(), end="")
    return 0


if __name__ == "__main__":
    sys.exit(_main(sys.argv[1:]))
