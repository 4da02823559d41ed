"""The STM32 link protocol (docs/protocols/stm32.md): the one definition of frames, commands,
status and CRC, used by the gateway's driver (drivers/stm32/driver.py) and by the virtual STM32
(drivers/sim/twin_stm32.py) alike. Pure: bytes in, bytes/objects out; no I/O, no clock.

Frame (every multi-byte field little-endian, as the STM32 stores it):

    A5 5A | LEN | SEQ | CMD | PAYLOAD (LEN bytes) | CRC16 lo, hi

CRC-16/MODBUS (poly 0x8005 reflected, init 0xFFFF) over LEN, SEQ, CMD and PAYLOAD.
"""
from __future__ import annotations

import enum
import math
import struct
from dataclasses import dataclass

START = b"\xA5\x5A"
MAX_PAYLOAD = 32          # a LEN byte above this cannot start a frame (the parser skips it)
OVERHEAD = 7              # start (2) + LEN + SEQ + CMD + CRC (2)
BITS_PER_CHAR = 10        # 8N1: start bit, 8 data bits, stop bit
DEFAULT_BAUD = 115200
RPM_SCALE = 100           # speeds on the wire: signed 32-bit, 0.01 rpm per count
DEFAULT_MAX_RPM = 600.0   # SET_SPEED range of the firmware: 0 … max_rpm
WATCHDOG_MS_MIN = 20
WATCHDOG_MS_MAX = 60000
#: the firmware's watchdog period after power-on, until the gateway sets its own (SET_WATCHDOG)
WATCHDOG_POWER_ON_S = 0.2
#: the gateway's watchdog period is the protection stop's `stop_after` plus this margin
#: (docs/protocols/stm32.md, "Safety argument"): a stall of the gateway's process shorter than
#: `stop_after` leaves at most stop_after + one slot (the last frame before the stall) + the
#: resumed process' first slot without a frame on the wire; 0.5 s covers the last two many times
WATCHDOG_MARGIN_S = 0.5


def watchdog_for(stop_after_s: float) -> float:
    """The watchdog period a gateway whose protection stop comes after ``stop_after_s`` of
    unsafe slots sets in the firmware: long enough that a stall of the gateway shorter than the
    protection stop never stops the drive, short enough that a dead gateway's motor stops
    within stop_after + WATCHDOG_MARGIN_S (clipped to the firmware's range)."""
    s = max(0.0, float(stop_after_s)) + WATCHDOG_MARGIN_S
    return min(WATCHDOG_MS_MAX / 1000.0, max(WATCHDOG_MS_MIN / 1000.0, s))


class Cmd(enum.IntEnum):
    PING = 0x01
    READ_STATUS = 0x02
    ENABLE = 0x10
    DISABLE = 0x11
    SET_SPEED = 0x12
    STOP = 0x13
    SET_WATCHDOG = 0x14
    # replies
    ACK = 0x80
    NAK = 0x81


#: payload length of every request (a different LEN is answered with NAK BAD_LENGTH)
REQUEST_PAYLOAD = {Cmd.PING: 0, Cmd.READ_STATUS: 0, Cmd.ENABLE: 0, Cmd.DISABLE: 0,
                   Cmd.SET_SPEED: 4, Cmd.STOP: 1, Cmd.SET_WATCHDOG: 2}


class NakCode(enum.IntEnum):
    BAD_LENGTH = 1        # LEN does not match the command's payload size
    UNKNOWN_COMMAND = 2
    OUT_OF_RANGE = 3      # speed outside 0 … max_rpm, unknown stop reason, watchdog outside range


class StopReason(enum.IntEnum):
    """Why the motor is (or was last) stopped; NONE while enabled."""
    NONE = 0
    POWER_ON = 1          # firmware reset: never enabled since
    COMMAND = 2           # STOP from the gateway (operator stop, generic)
    DISABLE = 3           # DISABLE command
    WATCHDOG = 4          # no valid command for watchdog_s while enabled
    STALL = 5             # the drive reported a stall for longer than the stall trip time
    OVERSPEED = 6         # actual speed above the overspeed limit
    PROTECTION = 7        # STOP from the gateway: METHOD.md §3 protection stop
    TEST_END = 8          # STOP from the gateway: test completed
    GATEWAY = 9           # STOP from the gateway: gateway start / shutdown


