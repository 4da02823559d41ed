"""Nothing non-finite and no live formula leaves the console (issue 27, items 4 and 5).

A real console on a loopback port is fed station states full of hostile values — ±Infinity and
NaN in every number a forecast or the method can produce, sample IDs and grades that start or
hide formulas behind a ``;`` or a TAB — through the real hand-over (``ConsoleOutput``). Every JSON
door (``/api/fleet``, ``/api/station/<id>``, its event stream, ``/api/due``) is fetched over HTTP
and parsed as a browser does (``NaN``/``Infinity`` are a syntax error there); the due list's CSV is
split the way a spreadsheet in any locale would (``,`` in en, ``;`` in de/fr/it/es, TAB when
pasted), even naively without honouring quotes: no cell starts a formula.
"""
from __future__ import annotations

import csv
import io
import math
import re
import urllib.request

from gateway.plumbing.safeout import loads_strict
from kit.console_helpers import HOSTILE_IDS, Client, hostile_states, start_console
from kit.jsondoc import numbers

FORMULA = ("=", "+", "-", "@")
_NUMBER = re.compile(r"[+-]?(?:\d+(?:\.\d*)?|\.\d+)(?:[eE][+-]?\d+)?")


def _raw(url: str) -> tuple[int, str]:
    with urllib.request.urlopen(url, timeout=30) as r:
        return r.status, r.read().decode("utf-8")



def test_no_json_door_of_the_console_emits_infinity_or_nan(tmp_path):
    srv, url, _outs, _dirs = start_console(tmp_path, hostile_states())
    try:
        docs = {}
        for path in ("/api/fleet", "/api/due", "/api/due?line=line-1", *(f"/api/station/{s}" for s in
                                                                        ("loom-a", "loom-b", "loom-c", "loom-d"))):
            st, text = _raw(url + path)
            assert st == 200, path
            assert "Infinity" not in text and "NaN" not in text, (path, text[:300])
            docs[path] = loads_strict(text)                   # as JSON.parse in a browser
            assert all(math.isfinite(x) for x in numbers(docs[path])), path
        cards = {c["station"]: c for c in docs["/api/fleet"]["stations"]}
        # a non-finite number has no value: null, the documented "none" of every figure
        assert cards["loom-a"]["t_cross"] is None and cards["loom-a"]["headroom"] is None
        snap = docs["/api/station/loom-a"]
        assert snap["summary"]["mu_ss"] is None and snap["summary"]["mu_th"] is None
        assert snap["summary"]["end_p50"] is None and snap["summary"]["k_b"] == 7
        assert snap["summary"]["sample_id"] == HOSTILE_IDS[0]          # strings unchanged in JSON
        due = {r["station"]: r for r in docs["/api/due"]["stations"]}
        assert due["loom-a"]["end_p50"] is None and due["loom-a"]["end_utc_p50"] is None
        assert due["loom-b"]["end_p50"] == 1800.0 and due["loom-b"]["p_end"] is None
        # the live stream's first message (what the browser draws from)
        req = urllib.request.Request(url + "/api/station/loom-a/stream")
        with urllib.request.urlopen(req, timeout=30) as r:
            line = r.readline().decode("utf-8")
        assert line.startswith("data: ")
        first = loads_strict(line[len("data: "):])
        assert first["summary"]["end_p10"] is None and all(math.isfinite(x) for x in numbers(first))
    finally:
        srv.stop()


def _pieces(text: str, sep: str) -> list[str]:
    """The cells a spreadsheet that splits every line on ``sep`` without honouring quotes sees."""
    return [p for line in text.splitlines() for p in line.split(sep)]


def _starts_formula(cell: str) -> bool:
    c = cell.lstrip(" \t\"\u00a0")
    return c.startswith(FORMULA) and not _NUMBER.fullmatch(c.rstrip('"'))


def test_due_csv_has_no_live_formula_in_any_locale(tmp_path):
    srv, url, _outs, _dirs = start_console(tmp_path, hostile_states())
    try:
        c = Client(url)
        text = c.opener.open(url + "/api/due.csv", timeout=30).read().decode("utf-8")
        # an honest RFC 4180 reader (Python's csv, LibreOffice with ',') gets the defused text back
        rows = list(csv.reader(io.StringIO(text)))
        head, body = rows[0], rows[1:]
        cells = {r[0]: dict(zip(head, r, strict=True)) for r in body}
        assert cells["loom-a"]["sample_id"] == "x;'=1+1;y" and cells["loom-a"]["grade"] == "'=G1"
        assert cells["loom-b"]["sample_id"] == "'\t'=cmd" and cells["loom-b"]["grade"] == "'\"=1\""
        assert cells["loom-c"]["sample_id"] == "a\t'@SUM(1)"
        assert cells["loom-d"]["sample_id"] == "x,'=1"
        # a non-finite figure is an empty cell, a number stays a number
        assert cells["loom-a"]["end_p50"] == "" and cells["loom-b"]["end_p50"] == "1800.0"
        # a cell holding a separator of any locale is quoted
        assert '"x;\'=1+1;y"' in text and "\"'\t'=cmd\"" in text
        # Excel in de/fr/it/es (';'), a paste into a sheet (TAB), or a naive split on ',':
        # no piece starts a formula, whatever the reader does with the quotes
        for sep in (";", "\t", ","):
            bad = [p for p in _pieces(text, sep) if _starts_formula(p)]
            assert bad == [], (repr(sep), bad)
        # … and the same reading with ';' honouring the quotes (Excel's own CSV import)
        for r in csv.reader(io.StringIO(text), delimiter=";"):
            assert not [x for x in r if _starts_formula(x)], r
        for r in csv.reader(io.StringIO(text), delimiter="\t"):
            assert not [x for x in r if _starts_formula(x)], r
    finally:
        srv.stop()
