"""A station as a Sparkplug device: the station-side Output (see gateway/core/records.py).

The station's loop calls ``on_record`` / ``on_event`` / ``on_state`` with O(1) work: records are
aggregated per ``data_interval_s``; state changes become metric values; both are handed to the
node's thread (:class:`~.client.NodeRuntime`) through its queue. ``start`` attaches the station
to its node (DBIRTH), ``stop`` detaches it (DDEATH; the last station ends the node: NDEATH).
"""
from __future__ import annotations

import asyncio
import datetime as _dt
import logging
import time
from typing import Any

from ...core import catalog
from ...core.alarms import ALARMS, ANNUNCIATED, AlarmState, from_station
from ...core.ports import StationView
from ...core.records import Event, EventType, SlotRecord, StationState
from ...core.slotwindow import SlotWindow
from ..broker.settings import broker_kwargs
from . import metrics as M
from . import runtime as _client
from .node_settings import SparkplugSettings

log = logging.getLogger("hookwatch.sparkplug")

def _alarm_values(name: str, value: str, shelved_until: float | None = None) -> dict[str, Any]:
    """The metrics of one alarm (``name`` of gateway.core.alarms.ALARMS) in ISA-18.2 state ``value``;
    ``shelved_until`` (s since the epoch) is shown only while the alarm is shelved."""
    try:
        s = from_station(value)
    except ValueError:
        s = AlarmState.NORMAL
    folder = M.ALARM_FOLDERS[name]
    until = int(round(shelved_until * 1000)) if s == AlarmState.SHELVED and shelved_until else None
    return {f"{folder}/State": s.value, f"{folder}/Active": s in ANNUNCIATED,
            f"{folder}/Priority": int(ALARMS[name].priority), f"{folder}/Shelved Until": until}


def _shelved_until(station: StationView | None, name: str) -> float | None:
    """When the station's alarm store shelved alarm ``name`` until (None: not shelved / no store)."""
    return station.alarms.shelved_until(name) if station is not None else None


def metric_value(v: catalog.Value, x: catalog.Reading) -> Any:
    """A catalog row's reading as its metric carries it: a list comma-separated, an ISO 8601 time
    as a DateTime (ms since the epoch), nothing as the row's ``empty`` (None: null)."""
    sp = v.sparkplug
    assert sp is not None
    if x is None:
        return sp.empty
    if isinstance(x, list):
        return ",".join(x)
    if sp.datatype == "DateTime" and isinstance(x, str):
        try:
            return int(round(_dt.datetime.fromisoformat(x.replace("Z", "+00:00")).timestamp() * 1000))
        except ValueError:
            return None
    return x


def state_values(st: StationState, station: StationView | None = None,
                 values: tuple[catalog.Value, ...] = M.STATE_VALUES) -> dict[str, Any]:
    """The device metrics that follow the station's state: the catalog's rows (but those that
    change with time alone, sent with every state: :func:`ticking_values`) and the alarms'
    folders (the shelving expiries from ``station``'s alarm store, when given)."""
    out = {v.sparkplug.name: metric_value(v, v.source(st))
           for v in values if v.sparkplug is not None and not v.ticks}
    out.update(_alarm_values("end_of_life", st.alarm, _shelved_until(station, "end_of_life")))
    out.update(_alarm_values("wear_warning", st.warning_alarm, _shelved_until(station, "wear_warning")))
    return out


def ticking_values(st: StationState, values: tuple[catalog.Value, ...] = M.STATE_VALUES) -> dict[str, Any]:
    """The rows that change with time alone (the elapsed time), sent with every state of a test."""
    if not st.test_id:
        return {}
    return {v.sparkplug.name: metric_value(v, x) for v in values
            if v.sparkplug is not None and v.ticks and (x := v.source(st))}


def window_values(w: SlotWindow, slots: tuple[catalog.SlotValue, ...] = catalog.SLOT_CATALOG) -> dict[str, Any]:
    """A data interval's device metrics from its window of slots (``gateway/core/slotwindow.py``):
    the catalog's slot records' rows with a Sparkplug metric (gateway/core/catalog.py)."""
    return catalog.read_sparkplug(slots, w)


