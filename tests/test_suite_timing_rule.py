"""The suite never times (issue 30 item 5; tests/README "What a test asserts"): no test asserts
that a measured duration was short. A duration measured with the clock (``time.monotonic()``,
``time.perf_counter()``, ``time.time()`` or their ``_ns`` forms, minus a start) and then bounded
from above in an ``assert`` fails on a loaded machine while the code is right; such a figure is
``bench/``'s.

What stays allowed, because a loaded machine cannot make it fail while the code is right:
- a deadline guard (``assert time.monotonic() < t_end, "never came up"``): a clock reading, not a
  duration; it is the test's own timeout with a message;
- a lower bound (``assert waited >= timeout_s``): a slow machine only makes the duration longer;
- an allowance that grows with the elapsed time (``assert accepted <= 30 + elapsed * rate``): the
  duration is on the side that a slow machine makes larger.

The check reads every test module's syntax tree: the names a function assigns from a clock
difference, then each ``assert`` comparison with such a duration (the name, or the difference
itself) on the small side of ``<``/``<=`` (or the large side of ``>``/``>=``) against a bound that
is not itself a duration; and any comparison of a timing figure by its name (``p50``, ``p99``,
``latency``, ``rtt``, ``per_s``, ``throughput``), or of a rate (a count over the time between two
instants), with a written number, either way (a rate of "40 to 60 slots per second" fails on a
loaded machine from below as well). The names are a convention the check relies on; it is a net,
not a proof, and each case it was built from (29d06f2's timed asserts) is in its self-check.
"""
from __future__ import annotations

import ast
import os
import re

import conftest as C

ROOT = C.ROOT
CLOCKS = {"monotonic", "perf_counter", "time", "monotonic_ns", "perf_counter_ns", "time_ns"}


def _is_clock_call(n: ast.AST) -> bool:
    if not isinstance(n, ast.Call) or n.args:
        return False
    f = n.func
    return ((isinstance(f, ast.Attribute) and f.attr in CLOCKS and isinstance(f.value, ast.Name)
             and f.value.id == "time") or (isinstance(f, ast.Name) and f.id in CLOCKS - {"time"}))


def _is_clock_difference(n: ast.AST) -> bool:
    return isinstance(n, ast.BinOp) and isinstance(n.op, ast.Sub) and _is_clock_call(n.left)


def _durations_of(fn: ast.AST) -> set[str]:
    """Names assigned (anywhere in the function) from a clock difference."""
    names: set[str] = set()
    for n in ast.walk(fn):
        if isinstance(n, ast.Assign) and _is_clock_difference(n.value):
            names |= {t.id for t in n.targets if isinstance(t, ast.Name)}
        elif isinstance(n, ast.AnnAssign) and n.value is not None and _is_clock_difference(n.value) \
                and isinstance(n.target, ast.Name):
            names.add(n.target.id)
    return names


def _is_duration(n: ast.AST, durations: set[str]) -> bool:
    return (isinstance(n, ast.Name) and n.id in durations) or _is_clock_difference(n)


def _mentions_duration(n: ast.AST, durations: set[str]) -> bool:
    return any(_is_duration(x, durations) for x in ast.walk(n))


#: a timing figure by its name (a percentile, a latency, a round trip, a rate per second)
FIGURE = re.compile(r"(^|_)(p50|p90|p95|p99|latency|latencies|rtt|rtts|per_s|throughput)(_(ms|s|us|ns))?$", re.I)


#: a name that holds a point in time (``t0``, ``t_start``, ``end_t``, ``ts1``, ``start_time``)
INSTANT = re.compile(r"^(t\d*|t_\w+|\w+_t|ts\d*|\w*time\w*)$")


def _is_instant(n: ast.AST) -> bool:
    return _is_clock_call(n) or (isinstance(n, ast.Name) and bool(INSTANT.match(n.id)))


def _is_figure(n: ast.AST) -> bool:
    """A name, attribute or string subscript that names a timing figure (``lat["p50"]``,
    ``stats.p99_ms``, ``slots_per_s``), or a rate: something divided by the time between two
    instants (``(v1 - v0) / (t1 - t0)``)."""
    if isinstance(n, ast.BinOp) and isinstance(n.op, ast.Div):
        d = n.right
        return isinstance(d, ast.BinOp) and isinstance(d.op, ast.Sub) and _is_instant(d.left) \
            and _is_instant(d.right)
    if isinstance(n, ast.Name):
        return bool(FIGURE.search(n.id))
    if isinstance(n, ast.Attribute):
        return bool(FIGURE.search(n.attr))
    if isinstance(n, ast.Subscript) and isinstance(n.slice, ast.Constant) and isinstance(n.slice.value, str):
        return bool(FIGURE.search(n.slice.value))
    return False


