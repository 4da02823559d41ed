"""METHOD.md §7a: where a new test's life prior comes from (pure), the records reader that feeds
it, and the configuration's `forecast:` section and `method:` prior."""
import json
import logging
import os
import statistics
import textwrap

import pytest

from gateway.config import ConfigError, load_station
from gateway.core.method.prior import PastTest, PriorEntry, priors_by_group, resolve_prior
from gateway.offline.history import read_history

MINIMAL = "station: {id: s1}\nmeter: {port: /dev/a-meter}\nstm32: {port: /dev/a-stm32}\n"


def fails(grade, t_set, *lives, status="failure"):
    return [PastTest(grade, t_set, status, x) for x in lives]


def test_config_entry_first_then_history_of_at_least_three_failures_then_none():
    cfg = [PriorEntry("I", 0.5, 32306.9, 951.7, 5), PriorEntry("II", 0.5, 21643.5, 120.6)]
    hist = (fails("I", 0.5, 30000, 31000, 32000) + fails("II", 0.3, 100, 110, 120)
            + fails("II", 0.3, 500, status="no_failure") + fails("II", 0.3, 9000, status="aborted"))
    p = resolve_prior(cfg, hist, "I", 0.5)
    assert (p.mean, p.sd, p.source, p.n) == (32306.9, 951.7, "config", 5)
    assert resolve_prior(cfg, hist, "II", 0.5005).source == "config"      # ±0.001 N
    # history: mean and sample SD (n − 1) of the failures only
    p = resolve_prior(cfg, hist, "II", 0.3)
    assert (p.source, p.n) == ("history", 3)
    assert p.mean == pytest.approx(110.0) and p.sd == pytest.approx(statistics.stdev([100, 110, 120]))
    assert resolve_prior([], hist, "II", 0.3009).n == 3 and resolve_prior([], hist, "II", 0.302).source is None
    # fewer than three failures (the others ended otherwise): none
    hist2 = fails("I", 0.7, 100, 200) + fails("I", 0.7, 300, status="no_failure")
    p = resolve_prior([], hist2, "I", 0.7)
    assert (p.mean, p.sd, p.source, p.n) == (None, None, None, None)


def test_history_sd_is_at_least_two_percent_of_the_mean():
    p = resolve_prior([], fails("I", 0.5, 1000.0, 1000.0, 1001.0), "I", 0.5)
    assert p.sd == pytest.approx(0.02 * p.mean) and p.source == "history"


def test_a_fixed_method_prior_wins_and_a_test_without_grade_gets_only_that():
    cfg = [PriorEntry("I", 0.5, 32306.9, 951.7)]
    p = resolve_prior(cfg, fails("I", 0.5, 1, 2, 3), "I", 0.5, fixed=(5000.0, 50.0))
    assert (p.mean, p.sd, p.source) == (5000.0, 50.0, "config")
    assert resolve_prior(cfg, fails(None, 0.5, 1, 2, 3), None, 0.5).source is None
    assert resolve_prior(cfg, [], None, 0.5, fixed=(5000.0, 50.0)).mean == 5000.0
    assert resolve_prior(cfg, [], "I", 0.5).sidecar() == {
        "prior_mean": 32306.9, "prior_sd": 951.7, "prior_source": "config", "prior_n": None,
        "prior_n_censored": None, "prior_n_early": None}


def test_priors_by_group_in_the_configuration_form():
    hist = (fails("II", 0.5, 21500, 21700, 21730) + fails("I", 0.5, 31000, 32000, 33000, 33500)
            + fails("I", 0.7, 1, 2) + fails("I", 0.5, 10, status="aborted"))
    got = priors_by_group(hist)
    assert [(e.grade, e.t_set, e.n) for e in got] == [("I", 0.5, 4), ("II", 0.5, 3)]
    assert got[0].mean == pytest.approx(statistics.mean([31000, 32000, 33000, 33500]))
    assert got[0].as_config() == {"grade": "I", "t_set_n": 0.5, "mean_s": got[0].mean,
                                  "sd_s": got[0].sd, "n": 4, "n_censored": 0, "n_early": 0}


def _result(d, grade, t_set, status, t_life):
    os.makedirs(d, exist_ok=True)
    with open(os.path.join(d, "result.json"), "w") as f:
        json.dump({"grade": grade, "t_set": t_set, "test_status": "completed",
                   "method": {"status": status, "t_life": t_life}}, f)


