"""The site's life history (issue 29 item 2; METHOD.md §7a): the gateways of one ``station.site``
share every completed test's life over the broker they already use, and each pools what the
others share into its §7a history, each test once (by test id).

Topic design — one retained message per station, ``<base>/lives`` (base = ``<prefix>/<site>/
<area>/<line>/<station>``), holding that station's newest :data:`MAX_LIVES_PER_STATION` lives;
every gateway subscribes to ``<prefix>/<site>/+/+/+/lives``. Why:

- *retained*: on a single broker, a gateway that joins late (or was away) gets every station's
  lives from the broker at once (and the request below makes sure of it on any broker);
- *one message per station, a snapshot*: the broker keeps a bounded amount per station (one
  message of at most :data:`MAX_LIVES_BYTES`), never a growing number of retained topics; a
  snapshot replaces the last one whole (no partial state, nothing to delete); a retired station is
  cleared by an empty retained message on its topic;
- *published again after every (re)connect*: a broker that lost its retained store (a restart
  without persistence, another node of a cluster) gets it back;
- *persisted locally* (``<station folder>/site_lives.json``): a gateway that restarts while the
  broker is down still has the site's history;
- *asked for on every (re)connect, never left to the retained store alone*: a clustered broker
  keeps a retained message on the node that received it (RabbitMQ 3.10), and a killed node loses
  it, so a gateway joining through another node gets nothing retained. A station that (re)connects
  publishes one small, non-retained request on the site's ``<prefix>/<site>/lives_request``
  (:func:`gateway.outputs.mqtt.schema.lives_request_topic`; payload: its station id); every station
  of the site that hears it publishes its snapshot again on its ``lives`` topic — retained, the same
  message as always: it reaches the asking gateway through the cluster's routing on any node, and
  it also gives the answering station's node its retained copy back. :class:`LivesAnswers` bounds
  the answers: at most one per station per :data:`ANSWER_INTERVAL_S` however many requests (the
  requests within an interval share one answer at its end), a flood is counted and logged as one
  rate-limited line, and costs nothing else (no parsing, no queue, at most one timer). The receiver
  keeps each station's newest snapshot (each test once by test id): a duplicate changes nothing.

Bounded everywhere: a message is read by the one bounded JSON reader
(:func:`gateway.core.command_intake.read_bounded_json`: bytes, depth, numbers, keys, strings);
at most :data:`MAX_LIVES_PER_STATION` lives per station, :data:`MAX_SITE_STATIONS` stations and
:data:`MAX_SITE_LIVES` lives in all. A malformed message or an implausible record (a life ≤ 0 or
beyond its planned duration, NaN, a huge string, a censored life that is not one) is refused with
one counted, rate-limited log line (:class:`gateway.plumbing.ratelog.RateLog`) and never reaches a prior.
"""
from __future__ import annotations

import dataclasses
import json
import logging
import math
import os
import threading
from collections.abc import Callable, Iterable, MutableMapping
from typing import Any

from ...core.command_intake import Refused, bounded_pairs, read_bounded_json
from ...core.method.prior import STOPPED, PastTest
from ...plumbing.ratelog import RateBound, RateLog, clip
from ...plumbing.safeout import write_atomic
from .schema import SCHEMA_VERSION

log = logging.getLogger("hookwatch.site")

#: the topic below a station's base that holds its lives (retained)
LIVES = "lives"
#: lives one station shares (its newest)
MAX_LIVES_PER_STATION = 500
#: one station's message, bytes (500 lives of ≈ 300 bytes)
MAX_LIVES_BYTES = 256 * 1024
#: stations of a site whose lives are kept
MAX_SITE_STATIONS = 256
#: lives of the whole site that are kept
MAX_SITE_LIVES = 20_000
#: the local copy, bytes (the site's lives at their largest)
MAX_STORE_BYTES = 16 * 1024 * 1024
#: characters of a test id, grade, reason
MAX_ID_CHARS = 128
MAX_GRADE_CHARS = 32
MAX_REASON_CHARS = 64
#: a planned duration longer than this (s, ≈ 116 days) is not plausible
MAX_T_END_S = 1e7
#: a T_set above this (N) is not plausible
MAX_T_SET_N = 100.0
#: the file beside a station's tests that holds the other stations' lives
STORE_NAME = "site_lives.json"
#: a station publishes its lives again at most once per this many seconds, however many requests
#: (the requests within one interval are answered together at its end)
ANSWER_INTERVAL_S = 10.0

