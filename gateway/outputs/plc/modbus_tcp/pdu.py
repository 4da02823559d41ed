"""Modbus PDUs for the register map: decode a request, encode replies and exceptions. Pure.

Only the function codes the register map documents (docs/registers.md) are served:
03 read holding registers, 04 read input registers, 06 write single register, 16 write multiple
registers, 23 read/write multiple registers. Every other function (coils and discrete inputs
01/02/05/15, diagnostics 08, report server id 17, file records 20/21, encapsulated interface 43 …)
is answered with exception 01 ILLEGAL FUNCTION. A request whose length does not fit its function,
a count of 0 or above the Modbus maximum, or a byte count that does not match is answered with
exception 03 ILLEGAL DATA VALUE (Modbus spec, 4.1 and the per-function state diagrams).
A command the station refuses is answered by the exception its rejection code maps to
(gateway/outputs/plc/registers.py ``refusal_exception``: 06 SERVER DEVICE BUSY, 03 ILLEGAL DATA
VALUE, 04 SERVER DEVICE FAILURE only when the station failed to answer).
"""
from __future__ import annotations

import enum
import struct
from dataclasses import dataclass


class Exc(enum.IntEnum):
    ILLEGAL_FUNCTION = 1
    ILLEGAL_ADDRESS = 2
    ILLEGAL_VALUE = 3
    DEVICE_FAILURE = 4
    DEVICE_BUSY = 6
    GATEWAY_NO_RESPONSE = 0x0B


READ_HOLDING = 3
READ_INPUT = 4
WRITE_SINGLE = 6
WRITE_MULTIPLE = 16
READ_WRITE_MULTIPLE = 23
SERVED = (READ_HOLDING, READ_INPUT, WRITE_SINGLE, WRITE_MULTIPLE, READ_WRITE_MULTIPLE)
MAX_READ = 125
MAX_WRITE = 123
MAX_RW_WRITE = 121


@dataclass(frozen=True, slots=True)
class Request:
    fc: int
    read_addr: int = 0
    read_count: int = 0
    write_addr: int = 0
    values: tuple[int, ...] = ()

    @property
    def writes(self) -> bool:
        return bool(self.values)

    @property
    def reads(self) -> bool:
        return self.read_count > 0


def decode(pdu: bytes) -> Request | Exc:
    """A request PDU → :class:`Request`, or the exception code to answer."""
    if not pdu:
        return Exc.ILLEGAL_FUNCTION
    fc = pdu[0]
    if fc not in SERVED:
        return Exc.ILLEGAL_FUNCTION
    body = pdu[1:]
    if fc in (READ_HOLDING, READ_INPUT):
        if len(body) != 4:
            return Exc.ILLEGAL_VALUE
        addr, count = struct.unpack(">HH", body)
        if not 1 <= count <= MAX_READ:
            return Exc.ILLEGAL_VALUE
        return Request(fc, addr, count)
    if fc == WRITE_SINGLE:
        if len(body) != 4:
            return Exc.ILLEGAL_VALUE
        addr, value = struct.unpack(">HH", body)
        return Request(fc, write_addr=addr, values=(value,))
    if fc == WRITE_MULTIPLE:
        if len(body) < 5:
            return Exc.ILLEGAL_VALUE
        addr, count, nbytes = struct.unpack(">HHB", body[:5])
        if not 1 <= count <= MAX_WRITE or nbytes != 2 * count or len(body) != 5 + nbytes:
            return Exc.ILLEGAL_VALUE
        return Request(fc, write_addr=addr, values=struct.unpack(f">{count}H", body[5:]))
    # READ_WRITE_MULTIPLE
    if len(body) < 9:
        return Exc.ILLEGAL_VALUE
    raddr, rcount, waddr, wcount, nbytes = struct.unpack(">HHHHB", body[:9])
    if (not 1 <= rcount <= MAX_READ or not 1 <= wcount <= MAX_RW_WRITE or nbytes != 2 * wcount
            or len(body) != 9 + nbytes):
        return Exc.ILLEGAL_VALUE
    return Request(fc, raddr, rcount, waddr, struct.unpack(f">{wcount}H", body[9:]))


def read_range(image: list[int], addr: int, count: int) -> list[int] | Exc:
    if addr + count > len(image):
        return Exc.ILLEGAL_ADDRESS
    return image[addr:addr + count]


def exception(fc: int, code: int) -> bytes:
    return bytes(((fc & 0x7F) | 0x80, int(code)))


def read_reply(fc: int, regs: list[int]) -> bytes:
    return struct.pack(f">BB{len(regs)}H", fc, 2 * len(regs), *regs)


def write_reply(req: Request) -> bytes:
    if req.fc == WRITE_SINGLE:
        return struct.pack(">BHH", req.fc, req.write_addr, req.values[0])
    return struct.pack(">BHH", req.fc, req.write_addr, len(req.values))
