"""A small file system for disk-full tests: a tmpfs of a given size (mount as root). Under
CI=true a missing capability fails instead of skipping (the tests would otherwise never run)."""
from __future__ import annotations

import contextlib
import errno
import os
import subprocess

import pytest


@contextlib.contextmanager
def small_tmpfs(path, size: str = "4m"):
    path = str(path)
    os.makedirs(path, exist_ok=True)
    p = subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size},mode=0755", "tmpfs", path],
                       capture_output=True, text=True)
    if p.returncode != 0:
        msg = f"cannot mount a tmpfs here (root needed): {p.stderr.strip()}"
        if os.environ.get("CI") == "true":
            pytest.fail(msg)
        pytest.skip(msg)
    try:
        yield path
    finally:
        subprocess.run(["chattr", "-R", "-i", path], capture_output=True)
        subprocess.run(["umount", "-l", path], capture_output=True)


def fill(path: str) -> str:
    """Fill the file system holding ``path`` to the last byte; returns the filler's path."""
    filler = os.path.join(path, "filler.bin")
    fd = os.open(filler, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
    chunk = b"\0" * 65536
    try:
        while True:
            try:
                os.write(fd, chunk)
            except OSError as e:
                if e.errno != errno.ENOSPC:
                    raise
                if len(chunk) == 1:
                    break
                chunk = chunk[: len(chunk) // 2]
    finally:
        os.close(fd)
    return filler
