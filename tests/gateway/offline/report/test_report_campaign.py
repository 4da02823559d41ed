"""`hookwatch report` over generated campaigns: every table and figure, both folder layouts,
the same result on one and on two processes."""
import csv
import io
import os
import subprocess
import sys

import pytest

from conftest import ROOT, hookwatch_cmd
from kit.images import png_info

sys.path.insert(0, os.path.join(ROOT, "bench"))
import gen_campaign as G  # noqa: E402

TABLES = ("table3_samples", "table4_summary", "table5_sensitivity", "table5_samples", "table6_wear",
          "table6_correlation", "samples_apart")


def read_csv(path):
    with open(path, encoding="utf-8") as f:
        return list(csv.DictReader(f))


@pytest.fixture(scope="module")
def paper_campaign(tmp_path_factory):
    """The paper's campaign at 100× compression (18 tests, wear table, Fig. 8 logs), reported
    once by the CLI on two processes."""
    camp = tmp_path_factory.mktemp("campaign")
    G.make_campaign(str(camp), compress=100)
    out = camp / "report"           # inside the campaign folder: must not be read as tests
    p = subprocess.run(hookwatch_cmd() + ["report", str(camp), "--out", str(out), "--jobs", "2"],
                       capture_output=True, text=True, timeout=300)
    assert p.returncode == 0, p.stderr
    return camp, out, p


def test_report_has_every_table_and_figure(paper_campaign):
    camp, out, p = paper_campaign
    assert "18 tests, 18 analysed, 18 in the statistics, 0 problem(s); 20 figures" in p.stdout
    assert "\r" not in p.stderr and p.stderr == ""        # no progress bar when not a terminal
    for t in TABLES:
        assert (out / f"{t}.csv").is_file(), t
    assert (out / "problems.txt").read_text() == ""
    md = (out / "report.md").read_text(encoding="utf-8")
    html = (out / "report.html").read_text(encoding="utf-8")
    for title in ("Table 3 — online wear life per sample", "Table 4 — summary per setpoint and grade",
                  "Table 5 — sensitivity to the threshold increment δ",
                  "Table 6 — offline wear with the online wear life",
                  "Rank correlation of t_life with each wear indicator", "Samples listed apart"):
        assert title in md and title in html, title
    figs = sorted(os.listdir(out / "figures"))
    assert len(figs) == 20
    assert "fig8_open_vs_closed_loop.png" in figs and "fig9_life_by_grade.png" in figs
    assert sum(f.startswith("fig7_") for f in figs) == 18
    for f in figs:
        assert f"(figures/{f})" in md and f'src="figures/{f}"' in html, f
        w, h, sd = png_info(out / "figures" / f)
        assert (w, h) == (1600, 1000) and sd > 10, f


def test_report_tables_match_the_campaign(paper_campaign):
    camp, out, _ = paper_campaign
    t3 = read_csv(out / "table3_samples.csv")
    assert len(t3) == 18 and {r["status"] for r in t3} == {"failure"}
    for r in t3:
        grade, t_set, life, mu_ss = G.PAPER_TABLE3[r["sample_id"]]
        assert r["grade"] == grade and float(r["t_set_N"]) == t_set
        assert float(r["t_life_s"]) == pytest.approx(life / 100, rel=0.01)   # compressed 100×
        assert float(r["mu_ss"]) == pytest.approx(mu_ss, abs=0.001)
        assert float(r["t_end_h"]) == 0.1
    t4 = read_csv(out / "table4_summary.csv")
    assert [(r["t_set_N"], r["grade"]) for r in t4] == [
        ("0.5", "I"), ("0.5", "II"), ("0.7", "I"), ("0.7", "II"), ("0.9", "I"), ("0.9", "II")]
    assert {r["ranking"] for r in t4} == {"I > II"} and {r["n"] for r in t4} == {"3"}
    t5 = read_csv(out / "table5_sensitivity.csv")
    assert len(t5) == 18 and {r["ranking_kept"] for r in t5} == {"yes"}
    for r in t5:   # lower δ: earlier end of life
        ch = float(r["change_vs_delta0_pct"])
        assert (ch < 0) if r["delta"] == "0.9*delta0" else (ch > 0) if r["delta"] == "1.1*delta0" else ch == 0
    corr = {(r["scope"], r["indicator"]): r for r in read_csv(out / "table6_correlation.csv")}
    # the 0.5 N samples carry the paper's wear values and its life order: the paper's ρ
    assert float(corr[("T_set 0.5 N", "dw3_um")]["rho"]) == pytest.approx(-29 / 35, abs=1e-6)
    assert float(corr[("T_set 0.5 N", "dw1_um")]["rho"]) == pytest.approx(-27 / 35, abs=1e-6)
    assert corr[("all samples", "dw3_um")]["agrees"] == "yes"
    assert read_csv(out / "samples_apart.csv") == []


def test_one_and_two_processes_give_the_same_tables(paper_campaign, tmp_path):
    from gateway.offline.report.pipeline import build_report

    camp, out, _ = paper_campaign
    for jobs in (1, 2):
        o = build_report(str(camp), str(tmp_path / f"j{jobs}"), jobs=jobs, progress=False, figures=False)
        assert o.n_analysed == 18 and not o.problems
        for t in TABLES:
            assert (tmp_path / f"j{jobs}" / f"{t}.csv").read_text() == (out / f"{t}.csv").read_text(), (jobs, t)


