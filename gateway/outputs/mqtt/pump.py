"""The MQTT transport of one station: paho client, on-disk outbox, reconnects — one thread.

The pump thread owns the paho client and the SQLite outbox: it moves queued messages (a bounded
:class:`gateway.plumbing.threadloop.Mailbox` filled by the station's loop) into the outbox (one transaction
per batch), publishes them strictly in seq order with at most ``window`` in flight, deletes them
when the broker confirms (``on_publish``), runs paho's network loop (``client.loop``) and reconnects
with back-off over the server list (:class:`..broker.paho_session.PahoSession`, the session engine it shares
with the Sparkplug node: a clustered broker's nodes, tried in turn). Because one thread does all of
this, paho's own resend of in-flight messages after a reconnect always happens before anything newer
is published: the order on the wire is the seq order. The thread is supervised (``_main``): a fault
anywhere in it (a callback, the outbox, paho) is counted and logged at most once a minute, the
client is dropped (the link goes down through ``on_link``; the broker publishes the Will) and the
pump restarts with back-off, keeping the outbox and the queued messages; unconfirmed rows are sent
again. It knows nothing of stations: link changes and received commands go to the two callbacks it
is given (called on the pump thread).

Retained topics are never left to the broker alone (a clustered broker keeps a retained message on
the node that received it, and loses it with that node): the latest confirmed message of every
retained topic (``state``, ``alarm``, the last ``result`` …) is published again, with its original
``seq``, after every (re)connect, before anything newer; ``status`` is published on every connect.

The pump is the session's thread, its lifecycle and its status; it works through three rooms of
its own, each one thread's state and nothing else:

- :class:`.delivery.Delivery`: the queue, the outbox, the messages in flight and the
  confirmations, and the retained replay's bookkeeping (:class:`.delivery.RetainedTopics`);
- :class:`.router.InboundRouter`: the subscriptions and where each received message goes
  (commands with their MQTT 5 Response Topic, the site's lives, the console's site view);
- :class:`.protocol_choice.ProtocolChoice`: MQTT 5 or 3.1.1 (``mqtt.protocol``, the fallback of
  ``auto``).
"""
from __future__ import annotations

import collections
import logging
import threading
import time
from collections.abc import Callable

import paho.mqtt.client as paho

from ..broker.outbox import Outbox
from ..broker.paho_session import PahoSession
from ..broker.settings import SecretError
from . import messages as M
from . import schema
from .delivery import Delivery
from .protocol_choice import ProtocolChoice
from .router import CommandCallback, InboundRouter, TopicCallback
from .settings import MqttSettings

__all__ = ["MqttPump"]

log = logging.getLogger("hookwatch.mqtt")

#: at most one log line per this many seconds about pump failures (with the count in between)
FAULT_LOG_INTERVAL_S = 60.0
#: a pump that ran this long without a fault starts again from the shortest restart delay
FAULT_RESET_S = 30.0


