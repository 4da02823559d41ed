"""An in-process serial link: python-can's virtual bus, for the RS-485 and UART links.

A :class:`LoopbackLink` is a connected pair of sockets (``socket.socketpair``) in one process — no
pseudo-terminal, no TCP port, nothing on the file system. The virtual device holds one end with the
same interface as :class:`~drivers.sim.pty.PtyLink` (``open``, ``master``, ``read_available``,
``write``, ``flush_input``, ``vanish``, ``restore``, ``close``); the driver opens the other end by
the URL :meth:`LoopbackLink.open` returns, ``hwloop://<name>``, through pyserial's URL handlers
(:mod:`drivers.sim.protocol_hwloop`) — so the drivers' code paths are the ones a real port takes
(pymodbus' serial transport for the meter, ``fileno()`` + ``add_reader`` for the STM32).

Like a pty, it has no baud rate: the virtual devices delay their replies by the wire time.
Back-to-back tests run each driver against its twin over a pty and over this link.
"""
from __future__ import annotations

import itertools
import socket
import threading

import serial

from .pty import PtyLink

SCHEME = "hwloop"

if "drivers.sim" not in serial.protocol_handler_packages:
    serial.protocol_handler_packages.append("drivers.sim")   # hwloop:// → protocol_hwloop

_lock = threading.Lock()
_ends: dict[str, socket.socket] = {}        # name → the driver's end, until the driver takes it
_names = itertools.count(1)


def take(name: str) -> socket.socket:
    """The driver's end of link ``name`` (once); OSError when there is no such link (unplugged)."""
    with _lock:
        end = _ends.pop(name, None)
    if end is None:
        raise OSError(f"{SCHEME}://{name}: no such link")
    return end


class LoopbackLink(PtyLink):
    """PtyLink's interface on a socket pair (vanish, restore, flush_input, is_open inherited)."""

    def __init__(self, name: str | None = None):
        super().__init__(None)
        self.name = name or f"link{next(_names)}"
        self._mine: socket.socket | None = None

    # ------------------------------------------------------------------ lifecycle
    def open(self) -> str:
        mine, theirs = socket.socketpair(socket.AF_UNIX, socket.SOCK_STREAM)
        mine.setblocking(False)
        with _lock:
            old = _ends.pop(self.name, None)
            _ends[self.name] = theirs
        if old is not None:
            old.close()
        self._mine, self.master = mine, mine.fileno()
        self.device = f"{SCHEME}://{self.name}"
        return self.device

    def close(self, remove_link: bool = True) -> None:
        """Both ends closed; vanish() (inherited) is close(): reopening fails until restore()."""
        if self._mine is not None:
            self._mine.close()
        with _lock:
            end = _ends.pop(self.name, None) if remove_link else None
        if end is not None:
            end.close()
        self._mine = self.master = None
        self.device = None

    # ------------------------------------------------------------------ I/O on the device side
    def read_available(self, limit: int = 4096) -> bytes:
        if self._mine is None:
            return b""
        try:
            return self._mine.recv(limit)
        except (BlockingIOError, InterruptedError):
            return b""
        except OSError:
            return b""

    def write(self, data: bytes) -> int:
        if self._mine is None:
            return 0
        try:
            return self._mine.send(data)
        except OSError:
            return 0
