"""METHOD.md §7a: the prior from failures and right-censored lives (the maximum-likelihood normal).

The product's fit (gateway/core/method/prior.py: Newton on the concave ℓ(α, β), pure Python) is held
against independent oracles: scipy.optimize on ℓ(m, ln s) with scipy's log-survival, and an EM of
the censored normal (scipy.stats.truncnorm's moments). Without censored lives it is exactly the
failures' mean and sample SD; edge cases (all failures equal, a censored life far beyond the mean,
large counts) never give NaN or inf.
"""
import math
import statistics

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from scipy import optimize
from scipy.special import log_ndtr
from scipy.stats import norm, truncnorm

from gateway.core.method.prior import (
    MIN_HISTORY,
    PastTest,
    censored_normal_mle,
    group_lives,
    history_prior,
    log_likelihood,
    log_sf,
    priors_by_group,
    resolve_prior,
    split_early,
    wear_out_prior,
)

#: the public campaign's grade I (tests/vectors/campaigns/c1_campaign.expected_priors.json)
C1_X = [2917.92, 3064.34, 3215.14, 3363.06]
C1_C = [2600.0, 2900.0, 3000.0]
C1_PRIOR = (3156.10905968845, 182.25402648037655)


def oracle_mle(xs, cs):
    """(m̂, ŝ) by scipy: Nelder-Mead then BFGS on −ℓ(m, ln s), standardised on the failures."""
    x0, d = statistics.mean(xs), statistics.stdev(xs)
    y, w = (np.asarray(xs) - x0) / d, (np.asarray(cs, dtype=float) - x0) / d

    def nll(p):
        m, ls = p
        s = math.exp(ls)
        return -(np.sum(-ls - 0.5 * ((y - m) / s) ** 2) + np.sum(norm.logsf((w - m) / s)))
    r = optimize.minimize(nll, [0.0, 0.0], method="Nelder-Mead",
                          options={"xatol": 1e-12, "fatol": 1e-14, "maxiter": 40000, "maxfev": 80000})
    r = optimize.minimize(nll, r.x, method="BFGS", options={"gtol": 1e-11})
    return x0 + d * r.x[0], d * math.exp(r.x[1])


def em_mle(xs, cs, iters=20000):
    """(m̂, ŝ) by EM: the censored lives replaced by their expected moments beyond c."""
    x, c = np.asarray(xs, float), np.asarray(cs, float)
    n = x.size + c.size
    m, s = x.mean(), x.std()
    for _ in range(iters):
        a = (c - m) / s
        e1 = truncnorm.mean(a, np.inf, loc=m, scale=s)
        e2 = truncnorm.var(a, np.inf, loc=m, scale=s) + e1 ** 2
        m2 = (x.sum() + e1.sum()) / n
        s2 = math.sqrt(max((np.sum((x - m2) ** 2) + np.sum(e2 - 2 * m2 * e1 + m2 ** 2)) / n, 1e-300))
        if abs(m2 - m) <= 1e-13 * abs(m) and abs(s2 - s) <= 1e-13 * s:
            return m2, s2
        m, s = m2, s2
    return m, s


def rel(a, b):
    return abs(a - b) / abs(b)


def test_log_survival_is_stable_in_both_tails_and_agrees_with_scipy():
    for a in [-40.0, -8.0, -1.0, 0.0, 0.5, 3.0, 19.999, 20.0, 20.001, 37.0, 38.5, 60.0, 1e4, 1e8]:
        ln_sf, hz, rest = log_sf(a)
        ref = float(log_ndtr(-a))
        assert math.isfinite(ln_sf) and ln_sf <= 0.0
        assert abs(ln_sf - ref) <= 1e-13 * max(1.0, abs(ref)), a
        # hazard φ(a)/Φ̄(a) and hazard − a (> 0); far out: a + 1/a − 2/a³ + 10/a⁵
        if a <= 20.0:
            ref_hz = math.exp(norm.logpdf(a) - ref)
            assert (rel(hz, ref_hz) <= 1e-12) if ref_hz > 1e-300 else hz >= 0.0
        elif a >= 1e3:
            assert rel(hz, a + 1 / a - 2 / a ** 3 + 10 / a ** 5) <= 1e-15
        assert rest > 0.0 and math.isfinite(rest)
    # far in the upper tail erfc underflows to 0 (log(0)); the continued fraction does not
    assert math.erfc(40.0 / math.sqrt(2)) == 0.0
    assert log_sf(40.0)[0] == pytest.approx(float(log_ndtr(-40.0)), rel=1e-14)


