"""Statistics across tests (METHOD.md §7) against the paper's printed Tables 3–6."""
import csv
import io
import os
import random
from fractions import Fraction

import pytest

from conftest import TESTS
from gateway.offline.report import stats as S
from gateway.offline.report import tables as T
from gateway.offline.report.campaign import DELTA_FACTORS, WearTable
from gateway.offline.report.render import table_csv

PAPER = os.path.join(TESTS, "paper")


def _rows(name):
    with open(os.path.join(PAPER, name), encoding="utf-8") as f:
        return list(csv.DictReader(f))


def _paper_samples():
    """Table 3 as report samples (status failure, t_life and μ_ss as printed)."""
    out = []
    for r in _rows("table3_online_wear_life.csv"):
        res = {"status": "failure", "t_life": float(r["t_life_s"]), "mu_ss": float(r["mu_ss"]),
               "n_valid": 1, "n_slots": 1}
        out.append(T.Sample(r["sample_id"], r["grade"], float(r["t_set_N"]),
                            float(r["t_end_h"]) * 3600, r["sample_id"] + ".csv.gz", "failure",
                            {f: dict(res) for f in DELTA_FACTORS}, delta0=0.25))
    return out


def test_table3_gives_table4_to_the_printed_digits():
    groups = {}
    for r in _rows("table3_online_wear_life.csv"):
        groups.setdefault((r["t_set_N"], r["grade"]), []).append(float(r["t_life_s"]))
    for r in _rows("table4_summary.csv"):
        st = S.group_stats(groups[(r["t_set_N"], r["grade"])]).rounded()
        assert f"{st.mean:.1f}" == r["t_life_avg_s"], r
        assert f"{st.sd:.1f}" == r["sd_s"], r
        assert f"{st.cv:.2f}" == r["cv_pct"], r
    # the reference figures quoted in METHOD.md §7
    st = S.group_stats(groups[("0.5", "I")]).rounded()
    assert (st.mean, st.sd, st.cv) == (32306.9, 951.7, 2.95)


def test_table4_csv_from_the_report_code_equals_the_paper():
    """The same path the report takes (samples → Table 4 → CSV) prints the paper's Table 4."""
    t4 = T.table4(_paper_samples())
    got = list(csv.DictReader(io.StringIO(table_csv(t4))))
    want = _rows("table4_summary.csv")
    assert len(got) == len(want) == 6
    for g, w in zip(got, want):
        for k in ("grade", "t_life_avg_s", "sd_s", "cv_pct", "ranking"):
            assert g[k] == w[k], (k, g, w)
        assert float(g["t_set_N"]) == float(w["t_set_N"])
        assert g["n"] == "3"
    assert {r["ranking"] for r in got} == {"I > II"}
    assert not t4.notes


def test_table5_change_column_from_its_means():
    rows = _rows("table5_sensitivity.csv")
    ref = {(r["t_set_N"], r["grade"]): float(r["t_life_avg_s"]) for r in rows if r["delta"] == "delta0"}
    for r in rows:
        ch = S.change_pct(float(r["t_life_avg_s"]), ref[(r["t_set_N"], r["grade"])])
        assert f"{S.round_half_up(ch, 2):.2f}" == f"{float(r['change_vs_delta0_pct']):.2f}", r
    # and the ranking is kept at every δ
    for f in ("0.9*delta0", "delta0", "1.1*delta0"):
        means = {r["grade"]: float(r["t_life_avg_s"]) for r in rows if r["delta"] == f}
        assert S.ranking(means) == "I > II"


def test_table5_from_samples_keeps_ranking_and_zero_change_at_delta0():
    samples = _paper_samples()
    for s in samples:  # a δ-dependent life: ±0.3 % for ±10 % δ
        for f in DELTA_FACTORS:
            s.results[f]["t_life"] = s.results[1.0]["t_life"] * (1 + 0.03 * (f - 1.0))
    t5, per = T.table5(samples, DELTA_FACTORS)
    assert len(t5.rows) == 3 * 3 * 2 and len(per.rows) == 18
    for r in t5.rows:
        assert r["ranking"] == "I > II" and r["ranking_kept"] is True
        if r["factor"] == 1.0:
            assert r["change_vs_delta0_pct"] == 0.0
        else:
            assert r["change_vs_delta0_pct"] == pytest.approx(3.0 * (r["factor"] - 1.0), abs=0.006)
    t4 = {(r["t_set_N"], r["grade"]): r["t_life_avg_s"] for r in T.table4(samples).rows}
    for r in t5.rows:
        if r["factor"] == 1.0:
            assert r["t_life_avg_s"] == t4[(r["t_set_N"], r["grade"])]


def test_table5_leaves_out_a_sample_that_does_not_fail_at_every_delta():
    samples = _paper_samples()
    s = samples[0]
    s.results[1.1] = {"status": "no_failure", "t_life": None}
    t5, per = T.table5(samples, DELTA_FACTORS)
    r = next(r for r in t5.rows if r["t_set_N"] == s.t_set and r["grade"] == s.grade and r["factor"] == 1.0)
    assert r["n"] == 2
    assert any(s.sample_id in n and "no_failure" in n for n in t5.notes)


