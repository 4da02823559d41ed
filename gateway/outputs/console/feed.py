"""From a station's slot loop to the console: one bounded, non-blocking hand-over per station.

:class:`ConsoleOutput` is an ordinary station output. On the slot loop it does nothing but append
the object it is given (the slot record, event or state copy the station already made) to the
station's :class:`~gateway.plumbing.threadloop.Mailbox` (the project's one bounded hand-over): never blocks.
If the console thread stalls for longer than the mailbox holds (:data:`HANDOVER_SLOTS` slots), the
oldest items are dropped and counted; the station and its recorder are never affected.

The console thread drains the mailbox a few times a second (:meth:`StationFeed.drain`) into a
:class:`Series`: μ(t) and the slow signals of the running test from slot 0, min/max-decimated
into at most :data:`MAX_BUCKETS` buckets. When the buckets are full, neighbours are merged and the
bucket width doubles, so a 10-hour test costs the same memory and the same bytes to a browser as a
one-minute one, and a one-slot spike of μ stays visible in the min/max envelope.
"""
from __future__ import annotations

import asyncio
import collections
import datetime as _dt
import logging
import math
import os
import time
import zlib
from dataclasses import asdict
from typing import Any

from ...core import catalog
from ...core.ports import StationView
from ...core.records import Event, EventType, SlotRecord, StationState
from ...offline.logio import tail_jsonl
from ...plumbing.threadloop import Mailbox
from ...station.hook_log import LIFE_KINDS, read_hooks
from ...station.recorder import LOG_COLUMNS

#: slots the hand-over holds (2 min 44 s at 50 Hz) before the oldest are dropped
HANDOVER_SLOTS = 8192
#: most buckets of a series (then neighbours merge and the width doubles)
MAX_BUCKETS = 1024
#: events kept per station for the event list
MAX_EVENTS = 200
#: ISA-18.2 alarm transitions kept per station for the alarm journal
MAX_JOURNAL = 500
#: transitions taken from one event (an event carries one per alarm it changed: two today)
MAX_TRANSITIONS_PER_EVENT = 8
#: recorded tests (newest first) whose events.jsonl seed the journal when the console starts
JOURNAL_TESTS = 5
#: the catalog's values the console shows, each with its label (GET /api/values)
VALUES = tuple(v for v in catalog.CATALOG if v.label)
#: the catalog's slot records' values the console shows (the latest slot's reading): none today
SLOT_VALUES = tuple(s for s in catalog.SLOT_CATALOG if s.label)


def values_json(values: tuple[catalog.Value, ...] = VALUES,
                slots: tuple[catalog.SlotValue, ...] = SLOT_VALUES) -> list[dict[str, str]]:
    """The rows the page shows under "all values" (GET /api/values): the key of its value in the
    station summary's ``values``, its label, unit and type (the state's, then the slot records')."""
    return [{"name": v.name, "label": v.label, "unit": v.unit, "type": v.base_type} for v in values + slots]


def slot_values(rec: SlotRecord | None, slots: tuple[catalog.SlotValue, ...] = SLOT_VALUES) -> dict[str, Any]:
    """The latest slot's readings of the labelled slot rows (a number that is not finite: None)."""
    return {k: (x if not isinstance(x, float) or math.isfinite(x) else None)
            for k, x in catalog.read_latest(slots, rec).items()}


#: states of a running test (TestState values): baseline search, monitoring, end of life
_RUNNING = (1, 2, 3)

log = logging.getLogger("hookwatch.console")

# bucket fields: first slot, mu min, mu max, n valid, sums of t1, t2 (n present), speed cmd (n),
# speed act (n act)
_K0, _MN, _MX, _NV, _S1, _S2, _NP, _SC, _NC, _SA, _NA = range(11)


def _new_bucket(k0: int) -> list:
    return [k0, math.inf, -math.inf, 0, 0.0, 0.0, 0, 0.0, 0, 0.0, 0]


def _num(x: float, nd: int = 5):
    return round(x, nd) if x is not None and math.isfinite(x) else None


