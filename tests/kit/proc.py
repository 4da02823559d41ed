"""Processes in tests: ONE way to stop one (signal, wait, kill after a timeout) and a process
whose stdout is read line by line."""
from __future__ import annotations

import os
import signal
import subprocess
import threading
import time
import weakref

from conftest import ROOT


def read_log(path, tail: int | None = 4000) -> str:
    """The end of a process' log file ("" when there is none)."""
    try:
        with open(path) as f:
            text = f.read()
    except OSError:
        return ""
    return text if tail is None else text[-tail:]


def stop_process(p: subprocess.Popen | None, sig: int = signal.SIGTERM, timeout: float = 15.0) -> int | None:
    """Send ``sig`` to a running process, wait ``timeout`` s, then SIGKILL; the exit code
    (None for no process). Pipes are left to their owner."""
    if p is None:
        return None
    if p.poll() is None:
        try:
            p.send_signal(sig)
        except ProcessLookupError:
            pass
        try:
            p.wait(timeout)
        except subprocess.TimeoutExpired:
            p.kill()
            p.wait()
    return p.returncode


#: every Proc not yet stopped (tests/conftest.py stops what a test leaves running)
LIVE: weakref.WeakSet[Proc] = weakref.WeakSet()
#: how much ahead of the test workers' own work (reports, fuzzing, campaigns) a Proc runs: the
#: gateways, simulators and demos a test starts are 50 Hz real-time processes — deployed, the slot
#: loop runs under SCHED_FIFO and the meter is hardware of its own — and on the 2-core box with 4
#: xdist workers one of them was once held 0.3 s by the CPU-bound tests around it (the STM32's
#: watchdog stopped the motor). Needs root or CAP_SYS_NICE (CI runs as root); elsewhere nothing
#: changes
PROC_NICE = -10


def _ahead_of_the_batch_work() -> None:
    try:
        os.setpriority(os.PRIO_PROCESS, 0, PROC_NICE)
    except OSError:
        pass


class Proc:
    """A process whose stdout lines are collected by a thread and whose stderr goes to a log."""

    def __init__(self, argv, log_path, env=None):
        LIVE.add(self)
        self.log_path = log_path
        self._log = open(log_path, "w")
        self.p = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=self._log, text=True,
                                  env=env, cwd=ROOT, preexec_fn=_ahead_of_the_batch_work)
        # stdout is read by a thread: a select() on the pipe would miss lines already buffered
        self._lines: list[str] = []
        self._next = 0
        self._eof = False
        self._cond = threading.Condition()
        self._reader = threading.Thread(target=self._pump, daemon=True)
        self._reader.start()

    def _pump(self) -> None:
        for line in self.p.stdout:
            with self._cond:
                self._lines.append(line)
                self._cond.notify_all()
        with self._cond:
            self._eof = True
            self._cond.notify_all()

    def readline_until(self, prefix: str, timeout: float = 20.0) -> str:
        """The rest of the first stdout line (not yet consumed) that starts with ``prefix``."""
        t_end = time.monotonic() + timeout
        with self._cond:
            while True:
                while self._next < len(self._lines):
                    line = self._lines[self._next]
                    self._next += 1
                    if line.startswith(prefix):
                        return line[len(prefix):].strip()
                left = t_end - time.monotonic()
                if self._eof or left <= 0:
                    break
                self._cond.wait(left)
        raise AssertionError(f"no '{prefix}' line from {self.p.args}; log:\n{self.log()}")

    def stdout_lines(self) -> list[str]:
        with self._cond:
            return list(self._lines)

    def log_all(self) -> str:
        return read_log(self.log_path, None)

    def log(self) -> str:
        return read_log(self.log_path)

    def stop(self, sig=signal.SIGTERM, timeout: float = 15.0) -> int:
        LIVE.discard(self)
        stop_process(self.p, sig, timeout)
        self._reader.join(5)
        with self._cond:
            out = "".join(self._lines[self._next:])
        if self.p.stdout:
            self.p.stdout.close()
        self._log.close()
        self.stdout_rest = out
        return self.p.returncode