def _is_number(n: ast.AST) -> bool:
    """A bound written as a number (``0.3``, ``-1``, ``2 * 0.02``)."""
    return all(isinstance(x, (ast.Constant, ast.UnaryOp, ast.BinOp, ast.operator, ast.unaryop))
               for x in ast.walk(n)) and all(isinstance(x.value, (int, float)) and not isinstance(x.value, bool)
                                             for x in ast.walk(n) if isinstance(x, ast.Constant))


def timed_asserts(src: str) -> list[int]:
    """Lines of the asserts that bound a measured duration from above, or a timing figure by a
    number on either side."""
    tree = ast.parse(src)
    bad: list[int] = []
    for fn in ast.walk(tree):
        if not isinstance(fn, (ast.FunctionDef, ast.AsyncFunctionDef)):
            continue
        durations = _durations_of(fn)
        for a in ast.walk(fn):
            if not isinstance(a, ast.Assert):
                continue
            for cmp in ast.walk(a.test):
                if not isinstance(cmp, ast.Compare):
                    continue
                operands = [cmp.left, *cmp.comparators]
                for i, op in enumerate(cmp.ops):
                    lo, hi = operands[i], operands[i + 1]
                    if isinstance(op, (ast.Lt, ast.LtE, ast.Gt, ast.GtE)) and (
                            (_is_figure(lo) and _is_number(hi)) or (_is_figure(hi) and _is_number(lo))):
                        bad.append(a.lineno)
                        continue
                    if isinstance(op, (ast.Gt, ast.GtE)):
                        lo, hi = hi, lo
                    elif not isinstance(op, (ast.Lt, ast.LtE)):
                        continue
                    # lo < hi: a duration below a bound that is no duration itself
                    if _is_duration(lo, durations) and not _mentions_duration(hi, durations):
                        bad.append(a.lineno)
    return sorted(set(bad))


def test_no_test_bounds_a_measured_duration_from_above():
    bad = []
    for d, _, files in os.walk(os.path.join(ROOT, "tests")):
        for f in files:
            if f.endswith(".py"):
                path = os.path.join(d, f)
                with open(path, encoding="utf-8") as fh:
                    bad += [f"{os.path.relpath(path, ROOT)}:{ln}" for ln in timed_asserts(fh.read())]
    assert bad == [], "a timing figure belongs in bench/ (tests/README): " + ", ".join(bad)


def test_the_timing_rule_flags_what_it_should():
    src = '''
import time
from time import perf_counter
def test_x(n):
    t0 = time.monotonic()
    elapsed = time.monotonic() - t0
    dt = perf_counter() - t0
    assert elapsed < 0.5                                  # 6: flagged
    assert 0.3 > dt                                       # 7: flagged
    assert time.perf_counter() - t0 <= 2                  # 8: flagged
    assert n > 1 and elapsed < 1.0                        # 9: flagged
    assert time.monotonic() < t0 + 5, "never came up"     # 10: a deadline guard
    assert elapsed >= 0.015                               # 11: a lower bound
    assert n <= 30 + elapsed * 4                          # 12: an allowance that grows
    assert dt < elapsed                                   # 13: two durations, no figure
    assert 0.0 <= lat["p50"] < 0.3                        # 14: flagged (a percentile)
    assert 40 <= stats.slots_per_s                        # 15: flagged (a rate)
    assert rtt_ms <= 2 * 10                               # 16: flagged (a round trip)
    assert p99 <= budget                                  # 17: against a computed bound
    assert latency_n >= 3                                 # 18: not a figure's name
    assert 40 <= (v1 - v0) / (t1 - t0) <= 60              # 19: flagged (a rate)
    assert (v1 - v0) / (b - a) <= 60                      # 20: not a time span by its names
'''
    assert [ln - 2 for ln in timed_asserts(src)] == [6, 7, 8, 9, 14, 15, 16, 19]
