"""The MQTT side of a Sparkplug edge node: one paho-mqtt 2.x client, one thread, one store.

One :class:`NodeRuntime` per edge node (per broker, group and edge node ID) in a process; the
stations of that node attach to it (:mod:`.output`). Its thread owns the paho client, the pure
:class:`~.node.EdgeNode` and the SQLite outbox (:mod:`gateway.northbound.outbox`, public API
only) that holds the bdSeq and the store-and-forward DDATA. Stations hand inputs over through one
bounded :class:`~gateway.threadloop.Mailbox` (``post``; beyond its bound the oldest telemetry-only
update is dropped, counted), never blocking their slot loop; paho's callbacks run on this thread
(``client.loop``), so the state machine is only ever touched here.

Each connection attempt takes the next bdSeq, persists it (kill -9 safe: a WAL commit), and
builds a new client whose Will is the NDEATH with that bdSeq, QoS 1, not retained, set before
CONNECT.

The thread is supervised: a bad payload is counted and logged (:mod:`.inbound`, one line per kind
per minute) and never ends the session; anything else that escapes ends the session *uncleanly*
(the socket is dropped without DISCONNECT, so the broker publishes the Will: the host always gets
an NDEATH) and a new session starts after a back-off. Commands reach a station's loop through the
one thread→loop hand-over (:func:`gateway.threadloop.submit_to`).

``servers`` is the Sparkplug 3.0 server set (§8.2): ``Node Control/Next Server``, the primary
host's STATE going offline and a server that cannot be reached move the node to the next one. The
server list, the back-off, the client's set-up and the unclean drop are the session engine it
shares with the JSON tree's pump (:class:`..paho_session.PahoSession`).
"""
from __future__ import annotations

import collections
import logging
import os
import sqlite3
import threading
import time
from concurrent.futures import Future
from dataclasses import dataclass
from typing import Any, ClassVar

import paho.mqtt.client as paho

from ... import __version__
from ...backoff import Backoff
from ...commandtypes import Rejection, reply_code
from ...ratelog import RateLog, safe
from ...records import CommandKind, CommandReply
from ...threadloop import Mailbox, call_soon_on, submit_to
from ..broker_settings import BrokerSettings, SecretError
from ..cmdparse import intake, rejected_event_data
from ..outbox import Outbox, Row
from ..paho_session import PahoSession
from .inbound import InboundLimits
from .node import Disconnect, EdgeNode, MemoryBuffer, Publish, Submit

log = logging.getLogger("hookwatch.sparkplug")

#: inputs waiting for the node thread at most (beyond: the oldest telemetry update is dropped)
QUEUE_MAX = 10_000
#: the first pause after the node thread failed (doubling up to reconnect_max_s)
CRASH_BACKOFF_MIN_S = 0.5


@dataclass
class SparkplugSettings(BrokerSettings):
    """What an edge node needs (built from a station's `sparkplug:` section by output.py); the broker
    connection is the shared :class:`BrokerSettings` (``servers`` defaults to its host and port)."""
    group_id: str
    edge_node_id: str
    device_id: str
    primary_host_id: str | None = None
    data_interval_s: float = 1.0
    store_path: str = "sparkplug.sqlite"
    history_budget_bytes: int = 50 * 1024 * 1024
    #: the first CONNECT waits this long after the first station attached, so that the stations of
    #: a fleet starting together get their DBIRTHs right after the NBIRTH
    gather_s: float = 0.5
    #: at most one birth per this interval; Rebirth requests inside it are coalesced into one
    rebirth_min_interval_s: float = 2.0
    max_command_bytes: int = 16384
    max_command_metrics: int = 64
    max_string_chars: int = 256
    state_max_bytes: int = 1024
    #: a STATE timestamp further ahead of this node's clock is taken as "now" (docs/sparkplug.md)
    state_future_skew_s: float = 300.0

    section: ClassVar[str] = "sparkplug"

    def node_key(self) -> tuple:
        return (tuple(self.servers), self.group_id, self.edge_node_id)