class SparkplugOutput:
    """Station output publishing the station as one Sparkplug device of its edge node."""

    def __init__(self, settings: SparkplugSettings, station: StationView | None = None):
        self.s = settings
        self.station = station
        self.loop: asyncio.AbstractEventLoop | None = None
        self.rt: _client.NodeRuntime | None = None
        self._agg: SlotWindow | None = None
        self._last: dict[str, Any] = {}

    async def start(self) -> None:
        self.loop = asyncio.get_running_loop()
        self._last = state_values(self.station.state, self.station) if self.station is not None else {}
        self.rt = _client.attach(self.s, self)
        self.rt.post(("up", self.s.device_id, dict(self._last)))

    async def stop(self) -> None:
        if self.rt is None:
            return
        self._flush(time.monotonic())
        self.rt.post(("down", self.s.device_id))
        last = _client.detach(self.s)
        if last is not None:
            await asyncio.get_running_loop().run_in_executor(None, last.stop, 5.0)
        self.rt = None

    def on_record(self, rec: SlotRecord) -> None:
        now = time.monotonic()
        agg = self._agg
        if agg is None:
            agg = self._agg = SlotWindow(now)
        agg.add(rec)
        if now - agg.t0 >= self.s.data_interval_s:
            self._flush(now)

    def _flush(self, now: float) -> None:
        agg = self._agg
        if agg is None or agg.n == 0 or self.rt is None:
            return
        self._agg = SlotWindow(now)
        self.rt.post(("update", self.s.device_id, window_values(agg), True))

    def on_state(self, st: StationState) -> None:
        vals = state_values(st, self.station)
        changed = {k: v for k, v in vals.items() if self._last.get(k, _NONE) != v}
        changed.update(ticking_values(st))
        self._last = vals
        if changed and self.rt is not None:
            self.rt.post(("update", self.s.device_id, changed, False))

    def on_event(self, ev: Event) -> None:
        # the alarm and test metrics follow the state pushed with each event; an end of life or a
        # wear warning is reported at once, with its numbers, even before the next state push
        if ev.type not in (EventType.END_OF_LIFE, EventType.WEAR_WARNING) or self.rt is None:
            return
        d = ev.data
        name = "end_of_life" if ev.type == EventType.END_OF_LIFE else "wear_warning"
        vals = _alarm_values(name, next((tr["to"] for tr in reversed(d.get("transitions") or [])
                                         if tr.get("alarm") == name), "unacknowledged"),
                             _shelved_until(self.station, name))
        for key in ("mu_ss", "mu_th", "t_life") if name == "end_of_life" else ("mu_ss", "mu_th"):
            vals[M.STATE_METRIC[key]] = d.get(key)
        self.rt.post(("update", self.s.device_id, vals, False))


_NONE = object()


def settings_from_config(cfg) -> SparkplugSettings:
    """SparkplugSettings from a station's configuration (its `sparkplug:` and `station:` sections)."""
    sp, st = cfg.sparkplug, cfg.station
    group = sp.group_id or st.site or "hookwatch"
    node = sp.edge_node_id or "-".join(x for x in (st.area, st.line) if x) or "edge"
    return SparkplugSettings(
        group_id=group, edge_node_id=node, device_id=sp.device_id or st.id, **broker_kwargs(sp),
        primary_host_id=sp.primary_host_id, data_interval_s=float(sp.data_interval_s),
        store_path=sp.store_path or _client.default_store(cfg.recorder.dir, group, node),
        history_budget_bytes=int(float(sp.history_budget_mb) * 1024 * 1024),
        rebirth_min_interval_s=float(sp.rebirth_min_interval_s), max_command_bytes=int(sp.max_command_bytes),
        max_command_metrics=int(sp.max_command_metrics), max_string_chars=int(sp.max_string_chars),
        state_max_bytes=int(sp.state_max_bytes), state_future_skew_s=float(sp.state_future_skew_s))
