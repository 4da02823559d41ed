"""METHOD.md §7a v3: early failures as a competing risk.

With at least 5 lives in the history (observed and censored together), an observed life below
0.75 × the median of all of them is an early failure: for the wear-out prior a right-censored life
at its x. The prior needs at least 3 wear-out failures; n_w replaces n_f in the SD correction.
Held here: the public campaign's two cases (I-09 early among 8 lives, II-04 short among 4: not
early), the rule's edges (the fence itself, an even count's median, fewer than 5 lives, fewer than
3 wear-out failures), and as properties over random histories: no failure within 20 % of the median
is ever early; an early failure far below the fence (the others' classes unchanged) moves m and s
by < 1e-6 relative; without a failure below the fence v3 is v2 exactly.
"""
import math
import statistics

import pytest
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st

from gateway.core.method.prior import (
    CENSORED,
    EARLY,
    MIN_HISTORY,
    WEAR_OUT,
    PastTest,
    censored_normal_mle,
    early_fence,
    history_prior,
    kind_in_history,
    median_life,
    prior_of_lives,
    priors_by_group,
    resolve_prior,
    split_early,
    wear_out_prior,
)

#: the public campaign (tests/vectors/campaigns/c1_campaign.expected_priors.json)
I_X = [2917.92, 3064.34, 3215.14, 3363.06, 1766.32]          # I-09: 1766.32
I_C = [2600.0, 2900.0, 3000.0]
I_PRIOR = (3156.1090596884496, 182.25402648037655)
II_X = [2613.48, 2714.62, 2867.64, 1709.48]                   # II-04: 1709.48, 4 lives only


def rel(a, b):
    return abs(a - b) / abs(b)


def test_the_public_campaigns_early_failure_and_short_life():
    # grade I: 8 lives, M = (2917.92 + 3000) / 2, the fence 0.75 · M; I-09 below it
    assert median_life(I_X, I_C) == (2917.92 + 3000.0) / 2
    assert split_early(I_X, I_C) == (I_X[:4], [1766.32])
    p = prior_of_lives(I_X, I_C)
    assert (p.source, p.n, p.n_censored, p.n_early) == ("history", 4, 3, 1)
    assert rel(p.mean, I_PRIOR[0]) <= 1e-10 and rel(p.sd, I_PRIOR[1]) <= 1e-9
    # it is the fit of the wear-out failures with I-09 censored, SD · √(n_w/(n_w − 1)), n_w = 4
    m, s = censored_normal_mle(I_X[:4], I_C + [1766.32])
    assert p.mean == m and p.sd == pytest.approx(s * math.sqrt(4 / 3), rel=1e-15)
    # v2 (I-09 a wear-out failure): 3,062 ± 639 s, the figures
    v2 = wear_out_prior(I_X, I_C)
    assert round(v2[0]) == 3062 and round(v2[1]) == 639
    # grade II: 4 lives, fewer than 5: II-04 is no early failure, the mean and sample SD of all 4
    assert early_fence(II_X, []) is None and split_early(II_X) == (II_X, [])
    q = prior_of_lives(II_X, [])
    assert (q.n, q.n_censored, q.n_early) == (4, 0, 0)
    assert (q.mean, q.sd) == (statistics.fmean(II_X), statistics.stdev(II_X))
    assert p.lives_words() == "4 wear-out failures, 3 censored, 1 early failure"


def test_the_fence_the_median_and_the_counts():
    # odd count: the middle value; even: the mean of the two middle ones (censored lives count)
    assert median_life([10.0, 30.0], [20.0]) == 20.0
    assert median_life([10.0, 40.0], [20.0, 30.0]) == 25.0
    # a failure exactly at 0.75 · M is not early (x < 0.75 · M is)
    xs = [75.0, 100.0, 100.0, 100.0, 100.0]
    assert early_fence(xs, []) == 75.0 and split_early(xs) == (xs, [])
    xs2 = [74.999, 100.0, 100.0, 100.0, 100.0]
    assert split_early(xs2) == (xs2[1:], [74.999])
    # an early failure is counted as censored: without other censored lives the fit runs
    assert prior_of_lives([50.0, 98.0, 100.0, 102.0, 104.0], []).n_early == 1
    # fewer than 3 wear-out failures: no prior, although 3 failures
    assert history_prior([10.0, 100.0, 101.0], [100.0, 100.0]) is None
    assert history_prior([10.0, 100.0, 101.0]) is not None        # 3 lives: nothing is early
    # all wear-out failures equal: their value and 0.02 · it (the early one censored aside)
    assert history_prior([10.0, 100.0, 100.0, 100.0], [120.0]) == (100.0, 2.0)
    # censored lives are never early, however short
    assert split_early([100.0, 101.0, 102.0], [1.0, 2.0]) == ([100.0, 101.0, 102.0], [])


def t(status, x=None, n_slots=None, stop=None, tid=None, grade="I", t_set=0.5):
    return PastTest(grade, t_set, status, x, k_b=10, stop_reasons=stop, n_slots=n_slots, ts=1.0,
                    test_id=tid)


