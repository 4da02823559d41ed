"""A test campaign on disk: discovery of the recorded tests, their sidecars and gateway results,
the offline wear table, and the parallel analysis of the logs.

A campaign folder holds recorded tests in either layout, found recursively:

- the gateway's ``<station>/<test_id>/log.csv.gz`` + ``log.meta.yaml`` (+ ``result.json``),
- plain ``NAME.csv[.gz]`` + ``NAME.meta.yaml`` pairs (+ optional ``NAME.result.json``),

and optionally ``wear.csv`` (offline wear measurements per sample). Every problem with the input
becomes a :class:`Problem` naming the file; the rest of the campaign is still analysed.
"""
from __future__ import annotations

import csv
import json
import math
import os
import re
import sys
import time
from collections.abc import Callable, Collection
from dataclasses import dataclass, field
from typing import Any

from ...core.method.params import MethodParams
from .. import logio
from ..analysis import AnalysisError, params_for
from ..logio import LogError, read_meta, sidecar_path

#: written into a report folder so that a report inside the campaign folder is never mistaken
#: for recorded tests on the next run
REPORT_MARKER = ".hookwatch-report"

#: δ factors of the sensitivity study (Table 5): 0.9 δ0, δ0, 1.1 δ0
DELTA_FACTORS = (0.9, 1.0, 1.1)

#: wear-table columns that describe the sample rather than measure wear
WEAR_META_COLUMNS = {"sample_id", "grade", "t_set", "t_set_n", "setpoint", "t_life", "t_life_s",
                     "t_end", "t_end_h", "t_end_s", "mu_ss", "status", "note", "notes",
                     "comment", "comments", "remark", "remarks"}

ROLE_OPEN = "open_loop"
ROLE_CLOSED = "closed_loop"


@dataclass
class Problem:
    file: str
    message: str

    def __str__(self) -> str:
        return f"{self.file}: {self.message}"


@dataclass
class TestSpec:
    """One recorded test of the campaign, as its sidecar and result.json describe it."""
    log: str                       # path of the log
    rel: str                       # path relative to the campaign folder (for display)
    sample_id: str
    grade: str | None
    params: MethodParams | None    # None: cannot be analysed (see problems)
    gateway_status: str | None = None      # result.json test_status (completed / aborted)
    gateway_reason: str | None = None      # result.json end_reason
    notes: list[str] = field(default_factory=list)
    size: int = 0
    duplicate_of: str | None = None        # another test already has this sample_id

    @property
    def t_set(self) -> float | None:
        return None if self.params is None else self.params.t_set


@dataclass
class ControlLog:
    """A log of the open-loop / closed-loop comparison (Fig. 8)."""
    log: str
    rel: str
    role: str
    t_set: float | None
    size: int = 0


@dataclass
class WearTable:
    path: str
    indicators: list[str]                       # column names, in file order
    rows: dict[str, dict[str, float | None]]    # sample_id -> indicator -> value
    order: list[str]                            # sample ids in file order
    decimals: dict[str, int] = field(default_factory=dict)  # as written in the file


@dataclass
class Campaign:
    root: str
    tests: list[TestSpec]
    control: list[ControlLog]
    wear: WearTable | None
    problems: list[Problem]


def _rel(path: str, root: str) -> str:
    try:
        r = os.path.relpath(path, root)
    except ValueError:
        return path
    return path if r.startswith("..") else r


def find_logs(root: str, skip: Collection[str] = frozenset()) -> list[str]:
    """Every ``*.csv`` / ``*.csv.gz`` below root (sorted), leaving out hidden folders, report
    folders (:data:`REPORT_MARKER`) and the paths in ``skip``."""
    out = []
    skip = {os.path.realpath(s) for s in skip}
    for dirpath, dirnames, filenames in os.walk(root):
        if REPORT_MARKER in filenames or os.path.realpath(dirpath) in skip:
            dirnames[:] = []
            continue
        dirnames[:] = sorted(d for d in dirnames if not d.startswith("."))
        for fn in sorted(filenames):
            if fn.endswith(".csv") or fn.endswith(".csv.gz"):
                p = os.path.join(dirpath, fn)
                if os.path.realpath(p) not in skip:
                    out.append(p)
    return out


