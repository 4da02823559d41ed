"""Small helpers shared by the serial drivers (meter, STM32)."""
from __future__ import annotations

import select

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
