"""The MQTT transport of one station: paho client, on-disk outbox, reconnects — one thread.

The pump thread owns the paho client and the SQLite outbox: it moves queued messages (a bounded
:class:`gateway.threadloop.Mailbox` filled by the station's loop) into the outbox (one transaction
per batch), publishes them strictly in seq order with at most ``window`` in flight, deletes them
when the broker confirms (``on_publish``), runs paho's network loop (``client.loop``) and reconnects
with back-off over the server list (:class:`.paho_session.PahoSession`, the session engine it shares
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
"""
from __future__ import annotations

import collections
import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass

import paho.mqtt.client as paho
from paho.mqtt.packettypes import PacketTypes
from paho.mqtt.properties import Properties

from ..ratelog import RateLog, clip
from ..threadloop import Mailbox
from . import mqtt_messages as M
from . import mqtt_schema as schema
from .broker_settings import BrokerSettings, SecretError
from .outbox import Outbox, Row
from .paho_session import PahoSession
from .sitelives import site_filter

log = logging.getLogger("hookwatch.mqtt")

#: messages waiting for the pump at most (a dead pump: the oldest are dropped and counted)
QUEUE_MAX = 100_000
#: at most one log line per this many seconds about pump failures (with the count in between)
FAULT_LOG_INTERVAL_S = 60.0
#: a pump that ran this long without a fault starts again from the shortest restart delay
FAULT_RESET_S = 30.0
#: an MQTT 5 Response Topic (characters) / Correlation Data (bytes) longer than this is not used
#: (the reply goes to the ``reply`` topic): a request cannot make the gateway publish much
RESPONSE_TOPIC_MAX = 256
CORRELATION_MAX = 256
#: values of ``mqtt.protocol``
PROTOCOLS = ("auto", "5", "3.1.1")
#: retained topics whose last message is published again after a (re)connect, at most
RETAINED_TOPICS_MAX = 256
#: what MQTT 3.1.1 costs against MQTT 5 (the one log line of a fallback; docs/mqtt.md says the same)
V311_COSTS = ("no Response Topic / Correlation Data (command replies go to `reply`, matched by "
              "`request_id`), no user properties, no message expiry")


#: where an MQTT 5 request wants its answer: (Response Topic, Correlation Data)
Response = tuple[str, bytes | None]


@dataclass
class MqttSettings(BrokerSettings):
    """What the MQTT output needs (built from a station's `mqtt:` section by wiring.py); the broker
    connection (host, port, credentials, TLS, back-off) is the shared :class:`BrokerSettings`."""
    station_id: str
    base_topic: str
    protocol: str = "auto"            # auto (MQTT 5, 3.1.1 if the broker refuses it), 5, 3.1.1
    telemetry_interval_s: float = 1.0
    outbox_path: str = "outbox.sqlite"
    telemetry_budget_bytes: int = 50 * 1024 * 1024
    window: int = 16                  # messages in flight at most
    drain_on_stop_s: float = 2.0      # on a clean stop, time allowed to deliver what is pending
    #: MQTT 5 Response Topics are obeyed only below this (``mqtt.reply_prefix``); None: ``<base>/reply``
    reply_prefix: str | None = None
    #: share the station's lives with its site and receive theirs (``mqtt.share_lives``;
    #: gateway/northbound/sitelives.py), and the station's records folder (its own lives)
    share_lives: bool = False
    records_dir: str | None = None


class RetainedTopics:
    """The latest message of every retained topic, for publishing again after a (re)connect (a
    retained message held by a broker node that is gone, or by another node of a cluster, is
    never the only copy). A topic whose newest message is not confirmed yet is left to that one;
    at most RETAINED_TOPICS_MAX topics, the oldest forgotten beyond (counted)."""

    def __init__(self, counters: dict[str, int]) -> None:
        self.counters = counters
        self._latest: dict[str, int] = {}           # topic → seq of its newest stored row
        self._unconfirmed: dict[int, Row] = {}      # seq → that row, until the broker confirms it
        self._confirmed: dict[str, Row] = {}        # topic → its newest row, confirmed

    def stored(self, row: Row) -> None:
        old = self._latest.pop(row.topic, None)
        if old is not None:
            self._unconfirmed.pop(old, None)
        self._confirmed.pop(row.topic, None)
        self._latest[row.topic] = row.seq
        self._unconfirmed[row.seq] = row
        while len(self._latest) > RETAINED_TOPICS_MAX:
            topic = next(iter(self._latest))
            self._unconfirmed.pop(self._latest.pop(topic), None)
            self._confirmed.pop(topic, None)
            self.counters["retained_topics_forgotten"] += 1

    def confirmed(self, seq: int) -> None:
        row = self._unconfirmed.pop(seq, None)
        if row is not None:
            self._confirmed[row.topic] = row

    def to_publish(self) -> list[Row]:
        """The confirmed newest row of each topic, in seq order."""
        return sorted(self._confirmed.values(), key=lambda r: r.seq)


