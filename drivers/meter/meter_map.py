"""Register map of the ZN-S dual-channel yarn tension meter (Modbus RTU slave).

Pure: numbers in, numbers out. The same :class:`MeterMap` is used by the gateway's meter driver
(``drivers/meter/driver.py``, decode) and by the virtual meter (``drivers/sim/meter.py``, encode), so both
sides of the wire always agree. File format and wire timing: ``docs/protocols/zn-s.md``.

Example (the shipped default, ``config/meters/zn-s.yaml``)::

    unit_id: 1
    baud: 115200
    parity: N
    function: 3            # 3 holding registers, 4 input registers
    address_base: 0        # addresses below are protocol (PDU) addresses; 1 = "register 1" numbering
    turnaround_ms: 2.0
    channels:
      ch1: {address: 0, type: float32, word_order: big}
      ch2: {address: 2, type: float32, word_order: big}
"""
from __future__ import annotations

import math
import os
import struct
from collections.abc import Sequence
from dataclasses import dataclass, replace
from typing import Any

import gateway.plumbing.safeyaml as safeyaml
from gateway.core.validation import Problem, ValidationError, did_you_mean, key_text, suggestion_text

#: the repository's default map (the gateway's configuration model may point elsewhere)
DEFAULT_MAP_PATH = os.path.join(os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))),
                                "config", "meters", "zn-s.yaml")

BITS_PER_CHAR = 11                     # Modbus RTU character: start, 8 data, parity/2nd stop, stop
RESOLUTION_N = 0.001                   # the meter resolves 1 mN
BAUDS = (1200, 2400, 4800, 9600, 19200, 38400, 57600, 115200, 230400)
PARITIES = ("N", "E", "O")
FUNCTIONS = (3, 4)
MAX_READ_REGISTERS = 125               # Modbus limit for FC 3/4
MAX_DECIMALS = 6

#: type -> (registers, struct code, min, max)
DATA_TYPES: dict[str, tuple[int, str, float, float]] = {
    "int16": (1, "h", -0x8000, 0x7FFF),
    "uint16": (1, "H", 0, 0xFFFF),
    "int32": (2, "i", -0x80000000, 0x7FFFFFFF),
    "float32": (2, "f", -3.4028234663852886e38, 3.4028234663852886e38),
}
WORD_ORDERS = ("big", "little")

TOP_KEYS = ("model", "description", "unit_id", "baud", "parity", "stopbits", "bytesize",
            "function", "address_base", "turnaround_ms", "channels")
CHANNEL_NAMES = ("ch1", "ch2")
CHANNEL_KEYS = ("address", "type", "word_order", "scale", "decimals_register", "decimals")

DEFAULTS: dict[str, Any] = {"unit_id": 1, "baud": 115200, "parity": "N", "stopbits": 1,
                            "bytesize": 8, "function": 3, "address_base": 0, "turnaround_ms": 2.0}


class MapError(ValidationError):
    """A register map (or an override) is not valid; the message names file, key, value and what
    is allowed, and ``problem`` holds the same as data (file, key path, value, allowed)."""

    def __init__(self, text: str, problem: Problem | None = None):
        super().__init__(problem or Problem((), text), text=text)


class DecodeError(ValueError):
    """Registers read from the meter cannot be turned into tensions (e.g. a decimal-point register
    holding 9)."""


from ..serial.crc import crc16_modbus  # noqa: E402,F401  (re-exported: the meter's frames use it)


def with_crc(frame: bytes) -> bytes:
    return frame + crc16_modbus(frame).to_bytes(2, "little")


def crc_ok(frame: bytes) -> bool:
    return len(frame) >= 4 and crc16_modbus(frame[:-2]) == int.from_bytes(frame[-2:], "little")


