"""Sparkplug B 3.0 edge node as a pure state machine: no sockets, no clock, no threads.

Inputs (method calls, each with the time in ms where it matters):
  ``connecting()`` before each MQTT CONNECT (→ the Will: NDEATH with the next bdSeq, persisted
  by the caller before it connects), ``connected()``, ``disconnected()``, ``host_state()`` (the
  primary host's ``spBv1.0/STATE/<host_id>``), ``device_up()`` / ``device_update()`` /
  ``device_down()`` (a station), ``command()`` (NCMD/DCMD payloads), ``command_result()``.
Outputs: :class:`Publish` (topic, payload bytes, qos, retain), :class:`Disconnect`,
:class:`Submit` (a device command for the station's one command path) — returned as lists.

Everything received is parsed within bounds (:mod:`.inbound`); a bad payload is counted
(``counters["bad_<kind>"]``) and noted in :attr:`EdgeNode.bad` for the caller's rate-limited log,
never raised. STATE timestamps follow the rule of :meth:`EdgeNode.host_state`; rebirths, Reboots and
Next Servers are rate-limited (:meth:`EdgeNode.rebirth`, :meth:`EdgeNode.reboot`, :meth:`EdgeNode.tick`).

Store and forward: while no primary host is online (or no connection), device data goes to a
:class:`Buffer` as DDATA payloads whose metrics carry ``is_historical = true`` and their original
timestamps; when the host is online again, after NBIRTH and the DBIRTHs, :meth:`EdgeNode.drain`
replays them in order (seq assigned at sending), and only then is data published live.

See docs/sparkplug.md for the rules implemented (with the specification's statement IDs).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Protocol

from ...commandtypes import COMMAND_KEYS
from ...records import CommandKind
from . import metrics as M
from .inbound import BadInput, InboundLimits, parse_payload, parse_state
from .sparkplug_b_pb2 import Payload

NAMESPACE = "spBv1.0"
QOS_DATA = 0          # NBIRTH, DBIRTH, NDATA, DDATA, DDEATH: QoS 0, not retained
QOS_DEATH = 1         # NDEATH (the Will): QoS 1, not retained


@dataclass(frozen=True)
class Publish:
    topic: str
    payload: bytes
    qos: int = QOS_DATA
    retain: bool = False


@dataclass(frozen=True)
class Disconnect:
    reason: str
    next_server: bool = False


@dataclass(frozen=True)
class Submit:
    device_id: str
    kind: str                       # gateway.records.CommandKind value
    args: dict[str, Any]


class Buffer(Protocol):
    """Store-and-forward of DDATA payloads (the runtime uses the SQLite outbox)."""

    def put(self, topic: str, payload: bytes, telemetry: bool) -> None: ...
    def peek(self, n: int) -> list[tuple[int, str, bytes]]: ...     # (key, topic, payload), oldest first
    def remove(self, keys: list[int]) -> None: ...
    def __len__(self) -> int: ...


class MemoryBuffer:
    """A Buffer in memory (tests, and the fallback when the outbox cannot be opened)."""

    def __init__(self) -> None:
        self.rows: list[tuple[int, str, bytes]] = []
        self._n = 0

    def put(self, topic: str, payload: bytes, telemetry: bool) -> None:
        self._n += 1
        self.rows.append((self._n, topic, payload))

    def peek(self, n: int) -> list[tuple[int, str, bytes]]:
        return self.rows[:n]

    def remove(self, keys: list[int]) -> None:
        ks = set(keys)
        self.rows = [r for r in self.rows if r[0] not in ks]

    def __len__(self) -> int:
        return len(self.rows)


def valid_id(s: str) -> bool:
    """Sparkplug IDs: UTF-8, non-empty, no MQTT separators or wildcards."""
    return bool(s) and not any(c in s for c in "/+#")


# ----------------------------------------------------------------------------- payload helpers
def set_value(m: Payload.Metric, dt: M.DataType, value: Any) -> None:
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        m.is_null = True
        return
    if dt in (M.DataType.Int8, M.DataType.Int16, M.DataType.Int32):
        m.int_value = int(value) & 0xFFFFFFFF       # two's complement in uint32 (the spec's encoding)
    elif dt in (M.DataType.UInt8, M.DataType.UInt16, M.DataType.UInt32):
        m.int_value = int(value)
    elif dt in (M.DataType.Int64,):
        m.long_value = int(value) & 0xFFFFFFFFFFFFFFFF
    elif dt in (M.DataType.UInt64, M.DataType.DateTime):
        m.long_value = int(value)
    elif dt == M.DataType.Float:
        m.float_value = float(value)
    elif dt == M.DataType.Double:
        m.double_value = float(value)
    elif dt == M.DataType.Boolean:
        m.boolean_value = bool(value)
    else:
        m.string_value = str(value)


def get_value(m: Payload.Metric) -> Any:
    if m.HasField("is_null") and m.is_null:
        return None
    which = m.WhichOneof("value")
    return getattr(m, which) if which else None


def _properties(m: Payload.Metric, d: M.MetricDef) -> None:
    keys: list[str] = []
    vals: list[str | bool] = []
    if d.units:
        keys.append("engUnit")
        vals.append(d.units)
    if d.description:
        keys.append("description")
        vals.append(d.description)
    if d.writable:
        keys.append("writable")
        vals.append(True)
    for k, v in zip(keys, vals):
        m.properties.keys.append(k)
        pv = m.properties.values.add()
        if isinstance(v, bool):
            pv.type = M.DataType.Boolean
            pv.boolean_value = v
        else:
            pv.type = M.DataType.String
            pv.string_value = v


@dataclass
class Device:
    device_id: str
    alias_base: int
    values: dict[str, Any] = field(default_factory=dict)
    stamps: dict[str, int] = field(default_factory=dict)
    born: bool = False
    stopped: bool = False          # its station stopped while data of it waits in the buffer


class EdgeNode:
    """One Sparkplug edge node hosting stations as devices (see the module docstring)."""

    def __init__(self, group_id: str, edge_node_id: str, *, primary_host_id: str | None = None,
                 last_bdseq: int | None = None, software: str = "hookwatch", replay_batch: int = 50,
                 limits: InboundLimits | None = None, rebirth_min_interval_ms: int = 2000,
                 state_future_skew_ms: int = 300_000):
        for what, v in (("group_id", group_id), ("edge_node_id", edge_node_id)):
            if not valid_id(v):
                raise ValueError(f"sparkplug.{what} {v!r}: must be non-empty without '/', '+' or '#'")
        if primary_host_id is not None and not valid_id(primary_host_id):
            raise ValueError(f"sparkplug.primary_host_id {primary_host_id!r}: must be non-empty without "
                             "'/', '+' or '#'")
        self.group_id = group_id
        self.edge_node_id = edge_node_id
        self.host_id = primary_host_id
        self.software = software
        self.replay_batch = replay_batch
        #: bdSeq of the current session (the last one used before a restart until connecting());
        #: the caller persists it after connecting() and before it connects
        self.bdseq = 0 if last_bdseq is None else int(last_bdseq) % 256
        self._fresh = last_bdseq is None
        self._before_connect = (self.bdseq, self._fresh)
        self.seq = 0
        self.connected = False
        self.node_born = False
        self.host_online = primary_host_id is None
        self.host_ts = -1
        self.limits = limits or InboundLimits()
        self.rebirth_min_interval_ms = int(rebirth_min_interval_ms)
        self.state_future_skew_ms = int(state_future_skew_ms)
        self._last_birth_ms: int | None = None
        self.rebirth_pending = False
        #: a Reboot / Next Server asked within the interval: carried out by :meth:`tick`
        self.disconnect_pending: Disconnect | None = None
        self._last_reboot_ms: int | None = None
        #: bad inputs not yet taken by the caller (kind, reason), at most BAD_MAX kept
        self.bad: list[tuple[str, str]] = []
        self.devices: dict[str, Device] = {}
        self.buffer: Buffer = MemoryBuffer()
        self._replaying = False
        self._dirty: dict[str, set[str]] = {}
        self.counters: dict[str, int] = {"stored": 0, "replayed": 0, "births": 0, "rebirths": 0,
                                         "ignored_commands": 0, "rebirths_coalesced": 0,
                                         "reboots": 0, "reboots_coalesced": 0,
                                         "bad_state": 0, "bad_ncmd": 0, "bad_dcmd": 0, "bad_topic": 0,
                                         "stale_state": 0, "future_state": 0}
        self._node_alias = M.node_aliases()

    # ------------------------------------------------------------------ topics
    def topic(self, kind: str, device_id: str | None = None) -> str:
        t = f"{NAMESPACE}/{self.group_id}/{kind}/{self.edge_node_id}"
        return f"{t}/{device_id}" if device_id is not None else t

    def state_topic(self) -> str | None:
        return f"{NAMESPACE}/STATE/{self.host_id}" if self.host_id else None

    def subscriptions(self) -> list[tuple[str, int]]:
        subs = [(self.topic("NCMD"), 1), (self.topic("DCMD", "+"), 1)]
        st = self.state_topic()
        if st:
            subs.append((st, 1))
        return subs

    @property
    def publishing(self) -> bool:
        """Live data may go out now: connected, host online, births done."""
        return self.connected and self.host_online and self.node_born

    # ------------------------------------------------------------------ session
    def connecting(self) -> Publish:
        """Before each CONNECT: the next bdSeq and the Will (NDEATH, QoS 1, not retained). The caller
        persists :attr:`bdseq` before connecting, so a restart after kill -9 continues from it."""
        self._before_connect = (self.bdseq, self._fresh)
        if self._fresh:
            self._fresh = False
        else:
            self.bdseq = (self.bdseq + 1) % 256
        return self.ndeath()

    @property
    def fresh(self) -> bool:
        """No bdSeq used yet (the first CONNECT will carry 0)."""
        return self._fresh

    def connect_failed(self) -> None:
        """No CONNECT packet went out (the TCP connection failed): the bdSeq is not used up."""
        self.bdseq, self._fresh = self._before_connect

    def ndeath(self) -> Publish:
        p = Payload()
        m = p.metrics.add()
        m.name = M.BDSEQ
        m.datatype = M.DataType.Int64
        m.long_value = self.bdseq
        return Publish(self.topic("NDEATH"), p.SerializeToString(), QOS_DEATH, False)

    def _bad(self, e: BadInput) -> None:
        self.counters[f"bad_{e.kind}"] = self.counters.get(f"bad_{e.kind}", 0) + 1
        self.counters["ignored_commands"] += 1
        if len(self.bad) < BAD_MAX:
            self.bad.append((e.kind, e.reason))

    def take_bad(self) -> list[tuple[str, str]]:
        """The bad inputs noted since the last call (for the caller's rate-limited log)."""
        out, self.bad = self.bad, []
        return out

    def connected_ok(self, now_ms: int) -> list[Publish]:
        self.connected = True
        self.node_born = False
        # STATE timestamps are compared within one MQTT session only (see host_state)
        self.host_ts = -1
        if self.host_id is not None:
            # wait for the host's retained STATE before any birth
            self.host_online = False
            return []
        return self._births(now_ms)

    def disconnected(self) -> None:
        self.connected = False
        self.node_born = False
        self.disconnect_pending = None     # the session it asked to end has ended
        self._replaying = False
        for d in self.devices.values():
            d.born = False

    def host_state(self, payload: bytes, now_ms: int) -> list[Publish | Disconnect]:
        """``spBv1.0/STATE/<host_id>`` in the 3.0 form ``{"online": bool, "timestamp": ms}``.

        The timestamp rule (docs/sparkplug.md "STATE timestamps"):

        - timestamps are compared with the last STATE accepted **in this MQTT session** only (reset
          at each CONNECT: the retained STATE a server delivers after SUBSCRIBE is that server's
          current word, so nothing seen before a reconnect or on another server can lock the host
          out);
        - a STATE older than the last one accepted in the session is ignored (counted
          ``stale_state``): tck-id-message-flow-edge-node-birth-publish-phid-wait-timestamp and
          tck-id-operational-behavior-edge-node-termination-host-offline-timestamp;
        - a timestamp more than ``state_future_skew_ms`` ahead of the node's clock is accepted
          (counted ``future_state``) but remembered as the node's clock at receipt, so that it
          cannot make the host's later, correctly dated STATE look stale.
        """
        try:
            online, ts = parse_state(payload, self.limits)
        except BadInput as e:
            self._bad(e)
            return []
        if ts < self.host_ts:
            self.counters["stale_state"] += 1
            return []              # an older STATE than one already seen: ignored
        if ts > now_ms + self.state_future_skew_ms:
            self.counters["future_state"] += 1
            if len(self.bad) < BAD_MAX:
                self.bad.append(("future_state", f"STATE timestamp {ts} is more than "
                                 f"{self.state_future_skew_ms} ms ahead of this node's clock {now_ms}; "
                                 "taken as now"))
            ts = max(int(now_ms), self.host_ts)
        self.host_ts = ts
        if online and not self.host_online:
            self.host_online = True
            if self.connected:
                return [*self._births(now_ms)]
        elif not online and self.host_online:
            self.host_online = False
            if self.connected and self.node_born:
                # the host is gone: end this session (NDEATH first) and connect to the next server
                # of the set (tck-id-operational-behavior-edge-node-termination-host-offline-reconnect)
                out: list[Publish | Disconnect] = [self.ndeath()]
                self.node_born = False
                for d in self.devices.values():
                    d.born = False
                out.append(Disconnect("primary host offline", next_server=True))
                return out
        return []

    # ------------------------------------------------------------------ births and deaths
    def _next_seq(self) -> int:
        s = self.seq
        self.seq = (self.seq + 1) % 256
        return s

    def _payload(self, now_ms: int, seq: bool = True) -> Payload:
        p = Payload()
        p.timestamp = int(now_ms)
        if seq:
            p.seq = self._next_seq()
        return p

    def nbirth(self, now_ms: int) -> Publish:
        self.seq = 0
        p = self._payload(now_ms)
        for d in M.NODE_METRICS:
            m = p.metrics.add()
            m.name = d.name
            if d.name in self._node_alias:
                m.alias = self._node_alias[d.name]
            m.timestamp = int(now_ms)
            m.datatype = d.datatype
            if d.name == M.BDSEQ:
                set_value(m, d.datatype, self.bdseq)
            elif d.writable:
                set_value(m, d.datatype, False)
            elif d.name == "Properties/Software":
                set_value(m, d.datatype, self.software)
            elif d.name == "Properties/Devices":
                set_value(m, d.datatype, sum(1 for x in self.devices.values() if not x.stopped))
            _properties(m, d)
        self.node_born = True
        self.counters["births"] += 1
        self._last_birth_ms = int(now_ms)
        self.rebirth_pending = False
        return Publish(self.topic("NBIRTH"), p.SerializeToString())

    def dbirth(self, dev: Device, now_ms: int) -> Publish:
        p = self._payload(now_ms)
        for i, d in enumerate(M.DEVICE_METRICS):
            m = p.metrics.add()
            m.name = d.name
            m.alias = dev.alias_base + i
            m.timestamp = dev.stamps.get(d.name, int(now_ms))
            m.datatype = d.datatype
            set_value(m, d.datatype, False if d.writable and d.datatype == M.DataType.Boolean
                      else dev.values.get(d.name))
            _properties(m, d)
        dev.born = True
        return Publish(self.topic("DBIRTH", dev.device_id), p.SerializeToString())

    def _births(self, now_ms: int) -> list[Publish]:
        out = [self.nbirth(now_ms)]
        for dev in self.devices.values():
            if not dev.stopped or len(self.buffer):
                out.append(self.dbirth(dev, now_ms))
        self._replaying = len(self.buffer) > 0
        self._dirty = {}
        if not self._replaying:
            out.extend(self._bury_stopped(now_ms))
        return out

    def _birth_due(self, now_ms: int) -> bool:
        last = self._last_birth_ms
        return last is None or now_ms < last or now_ms - last >= self.rebirth_min_interval_ms

    def rebirth(self, now_ms: int) -> list[Publish]:
        """Node Control/Rebirth: NBIRTH (same bdSeq, seq 0) and every DBIRTH again — at most one
        birth per ``rebirth_min_interval_ms``: a request inside that interval is coalesced into
        one pending rebirth, carried out by :meth:`tick` when the interval has passed."""
        if not (self.connected and self.host_online):
            return []
        if not self._birth_due(now_ms):
            if self.rebirth_pending:
                self.counters["rebirths_coalesced"] += 1
            self.rebirth_pending = True
            return []
        self.counters["rebirths"] += 1
        return self._births(now_ms)

    def _reboot_due(self, now_ms: int) -> bool:
        """A Reboot / Next Server may end the session now: the interval has passed since the
        session's birth and since the last one (a reconnect is a birth too)."""
        for last in (self._last_birth_ms, self._last_reboot_ms):
            if last is not None and last <= now_ms and now_ms - last < self.rebirth_min_interval_ms:
                return False
        return True

    def reboot(self, name: str, now_ms: int) -> list[Publish | Disconnect]:
        """Node Control/Reboot or Next Server: NDEATH, then the session ends (the runtime
        reconnects: to the next server for Next Server) — at most one per
        ``rebirth_min_interval_ms``, as births: a request inside that interval is coalesced into
        one pending one (Next Server over Reboot), carried out by :meth:`tick` when it is due."""
        d = Disconnect(name, next_server=name == M.NEXT_SERVER)
        if not self._reboot_due(now_ms):
            if self.disconnect_pending is not None:
                self.counters["reboots_coalesced"] += 1
            if self.disconnect_pending is None or d.next_server:
                self.disconnect_pending = d
            return []
        return self._end_session(d, now_ms)

    def _end_session(self, d: Disconnect, now_ms: int) -> list[Publish | Disconnect]:
        out: list[Publish | Disconnect] = []
        self.disconnect_pending = None
        self._last_reboot_ms = int(now_ms)
        self.counters["reboots"] += 1
        if self.connected:
            out.append(self.ndeath())
        self.node_born = False
        out.append(d)
        return out

    def tick(self, now_ms: int) -> list[Publish | Disconnect]:
        """Called often by the runtime: the pending (coalesced) Reboot / Next Server, then the
        pending (coalesced) rebirth, once due."""
        pending = self.disconnect_pending
        if pending is not None:
            if not self.connected:
                self.disconnect_pending = None
            elif self._reboot_due(now_ms):
                self.rebirth_pending = False      # the next session's births carry everything
                return self._end_session(pending, now_ms)
        if not self.rebirth_pending:
            return []
        if not (self.connected and self.host_online and self.node_born):
            self.rebirth_pending = False       # the next session's births carry everything
            return []
        if not self._birth_due(now_ms):
            return []
        self.counters["rebirths"] += 1
        return list(self._births(now_ms))

    def _ddeath(self, dev: Device, now_ms: int) -> Publish:
        dev.born = False
        return Publish(self.topic("DDEATH", dev.device_id), self._payload(now_ms).SerializeToString())

    def _bury_stopped(self, now_ms: int) -> list[Publish]:
        out = []
        for dev in list(self.devices.values()):
            if dev.stopped:
                if dev.born:
                    out.append(self._ddeath(dev, now_ms))
                del self.devices[dev.device_id]
        return out

    # ------------------------------------------------------------------ devices
    def device_up(self, device_id: str, values: dict[str, Any], now_ms: int) -> list[Publish]:
        if not valid_id(device_id):
            raise ValueError(f"sparkplug device id {device_id!r}: must be non-empty without '/', '+' or '#'")
        base = M.device_alias_base(device_id)
        taken = {d.alias_base for k, d in self.devices.items() if k != device_id}
        while base in taken:       # a CRC clash between two station IDs: the next free block
            base += 1 << 12
        dev = self.devices.get(device_id)
        if dev is None or dev.alias_base != base:
            dev = Device(device_id, base)
            self.devices[device_id] = dev
        dev.stopped = False
        for k, v in values.items():
            if k in M.DEVICE_BY_NAME:
                dev.values[k] = v
                dev.stamps[k] = int(now_ms)
        if self.publishing:
            return [self.dbirth(dev, now_ms)]
        return []

    def device_down(self, device_id: str, now_ms: int) -> list[Publish]:
        dev = self.devices.get(device_id)
        if dev is None:
            return []
        if self.publishing and not self._replaying:
            out = [self._ddeath(dev, now_ms)] if dev.born else []
            del self.devices[device_id]
            return out
        dev.stopped = True         # buried after its stored data went out
        return []

    def device_update(self, device_id: str, values: dict[str, Any], now_ms: int) -> list[Publish]:
        """New values of a station's metrics: DDATA by alias now, or into the buffer."""
        dev = self.devices.get(device_id)
        if dev is None:
            return []
        changed = {}
        for k, v in values.items():
            d = M.DEVICE_BY_NAME.get(k)
            if d is None:
                continue
            if d.telemetry or dev.values.get(k, _MISSING) != v:
                changed[k] = v
            dev.values[k] = v
            dev.stamps[k] = int(now_ms)
        if not changed:
            return []
        if self.publishing and dev.born and not self._replaying:
            p = self._payload(now_ms)
            self._add_data(p, dev, changed, now_ms, historical=False)
            return [Publish(self.topic("DDATA", device_id), p.SerializeToString())]
        if self._replaying and self.publishing:
            self._dirty.setdefault(device_id, set()).update(changed)
        p = Payload()
        p.timestamp = int(now_ms)
        self._add_data(p, dev, changed, now_ms, historical=True)
        telemetry = all(M.DEVICE_BY_NAME[k].telemetry for k in changed)
        self.buffer.put(self.topic("DDATA", device_id), p.SerializeToString(), telemetry)
        self.counters["stored"] += 1
        return []

    @staticmethod
    def _add_data(p: Payload, dev: Device, values: dict[str, Any], now_ms: int, historical: bool) -> None:
        index = _DEVICE_INDEX
        for k, v in values.items():
            d = M.DEVICE_BY_NAME[k]
            m = p.metrics.add()
            m.alias = dev.alias_base + index[k]      # by alias only, no name, no datatype
            m.timestamp = int(now_ms)
            if historical:
                m.is_historical = True
            set_value(m, d.datatype, v)

    # ------------------------------------------------------------------ replay
    @property
    def replaying(self) -> bool:
        return self._replaying

    def drain(self, now_ms: int) -> tuple[list[Publish], list[int]]:
        """The next batch of stored DDATA (oldest first, seq assigned now) and the buffer keys to
        remove once they are handed to the client. When the buffer is empty, the replay ends: the
        latest values that changed meanwhile go out live, stopped stations get their DDEATH."""
        if not (self.publishing and self._replaying):
            return [], []
        rows = self.buffer.peek(self.replay_batch)
        out: list[Publish] = []
        keys: list[int] = []
        for key, topic, payload in rows:
            dev_id = topic.rsplit("/", 1)[-1]
            dev = self.devices.get(dev_id)
            if dev is None:
                # stored before a restart, for a station not (yet) running here: birth it, so that
                # its history is not lost; buried at the end of the replay
                dev = Device(dev_id, M.device_alias_base(dev_id), stopped=True)
                self.devices[dev_id] = dev
            if not dev.born:
                out.append(self.dbirth(dev, now_ms))
            p = Payload()
            try:
                p.ParseFromString(payload)
            except Exception:   # noqa: BLE001 - a damaged row: skip it, counted
                self.counters["ignored_commands"] += 1
                keys.append(key)
                continue
            p.seq = self._next_seq()
            out.append(Publish(self.topic("DDATA", dev_id), p.SerializeToString()))
            keys.append(key)
            self.counters["replayed"] += 1
        if len(rows) < self.replay_batch and len(self.buffer) <= len(rows):
            self._replaying = False
            for dev_id, names in self._dirty.items():
                dev = self.devices.get(dev_id)
                if dev is None or not dev.born:
                    continue
                p = self._payload(now_ms)
                self._add_data(p, dev, {k: dev.values.get(k) for k in names}, now_ms, historical=False)
                out.append(Publish(self.topic("DDATA", dev_id), p.SerializeToString()))
            self._dirty = {}
            out.extend(self._bury_stopped(now_ms))
        return out, keys

    # ------------------------------------------------------------------ commands
    def command(self, topic: str, payload: bytes, now_ms: int) -> list[Publish | Disconnect | Submit]:
        """An NCMD or DCMD; metrics by name or by alias. Bad payloads (beyond the limits of
        :class:`InboundLimits`, undecodable) are counted and noted, unknown metrics counted."""
        parts = topic.split("/")
        if len(parts) == 4 and parts[2] == "NCMD" and topic == self.topic("NCMD"):
            kind = "ncmd"
        elif len(parts) == 5 and parts[2] == "DCMD" and topic.startswith(self.topic("DCMD") + "/"):
            kind = "dcmd"
        else:
            self._bad(BadInput("topic", f"a message on {topic[:80]!r}, which is not a command topic "
                               "of this node"))
            return []
        try:
            p = parse_payload(kind, payload, self.limits)
        except BadInput as e:
            self._bad(e)
            return []
        if len(parts) == 4 and parts[2] == "NCMD":
            by_alias = {a: n for n, a in self._node_alias.items()}
            out: list[Publish | Disconnect | Submit] = []
            for m in p.metrics:
                name = m.name or by_alias.get(m.alias, "")
                if get_value(m) is not True:
                    continue
                if name == M.REBIRTH:
                    out.extend(self.rebirth(now_ms))
                elif name in (M.NEXT_SERVER, M.REBOOT):
                    out.extend(self.reboot(name, now_ms))
                else:
                    self.counters["ignored_commands"] += 1
            return out
        if len(parts) == 5 and parts[2] == "DCMD":
            dev = self.devices.get(parts[4])
            if dev is None or dev.stopped:
                self.counters["ignored_commands"] += 1
                return []
            names = {dev.alias_base + i: d.name for i, d in enumerate(M.DEVICE_METRICS)}
            vals = {}
            for m in p.metrics:
                name = m.name or names.get(m.alias, "")
                if name in M.DEVICE_BY_NAME and M.DEVICE_BY_NAME[name].writable:
                    vals[name] = get_value(m)
                else:
                    self.counters["ignored_commands"] += 1
            args = {M.COMMAND_ARGS[k]: v for k, v in vals.items() if k in M.COMMAND_ARGS and v is not None}
            subs: list[Publish | Disconnect | Submit] = []
            for name, ck in M.COMMANDS.items():
                if vals.get(name) is True:      # each command takes the arguments it knows
                    keys = COMMAND_KEYS[CommandKind(ck)] + ("request_id",)
                    subs.append(Submit(dev.device_id, ck, {k: v for k, v in args.items() if k in keys}))
            return subs
        self.counters["ignored_commands"] += 1
        return []

    def command_result(self, device_id: str, kind: str, ok: bool, code: int, reason: str,
                       now_ms: int) -> list[Publish]:
        text = (f"{kind}: accepted" + (f" ({reason})" if reason else "")) if ok else f"{kind}: rejected: {reason}"
        return self.device_update(device_id, {"Device Control/Last Command": text,
                                              "Device Control/Last Result Code": 0 if ok else int(code)},
                                  now_ms)


_MISSING = object()
#: bad inputs kept for the caller between two takes (the counters count them all)
BAD_MAX = 64
_DEVICE_INDEX = {d.name: i for i, d in enumerate(M.DEVICE_METRICS)}
