"""METHOD.md §3 (a test ended on purpose) and §5a (headroom, headroom runs, projection) on
hand-made slot sequences whose expected figures are computed here from the text of the spec.
The §5b forecast and early warning: test_method_forecast.py."""
import math
import os

import numpy as np
import pytest

from conftest import VECTORS
from gateway.core.method import MethodParams, ParamError, StreamingMonitor, analyze_slots, build_params, to_slots
from gateway.core.method.core import SlotArrays
from gateway.core.method.rules import theil_sen_slope
from gateway.offline.analysis import params_for
from gateway.offline.logio import read_log

THETA = math.radians(105)


def log_of(mu, t1=0.4):
    """Slot arrays whose valid μ are exactly the given values (NaN → a MISSING slot)."""
    mu = np.asarray(mu, dtype=np.float64)
    present = ~np.isnan(mu)
    a = np.where(present, t1, np.nan)
    b = np.where(present, t1 * np.exp(np.where(present, mu, 0.0) * THETA), np.nan)
    return present, a, b


def both(p, present, a, b):
    r = analyze_slots(SlotArrays(present, a, b), p)
    mon = StreamingMonitor(p)
    outs = []
    for k in range(len(present)):
        if mon.finished:
            break
        outs.append(mon.push(bool(present[k]), float(a[k]), float(b[k])))
    s = mon.close(len(present))
    assert s.as_dict() == r.as_dict()
    return r, [o.window for o in outs if o.window is not None], outs


# small windows: N_ss = 10 slots, baseline after 2 steady windows
P = dict(t_set=0.5, w_ss=0.2, w_hold=0.4, tau=100.0, stop_after=100.0)


def windows_with_values(vals, n_ss=10, base=0.25):
    """Two baseline windows at `base`, then one window per value (None: an empty window)."""
    mu = [base] * (2 * n_ss)
    for v in vals:
        mu += [math.nan] * n_ss if v is None else [v] * n_ss
    return mu


def test_headroom_is_one_at_the_baseline_zero_at_the_threshold_and_not_clipped():
    p = MethodParams(**P)
    present, a, b = log_of(windows_with_values([0.25, 0.3125, 0.35]))
    r, wins, _ = both(p, present, a, b)
    assert r.k_b == 19 and [w.j for w in wins] == [2, 3, 4]
    mu_ss, mu_th = r.mu_ss, r.mu_th
    hs = [w.headroom for w in wins]
    assert hs[0] == pytest.approx(1.0, abs=1e-9)
    assert hs[1] == pytest.approx((mu_th - 0.3125) / (mu_th - mu_ss), abs=1e-12)
    assert abs(hs[1]) < 1e-6
    assert hs[2] < -0.5                          # above the threshold: negative, not clipped
    assert r.headroom == hs[2]


def test_window_value_is_the_median_and_even_counts_take_the_middle_two():
    p = MethodParams(**P)
    mu = windows_with_values([]) + [0.25, 0.26, 0.27, 0.28, 0.29, 0.30, 0.31, 0.32, 0.33, 0.34]
    present, a, b = log_of(mu)
    _, wins, _ = both(p, present, a, b)
    vals = np.log(b[20:30] / a[20:30]) / THETA
    assert wins[0].value == pytest.approx((vals[4] + vals[5]) / 2, abs=1e-15)


def test_a_window_with_too_few_valid_slots_has_no_value_and_breaks_the_headroom_run():
    p = MethodParams(**P, h_warn=0.5, n_warn=3)
    hi = 0.30   # h = (0.3125 - 0.30) / 0.0625 = 0.2 < 0.5
    # run of 2, a window without a value, then a run of 3: the warning is the end of the second run
    present, a, b = log_of(windows_with_values([hi, hi, None, hi, hi, hi, hi]))
    r, wins, outs = both(p, present, a, b)
    assert wins[2].value is None and wins[2].headroom is None and wins[2].n_eff == 0
    assert r.warn_slot == (7 + 1) * 10 - 1 == 79     # last slot of window j = 7 (2, 3 | 4 | 5, 6, 7)
    assert r.warn_reasons == ["headroom"]
    assert [o.k for o in outs if "wear_warning" in o.events] == [79]   # once per test
    # every window that completes a run says so (j = 7 and j = 8), the warning is the first
    assert [w.j for w in wins if w.headroom_run] == [7, 8]
    # a window with 8 of 10 valid slots has no value either (valid_ratio_min 0.9)
    mu = windows_with_values([]) + [hi] * 8 + [math.nan] * 2
    r2, w2, _ = both(p, *log_of(mu))
    assert w2[0].value is None and r2.headroom is None


