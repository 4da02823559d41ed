"""The site's lives off the station's threads (issue 34 item 1): lives cost what they are worth.

A station of the site may publish a new lives snapshot as often as it likes (a careless or hostile
peer: 400 changing snapshots in 0.3 s). What arrives costs the station's own threads nothing but
an append: the MQTT pump thread (paho's) hands each snapshot, unread, to a bounded
:class:`gateway.plumbing.threadloop.Mailbox` keyed by its topic — the newest snapshot of a station replaces
the one still waiting (the older is dropped and counted: ``lives_dropped`` in the MQTT counters),
at most :data:`INTAKE_MAX` stations' snapshots wait (beyond: the oldest dropped, counted too).

One worker thread per station (``site-lives``) is the store's one writer (:class:`SiteLives`):

- it reads the local copy first (``site_lives.json``), then takes one snapshot at a time, checks
  and merges it; it is *paced*: a station's snapshots are checked at most once per
  :data:`STATION_PERIOD_S` (its newest then), and after a snapshot that took *d* seconds the
  worker rests ``d · (1/BUSY_SHARE − 1)``, so the lives use at most :data:`BUSY_SHARE` of one
  core however fast they come (the waiting ones are meanwhile replaced by their stations' newer
  ones) — a station's lives change once per test, a snapshot every 5 s is already more than
  they are worth;
- a station's snapshot is checked once its station has been quiet for :data:`SETTLE_S` (no newer
  one came), or :data:`MAX_SETTLE_S` after the first of them came if it keeps publishing: a burst
  comes together, and the check does not run while the burst is still being read;
- it saves the store at most once per :data:`SAVE_INTERVAL_S` (the first change after a quiet
  interval :data:`SAVE_LEAD_S` later, the changes within an interval together at its end, and at
  the close),
  atomically (:func:`gateway.plumbing.safeout.write_atomic`: exclusive, link-refusing temporary file,
  fsync, rename; the records folder made when missing, so a station that never ran a test keeps
  the site's lives on disk from the first minute);
- it gives the station the site's lives (the hand-over onto the station's loop, which re-fits the
  §7a priors off the loop) at most once per :data:`GIVE_INTERVAL_S`, in the same way
  (:data:`GIVE_LEAD_S`), so that the check, the re-fit and the save never run at one moment;
- it logs what changed in one rate-limited line (:class:`gateway.plumbing.ratelog.RateLog`), never a line
  per snapshot.

So commands, slots and state never wait behind lives: nothing of a snapshot is read, merged, saved
or logged on the pump thread or the slot loop.
"""
from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable, MutableMapping

from ...core.method.prior import PastTest
from ...plumbing.ratelog import RateLog
from ...plumbing.threadloop import Mailbox
from .sitelives import SiteLives, station_of

log = logging.getLogger("hookwatch.site")

#: stations whose newest snapshot may wait to be read (one each)
INTAKE_MAX = 64
#: the store is saved at most once per this many seconds
SAVE_INTERVAL_S = 5.0
#: the station is given the site's lives at most once per this many seconds
GIVE_INTERVAL_S = 2.0
#: the share of one core the lives' checking may take (the worker rests in between)
BUSY_SHARE = 0.1
#: one station's snapshots are checked at most once per this many seconds (its newest then)
STATION_PERIOD_S = 5.0
#: a snapshot is checked this long after it (or an older one of its station still waiting) came:
#: a burst comes together first, and the check does not run while the burst is still being read
SETTLE_S = 1.0
#: a station that keeps publishing has its newest checked this long after the first came
MAX_SETTLE_S = 5.0
#: the station is given changed lives, and the store saved, this long after the change at the
#: earliest (the three never at the same moment as the check)
GIVE_LEAD_S = 0.5
SAVE_LEAD_S = 1.5
#: a rest is at most this long (s)
MAX_REST_S = 2.0

Give = Callable[[tuple[PastTest, ...]], None]


class _Edge:
    """At most one action per ``interval_s``: a change after a quiet interval acts ``lead_s``
    later (so that what a burst brings comes together, and the actions of one change do not all
    run at the same moment), the changes within an interval together at its end (the worker's
    clock, never the loop's)."""

    def __init__(self, interval_s: float, lead_s: float = 0.0) -> None:
        self.interval_s = interval_s
        self.lead_s = lead_s
        self.pending = False
        self._since = 0.0
        self._last = float("-inf")

    def set(self, now: float, lead: bool = True) -> None:
        if not self.pending:
            self.pending = True
            self._since = now if lead else now - self.lead_s

    def due_in(self, now: float) -> float | None:
        """None: nothing pending; else seconds until it is due (≤ 0: now)."""
        if not self.pending:
            return None
        return max(self._last + self.interval_s, self._since + self.lead_s) - now

    def done(self, now: float) -> None:
        self.pending = False
        self._last = now