def test_reader_scans_a_station_folder_and_skips_damaged_results_with_one_line(tmp_path, caplog):
    st = tmp_path / "records" / "loom-01"
    for i, life in enumerate((30000, 31000, 32000)):
        _result(str(st / f"2026010{i}T000000Z-S-{i}"), "I", 0.5, "failure", life)
    _result(str(st / "20260105T000000Z-S-x"), "I", 0.5, "no_failure", None)
    bad = st / "20260106T000000Z-S-bad"
    bad.mkdir()
    (bad / "result.json").write_text('{"method": {"status": "fail')          # cut off
    (st / "20260107T000000Z-S-list").mkdir()
    (st / "20260107T000000Z-S-list" / "result.json").write_text("[1, 2]")  # not a result
    (st / "20260108T000000Z-S-running").mkdir()                             # no result yet
    with caplog.at_level(logging.WARNING, logger="gateway.offline.history"):
        hist = read_history(str(st))
    assert len(hist) == 4
    lines = [r for r in caplog.records if "damaged" in r.getMessage()]
    assert len(lines) == 1 and "2 damaged result file(s)" in lines[0].getMessage()
    p = resolve_prior([], hist, "I", 0.5)
    assert (p.source, p.n, p.mean) == ("history", 3, 31000.0)
    # the records root (station folders below it) works too, and a missing folder is empty
    assert len(read_history(str(tmp_path / "records"))) == 4
    assert read_history(str(tmp_path / "nope")) == []
    assert len(read_history(str(st), max_files=3)) == 1     # the newest three: two damaged


def write(path, text):
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(textwrap.dedent(text))
    return str(path)


def test_forecast_section_and_method_prior_in_a_station_file(tmp_path):
    cfg = load_station(write(tmp_path / "s.yaml", MINIMAL + """\
forecast:
  priors:
    - {grade: I, t_set_n: 0.5, mean_s: 32306.9, sd_s: 951.7, n: 5}
    - {grade: II, t_set_n: 0.5, mean_s: 21643.5, sd_s: 120.6}
method: {lead: 7200, p_due: 0.2}
"""))
    assert cfg.forecast.priors == (PriorEntry("I", 0.5, 32306.9, 951.7, 5), PriorEntry("II", 0.5, 21643.5, 120.6))
    assert (cfg.method["lead"], cfg.method["p_due"], cfg.method["prior_mean"]) == (7200.0, 0.2, None)
    assert load_station(write(tmp_path / "d.yaml", MINIMAL)).forecast.priors == ()
    cfg = load_station(write(tmp_path / "m.yaml", MINIMAL + "method: {prior_mean: 5000, prior_sd: 50}\n"))
    assert (cfg.method["prior_mean"], cfg.method["prior_sd"]) == (5000.0, 50.0)


@pytest.mark.parametrize("text,words", [
    ("forecast: {priors: [{grade: III, t_set_n: 0.5, mean_s: 100, sd_s: 5}]}",
     "forecast.priors: entry 1: grade 'III' is not one of the grades"),
    ("forecast: {priors: [{grade: I, t_set_n: 0.5, mean_s: 100, sd_s: 0}]}",
     "forecast.priors: .*entry 1 \\(grade I\\): sd_s 0 is impossible; allowed: > 0"),
    ("forecast: {priors: [{grade: I, t_set_n: 0.5, mean_s: 100, sd_s: -3}]}", "sd_s -3 is impossible"),
    ("forecast: {priors: [{grade: I, t_set_n: 0.5, mean_s: 100}]}", "entry 1: sd_s is missing"),
    ("forecast: {priors: [{grade: I, t_set_n: 0.5, mean_s: 100, sd_s: 5, sd: 3}]}", "unknown key 'sd'"),
    ("forecast: {priors: [{grade: I, t_set_n: 0.5, mean_s: 100, sd_s: 5}, "
     "{grade: I, t_set_n: 0.5004, mean_s: 90, sd_s: 5}]}", "entry 2: grade I at 0.5004 N is given twice"),
    ("forecast: {priors: {grade: I}}", "forecast.priors: a mapping is not allowed"),
    ("method: {prior_mean: 5000, prior_sd: 0}", "method.prior_sd: 0.0 is impossible"),
    ("method: {prior_mean: 5000}", "method.prior_mean: prior_mean without prior_sd; a life prior needs both"),
    ("method: {lead: -1}", "method.lead: -1.0 is impossible"),
    ("method: {p_due: 1.0}", "method.p_due: 1.0 is impossible; allowed: 0 < p_due < 1"),
])
def test_bad_priors_are_clear_validation_errors(tmp_path, text, words):
    with pytest.raises(ConfigError, match=words):
        load_station(write(tmp_path / "s.yaml", MINIMAL + text + "\n"))