def test_gateway_layout_and_gateway_aborted_tests(tmp_path):
    camp = tmp_path / "records"
    kw = dict(t_end=120.0, run_in_s=10.0, method={"w_ss": 5, "w_hold": 20, "tau": 5})
    tests = [G.TestDef("A-1", "I", 0.5, life=90.0, **kw), G.TestDef("A-2", "I", 0.5, life=95.0, **kw),
             G.TestDef("B-1", "II", 0.5, life=60.0, **kw), G.TestDef("B-2", "II", 0.5, life=65.0, **kw),
             G.TestDef("B-3", "II", 0.5, life=70.0, abort_at=40.0, **kw)]
    logs = [G.write_test(str(camp), d, layout="gateway") for d in tests]
    assert all(lg.endswith(os.path.join("", "log.csv.gz")) for lg in logs)
    # the operator stopped A-2 after its end of life: the gateway closed it as aborted, but the
    # t_life found before stands (METHOD.md §3) and is averaged in
    res = os.path.join(os.path.dirname(logs[1]), "result.json")
    with open(res, "w") as f:
        f.write('{"test_status": "aborted", "end_reason": "stop command"}')
    # and B-4 was cut off by a gateway restart before its end of life: aborted, listed apart
    cut = G.TestDef("B-4", "II", 0.5, life=65.0, abort_at=30.0, **kw)
    logs.append(G.write_test(str(camp), cut, layout="gateway"))
    with open(os.path.join(os.path.dirname(logs[-1]), "result.json"), "w") as f:
        f.write('{"test_status": "aborted", "end_reason": "gateway restart"}')
    out = tmp_path / "rep"
    p = subprocess.run(hookwatch_cmd() + ["report", str(camp), "--out", str(out), "--quiet"],
                       capture_output=True, text=True, timeout=300)
    assert p.returncode == 0, p.stderr
    rows = {r["sample_id"]: r for r in read_csv(out / "table3_samples.csv")}
    assert set(rows) == {"A-1", "A-2", "B-1", "B-2", "B-3", "B-4"}
    assert rows["B-3"]["status"] == "aborted" and "protection stop" in rows["B-3"]["note"]
    assert rows["A-2"]["status"] == "failure"
    assert "stop command" in rows["A-2"]["note"] and "t_life stands" in rows["A-2"]["note"]
    apart = {r["sample_id"]: r for r in read_csv(out / "samples_apart.csv")}
    assert set(apart) == {"B-3", "B-4"} and rows["B-4"]["status"] == "aborted"
    assert "gateway restart" in rows["B-4"]["note"]
    t4 = {r["grade"]: r for r in read_csv(out / "table4_summary.csv")}
    assert t4["I"]["n"] == "2" and t4["I"]["ranking"] == "I > II"
    a = [float(rows[s]["t_life_s"]) for s in ("A-1", "A-2")]
    assert t4["I"]["t_life_avg_s"] == f"{sum(a) / 2:.1f}"


def test_progress_bar():
    from gateway.offline.report.campaign import Progress

    buf = io.StringIO()
    bar = Progress(3, "analysing", enabled=True, stream=buf)
    for _ in range(3):
        bar.advance()
    bar.close()
    text = buf.getvalue()
    assert "\r" in text and "3/3" in text and text.endswith("\n") and "#" * 30 in text
    quiet = io.StringIO()
    Progress(3, "x", stream=quiet).advance()          # StringIO is not a terminal: silent
    assert quiet.getvalue() == ""


def test_shipped_example_campaign_gives_a_full_report(tmp_path):
    example = os.path.join(ROOT, "docs", "example-campaign")
    size = sum(os.path.getsize(os.path.join(d, f)) for d, _, fs in os.walk(example) for f in fs)
    assert size < 4 << 20                              # a few MB at most
    out = tmp_path / "example-report"
    p = subprocess.run(hookwatch_cmd() + ["report", example, "--out", str(out)],
                       capture_output=True, text=True, timeout=300)
    assert p.returncode == 0, p.stderr
    assert "18 tests, 18 analysed, 18 in the statistics, 0 problem(s); 20 figures" in p.stdout
    t4 = read_csv(out / "table4_summary.csv")
    assert len(t4) == 6 and {r["ranking"] for r in t4} == {"I > II"}
    assert len(read_csv(out / "table6_wear.csv")) == 18
    assert (out / "figures" / "fig8_open_vs_closed_loop.png").is_file()
    # the example's priors (Table 4, compressed like the lives) warn every failure, never late
    tp = {(r["t_set_N"], r["grade"]): r for r in read_csv(out / "table_prognosis.csv")}
    assert len(tp) == 7 and (tp["", "all"]["n"], tp["", "all"]["warned"], tp["", "all"]["late"],
                             tp["", "all"]["with_prior"]) == ("18", "18", "0", "18")
    assert not [f for f in os.listdir(example) if f.startswith(".hookwatch")]   # nothing written there


def test_example_generator_samples_the_virtual_bench():
    """The shipped example's source: the plant under the gateway's controller, offline."""
    from gateway.core.method.core import analyze_readings
    from gateway.core.method.params import build_params

    t, t1, t2, truth = G.plant_run("II", 0.9, 7, 220.0, time_scale=100.0)
    assert 0.99 * 11000 < t.size < 11000                # ~0.2 % of the slots lost
    p = build_params({"t_set": 0.9, "t_end": 220.0, "w_ss": 10, "w_hold": 60, "tau": 10})
    r = analyze_readings(t, t1, t2, p)
    assert r.status == "failure"
    assert abs(r.t_life - truth["cross_run_s"]) < 5.0
    assert abs(((t1 + t2) / 2)[t > 10].mean() - 0.9) < 0.01    # the loop holds T_set