_STATUSES = ("failure", "no_failure", "aborted")
_RECORD_KEYS = ("test_id", "grade", "t_set", "status", "t_life", "censored_s", "n_slots", "ts",
                "k_b", "stop_reasons", "end_reason", "t_end")
_pairs = bounded_pairs(16, 32, MAX_ID_CHARS)


def lives_topic(base: str) -> str:
    return f"{base}/{LIVES}"


def site_filter(base: str) -> str:
    """The subscription that receives the lives of every station of the base's site."""
    parts = base.split("/")
    return "/".join(parts[:-3] + ["+", "+", "+", LIVES])


def station_of(topic: str) -> str | None:
    """The station level of a ``…/<station>/lives`` topic."""
    parts = topic.split("/")
    return parts[-2] if len(parts) >= 6 and parts[-1] == LIVES else None


# ----------------------------------------------------------------------------- records
def record_of(t: PastTest) -> dict[str, Any] | None:
    """What a station shares of one of its tests (None: it gives the history no life, or lacks
    what a receiver checks it by: a test id, grade, T_set, planned duration)."""
    lf = t.life()
    if (lf is None or t.test_id is None or t.grade is None or t.t_set is None or t.t_end is None
            or not math.isfinite(t.t_end)):
        return None
    return {"test_id": t.test_id, "grade": t.grade, "t_set": t.t_set, "status": t.status,
            "t_life": t.t_life if lf[0] == "failure" else None,
            "censored_s": lf[1] if lf[0] == "censored" else None,
            "n_slots": t.n_slots, "ts": t.ts, "k_b": t.k_b,
            "stop_reasons": None if t.stop_reasons is None else list(t.stop_reasons),
            "end_reason": t.end_reason, "t_end": t.t_end}


def _printable(s: Any, n: int) -> bool:
    return isinstance(s, str) and 0 < len(s) <= n and all(0x20 <= ord(c) <= 0x7E for c in s)


def _fin(v: Any) -> bool:
    return not isinstance(v, bool) and isinstance(v, (int, float)) and math.isfinite(v)


def _int(v: Any) -> bool:
    return isinstance(v, int) and not isinstance(v, bool)


def parse_record(r: Any, station: str) -> PastTest | str:
    """A shared record → a PastTest of ``station``, or why it is refused."""
    if not isinstance(r, dict):
        return "a record is not an object"
    unknown = [k for k in r if k not in _RECORD_KEYS]
    if unknown:
        return f"unknown key {clip(unknown[0], 32)}"
    v: dict[str, Any] = {k: r.get(k) for k in _RECORD_KEYS}
    tid, grade, t_set, status = v["test_id"], v["grade"], v["t_set"], v["status"]
    if not _printable(tid, MAX_ID_CHARS):
        return f"test_id {clip(tid, 40)} is not an id"
    if not _printable(grade, MAX_GRADE_CHARS):
        return f"{tid}: grade {clip(grade, 40)} is not a grade"
    if not (_fin(t_set) and 0 < t_set <= MAX_T_SET_N):
        return f"{tid}: t_set {clip(t_set, 40)} is not plausible"
    if status not in _STATUSES:
        return f"{tid}: status {clip(status, 40)} gives no life"
    t_end, ts, n_slots, k_b = v["t_end"], v["ts"], v["n_slots"], v["k_b"]
    if not (_fin(t_end) and 0 < t_end <= MAX_T_END_S):
        return f"{tid}: t_end {clip(t_end, 40)} is not a planned duration"
    if not (_fin(ts) and 0 < ts <= 1.0):
        return f"{tid}: ts {clip(ts, 40)} is not a sampling period"
    if not (_int(n_slots) and 0 < n_slots <= t_end / ts + 2):
        return f"{tid}: n_slots {clip(n_slots, 40)} is not plausible for t_end {t_end:g} s"
    if k_b is not None and not (_int(k_b) and 0 <= k_b < n_slots):
        return f"{tid}: k_b {clip(k_b, 40)} is not plausible"
    reasons = v["stop_reasons"]
    if reasons is not None and not (isinstance(reasons, list) and len(reasons) <= 8
                                    and all(_printable(x, 32) for x in reasons)):
        return f"{tid}: stop_reasons {clip(reasons, 40)} are not reasons"
    why = v["end_reason"]
    if why is not None and not _printable(why, MAX_REASON_CHARS):
        return f"{tid}: end_reason {clip(why, 40)} is not a reason"
    t_life = v["t_life"]
    if status == "failure":
        if not (_fin(t_life) and 0 < t_life <= t_end + ts):
            return f"{tid}: t_life {clip(t_life, 40)} is not a life within t_end {t_end:g} s"
    elif t_life is not None:
        return f"{tid}: a t_life without a failure"
    t = PastTest(grade, float(t_set), status, None if t_life is None else float(t_life), k_b=k_b,
                 stop_reasons=None if reasons is None else tuple(reasons), n_slots=n_slots,
                 ts=float(ts), test_id=tid, station=station, t_end=float(t_end), end_reason=why)
    lf = t.life()
    if lf is None:
        return f"{tid}: {status} without a baseline or ended by a protection stop gives no life"
    if lf[0] == "censored":
        c = v["censored_s"]
        if not (_fin(c) and abs(c - lf[1]) <= 1e-6 * lf[1] + 1e-9) or lf[1] > t_end + ts:
            return f"{tid}: censored_s {clip(c, 40)} is not n_slots · ts within t_end"
        if status == "aborted" and t.stop_reasons != (STOPPED,):
            return f"{tid}: an aborted test that was not stopped gives no life"
    return t