# ---------------------------------------------------------------------------------- the map
@dataclass(frozen=True)
class ChannelMap:
    name: str                     # ch1 / ch2
    address: int                  # protocol (wire) address of the value's first register
    type: str                     # int16 | uint16 | int32 | float32
    word_order: str               # big (high word first) | little (low word first); 32-bit only
    scale: float | None           # N per count (None when a decimal-point register is used)
    decimals_register: int | None  # protocol address of the register holding the decimals
    decimals: int                 # what the virtual meter puts there (encode); decode reads it

    @property
    def width(self) -> int:
        return DATA_TYPES[self.type][0]

    @property
    def step_n(self) -> float:
        """Resolution of the encoded value, N (at least the meter's 0.001 N)."""
        if self.type == "float32":
            return RESOLUTION_N
        step = self.scale if self.scale is not None else 10.0 ** -self.decimals
        return max(step, RESOLUTION_N)


@dataclass(frozen=True)
class MeterMap:
    path: str
    unit_id: int
    baud: int
    parity: str
    stopbits: int
    bytesize: int
    function: int
    address_base: int
    turnaround_s: float
    ch1: ChannelMap
    ch2: ChannelMap
    model: str = "ZN-S"

    # ------------------------------------------------------------------ block and timing
    @property
    def channels(self) -> tuple[ChannelMap, ChannelMap]:
        return (self.ch1, self.ch2)

    def _spans(self) -> list[tuple[int, int, str]]:
        spans = [(c.address, c.width, f"channels.{c.name}.address") for c in self.channels]
        seen = set()
        for c in self.channels:
            if c.decimals_register is not None and c.decimals_register not in seen:
                seen.add(c.decimals_register)
                spans.append((c.decimals_register, 1, f"channels.{c.name}.decimals_register"))
        return spans

    @property
    def read_block(self) -> tuple[int, int, int]:
        """(function, first protocol address, register count): one read covers everything."""
        spans = self._spans()
        start = min(a for a, _, _ in spans)
        end = max(a + w for a, w, _ in spans)
        return self.function, start, end - start

    @property
    def request_bytes(self) -> int:
        return 8                    # unit, fc, address(2), count(2), crc(2)

    @property
    def response_bytes(self) -> int:
        return 5 + 2 * self.read_block[2]   # unit, fc, byte count, data, crc(2)

    def wire_time_s(self, n_bytes: int) -> float:
        return n_bytes * BITS_PER_CHAR / float(self.baud)

    def poll_time_s(self) -> float:
        """Request + turnaround + response on the wire at this map's baud (11 bits a character)."""
        return (self.wire_time_s(self.request_bytes) + self.turnaround_s
                + self.wire_time_s(self.response_bytes))

    # ------------------------------------------------------------------ values
    def decode(self, registers: Sequence[int]) -> tuple[float, float]:
        """Registers of :attr:`read_block` → (ch1, ch2) in N. Raises DecodeError on a bad block."""
        _, start, count = self.read_block
        if len(registers) != count:
            raise DecodeError(f"expected {count} registers, got {len(registers)}")
        out = []
        for c in self.channels:
            off = c.address - start
            raw = _unpack(c, registers[off:off + c.width])
            if c.decimals_register is not None:
                dp = int(registers[c.decimals_register - start])
                if not 0 <= dp <= MAX_DECIMALS:
                    raise DecodeError(f"{c.name}: decimal-point register {c.decimals_register} holds "
                                      f"{dp}; allowed 0..{MAX_DECIMALS}")
                out.append(raw / 10 ** dp if dp else float(raw))
            elif c.type == "float32":
                v = raw * c.scale if c.scale != 1.0 else raw  # type: ignore[operator]  # set for float32
                out.append(float(f"{v:.7g}") if math.isfinite(v) else v)
            else:
                out.append(round(raw * c.scale, 9))  # type: ignore[operator]  # no decimals_register
        return out[0], out[1]

    def encode(self, ch1: float, ch2: float) -> list[int]:
        """(ch1, ch2) in N → the full register block, quantised to the meter's resolution (0.001 N,
        or the coarser step of an integer type) and clipped to the type's range. Raises ValueError
        for NaN on an integer type."""
        _, start, count = self.read_block
        regs = [0] * count
        for c, v in zip(self.channels, (ch1, ch2)):
            off = c.address - start
            regs[off:off + c.width] = _pack(c, float(v))
            if c.decimals_register is not None:
                regs[c.decimals_register - start] = c.decimals
        return regs

    # ------------------------------------------------------------------ overrides
    def with_overrides(self, baud: int | None = None, unit_id: int | None = None,
                       parity: str | None = None) -> MeterMap:
        """A copy with the station's overrides (None = keep the map's value); validated."""
        kw: dict[str, Any] = {}
        where = f"{self.path} (station override)"
        if baud is not None:
            kw["baud"] = _check_baud(where, "baud", baud)
        if unit_id is not None:
            kw["unit_id"] = _check_unit(where, "unit_id", unit_id)
        if parity is not None:
            kw["parity"] = _check_parity(where, "parity", parity)
        return replace(self, **kw) if kw else self

    def describe(self) -> str:
        fc, a, n = self.read_block
        return (f"{self.model} unit {self.unit_id} @ {self.baud} {self.bytesize}{self.parity}"
                f"{self.stopbits}, FC{fc} address {a} count {n}, poll {self.poll_time_s() * 1e3:.2f} ms")


