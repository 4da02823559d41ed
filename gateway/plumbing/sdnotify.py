"""systemd notifications (sd_notify(3)) without libsystemd: READY, STATUS, WATCHDOG, STOPPING.

Messages go as one datagram to the unix socket named by ``$NOTIFY_SOCKET`` (a path, or an abstract
socket written with a leading ``@``). Without ``$NOTIFY_SOCKET`` — not started by systemd, or a unit
that is not ``Type=notify`` — every call is a no-op. Never raises: a lost notification must not take
the station down (systemd's watchdog notices a gateway that stopped notifying).
"""
from __future__ import annotations

import os
import socket

__all__ = ["notify", "ready", "status", "watchdog", "stopping", "watchdog_interval_s", "enabled"]


def _address() -> str | bytes | None:
    addr = os.environ.get("NOTIFY_SOCKET")
    if not addr:
        return None
    if addr.startswith("@"):
        return "\0" + addr[1:]       # abstract namespace
    if addr.startswith("/"):
        return addr
    return None                      # vsock:… and other forms are not used by the units we ship


def enabled() -> bool:
    return _address() is not None


def notify(*lines: str) -> bool:
    """Send ``KEY=VALUE`` lines as one datagram; True if it was sent."""
    addr = _address()
    if addr is None:
        return False
    msg = "\n".join(lines).encode("utf-8", "replace")
    try:
        with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM | socket.SOCK_CLOEXEC) as s:
            s.connect(addr)
            s.sendall(msg)
        return True
    except OSError:
        return False


def ready(text: str | None = None) -> bool:
    """Start-up is done (a ``Type=notify`` unit becomes active now)."""
    return notify("READY=1", f"MAINPID={os.getpid()}", *((f"STATUS={_one_line(text)}",) if text else ()))


def status(text: str) -> bool:
    """A one-line status that `systemctl status` shows."""
    return notify(f"STATUS={_one_line(text)}")


def watchdog() -> bool:
    """Keep-alive for ``WatchdogSec=``: send it from the loop that must stay alive."""
    return notify("WATCHDOG=1")


def stopping(text: str | None = None) -> bool:
    """A clean shutdown has begun."""
    return notify("STOPPING=1", *((f"STATUS={_one_line(text)}",) if text else ()))


def watchdog_interval_s() -> float | None:
    """Half of the unit's ``WatchdogSec=`` (the recommended keep-alive period), or None."""
    usec = os.environ.get("WATCHDOG_USEC")
    pid = os.environ.get("WATCHDOG_PID")
    if not usec or (pid and pid != str(os.getpid())):
        return None
    try:
        v = int(usec)
    except ValueError:
        return None
    return v / 2e6 if v > 0 else None


def _one_line(text: str) -> str:
    return " ".join(str(text).split())
