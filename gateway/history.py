"""The completed tests of a records folder, as METHOD.md §7a's history needs them.

Reads ``<folder>/<test_id>/result.json`` (one station's folder) — or, given a records root,
``<root>/<station>/<test_id>/result.json`` — and returns one :class:`PastTest` per readable
result. A damaged, unreadable or oversized result file is skipped with one log line (with a
count), never fatal. Bounded: at most ``max_files`` result files (the newest by folder name,
which starts with the test's UTC start time) and ``MAX_RESULT_BYTES`` each.
"""
from __future__ import annotations

import json
import logging
import math
import os
from typing import Any

from .method.prior import PastTest

log = logging.getLogger(__name__)

RESULT_NAME = "result.json"
#: a result file is a few kB; larger ones are not read
MAX_RESULT_BYTES = 1 << 20
#: result files read per call (the newest); a station records one test per hook life
MAX_FILES = 20000


def _num(v: Any) -> float | None:
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        return None
    f = float(v)
    return f if math.isfinite(f) else None


def past_test(result: Any) -> PastTest | None:
    """A result.json's content as a PastTest, or None when it is not a result."""
    if not isinstance(result, dict):
        return None
    method = result.get("method")
    if not isinstance(method, dict):
        return None
    grade = result.get("grade")
    status = method.get("status")
    return PastTest(grade=grade if isinstance(grade, str) else None,
                    t_set=_num(result.get("t_set")),
                    status=status if isinstance(status, str) else None,
                    t_life=_num(method.get("t_life")))


def _result_files(folder: str) -> list[str]:
    """result.json files one or two levels below ``folder``."""
    out: list[str] = []
    try:
        subs = sorted(os.scandir(folder), key=lambda e: e.name)
    except OSError:
        return out
    for e in subs:
        if not e.is_dir(follow_symlinks=False):
            continue
        p = os.path.join(e.path, RESULT_NAME)
        if os.path.isfile(p):
            out.append(p)
            continue
        try:
            inner = sorted(os.scandir(e.path), key=lambda x: x.name)
        except OSError:
            continue
        out += [os.path.join(x.path, RESULT_NAME) for x in inner
                if x.is_dir(follow_symlinks=False) and os.path.isfile(os.path.join(x.path, RESULT_NAME))]
    return out


def read_history(folder: str, max_files: int = MAX_FILES) -> list[PastTest]:
    """The completed tests under ``folder`` (a station's records folder or the records root)."""
    files = _result_files(folder)
    if len(files) > max_files:
        log.warning("%s: %d result files; the history uses the newest %d", folder, len(files), max_files)
        files = sorted(files, key=lambda p: os.path.basename(os.path.dirname(p)))[-max_files:]
    out: list[PastTest] = []
    bad: list[str] = []
    for p in files:
        try:
            if os.path.getsize(p) > MAX_RESULT_BYTES:
                bad.append(f"{p} (larger than {MAX_RESULT_BYTES} bytes)")
                continue
            with open(p, encoding="utf-8") as f:
                t = past_test(json.load(f))
        except (OSError, UnicodeDecodeError, ValueError, RecursionError) as e:
            bad.append(f"{p} ({type(e).__name__})")
            continue
        if t is None:
            bad.append(f"{p} (not a test result)")
            continue
        out.append(t)
    if bad:
        log.warning("%s: %d damaged result file(s) skipped by the life history, e.g. %s",
                    folder, len(bad), bad[0])
    return out
