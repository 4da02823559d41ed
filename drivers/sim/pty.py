"""A serial port emulated by a pseudo-terminal.

The simulator holds the master side; the gateway opens the slave device (``/dev/pts/N``) or, better,
the stable symlink that points at it. A pty has no baud rate: whoever emulates a device must delay
its replies by the real wire time itself.

``vanish()`` closes both sides, so the device node disappears and a client's open file gets an
error, exactly like a USB–RS-485 adapter that is pulled out; ``restore()`` opens a new pty and points
the symlink at it (the node name usually changes, as it does when an adapter is plugged back in).
"""
from __future__ import annotations

import errno
import os
import termios
import tty


class PtyLink:
    def __init__(self, link_path: str | None = None):
        self.link_path = link_path
        self.master: int | None = None
        self._slave: int | None = None
        self.device: str | None = None

    # ------------------------------------------------------------------ lifecycle
    def open(self) -> str:
        """Create the pty (raw mode, non-blocking master) and the symlink; return the device path."""
        master, slave = os.openpty()
        tty.setraw(slave, termios.TCSANOW)
        attrs = termios.tcgetattr(slave)
        attrs[3] &= ~termios.ECHO
        termios.tcsetattr(slave, termios.TCSANOW, attrs)
        os.set_blocking(master, False)
        # keep our own slave fd open: the master then never sees EIO while no client is attached
        self.master, self._slave = master, slave
        self.device = os.ttyname(slave)
        if self.link_path:
            tmp = f"{self.link_path}.tmp{os.getpid()}"
            try:
                os.unlink(tmp)
            except FileNotFoundError:
                pass
            os.symlink(self.device, tmp)
            os.replace(tmp, self.link_path)
        return self.device

    @property
    def is_open(self) -> bool:
        return self.master is not None

    def close(self, remove_link: bool = True) -> None:
        for fd in (self.master, self._slave):
            if fd is not None:
                try:
                    os.close(fd)
                except OSError:
                    pass
        self.master = self._slave = None
        self.device = None
        if remove_link and self.link_path:
            try:
                os.unlink(self.link_path)
            except FileNotFoundError:
                pass

    def vanish(self) -> None:
        """The adapter is pulled out: device node and symlink disappear."""
        self.close(remove_link=True)

    def restore(self) -> str:
        """The adapter is plugged back in: a new pty, the symlink points at it."""
        if self.master is not None:
            return self.device or ""
        return self.open()

    # ------------------------------------------------------------------ I/O on the master side
    def read_available(self, limit: int = 4096) -> bytes:
        """Whatever the client has written so far (b'' if nothing, or if the pty is gone)."""
        if self.master is None:
            return b""
        try:
            return os.read(self.master, limit)
        except BlockingIOError:
            return b""
        except OSError as e:
            if e.errno in (errno.EIO, errno.EBADF):
                return b""
            raise

    def write(self, data: bytes) -> int:
        """Send bytes to the client at once (the caller has already waited the wire time)."""
        if self.master is None:
            return 0
        try:
            return os.write(self.master, data)
        except (BlockingIOError, OSError):
            return 0

    def flush_input(self) -> None:
        """Discard what the client sent and nobody read yet."""
        while self.read_available():
            pass


def frame_time_s(n_bytes: int, baud: int, bits_per_char: int = 11) -> float:
    """Wire time of n bytes on a UART: 11 bits a character for Modbus RTU (start, 8 data,
    parity or a second stop bit, stop)."""
    return n_bytes * bits_per_char / float(baud)