class MqttPump(PahoSession):
    """Store-and-forward of one station's messages (see the module docstring)."""

    def __init__(self, settings: MqttSettings, on_link: Callable[[bool], None] = lambda ok: None,
                 on_command: CommandCallback = lambda name, payload, response, source: None,
                 on_lives: TopicCallback | None = None) -> None:
        super().__init__(settings, settings.station_id, log)
        self.s = settings
        self.on_link = on_link
        self.counters: dict[str, int] = collections.Counter()
        #: what the session delivers: queue → outbox → wire in seq order, the confirmations
        self.delivery = Delivery(settings, self.counters)
        #: what the session receives: commands, the site's lives, the console's site view
        self.inbound = InboundRouter(settings, self.counters, on_command, on_lives)
        #: MQTT 5 or 3.1.1 for the next connection
        self.version = ProtocolChoice(settings, self.counters)
        self._stop_evt = threading.Event()
        self._thread: threading.Thread | None = None
        self._status_topic = schema.topic_for(settings.base_topic, "status")
        self.connected = False
        self._setup_error: str | None = None
        self._refused: str | None = None
        # supervision (see _main): fault counting and the restart delay
        self.faults = 0
        self._faults_unlogged = 0
        self._fault_logged_at = -FAULT_LOG_INTERVAL_S
        self._restart_delay = settings.reconnect_min_s
        self._client_cid = ""   # the client ID the current paho client was made with

    @property
    def outbox(self) -> Outbox:
        return self.delivery.outbox

    # ================================================================ any thread
    def put(self, msg: M.Message) -> int:
        """Queue ``msg`` (never blocks): its seq is the next of the stream."""
        return self.delivery.put(msg)

    def add_site_feed(self, topic_filters: tuple[str, ...], on_site: TopicCallback) -> None:
        """Also subscribe to ``topic_filters`` (on every connect) and hand what arrives on them to
        ``on_site`` (pump thread): the console's site view rides on this session (before
        :meth:`start`)."""
        self.inbound.add_site_feed(topic_filters, on_site)

    def start(self) -> None:
        if self._thread is None:
            self._thread = threading.Thread(target=self._main, name=f"mqtt-{self.s.station_id}",
                                            daemon=True)
            self._thread.start()

    def request_stop(self) -> None:
        self._stop_evt.set()
        self.delivery.queue.wake()

    def join(self, timeout: float) -> None:
        """Wait for the pump to deliver what it can (``drain_on_stop_s``) and close the outbox."""
        if self._thread is not None:
            self._thread.join(timeout)
        else:
            self.delivery.store()
            self.delivery.close()

    @property
    def started(self) -> bool:
        return self._thread is not None

    def _status(self, online: bool) -> bytes:
        return M.status_message(self.s.base_topic, self.s.station_id, time.time(), online).encode(
            self.delivery.session)

    # ================================================================ pump thread
    def _main(self) -> None:
        """Supervisor: any exception of the pump (a callback, the outbox, paho) is logged (rate-
        limited, with a count), the client is dropped (the link goes down, the broker publishes the
        Will) and the pump restarts after a back-off, keeping the outbox and the queue."""
        try:
            while True:
                t0 = time.monotonic()
                try:
                    self._pump()
                    return
                except Exception as e:
                    if time.monotonic() - t0 >= FAULT_RESET_S:
                        self._restart_delay = self.s.reconnect_min_s
                    self._fault(e)
                if self._stop_evt.wait(self._restart_delay):
                    return
                self._restart_delay = min(self.s.reconnect_max_s, self._restart_delay * 2)
        finally:
            try:
                self.delivery.store()
            except Exception:
                log.exception("%s: could not store the last messages", self.s.station_id)
            self._close_client()
            self.delivery.close()
            self.inbound.close()      # the counts of the last window, and no timer after

    def _fault(self, e: Exception) -> None:
        """One pump fault: count it, log it (the first with its traceback, then one line a minute
        with the count), drop the client; what was in flight is sent again from the outbox."""
        self.faults += 1
        self.counters["pump_restarts"] += 1
        self._faults_unlogged += 1
        now = time.monotonic()
        if now - self._fault_logged_at >= FAULT_LOG_INTERVAL_S:
            log.error("%s: MQTT pump failed (%d fault(s) since the last report, %d in all): %s: %s; "
                      "restarting in %.1f s, messages are kept in the outbox", self.s.station_id,
                      self._faults_unlogged, self.faults, type(e).__name__, e, self._restart_delay,
                      exc_info=self.faults == 1)
            self._faults_unlogged = 0
            self._fault_logged_at = now
        try:
            self._abandon_client()
        except Exception:   # the link callback itself failed: the client is dropped all the same
            log.debug("%s: error while dropping the client", self.s.station_id, exc_info=True)

    def _abandon_client(self) -> None:
        """Drop the client without a clean disconnect (the broker publishes the Will): the link is
        down, unconfirmed rows stay in the outbox and are sent again by the next client."""
        c, self._client = self._client, None
        self._sock_open = False
        self.delivery.forget_in_flight()
        self._retry_now()
        if c is not None:
            self._drop_socket(c)
        self._set_connected(False)

    def _pump(self) -> None:
        stop_deadline = None
        queue = self.delivery.queue
        while True:
            queue.clear_wake()
            self.delivery.store()
            if self.connected:
                self.delivery.send_more(self._client, self.version.v5)
            if self._stop_evt.is_set():
                if stop_deadline is None:
                    stop_deadline = time.monotonic() + (self.s.drain_on_stop_s if self.connected else 0.0)
                done = self.delivery.delivered()
                if done or time.monotonic() >= stop_deadline or not self.connected:
                    self.delivery.store()
                    break
            if self._sock_open and self._client is not None:
                rc = self._client.loop(timeout=self.s.poll_s)
                if rc != paho.MQTT_ERR_SUCCESS:
                    self._lost(f"network loop: {paho.error_string(rc)}")
            else:
                wait = self._attempt_wait()
                if wait <= 0:
                    self._connect()
                else:
                    queue.wait(min(0.1, wait))

    def _make_client(self, client_id: str) -> paho.Client:
        s = self.s
        c = self._paho_client(client_id, v5=self.version.v5)
        c.max_inflight_messages_set(max(1, s.window))
        st = self._status_topic
        c.will_set(st, self._status(False), qos=1, retain=True)
        c.on_connect = self._on_connect
        c.on_disconnect = self._on_disconnect
        c.on_publish = self._on_publish
        c.on_message = self.inbound.on_message
        return c

    def _connect(self) -> None:
        s = self.s
        try:
            self.delivery.new_session()
            cid = self.client_id_for(s.client_id or f"hookwatch-{s.station_id}")
            if self._client is not None and cid != self._client_cid:
                # another server of the list: a client of its own (what was in flight is sent
                # again from the outbox, in seq order)
                self._abandon_client()
            if self._client is None:
                self._client = self._make_client(cid)
                self._client_cid = cid
            else:   # the Last Will carries this session's number
                self._client.will_set(self._status_topic, self._status(False), qos=1, retain=True)
            self._setup_error = None
        except (SecretError, OSError, ValueError) as e:
            msg = str(e)
            if msg != self._setup_error:
                log.error("%s: MQTT not started: %s (messages are kept in the outbox)", s.station_id, msg)
            self._setup_error = msg
            self._client = None
            self._schedule_retry(max_delay=True)
            return
        self.version.connecting()
        if not self._open(self._client, v5=self.version.v5):
            self.counters["connect_errors"] += 1

    def _lost(self, why: str) -> None:
        if self.connected:
            log.warning("%s: MQTT connection lost (%s)", self.s.station_id, why)
        self._set_connected(False)
        self._sock_open = False
        self.counters["disconnects"] += 1
        self._schedule_retry()
        # a broker that does not speak MQTT 5 may just close the connection (protocol_choice.py)
        refused = self.version.closed(why)
        if refused is not None:
            self._refused_v5(refused)

    def _refused_v5(self, why: str) -> None:
        """``protocol: auto`` and the broker did not take an MQTT 5 CONNECT: use 3.1.1 from now on
        (a new client, at once)."""
        if self.version.fall_back(why, self.server):
            self._abandon_client()

    def _close_client(self) -> None:
        c = self._client
        if c is None:
            return
        was_connected = self.connected
        self._set_connected(False)
        try:
            if was_connected:
                info = c.publish(self._status_topic, self._status(False), qos=1, retain=True)
                t_end = time.monotonic() + 1.0
                while not info.is_published() and time.monotonic() < t_end and self._sock_open:
                    if c.loop(timeout=0.05) != paho.MQTT_ERR_SUCCESS:
                        break
                c.disconnect()
                c.loop(timeout=0.05)
        except Exception:
            log.debug("%s: error while disconnecting", self.s.station_id, exc_info=True)
        finally:
            self._set_connected(False)
            self._sock_open = False
            self._drop_socket(c)
            self._client = None

    def _set_connected(self, ok: bool) -> None:
        was, self.connected = self.connected, ok
        if was != ok:
            self.on_link(ok)

    # -- paho callbacks (run inside client.loop, on the pump thread)
    def _on_connect(self, client, userdata, flags, reason_code, properties) -> None:
        if self.version.version_refused(reason_code.is_failure, reason_code.value):
            client.disconnect()
            self._refused_v5(str(reason_code))
            return
        self.version.connack()
        if reason_code.is_failure:
            why = str(reason_code)
            (log.error if why != self._refused else log.debug)(
                "%s: MQTT broker refused the connection: %s (retrying every %.0f s; messages are kept "
                "in the outbox)", self.s.station_id, why, self.s.reconnect_max_s)
            self._refused = why
            self._set_connected(False)
            client.disconnect()
            self._sock_open = False
            self._schedule_retry(max_delay=True)
            return
        host, port = self.server
        log.info("%s: MQTT %s connected to %s:%s", self.s.station_id, "5" if self.version.v5 else "3.1.1",
                 host, port)
        self._set_connected(True)
        self.version.accepted()
        self._refused = None
        self._session_up()
        self.counters["connects"] += 1
        self.inbound.subscribe(client)
        client.publish(self._status_topic, self._status(True), qos=1, retain=True)
        # the latest confirmed message of every retained topic again (delivery.RetainedTopics),
        # before paho resends what was in flight: older first
        self.delivery.retained.publish_again(client)

    def _on_disconnect(self, client, userdata, flags, reason_code, properties) -> None:
        if self.connected:
            log.warning("%s: MQTT disconnected (%s)", self.s.station_id, reason_code)
        self._set_connected(False)

    def _on_publish(self, client, userdata, mid, reason_code, properties) -> None:
        self.delivery.published(mid)
