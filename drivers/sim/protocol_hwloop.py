"""pyserial URL handler for ``hwloop://<name>``: the driver's end of a
:class:`~drivers.sim.loopback.LoopbackLink` as a ``serial.Serial`` (registered by importing
:mod:`drivers.sim.loopback`). Line settings (baud, parity) are accepted and have no effect, as on
a pseudo-terminal."""
from __future__ import annotations

import select
import socket
from typing import Any

from serial.serialutil import PortNotOpenError, SerialBase, SerialException, Timeout

from . import loopback


class Serial(SerialBase):
    _sock: socket.socket | None = None

    def open(self) -> None:
        if self._port is None:
            raise SerialException("port must be configured before it can be used")
        if self.is_open:  # type: ignore[has-type]
            raise SerialException("port already open")
        name = str(self.portstr).split("://", 1)[-1]
        try:
            self._sock = loopback.take(name)
        except OSError as e:
            raise SerialException(str(e)) from None
        self._sock.setblocking(False)
        self.is_open = True

    def _reconfigure_port(self, *args: Any, **kw: Any) -> None:
        pass

    def close(self) -> None:
        if self._sock is not None:
            self._sock.close()
            self._sock = None
        self.is_open = False

    def fileno(self) -> int:
        if self._sock is None:
            raise PortNotOpenError()
        return self._sock.fileno()

    @property
    def in_waiting(self) -> int:
        if self._sock is None:
            raise PortNotOpenError()
        r, _, _ = select.select([self._sock], [], [], 0)
        if not r:
            return 0
        try:
            return len(self._sock.recv(65536, socket.MSG_PEEK))
        except BlockingIOError:
            return 0

    def read(self, size: int = 1) -> bytes:
        if self._sock is None:
            raise PortNotOpenError()
        out = bytearray()
        timeout = Timeout(self._timeout)
        while len(out) < size:
            try:
                chunk = self._sock.recv(size - len(out))
            except BlockingIOError:
                chunk = None
            if chunk == b"":
                raise SerialException("device reports readiness to read but returned no data "
                                      "(device disconnected?)")
            if chunk:
                out += chunk
                continue
            if timeout.expired():
                break
            left = timeout.time_left()
            select.select([self._sock], [], [], None if left is None else max(left, 0.0))
        return bytes(out)

    def write(self, data: bytes) -> int:   # type: ignore[override]
        if self._sock is None:
            raise PortNotOpenError()
        try:
            return self._sock.send(bytes(data))
        except BlockingIOError:
            return 0
        except OSError as e:
            raise SerialException(f"write failed: {e}") from None

    def reset_input_buffer(self) -> None:
        if self._sock is None:
            raise PortNotOpenError()
        while True:
            try:
                if not self._sock.recv(4096):
                    return
            except BlockingIOError:
                return

    def reset_output_buffer(self) -> None:
        pass

    def flush(self) -> None:
        pass

    @property
    def cts(self) -> bool:
        return True

    @property
    def dsr(self) -> bool:
        return True

    @property
    def ri(self) -> bool:
        return False

    @property
    def cd(self) -> bool:
        return True
