"""The edge node's paho session: its CONNECT with the NDEATH as Will, its publishing, its end.

One :class:`NodeSession` per edge node, used by the node's thread only (:class:`~.client.NodeRuntime`);
it is the one paho session engine (:class:`..broker.paho_session.PahoSession`: the server set, the
back-off, the client's set-up, the unclean drop) with what is Sparkplug's:

- each connection attempt takes the next bdSeq, persists it (:class:`~.node_store.NodeStore`,
  kill -9 safe: a WAL commit), and builds a new client whose Will is the NDEATH with that bdSeq,
  QoS 1, not retained, set before CONNECT; a connection that sent no CONNECT gives the bdSeq back;
- after CONNACK it subscribes to the node's NCMD, DCMD and the primary host's STATE, and hands the
  node's births to the runtime; every message received goes to the runtime's handler;
- a deliberate end publishes the NDEATH itself and waits for the PUBACKs of what is queued (the
  DDEATHs, the NDEATH) before DISCONNECT; when the NDEATH is not acknowledged it drops the socket
  without DISCONNECT instead, so that the broker sends the Will: the host always gets an NDEATH.
"""
from __future__ import annotations

import collections
import logging
import time
from collections.abc import Callable, Iterable

import paho.mqtt.client as paho

from ..broker.paho_session import PahoSession
from ..broker.settings import SecretError
from .actions import Action, Disconnect, Publish
from .node import EdgeNode
from .node_settings import SparkplugSettings
from .node_store import NodeStore

log = logging.getLogger("hookwatch.sparkplug")


def now_ms() -> int:
    """The node's clock: ms since the epoch (the Sparkplug timestamps)."""
    return int(time.time() * 1000)


class NodeSession(PahoSession):
    """The paho session of one edge node (see the module docstring)."""

    def __init__(self, s: SparkplugSettings, node: EdgeNode, store: NodeStore, counters: collections.Counter[str],
                 act: Callable[[Iterable[Action]], None], handle: Callable[[str, bytes], None]) -> None:
        super().__init__(s, f"sparkplug {s.edge_node_id}", log)
        self.s = s
        self.node = node
        self.store = store
        self.counters = counters
        #: carries out the node's outputs (the runtime's), and handles a message received
        self._act = act
        self._handle = handle
        self._disconnect: Disconnect | None = None
        self._qos1: list[paho.MQTTMessageInfo] = []      # QoS 1 publishes (NDEATH) not yet acknowledged

    @property
    def is_open(self) -> bool:
        """A socket to the broker is open (CONNACK may still be due)."""
        return self._sock_open

    def connect_after(self, delay_s: float) -> None:
        self._next_attempt = time.monotonic() + delay_s

    def due_in(self) -> float:
        """Seconds until the next connect attempt is due (≤ 0: now)."""
        return self._attempt_wait()

    # ------------------------------------------------------------------ connect
    def connect(self) -> None:
        s = self.s
        will = self.node.connecting()
        self.store.persist_bdseq(self.node.bdseq)
        try:                            # credentials and TLS
            c = self._paho_client(self.client_id_for(s.client_id or f"hookwatch-spb-{s.group_id}-{s.edge_node_id}"))
        except (SecretError, OSError, ValueError) as e:     # ssl.SSLError is an OSError
            self.counters["tls_errors"] += 1
            if self.counters["tls_errors"] == 1:
                log.error("sparkplug %s: TLS set-up failed or the password cannot be read (%s); retrying, "
                          "data is held", s.edge_node_id, e)
            self._client = None
            self.node.connect_failed()
            self.store.persist_bdseq(self.node.bdseq)
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
            self.store.persist_bdseq(self.node.bdseq)

    # ------------------------------------------------------------------ connected
    def publish(self, o: Publish) -> None:
        if self._client is None or not self._sock_open:
            return
        info = self._client.publish(o.topic, o.payload, qos=o.qos, retain=o.retain)
        if o.qos:
            self._qos1.append(info)
        self.counters["published"] += 1
        if info.rc != paho.MQTT_ERR_SUCCESS:
            log.warning("sparkplug: publish on %s failed: %s", o.topic, paho.error_string(info.rc))

    def end_after_loop(self, d: Disconnect) -> None:
        """End the session once the network loop returns (we may be inside a paho callback), once
        the NDEATH queued before it is on the wire."""
        self._disconnect = d

    def network(self) -> None:
        """One turn of the network loop (at most ``poll_s``), then a planned end or a lost
        connection."""
        client = self._client
        if client is None:      # not reached: the socket is open only with a client
            return
        rc = client.loop(timeout=self.s.poll_s)
        if self._disconnect is not None:
            self._planned_disconnect(self._disconnect)
        elif rc != paho.MQTT_ERR_SUCCESS:
            self._lost(f"network loop: {paho.error_string(rc)}")

    # ------------------------------------------------------------------ ends
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

    def abort_quietly(self) -> None:
        try:
            self._abort()
        except Exception:  # noqa: BLE001 - a broken client: dropped
            self._client = None
            self._sock_open = False

    def crashed(self) -> None:
        """The node thread failed: the session is dropped (the broker sends the NDEATH) and a new
        one may start at once (the runtime waits its crash back-off first)."""
        self.abort_quietly()
        self.node.disconnected()
        self._next_attempt = time.monotonic()

    def shut(self) -> None:
        """The node stops: a clean end (NDEATH, DISCONNECT), or the Will when that fails."""
        try:
            self._close(clean=True)
        except Exception:  # noqa: BLE001 - stopping: the broker sends the Will instead
            log.exception("sparkplug %s: closing the session failed", self.s.edge_node_id)
            self.abort_quietly()

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
            d = self.node.ndeath()
            self._qos1.append(c.publish(d.topic, d.payload, d.qos, d.retain))
        # what is queued (DDEATH, NDEATH) goes out before the DISCONNECT: wait for the QoS 1 ones
        t_end = time.monotonic() + 2.0
        while self._sock_open and time.monotonic() < t_end and (c.want_write() or self._unacked()):
            if c.loop(timeout=0.05) != paho.MQTT_ERR_SUCCESS:
                break
        if self._sock_open and self._unacked():
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

    def _unacked(self) -> bool:
        self._qos1 = [i for i in self._qos1 if not i.is_published()]
        return bool(self._qos1)

    # ------------------------------------------------------------------ paho callbacks (this thread, from client.loop)
    def _on_connect(self, client, userdata, flags, reason_code, properties) -> None:
        if reason_code.is_failure:
            log.error("sparkplug %s: broker refused the connection: %s", self.s.edge_node_id, reason_code)
            self._close(clean=False)
            self._schedule_retry()
            return
        log.info("sparkplug %s/%s: connected (bdSeq %d)", self.s.group_id, self.s.edge_node_id,
                 self.node.bdseq.value)
        self._session_up()
        for t, q in self.node.topics.subscriptions():
            client.subscribe(t, qos=q)
        self._act(self.node.connected_ok(now_ms()))

    def _on_disconnect(self, client, userdata, flags, reason_code, properties) -> None:
        if self._sock_open:
            self._sock_open = False
            self._client = None
            self.node.disconnected()
            self._schedule_retry()

    def _on_message(self, client, userdata, msg) -> None:
        self._handle(msg.topic, msg.payload)
