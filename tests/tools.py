"""Helpers for tests that need real external tools and free loopback ports."""
import os
import shutil
import socket

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
