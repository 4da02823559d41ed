"""METHOD.md §5b (remaining life from a prior, the due rule, the early warning) on hand-made slot
sequences; expected figures computed here from the text of the spec."""
import math

import numpy as np
import pytest
from scipy.special import ndtr, ndtri
from test_method_end_and_wear import P, both, log_of, windows_with_values

from gateway.core.method import MethodParams, ParamError, build_params, prior_forecast
from gateway.offline.analysis import AnalysisError, params_for


def test_prior_forecast_is_the_prior_cut_at_t():
    """Against scipy.special as the oracle: the product's Φ (erfc) and Φ⁻¹ (AS241) agree to
    ≈ 1e-16 relative; 1e-12 here (the vectors compare to 1e-9)."""
    m, s, lead = 3300.0, 150.0, 600.0
    for t in (100.0, 2520.0, 3300.0, 3600.0):
        f = prior_forecast(t, m, s, lead)
        a = (t - m) / s
        surv = 1 - ndtr(a)
        for q, e in zip((0.1, 0.5, 0.9), (f.e10, f.e50, f.e90)):
            assert e == pytest.approx(max(m + s * ndtri(1 - surv * (1 - q)), t), rel=1e-12)
            assert e >= t
        assert f.p == pytest.approx((ndtr((t + lead - m) / s) - ndtr(a)) / surv, rel=1e-12, abs=1e-15)
        assert f.e10 <= f.e50 <= f.e90 and 0 <= f.p <= 1
    # long before the mean: the quantiles of the prior itself
    f = prior_forecast(0.0, m, s, lead)
    assert f.e50 == pytest.approx(m, abs=1e-6) and f.e10 == pytest.approx(m - 1.2815515655 * s, abs=1e-6)
    # far beyond the prior (S < 1e-12): e_p = t, P = 1
    f = prior_forecast(m + 8 * s, m, s, lead)
    assert (f.e10, f.e50, f.e90, f.p) == (m + 8 * s, m + 8 * s, m + 8 * s, 1.0)


def test_the_prior_makes_a_window_due_and_the_warning_may_come_before_the_baseline():
    # N_ss = 10 slots = 0.2 s; windows end at 0.2, 0.4, … s
    p = MethodParams(**P, prior_mean=1.0, prior_sd=0.1, lead=0.2, p_due=0.5)
    present, a, b = log_of(windows_with_values([0.25] * 6))     # 8 windows, 1.6 s, no wear
    r, _, outs = both(p, present, a, b)
    fc = [o.forecast for o in outs if o.forecast is not None]
    assert [f.j for f in fc] == list(range(8)) and [f.t for f in fc][:2] == [0.2, 0.4]
    # P ≥ 0.5 first at t = 0.8 (P(end in (0.8, 1.0] | > 0.8) = (0.5 − Φ(−2)) / (1 − Φ(−2)) ≈ 0.49 <
    # 0.5; at t = 1.0: (Φ(2) − 0.5) / 0.5 ≈ 0.95)
    ps = [f.p_end for f in fc]
    first = next(i for i, x in enumerate(ps) if x >= 0.5)
    assert fc[first].t == pytest.approx(1.0) and ps[first - 1] < 0.5
    assert r.warn_slot == fc[first].last_slot == 49 and r.warn_reasons == ["prior"]
    assert [o.k for o in outs if "wear_warning" in o.events] == [49]
    assert (r.end_p10, r.end_p50, r.end_p90, r.p_end) == (fc[-1].e10, fc[-1].e50, fc[-1].e90, fc[-1].p_end)
    # a warning before the baseline: the forecast speaks from window 0 on
    p2 = MethodParams(**P, prior_mean=0.3, prior_sd=0.1, lead=0.2)
    r2, _, _ = both(p2, present, a, b)
    assert r2.warn_slot == 9 and r2.warn_slot < r2.k_b and r2.warn_reasons == ["prior"]


def test_reasons_are_sorted_and_all_that_hold_at_the_warning():
    # window j = 2 (the first after Ω_stable) at h = 0.2 completes a run of n_warn = 1, and the
    # prior (mean 0.7 s, SD 0.05 s, lead 0.05 s) gives P = (Φ(−1) − Φ(−2)) / (1 − Φ(−2)) ≈ 0.14 at
    # its end t = 0.6 s (at 0.4 s: ≈ 3e-7)
    vals = [0.30] * 4
    p = MethodParams(**P, n_warn=1, prior_mean=0.7, prior_sd=0.05, lead=0.05)
    r, wins, outs = both(p, *log_of(windows_with_values(vals)))
    fc = [o.forecast for o in outs if o.forecast is not None]
    assert fc[2].p_end == pytest.approx((ndtr(-1) - ndtr(-2)) / (1 - ndtr(-2)), rel=1e-9)
    assert fc[1].p_end < 1e-6 and not fc[1].due
    assert r.warn_slot == 29 and r.warn_reasons == ["headroom", "prior"]
    assert fc[2].warning and list(fc[2].reasons) == ["headroom", "prior"]
    assert fc[3].due and not fc[3].warning and sum(f.warning for f in fc) == 1


