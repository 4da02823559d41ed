"""METHOD.md §7a through the CLI: `hookwatch report CAMPAIGN --priors FILE` on the public campaign
(tests/vectors/campaigns/, copied from ../shared/vectors/campaigns), compared as
../shared/tools/check_priors.py compares it: every (grade, T_set) group with grade, T_set within
0.001 N, `n` (wear-out failures), `n_censored` and `n_early` (METHOD.md §7a v3) exact, mean and SD
to 1e-6 relative; a group without a prior absent.
And the file's comment names the campaign folder escaped: a newline in the folder's name cannot
inject YAML (issue 27 item 4)."""
import glob
import json
import os
import shutil
import subprocess

import pytest
import yaml

from conftest import VECTORS, hookwatch_cmd
from gateway.config import load_station
from gateway.core.method.prior import wear_out_prior

CAMPAIGNS = os.path.join(VECTORS, "campaigns")
NAMES = sorted(os.path.basename(p)[: -len(".expected_priors.json")]
               for p in glob.glob(os.path.join(CAMPAIGNS, "*.expected_priors.json")))
MINIMAL = "station: {id: s1}\nmeter: {port: /dev/a-meter}\nstm32: {port: /dev/a-stm32}\n"


def run_priors(camp, tmp_path):
    pf = tmp_path / "priors.yaml"
    p = subprocess.run(hookwatch_cmd() + ["report", str(camp), "--out", str(tmp_path / "rep"),
                                          "--priors", str(pf), "--no-figures", "-q"],
                       capture_output=True, text=True, timeout=600)
    assert p.returncode == 0, p.stderr
    return pf.read_text(encoding="utf-8")


def compare(got, expected):
    """check_priors.py's rule; returns the list of differences."""
    errs, used = [], set()
    for g in expected:
        match = [i for i, e in enumerate(got) if e.get("grade") == g["grade"]
                 and abs(float(e["t_set_n"]) - g["t_set"]) <= 0.001 + 1e-12]
        if g["prior"] is None:
            errs += [f"{g['grade']}: unexpected {got[i]}" for i in match]
            continue
        if len(match) != 1:
            errs.append(f"{g['grade']} @ {g['t_set']}: {len(match)} entries")
            continue
        e, p = got[match[0]], g["prior"]
        used.add(match[0])
        for k in ("mean_s", "sd_s"):
            if not abs(e[k] - p[k]) <= 1e-6 * abs(p[k]):
                errs.append(f"{g['grade']}: {k} {e[k]} != {p[k]}")
        for k in ("n", "n_censored", "n_early"):
            if e.get(k) != p[k]:
                errs.append(f"{g['grade']}: {k} {e.get(k)} != {p[k]}")
    errs += [f"extra {got[i]}" for i in range(len(got)) if i not in used]
    return errs


@pytest.mark.parametrize("name", NAMES)
def test_public_campaign_priors_through_the_cli(name, tmp_path):
    with open(os.path.join(CAMPAIGNS, name + ".expected_priors.json"), encoding="utf-8") as f:
        expected = json.load(f)
    text = run_priors(os.path.join(CAMPAIGNS, name), tmp_path)
    got = yaml.safe_load(text)["forecast"]["priors"]
    assert compare(got, expected) == []
    # the campaign has censored lives in grade I: a failures-only prior would differ; and an early
    # failure (I-09): counted as a wear-out failure (§7a v2) it would widen the prior
    assert any(g["prior"] and g["prior"]["n_censored"] for g in expected)
    assert any(g["prior"] and g["prior"]["n_early"] for g in expected)
    for g in expected:
        if g["prior"] and g["prior"]["n_early"]:
            xs = [lf[1] for *_, lf in g["tests"] if lf and lf[0] == "failure"]
            cs = [lf[1] for *_, lf in g["tests"] if lf and lf[0] == "censored"]
            v2 = wear_out_prior(xs, cs)
            assert v2[1] > 2 * g["prior"]["sd_s"] and v2[0] < g["prior"]["mean_s"]
    # and a station file takes the section as it is (n, n_censored and n_early included)
    st = tmp_path / "s.yaml"
    st.write_text(MINIMAL + text, encoding="utf-8")
    cfg = load_station(str(st))
    assert [(e.grade, e.n, e.n_censored, e.n_early) for e in cfg.forecast.priors] == [
        (e["grade"], e["n"], e["n_censored"], e["n_early"]) for e in got]


def test_the_campaign_folder_in_the_comment_cannot_inject_yaml(tmp_path):
    camp = tmp_path / "plant\nforecast: {priors: []}\n# x"
    camp.mkdir()
    for name in ("II-01", "II-02", "II-03"):                 # grade II: three failures
        for ext in (".csv.gz", ".meta.yaml"):
            shutil.copy(os.path.join(CAMPAIGNS, "c1_campaign", name + ext), camp)
    text = run_priors(camp, tmp_path)
    head = [ln for ln in text.splitlines() if ln.startswith("#")]
    assert len(head) == 2 and "\\nforecast: {priors: []}\\n# x" in head[0]
    doc = yaml.safe_load(text)
    (e,) = doc["forecast"]["priors"]             # the injected `forecast: {priors: []}` is not there
    assert (e["grade"], e["n"], e["n_censored"], e["n_early"]) == ("II", 3, 0, 0)
