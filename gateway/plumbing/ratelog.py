"""Client text made safe to echo, and refusals counted instead of logged one by one.

Every door (MQTT, the PLC's Modbus TCP, the web console, Sparkplug, the CLI) quotes what a client
sent in replies, events, metrics and log lines. Two helpers do that in one place:

- :func:`clip` — ``repr`` of the value cut to about :data:`ECHO_CHARS` characters, with the full
  length named: one line, quoted, control characters and newlines escaped (``'a\\nb'``), never
  more than a few dozen characters whatever came in;
- :func:`safe` — the same without the quotes, for a name in a sentence (``command 'x…'``).

:class:`RateLog` logs a refusal once per *kind* per window (:data:`WINDOW_S`, 60 s by default) with
the count: the first refusal of a kind in a window is logged at once (``×1``), the rest of the
window is counted and logged as one line when the window ends (``×2999 in the last 60 s``), so a
flood of 3,000 refused writes is two lines, not 3,000. :class:`RefusalWindow` is the same
bookkeeping without the logger and without a clock of its own (pure: the caller passes the time);
the station's bounded ``command_rejected`` events use it (gateway/station/command_desk.py).
:class:`RateBound` is the one token bucket of requests per key (the console's stream and file
reads, every door's commands at the station's command desk).

This module imports nothing of the project: every door may use it.
"""
from __future__ import annotations

import logging
import os
import threading
import time
from collections.abc import Callable, Hashable
from dataclasses import dataclass, field
from typing import Any

#: longest piece of client input quoted anywhere (reasons, events, log lines)
ECHO_CHARS = 40
#: refusals of one kind are logged (and reported as events) at most once per this many seconds,
#: with the count; ``HW_REFUSAL_WINDOW_S`` in the environment changes it (docs/limits.md)
WINDOW_S = float(os.environ.get("HW_REFUSAL_WINDOW_S", 60.0))
#: kinds tracked at once; more fold into one ``other`` kind (kinds are made by the code, this only
#: bounds a kind that carries a client's address)
MAX_KINDS = 256


def clip(value: Any, n: int = ECHO_CHARS) -> str:
    """``repr`` of client input, cut to about ``n`` characters (with the full length named).
    One line: ``repr`` escapes newlines and control characters. A long string is cut before its
    ``repr`` is made (a megabyte is never copied to be shortened)."""
    if isinstance(value, (str, bytes, bytearray)):
        if len(value) <= n:
            r = repr(value if not isinstance(value, bytearray) else bytes(value))
            if len(r) <= n + 2:
                return r
        head = value[:n] if not isinstance(value, bytearray) else bytes(value[:n])
        return f"{repr(head)[:n]}… ({len(value)} chars)"
    try:
        r = repr(value)
    except Exception:   # noqa: BLE001 - an object whose repr fails: its type only
        r = f"<{type(value).__name__}>"
    if len(r) <= n:
        return r
    return f"{r[:n]}… ({len(r)} chars)"


def safe(value: Any, n: int = ECHO_CHARS) -> str:
    """Client text for a sentence: printable, one line, at most about ``n`` characters; a string
    that is already all printable ASCII and short is shown as it is, anything else as :func:`clip`."""
    if isinstance(value, str) and len(value) <= n and value.isascii() and value.isprintable():
        return value
    return clip(value, n)


@dataclass
class _Kind:
    start: float
    count: int = 0              # refusals after the first of the window, not yet reported
    last: tuple[Any, ...] = field(default_factory=tuple)


class RefusalWindow:
    """Per kind: the first refusal of a window is reported at once, the rest counted; the count is
    reported when the window ends. Pure: every call takes the time ``now``."""

    def __init__(self, window_s: float | None = None, max_kinds: int = MAX_KINDS):
        self.window_s = float(WINDOW_S if window_s is None else window_s)
        self.max_kinds = int(max_kinds)
        self._kinds: dict[Hashable, _Kind] = {}

    def add(self, kind: Hashable, now: float, *detail: Any) -> int:
        """One refusal of ``kind`` (``detail``: what to say when its count is reported). Returns 1
        when it is to be reported now (the first of a window), 0 when it is counted."""
        k = self._kinds.get(kind)
        if k is None and len(self._kinds) >= self.max_kinds:
            kind = "other"
            k = self._kinds.get(kind)
        if k is not None and now - k.start < self.window_s:
            k.count += 1
            k.last = detail
            return 0
        self._kinds[kind] = _Kind(now)
        return 1

    def due(self, now: float) -> list[tuple[Hashable, int, tuple[Any, ...]]]:
        """The kinds whose window has ended: ``(kind, count, detail of the last)`` for those with
        refusals not yet reported (forgotten after)."""
        out = []
        for kind, k in list(self._kinds.items()):
            if now - k.start >= self.window_s:
                if k.count:
                    out.append((kind, k.count, k.last))
                del self._kinds[kind]
        return out

    def next_due(self) -> float | None:
        """When the next window with counted refusals ends (None: none counted)."""
        ts = [k.start + self.window_s for k in self._kinds.values() if k.count]
        return min(ts) if ts else None


