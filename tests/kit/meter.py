"""The virtual ZN-S meter as a separate process (``python -m drivers.sim.meter``), driven over stdin:
fault switches, vanish/restore, counters."""
from __future__ import annotations

import json
import os
import selectors
import subprocess
import sys
import time

from conftest import ROOT
from kit.proc import read_log, stop_process


class MeterProcess:
    def __init__(self, log_path, *args: str, link: str | None = None):
        argv = [sys.executable, "-m", "drivers.sim.meter", *args]
        if link:
            argv += ["--link", link]
        self.log_path = str(log_path)
        self._log = open(self.log_path, "w")
        self.p = subprocess.Popen(argv, stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                                  stderr=self._log, cwd=ROOT)
        self.link = link
        self._buf = b""
        try:
            self.device = self.expect("meter: ")
        except BaseException:
            self.stop()
            raise

    @property
    def path(self) -> str:
        return self.link or self.device

    def expect(self, prefix: str, timeout: float = 20.0) -> str:
        """The rest of the next stdout line starting with prefix (own line buffer: a buffered
        readline() would hide lines from select())."""
        fd = self.p.stdout.fileno()
        t_end = time.monotonic() + timeout
        with selectors.DefaultSelector() as sel:
            sel.register(fd, selectors.EVENT_READ)
            while True:
                while b"\n" in self._buf:
                    raw, self._buf = self._buf.split(b"\n", 1)
                    line = raw.decode()
                    if line.startswith(prefix):
                        return line[len(prefix):].strip()
                    if line.startswith("error:"):
                        raise AssertionError(f"virtual meter: {line.strip()}")
                left = t_end - time.monotonic()
                if left <= 0 or not sel.select(left):
                    break
                chunk = os.read(fd, 4096)
                if not chunk:
                    break
                self._buf += chunk
        raise AssertionError(f"no '{prefix}' line from the virtual meter; log:\n{self.log()}")

    def command(self, line: str, reply: str = "ok: ") -> str:
        self.p.stdin.write((line + "\n").encode())
        self.p.stdin.flush()
        return self.expect(reply)

    def counters(self) -> dict:
        return json.loads(self.command("counters", "counters: "))

    def log(self) -> str:
        return read_log(self.log_path)

    def stop(self) -> None:
        stop_process(self.p, timeout=10)
        for f in (self.p.stdin, self.p.stdout):
            if f:
                try:
                    f.close()
                except OSError:
                    pass
        self._log.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.stop()
