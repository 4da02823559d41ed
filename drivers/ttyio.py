"""Small helpers shared by the serial drivers (meter, STM32): hang-up detection, and what a real
adapter needs — low-latency mode, the kernel's RS-485 mode for board UARTs, the FTDI latency
timer."""
from __future__ import annotations

import fcntl
import logging
import os
import select
import struct
import termios
from typing import Any

_HANGUP = select.POLLHUP | select.POLLERR | select.POLLNVAL


def hung_up(fd: int) -> bool:
    """The port reports a hang-up or an error now (a pty whose other end closed, a USB adapter
    unplugged): one poll(2) without waiting.

    Called only after an empty read: with VMIN 0 (as pyserial sets it) an empty read also happens
    when there is simply nothing to read — e.g. the event loop runs a readiness callback after
    another read in the same loop turn took the bytes — and that is no hang-up."""
    p = select.poll()
    p.register(fd, select.POLLIN)
    return any(ev & _HANGUP for _, ev in p.poll(0))


# ------------------------------------------------------------------------------ real adapters
# (docs/protocols/zn-s.md, "Adapters"; docs/deploy.md, "USB–RS-485 adapters")

#: TIOCGRS485 / TIOCSRS485 (include/uapi/asm-generic/ioctls.h) and struct serial_rs485's flags
TIOCGRS485 = getattr(termios, "TIOCGRS485", 0x542E)
TIOCSRS485 = getattr(termios, "TIOCSRS485", 0x542F)
SER_RS485_ENABLED = 1 << 0
SER_RS485_RTS_ON_SEND = 1 << 1
SER_RS485_RTS_AFTER_SEND = 1 << 2
SER_RS485_RX_DURING_TX = 1 << 4
#: struct serial_rs485: flags, delay_rts_before_send, delay_rts_after_send (ms), 5 words padding
_RS485 = struct.Struct("=8I")
#: what a delay of struct serial_rs485 can hold here (ms; the kernel clamps to 100 ms anyway)
RS485_DELAY_MAX_S = 0.1

_refused_logged: set[tuple[str, str]] = set()


def _once(what: str, port: str) -> bool:
    """True the first time (what, port) is seen in this process (bounded: 256 entries)."""
    k = (what, port)
    if k in _refused_logged or len(_refused_logged) >= 256:
        return False
    _refused_logged.add(k)
    return True


def set_low_latency(ser: Any, port: str, log: logging.Logger) -> bool:
    """Ask the kernel to hand received bytes over at once (ASYNC_LOW_LATENCY through TIOCSSERIAL,
    pyserial's ``set_low_latency_mode``). True when set; a port that has no such setting (a pty,
    many USB drivers, a pyserial URL) refuses it: logged once per port at debug, never an error."""
    fn = getattr(ser, "set_low_latency_mode", None)
    if fn is None:
        if _once("low_latency", port):
            log.debug("%s: no low-latency mode on this kind of port", port)
        return False
    try:
        fn(True)
    except (OSError, ValueError, NotImplementedError) as e:
        if _once("low_latency", port):
            log.debug("%s: the kernel refused low-latency mode (%s); fine on a pty", port, e)
        return False
    return True


def rs485_flags(rts_on_send: str = "high", rts_after_send: str = "low", rx_during_tx: bool = False) -> int:
    """struct serial_rs485 flags: RS-485 mode on, RTS level while sending / after sending."""
    f = SER_RS485_ENABLED
    if rts_on_send == "high":
        f |= SER_RS485_RTS_ON_SEND
    if rts_after_send == "high":
        f |= SER_RS485_RTS_AFTER_SEND
    if rx_during_tx:
        f |= SER_RS485_RX_DURING_TX
    return f


def set_rs485(fd: int, rts_on_send: str = "high", rts_after_send: str = "low",
              delay_before_send_s: float = 0.0, delay_after_send_s: float = 0.0) -> str | None:
    """Put a board UART into the kernel's RS-485 mode (TIOCSRS485): the driver raises RTS (the
    transceiver's DE) for each transmission and drops it after the last stop bit, with the given
    delays. None when set; else one sentence why not (a pty, a USB adapter that switches
    direction itself, a UART driver without RS-485 support)."""
    ms_before = int(round(min(max(delay_before_send_s, 0.0), RS485_DELAY_MAX_S) * 1000))
    ms_after = int(round(min(max(delay_after_send_s, 0.0), RS485_DELAY_MAX_S) * 1000))
    buf = bytearray(_RS485.pack(rs485_flags(rts_on_send, rts_after_send), ms_before, ms_after, 0, 0, 0, 0, 0))
    try:
        fcntl.ioctl(fd, TIOCSRS485, buf)
    except OSError as e:
        return (f"the port refuses the kernel's RS-485 mode ({e.strerror or e}): it is no UART with "
                f"RTS direction control (a pty, or a USB adapter, which switches direction itself: "
                f"remove the `rs485:` section for it)")
    return None


def get_rs485(fd: int) -> tuple[int, int, int] | None:
    """(flags, delay before send ms, delay after send ms) of the port, None if it has no RS-485 mode."""
    buf = bytearray(_RS485.size)
    try:
        fcntl.ioctl(fd, TIOCGRS485, buf)
    except OSError:
        return None
    flags, before, after, *_ = _RS485.unpack(buf)
    return flags, before, after


def latency_timer_path(port: str, sysfs: str = "/sys") -> str:
    """Where the kernel shows the latency timer of the USB serial adapter behind ``port`` (FTDI:
    ftdi_sio's ``latency_timer``, ms); the file is absent for every other kind of port."""
    name = os.path.basename(os.path.realpath(port))
    return os.path.join(sysfs, "class", "tty", name, "device", "latency_timer")


def latency_timer_ms(port: str, sysfs: str = "/sys") -> int | None:
    """The adapter's latency timer in ms, or None (not a USB serial adapter that has one)."""
    try:
        with open(latency_timer_path(port, sysfs)) as f:
            return int(f.read(16).strip())
    except (OSError, ValueError):
        return None