# ---------------------------------------------------------------------------------- packing
def _unpack(c: ChannelMap, regs: Sequence[int]) -> float:
    words = [int(r) & 0xFFFF for r in regs]
    if c.width == 2 and c.word_order == "little":
        words = words[::-1]
    raw = b"".join(w.to_bytes(2, "big") for w in words)
    return struct.unpack(">" + DATA_TYPES[c.type][1], raw)[0]


def _pack(c: ChannelMap, value: float) -> list[int]:
    _, code, lo, hi = DATA_TYPES[c.type]
    if c.type == "float32":
        if math.isnan(value):
            q = value
        else:
            q = round(min(max(value, lo), hi), 3) if math.isfinite(value) else (hi if value > 0 else lo)
            if c.scale not in (None, 1.0):
                q = q / c.scale  # type: ignore[operator]  # not None here
            q = min(max(q, lo), hi)
    else:
        if math.isnan(value):
            raise ValueError(f"{c.name}: cannot encode NaN as {c.type}")
        step = c.scale if c.scale is not None else 10.0 ** -c.decimals
        if math.isinf(value):
            q = hi if value > 0 else lo
        else:
            q = round(round(value, 3) / step)
            q = int(min(max(q, lo), hi))
    raw = struct.pack(">" + code, q)
    words = [int.from_bytes(raw[i:i + 2], "big") for i in range(0, len(raw), 2)]
    if c.width == 2 and c.word_order == "little":
        words = words[::-1]
    return words


# ---------------------------------------------------------------------------------- loading
def _is_int(v) -> bool:
    return isinstance(v, int) and not isinstance(v, bool)


def _is_num(v) -> bool:
    return (isinstance(v, (int, float)) and not isinstance(v, bool))


def _bad(where: str, key: str, value, allowed: str) -> MapError:
    msg = f"{value!r} is not allowed; {allowed}"
    return MapError(f"{where}: {key}: {msg}", Problem(_path(key), msg, value=value, allowed=allowed,
                                                      file=where))


def _unknown(where: str, key: str, k: Any, allowed) -> MapError:
    options = ", ".join(allowed)
    sugg = did_you_mean(k, allowed)
    msg = f"unknown key; allowed keys: {options}" + suggestion_text(sugg)
    path = _path(key) + (k,)
    return MapError(f"{where}: {key + '.' if key else ''}{key_text(k)}: {msg}",
                    Problem(path, msg, value=k, allowed=options, suggestion=sugg, file=where))


def _fail(where: str, key: str, msg: str) -> MapError:
    """A problem of ``key`` that is not one bad value (a missing key, a rule between keys)."""
    return MapError(f"{where}: {key}: {msg}", Problem(_path(key), msg, file=where))


def _path(key: str) -> tuple:
    return tuple(key.split(".")) if key else ()


def _check_int(where, key, v, lo, hi, allowed=None):
    if not _is_int(v) or not lo <= v <= hi:
        raise _bad(where, key, v, allowed or f"an integer {lo}..{hi}")
    return v


def _check_unit(where, key, v):
    return _check_int(where, key, v, 1, 247, "an integer 1..247 (Modbus RTU slave address)")


