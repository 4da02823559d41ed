"""Reports and METHOD.md §5b/§7a: Table 3's warning lead and reasons, the prognosis table (warned
at least `lead` ahead; t_life inside [e10, e90] at half-life) and `--priors FILE` in the
configuration's `forecast:` form — through `hookwatch report` on three failure vectors."""
import csv
import os
import shutil
import statistics
import subprocess

import pytest
import yaml
from scipy.special import ndtr, ndtri

from conftest import VECTORS, hookwatch_cmd
from gateway.config import load_station
from gateway.core.method.prior import PriorEntry

MINIMAL = "station: {id: s1}\nmeter: {port: /dev/a-meter}\nstm32: {port: /dev/a-stm32}\n"
LIVES = {"v1_failure": 3318.48, "v2_faults": 3506.1, "v6_prior": 3310.84}


@pytest.fixture(scope="module")
def report(tmp_path_factory):
    camp = tmp_path_factory.mktemp("campaign")
    for name in LIVES:
        shutil.copy(os.path.join(VECTORS, name + ".csv.gz"), camp)
        with open(os.path.join(VECTORS, name + ".meta.yaml"), encoding="utf-8") as f:
            meta = f.read().replace("grade: null", "grade: I")
        (camp / (name + ".meta.yaml")).write_text(meta, encoding="utf-8")
    out = tmp_path_factory.mktemp("out") / "r"
    priors = out.parent / "priors.yaml"
    p = subprocess.run(hookwatch_cmd() + ["report", str(camp), "--out", str(out), "-q", "-j", "1",
                                          "--no-figures", "--priors", str(priors)],
                       capture_output=True, text=True, timeout=300)
    assert p.returncode == 0, p.stderr
    assert f"priors: {priors} (1 grade/T_set group(s) with at least 3 wear-out failures)" in p.stdout
    return out, priors


def rows(path):
    with open(path, newline="", encoding="utf-8") as f:
        return list(csv.DictReader(f))


def test_table3_warning_lead_and_reasons(report):
    t3 = {r["sample_id"]: r for r in rows(report[0] / "table3_samples.csv")}
    v6 = t3["v6_prior"]
    assert float(v6["warn_s"]) == pytest.approx(2520.0)
    assert float(v6["warn_lead_s"]) == pytest.approx(3310.84 - 2520.0) and v6["warn_reasons"] == "prior"
    assert float(t3["v2_faults"]["warn_lead_s"]) == pytest.approx(3506.1 - 3030.0)


def test_prognosis_counts_warnings_a_lead_ahead_and_the_half_life_band(report):
    tp = rows(report[0] / "table_prognosis.csv")
    assert [r["grade"] for r in tp] == ["I", "all"]
    g = tp[0]
    # v6 (lead 600 s) warned 790.84 s ahead; v1 and v2 (default lead 3600 s) 408 and 476 s ahead
    assert (g["n"], g["warned"], g["warned_lead"], g["late"]) == ("3", "3", "1", "0")
    assert float(g["warned_lead_pct"]) == pytest.approx(100 / 3, abs=0.05)
    # only v6 has a prior: at 1650 s (the last window end before 3310.84 / 2) the band is about
    # m ± 1.28 s = [3108, 3492]: t_life inside
    assert (g["with_prior"], g["in_band"], float(g["in_band_pct"])) == ("1", "1", 100.0)
    surv = 1 - ndtr((1650.0 - 3300.0) / 150.0)
    e10, e90 = (3300 + 150 * ndtri(1 - surv * (1 - q)) for q in (0.1, 0.9))
    assert e10 < LIVES["v6_prior"] < e90
    md = (report[0] / "report.md").read_text(encoding="utf-8")
    assert "Prognosis" in md and "warned ≥ lead ahead" in md


def test_priors_file_is_the_configurations_forecast_section(report, tmp_path):
    text = report[1].read_text(encoding="utf-8")
    doc = yaml.safe_load(text)
    (e,) = doc["forecast"]["priors"]
    lives = list(LIVES.values())
    assert (e["grade"], e["t_set_n"], e["n"], e["n_censored"], e["n_early"]) == ("I", 0.5, 3, 0, 0)
    # no censored lives: the failures' mean and sample SD (to the file's 1e-6 s)
    assert e["mean_s"] == round(statistics.mean(lives), 6)
    assert e["sd_s"] == round(max(statistics.stdev(lives), 0.02 * statistics.mean(lives)), 6)
    # a station file takes it as it is
    st = tmp_path / "s.yaml"
    st.write_text(MINIMAL + text, encoding="utf-8")
    cfg = load_station(str(st))
    assert cfg.forecast.priors == (PriorEntry("I", 0.5, e["mean_s"], e["sd_s"], 3, 0, 0),)
