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

import serial

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


# ------------------------------------------------------------------------------ who holds a port
# A station's drivers open their ports exclusively (pyserial's ``exclusive=True``: flock(2)
# LOCK_EX on the open port). flock is advisory: a program that does not ask (pymodbus' client,
# a terminal program) is not stopped by it, and a serial port's settings (baud, parity) belong to
# the device, not to one opener — whoever opens it and sets 9600 baud sets it for the station
# too. So anything of ours that opens a port asks first (:func:`port_in_use`), opens it
# exclusively itself, and puts back what it changed (:func:`keep_settings`).

class PortInUse(serial.SerialException):
    """The port is locked by another open file (a running station, a probe): ``holders`` names
    the processes that hold it (as far as this user can see)."""

    def __init__(self, port: str, holders: str):
        super().__init__(f"{port} is in use by {holders}")
        self.port = port
        self.holders = holders


def port_in_use(port: str) -> bool | None:
    """True when another open file holds the exclusive lock on ``port``; False when it is free
    (the lock is taken and given back at once, nothing of the port is changed: no termios call);
    None when it cannot be asked (no such device, no permission, a pyserial URL)."""
    if "://" in port:
        return None
    try:
        fd = os.open(port, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
    except OSError:
        return None
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        return True
    except OSError:
        return None
    finally:
        os.close(fd)              # closing gives the lock back
    return False


class keep_settings:  # noqa: N801 - a context manager used like a function
    """``with keep_settings(path):`` the port's settings (termios) as found on entry are put back
    on exit, if the port is free then (its exclusive lock can be taken): whatever the block tried
    (a probe's scan sets other bauds), a free port is left as it was, and a port someone else
    took meanwhile is not touched. No lock is held during the block (pymodbus' client and the
    drivers take their own)."""

    def __init__(self, port: str):
        self.port = port
        self._fd: int | None = None
        self._saved: list[Any] | None = None

    def __enter__(self) -> keep_settings:
        if "://" in self.port:
            return self
        try:
            fd = os.open(self.port, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
        except OSError:
            return self
        self._fd = fd
        try:
            self._saved = termios.tcgetattr(fd)
        except termios.error:
            self._saved = None
        return self

    def __exit__(self, *exc: object) -> None:
        fd, self._fd = self._fd, None
        if fd is None:
            return
        try:
            if self._saved is not None:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
                termios.tcsetattr(fd, termios.TCSANOW, self._saved)
        except (OSError, termios.error):
            pass                               # in use now, or gone: left as it is
        finally:
            os.close(fd)


def lock_holders(port: str, proc: str = "/proc") -> list[int]:
    """The processes holding a flock(2) on ``port``, from /proc/locks (readable by every user):
    the one that opened it exclusively, not whoever else has it open (a pty's other side)."""
    try:
        st = os.stat(os.path.realpath(port))
        with open(f"{proc}/locks", encoding="ascii", errors="replace") as f:
            lines = f.read(1 << 20).splitlines()
    except OSError:
        return []
    want = f"{os.major(st.st_dev):02x}:{os.minor(st.st_dev):02x}:{st.st_ino}"
    out = set()
    for ln in lines:
        p = ln.split()
        # "1: FLOCK  ADVISORY  WRITE 4242 00:1a:3 0 EOF" (a waiter's line has "->" after the id)
        if len(p) >= 6 and p[1] == "FLOCK" and p[5] == want and p[4].isdigit():
            out.add(int(p[4]))
    out.discard(os.getpid())
    return sorted(out)


def port_holders(port: str, proc: str = "/proc") -> list[int]:
    """The processes (other than this one) that hold ``port``: its lock's holders
    (:func:`lock_holders`); else those with it open, from their file descriptors in /proc —
    those this user may see (all of them as root; else the user's own)."""
    held = lock_holders(port, proc)
    if held:
        return held
    try:
        target = os.path.realpath(port)
        st = os.stat(target)
    except OSError:
        return []
    me, out = os.getpid(), []
    try:
        pids = [int(p) for p in os.listdir(proc) if p.isdigit()]
    except OSError:
        return []
    for pid in pids:
        if pid == me:
            continue
        d = f"{proc}/{pid}/fd"
        try:
            fds = os.listdir(d)
        except OSError:
            continue
        for fd in fds:
            try:
                if os.readlink(f"{d}/{fd}") == target or os.stat(f"{d}/{fd}").st_rdev == st.st_rdev != 0:
                    out.append(pid)
                    break
            except OSError:
                continue
    return sorted(out)


def process_args(pid: int, proc: str = "/proc") -> list[str]:
    """A process' command line (readable for every process), [] when it is gone."""
    try:
        with open(f"{proc}/{pid}/cmdline", "rb") as f:
            raw = f.read(65536)
    except OSError:
        return []
    return [a.decode("utf-8", "replace") for a in raw.split(b"\0") if a]


def describe_holders(port: str) -> str:
    """Who holds ``port``, in words: ``pid 1234 (hookwatch run /etc/hookwatch/l1.yaml)``, or
    "another process" when this user cannot see which."""
    pids = port_holders(port)
    if not pids:
        return "another process (not visible to this user: run as root to see which)"
    parts = []
    for pid in pids[:4]:
        args = process_args(pid)
        cmd = " ".join(os.path.basename(a) if i == 0 else a for i, a in enumerate(args))
        if len(cmd) > 120:
            cmd = cmd[:120] + "…"
        parts.append(f"pid {pid} ({cmd})" if cmd else f"pid {pid}")
    more = len(pids) - len(parts)
    return ", ".join(parts) + (f" and {more} more" if more > 0 else "")


def open_exclusive(port: str, **settings: Any) -> Any:
    """``serial.serial_for_url(port, exclusive=True, **settings)`` (a device path, or a pyserial
    URL): the port's settings are applied only once the lock is held, so a port in use is left
    as it is; a lock held by another open file raises :class:`PortInUse` naming who holds it."""
    try:
        return serial.serial_for_url(port, exclusive=True, **settings)
    except serial.SerialException as e:
        if "://" not in port and port_in_use(port):
            raise PortInUse(port, describe_holders(port)) from e
        raise