def snapshot(station: str, tests: Iterable[PastTest], time_iso: str) -> dict[str, Any]:
    """The retained payload of a station's lives (its newest :data:`MAX_LIVES_PER_STATION`
    that fit :data:`MAX_LIVES_BYTES`, with room for the stream's ``seq``)."""
    recs = [r for r in (record_of(t) for t in tests) if r is not None][-MAX_LIVES_PER_STATION:]
    while True:
        doc = {"schema": SCHEMA_VERSION, "station": station, "time": time_iso, "lives": recs}
        size = len(json.dumps(doc, separators=(",", ":"), allow_nan=False).encode())
        if size <= MAX_LIVES_BYTES - 64 or not recs:
            return doc
        recs = recs[len(recs) // 10 + 1:]          # the oldest tenth goes


def parse_snapshot(payload: bytes, station: str) -> tuple[list[PastTest], list[str]]:
    """A station's retained message → its plausible lives and the reasons of the records refused;
    a message that is not one raises :class:`Refused`."""
    obj = read_bounded_json(payload, max_bytes=MAX_LIVES_BYTES, max_depth=4, pairs=_pairs)
    if not isinstance(obj, dict) or not isinstance(obj.get("lives"), list):
        raise Refused("not a lives message (an object with a `lives` list)")
    sv = obj.get("schema")
    if not isinstance(sv, int) or isinstance(sv, bool) or sv < 1:
        raise Refused(f"schema {clip(sv, 20)} is not a schema version")
    if any(k not in ("schema", "seq", "station", "time", "lives") for k in obj):
        raise Refused("unknown keys in a lives message")
    if obj.get("station") != station:
        raise Refused(f"station {clip(obj.get('station'), 40)} on the topic of {clip(station, 40)}")
    lives = obj["lives"]
    if len(lives) > MAX_LIVES_PER_STATION:
        raise Refused(f"{len(lives)} lives; at most {MAX_LIVES_PER_STATION}")
    good: list[PastTest] = []
    bad: list[str] = []
    for r in lives:
        t = parse_record(r, station)
        (bad.append if isinstance(t, str) else good.append)(t)   # type: ignore[arg-type]
    return good, bad


# ----------------------------------------------------------------------------- the store
class SiteLives:
    """The other stations' lives as this gateway last received them, persisted in ``path``
    (thread-safe: the intake's worker writes — gateway/outputs/mqtt/site_intake.py —, any thread
    reads :meth:`tests`)."""

    def __init__(self, path: str | None, own_station: str) -> None:
        self.path = path
        self.own = own_station
        self._by_station: dict[str, tuple[PastTest, ...]] = {}
        #: what the priors get: every station's lives but the contested ones, each test once
        self._view: tuple[PastTest, ...] = ()
        #: test ids that two or more stations claim with different lives → those stations (the
        #: test is refused from all of them; the same life claimed twice is one test)
        self.contested: dict[str, tuple[str, ...]] = {}
        self._told: set[str] = set()
        self._lock = threading.Lock()
        self.refused = RateLog(log)
        self.counters: dict[str, int] = {"snapshots": 0, "refused_messages": 0, "refused_records": 0,
                                         "contested_ids": 0}

    # -- any thread
    def tests(self) -> tuple[PastTest, ...]:
        """The site's lives as the priors take them (the contested ones left out)."""
        with self._lock:
            return self._view

    def names(self) -> tuple[str, ...]:
        """The stations whose lives are kept."""
        with self._lock:
            return tuple(self._by_station)

    def stations(self) -> int:
        with self._lock:
            return len(self._by_station)

    def load(self) -> int:
        """Read the local copy (bounded; every record checked again); the count of lives."""
        if self.path is None or not os.path.exists(self.path):
            return 0
        try:
            with open(self.path, "rb") as f:
                raw = f.read(MAX_STORE_BYTES + 1)
            obj = read_bounded_json(raw, max_bytes=MAX_STORE_BYTES, max_depth=5, pairs=bounded_pairs(
                MAX_SITE_STATIONS + 4, MAX_ID_CHARS, MAX_ID_CHARS))
            stations = obj.get("stations") if isinstance(obj, dict) else None
            if not isinstance(stations, dict):
                raise Refused("not a site lives file")
        except (OSError, Refused) as e:
            log.warning("%s: the site's lives in %s cannot be read (%s); they come again from the "
                        "broker", self.own, self.path, e)
            return 0
        n = 0
        for station, recs in stations.items():
            if not isinstance(recs, list):
                continue
            good = [t for t in (parse_record(r, station) for r in recs[:MAX_LIVES_PER_STATION])
                    if isinstance(t, PastTest)]
            if self._accept(station, good, view=False):
                n += len(good)
        with self._lock:
            self._update_view()
        return n

    def receive(self, topic: str, payload: bytes) -> bool:
        """A retained message of a station of the site (the intake's worker, never the pump
        thread: gateway/outputs/mqtt/site_intake.py): True when the store changed (the worker saves
        it, coalesced); the same snapshot again (a reconnect) changes nothing."""
        station = station_of(topic)
        if station is None or station == self.own:
            return False
        if not _printable(station, MAX_ID_CHARS):  # it is named in priors, the state, the sidecar
            self.counters["refused_messages"] += 1
            self.refused.warning("station", "%s: the lives of station %s refused: not a station id "
                                 "(1 to %d printable characters)", self.own, clip(station, 40), MAX_ID_CHARS)
            return False
        if not payload:                            # a retired station's topic cleared
            with self._lock:
                gone = self._by_station.pop(station, None) is not None
                if gone:
                    self._update_view()
            return gone
        try:
            good, bad = parse_snapshot(payload, station)
        except Refused as e:
            self.counters["refused_messages"] += 1
            self.refused.warning(("message", station), "%s: the lives of station %s refused: %s",
                                 self.own, clip(station, 40), e)
            return False
        if bad:
            self.counters["refused_records"] += len(bad)
            self.refused.warning(("record", station), "%s: %d record(s) of station %s refused, e.g. %s",
                                 self.own, len(bad), clip(station, 40), bad[0])
        self.counters["snapshots"] += 1
        return self._accept(station, good)     # False: refused by a bound, or nothing new

    def _accept(self, station: str, tests: list[PastTest], view: bool = True) -> bool:
        with self._lock:
            others = sum(len(v) for k, v in self._by_station.items() if k != station)
            if station not in self._by_station and len(self._by_station) >= MAX_SITE_STATIONS:
                why = f"more than {MAX_SITE_STATIONS} stations"
            elif others + len(tests) > MAX_SITE_LIVES:
                why = f"more than {MAX_SITE_LIVES} lives in all"
            else:
                changed = self._by_station.get(station) != tuple(tests)
                self._by_station[station] = tuple(tests)
                if changed and view:
                    self._update_view()
                return changed
        self.counters["refused_messages"] += 1
        self.refused.warning(("bound", station), "%s: the lives of station %s not kept: %s",
                             self.own, clip(station, 40), why)
        return False

    def _update_view(self) -> None:
        """The priors' view after a change (under the lock): a test id claimed by two stations
        with different lives is refused from both (once logged per id); the same life claimed
        by several stations is kept once."""
        first: dict[str, PastTest] = {}
        claims: dict[str, list[str]] = {}
        differ: set[str] = set()
        for station, ts in self._by_station.items():
            for t in ts:
                tid = t.test_id
                if tid is None:
                    continue
                seen = first.get(tid)
                if seen is None:
                    first[tid] = t
                    claims[tid] = [station]
                    continue
                if station not in claims[tid]:
                    claims[tid].append(station)
                if dataclasses.replace(seen, station=None) != dataclasses.replace(t, station=None):
                    differ.add(tid)
        self.contested = {tid: tuple(claims[tid]) for tid in differ}
        self._view = tuple(t for ts in self._by_station.values() for t in ts
                           if t.test_id not in differ)
        new = [tid for tid in differ if tid not in self._told]
        if not new:
            return
        if len(self._told) + len(new) > MAX_SITE_LIVES:
            self._told.clear()
        self._told.update(new)
        self.counters["contested_ids"] += len(new)
        eg = new[0]
        self.refused.warning("contested", "%s: %d test id(s) claimed by two or more stations with "
                             "different lives, refused from all of them (not in any prior), e.g. %s "
                             "claimed by %s", self.own, len(new), clip(eg, 60),
                             ", ".join(clip(x, 40) for x in self.contested[eg][:4]))

    def save(self) -> bool:
        """Write the store (atomically: :func:`gateway.plumbing.safeout.write_atomic`; the records folder
        made when missing); False when it cannot be written (kept in memory, one rate-limited
        line)."""
        if self.path is None:
            return True
        with self._lock:
            stations = list(self._by_station.items())
        # encoded station by station: a 4 MB store in one json.dumps would hold the GIL (and so
        # every thread of the process, the slot loop's too) for tens of ms
        parts = [json.dumps(s) + ":" + json.dumps([r for r in (record_of(t) for t in ts) if r is not None],
                                                  separators=(",", ":"), allow_nan=False)
                 for s, ts in stations]
        try:
            write_atomic(self.path, ('{"stations":{' + ",".join(parts) + "}}").encode())
        except OSError as e:
            self.refused.warning("save", "%s: the site's lives cannot be saved in %s (%s); kept in "
                                 "memory", self.own, self.path, e.strerror or e)
            return False
        return True

    def close(self) -> None:
        self.refused.close()


# ----------------------------------------------------------------------------- the answers
class LivesAnswers:
    """One station's answers to the site's lives requests (module docstring): at most one per
    ``interval_s`` (:data:`ANSWER_INTERVAL_S`); the requests within the interval after the last
    answer are answered once at its end (one timer at most), so a gateway joining then still gets
    the lives; any publication of the lives in between answers them instead. ``publish`` puts
    the station's lives message on its way (False: not read yet; it goes out when read); the counts
    go to ``counters`` (the MQTT pump's: ``lives_requests``, ``lives_answers``,
    ``lives_requests_deferred``). Thread-safe (the pump thread asks, a timer thread answers)."""

    def __init__(self, station: str, publish: Callable[[], bool], counters: MutableMapping[str, int],
                 interval_s: float | None = None) -> None:
        self.station = station
        self._own = station.encode()
        self._publish = publish
        self.counters = counters
        self.interval_s = ANSWER_INTERVAL_S if interval_s is None else interval_s
        self._gate = RateBound(60.0 / self.interval_s, burst=1)
        self._lock = threading.Lock()
        self._timer: threading.Timer | None = None
        self._closed = False
        self.flood = RateLog(log)

    def published(self) -> None:
        """The station's lives just went out (its start, a test, a connect, an answer): that
        answers every request so far (a deferred answer is dropped)."""
        with self._lock:
            self._cancel()

    def request(self, payload: bytes) -> None:
        """A lives request heard on the site's topic (pump thread); the station's own is ignored."""
        if payload == self._own:
            return
        with self._lock:
            if self._closed:
                return
            self.counters["lives_requests"] += 1
            wait = self._gate.take()
            if wait > 0:
                self.counters["lives_requests_deferred"] += 1
                self._arm(wait)
            else:
                self._cancel()
        if wait > 0:
            self.flood.info("deferred", "%s: lives requests of the site are answered at most once per "
                            "%.0f s (the next answer in %.1f s)", self.station, self.interval_s, wait)
            return
        self._answer()

    def close(self) -> None:
        with self._lock:
            self._closed = True
            self._cancel()
        self.flood.close()

    def _answer(self) -> None:
        if self._publish():
            with self._lock:
                self.counters["lives_answers"] += 1

    def _arm(self, wait: float) -> None:
        if self._timer is not None:
            return
        t = threading.Timer(wait + 0.01, self._fire)
        t.daemon = True
        try:
            t.start()
        except RuntimeError:        # no thread to be had: the next request tries again
            return
        self._timer = t

    def _cancel(self) -> None:
        t, self._timer = self._timer, None
        if t is not None:
            t.cancel()

    def _fire(self) -> None:
        with self._lock:
            if self._timer is not threading.current_thread():     # cancelled (or replaced)
                return
            self._timer = None
            if self._closed:
                return
            wait = self._gate.take()
            if wait > 0:
                self._arm(wait)
                return
        self._answer()
