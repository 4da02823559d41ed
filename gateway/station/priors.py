"""The life prior of a station's next test (METHOD.md §7a), resolved at each test start.

In this order: a fixed ``prior_mean``/``prior_sd`` in the station's ``method:`` section (source
``method``); else its ``forecast.priors`` entry for the test's grade and T_set (``config``); else the
recorded history — every completed test under the records root (``recorder.dir``: in a fleet,
every station of the box) with the same grade and T_set that ended in ``failure``, at least 3
(``history:N``); else none.

The history is read off the slot loop (a worker thread of the loop's default executor) when the
station opens, again when a test starts and after each test ends; the start uses the last
history read (a read still running is not waited for: the start keeps the slot loop's time).
Bounded by :mod:`gateway.history` (the newest 20,000 result files, 1 MiB each); a damaged result
is skipped there with one log line.
"""
from __future__ import annotations

import asyncio
import logging
from collections.abc import Iterable
from typing import Any

from ..history import past_test, read_history
from ..method.prior import NO_PRIOR, PastTest, Prior, PriorEntry, resolve_prior

__all__ = ["PriorBook", "SOURCE_METHOD"]

log = logging.getLogger("hookwatch.station")

#: the prior fixed in the station's `method:` section
SOURCE_METHOD = "method"


class PriorBook:
    """The §7a sources of one station: its configuration and its records root's history."""

    def __init__(self, station_id: str, records_root: str, entries: Iterable[PriorEntry] = ()) -> None:
        self.station_id = station_id
        self.records_root = records_root
        self.entries: tuple[PriorEntry, ...] = tuple(entries)
        #: the last history read (None: none finished yet)
        self.history: list[PastTest] | None = None
        self._reading: asyncio.Future[list[PastTest]] | None = None
        #: results of this station's tests ended since the last read began (kept until a read
        #: that began after them has finished)
        self._recent: list[PastTest] = []

    def refresh(self) -> None:
        """Read the history again, off the loop (nothing when a read is running or no loop runs)."""
        if self._reading is not None and not self._reading.done():
            return
        try:
            loop = asyncio.get_running_loop()
        except RuntimeError:
            return
        recent = list(self._recent)
        fut = loop.run_in_executor(None, read_history, self.records_root)
        self._reading = fut

        def done(f: asyncio.Future[list[PastTest]]) -> None:
            if f.cancelled():
                return
            exc = f.exception()
            if exc is not None:
                log.warning("%s: the life history under %s could not be read (%s)", self.station_id,
                            self.records_root, exc)
                return
            self.history = f.result()
            self._recent = [t for t in self._recent if t not in recent]
        fut.add_done_callback(done)

    def add_result(self, result: dict[str, Any]) -> None:
        """A test of this station ended: its result counts at once (before the next read)."""
        t = past_test(result)
        if t is not None:
            self._recent.append(t)

    def known(self) -> list[PastTest]:
        return list(self.history or []) + self._recent

    def resolve(self, grade: str | None, t_set: float, method_values: dict[str, Any]) -> Prior:
        """§7a for a test of ``grade`` at ``t_set``; the source as the station publishes it."""
        fixed = (method_values.get("prior_mean"), method_values.get("prior_sd"))
        if fixed[0] is not None and fixed[1] is not None:
            return Prior(float(fixed[0]), float(fixed[1]), SOURCE_METHOD, None)
        if self.history is None and grade is not None and not any(
                e.grade == grade for e in self.entries):
            log.info("%s: the life history is still being read; this test may start without a "
                     "prior from it", self.station_id)
        pr = resolve_prior(self.entries, self.known(), grade, t_set)
        if pr.source == "history":
            return Prior(pr.mean, pr.sd, f"history:{pr.n}", pr.n)
        return pr if pr.mean is not None else NO_PRIOR
