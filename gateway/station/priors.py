"""The life prior of a station's next test (METHOD.md §7a), resolved at each test start.

In this order: a fixed ``prior_mean``/``prior_sd`` in the station's ``method:`` section (published
source ``method``); else its ``forecast.priors`` entry for the test's grade and T_set (``config``);
else the recorded history — every completed test under the records root (``recorder.dir``: in a
fleet, every station of the box) and every one the site's other stations shared (MQTT,
gateway/outputs/mqtt/sitelives.py), each test once by test id, with the same grade and T_set: its
wear-out failures (at least 3), its right-censored lives (a test that found its baseline and ended
on purpose or at t_end) and its early failures (§7a v3: censored at their life), the
maximum-likelihood normal of them (``history:N``, N wear-out failures); else none. The sidecar
records the §7a source (``config`` or ``history``) with ``prior_n``, ``prior_n_censored`` and
``prior_n_early``; the state carries the same counts for the planner.

The history is read off the slot loop (a worker thread of the loop's default executor) when the
station opens, again when a test starts and after each test ends; the same worker fits the prior of
every (grade, T_set) group it read (a fit of 20,000 lives takes ≈ 0.1 s: never on the slot loop).
The start uses the last history read (a read still running is not waited for: the start keeps the
slot loop's time) with the results of this station's tests ended since: a group's fit is looked up
by its lives; a group the worker has not fitted (a test just ended) is fitted at the start when it
holds at most :data:`SYNC_FIT_MAX` lives (≈ 2 ms), else the last read's fit of the group is used
(one log line); a start while the site's lives are being fitted again scans a history of at most
:data:`SCAN_MAX` tests, else uses the last fit. Bounded by :mod:`gateway.offline.history` (the newest
20,000 result files, 1 MiB each); a damaged result is skipped there with one log line.
"""
from __future__ import annotations

import asyncio
import logging
from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any

from ..core.method.prior import (
    NO_PRIOR,
    OBSERVED,
    SOURCE_CONFIG,
    SOURCE_HISTORY,
    PastTest,
    Prior,
    PriorEntry,
    group_tests,
    kind_in_history,
    prior_of_lives,
    resolve_prior,
    same_t_set,
)
from ..offline.history import past_test, read_history
from ..plumbing.ratelog import safe

__all__ = ["PriorBook", "SOURCE_METHOD", "life_kind"]

log = logging.getLogger("hookwatch.station")

#: the prior fixed in the station's `method:` section (as the state publishes its source)
SOURCE_METHOD = "method"
#: a group of at most this many lives that the reading worker has not fitted is fitted at the start
SYNC_FIT_MAX = 400

#: a history of at most this many tests may be scanned at a start (≈ 3 ms); beyond it a start
#: that finds the worker's fit out of date uses it all the same (one log line)
SCAN_MAX = 5000
#: (grade, T_set) groups the reading worker fits, at most
MAX_GROUPS = 256
#: other stations a history prior names in its words (the console, the state), at most
NAMED_IN_WORDS = 3
#: stations a history prior names in the sidecar (``prior_station_ids``), at most
NAMED_IN_SIDECAR = 16
#: a group's lives, as the key of its fit
FitKey = tuple[tuple[float, ...], tuple[float, ...]]


def _key(xs: list[float], cs: list[float]) -> FitKey:
    return tuple(sorted(xs)), tuple(sorted(cs))


@dataclass(frozen=True)
class Fitted:
    """What the reading worker found: the fits by their lives, and per (grade, T_set) of the tests
    read the prior as a test of that grade and T_set gets it (with its origin) and the test ids
    it holds — a start then only looks it up (no scan of 40,000 tests on the slot loop)."""
    by_lives: dict[FitKey, Prior]
    by_group: dict[tuple[str, float], tuple[Prior, frozenset[str], list[tuple[PastTest, str, float]]]]


def fit_groups(history: list[PastTest], station_id: str = "") -> Fitted:
    """The §7a prior of every (grade, T_set) group of ``history`` (each group as a test of that
    grade at that T_set sees it). Run by the reading worker, off the loop."""
    out = Fitted({}, {})
    for t in history:
        if t.grade is None or t.t_set is None or (t.grade, t.t_set) in out.by_group:
            continue
        if len(out.by_group) >= MAX_GROUPS:
            break
        group = group_tests(history, t.grade, t.t_set)
        xs = [v for _, k, v in group if k == OBSERVED]
        cs = [v for _, k, v in group if k != OBSERVED]
        k = _key(xs, cs)
        if k not in out.by_lives:
            out.by_lives[k] = prior_of_lives(xs, cs)
        ids = frozenset(x.test_id for x, _, _ in group if x.test_id is not None)
        out.by_group[(t.grade, t.t_set)] = (_labelled(out.by_lives[k], station_id, group), ids, group)
    return out