class Flag(enum.IntFlag):
    ENABLED = 0x01        # drive enabled (commands are applied)
    RUNNING = 0x02        # motor turning: |actual| >= 1 rpm (also while coasting down)
    WATCHDOG = 0x04       # the watchdog stopped the motor (latched until ENABLE)
    STALL = 0x08          # the drive reports a stall right now
    FAULT = 0x10          # a protection trip (stall, overspeed) stopped the motor (latched until ENABLE)
    OVERSPEED = 0x20      # overspeed trip (latched until ENABLE)


RUNNING_RPM = 1.0

_STATUS = struct.Struct("<iiHBHH")   # actual, command (0.01 rpm), flags, stop reason, watchdog ms, rx errors
STATUS_LEN = _STATUS.size            # 15
ACK_PAYLOAD = 1 + STATUS_LEN         # request command + status
NAK_PAYLOAD = 2                      # request command + error code


class ProtocolError(ValueError):
    """A frame that passed its CRC but does not make sense (wrong length, unknown type).
    ``code`` is the NAK code to answer a bad request with (None for a bad reply)."""

    code: int | None = None


# ---------------------------------------------------------------------------------------- CRC
from ..serial.crc import crc16_modbus as crc16  # noqa: E402  (one CRC for both links)


# ---------------------------------------------------------------------------------------- frames
@dataclass(frozen=True)
class Frame:
    seq: int
    cmd: int
    payload: bytes = b""

    def encode(self) -> bytes:
        return encode_frame(self.seq, self.cmd, self.payload)

    def __len__(self) -> int:
        return OVERHEAD + len(self.payload)


def encode_frame(seq: int, cmd: int, payload: bytes = b"") -> bytes:
    if not 0 <= seq <= 255:
        raise ValueError(f"seq {seq} outside 0…255")
    if not 0 <= cmd <= 255:
        raise ValueError(f"cmd {cmd} outside 0…255")
    if len(payload) > MAX_PAYLOAD:
        raise ValueError(f"payload of {len(payload)} bytes, at most {MAX_PAYLOAD}")
    body = bytes((len(payload), seq, cmd)) + bytes(payload)
    c = crc16(body)
    return START + body + bytes((c & 0xFF, c >> 8))


def decode_frame(data: bytes) -> Frame:
    """Strict decode of exactly one frame (start, length, CRC); ProtocolError otherwise."""
    if len(data) < OVERHEAD or data[:2] != START:
        raise ProtocolError("no frame start")
    n = data[2]
    if n > MAX_PAYLOAD or len(data) != OVERHEAD + n:
        raise ProtocolError(f"length byte {n} does not match {len(data)} bytes")
    if crc16(data[2:-2]) != data[-2] | (data[-1] << 8):
        raise ProtocolError("bad CRC")
    return Frame(data[3], data[4], bytes(data[5:5 + n]))


class FrameParser:
    """Streaming parser: feed it bytes as they come, get whole frames with a good CRC.

    Never raises. Garbage is skipped byte by byte; a candidate frame whose CRC fails is dropped
    by one byte only, so a real frame hidden behind a false start is still found. A partial frame
    waits for more bytes; ``flush()`` (call it after an idle gap on the line) gives up on partial
    frames and returns whatever whole frames the remaining bytes still contain."""

    def __init__(self) -> None:
        self._buf = bytearray()
        self.frames = 0
        self.crc_errors = 0       # candidates (start + plausible length) whose CRC failed
        self.garbage_bytes = 0    # bytes skipped that belonged to no frame

    @property
    def pending(self) -> int:
        return len(self._buf)

    def reset(self) -> None:
        self.garbage_bytes += len(self._buf)
        self._buf.clear()

    def feed(self, data: bytes) -> list[Frame]:
        if data:
            self._buf += data
        return self._scan(final=False)

    def flush(self) -> list[Frame]:
        return self._scan(final=True)

    def _drop(self, n: int) -> None:
        self.garbage_bytes += n
        del self._buf[:n]

    def _scan(self, final: bool) -> list[Frame]:
        out: list[Frame] = []
        buf = self._buf
        while buf:
            i = buf.find(START)
            if i < 0:
                keep = 1 if (buf[-1] == START[0] and not final) else 0
                self._drop(len(buf) - keep)
                break
            if i:
                self._drop(i)
            if len(buf) < 3:
                if final:
                    self._drop(1)
                    continue
                break
            n = buf[2]
            if n > MAX_PAYLOAD:
                self._drop(1)
                continue
            total = OVERHEAD + n
            if len(buf) < total:
                if final:
                    self._drop(1)
                    continue
                break
            if crc16(memoryview(buf)[2:total - 2]) != buf[total - 2] | (buf[total - 1] << 8):
                self.crc_errors += 1
                self._drop(1)
                continue
            out.append(Frame(buf[3], buf[4], bytes(buf[5:5 + n])))
            self.frames += 1
            del buf[:total]
        return out