def test_groups_resolve_and_the_kind_of_a_test_in_its_history():
    hist = ([t("failure", x, tid=f"F{i}") for i, x in enumerate(I_X)]
            + [t("aborted", n_slots=int(c), stop=("STOPPED",), tid=f"C{i}") for i, c in enumerate(I_C)]
            + [t("aborted", n_slots=10, stop=("MISSING",), tid="P")]
            + [t("failure", x, tid=f"G{i}", grade="II") for i, x in enumerate(II_X)])
    p = resolve_prior([], hist, "I", 0.5)
    assert (p.n, p.n_censored, p.n_early) == (4, 3, 1)
    assert p.sidecar()["prior_n_early"] == 1 and p.sidecar()["prior_n"] == 4
    got = {(e.grade, e.n, e.n_censored, e.n_early) for e in priors_by_group(hist)}
    assert got == {("I", 4, 3, 1), ("II", 4, 0, 0)}
    (e,) = [e for e in priors_by_group(hist) if e.grade == "I"]
    assert e.as_config()["n_early"] == 1
    # the kind of each test in that history (the test counted once by its id)
    assert kind_in_history(hist[4], hist) == EARLY
    assert kind_in_history(hist[0], hist) == WEAR_OUT
    assert kind_in_history(hist[5], hist) == CENSORED
    assert kind_in_history(hist[8], hist) is None                      # a protection stop
    assert kind_in_history(hist[-1], hist) == WEAR_OUT                  # grade II: 4 lives only
    # a short failure in a history that is not yet 5 lives long (with it) is a wear-out one
    assert kind_in_history(hist[4], hist[:3]) == WEAR_OUT
    assert kind_in_history(hist[4], hist[:4]) == EARLY


# ---------------------------------------------------------------------------------------------
# Properties over random histories
# ---------------------------------------------------------------------------------------------

life = st.floats(min_value=1.0, max_value=1e6, allow_nan=False, allow_infinity=False)


@settings(max_examples=300, deadline=None)
@given(xs=st.lists(life, min_size=0, max_size=30), cs=st.lists(life, max_size=30))
def test_property_no_failure_within_20_percent_of_the_median_is_ever_early(xs, cs):
    assume(xs or cs)
    wear, early = split_early(xs, cs)
    assert sorted(wear + early) == sorted(xs)
    m = median_life(xs, cs)
    for x in xs:
        if abs(x - m) <= 0.2 * m:
            assert x not in early
    # and exactly the failures below 0.75 · M are early, with at least 5 lives; none with fewer
    if len(xs) + len(cs) < 5:
        assert early == []
    else:
        assert early == [x for x in xs if x < 0.75 * m]


#: a history around a mean life: relative deviations of the failures and the censored lives
dev = st.floats(min_value=-0.06, max_value=0.06, allow_nan=False)
cdev = st.floats(min_value=-0.3, max_value=0.3, allow_nan=False)


@settings(max_examples=200, deadline=None, suppress_health_check=[HealthCheck.filter_too_much])
@given(mu=st.floats(min_value=100.0, max_value=1e5), dx=st.lists(dev, min_size=3, max_size=20),
       dc=st.lists(cdev, max_size=12), early=st.lists(st.floats(min_value=0.01, max_value=0.45),
                                                        max_size=3),
       far=st.floats(min_value=0.01, max_value=1.0))
def test_property_an_early_failure_far_below_the_fence_moves_m_and_s_by_less_than_1e6(
        mu, dx, dc, early, far):
    xs = [mu * (1 + d) for d in dx] + [mu * e for e in early]
    cs = [mu * (1 + d) for d in dc]
    base = prior_of_lives(xs, cs)
    assume(base.mean is not None)
    # far below the fence: at most 8 SD below the prior's mean (its survival there is 1 to 1e-15)
    x_e = far * min(0.7 * median_life(xs, cs), base.mean - 8 * base.sd)
    assume(x_e > 0)
    wear0, early0 = split_early(xs, cs)
    wear1, early1 = split_early(xs + [x_e], cs)
    # it is an early failure, and the median did not move across any other failure's fence
    assume(wear1 == wear0 and early1 == early0 + [x_e])
    after = prior_of_lives(xs + [x_e], cs)
    assert (after.n, after.n_censored, after.n_early) == (base.n, base.n_censored, base.n_early + 1)
    assert rel(after.mean, base.mean) < 1e-6 and rel(after.sd, base.sd) < 1e-6


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.filter_too_much])
@given(mu=st.floats(min_value=1.0, max_value=1e5), dx=st.lists(st.floats(min_value=-0.5, max_value=0.6),
                                                               min_size=MIN_HISTORY, max_size=25),
       dc=st.lists(st.floats(min_value=-0.9, max_value=2.0), max_size=25))
def test_property_v3_is_v2_exactly_when_no_failure_is_below_the_fence(mu, dx, dc):
    xs = [mu * (1 + d) for d in dx]
    cs = [mu * (1 + d) for d in dc]
    fence = early_fence(xs, cs)
    assume(fence is None or min(xs) >= fence)
    assert history_prior(xs, cs) == wear_out_prior(xs, cs)          # exactly: the same figures
    p = prior_of_lives(xs, cs)
    assert p.n_early == 0 and (p.n is None or p.n == len(xs))
