"""Helpers for tests that need real external tools and free loopback ports."""
import os
import shutil
import socket
import subprocess
import time

import pytest

IN_CI = os.environ.get("CI", "").lower() in ("1", "true", "yes")


def require_tool(name: str) -> str:
    """Path of a tool the test needs: skip locally when it is missing, fail under CI=true."""
    path = shutil.which(name) or (f"/usr/sbin/{name}" if os.path.exists(f"/usr/sbin/{name}") else None)
    if path is None:
        msg = f"{name} is not installed (Debian: apt-get install {name})"
        if IN_CI:
            pytest.fail(msg + " — CI must install it (scripts/setup.sh --tools)")
        pytest.skip(msg)
    return path


def free_port(host: str = "127.0.0.1") -> int:
    with socket.socket() as s:
        s.bind((host, 0))
        return s.getsockname()[1]


def wait_port(port: int, timeout: float = 20.0, host: str = "127.0.0.1",
              proc: subprocess.Popen | None = None) -> None:
    """Until something accepts on host:port (fails at once when ``proc`` exits first)."""
    t_end = time.monotonic() + timeout
    while time.monotonic() < t_end:
        if proc is not None and proc.poll() is not None:
            raise AssertionError(f"process exited with {proc.returncode}")
        try:
            with socket.create_connection((host, port), timeout=0.5):
                return
        except OSError:
            time.sleep(0.05)
    raise AssertionError(f"nothing listens on {host}:{port} after {timeout} s")


def wait_for(cond, timeout: float = 20.0, interval: float = 0.05, what: str = "condition"):
    t_end = time.monotonic() + timeout
    while True:
        v = cond()
        if v:
            return v
        if time.monotonic() > t_end:
            raise AssertionError(f"timed out after {timeout} s waiting for {what}")
        time.sleep(interval)


def connect_many(port: int, n: int, src: str | None = None, within_s: float = 30.0) -> list[socket.socket]:
    """Up to ``n`` idle connections to a loopback ``port`` (from ``src``.2, ``src``.3, … when
    given), for at most ``within_s`` (a server that stopped accepting makes each connect wait for
    its timeout). The caller closes them."""
    out = []
    t_end = time.monotonic() + within_s
    for i in range(n):
        if time.monotonic() > t_end:
            break
        try:
            kw = {"source_address": (f"{src}.{2 + i % 250}", 0)} if src else {}
            out.append(socket.create_connection(("127.0.0.1", port), timeout=1, **kw))
        except OSError:
            pass
    return out


def http_status(url: str) -> int:
    """The HTTP status of a GET of ``url`` (0: no answer)."""
    import urllib.error
    import urllib.request
    try:
        with urllib.request.urlopen(url, timeout=5) as r:
            r.read()
            return int(r.status)
    except urllib.error.HTTPError as e:
        return int(e.code)
    except OSError:
        return 0

