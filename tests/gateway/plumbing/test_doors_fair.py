"""Issue 27 item 7, fair doors: one client re-opening 300 idle sockets (every one the door closes
is opened again at once) must not starve another client of the console or of the metrics
endpoint. Over real sockets: the hostile client from 127.0.0.1, the operator's GETs and
Prometheus' scrapes from 127.0.0.2; every request of theirs is answered (no latency is asserted:
each has a generous timeout, and a refused or reset connection counts as not answered)."""
from __future__ import annotations

import errno
import http.client
import selectors
import socket
import threading
import time

from gateway.outputs.console import auth
from gateway.outputs.console.app import ConsoleServer
from gateway.outputs.console.settings import ConsoleSettings
from gateway.outputs.prometheus.http import Endpoint

HOSTILE = "127.0.0.1"
OPERATOR = "127.0.0.2"
SOCKETS = 300


class Reopener:
    """``n`` idle sockets from ``source`` to ``port``: each one the server closes is opened again
    at once (the hostile client of issue 27); it never sends a byte."""

    def __init__(self, port: int, n: int = SOCKETS, source: str = HOSTILE):
        self.port, self.n, self.source = port, n, source
        self.sel = selectors.DefaultSelector()
        self.stop = threading.Event()
        self.opened = 0
        self.closed_by_server = 0
        self.t = threading.Thread(target=self._run, daemon=True)

    def _open(self) -> None:
        s = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        s.setblocking(False)
        s.bind((self.source, 0))
        err = s.connect_ex(("127.0.0.1", self.port))
        if err not in (0, errno.EINPROGRESS):
            s.close()
            return
        self.opened += 1
        self.sel.register(s, selectors.EVENT_READ)

    def _run(self) -> None:
        for _ in range(self.n):
            self._open()
        while not self.stop.is_set():
            for key, _ in self.sel.select(0.1):
                s = key.fileobj
                try:
                    data = s.recv(4096)
                except OSError:
                    data = b""
                if data:
                    continue
                self.sel.unregister(s)
                s.close()
                self.closed_by_server += 1
                if not self.stop.is_set():
                    self._open()
            while len(self.sel.get_map()) < self.n and not self.stop.is_set():
                self._open()

    def __enter__(self) -> Reopener:
        self.t.start()
        return self

    def __exit__(self, *exc) -> None:
        self.stop.set()
        self.t.join(10)
        for key in list(self.sel.get_map().values()):
            key.fileobj.close()
        self.sel.close()


def _get(port: int, path: str, source: str = OPERATOR, timeout: float = 30.0) -> int | None:
    """One GET from ``source`` on a new connection: its status, or None when the connection
    was refused, reset or not answered within ``timeout``."""
    c = http.client.HTTPConnection("127.0.0.1", port, timeout=timeout, source_address=(source, 0))
    try:
        c.request("GET", path, headers={"Host": f"127.0.0.1:{port}"})
        r = c.getresponse()
        r.read()
        return r.status
    except (OSError, http.client.HTTPException):
        return None
    finally:
        c.close()


def _until(cond, timeout: float, what: str) -> None:
    t_end = time.monotonic() + timeout
    while not cond():
        assert time.monotonic() < t_end, what
        time.sleep(0.05)


def test_300_reopened_idle_sockets_from_one_address_do_not_starve_the_operators_console(tmp_path):
    users = str(tmp_path / "u.json")
    auth.add_user(users, "alice", "a long password")
    srv = ConsoleServer(ConsoleSettings(listen=("127.0.0.1:0",), users_file=users),
                        {"s1": str(tmp_path / "s1")})
    url = srv.start()[0].rstrip("/")
    port = int(url.rsplit(":", 1)[1])
    try:
        with Reopener(port) as hostile:
            _until(lambda: srv.door is not None and srv.door.connections >= 20, 30,
                   "the hostile client's sockets accepted")
            time.sleep(1.0)
            answers = [_get(port, "/api/session") for _ in range(13)]
            assert answers == [200] * 13, answers
            held = srv.door.per_address.get(HOSTILE, 0)
            refused = srv.door.counters["refused_per_address"]
        # the hostile address never held more than its share, and was told so (counted)
        assert held <= srv.settings.door.max_per_address, held
        assert refused > 0 and hostile.closed_by_server > 0
    finally:
        srv.stop()


def test_300_reopened_idle_sockets_from_one_address_do_not_starve_prometheus():
    ep = Endpoint("127.0.0.1", 0)
    try:
        _until(lambda: ep.listening.is_set(), 10, "the endpoint listening")
        port = ep.address[1]
        with Reopener(port) as hostile:
            _until(lambda: ep.door is not None and ep.door.connections >= ep.door.limits.max_per_address,
                   30, "the hostile client's sockets accepted")
            time.sleep(1.0)
            answers = [_get(port, "/metrics") for _ in range(15)]
            assert answers == [200] * 15, answers
            held = ep.door.per_address.get(HOSTILE, 0)
        assert held <= ep.limits.max_per_address, held
        assert ep.door.counters["refused_per_address"] > 0 and hostile.closed_by_server > 0
    finally:
        ep.shutdown()


def test_at_the_cap_a_newcomer_closes_a_connection_of_the_address_holding_the_most(tmp_path):
    """Several hostile addresses together fill the console's cap (each within its per-address
    share): the operator's address, holding none, still gets in — the door closes the oldest
    connection of the address holding the most instead of the operator's."""
    users = str(tmp_path / "u.json")
    auth.add_user(users, "alice", "a long password")
    from gateway.plumbing.doors import DoorLimits
    srv = ConsoleServer(ConsoleSettings(listen=("127.0.0.1:0",), users_file=users,
                                        door=DoorLimits(24, 10.0, 60.0, max_per_address=10)),
                        {"s1": str(tmp_path / "s1")})
    url = srv.start()[0].rstrip("/")
    port = int(url.rsplit(":", 1)[1])
    held: list[socket.socket] = []
    try:
        for i in range(30):              # 10 each from three addresses: 24 fit, 6 are refused
            s = socket.create_connection(("127.0.0.1", port), timeout=5,
                                         source_address=(f"127.0.3.{1 + i % 3}", 0))
            held.append(s)
        _until(lambda: srv.door.counters["accepted"] + srv.door.counters["refused_connections"] >= 30,
               20, "the 30 connects seen")
        assert srv.door.connections == 24
        answers = [_get(port, "/api/session") for _ in range(5)]
        assert answers == [200] * 5, answers
        assert srv.door.counters["evicted"] >= 1
        assert max(srv.door.per_address.get(f"127.0.3.{k}", 0) for k in (1, 2, 3)) <= 10
    finally:
        for s in held:
            s.close()
        srv.stop()


