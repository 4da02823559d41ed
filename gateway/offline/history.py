"""The completed tests of a records folder, as METHOD.md §7a's history needs them.

Reads ``<folder>/<test_id>/result.json`` (one station's folder) — or, given a records root,
``<root>/<station>/<test_id>/result.json`` — and returns one :class:`PastTest` per readable
result. A damaged, unreadable or oversized result file is skipped with one log line (with a
count), never fatal. Bounded: at most ``max_files`` result files (the newest by folder name,
which starts with the test's UTC start time) and ``MAX_RESULT_BYTES`` each.

A result carries what §7a needs: the method's ``status``, ``t_life``, ``k_b``, ``stop_reasons``
and ``n_slots``, and the test's ``ts`` (a censored life is c = n_slots · Ts). Results written
before ``ts`` and ``t_end`` went into result.json take them from the test's sidecar
(``log.meta.yaml`` beside it, ``method.ts``, ``method.t_end``), read only for a test that may be a
censored life (:func:`sidecar_method` gives the rest on demand).
"""
from __future__ import annotations

import dataclasses
import json
import logging
import math
import os
from typing import Any

from ..core.method.params import TEN_YEARS
from ..core.method.prior import STOPPED, PastTest
from ..plumbing import safeyaml

log = logging.getLogger(__name__)

RESULT_NAME = "result.json"
SIDECAR_NAME = "log.meta.yaml"
#: a result file is a few kB; larger ones are not read
MAX_RESULT_BYTES = 1 << 20
#: result files read per call (the newest); a station records one test per hook life
MAX_FILES = 20000


def _num(v: Any) -> float | None:
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        return None
    f = float(v)
    return f if math.isfinite(f) else None


def _int(v: Any) -> int | None:
    return v if isinstance(v, int) and not isinstance(v, bool) else None


def past_test(result: Any, ts: float | None = None) -> PastTest | None:
    """A result.json's content as a PastTest, or None when it is not a result. ``ts``: the test's
    sampling period when the result does not say it."""
    if not isinstance(result, dict):
        return None
    method = result.get("method")
    if not isinstance(method, dict):
        return None
    grade = result.get("grade")
    status = method.get("status")
    reasons = method.get("stop_reasons")
    tid, station, why = result.get("test_id"), result.get("station"), result.get("end_reason")
    r_ts = _num(result.get("ts"))
    return PastTest(grade=grade if isinstance(grade, str) else None,
                    t_set=_num(result.get("t_set")),
                    status=status if isinstance(status, str) else None,
                    t_life=_life(method.get("t_life")),
                    k_b=_int(method.get("k_b")),
                    stop_reasons=(tuple(reasons) if isinstance(reasons, list)
                                  and all(isinstance(x, str) for x in reasons) else None),
                    n_slots=_int(method.get("n_slots")),
                    ts=r_ts if r_ts is not None else ts,
                    test_id=tid if isinstance(tid, str) else None,
                    station=station if isinstance(station, str) else None,
                    t_end=_num(result.get("t_end")), end_reason=why if isinstance(why, str) else None)


def _life(v: Any) -> float | None:
    """A recorded life, s: a finite number of at most 10 years (method.params.TEN_YEARS), else none
    (a damaged or forged result.json must not make a prior that overflows the §5b forecast)."""
    f = _num(v)
    return f if f is not None and f <= TEN_YEARS else None


def _may_be_censored(t: PastTest) -> bool:
    return t.k_b is not None and (t.status == "no_failure" or (
        t.status == "aborted" and t.stop_reasons == (STOPPED,)))


def sidecar_method(test_dir: str) -> dict[str, Any]:
    """The ``method:`` section of the test's sidecar ({} when it has none or cannot be read)."""
    try:
        meta = safeyaml.read(os.path.join(test_dir, SIDECAR_NAME), limits=safeyaml.SIDECAR).data
    except (safeyaml.YamlError, OSError):
        return {}
    method = meta.get("method") if isinstance(meta, dict) else None
    return method if isinstance(method, dict) else {}


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
        if t.ts is None and _may_be_censored(t):
            m = sidecar_method(os.path.dirname(p))
            t = dataclasses.replace(t, ts=t.ts if t.ts is not None else _num(m.get("ts")),
                                    t_end=t.t_end if t.t_end is not None else _num(m.get("t_end")))
        out.append(t)
    if bad:
        log.warning("%s: %d damaged result file(s) skipped by the life history, e.g. %s",
                    folder, len(bad), bad[0])
    return out
