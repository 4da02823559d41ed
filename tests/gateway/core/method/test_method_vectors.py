"""The six method vectors (copied from ../shared/vectors) through the CLI and through both forms."""
import glob
import json
import os
import shutil
import subprocess

import pytest
import yaml

from conftest import VECTORS, hookwatch_cmd
from gateway.core.method import analyze_slots, run_streaming, to_slots
from gateway.offline.analysis import params_for
from gateway.offline.logio import read_log

EXACT = ["status", "k_b", "stable_first", "stable_last", "k_life", "n_slots", "n_valid", "reasons",
         "stop_slot", "stop_reasons", "interrupted", "warn_slot", "warn_reasons"]
CLOSE = ["mu_ss", "mu_th", "t_life", "headroom", "p_end"]
RELATIVE = ["t_cross", "end_p10", "end_p50", "end_p90"]
NAMES = sorted(os.path.basename(p)[:-len(".csv.gz")] for p in glob.glob(os.path.join(VECTORS, "*.csv.gz")))


def check(got, exp):
    for k in EXACT:
        assert got[k] == exp[k], k
    for k in CLOSE:
        if exp[k] is None:
            assert got[k] is None, k
        else:
            assert abs(got[k] - exp[k]) <= 1e-9, k
    for k in RELATIVE:
        if exp[k] is None:
            assert got[k] is None, k
        else:
            assert abs(got[k] - exp[k]) <= 1e-9 * max(1.0, abs(exp[k])), k


def expected(name):
    with open(os.path.join(VECTORS, name + ".expected.json")) as f:
        return json.load(f)


def test_there_are_six_vectors():
    assert NAMES == ["v1_failure", "v2_faults", "v3_no_failure", "v4_aborted", "v5_stopped", "v6_prior"]


def test_cli_json_reproduces_every_vector():
    logs = [os.path.join(VECTORS, n + ".csv.gz") for n in NAMES]
    p = subprocess.run(hookwatch_cmd() + ["analyze", *logs, "--json"], capture_output=True, text=True,
                       timeout=120)
    assert p.returncode == 0, p.stderr
    lines = [json.loads(ln) for ln in p.stdout.splitlines()]
    assert len(lines) == len(NAMES)
    from gateway.core.method import RESULT_KEYS
    for name, got in zip(NAMES, lines):
        assert set(got) == set(RESULT_KEYS) | {"log"}
        assert got["log"].endswith(name + ".csv.gz")
        check(got, expected(name))


@pytest.mark.parametrize("name", NAMES)
def test_batch_and_streaming_forms(name):
    log = read_log(os.path.join(VECTORS, name + ".csv.gz"))
    p = params_for(log.meta, {}, name)
    s = to_slots(log.t, log.t1, log.t2, p)
    batch = analyze_slots(s, p).as_dict()
    stream = run_streaming(p, s.present, s.t1, s.t2).as_dict()
    check(batch, expected(name))
    assert stream == batch


def test_cli_table_output_is_readable():
    p = subprocess.run(hookwatch_cmd() + ["analyze", os.path.join(VECTORS, "v4_aborted.csv.gz")],
                       capture_output=True, text=True, timeout=60)
    assert p.returncode == 0
    assert "aborted" in p.stdout and "protection stop at slot 95050 (MISSING)" in p.stdout


def test_set_overrides_sidecar():
    log = os.path.join(VECTORS, "v1_failure.csv.gz")
    p = subprocess.run(hookwatch_cmd() + ["analyze", log, "--json", "--set", "delta=0.5"],
                       capture_output=True, text=True, timeout=60)
    got = json.loads(p.stdout)
    exp = expected("v1_failure")
    assert got["mu_ss"] == pytest.approx(exp["mu_ss"], abs=1e-12)
    assert got["mu_th"] == pytest.approx(1.5 * exp["mu_ss"], abs=1e-12)


def test_streamed_windows_match_the_vector_figures():
    """What the runtime publishes per window (SlotOut.window) ends at the result's figures."""
    log = read_log(os.path.join(VECTORS, "v1_failure.csv.gz"))
    p = params_for(log.meta, {}, "v1")
    s = to_slots(log.t, log.t1, log.t2, p)
    from gateway.core.method import StreamingMonitor
    mon = StreamingMonitor(p)
    wins, warned = [], []
    for k in range(s.present.size):
        out = mon.push(bool(s.present[k]), float(s.t1[k]), float(s.t2[k]))
        if out.window is not None:
            wins.append(out.window)
        if "wear_warning" in out.events:
            warned.append(k)
            assert out.forecast is not None and out.forecast.warning
            assert list(out.forecast.reasons) == ["trend"]
    exp = expected("v1_failure")
    assert warned == [exp["warn_slot"]]
    assert wins[0].j == (exp["k_b"] + 1) // p.n_ss
    assert abs(wins[-1].headroom - exp["headroom"]) <= 1e-9
    assert any(w.t_cross is not None for w in wins) and wins[-1].t_cross is None


