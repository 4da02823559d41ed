"""The one restart back-off (pure: no clock, no I/O): how long to wait before the next start of
something that failed, growing while it fails in a row.

Used for a station's restart in this process (``gateway/station/fleet.py: StationRunner``), a
fleet worker's restart and a worker start that could not happen (``gateway/supervisor/
supervisor.py``). The wait is ``base_s · 2^(n-1)`` after the n-th failure in a row, capped at
``max_s``; a run of at least ``stable_s`` before a failure starts a new row.
"""
from __future__ import annotations

import math

__all__ = ["Backoff"]


class Backoff:
    """The failures in a row of one thing and the wait they call for."""
    __slots__ = ("base_s", "max_s", "stable_s", "in_row")

    def __init__(self, base_s: float, max_s: float, stable_s: float = math.inf) -> None:
        if not 0 <= base_s <= max_s:
            raise ValueError(f"a back-off needs 0 <= base_s <= max_s (got {base_s}, {max_s})")
        self.base_s = float(base_s)
        self.max_s = float(max_s)
        self.stable_s = float(stable_s)
        #: failures in a row (since the last run of ``stable_s`` or :meth:`reset`)
        self.in_row = 0

    def failed(self, ran_s: float = 0.0) -> float:
        """One more failure, after a run of ``ran_s`` s: the wait before the next start, s."""
        if ran_s >= self.stable_s:
            self.in_row = 0
        self.in_row += 1
        return self.wait_s(self.in_row)

    def wait_s(self, n: int) -> float:
        """The wait after the ``n``-th failure in a row (n ≥ 1)."""
        return min(self.max_s, self.base_s * 2.0 ** (n - 1))

    def reset(self) -> None:
        """A start that worked: the next failure begins a new row."""
        self.in_row = 0
