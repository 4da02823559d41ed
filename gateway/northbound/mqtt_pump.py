"""The MQTT transport of one station: paho client, on-disk outbox, reconnects — one thread.

The pump thread owns the paho client and the SQLite outbox: it moves queued messages (a bounded
:class:`gateway.threadloop.Mailbox` filled by the station's loop) into the outbox (one transaction
per batch), publishes them strictly in seq order with at most ``window`` in flight, deletes them
when the broker confirms (``on_publish``), runs paho's network loop (``client.loop``) and
reconnects with back-off. Because one thread does all of this, paho's own resend of in-flight
messages after a reconnect always happens before anything newer is published: the order on the
wire is the seq order. It knows nothing of stations: link changes and received commands go to
the two callbacks it is given (called on the pump thread).
"""
from __future__ import annotations

import collections
import logging
import os
import threading
import time
from dataclasses import dataclass
from typing import Callable

import paho.mqtt.client as paho
from paho.mqtt.enums import CallbackAPIVersion

from ..threadloop import Mailbox
from . import mqtt_messages as M
from . import schema
from .outbox import Outbox, Row

log = logging.getLogger("hookwatch.mqtt")

#: messages waiting for the pump at most (a dead pump: the oldest are dropped and counted)
QUEUE_MAX = 100_000


class SecretError(Exception):
    pass


@dataclass
class MqttSettings:
    """What the MQTT output needs (built from a station's `mqtt:` section by wiring.py)."""
    station_id: str
    base_topic: str
    host: str = "127.0.0.1"
    port: int = 1883
    client_id: str | None = None
    keepalive_s: int = 30
    username: str | None = None
    password_env: str | None = None
    password_file: str | None = None
    tls_enabled: bool = False
    ca_file: str | None = None
    cert_file: str | None = None
    key_file: str | None = None
    telemetry_interval_s: float = 1.0
    outbox_path: str = "outbox.sqlite"
    telemetry_budget_bytes: int = 50 * 1024 * 1024
    window: int = 16                  # messages in flight at most
    poll_s: float = 0.02              # network loop wait when connected (bounds the latency)
    reconnect_min_s: float = 1.0
    reconnect_max_s: float = 10.0
    drain_on_stop_s: float = 2.0      # on a clean stop, time allowed to deliver what is pending

    def password(self) -> str | None:
        if self.password_env:
            v = os.environ.get(self.password_env)
            if v is None:
                raise SecretError(f"mqtt.password_env: environment variable {self.password_env} is not set")
            return v
        if self.password_file:
            try:
                with open(self.password_file, encoding="utf-8") as f:
                    return f.read().rstrip("\r\n")
            except OSError as e:
                raise SecretError(f"mqtt.password_file {self.password_file!r}: {e.strerror}") from None
        return None




