"""Bad campaign input: a clear warning naming the file, listed in the report's problems; the rest
of the report is still written. Exit 0 with warnings, 1 when nothing could be analysed, 2 for
usage errors."""
import csv
import os
import subprocess
import sys

import pytest

from conftest import ROOT, hookwatch_cmd
from gateway.plumbing.safeout import md_text

sys.path.insert(0, os.path.join(ROOT, "bench"))
import gen_campaign as G  # noqa: E402

KW = dict(t_end=120.0, run_in_s=10.0, method={"w_ss": 5, "w_hold": 20, "tau": 5})


def read_csv(path):
    with open(path, encoding="utf-8") as f:
        return list(csv.DictReader(f))


def report(camp, out, *extra):
    return subprocess.run(hookwatch_cmd() + ["report", str(camp), "--out", str(out), *extra],
                          capture_output=True, text=True, timeout=300)


@pytest.fixture(scope="module")
def messy(tmp_path_factory):
    camp = tmp_path_factory.mktemp("messy")
    good = [G.TestDef("I-1", "I", 0.5, life=95.0, **KW), G.TestDef("I-2", "I", 0.5, life=90.0, **KW),
            G.TestDef("II-1", "II", 0.5, life=60.0, **KW), G.TestDef("II-2", "II", 0.5, life=64.0, **KW),
            G.TestDef("I-3", "I", 0.7, life=80.0, **KW)]           # grade II missing at 0.7 N
    special = [G.TestDef("II-NF", "II", 0.5, life=None, **KW),      # no_failure
               G.TestDef("II-NB", "II", 0.5, life=60.0, mu_noise=0.02, **KW),   # no_baseline
               G.TestDef("II-AB", "II", 0.5, life=60.0, abort_at=35.0, **KW),   # aborted
               G.TestDef("NOGRADE", None, 0.5, life=70.0, **KW)]
    for d in good + special:
        G.write_test(str(camp), d)
    # the same sample twice
    G.write_test(str(camp / "again"), G.TestDef("I-1", "I", 0.5, life=99.0, **KW))
    # a log without sidecar
    G.write_log(str(camp / "orphan.csv.gz"), *G.synth(G.TestDef("X", "I", 0.5, life=60.0, **KW)))
    # an unreadable log (garbage) with a good sidecar
    (camp / "broken.csv.gz").write_bytes(b"\x1f\x8b\x08\x00garbage-not-gzip" * 10)
    (camp / "broken.meta.yaml").write_text("sample_id: BROKEN\ngrade: I\nt_set: 0.5\n")
    # a sidecar that is not YAML, and one without t_set
    G.write_log(str(camp / "badyaml.csv"), *G.synth(G.TestDef("Y", "I", 0.5, life=60.0, **KW)))
    (camp / "badyaml.meta.yaml").write_text("sample_id: [unclosed\n")
    G.write_log(str(camp / "noset.csv.gz"), *G.synth(G.TestDef("Z", "I", 0.5, life=60.0, **KW)))
    (camp / "noset.meta.yaml").write_text("sample_id: NOSET\ngrade: I\n")
    # wear: an unknown sample and a cell that is not a number
    rows = G.wear_rows(good + special)
    rows.append({**rows[0], "sample_id": "GHOST-01"})
    rows[1]["dw3_um"] = "n/a"
    G.write_wear(str(camp / "wear.csv"), rows)
    out = camp.parent / (camp.name + "-report")
    p = report(camp, out, "--jobs", "2")
    return camp, out, p


def test_exit_zero_and_a_warning_naming_each_bad_file(messy):
    camp, out, p = messy
    assert p.returncode == 0, p.stderr
    err = p.stderr
    warnings = [ln for ln in err.splitlines() if ln.startswith("hookwatch report: warning: ")]
    expect = {
        "orphan.csv.gz": "no sidecar orphan.meta.yaml",
        "NOGRADE.meta.yaml": "no grade",
        "wear.csv": "GHOST-01 is not a test of this campaign",
        "broken.csv.gz": "corrupt gzip",
        "badyaml.meta.yaml": "not valid YAML",
        "noset.meta.yaml": "t_set",
        os.path.join("again", "I-1.csv.gz"): "already recorded in I-1.csv.gz",
    }
    for f, msg in expect.items():
        assert any(f"warning: {f}:" in w and msg in w for w in warnings), (f, msg, err)
    assert any("wear.csv: line 3, column dw3_um: 'n/a' is not a number" in w for w in warnings), err
    assert any("T_set 0.7 N, grade II: no test in the campaign" in w for w in warnings), err
    problems = (out / "problems.txt").read_text(encoding="utf-8").splitlines()
    assert len(problems) == len(warnings)
    md = (out / "report.md").read_text(encoding="utf-8")
    html = (out / "report.html").read_text(encoding="utf-8")
    for line in problems:
        assert md_text(line) in md
    assert "orphan.csv.gz: no sidecar" in html


