"""Nothing non-finite enters the method or leaves the box as JSON (issue 27, item 4).

- ``hookwatch analyze --set`` refuses a parameter beyond its plausible bound (a prior of 1e308),
  naming the key and the bound; so does a log whose sidecar carries one. Before, the forecast
  of such a prior overflowed and ``analyze --json`` printed ``Infinity``.
- Within the bounds (the largest prior allowed) every forecast figure stays finite.
- ``result.json`` is strict JSON whatever the result holds (a non-finite number is null).
- A forged history (result.json files with lives of 1e308 s) gives no prior that overflows.
"""
from __future__ import annotations

import json
import math
import os
import shutil
import subprocess

import numpy as np
import pytest

from conftest import ROOT, VECTORS, hookwatch_cmd
from gateway.core.method.params import TEN_YEARS
from gateway.core.method.prior import resolve_prior
from gateway.offline.history import read_history
from gateway.plumbing.safeout import loads_strict
from gateway.station.recorder import write_result
from kit.jsondoc import numbers

V1 = os.path.join(VECTORS, "v1_failure")


def analyze(*args):
    return subprocess.run(hookwatch_cmd() + ["analyze", *args], capture_output=True, text=True,
                          cwd=ROOT, timeout=120)



@pytest.mark.parametrize("sets,key", [
    (["prior_mean=1e308", "prior_sd=1"], "prior_mean"),
    (["prior_mean=36000", "prior_sd=1e308"], "prior_sd"),
    (["lead=1e308"], "lead"),
    (["w_hold=1e308"], "w_hold"),
], ids=["prior_mean", "prior_sd", "lead", "w_hold"])
def test_analyze_set_refuses_a_value_beyond_its_bound(sets, key):
    p = analyze(V1 + ".csv.gz", "--json", *(a for s in sets for a in ("--set", s)))
    assert p.returncode != 0
    assert p.stdout == ""
    assert f"{key}: 1e+308 is out of range; allowed: ≤ 315576000 s (10 years)" in p.stderr, p.stderr
    assert "Traceback" not in p.stderr


def test_a_sidecar_with_a_huge_prior_is_refused_and_never_printed_as_infinity(tmp_path):
    shutil.copy(V1 + ".csv.gz", tmp_path / "v1.csv.gz")
    with open(V1 + ".meta.yaml", encoding="utf-8") as f:
        meta = f.read()
    (tmp_path / "v1.meta.yaml").write_text(meta + "  prior_mean: 1.0e+308\n  prior_sd: 1.0e+308\n")
    p = analyze(str(tmp_path / "v1.csv.gz"), "--json")
    for line in p.stdout.splitlines():           # whatever is printed parses strictly
        loads_strict(line)
    assert "Infinity" not in p.stdout and "NaN" not in p.stdout
    assert p.returncode != 0 and "prior_mean: 1e+308 is out of range" in p.stderr, p.stderr


def test_the_largest_prior_allowed_gives_finite_forecasts():
    p = analyze(V1 + ".csv.gz", "--json", "--set", f"prior_mean={TEN_YEARS!r}", "--set",
                f"prior_sd={TEN_YEARS!r}", "--set", f"lead={TEN_YEARS!r}")
    assert p.returncode == 0, p.stderr
    out = loads_strict(p.stdout)
    assert out["status"] == "failure" and out["end_p90"] is not None
    assert all(math.isfinite(x) for x in numbers(out))


def test_result_json_is_strict_whatever_the_result_holds(tmp_path):
    d = tmp_path / "T-1"
    d.mkdir()
    res = {"test_id": "T-1", "t_set": np.float64(0.5), "method": {
        "status": "failure", "t_life": math.inf, "mu_ss": math.nan, "end_p50": -math.inf,
        "k_b": np.int64(12), "reasons": {"MISSING": np.int32(3)}, "headroom": np.float32("nan")}}
    assert write_result(str(d), res)
    text = (d / "result.json").read_text(encoding="utf-8")
    doc = loads_strict(text)                      # a browser's JSON.parse, an MES
    m = doc["method"]
    assert m["t_life"] is None and m["mu_ss"] is None and m["end_p50"] is None and m["headroom"] is None
    assert m["k_b"] == 12 and m["reasons"] == {"MISSING": 3} and doc["t_set"] == 0.5
    assert json.loads(text) == doc


def test_a_forged_history_gives_no_prior_that_overflows(tmp_path):
    """Three 'failure' results with lives of up to 1e308 s: before, the mean and SD of them
    overflowed (an OverflowError when a test started, or an infinite prior); a life beyond
    10 years is no life, so there is no history prior from them."""
    st = tmp_path / "loom-1"
    for i, life in enumerate((1e308, 1e300, 5e307, 1.2e308)):
        d = st / f"2026112{i}T060000Z-S{i}"
        d.mkdir(parents=True)
        (d / "result.json").write_text(json.dumps({
            "test_id": d.name, "grade": "I", "t_set": 0.5,
            "method": {"status": "failure", "t_life": life}}))
    hist = read_history(str(st))
    assert len(hist) == 4
    pr = resolve_prior((), hist, "I", 0.5)
    assert pr.mean is None and pr.sd is None
