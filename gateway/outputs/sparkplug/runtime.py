"""The MQTT side of a Sparkplug edge node: one thread, one paho session, one store.

One :class:`NodeRuntime` per edge node (per broker, group and edge node ID) in a process; the
stations of that node attach to it (:mod:`.output`, :class:`~.node_stations.NodeStations`). Its
thread owns the pure :class:`~.node.EdgeNode`, the node's paho session
(:class:`~.node_session.NodeSession`, on the one session engine
:class:`..broker.paho_session.PahoSession`) and its SQLite store (:class:`~.node_store.NodeStore`: the
bdSeq and the store-and-forward DDATA). Stations hand inputs over through one bounded
:class:`~gateway.plumbing.threadloop.Mailbox` (``post``; beyond its bound the oldest telemetry-only update
is dropped, counted), never blocking their slot loop; paho's callbacks run on this thread
(``client.loop``), so the state machine is only ever touched here. The node's outputs are carried
out here in order: a publish on the session, a session end after its network loop, a command to
its station.

The thread is supervised: a bad payload is counted and logged (:mod:`.inbound`, one line per kind
per minute) and never ends the session; anything else that escapes ends the session *uncleanly*
(the socket is dropped without DISCONNECT, so the broker publishes the Will: the host always gets
an NDEATH) and a new session starts after a back-off. Commands reach a station's loop through the
one thread→loop hand-over (:func:`gateway.plumbing.threadloop.submit_to`).

``servers`` is the Sparkplug 3.0 server set (§8.2): ``Node Control/Next Server``, the primary
host's STATE going offline and a server that cannot be reached move the node to the next one.
"""
from __future__ import annotations

import collections
import logging
import os
import threading
import time
from collections.abc import Iterable
from typing import Any

from ... import __version__
from ...plumbing.backoff import Backoff
from ...plumbing.ratelog import RateLog, safe
from ...plumbing.threadloop import Mailbox
from .actions import Action, Disconnect, Publish, Submit
from .inbound import InboundLimits
from .node import EdgeNode
from .node_session import NodeSession, now_ms
from .node_settings import SparkplugSettings
from .node_stations import NodeDevice, NodeStations, Result
from .node_store import NodeStore

log = logging.getLogger("hookwatch.sparkplug")

#: inputs waiting for the node thread at most (beyond: the oldest telemetry update is dropped)
QUEUE_MAX = 10_000
#: the first pause after the node thread failed (doubling up to reconnect_max_s)
CRASH_BACKOFF_MIN_S = 0.5


def _telemetry_only(it: tuple) -> bool:
    """The Mailbox's drop policy: a telemetry-only update may go (the oldest such first; when none
    waits, the oldest item of all), never a birth, a command reply or an event."""
    return bool(it[0] == "update" and it[3])