def test_the_public_campaigns_grade_I_and_the_oracles():
    m, s = history_prior(C1_X, C1_C)
    assert rel(m, C1_PRIOR[0]) <= 1e-10 and rel(s, C1_PRIOR[1]) <= 1e-10
    mh, sh = censored_normal_mle(C1_X, C1_C)
    om, os_ = oracle_mle(C1_X, C1_C)
    assert rel(mh, om) <= 1e-6 and rel(sh, os_) <= 1e-6
    em, es = em_mle(C1_X, C1_C)
    assert rel(mh, em) <= 1e-6 and rel(sh, es) <= 1e-6
    # the maximum: ℓ is lower a little away from it in every direction
    best = log_likelihood(C1_X, C1_C, mh, sh)
    for dm, ds in ((1, 0), (-1, 0), (0, 1), (0, -1), (1, 1), (-1, -1)):
        assert log_likelihood(C1_X, C1_C, mh + dm * 1e-3 * sh, sh * (1 + ds * 1e-4)) < best
    # the SD: ŝ·√(n_f/(n_f − 1))
    assert s == pytest.approx(sh * math.sqrt(4 / 3), rel=1e-15)


def test_without_censored_lives_exactly_the_mean_and_the_sample_sd():
    xs = [21500.0, 23700.0, 20730.0, 22644.0]
    assert statistics.stdev(xs) > 0.02 * statistics.fmean(xs)
    assert history_prior(xs) == (statistics.fmean(xs), statistics.stdev(xs))
    assert history_prior(xs, []) == history_prior(xs)


def test_fewer_than_three_failures_none_and_all_failures_equal_two_percent():
    assert history_prior([100.0, 200.0], [300.0, 400.0, 500.0]) is None
    assert history_prior([], [1.0] * 10) is None
    # all equal: that value and 0.02 · it, censored lives or not (ℓ has no maximum then)
    assert history_prior([500.0] * 3) == (500.0, 10.0)
    assert history_prior([500.0] * 3, [700.0, 900.0]) == (500.0, 10.0)


def test_the_sd_floor_of_two_percent_of_the_mean():
    xs = [1000.0, 1000.5, 1001.0]
    m, s = history_prior(xs, [990.0])
    assert s == pytest.approx(0.02 * m, rel=1e-15)


@pytest.mark.parametrize("xs,cs", [
    (C1_X, [1e9]),                                   # one censored life absurdly far beyond
    (C1_X, [3e4] * 5000),                            # many far beyond (huge log survival)
    (C1_X, [1.0] * 5000),                            # many far below (they say nothing)
    ([10.0, 10.0 + 1e-9, 10.0 + 2e-9], [10.0]),     # failures a hair apart
    ([1e-3, 2e-3, 3e-3], [5e-3, 4e-3]),              # tiny lives
    ([1e12, 1.1e12, 1.2e12], [1.3e12]),               # huge lives
    ([3000.0, 3100.0, 3200.0], [1e300]),              # beyond any float square
])
def test_extremes_give_finite_figures_or_none_never_nan(xs, cs):
    h = history_prior(xs, cs)
    if h is not None:
        assert all(math.isfinite(v) and v > 0 for v in h)
        assert h[1] >= 0.02 * h[0] * (1 - 1e-15)


def test_censored_lives_far_beyond_move_the_mean_up_and_below_the_failures_barely():
    base = history_prior(C1_X)
    assert history_prior(C1_X, [5000.0] * 3)[0] > base[0] + 100
    low = history_prior(C1_X, [100.0] * 50)
    assert rel(low[0], base[0]) < 1e-6


def test_a_long_history_converges_to_the_oracle():
    rng = np.random.default_rng(7)
    lives = rng.normal(16577.0, 489.0, 600)
    stop = rng.uniform(14000.0, 17500.0, 600)
    xs = [float(x) for x, c in zip(lives, stop) if x <= c]
    cs = [float(c) for x, c in zip(lives, stop) if x > c]
    assert len(xs) > 50 and len(cs) > 50
    mh, sh = censored_normal_mle(xs, cs)
    om, os_ = oracle_mle(xs, cs)
    assert rel(mh, om) <= 1e-6 and rel(sh, os_) <= 1e-6
    # the truth is recovered (a failures-only prior would be biased low)
    assert abs(mh - 16577.0) < 100 and abs(sh - 489.0) < 80
    assert statistics.fmean(xs) < mh - 100


lives = st.floats(min_value=100.0, max_value=1e5, allow_nan=False, allow_infinity=False)


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(xs=st.lists(lives, min_size=MIN_HISTORY, max_size=25),
       frac=st.lists(st.floats(min_value=0.0, max_value=4.0), max_size=40))