class Series:
    """The running test as min/max buckets from slot 0 (bounded memory)."""

    def __init__(self, ts: float = 0.02, max_buckets: int = MAX_BUCKETS):
        self.ts = ts
        self.max = max_buckets
        self.width = 1                # slots per bucket
        self.buckets: list[list] = []
        self.gen = 0                  # changes whenever earlier buckets change (merge or reset)
        self.dirty_from = 0           # first bucket changed since the last take_changes()
        self.recent_mu: collections.deque = collections.deque(maxlen=50)
        self.n_slots = 0
        self.n_valid = 0
        self.n_present = 0
        self.last_k = -1

    def reset(self) -> None:
        self.width = 1
        self.buckets = []
        self.gen += 1
        self.dirty_from = 0
        self.recent_mu.clear()
        self.n_slots = self.n_valid = self.n_present = 0
        self.last_k = -1

    def add(self, rec: SlotRecord) -> None:
        k = rec.k
        b = self.buckets[-1] if self.buckets else None
        if b is None or k >= b[_K0] + self.width:
            if len(self.buckets) >= self.max:
                self._merge()
            b = _new_bucket(k - k % self.width)
            self.buckets.append(b)
            self.dirty_from = min(self.dirty_from, len(self.buckets) - 1)
        elif self.dirty_from > len(self.buckets) - 1:
            self.dirty_from = len(self.buckets) - 1
        self.n_slots += 1
        self.last_k = k
        mu = rec.mu
        if rec.q and mu is not None:
            self.n_valid += 1
            self.recent_mu.append(mu)
            if mu < b[_MN]:
                b[_MN] = mu
            if mu > b[_MX]:
                b[_MX] = mu
            b[_NV] += 1
        if rec.present:
            self.n_present += 1
            b[_S1] += rec.t1
            b[_S2] += rec.t2
            b[_NP] += 1
        if math.isfinite(rec.speed_cmd):
            b[_SC] += rec.speed_cmd
            b[_NC] += 1
        if math.isfinite(rec.speed_act):
            b[_SA] += rec.speed_act
            b[_NA] += 1

    def _merge(self) -> None:
        w = self.width * 2
        out: list[list] = []
        for b in self.buckets:
            k0 = b[_K0] - b[_K0] % w
            if out and out[-1][_K0] == k0:
                o = out[-1]
                o[_MN] = min(o[_MN], b[_MN])
                o[_MX] = max(o[_MX], b[_MX])
                for i in (_NV, _S1, _S2, _NP, _SC, _NC, _SA, _NA):
                    o[i] += b[i]
            else:
                out.append([k0] + b[1:])
        self.buckets = out
        self.width = w
        self.gen += 1
        self.dirty_from = 0

    def row(self, b: list) -> list:
        """[t, μ min, μ max, T1, T2, mean tension, speed cmd, speed act] of one bucket."""
        np_ = b[_NP]
        t1 = b[_S1] / np_ if np_ else None
        t2 = b[_S2] / np_ if np_ else None
        return [round(b[_K0] * self.ts, 3),
                _num(b[_MN], 6) if b[_NV] else None, _num(b[_MX], 6) if b[_NV] else None,
                _num(t1, 4) if t1 is not None else None, _num(t2, 4) if t2 is not None else None,
                _num((t1 + t2) / 2, 4) if t1 is not None else None,
                _num(b[_SC] / b[_NC], 2) if b[_NC] else None,
                _num(b[_SA] / b[_NA], 2) if b[_NA] else None]

    def rows(self, start: int = 0) -> list[list]:
        return [self.row(b) for b in self.buckets[start:]]

    def take_changes(self) -> tuple[int, list[list]] | None:
        """(first changed index, its rows onwards) since the last call, or None."""
        if self.dirty_from >= len(self.buckets):
            return None
        start = self.dirty_from
        self.dirty_from = len(self.buckets)
        return start, self.rows(start)

    def mu_now(self) -> float | None:
        """Median of the last (up to) 50 valid μ: one second of a healthy test."""
        if not self.recent_mu:
            return None
        s = sorted(self.recent_mu)
        n = len(s)
        return s[n // 2] if n % 2 else (s[n // 2 - 1] + s[n // 2]) / 2


def series_from_log(path: str, ts: float = 0.02, max_buckets: int = MAX_BUCKETS) -> Series:
    """The series of a recorded test from its log on disk — also while the recorder still writes
    it (the recorder writes one complete gzip member per flush, about once a second: every member
    on disk is read, one after the other; a torn last member or line is left out)."""
    s = Series(ts, max_buckets)
    d = zlib.decompressobj(16 + zlib.MAX_WBITS)
    col = {c: i for i, c in enumerate(LOG_COLUMNS)}
    it, i1, i2, ic, ia, iq, imu = (col[c] for c in ("t", "T1", "T2", "speed_cmd", "speed_act", "q", "mu"))
    tail = b""
    header = True
    with open(path, "rb") as f:
        while True:
            chunk = f.read(1 << 20)
            if not chunk:
                break
            try:
                data = d.decompress(chunk)
                while d.eof and d.unused_data:     # the next gzip member (one per recorder flush)
                    rest = d.unused_data
                    d = zlib.decompressobj(16 + zlib.MAX_WBITS)
                    data += d.decompress(rest)
            except zlib.error:
                break               # a damaged stream: what was read so far stands
            data = tail + data
            lines = data.split(b"\n")
            tail = lines.pop()
            for ln in lines:
                if header:
                    header = False
                    continue
                v = ln.split(b",")
                try:
                    k = int(float(v[it]) / ts + 1e-6)
                    q = int(v[iq])
                    mu = float(v[imu]) if q else None
                    rec = SlotRecord(k=k, t=k * ts, present=True, t1=float(v[i1]), t2=float(v[i2]),
                                     q=q, mask=0, ratio=None, mu=mu, mean_filt=math.nan,
                                     speed_cmd=float(v[ic]), speed_act=float(v[ia]), saturated=False)
                except (ValueError, IndexError):
                    continue        # a bad row is skipped, never fatal
                s.add(rec)
    return s


class StationFeed:
    """What the console knows about one station; lives on the console thread (except ``q``, the
    hand-over from the slot loop)."""

    def __init__(self, name: str, ts: float = 0.02):
        self.name = name
        self.q: Mailbox[SlotRecord | Event | StationState] = Mailbox(HANDOVER_SLOTS)
        #: records lost before they reached this station's output (a fleet worker's IPC hand-over)
        self.lost_upstream = 0
        self.series = Series(ts)
        self.state: StationState | None = None
        self.events: collections.deque = collections.deque(maxlen=MAX_EVENTS)
        self.markers: dict[str, Any] = {}
        self.headroom: float | None = None
        self.t_cross: float | None = None
        self.running = False
        self.test_id: str | None = None
        #: live records kept while the series is rebuilt from disk after a loss in the hand-over
        self.pending: list | None = None
        self.rebuilds = 0
        self._dropped_seen = 0
        self.last_k: int | None = None
        self.last_seen = 0.0
        # set by the ConsoleOutput bound to the current Station object
        self.station: StationView | None = None
        self.loop: asyncio.AbstractEventLoop | None = None
        self.mqtt_enabled = False
        # where the station stands in the plant (station.line / station.area of its file)
        self.line = ""
        self.area = ""
        #: the ISA-18.2 transitions of the station's alarms, oldest first (bounded)
        self.journal: collections.deque = collections.deque(maxlen=MAX_JOURNAL)
        self.journal_seeded = False
        #: the latest slot record handed over (the labelled slot rows' readings: SLOT_VALUES)
        self.latest: SlotRecord | None = None
        #: the slot rows this feed shows (the catalog's labelled ones)
        self.slot_values = SLOT_VALUES

    # ----------------------------------------------------------------- console thread
    @property
    def dropped(self) -> int:
        """Items lost on the way: dropped by the full hand-over, or before it (``lost_upstream``)."""
        return self.q.dropped + self.lost_upstream

    def drain(self) -> bool:
        """Move what the slot loop handed over into the series; True if anything changed."""
        items = self.q.drain()
        n = len(items)
        changed = n > 0
        for item in items:
            if isinstance(item, SlotRecord):
                self.latest = item
                if self.pending is not None:
                    if len(self.pending) < HANDOVER_SLOTS * 8:
                        self.pending.append(item)
                elif self.running:
                    self.series.add(item)
                    self.last_k = item.k
            elif isinstance(item, Event):
                self._event(item)
            elif isinstance(item, StationState):
                self.state = item
                if item.headroom is not None:
                    self.headroom = item.headroom
                if item.t_cross is not None:
                    self.t_cross = item.t_cross
        if n:
            self.last_seen = time.time()
        if self.dropped != self._dropped_seen:
            self._dropped_seen = self.dropped
            st = self.state
            if self.running or (st is not None and st.test_id and st.state.value in (1, 2, 3)):
                self.running = True
                self.test_id = self.test_id or (st.test_id if st is not None else None)
                if self.pending is None and self.test_id:
                    self.pending = []       # the server rebuilds the series from the log on disk
        return changed

    def rebuild_from(self, disk: Series) -> None:
        """Swap in the series read from disk, then the live records it does not have yet."""
        pending, self.pending = self.pending or [], None
        for rec in pending:
            if rec.k > disk.last_k:
                disk.add(rec)
        disk.gen = self.series.gen + 1
        disk.dirty_from = 0
        self.series = disk
        self.rebuilds += 1

    def _event(self, ev: Event) -> None:
        d = ev.data
        if ev.type == EventType.TEST_STARTED:
            self.series.reset()
            self.markers = {"t_set": d.get("t_set")}
            self.headroom = self.t_cross = None
            self.running = True
            self.test_id = ev.test_id
            self.pending = None
            self.events.clear()
        elif ev.type == EventType.TEST_ENDED:
            self.running = False
            self.markers["t_end"] = (ev.k + 1) * self.series.ts if ev.k is not None else None
        elif ev.type == EventType.BASELINE:
            ts = self.series.ts
            self.markers.update(mu_ss=d.get("mu_ss"), mu_th=d.get("mu_th"),
                                k_b=d.get("k_b"), t_b=(d["k_b"] * ts if d.get("k_b") is not None else None),
                                t_stable=(d["stable_first"] * ts if d.get("stable_first") is not None else None))
        elif ev.type == EventType.END_OF_LIFE:
            self.markers["t_life"] = d.get("t_life")
        for name in ("headroom", "t_cross"):
            if d.get(name) is not None:
                setattr(self, name, d[name])
        if d.get("warn_slot") is not None:
            self.markers["t_warn"] = (d["warn_slot"] + 1) * self.series.ts
        self.journal.extend(journal_entries(ev.as_dict()))
        self.events.append(ev.as_dict())

    def seed_journal(self, entries: list[dict[str, Any]]) -> None:
        """Put the transitions read from the recorded tests before those seen live (once)."""
        self.journal_seeded = True
        self.journal = merge_journal(entries, list(self.journal))

    def summary(self, values: bool = False) -> dict[str, Any]:
        """The fleet card; with ``values`` (the station page's) every labelled value of the
        catalog (gateway/core/catalog.py) under ``values``, for the page's "all values"."""
        st = self.state
        s: dict[str, Any] = asdict(st) if st is not None else {"station": self.name}
        if st is not None:
            s["state"] = st.state.name.lower()
        s.update(mu_now=_num(self.series.mu_now() or math.nan, 6), headroom=self.headroom,
                 t_cross=self.t_cross, slots=self.series.n_slots, valid=self.series.n_valid,
                 filled=self.series.n_present,
                 running=self.running, handover_dropped=self.dropped,
                 online=self.station is not None, last_seen=self.last_seen,
                 line=self.line, area=self.area)
        if st is not None:
            # the station's own projection is the truth (not the last one any record carried)
            s["t_cross"] = st.t_cross
        if st is None or st.t_life is not None or st.state.value not in _RUNNING:
            # no projection after the end of life nor outside a running test (the hook's life is
            # known, or there is no test): a stale "projected crossing" is never shown
            s.update(t_cross=None, end_p10=None, end_p50=None, end_p90=None, p_end=None, due=False)
        s["past_threshold"] = bool(st is not None and (st.t_life is not None or st.state.value == 3))
        if values:
            s["values"] = catalog.read(VALUES, st) if st is not None else {}
            if self.slot_values:
                s["values"].update(slot_values(self.latest, self.slot_values))
        if not self.mqtt_enabled:
            s["mqtt_ok"] = None         # no MQTT link configured: nothing to show
        # else the station's state says it (StationState.mqtt_ok, from the MQTT output's uplink
        # through Station.set_uplink, in a fleet worker as in one process)
        return s

    def snapshot(self) -> dict[str, Any]:
        s = self.series
        return {"type": "snapshot", "station": self.name, "gen": s.gen, "width_s": s.width * s.ts,
                "rows": s.rows(), "markers": self.markers, "summary": self.summary(values=True),
                "events": list(self.events)}


def _wall(start: Any, offset_s: Any) -> str | None:
    """``start`` (ISO 8601 of slot 0) + ``offset_s`` seconds as ISO 8601 UTC (seconds, ``Z``)."""
    if not isinstance(start, str) or not isinstance(offset_s, (int, float)) or isinstance(offset_s, bool) \
            or not math.isfinite(offset_s) or abs(offset_s) > 1e9:
        return None
    try:
        t0 = _dt.datetime.fromisoformat(start.replace("Z", "+00:00"))
    except ValueError:
        return None
    if t0.tzinfo is None:
        t0 = t0.replace(tzinfo=_dt.UTC)
    t = (t0 + _dt.timedelta(seconds=float(offset_s))).astimezone(_dt.UTC)
    return t.strftime("%Y-%m-%dT%H:%M:%SZ")


#: the columns of the planner's due list (JSON keys and CSV header, in this order)
DUE_COLUMNS = ("station", "line", "area", "sample_id", "grade", "state", "due", "end_utc_p10",
               "end_utc_p50", "end_utc_p90", "p_end", "reasons", "t_life_utc", "headroom",
               "alarm", "test_id", "test_started_utc", "end_p10", "end_p50", "end_p90", "t_life",
               "prior_mean", "prior_sd", "prior_source", "prior_n", "prior_n_censored",
               "prior_n_early", "remote", "online", "silent_since")


def due_row(s: dict[str, Any]) -> dict[str, Any]:
    """One station of the due list from its fleet card (:meth:`StationFeed.summary`)."""
    start = s.get("test_started_utc")
    life = s.get("t_life")
    reasons = s.get("warn_reasons") or []
    row = {k: s.get(k) for k in DUE_COLUMNS}
    row.update(end_utc_p10=_wall(start, s.get("end_p10")), end_utc_p50=_wall(start, s.get("end_p50")),
               end_utc_p90=_wall(start, s.get("end_p90")), t_life_utc=_wall(start, life),
               reasons=[str(r) for r in reasons] if isinstance(reasons, list) else [],
               due=bool(s.get("due")) or life is not None,
               line=s.get("line") or "", area=s.get("area") or "", remote=bool(s.get("remote")))
    # how soon it is due: the hook past its end of life first (at the wall time of t_life), then
    # by the median projected end (p50, then p10), then running tests without a projection, then
    # the rest; the station's name breaks ties
    if life is not None:
        row["_key"] = (0, row["t_life_utc"] or "", s.get("station", ""))
    elif row["end_utc_p50"] or row["end_utc_p10"]:
        row["_key"] = (1, row["end_utc_p50"] or row["end_utc_p10"], s.get("station", ""))
    elif s.get("state") in ("baseline_search", "monitoring", "end_of_life"):
        row["_key"] = (2, "", s.get("station", ""))
    else:
        row["_key"] = (3, "", s.get("station", ""))
    return row


def due_list(cards: list[dict[str, Any]], line: str | None = None,
             area: str | None = None) -> list[dict[str, Any]]:
    """The planner's due list: every station (of ``line`` / ``area`` when given), the soonest
    due first."""
    rows = [due_row(c) for c in cards
            if (line is None or (c.get("line") or "") == line)
            and (area is None or (c.get("area") or "") == area)]
    rows.sort(key=lambda r: r["_key"])
    for r in rows:
        del r["_key"]
    return rows


def journal_entries(ev: dict[str, Any]) -> list[dict[str, Any]]:
    """The journal lines of one station event (``Event.as_dict`` or a line of events.jsonl): one
    per ISA-18.2 transition it carries (``transitions``), with the event's type, test and source."""
    trs = ev.get("transitions")
    if not isinstance(trs, list):
        return []
    out = []
    for t in trs[:MAX_TRANSITIONS_PER_EVENT]:
        if not isinstance(t, dict) or not isinstance(t.get("time"), (int, float)):
            continue
        out.append({"time": float(t["time"]), "alarm": _short(t.get("alarm")),
                    "from": _short(t.get("from")), "to": _short(t.get("to")),
                    "action": _short(t.get("action")), "by": _short(t.get("by")),
                    "hook": _short(t.get("hook")), "priority": t.get("priority")
                    if isinstance(t.get("priority"), int) else None,
                    "event": _short(ev.get("type")), "test_id": _short(ev.get("test_id"))})
    return out


def _short(v: Any, n: int = 128) -> str | None:
    return None if v is None else str(v)[:n]


def _jkey(e: dict[str, Any]) -> tuple:
    return (e.get("time"), e.get("alarm"), e.get("action"), e.get("from"), e.get("to"))


def merge_journal(older: list[dict[str, Any]], newer: list[dict[str, Any]],
                  n: int = MAX_JOURNAL) -> collections.deque:
    """Both lists as one journal in time order, each transition once, the newest ``n`` kept."""
    seen: set[tuple] = set()
    out = []
    for e in sorted(older + newer, key=lambda e: e.get("time") or 0.0):
        k = _jkey(e)
        if k not in seen:
            seen.add(k)
            out.append(e)
    return collections.deque(out[-n:], maxlen=n)


def journal_from_disk(station_dir: str, n_tests: int = JOURNAL_TESTS) -> list[dict[str, Any]]:
    """The alarm transitions recorded in the events.jsonl of the station's newest tests."""
    try:
        names = sorted((n for n in os.listdir(station_dir)
                        if os.path.isfile(os.path.join(station_dir, n, "events.jsonl"))),
                       reverse=True)[:n_tests]
    except OSError:
        return []
    out: list[dict[str, Any]] = []
    for n in reversed(names):
        evs, bad = tail_jsonl(os.path.join(station_dir, n, "events.jsonl"))
        if bad:
            log.warning("console: %s/events.jsonl: %d damaged lines skipped", n, bad)
        for ev in evs:
            out.extend(journal_entries(ev))
    return out[-MAX_JOURNAL:]


#: the fields of one hooks.jsonl line (the station's life log; docs/console.md)
HOOK_FIELDS = ("station", "old_sample_id", "new_sample_id", "grade", "by", "utc", "test_id", "life_s",
               "life_kind")


def hook_history(station_dir: str) -> list[dict[str, Any]]:
    """The successive hooks of a station (``<station dir>/hooks.jsonl``, read by
    :func:`gateway.station.hook_log.read_hooks`: bounded, a damaged line skipped), newest first, each
    with the :data:`HOOK_FIELDS` only, texts clipped, ``life_s`` a finite number or None,
    ``life_kind`` one of §7a's kinds (:data:`~gateway.station.hook_log.LIFE_KINDS`) or None."""
    rows = read_hooks(station_dir)
    out = []
    for r in reversed(rows):
        h = {k: r.get(k) for k in HOOK_FIELDS}
        for k in ("station", "old_sample_id", "new_sample_id", "grade", "by", "utc", "test_id"):
            if h[k] is not None:
                h[k] = str(h[k])[:128]
        life = h["life_s"]
        h["life_s"] = float(life) if isinstance(life, (int, float)) and not isinstance(life, bool) \
            and math.isfinite(life) else None
        if h["life_kind"] not in LIFE_KINDS:      # §7a v3's kinds only (older lines: none)
            h["life_kind"] = None
        out.append(h)
    return out


class ConsoleOutput:
    """The station-side end of the hand-over (one per Station object)."""

    def __init__(self, feed: StationFeed, station: StationView | None = None):
        self.feed = feed
        self.station = station
        self._put = feed.q.put_nowait

    async def start(self) -> None:
        self.feed.loop = asyncio.get_running_loop()
        self.feed.station = self.station

    async def stop(self) -> None:
        if self.feed.station is self.station:
            self.feed.station = None
            self.feed.loop = None

    def on_record(self, rec: SlotRecord) -> None:
        self._put(rec)

    def on_event(self, ev: Event) -> None:
        self._put(ev)

    def on_state(self, st: StationState) -> None:
        self._put(st)

    # -- a station in a worker process, fed by the fleet supervisor (gateway/supervisor/remote.py)
    def on_worker(self, up: bool, restarts: int = 0) -> None:
        """The station's worker process came up or went down: the card shows it online/offline
        and commands are refused while it is down."""
        self.feed.station = self.station if up else None

    def on_lost(self, n: int) -> None:
        """``n`` slot records were lost before they reached this output (the IPC hand-over): the
        console rebuilds the running test's curve from the recorder's log, as for its own losses."""
        self.feed.lost_upstream += int(n)

    def on_metrics(self, snap: dict[str, object]) -> None:
        pass        # the console shows the station's own figures, not the worker's snapshot
