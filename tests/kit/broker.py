"""A real Mosquitto on a free loopback port, mosquitto_sub as a subscriber, mosquitto_pub."""
from __future__ import annotations

import getpass
import json
import subprocess
import threading
import time

from kit.proc import stop_process
from kit.tools import free_port, require_tool, wait_for, wait_port


class Broker:
    """Mosquitto on a free loopback port; ``persistent`` keeps sessions across restarts."""

    def __init__(self, tmp_path, persistent: bool = False, port: int | None = None):
        self.exe = require_tool("mosquitto")
        self.port = port or free_port()
        self.dir = tmp_path / f"broker-{self.port}"
        self.dir.mkdir(exist_ok=True)
        self.conf = self.dir / "mosquitto.conf"
        # as root, mosquitto would drop to user `mosquitto`, who may not write to the test folder
        lines = [f"user {getpass.getuser()}", f"listener {self.port} 127.0.0.1", "allow_anonymous true",
                 f"persistence {'true' if persistent else 'false'}",
                 f"persistence_location {self.dir}/", "autosave_interval 1",
                 "max_queued_messages 100000", "log_type error", "log_type warning",
                 f"log_dest file {self.dir}/mosquitto.log"]
        self.conf.write_text("\n".join(lines) + "\n")
        self.p: subprocess.Popen | None = None

    def start(self) -> Broker:
        self.p = subprocess.Popen([self.exe, "-c", str(self.conf)], stdout=subprocess.DEVNULL,
                                  stderr=subprocess.DEVNULL)
        wait_port(self.port)
        return self

    def stop(self) -> None:
        stop_process(self.p, timeout=10)
        self.p = None

    def __enter__(self):
        return self.start()

    def __exit__(self, *exc):
        self.stop()


class Sub:
    """mosquitto_sub printing `retain<TAB>topic<TAB>payload` lines, collected by a thread."""

    def __init__(self, port: int, topic: str, *, qos: int = 1, client_id: str | None = None,
                 clean: bool = True, extra: list[str] | None = None):
        exe = require_tool("mosquitto_sub")
        argv = [exe, "-h", "127.0.0.1", "-p", str(port), "-t", topic, "-q", str(qos),
                "-F", "%r\t%t\t%p", "-k", "5"]
        if client_id:
            argv += ["-i", client_id]
        if not clean:
            argv += ["-c"]
        argv += extra or []
        self.p = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        self.lines: list[tuple[bool, str, str, float]] = []
        self._lock = threading.Lock()
        self._t = threading.Thread(target=self._read, daemon=True)
        self._t.start()

    def _read(self) -> None:
        for line in self.p.stdout:
            line = line.rstrip("\n")
            parts = line.split("\t", 2)
            if len(parts) == 3:
                with self._lock:
                    self.lines.append((parts[0] == "1", parts[1], parts[2], time.time()))

    def messages(self, suffix: str | None = None) -> list[tuple[bool, str, dict, float]]:
        with self._lock:
            lines = list(self.lines)
        out = []
        for r, t, p, ts in lines:
            if suffix is not None and not (t == suffix or t.endswith("/" + suffix)):
                continue
            try:
                out.append((r, t, json.loads(p), ts))
            except json.JSONDecodeError:
                out.append((r, t, {"_raw": p}, ts))
        return out

    def wait(self, cond, timeout: float = 20.0, what: str = "messages"):
        return wait_for(lambda: cond(self), timeout, what=what)

    def stop(self) -> None:
        stop_process(self.p, timeout=5)
        self._t.join(5)
        self.p.stdout.close()
        self.p.stderr.close()


def pub(port: int, topic: str, payload: str, *, retain: bool = False, qos: int = 1) -> None:
    exe = require_tool("mosquitto_pub")
    argv = [exe, "-h", "127.0.0.1", "-p", str(port), "-t", topic, "-m", payload, "-q", str(qos)]
    if retain:
        argv.append("-r")
    subprocess.run(argv, check=True, timeout=20)