def test_property_agrees_with_scipy_for_random_histories(xs, frac):
    lo, hi = min(xs), max(xs)
    if hi - lo < 1e-6 * hi:
        assert history_prior(xs, []) is not None
        return
    cs = [lo + f * (hi - lo) for f in frac]
    h = history_prior(xs, cs)
    # v3: a prior when at least 3 failures are wear-out ones (not below 0.75 × the median)
    assert (h is None) == (len(split_early(xs, cs)[0]) < MIN_HISTORY)
    assert h is None or all(math.isfinite(v) for v in h)
    fit = censored_normal_mle(xs, cs)
    om, os_ = oracle_mle(xs, cs)
    # both maximise ℓ: the product's fit is at least as likely as scipy's (to rounding) and agrees
    assert (log_likelihood(xs, cs, *fit) >= log_likelihood(xs, cs, om, os_)
            - 1e-9 * abs(log_likelihood(xs, cs, om, os_)))
    assert rel(fit[0], om) <= 1e-6 and rel(fit[1], os_) <= 1e-6
    # the rule on these lives as they are (§7a v2: every failure a wear-out one) …
    n = len(xs)
    v2 = wear_out_prior(xs, cs)
    assert v2 == pytest.approx((fit[0], max(fit[1] * math.sqrt(n / (n - 1)), 0.02 * fit[0])), rel=1e-12)
    # … and v3: the early failures censored at their life (the same rule on the split lives)
    wear, early = split_early(xs, cs)
    assert h == wear_out_prior(wear, cs + early)


def t(status, t_life=None, k_b=100, stop=None, n_slots=None, grade="I", t_set=0.5, test_id=None):
    return PastTest(grade, t_set, status, t_life, k_b=k_b, stop_reasons=stop, n_slots=n_slots,
                    ts=0.02, test_id=test_id)


def test_which_tests_enter_the_history_and_how():
    assert t("failure", 3000.0).life() == ("failure", 3000.0)
    assert t("aborted", stop=("STOPPED",), n_slots=130000).life() == ("censored", 2600.0)
    assert t("no_failure", n_slots=150000).life() == ("censored", 3000.0)
    # no baseline, a protection stop, stopped without a baseline, no ts: nothing
    assert t("no_baseline", n_slots=5000, k_b=None).life() is None
    assert t("aborted", stop=("MISSING",), n_slots=100051).life() is None
    assert t("aborted", stop=("STOPPED",), n_slots=5000, k_b=None).life() is None
    assert PastTest("I", 0.5, "no_failure", None, k_b=1, n_slots=10).life() is None
    # implausible figures never enter
    for bad in (0.0, -5.0, math.nan, math.inf):
        assert t("failure", bad).life() is None
    assert t("no_failure", n_slots=0).life() is None


def test_resolve_and_groups_count_failures_and_censored_lives_each_test_once():
    hist = ([t("failure", x, test_id=f"F{i}") for i, x in enumerate(C1_X)]
            + [t("aborted", stop=("STOPPED",), n_slots=int(c / 0.02), test_id=f"C{i}")
               for i, c in enumerate(C1_C[:2])]
            + [t("no_failure", n_slots=150000, test_id="C2")]
            + [t("aborted", stop=("MISSING",), n_slots=100051, test_id="P")]
            + [t("failure", 2917.92, test_id="F0")]           # the same test again (shared twice)
            + [t("failure", 100.0, grade="II"), t("failure", 120.0, t_set=0.7)])
    assert group_lives(hist, "I", 0.5) == (C1_X, C1_C)
    p = resolve_prior([], hist, "I", 0.5)
    assert (p.source, p.n, p.n_censored) == ("history", 4, 3)
    assert rel(p.mean, C1_PRIOR[0]) <= 1e-10 and rel(p.sd, C1_PRIOR[1]) <= 1e-10
    assert p.sidecar()["prior_n_censored"] == 3
    (e,) = priors_by_group(hist)
    assert (e.grade, e.t_set, e.n, e.n_censored) == ("I", 0.5, 4, 3)
    assert e.as_config()["n_censored"] == 3


def test_a_fit_that_does_not_converge_gives_no_prior_never_a_wrong_one(monkeypatch):
    import gateway.core.method.prior as P
    monkeypatch.setattr(P, "MAX_NEWTON", 1)          # a bound too tight to converge in
    assert censored_normal_mle(C1_X, C1_C) is None
    assert history_prior(C1_X, C1_C) is None
    hist = [t("failure", x) for x in C1_X] + [t("no_failure", n_slots=150000)]
    assert resolve_prior([], hist, "I", 0.5).source is None
    # without censored lives the closed form needs no iteration
    assert history_prior(C1_X) == (statistics.fmean(C1_X), statistics.stdev(C1_X))