def join_site(client: paho.Client, s: MqttSettings, lives: bool, filters: tuple[str, ...]) -> None:
    """The site's subscriptions of a connected session: with ``lives``, the site's lives and its
    lives requests, and a request of this station (non-retained: a clustered broker's retained
    store is per node, so a late joiner is never left to it; gateway/northbound/sitelives.py);
    and ``filters`` (the console's site view)."""
    if lives:
        client.subscribe(site_filter(s.base_topic), qos=1)
        client.subscribe(schema.lives_request_topic(s.base_topic), qos=1)
    for f in filters:
        client.subscribe(f, qos=1)
    if lives:
        client.publish(schema.lives_request_topic(s.base_topic), s.station_id.encode(), qos=1, retain=False)


class MqttPump(PahoSession):
    """Store-and-forward of one station's messages (see the module docstring)."""

    def __init__(self, settings: MqttSettings, on_link: Callable[[bool], None] = lambda ok: None,
                 on_command: Callable[[str, bytes, Response | None], None] = lambda name, payload, response: None,
                 on_lives: Callable[[str, bytes], None] | None = None) -> None:
        super().__init__(settings, settings.station_id, log)
        self.s = settings
        self.on_link = on_link
        self.on_command = on_command
        #: the site's retained lives and its lives requests (topic, payload), when the station shares them
        self.on_lives = on_lives
        #: more subscriptions of the site (the console's site view: other stations' state and
        #: status) and where their messages go (pump thread); set by :meth:`add_site_feed`
        self._site_filters: tuple[str, ...] = ()
        self.on_site: Callable[[str, bytes], object] | None = None
        self._cmd_prefix = M.command_filter(settings.base_topic)[:-1]
        self.outbox = Outbox(settings.outbox_path, settings.telemetry_budget_bytes)
        self._queue: Mailbox[Row] = Mailbox(QUEUE_MAX)
        self._dropped_logged = 0
        self._lock = threading.Lock()
        self._stop_evt = threading.Event()
        self._thread: threading.Thread | None = None
        self._status_topic = schema.topic_for(settings.base_topic, "status")
        #: a Response Topic must start with this (the configured reply prefix and a slash)
        self.response_prefix = (settings.reply_prefix or schema.topic_for(settings.base_topic, "reply")) + "/"
        self._refusals = RateLog(log)
        self.connected = False
        self.counters: dict[str, int] = collections.Counter()
        self._sent_upto = 0
        self._mid2seq: dict[int, int] = {}
        self._acked: collections.deque = collections.deque()
        self._setup_error: str | None = None
        self._refused: str | None = None
        # supervision (see _main): rows taken from the queue but not yet stored, fault counting
        self._unstored: list[Row] = []
        self.faults = 0
        self._faults_unlogged = 0
        self._fault_logged_at = -FAULT_LOG_INTERVAL_S
        self._restart_delay = settings.reconnect_min_s
        self._session = 0       # the status's own counter (see schema.STATUS_FIELDS)
        self._client_cid = ""   # the client ID the current paho client was made with
        #: MQTT 5 for the next connection (auto: until the broker refuses it)
        self.v5 = settings.protocol in ("auto", "5")
        self._connack = False
        self._v5_ok = False         # the broker accepted MQTT 5 once: never fall back
        self._v5_closed = 0         # MQTT 5 connections closed before their CONNACK, in a row
        self.retained = RetainedTopics(self.counters)

    # ================================================================ any thread
    def put(self, msg: M.Message) -> int:
        """Queue ``msg`` (never blocks): its seq is the next of the stream."""
        with self._lock:
            seq = self.outbox.next_seq()
            payload = msg.encode(seq)
            self._queue.put_nowait(Row(seq, msg.kind, msg.topic, payload, msg.qos, msg.retain, time.time(),
                                       msg.correlation))
        return seq

    def add_site_feed(self, topic_filters: tuple[str, ...], on_site: Callable[[str, bytes], object]) -> None:
        """Also subscribe to ``topic_filters`` (on every connect) and hand what arrives on them to
        ``on_site`` (pump thread): the console's site view rides on this session (before
        :meth:`start`)."""
        self._site_filters = tuple(topic_filters)
        self.on_site = on_site

    def start(self) -> None:
        if self._thread is None:
            self._thread = threading.Thread(target=self._main, name=f"mqtt-{self.s.station_id}",
                                            daemon=True)
            self._thread.start()

    def request_stop(self) -> None:
        self._stop_evt.set()
        self._queue.wake()

    def join(self, timeout: float) -> None:
        """Wait for the pump to deliver what it can (``drain_on_stop_s``) and close the outbox."""
        if self._thread is not None:
            self._thread.join(timeout)
        else:
            self._drain_queue()
            self.outbox.close()

    @property
    def started(self) -> bool:
        return self._thread is not None

    def _status(self, online: bool) -> bytes:
        return M.status_message(self.s.base_topic, self.s.station_id, time.time(), online).encode(
            self._session)

    def _new_session(self) -> None:
        """The next ``status`` session number (persisted in the outbox's meta table)."""
        if self._session == 0:
            self._session = int(self.outbox.meta_get("status_session") or 0)
        self._session += 1
        self.outbox.add([], self._sent_upto, meta={"status_session": self._session})

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
                self._drain_queue()
            except Exception:
                log.exception("%s: could not store the last messages", self.s.station_id)
            self._close_client()
            self.outbox.close()
            self._refusals.close()      # the counts of the last window, and no timer after

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
        self._mid2seq.clear()
        self._sent_upto = 0
        self._retry_now()
        if c is not None:
            self._drop_socket(c)
        self._set_connected(False)

    def _drain_queue(self) -> None:
        # rows and confirmations leave their holders only once the outbox took them (a fault in
        # between keeps them for the restarted pump)
        self._unstored += self._queue.drain()
        if self._queue.dropped != self._dropped_logged:
            log.error("%s: MQTT pump behind: %d message(s) dropped before reaching the outbox",
                      self.s.station_id, self._queue.dropped - self._dropped_logged)
            self._dropped_logged = self._queue.dropped
        if self._unstored:
            self.outbox.add(self._unstored, self._sent_upto)
            for row in self._unstored:
                if row.retain:
                    self.retained.stored(row)
            self._unstored = []
        acked = list(self._acked)
        if acked:
            self.outbox.confirm(acked)
            for seq in acked:
                self._acked.popleft()
                self.retained.confirmed(seq)

    def _pump(self) -> None:
        stop_deadline = None
        while True:
            self._queue.clear_wake()
            self._drain_queue()
            if self.connected:
                self._send_more()
            if self._stop_evt.is_set():
                if stop_deadline is None:
                    stop_deadline = time.monotonic() + (self.s.drain_on_stop_s if self.connected else 0.0)
                done = not self._mid2seq and not self.outbox.pending(self._sent_upto, 1)
                if done or time.monotonic() >= stop_deadline or not self.connected:
                    self._drain_queue()
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
                    self._queue.wait(min(0.1, wait))

    def _make_client(self, client_id: str) -> paho.Client:
        s = self.s
        c = self._paho_client(client_id, v5=self.v5)
        c.max_inflight_messages_set(max(1, s.window))
        st = self._status_topic
        c.will_set(st, self._status(False), qos=1, retain=True)
        c.on_connect = self._on_connect
        c.on_disconnect = self._on_disconnect
        c.on_publish = self._on_publish
        c.on_message = self._on_message
        return c

    def _connect(self) -> None:
        s = self.s
        try:
            self._new_session()
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
        self._connack = False
        if not self._open(self._client, v5=self.v5):
            self.counters["connect_errors"] += 1

    def _lost(self, why: str) -> None:
        if self.connected:
            log.warning("%s: MQTT connection lost (%s)", self.s.station_id, why)
        self._set_connected(False)
        self._sock_open = False
        self.counters["disconnects"] += 1
        self._schedule_retry()
        if not self._connack and self.v5:
            # a broker that does not speak MQTT 5 may just close the connection; so may a broker
            # that is going down: the second time in a row counts as a refusal
            self._v5_closed += 1
            if self._v5_closed >= 2:
                self._refused_v5(f"connection closed before CONNACK twice ({why})")

    def _refused_v5(self, why: str) -> None:
        """``protocol: auto`` and the broker did not take an MQTT 5 CONNECT: use 3.1.1 from now on
        (a new client, at once)."""
        if not (self.v5 and self.s.protocol == "auto") or self._v5_ok:
            return
        host, port = self.server
        log.warning("%s: MQTT broker %s:%s refused MQTT 5 (%s); using MQTT 3.1.1 from now on, which "
                    "costs: %s", self.s.station_id, host, port, why, V311_COSTS)
        self.counters["mqtt311_fallbacks"] += 1
        self.v5 = False
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
        if reason_code.is_failure and self.v5 and reason_code.value in (1, 132):
            # 132 Unsupported Protocol Version (a 3.1.1 broker answers 1, unacceptable version)
            client.disconnect()
            self._refused_v5(str(reason_code))
            return
        self._connack = True
        self._v5_closed = 0
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
        log.info("%s: MQTT %s connected to %s:%s", self.s.station_id, "5" if self.v5 else "3.1.1",
                 host, port)
        self._set_connected(True)
        self._v5_ok = self._v5_ok or self.v5
        self._refused = None
        self._session_up()
        self.counters["connects"] += 1
        client.subscribe(M.command_filter(self.s.base_topic), qos=1)
        join_site(client, self.s, self.on_lives is not None, self._site_filters)
        client.publish(self._status_topic, self._status(True), qos=1, retain=True)
        # the latest confirmed message of every retained topic again (see RetainedTopics); paho
        # puts these on the wire before it resends what was in flight: older first
        for row in self.retained.to_publish():
            info = client.publish(row.topic, row.payload, qos=row.qos, retain=True)
            if info.rc == paho.MQTT_ERR_SUCCESS:
                self.counters["retained_republished"] += 1

    def _on_disconnect(self, client, userdata, flags, reason_code, properties) -> None:
        if self.connected:
            log.warning("%s: MQTT disconnected (%s)", self.s.station_id, reason_code)
        self._set_connected(False)

    def _on_publish(self, client, userdata, mid, reason_code, properties) -> None:
        seq = self._mid2seq.pop(mid, None)
        if seq is not None:
            self._acked.append(seq)
            self.counters["confirmed"] += 1

    def _send_more(self) -> None:
        room = self.s.window - len(self._mid2seq)
        c = self._client
        if room <= 0 or c is None:
            return
        for row in self.outbox.pending(self._sent_upto, room):
            props = None
            if row.correlation is not None and self.v5:
                props = Properties(PacketTypes.PUBLISH)
                props.CorrelationData = row.correlation
            info = c.publish(row.topic, row.payload, qos=row.qos, retain=row.retain, properties=props)
            if info.rc not in (paho.MQTT_ERR_SUCCESS, paho.MQTT_ERR_NO_CONN):
                log.error("%s: publish of seq %d failed: %s", self.s.station_id, row.seq,
                          paho.error_string(info.rc))
                break
            self._mid2seq[info.mid] = row.seq
            self._sent_upto = row.seq
            self.counters["sent"] += 1
            if log.isEnabledFor(logging.DEBUG):
                log.debug("%s: sent seq %d (%s)", self.s.station_id, row.seq, row.kind)

    def _on_message(self, client, userdata, msg) -> None:
        if not msg.topic.startswith(self._cmd_prefix):
            if self.on_lives is not None and msg.topic.endswith(("/lives", "/" + schema.LIVES_REQUEST)):
                self.counters["site_lives"] += 1
                self.on_lives(msg.topic, bytes(msg.payload))
            elif self.on_site is not None:
                self.counters["site_view"] += 1
                self.on_site(msg.topic, bytes(msg.payload))
            return
        self.counters["commands"] += 1
        self.on_command(msg.topic.rsplit("/", 1)[-1], msg.payload, self._response_of(msg))

    def _response_of(self, msg) -> Response | None:
        """MQTT 5: where the request wants its answer, ``(Response Topic, Correlation Data)``, if
        it names a topic one may publish to within the bounds and below the reply prefix
        (``mqtt.reply_prefix``, default ``<base>/reply``); None: answer on ``reply``. A request
        allowed to publish on ``cmd/…`` only cannot make the gateway publish on result, state or
        other stations' command topics (or Sparkplug's): such a Response Topic is not obeyed,
        counted (``response_topic_refused``) and logged once a minute with the count."""
        props = getattr(msg, "properties", None)
        topic = getattr(props, "ResponseTopic", None) if props is not None else None
        if topic is None:
            return None
        corr = getattr(props, "CorrelationData", None)
        if (not isinstance(topic, str) or not 0 < len(topic) <= RESPONSE_TOPIC_MAX
                or any(ch in topic for ch in "+#\x00") or topic.startswith("$")
                or (corr is not None and len(corr) > CORRELATION_MAX)):
            self.counters["bad_response_topic"] += 1
            return None
        if not topic.startswith(self.response_prefix):
            self.counters["response_topic_refused"] += 1
            self._refusals.warning("response_topic", "%s: MQTT 5 Response Topic %s is not below %s: not obeyed, "
                                   "answered on reply", self.s.station_id, clip(topic), self.response_prefix)
            return None
        return topic, None if corr is None else bytes(corr)