def test_trend_reason_compares_t_cross_minus_the_window_end_with_the_lead():
    vals = [0.25 + 0.001 * i for i in range(12)]
    base = MethodParams(**P, n_warn=100)
    r, wins, outs = both(base.__class__(**{**base.as_dict(), "lead": 1e6}), *log_of(windows_with_values(vals)))
    fc = [o.forecast for o in outs if o.forecast is not None]
    first = next(f for f in fc if f.t_cross is not None)
    gap = first.t_cross - first.t
    assert r.warn_slot == first.last_slot and r.warn_reasons == ["trend"]
    for lead, warned in ((gap, True), (gap * (1 - 1e-9), False)):
        p = MethodParams(**{**base.as_dict(), "lead": lead})
        r2, _, outs2 = both(p, *log_of(windows_with_values(vals)))
        fc2 = [o.forecast for o in outs2 if o.forecast is not None]
        assert (fc2[first.j].due) is warned


def test_no_prior_means_null_prior_parts():
    present, a, b = log_of(windows_with_values([0.25] * 3))
    r, _, outs = both(MethodParams(**P), present, a, b)
    assert (r.end_p10, r.end_p50, r.end_p90, r.p_end, r.warn_slot, r.warn_reasons) == (None,) * 6
    assert all(o.forecast.p_end is None for o in outs if o.forecast is not None)


def test_a_log_prior_with_sd_le_0_is_no_prior_but_a_configured_one_is_an_error():
    meta = {"method": {"t_set": 0.5, "prior_mean": 3300, "prior_sd": 0}}
    p = params_for(meta, {}, "log")
    assert p.prior_sd == 0
    present, a, b = log_of(windows_with_values([0.25] * 3))
    r, _, _ = both(MethodParams(**P, prior_mean=0.2, prior_sd=0.0), present, a, b)
    assert r.p_end is None and r.warn_slot is None
    assert params_for({"method": {"t_set": 0.5, "prior_mean": 3300}}, {}, "log").prior_sd is None
    with pytest.raises(AnalysisError, match="prior_sd"):
        params_for(meta, {"prior_sd": "-1"}, "log")
    for bad, words in (({"prior_mean": 3300, "prior_sd": 0}, "prior_sd: 0.0 is impossible"),
                       ({"prior_mean": 3300, "prior_sd": -5}, "prior_sd"),
                       ({"prior_mean": 3300}, "prior_sd"), ({"prior_sd": 30}, "prior_mean"),
                       ({"prior_mean": 0, "prior_sd": 30}, "prior_mean"),
                       ({"lead": -1}, "lead: -1.0 is impossible"),
                       ({"p_due": 0}, "p_due"), ({"p_due": 1}, "p_due"), ({"p_due": 1.5}, "p_due")):
        with pytest.raises(ParamError, match=words):
            build_params({"t_set": 0.5, **bad})
    p = build_params({"t_set": 0.5, "prior_mean": "3300", "prior_sd": 150, "lead": 0, "p_due": "0.2"})
    assert (p.prior_mean, p.prior_sd, p.lead, p.p_due) == (3300.0, 150.0, 0.0, 0.2)
    assert MethodParams(t_set=0.5).lead == 3600 and MethodParams(t_set=0.5).p_due == 0.1


def test_forecast_times_stop_at_a_protection_stop_and_at_end_slot():
    present, a, b = log_of(windows_with_values([0.25] * 6))
    p = MethodParams(**{**P, "stop_after": 0.1}, prior_mean=10.0, prior_sd=1.0)
    present = present.copy()
    present[42:60] = False                 # stop at slot 42 + 5 = 47: windows 0..3 only
    r, _, outs = both(p, present, a, b)
    assert r.stop_slot == 47
    assert [o.forecast.j for o in outs if o.forecast is not None] == [0, 1, 2, 3]
    p2 = MethodParams(**P, prior_mean=10.0, prior_sd=1.0, end_slot=35)
    pr, a2, b2 = log_of(windows_with_values([0.25] * 6))
    r2, _, outs2 = both(p2, pr[:35], a2[:35], b2[:35])
    assert [o.forecast.j for o in outs2 if o.forecast is not None] == [0, 1, 2]
    assert math.isfinite(r2.p_end) and np.isfinite(r2.end_p50)