class RateLog:
    """A logger for refusals: once per kind per window, with a count (``×N``).

    ``log(kind, level, msg, *args)`` logs ``msg % args`` at once when it is the first of its kind in
    the window, else counts it; a timer thread logs the count of a window when it ends (the last
    message of the kind with ``×N in the last 60 s``). ``msg % args`` is only formatted when
    logged: give client text through :func:`clip`/:func:`safe`."""

    def __init__(self, logger: logging.Logger, window_s: float | None = None,
                 clock: Callable[[], float] = time.monotonic):
        self.logger = logger
        self.clock = clock
        self._w = RefusalWindow(window_s)
        self._lock = threading.Lock()
        self._timer: threading.Timer | None = None
        self.logged = 0             # lines written (tests, metrics)

    @property
    def window_s(self) -> float:
        return self._w.window_s

    def log(self, kind: Hashable, level: int, msg: str, *args: Any, exc_info: bool = False) -> None:
        """``exc_info``: the traceback of the exception being handled goes with the first line of
        the window only (the count line has none)."""
        with self._lock:
            now = self.clock()
            due = self._w.due(now)
            first = self._w.add(kind, now, level, msg, args)
            if not first:
                self._arm(now)
        self._emit(due)
        if first:
            self.logged += 1
            self.logger.log(level, msg + " (×1)", *args, exc_info=exc_info)

    def info(self, kind: Hashable, msg: str, *args: Any) -> None:
        self.log(kind, logging.INFO, msg, *args)

    def warning(self, kind: Hashable, msg: str, *args: Any) -> None:
        self.log(kind, logging.WARNING, msg, *args)

    def flush(self, force: bool = False) -> None:
        """Log the counts of the windows that have ended (``force``: of every window)."""
        with self._lock:
            due = self._w.due(float("inf") if force else self.clock())
        self._emit(due)

    def close(self) -> None:
        with self._lock:
            t, self._timer = self._timer, None
        if t is not None:
            t.cancel()
        self.flush(force=True)

    def _emit(self, due: list[tuple[Hashable, int, tuple[Any, ...]]]) -> None:
        for _kind, n, (level, msg, args) in due:
            self.logged += 1
            self.logger.log(level, msg + " (×%d in the last %.0f s)", *args, n, self._w.window_s)

    def _arm(self, now: float) -> None:
        if self._timer is not None:
            return
        at = self._w.next_due()
        if at is None:
            return
        t = threading.Timer(max(0.0, at - now) + 0.01, self._fire)
        t.daemon = True
        try:
            t.start()               # (under the lock: its _fire waits for this call to end)
        except RuntimeError:        # no thread to be had: the count comes with the next line or
            return                  # at close, and the next refusal tries again
        self._timer = t

    def _fire(self) -> None:
        with self._lock:
            self._timer = None
            now = self.clock()
            due = self._w.due(now)
            self._arm(now)
        self._emit(due)


class RateBound:
    """At most ``per_min`` events per key within any minute, with a burst of ``per_min``
    (a token bucket refilled at ``per_min`` / 60 per second), or of ``burst`` when given.
    ``max_keys`` keys are kept (the one not seen the longest is forgotten). The one token bucket
    of requests per key: the console's stream and file reads and logins, every door's commands
    at the station's command desk."""

    def __init__(self, per_min: float, clock: Callable[[], float] = time.monotonic,
                 max_keys: int = 4096, burst: float | None = None):
        self.per_min = max(1e-3, float(per_min))
        self.burst = max(1.0, float(self.per_min if burst is None else burst))
        self.clock = clock
        self.max_keys = max_keys
        self._b: dict[str, tuple[float, float]] = {}     # key → (tokens, time)

    def _tokens(self, key: str, now: float) -> float:
        tokens, t = self._b.get(key, (self.burst, now))
        return min(self.burst, tokens + (now - t) * self.per_min / 60.0)

    def wait(self, key: str = "") -> float:
        """0 when one more is allowed now (nothing taken); else the seconds until it is."""
        tokens = self._tokens(key, self.clock())
        return 0.0 if tokens >= 1.0 else (1.0 - tokens) * 60.0 / self.per_min

    def take(self, key: str = "") -> float:
        """0 when allowed (and counted); else the seconds until the next one is allowed."""
        now = self.clock()
        tokens = self._tokens(key, now)
        self._b.pop(key, None)
        if len(self._b) >= self.max_keys:          # forget the key not seen the longest
            self._b.pop(next(iter(self._b)))
        if tokens >= 1.0:
            self._b[key] = (tokens - 1.0, now)
            return 0.0
        self._b[key] = (tokens, now)
        return (1.0 - tokens) * 60.0 / self.per_min
