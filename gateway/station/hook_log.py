"""A station's life log of its hooks: ``<recorder.dir>/<station>/hooks.jsonl``.

One JSON line per replaced hook, appended (never rewritten) when ``hook_replaced`` is carried
out: ``{"station", "old_sample_id", "new_sample_id", "grade", "by", "utc", "test_id", "life_s",
"life_kind"}`` (``test_id``: the old hook's last test or null; ``life_s``: its t_life if it failed,
else the elapsed time of that test, or null; ``life_kind``: what that life is in the METHOD.md §7a
history of its grade and T_set when the hook was replaced — :data:`LIFE_KINDS`: a wear-out failure,
an early failure (§7a v3: below 0.75 × the median of all lives, counted as censored), censored
(replaced before its end of life) —, or null: no life for the history, or a line written before
§7a v3). A line is at most :data:`MAX_LINE` bytes (longer values are
clipped). A line that cannot be written (ENOSPC, EACCES, …) is a state (the caller reports the
records disk), never an exception. :func:`read_hooks` reads the last :data:`MAX_LINES` lines; a
damaged line is skipped (one log line with the count).
"""
from __future__ import annotations

import json
import logging
import os
import re
from typing import Any

from ..core.method.prior import CENSORED, EARLY, WEAR_OUT
from ..offline.logio import tail_jsonl

__all__ = ["HOOKS_NAME", "LIFE_KINDS", "MAX_LINE", "MAX_LINES", "append_hook", "next_sample_id",
           "read_hooks"]

log = logging.getLogger("hookwatch.station")

HOOKS_NAME = "hooks.jsonl"
#: bytes per line, newline included
MAX_LINE = 4096
#: lines read back (the newest)
MAX_LINES = 10_000
#: characters kept of a text value of a line
_CLIP = 256
#: a life's kind in the §7a history (gateway.core.method.prior) and its words
LIFE_KINDS = {WEAR_OUT: "wear-out failure", EARLY: "early failure",
              CENSORED: "censored: replaced before its end of life"}

_REPLACED = re.compile(r"^(.*)-R(\d{1,6})$")


def next_sample_id(old: str | None, limit: int) -> str:
    """The sample id a new hook gets when the command names none: ``<old>-R<n>`` (n counts up
    over ``-R`` suffixes: S-1 → S-1-R1 → S-1-R2), at most ``limit`` characters."""
    base, n = (old or "hook"), 1
    m = _REPLACED.match(base)
    if m:
        base, n = m.group(1), int(m.group(2)) + 1
    tail = f"-R{n}"
    return base[: max(1, limit - len(tail))] + tail


def _clip(v: Any) -> Any:
    return v[:_CLIP] if isinstance(v, str) else v


def append_hook(station_dir: str, record: dict[str, Any]) -> str | None:
    """Append one record to the station's hooks.jsonl; None when written, else the OS's reason."""
    rec = {k: _clip(v) for k, v in record.items()}
    line = json.dumps(rec, ensure_ascii=True, separators=(",", ":"), allow_nan=False) + "\n"
    if len(line) > MAX_LINE:      # cannot happen with clipped values; never write a longer line
        line = json.dumps({k: rec.get(k) for k in ("station", "old_sample_id", "new_sample_id",
                                                    "utc", "test_id")}) + "\n"
    try:
        os.makedirs(station_dir, exist_ok=True)
        fd = os.open(os.path.join(station_dir, HOOKS_NAME),
                     os.O_WRONLY | os.O_CREAT | os.O_APPEND, 0o644)
        try:
            os.write(fd, line.encode("ascii"))
            os.fsync(fd)
        finally:
            os.close(fd)
    except OSError as e:
        return e.strerror or str(e)
    return None


def read_hooks(station_dir: str, max_lines: int = MAX_LINES) -> list[dict[str, Any]]:
    """The last ``max_lines`` records of the station's hooks.jsonl, oldest first (none when it is
    absent or cannot be read: one log line); read from the end within a bounded number of bytes
    (:func:`gateway.offline.logio.tail_jsonl`); a damaged line is skipped (one log line with the count)."""
    path = os.path.join(station_dir, HOOKS_NAME)
    try:
        out, bad = tail_jsonl(path, max_lines, MAX_LINE)
    except OSError as e:
        log.warning("%s: cannot be read (%s)", path, e.strerror or e)
        return []
    if bad:
        log.warning("%s: %d damaged line(s) skipped", path, bad)
    return out