class OutboxBuffer:
    """The node's store-and-forward buffer on the SQLite outbox (its public API only).

    A store that cannot be written (disk full, I/O error) is a state, not a crash: rows wait in
    memory (at most ``memory_max``; beyond, the oldest measured values are dropped, counted) and
    are written to disk as soon as it accepts them again; the replay takes disk rows, then these.
    """

    def __init__(self, outbox: Outbox, memory_max: int = 20_000):
        self.ob = outbox
        self.memory: collections.deque = collections.deque()    # (key, Row, telemetry)
        self.memory_max = memory_max
        self.store_errors = 0
        self.dropped = 0

    def _flush_memory(self) -> bool:
        if not self.memory:
            return True
        try:
            self.ob.add([r for _k, r, _t in self.memory])
        except sqlite3.Error:
            return False
        self.memory.clear()
        log.warning("sparkplug store %s writable again; held rows written", self.ob.path)
        return True

    def put(self, topic: str, payload: bytes, telemetry: bool) -> None:
        row = Row(self.ob.next_seq(), "telemetry" if telemetry else "event", topic, payload, 0, False,
                  time.time())
        if self._flush_memory():
            try:
                self.ob.add([row])
                return
            except sqlite3.Error as e:
                self.store_errors += 1
                if self.store_errors == 1 or self.store_errors % 1000 == 0:
                    log.error("sparkplug store %s not writable (%s): data held in memory (%d errors so "
                              "far)", self.ob.path, e, self.store_errors)
        self.memory.append((row.seq, row, telemetry))
        if len(self.memory) > self.memory_max:
            for i, (_k, _r, tel) in enumerate(self.memory):
                if tel:
                    del self.memory[i]
                    break
            else:
                self.memory.popleft()
            self.dropped += 1

    def peek(self, n: int) -> list[tuple[int, str, bytes]]:
        self._flush_memory()
        try:
            rows = [(r.seq, r.topic, r.payload) for r in self.ob.pending(0, n)]
        except sqlite3.Error:
            rows = []
        for k, r, _t in self.memory:
            if len(rows) >= n:
                break
            rows.append((k, r.topic, r.payload))
        return rows

    def remove(self, keys: list[int]) -> None:
        ks = set(keys)
        if self.memory:
            self.memory = collections.deque(x for x in self.memory if x[0] not in ks)
        try:
            self.ob.confirm(keys)
        except sqlite3.Error as e:
            # they were published: a resend after a restart is flagged historical, harmless
            log.error("sparkplug store %s: cannot delete replayed rows: %s", self.ob.path, e)

    def __len__(self) -> int:
        try:
            n = self.ob.count()
        except sqlite3.Error:
            n = 0
        return n + len(self.memory)


def _telemetry_only(it: tuple) -> bool:
    """The Mailbox's drop policy: a telemetry-only update may go (the oldest such first; when none
    waits, the oldest item of all), never a birth, a command reply or an event."""
    return bool(it[0] == "update" and it[3])