def test_set_end_slot_and_warning_parameters_on_the_command_line():
    log = os.path.join(VECTORS, "v1_failure.csv.gz")
    exp = expected("v1_failure")
    runs = {}
    for end, extra in ((100000, ()), (170000, ()), (170000, ("h_warn=0.9", "n_warn=2"))):
        # lead 0: no trend reason (t_cross lies after the window), the headroom run alone
        sets = [a for x in ("lead=0", f"end_slot={end}", *extra) for a in ("--set", x)]
        p = subprocess.run(hookwatch_cmd() + ["analyze", log, "--json", *sets],
                           capture_output=True, text=True, timeout=60)
        assert p.returncode == 0, p.stderr
        runs[end, extra] = json.loads(p.stdout)
    got = runs[100000, ()]       # stopped before the end of life
    assert (got["status"], got["stop_slot"], got["stop_reasons"], got["n_slots"], got["interrupted"]) == \
        ("aborted", 100000, ["STOPPED"], 100000, False)
    got = runs[170000, ()]       # stopped after t_life: stays a failure, interrupted
    assert (got["status"], got["stop_slot"], got["stop_reasons"], got["interrupted"], got["k_life"]) == \
        ("failure", 170000, ["STOPPED"], True, exp["k_life"])
    assert got["warn_reasons"] == ["headroom"] and got["warn_slot"] > exp["warn_slot"]
    # a higher h_warn and a shorter run warn earlier
    got2 = runs[170000, ("h_warn=0.9", "n_warn=2")]
    assert got2["warn_reasons"] == ["headroom"] and got2["warn_slot"] < got["warn_slot"]


def test_cli_table_shows_headroom_warning_projection_and_stopped():
    logs = [os.path.join(VECTORS, n + ".csv.gz") for n in ("v1_failure", "v3_no_failure", "v5_stopped")]
    p = subprocess.run(hookwatch_cmd() + ["analyze", *logs], capture_output=True, text=True, timeout=60)
    assert p.returncode == 0, p.stderr
    head = p.stdout.splitlines()[0].split()
    assert head[-6:] == ["headroom", "warn_s", "warn_by", "t_cross_s", "end_p50_s", "p_end"]
    rows = {ln.split()[0]: ln.split() for ln in p.stdout.splitlines()[1:4]}
    v1, v3, v5 = (rows[x] for x in logs)
    assert v1[-6:] == ["-0.496", "2910.00", "trend", "-", "-", "-"]   # the end of slot 145499
    assert v3[-6:] == ["1.001", "-", "-", "80836", "-", "-"]
    assert v5[-6:] == ["0.986", "-", "-", "-", "-", "-"] and v5[1] == "aborted"
    assert "early warning at 2910.00 s (slot 145499; due by trend)" in p.stdout
    assert "reaches mu_th at 80836 s (22.5 h" in p.stdout
    assert "ended on purpose at slot 125000 (STOPPED)" in p.stdout


def test_cli_table_shows_the_forecast_from_a_prior():
    p = subprocess.run(hookwatch_cmd() + ["analyze", os.path.join(VECTORS, "v6_prior.csv.gz")],
                       capture_output=True, text=True, timeout=60)
    assert p.returncode == 0, p.stderr
    row = p.stdout.splitlines()[1].split()
    assert row[-6:] == ["-0.506", "2520.00", "prior", "-", "3421", "1.000"]
    assert "early warning at 2520.00 s (slot 125999; due by prior); prior 3300 ± 150 s;" in p.stdout
    assert "end 3346 / 3421 / 3559 s (10/50/90 %), P(end within 600 s) 1.000" in p.stdout


def test_cli_says_how_many_lives_a_history_prior_came_from(tmp_path):
    """A sidecar written by the gateway at a test's start carries the §7a counts (v3: wear-out
    failures, censored lives, early failures); `hookwatch analyze` says them beside the prior."""
    shutil.copy(os.path.join(VECTORS, "v6_prior.csv.gz"), tmp_path / "t.csv.gz")
    with open(os.path.join(VECTORS, "v6_prior.meta.yaml"), encoding="utf-8") as f:
        meta = yaml.safe_load(f)
    meta.update(prior_source="history", prior_n=4, prior_n_censored=3, prior_n_early=1)
    (tmp_path / "t.meta.yaml").write_text(yaml.safe_dump(meta), encoding="utf-8")
    p = subprocess.run(hookwatch_cmd() + ["analyze", str(tmp_path / "t.csv.gz")],
                       capture_output=True, text=True, timeout=60)
    assert p.returncode == 0, p.stderr
    assert ("prior 3300 ± 150 s, from history (4 wear-out failures, 3 censored, 1 early failure);"
            in p.stdout), p.stdout


@pytest.mark.parametrize("name", ["v1_failure", "v6_prior"])
def test_streamed_forecasts_equal_the_batch_forecasts_at_every_window(name):
    """METHOD.md §5b online: every forecast time's e10/e50/e90, P, headroom, t_cross, reasons and
    the warning, as the runtime gets them (SlotOut.forecast), equal the batch form's."""
    from gateway.core.method import StreamingMonitor
    from gateway.core.method.core import gate_and_baseline, life_detail
    log = read_log(os.path.join(VECTORS, name + ".csv.gz"))
    p = params_for(log.meta, {}, name)
    s = to_slots(log.t, log.t1, log.t2, p)
    mon = StreamingMonitor(p)
    online = []
    for k in range(s.present.size):
        out = mon.push(bool(s.present[k]), float(s.t1[k]), float(s.t2[k]))
        if out.forecast is not None:
            online.append(out.forecast)
        if "wear_warning" in out.events:
            assert out.forecast.warning and out.forecast.reasons
    res, _, offline = life_detail(gate_and_baseline(s, p))
    assert online == offline
    k_det = res.k_life + p.n_tau - 1
    assert offline[-1].last_slot < k_det <= offline[-1].last_slot + p.n_ss
    assert [f.last_slot for f in online if f.warning] == [expected(name)["warn_slot"]]
    if name == "v6_prior":
        assert all(f.p_end is not None and f.e10 <= f.e50 <= f.e90 for f in online)
        assert [f.p_end for f in online] == sorted(f.p_end for f in online)   # P grows with t
