"""Reports with METHOD.md §3 (STOPPED), §5a (headroom) and §5b (warning): Table 3's columns, the
samples listed apart, and Fig. 7's warning line and headroom windows — through `hookwatch report`
on two of the method vectors."""
import csv
import os
import shutil
import subprocess

import numpy as np
import pytest

from conftest import VECTORS, hookwatch_cmd


@pytest.fixture(scope="module")
def report(tmp_path_factory):
    camp = tmp_path_factory.mktemp("campaign")
    for name in ("v1_failure", "v5_stopped"):
        shutil.copy(os.path.join(VECTORS, name + ".csv.gz"), camp)
        with open(os.path.join(VECTORS, name + ".meta.yaml"), encoding="utf-8") as f:
            meta = f.read().replace("grade: null", "grade: I")
        (camp / (name + ".meta.yaml")).write_text(meta, encoding="utf-8")
    out = tmp_path_factory.mktemp("out") / "r"
    p = subprocess.run(hookwatch_cmd() + ["report", str(camp), "--out", str(out), "-q", "-j", "1"],
                       capture_output=True, text=True, timeout=300)
    assert p.returncode == 0, p.stderr
    return out


def rows(path):
    with open(path, newline="", encoding="utf-8") as f:
        return {r["sample_id"]: r for r in csv.DictReader(f)}


def test_table3_has_the_warning_time_and_the_last_headroom(report):
    t3 = rows(report / "table3_samples.csv")
    v1, v5 = t3["v1_failure"], t3["v5_stopped"]
    assert float(v1["warn_s"]) == pytest.approx((145499 + 1) * 0.02)       # METHOD.md §5b
    assert float(v1["warn_lead_s"]) == pytest.approx(3318.48 - 2910.0) and v1["warn_reasons"] == "trend"
    assert float(v1["headroom"]) == pytest.approx(-0.495569, abs=1e-6)
    assert v5["warn_s"] == "" and float(v5["headroom"]) == pytest.approx(0.986258, abs=1e-6)
    assert v5["warn_lead_s"] == "" and v5["warn_reasons"] == ""
    md = (report / "report.md").read_text(encoding="utf-8")
    assert "early warning (s)" in md and "last headroom" in md and "warning lead (s)" in md


def test_a_stopped_test_is_listed_apart_as_censored_not_as_a_missing_meter(report):
    t3 = rows(report / "table3_samples.csv")
    v5 = t3["v5_stopped"]
    assert v5["status"] == "aborted" and v5["t_life_s"] == ""
    assert "ended on purpose at 2,500.00 s (STOPPED)" in v5["note"] and "MISSING" not in v5["note"]
    apart = rows(report / "samples_apart.csv")
    assert set(apart) == {"v5_stopped"}
    assert apart["v5_stopped"]["reason"] == "aborted (STOPPED: ended on purpose before t_life)"
    with open(report / "table4_summary.csv", newline="", encoding="utf-8") as f:
        t4 = list(csv.DictReader(f))
    assert [r["n"] for r in t4] == ["1"]          # only v1 in the statistics


def _pixels(path, rgb, tol=12):
    import matplotlib.image as mpimg
    img = (mpimg.imread(str(path))[:, :, :3] * 255).astype(int)
    return np.all(np.abs(img - np.array(rgb)) <= tol, axis=2)


def test_fig7_marks_the_warning_and_draws_the_headroom_windows(report):
    pink = (0xE3, 0x77, 0xC2)     # early warning line and the windows under h_warn
    brown = (0x8C, 0x56, 0x4B)    # windows with headroom ≥ h_warn
    f1 = report / "figures" / "fig7_v1_failure.png"
    f5 = report / "figures" / "fig7_v5_stopped.png"
    p1, p5 = _pixels(f1, pink), _pixels(f5, pink)
    # a vertical pink line through both panels: one column with pink far down the figure
    cols = np.flatnonzero(p1[700:950].sum(axis=0) > 20)
    assert cols.size > 0
    # v1's windows under h_warn are pink segments; v5 has no warning and no pink segment (only
    # the thin dotted h_warn level)
    assert p1.sum() > 3 * p5.sum()
    assert _pixels(f5, brown).sum() > 500