class MqttPump:
    """Store-and-forward of one station's messages (see the module docstring)."""

    def __init__(self, settings: MqttSettings, on_link: Callable[[bool], None] = lambda ok: None,
                 on_command: Callable[[str, bytes], None] = lambda name, payload: None) -> None:
        self.s = settings
        self.on_link = on_link
        self.on_command = on_command
        self.outbox = Outbox(settings.outbox_path, settings.telemetry_budget_bytes)
        self._queue: Mailbox[Row] = Mailbox(QUEUE_MAX)
        self._dropped_logged = 0
        self._lock = threading.Lock()
        self._stop_evt = threading.Event()
        self._thread: threading.Thread | None = None
        self._status_topic = schema.topic_for(settings.base_topic, "status")
        self.connected = False
        self.counters: dict[str, int] = collections.Counter()
        self._client: paho.Client | None = None
        self._sock_open = False
        self._sent_upto = 0
        self._mid2seq: dict[int, int] = {}
        self._acked: collections.deque = collections.deque()
        self._next_attempt = 0.0
        self._backoff = settings.reconnect_min_s
        self._setup_error: str | None = None
        self._connect_error_logged = False
        self._refused: str | None = None

    # ================================================================ any thread
    def put(self, msg: M.Message) -> int:
        """Queue ``msg`` (never blocks): its seq is the next of the stream."""
        with self._lock:
            seq = self.outbox.next_seq()
            payload = msg.encode(seq)
            self._queue.put_nowait(Row(seq, msg.kind, msg.topic, payload, msg.qos, msg.retain, time.time()))
        return seq

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
            self.outbox.last_seq)

    # ================================================================ pump thread
    def _main(self) -> None:
        try:
            self._pump()
        except Exception:
            log.exception("%s: MQTT pump crashed; messages stay in the outbox", self.s.station_id)
        finally:
            try:
                self._drain_queue()
            except Exception:
                log.exception("%s: could not store the last messages", self.s.station_id)
            self._close_client()
            self.outbox.close()

    def _drain_queue(self) -> None:
        rows = self._queue.drain()
        if self._queue.dropped != self._dropped_logged:
            log.error("%s: MQTT pump behind: %d message(s) dropped before reaching the outbox",
                      self.s.station_id, self._queue.dropped - self._dropped_logged)
            self._dropped_logged = self._queue.dropped
        if rows:
            self.outbox.add(rows, self._sent_upto)
        acked = []
        while True:
            try:
                acked.append(self._acked.popleft())
            except IndexError:
                break
        if acked:
            self.outbox.confirm(acked)

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
            if self._sock_open:
                rc = self._client.loop(timeout=self.s.poll_s)
                if rc != paho.MQTT_ERR_SUCCESS:
                    self._lost(f"network loop: {paho.error_string(rc)}")
            else:
                now = time.monotonic()
                if now >= self._next_attempt:
                    self._connect()
                else:
                    self._queue.wait(min(0.1, self._next_attempt - now))

    def _make_client(self) -> paho.Client:
        s = self.s
        c = paho.Client(CallbackAPIVersion.VERSION2, client_id=s.client_id or f"hookwatch-{s.station_id}",
                        clean_session=True, protocol=paho.MQTTv311)
        c.max_inflight_messages_set(max(1, s.window))
        c.max_queued_messages_set(0)
        if s.username:
            c.username_pw_set(s.username, s.password())
        if s.tls_enabled:
            c.tls_set(ca_certs=s.ca_file, certfile=s.cert_file, keyfile=s.key_file)
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
            if self._client is None:
                self._client = self._make_client()
            else:   # the Last Will carries the stream position at the start of this session
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
        try:
            self._client.connect(s.host, int(s.port), keepalive=int(s.keepalive_s))
        except (OSError, ValueError) as e:
            if not self._connect_error_logged:
                log.warning("%s: MQTT broker %s:%s unreachable (%s); retrying, messages are kept in the "
                            "outbox", s.station_id, s.host, s.port, e)
                self._connect_error_logged = True
            self._schedule_retry()
            return
        self._sock_open = True

    def _schedule_retry(self, max_delay: bool = False) -> None:
        delay = self.s.reconnect_max_s if max_delay else self._backoff
        self._next_attempt = time.monotonic() + delay
        self._backoff = min(self.s.reconnect_max_s, self._backoff * 2)

    def _lost(self, why: str) -> None:
        if self.connected:
            log.warning("%s: MQTT connection lost (%s)", self.s.station_id, why)
        self._set_connected(False)
        self._sock_open = False
        self.counters["disconnects"] += 1
        self._schedule_retry()

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
            try:
                if c.socket() is not None:
                    c.socket().close()
            except Exception:
                pass
            self._client = None

    def _set_connected(self, ok: bool) -> None:
        was, self.connected = self.connected, ok
        if was != ok:
            self.on_link(ok)

    # -- paho callbacks (run inside client.loop, on the pump thread)
    def _on_connect(self, client, userdata, flags, reason_code, properties) -> None:
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
        log.info("%s: MQTT connected to %s:%s", self.s.station_id, self.s.host, self.s.port)
        self._set_connected(True)
        self._connect_error_logged = False
        self._refused = None
        self._backoff = self.s.reconnect_min_s
        self.counters["connects"] += 1
        client.subscribe(M.command_filter(self.s.base_topic), qos=1)
        client.publish(self._status_topic, self._status(True), qos=1, retain=True)

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
        if room <= 0:
            return
        for row in self.outbox.pending(self._sent_upto, room):
            info = self._client.publish(row.topic, row.payload, qos=row.qos, retain=row.retain)
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
        self.counters["commands"] += 1
        self.on_command(msg.topic.rsplit("/", 1)[-1], msg.payload)
