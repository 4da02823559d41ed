"""The planner's site view (issue 29 item 3): the stations of the other boxes of this console's
``station.site``, learned from the broker.

Every station publishes its retained ``<base>/state`` and ``<base>/status`` (docs/mqtt.md); the
console's box subscribes to ``<prefix>/<site>/+/+/+/state`` and ``…/status`` through the MQTT pump
it already has (one of its stations' sessions; no second MQTT session) and keeps, per station of
another box, what the due list and the fleet cards show. Read-only: commands only go to the
stations of this box (the console's own feeds).

Liveness: a station whose ``status`` is ``offline`` (its gateway's Last Will, or a clean stop) or
whose last ``state`` arrived more than :data:`STALE_S` ago (a station publishes it at least every
10 s) is *silent since* the time of the last thing it said (its last state's ``time``, else the
status's).

Bounded everywhere: a message goes through the one bounded JSON reader
(:func:`gateway.core.command_intake.read_bounded_json`: bytes, depth, numbers, keys, strings), then
every kept field is type-checked and every string is clipped to printable ASCII
(:func:`gateway.plumbing.ratelog.clip`); at most :data:`MAX_SITE_STATIONS` stations are kept. A malformed
message is refused with one counted, rate-limited log line (:class:`gateway.plumbing.ratelog.RateLog`) and
changes nothing. Thread-safe: the pump thread writes, the console's loop reads.
"""
from __future__ import annotations

import logging
import math
import threading
import time
from typing import Any

from ...core import catalog
from ...core.command_intake import Refused, bounded_pairs, read_bounded_json
from ...plumbing.ratelog import RateLog, clip, safe
from .boxes import BoxReports, box_filter

log = logging.getLogger("hookwatch.console")

#: the topics below a station's base that the site view reads (both retained)
TOPICS = ("state", "status")
#: stations of other boxes kept at most
MAX_SITE_STATIONS = 256
#: one state / status message, bytes (a state is about 1.5 KB)
MAX_MESSAGE_BYTES = 8 * 1024
#: characters of a remote string shown (station, sample, grade, …)
MAX_TEXT = 64
#: a station whose last state is older than this (s) is silent (it publishes one at least every 10 s)
STALE_S = 35.0

_pairs = bounded_pairs(64, 32, 256)
#: the keys of a remote `state` kept, by their type: the catalog's rows with an MQTT key
#: (gateway/core/catalog.py), and the envelope's time
_STATE = tuple(v for v in catalog.CATALOG if v.mqtt)
_TEXT = tuple(v.name for v in _STATE if v.base_type == "str") + ("time",)
_NUM = tuple(v.name for v in _STATE if v.base_type == "float")
_BOOL = tuple(v.name for v in _STATE if v.base_type == "bool")
#: counts (the lives a history prior came from, §7a v3) and slots
_COUNT = tuple(v.name for v in _STATE if v.base_type == "int")
#: the largest count or slot shown (more than any site holds: 20,000 lives; 30 days of slots)
_MAX_COUNT = 1 << 32
_LISTS = tuple(v for v in _STATE if v.base_type == "list")
_RUNNING = ("baseline_search", "monitoring", "end_of_life")


def filters(base: str) -> tuple[str, ...]:
    """The subscriptions that receive the state and status of every station of the base's site,
    and every box's config report (the Boxes page: gateway/outputs/console/boxes.py)."""
    parts = base.split("/")
    return tuple("/".join(parts[:-3] + ["+", "+", "+", t]) for t in TOPICS) + (box_filter(base),)


def text(v: Any, n: int = MAX_TEXT) -> str | None:
    """A remote string as it may be shown: None, or one line of printable ASCII of at most ``n``
    characters: shown as it is when it already is one, else its ``repr`` clipped (control
    characters escaped)."""
    if v is None:
        return None
    s = safe(v, n)
    return "".join(c if 0x20 <= ord(c) <= 0x7E else "?" for c in s)


def _place(topic: str) -> tuple[str, str, str, str] | None:
    """``…/<area>/<line>/<station>/<state|status>`` → (area, line, station, kind)."""
    parts = topic.split("/")
    if len(parts) < 6 or parts[-1] not in TOPICS:
        return None
    return parts[-4], parts[-3], parts[-2], parts[-1]


def _fin(v: Any) -> bool:
    return not isinstance(v, bool) and isinstance(v, (int, float)) and math.isfinite(v)


