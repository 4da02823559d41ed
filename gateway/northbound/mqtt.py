"""MQTT output of one station: topic tree, payloads (schema.py), store-and-forward (outbox.py).

Threads:
- the station's loop calls ``on_record`` / ``on_event`` / ``on_state``: O(1) work (telemetry is
  aggregated in memory; a message is a JSON encode plus a deque append), never I/O;
- one pump thread per station owns the paho client and the SQLite outbox: it moves queued
  messages into the outbox (one transaction per batch), publishes them strictly in seq order
  with at most ``window`` in flight, deletes them when the broker confirms (``on_publish``),
  runs paho's network loop (``client.loop``) and reconnects with back-off. Because one thread
  does all of this, paho's own resend of in-flight messages after a reconnect always happens
  before anything newer is published: the order on the wire is the seq order.
- commands received on ``cmd/…`` are handed to the station's loop
  (``run_coroutine_threadsafe(station.submit(cmd))``); the answer goes out on ``reply``.
"""
from __future__ import annotations

import asyncio
import collections
import logging
import math
import os
import threading
import time
from dataclasses import dataclass
from typing import Any, Callable

import paho.mqtt.client as paho
from paho.mqtt.enums import CallbackAPIVersion

from .. import __version__
from ..method.rules import REASONS
from ..records import Event, EventType, SlotRecord, StationState
from ..station.commands import CODE, Rejection
from .cmdparse import RejectionLimiter, clip, parse_command, rejected_event_data
from . import schema
from .outbox import Outbox, Row
from .registers import MAP_VERSION

log = logging.getLogger("hookwatch.mqtt")

SOFTWARE = f"hookwatch {__version__}"
STATE_REFRESH_S = 10.0


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


def _r(x: float) -> float:
    return round(x, 6)


class _Telemetry:
    """Per-interval aggregation of slot records (O(1) per record)."""
    __slots__ = ("n", "n_read", "s1", "s2", "sm", "mn", "mx", "n_valid", "smu", "nmu", "counts",
                 "n_sat", "speed_cmd", "speed_act", "t0")

    def __init__(self, t0: float):
        self.t0 = t0
        self.n = self.n_read = self.n_valid = self.nmu = self.n_sat = 0
        self.s1 = self.s2 = self.sm = self.smu = 0.0
        self.mn = math.inf
        self.mx = -math.inf
        self.counts = [0] * len(REASONS)
        self.speed_cmd = 0.0
        self.speed_act = math.nan

    def add(self, rec: SlotRecord) -> None:
        self.n += 1
        if rec.present:
            t1, t2 = rec.t1, rec.t2
            if t1 == t1 and t2 == t2:
                self.n_read += 1
                self.s1 += t1
                self.s2 += t2
                m = (t1 + t2) * 0.5
                self.sm += m
                if m < self.mn:
                    self.mn = m
                if m > self.mx:
                    self.mx = m
        if rec.q:
            self.n_valid += 1
            if rec.mu is not None:
                self.smu += rec.mu
                self.nmu += 1
        mask = rec.mask
        if mask:
            for i, (bit, _) in enumerate(REASONS):
                if mask & bit:
                    self.counts[i] += 1
        if rec.saturated:
            self.n_sat += 1
        self.speed_cmd = rec.speed_cmd
        self.speed_act = rec.speed_act

    def summary(self, now: float, test_id: str | None) -> dict[str, Any]:
        nr = self.n_read
        return {
            "test_id": test_id, "interval_s": round(now - self.t0, 3), "slots": self.n,
            "t1": _r(self.s1 / nr) if nr else None, "t2": _r(self.s2 / nr) if nr else None,
            "tension": {"mean": _r(self.sm / nr) if nr else None, "min": _r(self.mn) if nr else None,
                        "max": _r(self.mx) if nr else None},
            "mu": _r(self.smu / self.nmu) if self.nmu else None,
            "valid_ratio": (self.n_valid / self.n if self.n else None) if test_id else None,
            "counts": {name: c for (_, name), c in zip(REASONS, self.counts)},
            "speed_cmd": self.speed_cmd, "speed_act": self.speed_act,
            "saturated_slots": self.n_sat, "saturation": self.n_sat > 0,
        }