class NodeRuntime(PahoSession):
    """The edge node's thread: paho client + EdgeNode + outbox (see the module docstring)."""

    def __init__(self, s: SparkplugSettings):
        super().__init__(s, f"sparkplug {s.edge_node_id}", log)
        self.s = s
        self.outbox: Outbox | None = None
        last = None
        try:
            self.outbox = Outbox(s.store_path, s.history_budget_bytes)
            last = self.outbox.meta_get("bdseq")
        except (OSError, sqlite3.Error) as e:
            log.error("sparkplug %s/%s: store %s unusable (%s): data is held in memory only and bdSeq "
                      "restarts at 0", s.group_id, s.edge_node_id, s.store_path, e)
        limits = InboundLimits(max_payload_bytes=int(s.max_command_bytes), max_metrics=int(s.max_command_metrics),
                               max_string_chars=int(s.max_string_chars), state_max_bytes=int(s.state_max_bytes))
        self.node = EdgeNode(s.group_id, s.edge_node_id, primary_host_id=s.primary_host_id,
                             last_bdseq=last, software=f"hookwatch {__version__}", limits=limits,
                             rebirth_min_interval_ms=int(round(s.rebirth_min_interval_s * 1000)),
                             state_future_skew_ms=int(round(s.state_future_skew_s * 1000)))
        self.node.buffer = OutboxBuffer(self.outbox) if self.outbox is not None else MemoryBuffer()
        self.outputs: dict[str, Any] = {}          # device id → SparkplugOutput
        self._q: Mailbox[tuple] = Mailbox(QUEUE_MAX, droppable=_telemetry_only)
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._disconnect: Disconnect | None = None
        self._qos1: list = []              # QoS 1 publishes (NDEATH) not yet acknowledged
        self.counters: dict[str, int] = collections.Counter()
        #: bad payloads and internal errors: one line per kind per minute with a count
        self._rlog = RateLog(log)
        #: the back-off after a crash of the node thread (the one back-off, gateway/backoff.py):
        #: doubling from CRASH_BACKOFF_MIN_S to reconnect_max_s, a new row after a minute's run
        self._crash = Backoff(CRASH_BACKOFF_MIN_S, max(s.reconnect_max_s, CRASH_BACKOFF_MIN_S),
                              stable_s=60.0)

    # ------------------------------------------------------------------ any thread
    def post(self, item: tuple) -> None:
        self._q.put_nowait(item)

    def start(self) -> None:
        if self._thread is None:
            self._next_attempt = time.monotonic() + self.s.gather_s
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
        return {"group": self.s.group_id, "node": self.s.edge_node_id, "connected": bool(self._sock_open),
                "counters": counters}

    # ------------------------------------------------------------------ node thread
    def _now(self) -> int:
        return int(time.time() * 1000)

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
                    self._abort_quietly()
                    self.node.disconnected()
                    self._next_attempt = time.monotonic()
                    if self._stop.wait(pause):
                        break
        finally:
            try:
                self._close(clean=True)
            except Exception:  # noqa: BLE001 - stopping: the broker sends the Will instead
                log.exception("sparkplug %s: closing the session failed", self.s.edge_node_id)
                self._abort_quietly()
            if self.outbox is not None:
                self.outbox.close()

    def _abort_quietly(self) -> None:
        try:
            self._abort()
        except Exception:  # noqa: BLE001 - a broken client: dropped
            self._client = None
            self._sock_open = False

    def _run(self) -> None:
        while True:
            self._q.clear_wake()
            self._inputs()
            if self._stop.is_set():
                self._inputs()
                break
            self._housekeeping()
            if self._sock_open:
                if self.node.replaying and self.node.publishing:
                    pubs, keys = self.node.drain(self._now())
                    self._act(pubs)
                    self.node.buffer.remove(keys)
                client = self._client
                if client is None:      # not reached: _sock_open is True only with a client
                    continue
                rc = client.loop(timeout=self.s.poll_s)
                if self._disconnect is not None:
                    self._planned_disconnect(self._disconnect)
                elif rc != paho.MQTT_ERR_SUCCESS:
                    self._lost(f"network loop: {paho.error_string(rc)}")
            else:
                wait = self._attempt_wait()
                if wait <= 0:
                    self._connect()
                else:
                    self._q.wait(min(0.1, wait))

    def _housekeeping(self) -> None:
        """The coalesced rebirth when it is due; the rate-limited lines about bad inputs."""
        if self._sock_open:
            self._act(self.node.tick(self._now()))
        self._log_bad()

    def _log_bad(self) -> None:
        if not self.node.bad:
            return
        for kind, reason in self.node.take_bad():
            self._rlog.warning(("bad", kind), "sparkplug %s: a bad payload on %s ignored (counted: "
                               "hookwatch_sparkplug_bad_payloads_total): %s", self.s.edge_node_id,
                               kind, reason)

    def _inputs(self) -> None:
        for item in self._q.drain():
            kind = item[0]
            now = self._now()
            if kind == "up":
                self._act(self.node.device_up(item[1], item[2], now))
            elif kind == "update":
                self._act(self.node.device_update(item[1], item[2], now))
            elif kind == "down":
                self._act(self.node.device_down(item[1], now))
            elif kind == "result":
                _, dev, ck, ok, code, reason = item
                self._act(self.node.command_result(dev, ck, ok, code, reason, now))

    def _act(self, outs) -> None:
        for o in outs:
            if isinstance(o, Publish):
                if self._client is None or not self._sock_open:
                    continue
                info = self._client.publish(o.topic, o.payload, qos=o.qos, retain=o.retain)
                if o.qos:
                    self._qos1.append(info)
                self.counters["published"] += 1
                if info.rc != paho.MQTT_ERR_SUCCESS:
                    log.warning("sparkplug: publish on %s failed: %s", o.topic, paho.error_string(info.rc))
            elif isinstance(o, Disconnect):
                # carried out after the network loop returns (we may be inside a paho callback),
                # once the NDEATH queued before it is on the wire
                self._disconnect = o
            elif isinstance(o, Submit):
                self._submit(o)

    def _submit(self, sub: Submit) -> None:
        out = self.outputs.get(sub.device_id)
        try:
            ck = CommandKind(sub.kind)
        except ValueError:
            self._act(self.node.command_result(sub.device_id, sub.kind, False, 9,
                                               f"{sub.kind} is not available in this version", self._now()))
            return
        if out is None or out.station is None or out.loop is None or out.loop.is_closed():
            self._act(self.node.command_result(sub.device_id, sub.kind, False, 10, "the station is not running",
                                               self._now()))
            return
        # the one bounded intake (gateway/northbound/cmdparse.py): a DCMD metric's Sparkplug type
        # is kept, so a String "0.6" for Arg T Set or a 1 MB Arg Sample ID is refused like over MQTT
        cmd = intake(ck.value, sub.args, "sparkplug")
        if isinstance(cmd, Rejection):
            self._act(self.node.command_result(sub.device_id, sub.kind, False, int(cmd.code), cmd.reason,
                                               self._now()))
            call_soon_on(out.loop, out.station.refused, rejected_event_data(ck.value, cmd, "sparkplug"))
            return
        fut = submit_to(out.loop, out.station.submit(cmd))
        if fut is None:
            self.post(("result", sub.device_id, sub.kind, False, 10, "the station is not running"))
            return

        def done(f: Future[CommandReply], dev: str = sub.device_id, kind: str = sub.kind) -> None:
            try:
                r = f.result()
                self.post(("result", dev, kind, bool(r.ok), reply_code(r), r.reason))
            except Exception as e:  # noqa: BLE001 - the station failed to carry it out
                self.post(("result", dev, kind, False, 10, f"the station failed: {type(e).__name__}: {e}"))

        fut.add_done_callback(done)

    def _connect(self) -> None:
        s = self.s
        will = self.node.connecting()
        self._persist_bdseq()
        try:                            # credentials and TLS
            c = self._paho_client(self.client_id_for(s.client_id or f"hookwatch-spb-{s.group_id}-{s.edge_node_id}"))
        except (SecretError, OSError, ValueError) as e:     # ssl.SSLError is an OSError
            self.counters["tls_errors"] += 1
            if self.counters["tls_errors"] == 1:
                log.error("sparkplug %s: TLS set-up failed or the password cannot be read (%s); retrying, "
                          "data is held", s.edge_node_id, e)
            self._client = None
            self.node.connect_failed()
            self._persist_bdseq()
            self._schedule_retry()
            return
        c.will_set(will.topic, will.payload, qos=will.qos, retain=will.retain)
        c.on_connect = self._on_connect
        c.on_disconnect = self._on_disconnect
        c.on_message = self._on_message
        self._client = c
        if not self._open(c):                   # the server set: the next one is tried (§8.2)
            self.counters["connect_errors"] += 1
            self._client = None
            self.node.connect_failed()          # no CONNECT packet was sent: bdSeq not used
            self._persist_bdseq()

    def _persist_bdseq(self) -> None:
        """The bdSeq of the coming CONNECT, or the last one used, kept for the next process."""
        if self.outbox is None:
            return
        last = self.node.bdseq if not self.node.fresh else None
        try:
            self.outbox.add([], meta={"bdseq": last})
        except sqlite3.Error as e:
            self.counters["bdseq_store_errors"] += 1
            log.error("sparkplug: cannot persist bdSeq %s: %s", last, e)

    def _lost(self, why: str) -> None:
        log.warning("sparkplug %s: connection lost (%s)", self.s.edge_node_id, why)
        self._abort()
        self._schedule_retry()

    def _abort(self) -> None:
        """End the session without DISCONNECT: the broker publishes the Will (the NDEATH)."""
        c, self._client = self._client, None
        self._sock_open = False
        self._qos1 = []
        if c is not None:
            self._drop_socket(c)
        self.node.disconnected()

    def _planned_disconnect(self, d: Disconnect) -> None:
        self._disconnect = None
        log.info("sparkplug %s: disconnecting: %s", self.s.edge_node_id, d.reason)
        if d.next_server:
            self._next_server()
        self._close(clean=False)
        self._next_attempt = time.monotonic() + 0.2

    def _close(self, clean: bool) -> None:
        c = self._client
        if c is None:
            return
        if clean and self._sock_open and self.node.connected:
            # a deliberate end: the NDEATH ourselves (the broker only sends the Will on a failure)
            self._qos1.append(c.publish(*_pub_args(self.node.ndeath())))
        # what is queued (DDEATH, NDEATH) goes out before the DISCONNECT: wait for the QoS 1 ones
        t_end = time.monotonic() + 2.0
        while self._sock_open and time.monotonic() < t_end and (c.want_write() or self._unacked(c)):
            if c.loop(timeout=0.05) != paho.MQTT_ERR_SUCCESS:
                break
        if self._sock_open and self._unacked(c):
            # the NDEATH is not acknowledged: no DISCONNECT, so that the broker sends the Will
            self._abort()
            return
        self._sock_open = False
        try:
            c.disconnect()
            c.loop(timeout=0.05)
        except Exception:  # noqa: BLE001 - closing a broken socket
            pass
        self._client = None
        self._qos1 = []
        self.node.disconnected()

    def _unacked(self, c: paho.Client) -> bool:
        self._qos1 = [i for i in self._qos1 if not i.is_published()]
        return bool(self._qos1)

    # paho callbacks (this thread, from client.loop)
    def _on_connect(self, client, userdata, flags, reason_code, properties) -> None:
        if reason_code.is_failure:
            log.error("sparkplug %s: broker refused the connection: %s", self.s.edge_node_id, reason_code)
            self._close(clean=False)
            self._schedule_retry()
            return
        log.info("sparkplug %s/%s: connected (bdSeq %d)", self.s.group_id, self.s.edge_node_id,
                 self.node.bdseq)
        self._session_up()
        for t, q in self.node.subscriptions():
            client.subscribe(t, qos=q)
        self._act(self.node.connected_ok(self._now()))

    def _on_disconnect(self, client, userdata, flags, reason_code, properties) -> None:
        if self._sock_open:
            self._sock_open = False
            self._client = None
            self.node.disconnected()
            self._schedule_retry()

    def _on_message(self, client, userdata, msg) -> None:
        """Whatever arrives: handled within bounds (bad payloads are counted by the node); an
        error of our own here is counted and logged, the message dropped, the session goes on."""
        try:
            now = self._now()
            if msg.topic == self.node.state_topic():
                self._act(self.node.host_state(msg.payload, now))
            else:
                self._act(self.node.command(msg.topic, msg.payload, now))
        except Exception as e:  # noqa: BLE001 - one message must not end the session
            self.counters["message_errors"] += 1
            self._rlog.log("internal", logging.ERROR, "sparkplug %s: handling a message on %s failed: "
                           "%s: %s", self.s.edge_node_id, safe(msg.topic, 80), type(e).__name__,
                           str(e)[:120], exc_info=True)
        self._log_bad()


def _pub_args(p: Publish) -> tuple:
    return (p.topic, p.payload, p.qos, p.retain)


# ---------------------------------------------------------------------- one runtime per node
_RUNTIMES: dict[tuple, NodeRuntime] = {}
_RT_LOCK = threading.Lock()


def node_figures() -> list[dict[str, Any]]:
    """:meth:`NodeRuntime.figures` of every edge node this process runs (the metrics endpoint)."""
    with _RT_LOCK:
        rts = list(_RUNTIMES.values())
    return sorted((rt.figures() for rt in rts), key=lambda f: (f["group"], f["node"]))


def attach(s: SparkplugSettings, output) -> NodeRuntime:
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