def _result_json(log: str) -> str | None:
    base = os.path.basename(log)
    d = os.path.dirname(log)
    stem = base[:-7] if base.endswith(".csv.gz") else base[:-4]
    for cand in (os.path.join(d, stem + ".result.json"),
                 os.path.join(d, "result.json") if stem == "log" else None):
        if cand and os.path.exists(cand):
            return cand
    return None


def _default_sample_id(log: str) -> str:
    base = os.path.basename(log)
    stem = base[:-7] if base.endswith(".csv.gz") else base[:-4]
    if stem == "log":  # gateway layout: the test folder names the test
        return os.path.basename(os.path.dirname(os.path.abspath(log))) or stem
    return stem


def _text(v: Any) -> str | None:
    if v is None:
        return None
    s = str(v).strip()
    return s or None


def _num(v: Any) -> float | None:
    if v is None or isinstance(v, bool):
        return None
    try:
        f = float(v)
    except (TypeError, ValueError):
        return None
    return f if math.isfinite(f) else None


def describe_test(log: str, root: str, overrides: dict[str, Any], problems: list[Problem]
                  ) -> TestSpec | ControlLog | None:
    """The test a log belongs to, from its sidecar; None (and a problem) when it has none."""
    rel = _rel(log, root)
    sp = sidecar_path(log)
    if not os.path.exists(sp):
        problems.append(Problem(rel, f"no sidecar {os.path.basename(sp)} beside the log (it names "
                                     "sample_id, grade and t_set); log not analysed"))
        return None
    try:
        meta = read_meta(log)
    except LogError as e:
        problems.append(Problem(_rel(sp, root), f"{e}; log not analysed".replace(sp + ": ", "")))
        return None
    try:
        size = os.path.getsize(log)
    except OSError:
        size = 0
    method = dict(meta.get("method") or {})
    top_t_set = meta.get("t_set")
    if method.get("t_set") is None and top_t_set is not None:
        method["t_set"] = top_t_set
    elif (top_t_set is not None and _num(top_t_set) is not None and _num(method.get("t_set")) is not None
          and _num(top_t_set) != _num(method.get("t_set"))):
        problems.append(Problem(_rel(sp, root), f"t_set {top_t_set!r} differs from method.t_set "
                                f"{method['t_set']!r}; the method's value is used"))
    control_meta = meta.get("control")
    control = control_meta if isinstance(control_meta, dict) else {}
    role = _text(meta.get("role"))
    if role is None and str(control.get("mode", "")).strip().lower() == "open":
        role = ROLE_OPEN
    if role is not None:
        role = role.lower().replace("-", "_").replace(" ", "_")
        if role not in (ROLE_OPEN, ROLE_CLOSED):
            problems.append(Problem(_rel(sp, root), f"role {meta.get('role')!r} is not known; "
                                    f"allowed: {ROLE_OPEN}, {ROLE_CLOSED} (or no role for a wear test); "
                                    "treated as a wear test"))
            role = None
    if role is not None:
        return ControlLog(log, rel, role, _num(method.get("t_set")), size)

    sample_id = _text(meta.get("sample_id"))
    spec_notes: list[str] = []
    if sample_id is None:
        sample_id = _default_sample_id(log)
        problems.append(Problem(_rel(sp, root), f"no sample_id; the test is called {sample_id!r}"))
    grade = _text(meta.get("grade"))
    if grade is None:
        problems.append(Problem(_rel(sp, root), f"sample {sample_id}: no grade in the sidecar; "
                                "analysed, but listed apart (not in the grade statistics)"))
    params = None
    values = dict(method)
    values.update(overrides)
    try:
        params = params_for({"method": values}, {}, _rel(sp, root))
    except AnalysisError as e:
        problems.append(Problem(_rel(sp, root), f"sample {sample_id}: cannot set up the method: "
                                f"{str(e).replace(_rel(sp, root) + ': ', '')}; log not analysed"))
    if params is not None and params.t_end is None:
        spec_notes.append("no t_end in the sidecar: open-ended test")
    spec = TestSpec(log, rel, sample_id, grade, params, notes=spec_notes, size=size)
    rj = _result_json(log)
    if rj is not None:
        try:
            with open(rj, encoding="utf-8") as f:
                res = json.load(f)
            if not isinstance(res, dict):
                raise ValueError(f"expected a JSON object, got {type(res).__name__}")
            spec.gateway_status = _text(res.get("test_status"))
            spec.gateway_reason = _text(res.get("end_reason"))
        except (OSError, ValueError) as e:
            problems.append(Problem(_rel(rj, root), f"unreadable result file ({e}); the gateway's "
                                    "test status is unknown, the log is analysed as it is"))
    return spec