def _check_baud(where, key, v):
    if not _is_int(v) or v not in BAUDS:
        raise _bad(where, key, v, "one of " + ", ".join(map(str, BAUDS)))
    return v


def _check_parity(where, key, v):
    if not isinstance(v, str) or v.upper() not in PARITIES:
        hint = " (quote it: YAML reads a bare no/off as false)" if isinstance(v, bool) else ""
        raise _bad(where, key, v, "N, E or O" + hint)
    return v.upper()


def _check_num(where, key, v, lo, hi, allowed):
    if not _is_num(v) or not math.isfinite(v) or not lo <= v <= hi:
        raise _bad(where, key, v, allowed)
    return float(v)


def load_map(path: str | os.PathLike) -> MeterMap:
    """Read and validate a register map file; raises MapError naming file, key, value, allowed.
    The file is read by the gateway's bounded YAML reader (size, nesting, aliases, encoding)."""
    path = os.fspath(path)
    try:
        data = safeyaml.read(path, limits=safeyaml.CONFIG).data
    except FileNotFoundError:
        raise MapError(f"{path}: register map file not found") from None
    except OSError as e:
        raise MapError(f"{path}: cannot read register map: {e.strerror}") from None
    except safeyaml.YamlError as e:
        raise MapError(f"{path}: {e.detail()}") from None
    return map_from_dict(data, path)


def map_from_dict(data: Any, path: str = "<map>") -> MeterMap:
    where = path
    if data is None:
        data = {}
    if not isinstance(data, dict):
        raise MapError(f"{where}: expected a mapping of keys ({', '.join(TOP_KEYS)}), "
                       f"got {type(data).__name__}")
    if data and not any(k in TOP_KEYS for k in data):
        # not a register map at all (say, meter.map: /etc/shadow): never echo its content
        raise MapError(f"{where}: not a register map: none of its {len(data)} key(s) is a map key; "
                       f"allowed keys: {', '.join(TOP_KEYS)}")
    for k in data:
        if k not in TOP_KEYS:
            raise _unknown(where, "", k, TOP_KEYS)
    d = {**DEFAULTS, **{k: v for k, v in data.items() if v is not None or k == "channels"}}
    model = d.get("model", "ZN-S")
    if not isinstance(model, str):
        raise _bad(where, "model", model, "a string")
    unit_id = _check_unit(where, "unit_id", d["unit_id"])
    baud = _check_baud(where, "baud", d["baud"])
    parity = _check_parity(where, "parity", d["parity"])
    stopbits = _check_int(where, "stopbits", d["stopbits"], 1, 2, "1 or 2")
    bytesize = d["bytesize"]
    if bytesize != 8 or not _is_int(bytesize):
        raise _bad(where, "bytesize", bytesize, "8 (Modbus RTU uses 8 data bits)")
    function = d["function"]
    if not _is_int(function) or function not in FUNCTIONS:
        raise _bad(where, "function", function, "3 (holding registers) or 4 (input registers)")
    base = d["address_base"]
    if not _is_int(base) or base not in (0, 1):
        raise _bad(where, "address_base", base,
                   "0 (addresses are protocol addresses) or 1 (addresses count from register 1)")
    turnaround_ms = _check_num(where, "turnaround_ms", d["turnaround_ms"], 0.0, 1000.0,
                               "a number of milliseconds 0..1000")
    chans = d.get("channels")
    if chans is None:
        raise _fail(where, "channels", "missing; give ch1 and ch2 (each with an address)")
    if not isinstance(chans, dict):
        raise _bad(where, "channels", chans, "a mapping with ch1 and ch2")
    for k in chans:
        if k not in CHANNEL_NAMES:
            raise _fail(where, f"channels.{key_text(k)}", "unknown channel; allowed: ch1, ch2")
    for k in CHANNEL_NAMES:
        if k not in chans:
            raise _fail(where, f"channels.{k}", "missing; the meter has two channels, ch1 and ch2")
    ch = [_channel(where, n, chans[n], base) for n in CHANNEL_NAMES]
    m = MeterMap(path=path, unit_id=unit_id, baud=baud, parity=parity, stopbits=stopbits,
                 bytesize=8, function=function, address_base=base,
                 turnaround_s=turnaround_ms / 1000.0, ch1=ch[0], ch2=ch[1], model=model)
    _check_layout(where, m)
    return m