def test_sidecar_prior_reads_the_new_keys_leniently():
    from gateway.offline.logio import sidecar_prior
    meta = {"method": {"t_set": 0.5, "prior_mean": 3300.0, "prior_sd": 150}, "prior_source": "history",
            "prior_n": 4}
    p = sidecar_prior(meta)
    assert (p.mean, p.sd, p.source, p.n) == (3300.0, 150.0, "history", 4)
    for bad in ({"prior_sd": 0}, {"prior_sd": -1}, {"prior_sd": None}, {"prior_mean": "x"},
                {"prior_mean": float("nan")}, {"prior_sd": True}):
        m = {**meta, "method": {**meta["method"], **bad}}
        assert sidecar_prior(m).mean is None and sidecar_prior(m).source is None
    assert sidecar_prior({}).mean is None and sidecar_prior({"method": "junk"}).mean is None
    q = sidecar_prior({**meta, "prior_source": "guess", "prior_n": -2})
    assert (q.mean, q.source, q.n) == (3300.0, None, None)


def test_too_many_prior_entries_is_a_validation_error(tmp_path):
    from gateway.config import sections as S
    entries = ", ".join(f"{{grade: I, t_set_n: {0.1 + 0.01 * i:.2f}, mean_s: 100, sd_s: 5}}"
                        for i in range(S.MAX_PRIOR_ENTRIES + 1))
    with pytest.raises(ConfigError, match=f"{S.MAX_PRIOR_ENTRIES + 1} entries; at most {S.MAX_PRIOR_ENTRIES}"):
        load_station(write(tmp_path / "s.yaml", MINIMAL + f"forecast: {{priors: [{entries}]}}\n"))


def test_reader_gives_the_censored_lives_their_ts_from_the_result_or_the_sidecar(tmp_path):
    st = tmp_path / "records" / "loom-01"
    for i, life in enumerate((2917.92, 3064.34, 3215.14, 3363.06)):
        _result(str(st / f"2026010{i}T000000Z-S-{i}"), "I", 0.5, "failure", life)

    def ended(name, method, ts=None, sidecar_ts=None):
        d = st / name
        d.mkdir(parents=True)
        res = {"test_id": name, "station": "loom-01", "grade": "I", "t_set": 0.5,
               "method": {"k_b": 40000, **method}}
        if ts is not None:
            res["ts"] = ts
        (d / "result.json").write_text(json.dumps(res))
        if sidecar_ts is not None:
            (d / "log.meta.yaml").write_text(f"method: {{t_set: 0.5, ts: {sidecar_ts}}}\n")
    # replaced early (STOPPED) with ts in the result; stopped and at t_end from before `ts` was
    # written (the sidecar says it); a protection stop and a test without baseline: not censored
    ended("20260110T000000Z-S-a", {"status": "aborted", "stop_reasons": ["STOPPED"],
                                   "n_slots": 130000, "t_life": None}, ts=0.02)
    ended("20260111T000000Z-S-b", {"status": "aborted", "stop_reasons": ["STOPPED"],
                                   "n_slots": 145000}, sidecar_ts=0.02)
    ended("20260112T000000Z-S-c", {"status": "no_failure", "n_slots": 150000}, sidecar_ts=0.02)
    ended("20260113T000000Z-S-d", {"status": "aborted", "stop_reasons": ["MISSING"],
                                   "n_slots": 100051}, ts=0.02)
    ended("20260114T000000Z-S-e", {"status": "no_baseline", "k_b": None, "n_slots": 9000}, ts=0.02)
    hist = read_history(str(st))
    assert len(hist) == 9
    a = [t for t in hist if t.test_id == "20260110T000000Z-S-a"][0]
    assert (a.station, a.k_b, a.stop_reasons, a.n_slots, a.ts) == ("loom-01", 40000, ("STOPPED",), 130000, 0.02)
    assert sorted(t.life()[1] for t in hist if t.life() and t.life()[0] == "censored") == [2600.0, 2900.0, 3000.0]
    p = resolve_prior([], hist, "I", 0.5)
    assert (p.source, p.n, p.n_censored) == ("history", 4, 3)
    assert p.mean == pytest.approx(3156.10905968845, rel=1e-10)
    assert p.sd == pytest.approx(182.25402648037655, rel=1e-10)


def test_a_forged_sampling_period_gives_no_huge_censored_life():
    """A result.json whose ``ts`` (or ``n_slots``) is forged must not carry a censored life beyond
    10 years into the §7a fit (the observed lives are bounded the same way by the reader)."""
    from gateway.core.method.params import TEN_YEARS
    from gateway.core.method.prior import CENSORED, PastTest
    ok = PastTest(grade="I", t_set=0.5, status="no_failure", t_life=None, k_b=10, n_slots=150_000,
                  ts=0.02)
    assert ok.life() == (CENSORED, 3000.0)
    forged = PastTest(grade="I", t_set=0.5, status="no_failure", t_life=None, k_b=10,
                      n_slots=150_000, ts=1e300)
    assert forged.life() is None
    edge = PastTest(grade="I", t_set=0.5, status="failure", t_life=TEN_YEARS * 1.5, k_b=10,
                    n_slots=1, ts=0.02)
    assert edge.life() is None