_NUM_RE = re.compile(r"^[+-]?(\d+(\.\d*)?|\.\d+)([eE][+-]?\d+)?$")


def _norm_col(name: str) -> str:
    return re.sub(r"[\s\-]+", "_", name.strip().lstrip("\ufeff").lower())


def read_wear(path: str, root: str, problems: list[Problem]) -> WearTable | None:
    """The offline wear table: a ``sample_id`` column and free columns of wear indicators
    (numbers; an empty cell is a missing measurement). Bad cells and rows are problems."""
    rel = _rel(path, root)
    try:
        with open(path, encoding="utf-8-sig", newline="") as f:
            rows = list(csv.reader(f))
    except (OSError, UnicodeDecodeError) as e:
        problems.append(Problem(rel, f"cannot read the wear table ({e}); wear consistency skipped"))
        return None
    rows = [r for r in rows if any(c.strip() for c in r)]
    if not rows:
        problems.append(Problem(rel, "empty wear table; wear consistency skipped"))
        return None
    header = [h.strip() for h in rows[0]]
    norm = [_norm_col(h) for h in header]
    sid_col = next((i for i, h in enumerate(norm) if h in ("sample_id", "sample", "sampleid")), None)
    if sid_col is None:
        problems.append(Problem(rel, f"no sample_id column in header {','.join(header)!r}; "
                                "wear consistency skipped"))
        return None
    cand = [i for i, h in enumerate(norm) if i != sid_col and h and h not in WEAR_META_COLUMNS]
    values: dict[str, dict[str, float | None]] = {}
    order: list[str] = []
    numeric_seen = {i: False for i in cand}
    decimals: dict[str, int] = {}
    for lineno, r in enumerate(rows[1:], start=2):
        sid = r[sid_col].strip() if sid_col < len(r) else ""
        if not sid:
            problems.append(Problem(rel, f"line {lineno}: no sample_id; row ignored"))
            continue
        if sid in values:
            problems.append(Problem(rel, f"line {lineno}: sample {sid} appears again; the first row is used"))
            continue
        vals: dict[str, float | None] = {}
        for i in cand:
            cell = r[i].strip() if i < len(r) else ""
            if not cell:
                vals[header[i]] = None
            elif _NUM_RE.match(cell) and math.isfinite(float(cell)):
                vals[header[i]] = float(cell)
                numeric_seen[i] = True
                mant = cell.lower().split("e")[0]
                nd = len(mant.split(".")[1]) if "." in mant else 0
                decimals[header[i]] = max(decimals.get(header[i], 0), nd)
            else:
                vals[header[i]] = None
                problems.append(Problem(rel, f"line {lineno}, column {header[i]}: {cell[:40]!r} is "
                                        "not a number; treated as not measured"))
        values[sid] = vals
        order.append(sid)
    indicators = [header[i] for i in cand if numeric_seen[i]]
    for i in cand:
        if not numeric_seen[i]:
            problems.append(Problem(rel, f"column {header[i]}: no numeric value; not a wear indicator"))
    if not indicators:
        problems.append(Problem(rel, "no numeric wear indicator column; wear consistency skipped"))
        return None
    return WearTable(path, indicators,
                     {s: {k: v[k] for k in indicators} for s, v in values.items()}, order,
                     {k: min(decimals.get(k, 0), 6) for k in indicators})