def test_the_warning_never_comes_at_or_after_the_detection_slot():
    """§5b: from k_det = k_life + N_τ − 1 on the end-of-life alarm speaks, not the forecast (the
    §5a version of the warning came after t_life here)."""
    p = MethodParams(**{**P, "tau": 0.1}, n_warn=4)
    present, a, b = log_of(windows_with_values([0.4] * 5))
    r, wins, outs = both(p, present, a, b)
    assert r.status == "failure" and r.k_life == 20
    assert [w.j for w in wins if w.headroom_run] == [5, 6]     # the runs still exist (§5a) …
    assert r.warn_slot is None and r.warn_reasons is None       # … but come after k_det = 24
    assert not any("wear_warning" in o.events for o in outs)
    # the forecast times are the windows that end before k_det: j = 0 and 1 (slots 9, 19)
    assert [o.forecast.j for o in outs if o.forecast is not None] == [0, 1]


def test_projection_needs_ten_windows_and_follows_a_linear_trend():
    p = MethodParams(**P)
    slope_per_window = 0.001
    vals = [0.25 + slope_per_window * i for i in range(12)]
    present, a, b = log_of(windows_with_values(vals))
    r, wins, _ = both(p, present, a, b)
    assert all(w.t_cross is None and w.slope is None for w in wins[:9])
    assert all(w.slope is not None for w in wins[9:])
    w = wins[-1]
    window_s = p.n_ss * p.ts
    assert w.slope == pytest.approx(slope_per_window / window_s, rel=1e-6)
    expect = (w.j + 1) * window_s + (r.mu_th - w.value) / w.slope
    assert w.t_cross == pytest.approx(expect, rel=1e-12) and r.t_cross == w.t_cross
    # roughly where the straight line reaches μ_th (t of the value 0.3125 ≈ 62.5 windows later)
    assert w.t_cross == pytest.approx((2 + 62.5 + 0.5) * window_s, rel=0.02)


def test_no_projection_when_flat_or_falling_or_past_the_threshold():
    p = MethodParams(**P)
    for vals in ([0.25] * 12, [0.26 - 0.001 * i for i in range(12)], [0.32 + 0.001 * i for i in range(12)]):
        r, wins, _ = both(p, *log_of(windows_with_values(vals)))
        assert r.t_cross is None and wins[-1].t_cross is None


def test_theil_sen_is_robust_to_one_outlier_and_uses_every_pair():
    t = np.arange(11, dtype=float)
    v = 2.0 * t
    v[5] = 1000.0
    assert theil_sen_slope(v, t) == 2.0
    # pairwise slopes of (0,0), (1,1), (2,4): 1, 2, 3 → median 2
    assert theil_sen_slope(np.array([0.0, 1.0, 4.0]), np.array([0.0, 1.0, 2.0])) == 2.0


def test_trend_uses_only_the_last_trend_windows_values():
    p = MethodParams(**P, trend_windows=10)
    vals = [0.30 - 0.002 * i for i in range(10)] + [0.25 + 0.001 * i for i in range(10)]
    r, wins, _ = both(p, *log_of(windows_with_values(vals)))
    assert wins[-1].slope > 0          # the old falling windows are out of the trend
    assert MethodParams(**P).trend_windows == 60


# ---------------------------------------------------------------------------- end_slot (§3)

def steady(n, mu=0.25):
    return log_of([mu] * n)


def test_a_stopped_test_has_exactly_end_slot_slots_and_ignores_later_readings():
    present, a, b = steady(500)
    p = MethodParams(**P, end_slot=300, t_end=1000.0)
    s = to_slots(np.arange(500) * 0.02, a, b, p)
    assert s.present.size == 300 and s.out_of_grid == 200
    r, _, _ = both(p, s.present, s.t1, s.t2)
    assert (r.status, r.stop_slot, r.stop_reasons, r.n_slots, r.interrupted) == \
        ("aborted", 300, ["STOPPED"], 300, False)
    assert r.reasons["MISSING"] == 0          # t_end adds no slots
    # slots before end_slot without a reading are MISSING as usual
    s = to_slots(np.arange(280) * 0.02, a[:280], b[:280], p)
    r, _, _ = both(p, s.present, s.t1, s.t2)
    assert r.n_slots == 300 and r.reasons["MISSING"] == 20 and r.stop_reasons == ["STOPPED"]