def _channel(where: str, name: str, c: Any, base: int) -> ChannelMap:
    key = f"channels.{name}"
    if not isinstance(c, dict):
        raise _bad(where, key, c, f"a mapping with keys {', '.join(CHANNEL_KEYS)}")
    for k in c:
        if k not in CHANNEL_KEYS:
            raise _unknown(where, key, k, CHANNEL_KEYS)
    if "address" not in c:
        raise _fail(where, f"{key}.address", "missing; give the register address of the value")
    lo = base
    addr = _check_int(where, f"{key}.address", c["address"], lo, 65535 + base,
                      f"an integer {lo}..{65535 + base} (address_base is {base})")
    typ = c.get("type", "float32")
    if typ not in DATA_TYPES:
        raise _bad(where, f"{key}.type", typ, "one of " + ", ".join(DATA_TYPES))
    width = DATA_TYPES[typ][0]
    if "word_order" in c and width == 1:
        raise _fail(where, f"{key}.word_order", f"only applies to 32-bit types (int32, float32); "
                       f"{typ} is one register; remove the key")
    wo = c.get("word_order", "big")
    if wo not in WORD_ORDERS:
        raise _bad(where, f"{key}.word_order", wo,
                   "big (high word first) or little (low word first)")
    if "scale" in c and "decimals_register" in c:
        raise _fail(where, key, "give either scale or decimals_register, not both")
    scale = None
    dreg = None
    decimals = 0
    if "decimals_register" in c:
        dreg = _check_int(where, f"{key}.decimals_register", c["decimals_register"], lo, 65535 + base,
                          f"an integer {lo}..{65535 + base} (address_base is {base})") - base
        decimals = _check_int(where, f"{key}.decimals", c.get("decimals", 3), 0, MAX_DECIMALS,
                              f"an integer 0..{MAX_DECIMALS} (value = raw / 10^decimals)")
    else:
        if "decimals" in c:
            raise _fail(where, f"{key}.decimals", "only with decimals_register (the value the "
                           "virtual meter serves there); for a fixed factor use scale")
        scale = c.get("scale", 1.0 if typ == "float32" else None)
        if scale is None:
            raise _fail(where, key, f"{typ} needs scale (N per count, e.g. 0.001) or "
                           f"decimals_register")
        if not _is_num(scale) or not math.isfinite(scale) or scale <= 0:
            raise _bad(where, f"{key}.scale", scale, "a positive number (N per count, e.g. 0.001)")
        scale = float(scale)
    return ChannelMap(name=name, address=addr - base, type=typ, word_order=wo, scale=scale,
                      decimals_register=dreg, decimals=decimals)


def _check_layout(where: str, m: MeterMap) -> None:
    # registers must not overlap (a shared decimal-point register is fine)
    used: dict[int, str] = {}
    for a, w, key in m._spans():
        for r in range(a, a + w):
            if r > 65535:
                raise _fail(where, key, f"register {r + m.address_base} is past the end of "
                               f"the address space")
            if r in used:
                raise _fail(where, key, f"register {r + m.address_base} overlaps {used[r]}")
            used[r] = key
    dregs: dict[int, int] = {}
    for c in m.channels:
        if c.decimals_register is not None:
            if c.decimals_register in dregs and dregs[c.decimals_register] != c.decimals:
                raise _fail(where, f"channels.{c.name}.decimals", f"{c.decimals} differs from "
                               f"{dregs[c.decimals_register]} for the shared decimal-point register "
                               f"{c.decimals_register + m.address_base}")
            dregs[c.decimals_register] = c.decimals
    _, start, count = m.read_block
    if count > MAX_READ_REGISTERS:
        raise _fail(where, "channels", f"the registers span {count} registers from "
                       f"{start + m.address_base}; one read (FC{m.function}) covers at most "
                       f"{MAX_READ_REGISTERS}: put the channels closer together")