def discover(root: str, *, wear_path: str | None = None, overrides: dict[str, Any] | None = None,
             skip: Collection[str] = frozenset()) -> Campaign:
    problems: list[Problem] = []
    overrides = overrides or {}
    default_wear = os.path.join(root, "wear.csv")
    if wear_path is None and os.path.exists(default_wear):
        wear_path = default_wear
    skip = set(skip)
    if wear_path is not None:
        skip.add(wear_path)
    tests: list[TestSpec] = []
    control: list[ControlLog] = []
    for log in find_logs(root, skip):
        d = describe_test(log, root, overrides, problems)
        if isinstance(d, ControlLog):
            control.append(d)
        elif d is not None:
            tests.append(d)
    # duplicate sample IDs: the first (in path order) counts, the others are listed apart
    seen: dict[str, TestSpec] = {}
    for t in tests:
        if t.sample_id in seen:
            t.duplicate_of = seen[t.sample_id].rel
            problems.append(Problem(t.rel, f"sample {t.sample_id} was already recorded in "
                                    f"{seen[t.sample_id].rel}; this test is listed apart"))
        else:
            seen[t.sample_id] = t
    wear = read_wear(wear_path, root, problems) if wear_path is not None else None
    if wear is not None:
        for sid in wear.order:
            if sid not in seen:
                problems.append(Problem(_rel(wear.path, root), f"sample {sid} is not a test of this "
                                        "campaign (no log with that sample_id); wear row ignored"))
    return Campaign(root, tests, control, wear, problems)


# ---------------------------------------------------------------------------------------------
# Progress and parallel analysis
# ---------------------------------------------------------------------------------------------

class Progress:
    """A one-line progress bar on stderr; silent unless stderr is a terminal (or forced)."""

    def __init__(self, total: int, label: str, enabled: bool | None = None, stream=None,
                 width: int = 30):
        self.stream = stream or sys.stderr
        if enabled is None:
            enabled = bool(getattr(self.stream, "isatty", lambda: False)())
        self.enabled = enabled and total > 0
        self.total, self.label, self.width = total, label, width
        self.done = 0
        self.t0 = time.monotonic()
        self._draw()

    def _draw(self) -> None:
        if not self.enabled:
            return
        frac = self.done / self.total if self.total else 1.0
        n = int(round(frac * self.width))
        el = time.monotonic() - self.t0
        self.stream.write(f"\r{self.label} [{'#' * n}{'.' * (self.width - n)}] "
                          f"{self.done}/{self.total}  {el:5.1f} s")
        self.stream.flush()

    def advance(self, n: int = 1) -> None:
        self.done += n
        self._draw()

    def close(self) -> None:
        if self.enabled:
            self.stream.write("\n")
            self.stream.flush()


def run_parallel(fn: Callable, tasks: list, jobs: int, on_done: Callable[[], None] | None = None
                 ) -> list:
    """``[fn(t) for t in tasks]`` on up to ``jobs`` processes (results in task order). ``fn``
    must not raise (it reports errors in its result). With one job, or one task, it runs in this
    process. The log reader's own two-core parsing is left on only when it has the cores to
    itself (a single task with jobs ≥ 2)."""

    results: list = [None] * len(tasks)
    workers = max(1, min(jobs, len(tasks)))
    if workers == 1:
        saved = logio.PARALLEL_PARSE_BYTES
        if jobs < 2:
            logio.PARALLEL_PARSE_BYTES = 1 << 62
        try:
            for i, t in enumerate(tasks):
                results[i] = fn(t)
                if on_done:
                    on_done()
        finally:
            logio.PARALLEL_PARSE_BYTES = saved
        return results

    import multiprocessing as mp
    from concurrent.futures import ProcessPoolExecutor, as_completed
    from concurrent.futures.process import BrokenProcessPool

    ctx = mp.get_context("forkserver") if "forkserver" in mp.get_all_start_methods() \
        else mp.get_context("spawn")
    if ctx.get_start_method() == "forkserver":
        ctx.set_forkserver_preload(["gateway.offline.report.per_log"])
    with ProcessPoolExecutor(max_workers=workers, mp_context=ctx,
                             initializer=_init_worker) as ex:
        futs = {ex.submit(fn, t): i for i, t in enumerate(tasks)}
        for fut in as_completed(futs):
            i = futs[fut]
            try:
                results[i] = fut.result()
            except BrokenProcessPool as e:
                results[i] = {"error": f"analysis process died ({e or 'killed'})"}
            except Exception as e:  # noqa: BLE001 - a worker bug must not lose the report
                results[i] = {"error": f"analysis failed: {type(e).__name__}: {e}"}
            if on_done:
                on_done()
    return results


def _init_worker() -> None:

    # one log per core already: the reader must not fork a second parser per worker
    logio.PARALLEL_PARSE_BYTES = 1 << 62
    os.environ.setdefault("MPLBACKEND", "Agg")