def _labelled(pr: Prior, station_id: str, group: list[tuple[PastTest, str, float]]) -> Prior:
    """A history prior with where it came from (NO_PRIOR for none)."""
    if pr.source != SOURCE_HISTORY:
        return NO_PRIOR
    k, words, names = origin(station_id, [t for t, _, _ in group])
    label = f"history:{pr.n}" if k == 1 else f"history:{pr.n} ({words})"
    return Prior(pr.mean, pr.sd, pr.source, pr.n, pr.n_censored, pr.n_early, label=label,
                 n_stations=k, origin=words, station_ids=names)


def life_kind(result: dict[str, Any], history: list[PastTest]) -> str | None:
    """What a test's result is in this §7a history (v3; the result with it, once by its test id):
    ``wear_out`` or ``early`` (a failure), ``censored``, or None (no life for the history). A scan
    of the history: off the slot loop."""
    t = past_test(result)
    return None if t is None else kind_in_history(t, history)


def _read_and_fit(root: str, site: tuple[PastTest, ...] = (), station_id: str = "",
                  history: list[PastTest] | None = None) -> tuple[list[PastTest], Fitted]:
    """The records root's history (``history``: the last read, not read again), and the fits of
    its groups with the site's lives."""
    hist = read_history(root) if history is None else history
    return hist, fit_groups(hist + list(site), station_id)


def origin(station_id: str, tests: list[PastTest]) -> tuple[int, str, tuple[str, ...]]:
    """How many stations a history prior's tests came from, in words — ``this station: N tests``
    or ``the site: N tests from K stations (M of this station; a 30, b 12)``, the other stations
    named with their tests, most first, at most :data:`NAMED_IN_WORDS` (``and J more``) — and
    the stations by name (this station first, then by tests, at most :data:`NAMED_IN_SIDECAR`:
    the sidecar's ``prior_station_ids``)."""
    count: dict[str, int] = {}
    for t in tests:
        name = t.station or station_id
        count[name] = count.get(name, 0) + 1
    here = count.pop(station_id, 0)
    others = sorted(count.items(), key=lambda kv: (-kv[1], kv[0]))
    names = ((station_id,) if here else ()) + tuple(n for n, _ in others)
    if not others:
        return 1, f"this station: {len(tests)} tests", names[:NAMED_IN_SIDECAR]
    k = len(others) + (1 if here else 0)
    named = ", ".join(f"{safe(n)} {c}" for n, c in others[:NAMED_IN_WORDS])
    more = len(others) - NAMED_IN_WORDS
    if more > 0:
        named += f" and {more} more"
    return k, (f"the site: {len(tests)} tests from {k} station{'' if k == 1 else 's'} "
               f"({here} of this station; {named})"), names[:NAMED_IN_SIDECAR]