class NodeRuntime:
    """The edge node's thread: EdgeNode + its session + its store + its stations (see the module
    docstring)."""

    def __init__(self, s: SparkplugSettings):
        self.s = s
        self.counters: collections.Counter[str] = collections.Counter()
        self.store = NodeStore(s, self.counters)
        limits = InboundLimits(max_payload_bytes=int(s.max_command_bytes), max_metrics=int(s.max_command_metrics),
                               max_string_chars=int(s.max_string_chars), state_max_bytes=int(s.state_max_bytes))
        self.node = EdgeNode(s.group_id, s.edge_node_id, primary_host_id=s.primary_host_id,
                             last_bdseq=self.store.last_bdseq, software=f"hookwatch {__version__}", limits=limits,
                             rebirth_min_interval_ms=int(round(s.rebirth_min_interval_s * 1000)),
                             state_future_skew_ms=int(round(s.state_future_skew_s * 1000)),
                             buffer=self.store.buffer())
        self.session = NodeSession(s, self.node, self.store, self.counters, self._act, self._message)
        self.stations = NodeStations(self._result, self.post)
        self._q: Mailbox[tuple] = Mailbox(QUEUE_MAX, droppable=_telemetry_only)
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        #: bad payloads and internal errors: one line per kind per minute with a count
        self._rlog = RateLog(log)
        #: the back-off after a crash of the node thread (the one back-off, gateway/plumbing/backoff.py):
        #: doubling from CRASH_BACKOFF_MIN_S to reconnect_max_s, a new row after a minute's run
        self._crash = Backoff(CRASH_BACKOFF_MIN_S, max(s.reconnect_max_s, CRASH_BACKOFF_MIN_S),
                              stable_s=60.0)

    @property
    def outputs(self) -> dict[str, NodeDevice]:
        """The attached stations' outputs by device ID."""
        return self.stations.outputs

    # ------------------------------------------------------------------ any thread
    def post(self, item: tuple) -> None:
        self._q.put_nowait(item)

    def start(self) -> None:
        if self._thread is None:
            self.session.connect_after(self.s.gather_s)
            self._thread = threading.Thread(target=self._main, daemon=True,
                                            name=f"sparkplug-{self.s.edge_node_id}")
            self._thread.start()

    def stop(self, timeout: float = 5.0) -> None:
        self._stop.set()
        self._q.wake()
        if self._thread is not None:
            self._thread.join(timeout)
        self._rlog.close()          # the counts of the last window

    def figures(self) -> dict[str, Any]:
        """For the metrics endpoint (any thread): the node's identity, whether its session is up,
        and its counters (the runtime's and the node's; ``bad_<kind>``: bad payloads by kind)."""
        counters: dict[str, int] = {"dropped_updates": self._q.dropped}
        for src in (self.counters, self.node.counters):
            for _ in range(3):          # another thread may add a key while this one copies
                try:
                    counters.update(src)
                    break
                except RuntimeError:
                    continue
        return {"group": self.s.group_id, "node": self.s.edge_node_id, "connected": self.session.is_open,
                "counters": counters}

    # ------------------------------------------------------------------ node thread
    def _main(self) -> None:
        """Supervised: a failure is logged and counted, the session ends without DISCONNECT (the
        broker sends the Will, the NDEATH) and a new one starts after a back-off (doubling from
        CRASH_BACKOFF_MIN_S to ``reconnect_max_s``, reset by a session that lives a minute)."""
        try:
            while True:
                started = time.monotonic()
                try:
                    self._run()
                    break
                except Exception:
                    self.counters["crashes"] += 1
                    pause = self._crash.failed(time.monotonic() - started)
                    log.exception("sparkplug %s: node thread failed (%d so far); the session is dropped "
                                  "(the broker sends the NDEATH) and restarts in %.1f s, stored data stays "
                                  "in %s", self.s.edge_node_id, self.counters["crashes"], pause,
                                  self.s.store_path)
                    self.session.crashed()
                    if self._stop.wait(pause):
                        break
        finally:
            self.session.shut()
            self.store.close()

    def _run(self) -> None:
        while True:
            self._q.clear_wake()
            self._inputs()
            if self._stop.is_set():
                self._inputs()
                break
            self._housekeeping()
            if self.session.is_open:
                if self.node.replaying and self.node.publishing:
                    pubs, keys = self.node.drain(now_ms())
                    self._act(pubs)
                    self.node.buffer.remove(keys)
                self.session.network()
            else:
                wait = self.session.due_in()
                if wait <= 0:
                    self.session.connect()
                else:
                    self._q.wait(min(0.1, wait))

    def _housekeeping(self) -> None:
        """The coalesced rebirth when it is due; the rate-limited lines about bad inputs."""
        if self.session.is_open:
            self._act(self.node.tick(now_ms()))
        self._log_bad()

    def _log_bad(self) -> None:
        for kind, reason in self.node.take_bad():
            self._rlog.warning(("bad", kind), "sparkplug %s: a bad payload on %s ignored (counted: "
                               "hookwatch_sparkplug_bad_payloads_total): %s", self.s.edge_node_id,
                               kind, reason)

    def _inputs(self) -> None:
        for item in self._q.drain():
            kind = item[0]
            now = now_ms()
            if kind == "up":
                self._act(self.node.device_up(item[1], item[2], now))
            elif kind == "update":
                self._act(self.node.device_update(item[1], item[2], now))
            elif kind == "down":
                self._act(self.node.device_down(item[1], now))
            elif kind == "result":
                self._result(item[1:])

    def _result(self, r: Result) -> None:
        """A command's outcome: the device's Last Command and Last Result Code."""
        dev, ck, ok, code, reason = r
        self._act(self.node.command_result(dev, ck, ok, code, reason, now_ms()))

    def _act(self, outs: Iterable[Action]) -> None:
        for o in outs:
            if isinstance(o, Publish):
                self.session.publish(o)
            elif isinstance(o, Disconnect):
                self.session.end_after_loop(o)
            elif isinstance(o, Submit):
                self.stations.submit(o)

    def _message(self, topic: str, payload: bytes) -> None:
        """Whatever arrives: handled within bounds (bad payloads are counted by the node); an
        error of our own here is counted and logged, the message dropped, the session goes on."""
        try:
            now = now_ms()
            if topic == self.node.topics.state_topic():
                self._act(self.node.host_state(payload, now))
            else:
                self._act(self.node.command(topic, payload, now))
        except Exception as e:  # noqa: BLE001 - one message must not end the session
            self.counters["message_errors"] += 1
            self._rlog.log("internal", logging.ERROR, "sparkplug %s: handling a message on %s failed: "
                           "%s: %s", self.s.edge_node_id, safe(topic, 80), type(e).__name__,
                           str(e)[:120], exc_info=True)
        self._log_bad()


# ---------------------------------------------------------------------- one runtime per node
_RUNTIMES: dict[tuple, NodeRuntime] = {}
_RT_LOCK = threading.Lock()


def node_figures() -> list[dict[str, Any]]:
    """:meth:`NodeRuntime.figures` of every edge node this process runs (the metrics endpoint)."""
    with _RT_LOCK:
        rts = list(_RUNTIMES.values())
    return sorted((rt.figures() for rt in rts), key=lambda f: (f["group"], f["node"]))


def attach(s: SparkplugSettings, output: NodeDevice) -> NodeRuntime:
    with _RT_LOCK:
        rt = _RUNTIMES.get(s.node_key())
        if rt is None:
            rt = _RUNTIMES[s.node_key()] = NodeRuntime(s)
        rt.outputs[s.device_id] = output
        rt.start()
        return rt


def detach(s: SparkplugSettings) -> NodeRuntime | None:
    """Remove a station; the last one stops the node (NDEATH, disconnect). Returns the runtime to
    join when it was the last."""
    with _RT_LOCK:
        rt = _RUNTIMES.get(s.node_key())
        if rt is None:
            return None
        rt.outputs.pop(s.device_id, None)
        if rt.outputs:
            return None
        del _RUNTIMES[s.node_key()]
        return rt


def default_store(records_dir: str, group_id: str, edge_node_id: str) -> str:
    return os.path.join(records_dir, f"sparkplug-{group_id}-{edge_node_id}.sqlite")
