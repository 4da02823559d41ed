"""CRC-16/MODBUS, shared by the ZN-S meter (Modbus RTU) and the STM32 link protocol."""
from __future__ import annotations


def _crc_table() -> list[int]:
    table = []
    for i in range(256):
        c = i
        for _ in range(8):
            c = (c >> 1) ^ 0xA001 if c & 1 else c >> 1
        table.append(c)
    return table


_TABLE = _crc_table()


def crc16_modbus(data: bytes | bytearray | memoryview) -> int:
    """CRC-16/MODBUS: poly 0x8005 (reflected 0xA001), init 0xFFFF, no final xor; sent low byte
    first. crc16_modbus(b"123456789") == 0x4B37."""
    crc = 0xFFFF
    tbl = _TABLE
    for b in data:
        crc = (crc >> 8) ^ tbl[(crc ^ b) & 0xFF]
    return crc
