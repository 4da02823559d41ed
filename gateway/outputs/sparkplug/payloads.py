"""The edge node's messages as Sparkplug B payloads, each with its message sequence number. Pure.

Every message but NDEATH carries ``seq``: 0 on the NBIRTH, then +1 per message, 255 → 0
(tck-id-payloads-sequence-num-incrementing); NDEATH carries the bdSeq only. Births carry every
metric with name, alias (device metrics, and the node's but Rebirth and bdSeq), datatype, timestamp,
current value (``is_null`` when none or not finite) and properties (engUnit, description,
writable); device data carries aliases only (no name, no datatype).
"""
from __future__ import annotations

import math
from typing import Any

from . import metrics as M
from .actions import QOS_DEATH, Publish
from .devices import DEVICE_INDEX, Device
from .namespace import NodeTopics
from .sparkplug_b_pb2 import Payload


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


def add_data(p: Payload, dev: Device, values: dict[str, Any], now_ms: int, historical: bool) -> None:
    """Device metrics by alias only (no name, no datatype), each with its timestamp."""
    for k, v in values.items():
        d = M.DEVICE_BY_NAME[k]
        m = p.metrics.add()
        m.alias = dev.alias_base + DEVICE_INDEX[k]      # by alias only, no name, no datatype
        m.timestamp = int(now_ms)
        if historical:
            m.is_historical = True
        set_value(m, d.datatype, v)


class Outgoing:
    """The node's messages as they go out, in order: each payload takes the next ``seq``; a
    DBIRTH marks its device born, a DDEATH unborn."""

    def __init__(self, topics: NodeTopics, software: str = "hookwatch") -> None:
        self.topics = topics
        self.software = software
        self.seq = 0
        self._node_alias = M.node_aliases()

    @property
    def node_aliases(self) -> dict[str, int]:
        """The node metrics' aliases by name (Rebirth and bdSeq have none)."""
        return self._node_alias

    def next_seq(self) -> int:
        s = self.seq
        self.seq = (self.seq + 1) % 256
        return s

    def _payload(self, now_ms: int, seq: bool = True) -> Payload:
        p = Payload()
        p.timestamp = int(now_ms)
        if seq:
            p.seq = self.next_seq()
        return p

    def ndeath(self, bdseq: int) -> Publish:
        p = Payload()
        m = p.metrics.add()
        m.name = M.BDSEQ
        m.datatype = M.DataType.Int64
        m.long_value = bdseq
        return Publish(self.topics.topic("NDEATH"), p.SerializeToString(), QOS_DEATH, False)

    def nbirth(self, now_ms: int, bdseq: int, devices_running: int) -> Publish:
        """NBIRTH: seq starts again at 0; every node metric with its value."""
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
                set_value(m, d.datatype, bdseq)
            elif d.writable:
                set_value(m, d.datatype, False)
            elif d.name == "Properties/Software":
                set_value(m, d.datatype, self.software)
            elif d.name == "Properties/Devices":
                set_value(m, d.datatype, devices_running)
            _properties(m, d)
        return Publish(self.topics.topic("NBIRTH"), p.SerializeToString())

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
        return Publish(self.topics.topic("DBIRTH", dev.device_id), p.SerializeToString())

    def ddeath(self, dev: Device, now_ms: int) -> Publish:
        dev.born = False
        return Publish(self.topics.topic("DDEATH", dev.device_id), self._payload(now_ms).SerializeToString())

    def ddata(self, dev: Device, values: dict[str, Any], now_ms: int) -> Publish:
        """Live DDATA of ``values`` (metric name → value) by alias."""
        p = self._payload(now_ms)
        add_data(p, dev, values, now_ms, historical=False)
        return Publish(self.topics.topic("DDATA", dev.device_id), p.SerializeToString())

    @staticmethod
    def historical(dev: Device, values: dict[str, Any], now_ms: int) -> bytes:
        """A DDATA payload to store: no seq yet (given at sending), every metric historical."""
        p = Payload()
        p.timestamp = int(now_ms)
        add_data(p, dev, values, now_ms, historical=True)
        return p.SerializeToString()

    def resend(self, device_id: str, payload: bytes) -> Publish | None:
        """A stored DDATA payload as it goes out now (with the next seq); None when it cannot be
        decoded (a damaged row: no seq is used)."""
        p = Payload()
        try:
            p.ParseFromString(payload)
        except Exception:   # noqa: BLE001 - a damaged row: the caller skips it, counted
            return None
        p.seq = self.next_seq()
        return Publish(self.topics.topic("DDATA", device_id), p.SerializeToString())