class PriorBook:
    """The §7a sources of one station: its configuration and its records root's history."""

    def __init__(self, station_id: str, records_root: str, entries: Iterable[PriorEntry] = ()) -> None:
        self.station_id = station_id
        self.records_root = records_root
        self.entries: tuple[PriorEntry, ...] = tuple(entries)
        #: the last history read (None: none finished yet)
        self.history: list[PastTest] | None = None
        #: the fits of the last read's groups (by their lives, and by grade and T_set)
        self.fitted = Fitted({}, {})
        self._fitted_site: tuple[PastTest, ...] = ()
        self._reading: asyncio.Future[tuple[list[PastTest], Fitted]] | None = None
        #: results of this station's tests ended since the last read began (kept until a read
        #: that began after them has finished)
        self._recent: list[PastTest] = []
        #: the other stations' lives that the site shared (gateway/outputs/mqtt/sitelives.py)
        self.site: tuple[PastTest, ...] = ()
        self._again = False
        self._again_read = False

    def refresh(self, read: bool = True) -> None:
        """Read the history again and fit its groups, off the loop (nothing when a read is running
        or no loop runs). ``read=False``: only fit again, with the last read's history and the
        site's lives as they are now (the site's lives changed; the records folder did not)."""
        if self._reading is not None and not self._reading.done():
            self._again = True              # read (or fit) again when this one is done
            self._again_read = self._again_read or read
            return
        try:
            loop = asyncio.get_running_loop()
        except RuntimeError:
            return
        last = None if read else self.history
        recent = list(self._recent) if last is None else []
        self._again = self._again_read = False
        site = self.site
        fut = loop.run_in_executor(None, _read_and_fit, self.records_root, site, self.station_id, last)
        self._reading = fut

        def done(f: asyncio.Future[tuple[list[PastTest], Fitted]]) -> None:
            if f.cancelled():
                return
            exc = f.exception()
            if exc is not None:
                log.warning("%s: the life history under %s could not be read (%s)", self.station_id,
                            self.records_root, exc)
                return
            self.history, self.fitted = f.result()
            self._fitted_site = site
            if self._again:
                self.refresh(self._again_read)
            self._recent = [t for t in self._recent if t not in recent]
        fut.add_done_callback(done)

    def add_result(self, result: dict[str, Any]) -> None:
        """A test of this station ended: its result counts at once (before the next read)."""
        t = past_test(result)
        if t is not None:
            self._recent.append(t)

    def set_site(self, tests: tuple[PastTest, ...]) -> None:
        """The site's lives changed (received from the broker): kept, and fitted off the loop with
        the last history read (the records folder is not read again for them)."""
        self.site = tuple(tests)
        self.refresh(read=False)

    def known(self) -> list[PastTest]:
        return list(self.history or []) + self._recent + list(self.site)

    def resolve(self, grade: str | None, t_set: float, method_values: dict[str, Any]) -> Prior:
        """§7a for a test of ``grade`` at ``t_set``, with the §7a source (``config``,
        ``history``) and the source as the state publishes it (``label``: ``method``, ``config``,
        ``history:N``)."""
        fixed = (method_values.get("prior_mean"), method_values.get("prior_sd"))
        if fixed[0] is not None and fixed[1] is not None:
            return Prior(float(fixed[0]), float(fixed[1]), SOURCE_CONFIG, None, label=SOURCE_METHOD)
        if self.history is None and grade is not None and not any(
                e.grade == grade for e in self.entries):
            log.info("%s: the life history is still being read; this test may start without a "
                     "prior from it", self.station_id)
        pr = resolve_prior(self.entries, (), grade, t_set)
        if pr.source == SOURCE_CONFIG or grade is None:
            return pr
        quick = self._looked_up(grade, t_set)
        if quick is not None:
            return quick
        group = group_tests(self.known(), grade, t_set)
        xs = [v for _, k, v in group if k == OBSERVED]
        cs = [v for _, k, v in group if k != OBSERVED]
        return _labelled(self.fitted.by_lives.get(_key(xs, cs)) or self._fit(grade, t_set, xs, cs),
                         self.station_id, group)

    def _looked_up(self, grade: str, t_set: float) -> Prior | None:
        """The worker's group of this grade and T_set (None: it has none, the start computes):
        its prior when nothing changed since it read (the same site's lives, no test of the group
        ended since); with the tests ended since, fitted at the start when the group is small, else
        the worker's fit (one log line; the next read fits them)."""
        hit = self.fitted.by_group.get((grade, t_set))
        if hit is None:
            return None
        pr, ids, group = hit
        if self._fitted_site is not self.site:
            # the site's lives changed since the worker's fit (it is fitting them now): a small
            # history is scanned at the start, a large one starts with the last fit
            if len(self.history or ()) + len(self.site) <= SCAN_MAX:
                return None
            log.info("%s: the site's lives changed and are being fitted off the loop; this test "
                     "starts with the last fit", self.station_id)
            return pr
        extra = []
        for t in self._recent:
            lf = t.life()
            if (lf is not None and t.grade == grade and t.t_set is not None and same_t_set(t.t_set, t_set)
                    and (t.test_id is None or t.test_id not in ids)):
                extra.append((t, lf[0], lf[1]))
        if not extra:
            return pr
        if len(group) + len(extra) > SYNC_FIT_MAX:
            log.info("%s: the life history of %s at %g N (%d lives) is being fitted again off the "
                     "loop; this test starts with the last fit", self.station_id, grade, t_set,
                     len(group) + len(extra))
            return pr
        both = group + extra
        xs = [v for _, k, v in both if k == OBSERVED]
        cs = [v for _, k, v in both if k != OBSERVED]
        return _labelled(prior_of_lives(xs, cs), self.station_id, both)

    def _fit(self, grade: str, t_set: float, xs: list[float], cs: list[float]) -> Prior:
        """A group the reading worker did not fit: at once when small, else the worker's fit of
        the nearest group of the grade (one log line)."""
        if len(xs) + len(cs) <= SYNC_FIT_MAX:
            return prior_of_lives(xs, cs)
        near = next((v[0] for (g, ts), v in self.fitted.by_group.items()
                     if g == grade and same_t_set(ts, t_set)), NO_PRIOR)
        log.info("%s: the life history of %s at %g N (%d lives) is being fitted again off the loop; "
                 "this test starts with the last fit", self.station_id, grade, t_set, len(xs) + len(cs))
        return near