class MqttOutput:
    """Station output (see docs/architecture.md) publishing the station over MQTT."""

    def __init__(self, settings: MqttSettings, station=None):
        self.s = settings
        self.station = station
        self.loop: asyncio.AbstractEventLoop | None = None
        self.outbox = Outbox(settings.outbox_path, settings.telemetry_budget_bytes)
        self._queue: collections.deque = collections.deque()
        self._lock = threading.Lock()
        self._wake = threading.Event()
        self._stop_evt = threading.Event()
        self._thread: threading.Thread | None = None
        self.connected = False
        self.counters: dict[str, int] = collections.Counter()
        # station-thread state
        self._test_id: str | None = None
        self._agg: _Telemetry | None = None
        self._last_state: StationState | None = None
        self._last_state_key: tuple | None = None
        self._last_state_pub = 0.0
        self._alarm: dict[str, Any] | None = self.outbox.meta_get("alarm")
        # pump-thread state
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
        self._rej_limiter = RejectionLimiter()

    # ================================================================ station side
    def _put(self, kind: str, topic: str, build: Callable[[int], dict], *, retain: bool = False,
             meta: dict | None = None) -> int:
        with self._lock:
            seq = self.outbox.next_seq()
            payload = schema.encode(build(seq))
            self._queue.append((Row(seq, kind, topic, payload, 1, retain, time.time()), meta))
        self._wake.set()
        return seq

    def _topic(self, key: str, **kw) -> str:
        return schema.topic_for(self.s.base_topic, key, **kw)

    async def start(self) -> None:
        self.loop = asyncio.get_running_loop()
        if self._thread is None:
            self._thread = threading.Thread(target=self._pump_main, name=f"mqtt-{self.s.station_id}",
                                            daemon=True)
            self._thread.start()

    async def stop(self) -> None:
        self._flush_telemetry(time.monotonic(), force=True)
        self._stop_evt.set()
        self._wake.set()
        if self._thread is not None:
            await asyncio.get_running_loop().run_in_executor(
                None, self._thread.join, self.s.drain_on_stop_s + 5.0)
        else:
            self._drain_queue()
            self.outbox.close()

    def on_record(self, rec: SlotRecord) -> None:
        agg = self._agg
        now = time.monotonic()
        if agg is None:
            agg = self._agg = _Telemetry(now)
        agg.add(rec)
        if now - agg.t0 >= self.s.telemetry_interval_s:
            self._flush_telemetry(now)

    def _flush_telemetry(self, now: float, force: bool = False) -> None:
        agg = self._agg
        if agg is None or agg.n == 0:
            return
        self._agg = _Telemetry(now)
        summ = agg.summary(now, self._test_id)
        t = time.time()
        self._put("telemetry", self._topic("telemetry"),
                  lambda seq: schema.telemetry_payload(seq, t, self.s.station_id, summ))

    def on_event(self, ev: Event) -> None:
        et = ev.type
        if et == EventType.TEST_STARTED:
            self._test_id = ev.test_id
            if self._alarm and self._alarm.get("state") in ("active", "acknowledged"):
                # an alarm raised before a gateway restart (the station no longer knows it): a new
                # test means the hook was replaced, so its lifecycle ends here as well
                a = dict(self._alarm)
                a.update(state="cleared", active=False, cleared_at=schema.iso_ms(ev.wall_time))
                self._set_alarm(ev.wall_time, a)
        self._put("event", self._topic("event", type=et.value), lambda seq: schema.event_payload(seq, ev))
        if et == EventType.END_OF_LIFE:
            d = ev.data
            self._set_alarm(ev.wall_time, {
                "state": "active", "active": True, "acknowledged": False, "test_id": ev.test_id,
                "sample_id": d.get("sample_id"), "t_life": d.get("t_life"), "k_life": d.get("k_life"),
                "mu_ss": d.get("mu_ss"), "mu_th": d.get("mu_th"), "raised_at": schema.iso_ms(ev.wall_time),
                "acknowledged_at": None, "acknowledged_by": None, "cleared_at": None})
        elif et == EventType.ALARM_ACK:
            a = dict(self._alarm or {"active": True})
            a.update(state="acknowledged", active=True, acknowledged=True,
                     acknowledged_at=schema.iso_ms(ev.wall_time), acknowledged_by=ev.data.get("source"))
            self._set_alarm(ev.wall_time, a)
        elif et == EventType.ALARM_CLEARED:
            a = dict(self._alarm or {})
            a.update(state="cleared", active=False, cleared_at=schema.iso_ms(ev.wall_time))
            self._set_alarm(ev.wall_time, a)
        elif et == EventType.TEST_ENDED:
            st = self._last_state
            self._put("result", self._topic("result"), lambda seq: schema.result_payload(seq, ev, st),
                      retain=True)
            if ev.test_id is not None and ev.test_id == self._test_id:
                self._test_id = None

    def _set_alarm(self, t: float, alarm: dict[str, Any]) -> None:
        self._alarm = alarm
        self._put("alarm", self._topic("alarm"),
                  lambda seq: schema.alarm_payload(seq, t, self.s.station_id, alarm), retain=True,
                  meta={"alarm": alarm})

    def on_state(self, st: StationState) -> None:
        self._last_state = st
        key = (st.state, st.test_id, st.sample_id, st.grade, st.t_set, st.t_end, st.mu_ss, st.mu_th,
               st.k_b, st.t_life, st.status, st.end_reason, st.alarm, st.protection_stop,
               st.meter_ok, st.stm32_ok)
        now = time.monotonic()
        if key == self._last_state_key and now - self._last_state_pub < STATE_REFRESH_S:
            return
        self._last_state_key = key
        self._last_state_pub = now
        t = time.time()
        self._put("state", self._topic("state"), lambda seq: schema.state_payload(seq, t, st), retain=True)

    # ================================================================ pump thread
    def _pump_main(self) -> None:
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
        rows, meta = [], {}
        while True:
            try:
                row, m = self._queue.popleft()
            except IndexError:
                break
            rows.append(row)
            if m:
                meta.update(m)
        if rows or meta:
            self.outbox.add(rows, self._sent_upto, meta)
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
            self._wake.clear()
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
                    self._wake.wait(min(0.1, self._next_attempt - now))

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
        st = self._topic("status")
        c.will_set(st, schema.encode(schema.status_payload(self.outbox.last_seq, time.time(), s.station_id,
                                                           "offline", SOFTWARE, MAP_VERSION)),
                   qos=1, retain=True)
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
                self._client.will_set(self._topic("status"), schema.encode(schema.status_payload(
                    self.outbox.last_seq, time.time(), s.station_id, "offline", SOFTWARE, MAP_VERSION)),
                    qos=1, retain=True)
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
        self.connected = False
        self._sock_open = False
        self.counters["disconnects"] += 1
        self._schedule_retry()

    def _close_client(self) -> None:
        c = self._client
        if c is None:
            return
        was_connected, self.connected = self.connected, False
        try:
            if was_connected:
                info = c.publish(self._topic("status"), schema.encode(schema.status_payload(
                    self.outbox.last_seq, time.time(), self.s.station_id, "offline", SOFTWARE, MAP_VERSION)),
                    qos=1, retain=True)
                t_end = time.monotonic() + 1.0
                while not info.is_published() and time.monotonic() < t_end and self._sock_open:
                    if c.loop(timeout=0.05) != paho.MQTT_ERR_SUCCESS:
                        break
                c.disconnect()
                c.loop(timeout=0.05)
        except Exception:
            log.debug("%s: error while disconnecting", self.s.station_id, exc_info=True)
        finally:
            self.connected = False
            self._sock_open = False
            try:
                if c.socket() is not None:
                    c.socket().close()
            except Exception:
                pass
            self._client = None

    # -- paho callbacks (run inside client.loop, on the pump thread)
    def _on_connect(self, client, userdata, flags, reason_code, properties) -> None:
        if reason_code.is_failure:
            why = str(reason_code)
            (log.error if why != self._refused else log.debug)(
                "%s: MQTT broker refused the connection: %s (retrying every %.0f s; messages are kept "
                "in the outbox)", self.s.station_id, why, self.s.reconnect_max_s)
            self._refused = why
            self.connected = False
            client.disconnect()
            self._sock_open = False
            self._schedule_retry(max_delay=True)
            return
        log.info("%s: MQTT connected to %s:%s", self.s.station_id, self.s.host, self.s.port)
        self.connected = True
        self._connect_error_logged = False
        self._refused = None
        self._backoff = self.s.reconnect_min_s
        self.counters["connects"] += 1
        client.subscribe(self._topic("cmd_start").rsplit("/", 1)[0] + "/+", qos=1)
        client.publish(self._topic("status"), schema.encode(schema.status_payload(
            self.outbox.last_seq, time.time(), self.s.station_id, "online", SOFTWARE, MAP_VERSION)),
            qos=1, retain=True)

    def _on_disconnect(self, client, userdata, flags, reason_code, properties) -> None:
        if self.connected:
            log.warning("%s: MQTT disconnected (%s)", self.s.station_id, reason_code)
        self.connected = False

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
        name = msg.topic.rsplit("/", 1)[-1]
        self.counters["commands"] += 1
        cmd = parse_command(name, msg.payload, "mqtt")   # bounded: size, depth, numbers, strings
        if isinstance(cmd, Rejection):
            self._reply(clip(name, 32).strip("'"), cmd.request_id, cmd)
            self._intake_rejected(name, cmd)
            return
        st, loop = self.station, self.loop
        if st is None or loop is None or loop.is_closed():
            self._reply(name, cmd.request_id, Rejection(False, "the station is not running", cmd.request_id,
                                                        CODE["NO_STATION"]))
            return
        try:
            fut = asyncio.run_coroutine_threadsafe(st.submit(cmd), loop)
        except RuntimeError:
            self._reply(name, cmd.request_id, Rejection(False, "the station is not running", cmd.request_id,
                                                        CODE["NO_STATION"]))
            return

        def done(f, cmd=cmd):
            try:
                r = f.result()
            except Exception as e:  # the station failed to carry it out
                r = Rejection(False, f"the station failed: {type(e).__name__}: {e}", cmd.request_id,
                              CODE["NO_STATION"])
            self._reply(cmd.kind.value, cmd.request_id, r)

        fut.add_done_callback(done)

    def _intake_rejected(self, name: str, rej: Rejection) -> None:
        """A code-9 refusal becomes a ``command_rejected`` event of the station (rate-limited)."""
        n = self._rej_limiter.allow(time.monotonic())
        st, loop = self.station, self.loop
        if n is None or st is None or loop is None or loop.is_closed():
            return
        data = rejected_event_data(name, rej, "mqtt")
        if n:
            data["suppressed"] = n
        try:
            loop.call_soon_threadsafe(lambda: st._emit_event(EventType.COMMAND_REJECTED, **data))
        except RuntimeError:
            pass

    def _reply(self, command: str, request_id: str | None, r) -> None:
        code = 0 if r.ok else int(getattr(r, "code", CODE["BAD_REQUEST"]) or CODE["BAD_REQUEST"])
        t = time.time()
        rid = request_id if request_id is not None else r.request_id
        self._put("reply", self._topic("reply"), lambda seq: schema.reply_payload(
            seq, t, self.s.station_id, command, rid, r.ok, code, r.reason))