class LivesIntake:
    """The site's lives of one station, taken off its threads (module docstring). ``give`` hands
    the site's lives to the station (any thread; it must not block); ``counters`` are the MQTT
    pump's (``lives_dropped``, ``lives_checked``, ``lives_saves``, ``lives_save_errors``,
    ``contested_ids``)."""

    def __init__(self, site: SiteLives, give: Give, counters: MutableMapping[str, int],
                 save_interval_s: float = SAVE_INTERVAL_S, give_interval_s: float = GIVE_INTERVAL_S,
                 busy_share: float = BUSY_SHARE, station_period_s: float = STATION_PERIOD_S,
                 settle_s: float = SETTLE_S) -> None:
        self.site = site
        self.give = give
        self.counters = counters
        self.busy_share = min(1.0, max(0.01, busy_share))
        self.station_period_s = station_period_s
        #: when each station's snapshot was last checked (by topic; bounded by the site's stations)
        self._checked_at: dict[str, float] = {}
        self.box: Mailbox[tuple[str, bytes]] = Mailbox(INTAKE_MAX, key=lambda it: it[0])
        self._save = _Edge(save_interval_s, SAVE_LEAD_S)
        self._give = _Edge(give_interval_s, GIVE_LEAD_S)
        #: when the oldest waiting snapshot of each station came (by topic; the pump thread
        #: sets it, the worker clears it once it checked the station)
        self._arrived: dict[str, float] = {}
        #: when each station's newest waiting snapshot came (the same bounds)
        self._latest: dict[str, float] = {}
        self.settle_s = settle_s
        self._closed = threading.Event()
        self._thread: threading.Thread | None = None
        self.changes = RateLog(log)
        self.loaded = threading.Event()

    # -- the pump thread
    def put(self, topic: str, payload: bytes) -> None:
        """A station's retained lives (the pump thread): queued unread, O(1)."""
        station = station_of(topic)
        if station is None or station == self.site.own or self._closed.is_set():
            return
        before = self.box.dropped
        now = time.monotonic()
        if topic not in self._arrived:
            if len(self._arrived) >= 4 * INTAKE_MAX:
                self._arrived.clear()           # bounded (dropped ones' times): they settle again
                self._latest.clear()
            self._arrived[topic] = now
        self._latest[topic] = now
        self.box.put_nowait((topic, payload))
        if self.box.dropped != before:
            self.counters["lives_dropped"] += self.box.dropped - before

    # -- the owner
    def start(self) -> None:
        if self._thread is not None:
            return
        self._thread = threading.Thread(target=self._run, name=f"site-lives-{self.site.own}"[:60],
                                        daemon=True)
        self._thread.start()

    def close(self, timeout: float = 10.0) -> None:
        """Stop the worker; a change not yet saved is saved now."""
        self._closed.set()
        self.box.wake()
        th = self._thread
        if th is not None and th is not threading.current_thread():
            th.join(timeout)
        if th is None or not th.is_alive():
            self._flush_save(time.monotonic(), force=True)
        self.changes.close()

    # -- the worker
    def _run(self) -> None:
        try:
            n = self.site.load()
            if n:
                log.info("%s: the site's lives: %d tests of %d stations from %s", self.site.own, n,
                         self.site.stations(), self.site.path)
                self._give.set(time.monotonic(), lead=False)   # at once: the start
        except Exception:   # noqa: BLE001 - the store's load never ends the worker
            log.exception("%s: the site's lives could not be read", self.site.own)
        self.loaded.set()
        while not self._closed.is_set():
            now = time.monotonic()
            self._due(now)
            waits = [w for w in (self._save.due_in(now), self._give.due_in(now)) if w is not None]
            self.box.wait(max(0.0, min(waits)) + 0.01 if waits else None)
            if self._closed.is_set():
                break
            now = time.monotonic()
            got = self.box.take(1, ready=self._ready_at(now))
            if not got:             # snapshots wait to settle or for their station's period
                if len(self.box):
                    self._closed.wait(0.1)
                continue
            topic, payload = got[0]
            self._arrived.pop(topic, None)
            self._latest.pop(topic, None)
            if topic not in self._checked_at and len(self._checked_at) >= 4 * INTAKE_MAX:
                self._checked_at.clear()            # bounded: the periods start again
            self._checked_at[topic] = now
            self._check(topic, payload)

    def _ready_at(self, now: float) -> Callable[[tuple[str, bytes]], bool]:
        """Whether a waiting snapshot's station was last checked long enough ago."""
        def ready(item: tuple[str, bytes]) -> bool:
            return (now - self._checked_at.get(item[0], -1e18) >= self.station_period_s
                    and (now - self._latest.get(item[0], -1e18) >= self.settle_s
                         or now - self._arrived.get(item[0], -1e18) >= max(self.settle_s, MAX_SETTLE_S)))
        return ready

    def _check(self, topic: str, payload: bytes) -> None:
        t0 = time.monotonic()
        try:
            changed = self.site.receive(topic, payload)
        except Exception:   # noqa: BLE001 - a snapshot never ends the worker
            self.changes.log("error", logging.ERROR, "%s: a lives snapshot could not be checked",
                             self.site.own, exc_info=True)
            changed = False
        self.counters["lives_checked"] += 1
        self.counters["contested_ids"] = self.site.counters["contested_ids"]
        if changed:
            now = time.monotonic()
            self._save.set(now)
            self._give.set(now)
            self.changes.info("changed", "%s: the site's lives: %d tests of %d other station(s)",
                              self.site.own, len(self.site.tests()), self.site.stations())
        d = time.monotonic() - t0
        rest = min(MAX_REST_S, d * (1.0 / self.busy_share - 1.0))
        if rest > 0:
            self._closed.wait(rest)

    def _due(self, now: float) -> None:
        w = self._give.due_in(now)
        if w is not None and w <= 0:
            self._give.done(now)
            try:
                self.give(self.site.tests())
            except Exception:   # noqa: BLE001 - the station gone: the lives wait for the next
                log.debug("%s: the site's lives not given to the station", self.site.own, exc_info=True)
        self._flush_save(now)

    def _flush_save(self, now: float, force: bool = False) -> None:
        w = self._save.due_in(now)
        if w is None or (w > 0 and not force):
            return
        self._save.done(now)
        if self.site.save():
            self.counters["lives_saves"] += 1
        else:
            self.counters["lives_save_errors"] += 1