# ---------------------------------------------------------------------------------------- status
def rpm_to_wire(rpm: float) -> int:
    """rpm → signed 0.01 rpm counts (clamped to int32); ValueError for NaN/inf."""
    if not math.isfinite(rpm):
        raise ValueError(f"speed {rpm!r} is not a finite number")
    v = int(round(rpm * RPM_SCALE))
    return max(-2**31, min(2**31 - 1, v))


def rpm_from_wire(v: int) -> float:
    return v / RPM_SCALE


def _reason(code: int) -> StopReason | int:
    try:
        return StopReason(code)
    except ValueError:
        return code


@dataclass(frozen=True)
class Status:
    actual_rpm: float
    command_rpm: float
    enabled: bool
    flags: Flag
    stop_reason: StopReason | int
    watchdog_ms: int = 200
    rx_errors: int = 0            # frames the firmware dropped for a bad CRC (mod 65536)

    @property
    def running(self) -> bool:
        return bool(self.flags & Flag.RUNNING)

    @property
    def watchdog_tripped(self) -> bool:
        return bool(self.flags & Flag.WATCHDOG)

    @property
    def stalled(self) -> bool:
        return bool(self.flags & Flag.STALL)

    @property
    def fault(self) -> bool:
        return bool(self.flags & Flag.FAULT)

    @property
    def overspeed(self) -> bool:
        return bool(self.flags & Flag.OVERSPEED)

    @property
    def stop_reason_name(self) -> str:
        r = self.stop_reason
        return r.name if isinstance(r, StopReason) else f"code {int(r)}"

    def as_dict(self) -> dict:
        return {"actual_rpm": self.actual_rpm, "command_rpm": self.command_rpm,
                "enabled": self.enabled, "flags": int(self.flags),
                "flag_names": [f.name for f in Flag if self.flags & f],
                "stop_reason": self.stop_reason_name, "watchdog_ms": self.watchdog_ms,
                "rx_errors": self.rx_errors}


def encode_status(st: Status) -> bytes:
    flags = Flag(st.flags)
    flags = flags | Flag.ENABLED if st.enabled else flags & ~Flag.ENABLED
    return _STATUS.pack(rpm_to_wire(st.actual_rpm), rpm_to_wire(st.command_rpm), int(flags),
                        int(st.stop_reason) & 0xFF, max(0, min(0xFFFF, int(st.watchdog_ms))),
                        int(st.rx_errors) & 0xFFFF)


def decode_status(payload: bytes) -> Status:
    if len(payload) != STATUS_LEN:
        raise ProtocolError(f"status of {len(payload)} bytes, expected {STATUS_LEN}")
    act, cmd, flags, reason, wd, rxe = _STATUS.unpack(payload)
    return Status(rpm_from_wire(act), rpm_from_wire(cmd), bool(flags & Flag.ENABLED), Flag(flags),
                  _reason(reason), wd, rxe)


# ---------------------------------------------------------------------------------------- requests
def req_ping(seq: int) -> bytes:
    return encode_frame(seq, Cmd.PING)


def req_read_status(seq: int) -> bytes:
    return encode_frame(seq, Cmd.READ_STATUS)


def req_enable(seq: int) -> bytes:
    return encode_frame(seq, Cmd.ENABLE)


def req_disable(seq: int) -> bytes:
    return encode_frame(seq, Cmd.DISABLE)


def speed_payload(rpm: float) -> bytes:
    return struct.pack("<i", rpm_to_wire(rpm))


def req_set_speed(seq: int, rpm: float) -> bytes:
    return encode_frame(seq, Cmd.SET_SPEED, speed_payload(rpm))


def req_stop(seq: int, reason: int = StopReason.COMMAND) -> bytes:
    return encode_frame(seq, Cmd.STOP, bytes((int(reason) & 0xFF,)))


