"""The virtual ZN-S meter as a separate process (``python -m drivers.sim.meter``), driven over stdin:
fault switches, vanish/restore, counters."""
from __future__ import annotations

import json
import selectors
import subprocess
import sys
import time

from conftest import ROOT


class MeterProcess:
    def __init__(self, log_path, *args: str, link: str | None = None):
        argv = [sys.executable, "-m", "drivers.sim.meter", *args]
        if link:
            argv += ["--link", link]
        self.log_path = str(log_path)
        self._log = open(self.log_path, "w")
        self.p = subprocess.Popen(argv, stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                                  stderr=self._log, text=True, cwd=ROOT)
        self.link = link
        try:
            self.device = self.expect("meter: ")
        except BaseException:
            self.stop()
            raise

    @property
    def path(self) -> str:
        return self.link or self.device

    def expect(self, prefix: str, timeout: float = 20.0) -> str:
        sel = selectors.DefaultSelector()
        sel.register(self.p.stdout, selectors.EVENT_READ)
        t_end = time.monotonic() + timeout
        try:
            while time.monotonic() < t_end:
                if not sel.select(max(0.0, t_end - time.monotonic())):
                    break
                line = self.p.stdout.readline()
                if not line:
                    break
                if line.startswith(prefix):
                    return line[len(prefix):].strip()
                if line.startswith("error:"):
                    raise AssertionError(f"virtual meter: {line.strip()}")
        finally:
            sel.close()
        raise AssertionError(f"no '{prefix}' line from the virtual meter; log:\n{self.log()}")

    def command(self, line: str, reply: str = "ok: ") -> str:
        self.p.stdin.write(line + "\n")
        self.p.stdin.flush()
        return self.expect(reply)

    def counters(self) -> dict:
        return json.loads(self.command("counters", "counters: "))

    def log(self) -> str:
        try:
            with open(self.log_path) as f:
                return f.read()[-4000:]
        except OSError:
            return ""

    def stop(self) -> None:
        if self.p.poll() is None:
            self.p.terminate()
            try:
                self.p.wait(10)
            except subprocess.TimeoutExpired:
                self.p.kill()
                self.p.wait()
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
