"""A campaign whose sample IDs and folder name are hostile (issue 27, items 4 and 5): the report's
CSV tables hold no live formula for a spreadsheet in any locale (split on ``,``, ``;`` or TAB,
even without honouring quotes), and its Markdown and HTML show the names as text — a newline in
the folder's name starts no heading, ``<script>`` is no tag, ``[x](javascript:…)`` is no link."""
import csv
import io
import os
import re
import subprocess
import sys

from conftest import ROOT, hookwatch_cmd

sys.path.insert(0, os.path.join(ROOT, "bench"))
import gen_campaign as G  # noqa: E402

KW = dict(t_end=120.0, run_in_s=10.0, method={"w_ss": 5, "w_hold": 20, "tau": 5})
HOSTILE = ["x;=1+1;y", "\t=cmd", '"=1"', "[a](javascript:alert(1))|<b>"]
FORMULA = ("=", "+", "-", "@")
_NUMBER = re.compile(r"[+-]?(?:\d+(?:\.\d*)?|\.\d+)(?:[eE][+-]?\d+)?")


def _starts_formula(cell: str) -> bool:
    c = cell.lstrip(" \t\"\u00a0")
    return c.startswith(FORMULA) and not _NUMBER.fullmatch(c.rstrip('"'))


def test_hostile_sample_ids_and_folder_name_stay_text(tmp_path):
    camp = tmp_path / "camp\n# injected <script>alert(1)<i>"        # a name holds no "/"
    camp.mkdir()
    lives = (95.0, 90.0, 60.0, 64.0)
    for sid, grade, life in zip(HOSTILE, ("I", "I", "II", "II"), lives, strict=True):
        G.write_test(str(camp), G.TestDef(sid, grade, 0.5, life=life, **KW))
    out = tmp_path / "out"
    p = subprocess.run(hookwatch_cmd() + ["report", str(camp), "--out", str(out), "-q", "-j", "1"],
                       capture_output=True, text=True, timeout=300)
    assert p.returncode == 0, p.stderr
    tables = sorted(f for f in os.listdir(out) if f.endswith(".csv"))
    assert "table3_samples.csv" in tables, tables
    for name in tables:
        text = (out / name).read_text(encoding="utf-8")
        for sep in (",", ";", "\t"):
            bad = [c for line in text.splitlines() for c in line.split(sep) if _starts_formula(c)]
            assert bad == [], (name, repr(sep), bad)
        for sep in (",", ";", "\t"):                   # a reader that honours the quotes
            bad = [c for r in csv.reader(io.StringIO(text), delimiter=sep) for c in r if _starts_formula(c)]
            assert bad == [], (name, repr(sep), bad)
    t3 = list(csv.DictReader(io.StringIO((out / "table3_samples.csv").read_text(encoding="utf-8"))))
    ids = {r["sample_id"] for r in t3}
    assert {"x;'=1+1;y", "'=cmd", "'\"=1\""} <= ids, ids      # (the sidecar's ID is stripped)
    # Markdown: the folder's newline starts no heading; no raw tag, no link the names made
    md = (out / "report.md").read_text(encoding="utf-8")
    assert not [ln for ln in md.splitlines() if ln.startswith("# injected")]
    assert "<script>" not in md and "<b>" not in md and "<i>" not in md
    assert not re.search(r"(?<!\\)\]\(javascript:", md)              # only an escaped "\](" is left
    assert "\\<script\\>alert(1)\\<i\\>" in md            # shown as the text it is
    html = (out / "report.html").read_text(encoding="utf-8")
    assert "<script>" not in html and "&lt;script&gt;" in html and "|&lt;b&gt;" in html