def watchdog_payload(seconds: float) -> bytes:
    ms = int(round(seconds * 1000))
    return struct.pack("<H", max(0, min(0xFFFF, ms)))


def req_set_watchdog(seq: int, seconds: float) -> bytes:
    return encode_frame(seq, Cmd.SET_WATCHDOG, watchdog_payload(seconds))


@dataclass(frozen=True)
class Request:
    seq: int
    cmd: Cmd
    rpm: float | None = None          # SET_SPEED
    reason: int | None = None         # STOP
    watchdog_ms: int | None = None    # SET_WATCHDOG


def decode_request(frame: Frame) -> Request:
    """A request frame → Request. ProtocolError carries the NAK code as ``.code``."""
    try:
        cmd = Cmd(frame.cmd)
    except ValueError:
        cmd = None
    if cmd is None or cmd not in REQUEST_PAYLOAD:
        e = ProtocolError(f"unknown command 0x{frame.cmd:02X}")
        e.code = NakCode.UNKNOWN_COMMAND
        raise e
    if len(frame.payload) != REQUEST_PAYLOAD[cmd]:
        e = ProtocolError(f"{cmd.name}: payload of {len(frame.payload)} bytes, expected {REQUEST_PAYLOAD[cmd]}")
        e.code = NakCode.BAD_LENGTH
        raise e
    if cmd == Cmd.SET_SPEED:
        return Request(frame.seq, cmd, rpm=rpm_from_wire(struct.unpack("<i", frame.payload)[0]))
    if cmd == Cmd.STOP:
        return Request(frame.seq, cmd, reason=frame.payload[0])
    if cmd == Cmd.SET_WATCHDOG:
        return Request(frame.seq, cmd, watchdog_ms=struct.unpack("<H", frame.payload)[0])
    return Request(frame.seq, cmd)


# ---------------------------------------------------------------------------------------- replies
@dataclass(frozen=True)
class Reply:
    seq: int
    ok: bool                          # ACK (True) or NAK (False)
    request: int                      # the command this answers
    status: Status | None = None      # ACK
    error: NakCode | int | None = None  # NAK


def encode_ack(seq: int, request_cmd: int, status: Status) -> bytes:
    return encode_frame(seq, Cmd.ACK, bytes((int(request_cmd) & 0xFF,)) + encode_status(status))


def encode_nak(seq: int, request_cmd: int, code: int) -> bytes:
    return encode_frame(seq, Cmd.NAK, bytes((int(request_cmd) & 0xFF, int(code) & 0xFF)))


def decode_reply(frame: Frame) -> Reply:
    if frame.cmd == Cmd.ACK:
        if len(frame.payload) != ACK_PAYLOAD:
            raise ProtocolError(f"ACK with {len(frame.payload)} payload bytes, expected {ACK_PAYLOAD}")
        return Reply(frame.seq, True, frame.payload[0], status=decode_status(frame.payload[1:]))
    if frame.cmd == Cmd.NAK:
        if len(frame.payload) != NAK_PAYLOAD:
            raise ProtocolError(f"NAK with {len(frame.payload)} payload bytes, expected {NAK_PAYLOAD}")
        code = frame.payload[1]
        try:
            code = NakCode(code)
        except ValueError:
            pass
        return Reply(frame.seq, False, frame.payload[0], error=code)
    raise ProtocolError(f"not a reply: type 0x{frame.cmd:02X}")


# ---------------------------------------------------------------------------------------- timing
def wire_time_s(n_bytes: int, baud: int = DEFAULT_BAUD) -> float:
    """Time n bytes take on the UART at 8N1 (10 bits a character)."""
    return n_bytes * BITS_PER_CHAR / float(baud)


def request_len(cmd: Cmd) -> int:
    return OVERHEAD + REQUEST_PAYLOAD[cmd]


ACK_LEN = OVERHEAD + ACK_PAYLOAD      # 23 bytes
NAK_LEN = OVERHEAD + NAK_PAYLOAD      # 9 bytes


def exchange_time_s(cmd: Cmd, baud: int = DEFAULT_BAUD, processing_s: float = 0.0) -> float:
    """Request + firmware processing + ACK on the wire."""
    return wire_time_s(request_len(cmd) + ACK_LEN, baud) + processing_s
