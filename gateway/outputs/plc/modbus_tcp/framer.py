"""MBAP framing (Modbus Application Protocol header over TCP). Pure: bytes in, frames out.

A TCP segment may hold several requests, and a request may arrive split over segments:
:meth:`Framer.feed` takes whatever was received and returns every complete frame in order,
keeping the rest. A header that cannot be Modbus (protocol id ≠ 0, length < 2 or > 254) is a
:class:`FrameError`: the connection is closed (there is no way to find the next frame boundary).
"""
from __future__ import annotations

import struct
from dataclasses import dataclass

HEADER = struct.Struct(">HHHB")     # transaction id, protocol id, length, unit id
HEADER_LEN = 7
#: largest PDU (Modbus spec: 253 bytes) and ADU
MAX_PDU = 253
MAX_ADU = HEADER_LEN + MAX_PDU


class FrameError(ValueError):
    pass


@dataclass(frozen=True, slots=True)
class Frame:
    tid: int
    unit: int
    pdu: bytes


class Framer:
    def __init__(self) -> None:
        self._buf = bytearray()

    @property
    def pending(self) -> int:
        return len(self._buf)

    def feed(self, data: bytes) -> list[Frame]:
        self._buf += data
        out: list[Frame] = []
        buf = self._buf
        pos = 0
        while len(buf) - pos >= HEADER_LEN:
            tid, proto, length, unit = HEADER.unpack_from(buf, pos)
            if proto != 0:
                raise FrameError(f"protocol id {proto} (Modbus is 0)")
            if not 2 <= length <= MAX_PDU + 1:
                raise FrameError(f"length field {length} (2 … {MAX_PDU + 1})")
            end = pos + 6 + length
            if end > len(buf):
                break
            out.append(Frame(tid, unit, bytes(buf[pos + HEADER_LEN:end])))
            pos = end
        del buf[:pos]
        return out


def encode(tid: int, unit: int, pdu: bytes) -> bytes:
    return HEADER.pack(tid & 0xFFFF, 0, len(pdu) + 1, unit & 0xFF) + pdu