def test_the_rest_of_the_report_is_still_produced(messy):
    camp, out, p = messy
    t4 = {(r["t_set_N"], r["grade"]): r for r in read_csv(out / "table4_summary.csv")}
    assert t4[("0.5", "I")]["n"] == "2" and t4[("0.5", "II")]["n"] == "2"
    assert t4[("0.7", "I")]["n"] == "1" and t4[("0.7", "II")]["n"] == "0"
    assert t4[("0.5", "I")]["ranking"] == "I > II" and t4[("0.7", "I")]["ranking"] == "I"
    again = os.path.join("again", "I-1.csv.gz")
    t3 = {r["sample_id"]: r for r in read_csv(out / "table3_samples.csv") if r["log"] != again}
    assert t3["II-NF"]["status"] == "no_failure" and t3["II-NB"]["status"] == "no_baseline"
    assert t3["II-AB"]["status"] == "aborted" and t3["BROKEN"]["status"] == "error"
    apart = {}
    for r in read_csv(out / "samples_apart.csv"):
        apart.setdefault(r["sample_id"], []).append(r)
    assert {k: [r["reason"] for r in v] for k, v in apart.items()} == {
        "II-NF": ["no_failure"], "II-NB": ["no_baseline"], "II-AB": ["aborted"],
        "NOGRADE": ["no grade in the sidecar"], "BROKEN": ["log unreadable (see problems)"],
        "NOSET": ["method parameters unusable (see problems)"],
        "I-1": ["duplicate sample_id"]}
    # the listed-apart samples are in no mean: I at 0.5 N is the mean of I-1 and I-2 only
    i1, i2 = float(t3["I-1"]["t_life_s"]), float(t3["I-2"]["t_life_s"])
    assert float(t4[("0.5", "I")]["t_life_avg_s"]) == pytest.approx((i1 + i2) / 2, abs=0.05)
    wear = {r["sample_id"]: r for r in read_csv(out / "table6_wear.csv")}
    assert "GHOST-01" not in wear and wear["II-NF"]["t_life_s"] == ""
    corr = read_csv(out / "table6_correlation.csv")
    n = {r["indicator"]: int(r["n"]) for r in corr if r["scope"] == "all samples"}
    assert n["dw1_um"] == 5 and n["dw3_um"] == 4       # I-2's Δw3 was "n/a"
    figs = os.listdir(out / "figures")
    assert "fig9_life_by_grade.png" in figs and "fig7_II-NB.png" in figs
    assert "fig8_open_vs_closed_loop.png" not in figs
    assert "Fig. 8 (open loop vs closed loop) needs two comparison logs" in (out / "report.md").read_text()


def test_nothing_analysable_exits_1(tmp_path):
    camp = tmp_path / "c"
    G.write_log(str(camp / "orphan.csv.gz"), *G.synth(G.TestDef("X", "I", 0.5, life=60.0, **KW)))
    p = report(camp, tmp_path / "out")
    assert p.returncode == 1
    assert "orphan.csv.gz: no sidecar" in p.stderr and "no test could be analysed" in p.stderr
    assert "orphan.csv.gz" in (tmp_path / "out" / "problems.txt").read_text()
    assert (tmp_path / "out" / "report.html").is_file()
    empty = tmp_path / "empty"
    empty.mkdir()
    assert report(empty, tmp_path / "out2").returncode == 1


def test_usage_errors_exit_2(tmp_path):
    camp = tmp_path / "c"
    camp.mkdir()
    f = tmp_path / "file"
    f.write_text("x")
    cases = [
        ([str(tmp_path / "nope"), "--out", str(tmp_path / "o")], "not a folder"),
        ([str(camp), "--out", str(f)], "exists and is not a folder"),
        ([str(camp), "--out", str(tmp_path / "o"), "--jobs", "0"], "--jobs 0: must be at least 1"),
        ([str(camp), "--out", str(tmp_path / "o"), "--wear", str(tmp_path / "w.csv")], "no such file"),
        ([str(camp), "--out", str(tmp_path / "o"), "--set", "bogus=1"], "unknown parameter"),
        ([str(camp)], "--out"),
        ([str(camp), "--out", str(camp)], "is the campaign folder itself"),
    ]
    for args, msg in cases:
        p = subprocess.run(hookwatch_cmd() + ["report", *args], capture_output=True, text=True, timeout=60)
        assert p.returncode == 2, (args, p.stderr)
        assert msg in p.stderr, (args, p.stderr)
        assert "Traceback" not in p.stderr


def test_wear_table_without_sample_id_and_explicit_fig8_logs(tmp_path):
    camp = tmp_path / "c"
    for d in (G.TestDef("I-1", "I", 0.5, life=95.0, **KW), G.TestDef("II-1", "II", 0.5, life=60.0, **KW)):
        G.write_test(str(camp), d)
    (tmp_path / "w.csv").write_text("sample,grade\nI-1,I\n")        # no indicator column
    (tmp_path / "w2.csv").write_text("id,dw1\nI-1,3\n")              # no sample_id column
    op, cl = G.write_loop_logs(str(tmp_path / "loops"), duration=60.0)
    os.remove(cl[:-7] + ".meta.yaml")                                 # t_set from the open log
    p = report(camp, tmp_path / "o", "--wear", str(tmp_path / "w.csv"), "--open-loop", op,
               "--closed-loop", cl)
    assert p.returncode == 0, p.stderr
    assert "no numeric wear indicator column" in p.stderr
    assert (tmp_path / "o" / "figures" / "fig8_open_vs_closed_loop.png").is_file()
    p = report(camp, tmp_path / "o2", "--wear", str(tmp_path / "w2.csv"), "--no-figures")
    assert p.returncode == 0 and "no sample_id column" in p.stderr
    assert not os.listdir(tmp_path / "o2" / "figures")