def test_a_protection_stop_before_end_slot_wins():
    present, a, b = steady(400)
    present[100:160] = False
    p = MethodParams(**{**P, "stop_after": 1.0}, end_slot=300)
    r, _, _ = both(p, present[:300], a[:300], b[:300])
    assert (r.status, r.stop_slot, r.stop_reasons) == ("aborted", 150, ["MISSING"])


def test_t_life_before_end_slot_stays_failure_and_is_interrupted():
    p = MethodParams(**{**P, "tau": 0.2}, end_slot=200)
    present, a, b = log_of(windows_with_values([0.4] * 20))
    r, _, _ = both(p, present[:200], a[:200], b[:200])
    assert (r.status, r.interrupted, r.stop_slot, r.stop_reasons, r.n_slots) == \
        ("failure", True, 200, ["STOPPED"], 200)


def test_streaming_stop_equals_the_log_with_end_slot_in_its_sidecar():
    """The runtime's path: a stop command at slot 125000 of v5; the online result is the offline
    result of the log whose sidecar says end_slot: 125000 (the vector's expected result)."""
    log = read_log(os.path.join(VECTORS, "v5_stopped.csv.gz"))
    meta = dict(log.meta)
    method = dict(meta["method"])
    end_slot = method.pop("end_slot")
    p_online = params_for({"method": method}, {}, "v5")
    p_offline = params_for(meta, {}, "v5")
    s = to_slots(log.t, log.t1, log.t2, p_offline)
    mon = StreamingMonitor(p_online)
    last = s.present.size - 1
    while not s.present[last]:
        last -= 1
    for k in range(last + 1):       # the readings that came; the stop comes after the last one
        mon.push(bool(s.present[k]), float(s.t1[k]), float(s.t2[k]))
    online = mon.stop(end_slot)
    assert online.as_dict() == analyze_slots(s, p_offline).as_dict()
    assert online.stop_reasons == ["STOPPED"] and mon.finished
    with pytest.raises(ValueError):
        StreamingMonitor(p_online).stop(-1)


# ---------------------------------------------------------------------------- parameters

def test_new_parameters_parse_from_strings_yaml_and_reject_nonsense():
    p = build_params({"t_set": 0.5, "end_slot": "125000", "zero_check": "false", "n_warn": 3.0,
                      "h_warn": "0.4", "trend_windows": 20})
    assert (p.end_slot, p.zero_check, p.n_warn, p.h_warn, p.trend_windows) == (125000, False, 3, 0.4, 20)
    assert isinstance(p.end_slot, int) and isinstance(p.n_warn, int)
    assert build_params({"t_set": 0.5, "zero_check": True, "end_slot": None}).end_slot is None
    for bad, words in (({"end_slot": 12.5}, "whole number"), ({"end_slot": -1}, "≥ 0"),
                       ({"zero_check": "maybe"}, "true or false"), ({"trend_windows": 9}, "≥ 10"),
                       ({"n_warn": 0}, "≥ 1"), ({"settle_band": 1.5}, "settle_band"),
                       ({"start_timeout": 1, "settle_time": 2}, "longer than settle_time"),
                       ({"zero_tol": 0}, "zero_tol")):
        with pytest.raises(ParamError, match=words):
            build_params({"t_set": 0.5, **bad})


def test_streaming_stop_matches_the_batch_form_before_and_after_t_end():
    present, a, b = steady(400)
    for end in (120, 250, 300):     # t_end is 200 slots: before, after, and past the log
        p_on = MethodParams(**P, t_end=4.0)
        p_off = MethodParams(**P, t_end=4.0, end_slot=end)
        mon = StreamingMonitor(p_on)
        for k in range(min(end, 200)):
            mon.push(True, float(a[k]), float(b[k]))
        s = to_slots(np.arange(400) * 0.02, a, b, p_off)
        # the stop may come after t_end only if the runtime kept the test going; then the slots
        # between t_end and end_slot are MISSING online (nothing was pushed) and offline alike
        offline = analyze_slots(SlotArrays(s.present & (np.arange(s.present.size) < min(end, 200)),
                                           s.t1, s.t2), p_off)
        assert mon.stop(end).as_dict() == offline.as_dict()
        assert offline.n_slots == end and offline.stop_reasons == ["STOPPED"]