def test_table6_spearman_as_printed():
    rows = _rows("table6_offline_wear.csv")
    life = [float(r["t_life_s"]) for r in rows]
    rho3 = S.spearman(life, [float(r["dw3_um"]) for r in rows])
    rho1 = S.spearman(life, [float(r["dw1_um"]) for r in rows])
    assert rho3 == pytest.approx(-29 / 35, abs=1e-12)
    assert rho1 == pytest.approx(-27 / 35, abs=1e-12)
    assert f"{S.round_half_up(rho3, 3):.3f}" == "-0.829"
    assert f"{S.round_half_up(rho1, 3):.3f}" == "-0.771"
    # exact: no ties in these columns, so ρ = 1 − 6 Σd² / (n (n² − 1)) with rational ranks
    ranks_l = S.average_ranks(life)
    ranks_w = S.average_ranks([float(r["dw3_um"]) for r in rows])
    d2 = sum((Fraction(a) - Fraction(b)) ** 2 for a, b in zip(ranks_l, ranks_w))
    assert 1 - Fraction(6) * d2 / (6 * 35) == Fraction(-29, 35)


def test_table6_through_the_report_tables_with_expected_sign():
    rows = _rows("table6_offline_wear.csv")
    samples = [s for s in _paper_samples() if s.t_set == 0.5]
    cols = ["dw1_um", "dw21_um", "dw22_um", "dw23_um", "dw3_um"]
    wear = WearTable("wear.csv", cols, {r["sample_id"]: {c: float(r[c]) for c in cols} for r in rows},
                     [r["sample_id"] for r in rows], {c: 1 for c in cols})
    joined, corr = T.table6(samples, wear)
    assert [r["sample_id"] for r in joined.rows] == [r["sample_id"] for r in rows]
    by = {r["indicator"]: r for r in corr.rows}
    assert set(by) == set(cols)                   # one setpoint: pooled scope only
    assert by["dw3_um"]["rho"] == pytest.approx(-29 / 35) and by["dw3_um"]["agrees"] is True
    assert by["dw1_um"]["rho"] == pytest.approx(-27 / 35) and by["dw1_um"]["agrees"] is True
    assert by["dw22_um"]["rho"] > 0 and by["dw22_um"]["agrees"] is False   # the paper's Δw22: +1/35
    assert by["dw22_um"]["rho"] == pytest.approx(1 / 35)
    assert T.pretty_indicator("dw3_um") == "Δw3 (µm)"


def test_spearman_with_ties_matches_scipy():
    from scipy.stats import spearmanr

    rnd = random.Random(5)
    for _ in range(200):
        n = rnd.randint(3, 25)
        x = [rnd.choice([1.0, 2.0, 2.5, 3.0, 4.0, 7.0]) for _ in range(n)]
        y = [rnd.choice([0.1, 0.2, 0.2, 0.5, 0.9]) for _ in range(n)]
        got = S.spearman(x, y)
        if len(set(x)) == 1 or len(set(y)) == 1:
            assert got is None
            continue
        assert got == pytest.approx(spearmanr(x, y).statistic, abs=1e-12)


def test_average_ranks_ties():
    assert S.average_ranks([10, 20, 20, 5]) == [2.0, 3.5, 3.5, 1.0]
    assert S.average_ranks([1, 1, 1]) == [2.0, 2.0, 2.0]
    assert S.spearman([1, 2], [2, 1]) is None       # fewer than three pairs


def test_sd_cv_edge_cases():
    assert S.sample_sd([5.0]) is None
    st = S.group_stats([5.0]).rounded()
    assert (st.n, st.mean, st.sd, st.cv) == (1, 5.0, None, None)
    assert S.group_stats([]).mean is None
    assert S.sample_sd([1.0, 2.0, 3.0, 4.0]) == pytest.approx(1.2909944487358056)


def test_round_half_up_on_the_printed_decimal():
    assert S.round_half_up(0.125, 2) == 0.13       # round() gives 0.12
    assert S.round_half_up(2.675, 2) == 2.68       # binary 2.67499… but printed 2.675
    assert S.round_half_up(-0.255, 2) == -0.26
    assert S.round_half_up(None, 1) is None
    assert S.round_half_up(float("nan"), 1) is None


def test_ranking_order_and_ties():
    assert S.ranking({"II": 100.0, "I": 200.0}) == "I > II"
    assert S.ranking({"I": 100.0, "II": 200.0}) == "II > I"
    assert S.ranking({"I": 100.04, "II": 100.0, "III": 50.0}) == "I = II > III"
    assert S.ranking({"I": None, "II": 3.0}) == "II"
    assert S.ranking({}) == ""
    assert sorted(["X", "II", "IV", "I", "III", "B", "10", "2"], key=S.grade_sort_key) == \
        ["I", "II", "III", "IV", "X", "2", "10", "B"]