def parse_state(obj: Any, station: str) -> dict[str, Any]:
    """A remote ``state`` object → the fields the site view keeps (types checked, strings
    clipped), or :class:`Refused`."""
    if not isinstance(obj, dict):
        raise Refused("a state is a JSON object")
    if obj.get("station") != station:
        raise Refused(f"station {clip(obj.get('station'), 40)} on the topic of {clip(station, 40)}")
    if not isinstance(obj.get("test_state"), str):
        raise Refused("no test_state")
    out: dict[str, Any] = {}
    for k in _TEXT:
        v = obj.get(k)
        if v is not None and not isinstance(v, str):
            raise Refused(f"{k}: {clip(v, 20)} is not a string")
        out[k] = text(v, 128 if k == "prior_source" else MAX_TEXT)
    for k in _NUM:
        v = obj.get(k)
        if v is not None and not _fin(v):
            raise Refused(f"{k}: {clip(v, 20)} is not a number")
        out[k] = None if v is None else float(v)
    for k in _BOOL:
        v = obj.get(k)
        if v is not None and not isinstance(v, bool):
            raise Refused(f"{k}: {clip(v, 20)} is not true/false")
        out[k] = v
    for k in _COUNT:
        v = obj.get(k)
        if v is not None and (isinstance(v, bool) or not isinstance(v, int) or not 0 <= v <= _MAX_COUNT):
            raise Refused(f"{k}: {clip(v, 20)} is not a count")
        out[k] = v
    for row in _LISTS:
        r = obj.get(row.name) or []
        if not isinstance(r, list) or len(r) > len(row.choices) or any(x not in row.choices for x in r):
            raise Refused(f"{row.name} {clip(r, 40)} are not {row.label or row.name}")
        out[row.name] = list(r)
    return out


class SiteView:
    """The stations of the other boxes of the site as this console last heard them (see the
    module docstring). ``local``: the ids of this box's stations (never shown twice, never
    read-only)."""

    def __init__(self, local: set[str] | None = None) -> None:
        self.local: set[str] = set(local or ())
        self._st: dict[str, dict[str, Any]] = {}
        self._lock = threading.Lock()
        self.refused = RateLog(log)
        self.counters: dict[str, int] = {"messages": 0, "refused": 0, "over_bound": 0}
        #: the subscriptions (set when a pump carries them; None: the site view is not fed)
        self.filters: tuple[str, ...] | None = None
        #: the boxes of the site, by their config reports (the Boxes page)
        self.boxes = BoxReports(self.refused)

    # -- the pump thread
    def receive(self, topic: str, payload: bytes, now: float | None = None) -> bool:
        """A retained state/status of a station of the site (or a box's config report): True when
        it was kept."""
        if self.boxes.box_of(topic) is not None:
            return self.boxes.receive(topic, payload, now)
        place = _place(topic)
        if place is None:
            return False
        area, line, station, kind = place
        if station in self.local:
            return False
        now = time.time() if now is None else now
        self.counters["messages"] += 1
        if not payload:                       # a retired station's topic cleared
            with self._lock:
                return self._st.pop(station, None) is not None
        try:
            obj = read_bounded_json(payload, max_bytes=MAX_MESSAGE_BYTES, max_depth=3, pairs=_pairs)
            if kind == "state":
                new = {"state": parse_state(obj, station), "state_at": now}
            else:
                if not isinstance(obj, dict) or obj.get("station") != station \
                        or obj.get("status") not in ("online", "offline"):
                    raise Refused("not a status (station, online/offline)")
                t = obj.get("time")
                new = {"status": obj["status"], "status_at": now,
                       "status_time": text(t) if isinstance(t, str) else None}
        except Refused as e:
            self.counters["refused"] += 1
            self.refused.warning(("site", kind), "console: the %s of station %s of the site refused: %s",
                                 kind, text(station, 40), e)
            return False
        with self._lock:
            cur = self._st.get(station)
            if cur is None and len(self._st) >= MAX_SITE_STATIONS:
                self.counters["over_bound"] += 1
                self.refused.warning("bound", "console: station %s of the site not shown: more than "
                                     "%d stations", text(station, 40), MAX_SITE_STATIONS)
                return False
            cur = cur if cur is not None else {"area": text(area), "line": text(line)}
            cur.update(new)
            self._st[station] = cur
        return True

    # -- any thread
    def stations(self) -> int:
        with self._lock:
            return len(self._st)

    def cards(self, now: float | None = None) -> list[dict[str, Any]]:
        """One fleet card per station of another box (the keys of the console's own cards, plus
        ``remote``, ``online``, ``silent_since``, ``heard_at``)."""
        now = time.time() if now is None else now
        with self._lock:
            items = [(k, dict(v)) for k, v in self._st.items() if k not in self.local]
        out = []
        for sid, v in items:
            s: dict[str, Any] = dict(v.get("state") or {})
            st_name = s.pop("test_state", None)
            heard = max(v.get("state_at") or 0.0, v.get("status_at") or 0.0)
            offline = v.get("status") == "offline"
            stale = v.get("state_at") is None or now - v["state_at"] > STALE_S
            silent = offline or stale
            card = {**s, "station": text(sid), "state": st_name, "line": v.get("line") or "",
                    "area": v.get("area") or "", "remote": True, "online": not silent,
                    "silent_since": (s.get("time") or v.get("status_time")) if silent else None,
                    "heard_at": heard or None, "mqtt_ok": None}
            if st_name not in _RUNNING or card.get("t_life") is not None:
                card.update(t_cross=None, end_p10=None, end_p50=None, end_p90=None, p_end=None,
                            due=False)
            card["past_threshold"] = card.get("t_life") is not None or st_name == "end_of_life"
            out.append(card)
        return out

    def close(self) -> None:
        self.refused.close()
