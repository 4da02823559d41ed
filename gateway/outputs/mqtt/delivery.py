"""The delivery side of the MQTT pump: queue → outbox → wire in seq order, and the confirmations.

:class:`Delivery` owns what the pump (:mod:`.pump`) delivers: the bounded hand-over from the
station's loop (a :class:`gateway.plumbing.threadloop.Mailbox` of rows; a dead pump: the oldest are dropped
and counted), the on-disk :class:`..broker.outbox.Outbox` (one transaction per batch), the messages in
flight (at most ``window``, published strictly in seq order) and the broker's confirmations
(``on_publish``: the row is deleted from the outbox). Rows and confirmations leave their holders
only once the outbox took them, so a fault of the pump in between keeps them for its restart;
what was in flight when a client is dropped is sent again from the outbox, in seq order.

:class:`RetainedTopics` is the retained replay's bookkeeping: the latest confirmed message of every
retained topic, published again with its original ``seq`` after every (re)connect (a clustered
broker keeps a retained message on the node that received it, and loses it with that node).

Used from the pump thread, except :meth:`Delivery.put` (any thread).
"""
from __future__ import annotations

import collections
import logging
import threading
import time

import paho.mqtt.client as paho
from paho.mqtt.packettypes import PacketTypes
from paho.mqtt.properties import Properties

from ...plumbing.threadloop import Mailbox
from ..broker.outbox import Outbox, Row
from . import messages as M
from .settings import MqttSettings

log = logging.getLogger("hookwatch.mqtt")

#: messages waiting for the pump at most (a dead pump: the oldest are dropped and counted)
QUEUE_MAX = 100_000
#: retained topics whose last message is published again after a (re)connect, at most
RETAINED_TOPICS_MAX = 256


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

    def publish_again(self, client: paho.Client) -> None:
        """Hand every :meth:`to_publish` row to a client just connected (counted); paho puts these
        on the wire before it resends what was in flight: older first."""
        for row in self.to_publish():
            info = client.publish(row.topic, row.payload, qos=row.qos, retain=True)
            if info.rc == paho.MQTT_ERR_SUCCESS:
                self.counters["retained_republished"] += 1


class Delivery:
    """The queue, outbox, in-flight window and confirmations of one station's messages (see the
    module docstring); ``counters`` are the pump's."""

    def __init__(self, settings: MqttSettings, counters: dict[str, int]) -> None:
        self.s = settings
        self.counters = counters
        self.outbox = Outbox(settings.outbox_path, settings.telemetry_budget_bytes)
        #: the hand-over from the station's loop (the pump waits on it, and is woken through it)
        self.queue: Mailbox[Row] = Mailbox(QUEUE_MAX)
        self._lock = threading.Lock()
        self._dropped_logged = 0
        self._unstored: list[Row] = []                       # taken from the queue, not yet stored
        self._acked: collections.deque[int] = collections.deque()   # confirmed, not yet deleted
        self._mid2seq: dict[int, int] = {}                  # in flight: paho's mid → seq
        self._sent_upto = 0
        self.retained = RetainedTopics(counters)
        #: the ``status``'s own counter (see mqtt_schema.STATUS_FIELDS), persisted in the outbox
        self.session = 0

    # ================================================================ any thread
    def put(self, msg: M.Message) -> int:
        """Queue ``msg`` (never blocks): its seq is the next of the stream."""
        with self._lock:
            seq = self.outbox.next_seq()
            payload = msg.encode(seq)
            self.queue.put_nowait(Row(seq, msg.kind, msg.topic, payload, msg.qos, msg.retain, time.time(),
                                      msg.correlation))
        return seq

    # ================================================================ pump thread
    @property
    def sent_upto(self) -> int:
        """The newest seq handed to the current client (0: none since it was made)."""
        return self._sent_upto

    def store(self) -> None:
        """Move the queued rows into the outbox (one transaction) and delete the confirmed ones."""
        # rows and confirmations leave their holders only once the outbox took them (a fault in
        # between keeps them for the restarted pump)
        self._unstored += self.queue.drain()
        if self.queue.dropped != self._dropped_logged:
            log.error("%s: MQTT pump behind: %d message(s) dropped before reaching the outbox",
                      self.s.station_id, self.queue.dropped - self._dropped_logged)
            self._dropped_logged = self.queue.dropped
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

    def send_more(self, client: paho.Client | None, v5: bool) -> None:
        """Publish the next stored rows in seq order while fewer than ``window`` are in flight
        (``v5``: a reply to a Response Topic carries its Correlation Data)."""
        room = self.s.window - len(self._mid2seq)
        if room <= 0 or client is None:
            return
        for row in self.outbox.pending(self._sent_upto, room):
            props = None
            if row.correlation is not None and v5:
                props = Properties(PacketTypes.PUBLISH)
                props.CorrelationData = row.correlation
            info = client.publish(row.topic, row.payload, qos=row.qos, retain=row.retain, properties=props)
            if info.rc not in (paho.MQTT_ERR_SUCCESS, paho.MQTT_ERR_NO_CONN):
                log.error("%s: publish of seq %d failed: %s", self.s.station_id, row.seq,
                          paho.error_string(info.rc))
                break
            self._mid2seq[info.mid] = row.seq
            self._sent_upto = row.seq
            self.counters["sent"] += 1
            if log.isEnabledFor(logging.DEBUG):
                log.debug("%s: sent seq %d (%s)", self.s.station_id, row.seq, row.kind)

    def published(self, mid: int) -> None:
        """The broker confirmed paho's message ``mid``: its row is deleted at the next :meth:`store`."""
        seq = self._mid2seq.pop(mid, None)
        if seq is not None:
            self._acked.append(seq)
            self.counters["confirmed"] += 1

    def forget_in_flight(self) -> None:
        """The client is gone: what it had in flight is sent again, from the outbox, by the next."""
        self._mid2seq.clear()
        self._sent_upto = 0

    def delivered(self) -> bool:
        """Nothing in flight and nothing stored left to send."""
        return not self._mid2seq and not self.outbox.pending(self._sent_upto, 1)

    def new_session(self) -> int:
        """The next ``status`` session number (persisted in the outbox's meta table)."""
        if self.session == 0:
            self.session = self.outbox.meta_int("status_session") or 0
        self.session += 1
        self.outbox.add([], self._sent_upto, meta={"status_session": self.session})
        return self.session

    def close(self) -> None:
        self.outbox.close()
