"""Streaming form == batch form on thousands of random logs (hypothesis)."""
import math

import numpy as np
from hypothesis import HealthCheck, event, given, settings
from hypothesis import strategies as st

from gateway.core.method import MethodParams, StreamingMonitor, analyze_slots, gate_arrays
from gateway.core.method.core import SlotArrays, gate_and_baseline, life_detail, mark_lost

EVENT_KINDS = ["dropout", "burst", "spike", "low", "ratio_low", "ratio_high", "saturation", "nan",
               "gap_ng", "gap_ng1", "gap_stop", "gap_stop1"]


@st.composite
def prior_params(draw):
    """§5b parameters: a prior around the length of these short logs (or none, or one with SD ≤ 0,
    which a log's sidecar may carry: the prior parts are then null), a lead and p_due."""
    kind = draw(st.sampled_from(["none", "prior", "prior", "zero_sd"]))
    out = dict(lead=draw(st.sampled_from([0.0, 2.0, 10.0, 3600.0])),
               p_due=draw(st.sampled_from([0.05, 0.1, 0.5, 0.99])))
    if kind != "none":
        out["prior_mean"] = draw(st.floats(5.0, 150.0))
        out["prior_sd"] = 0.0 if kind == "zero_sd" else draw(st.floats(0.01, 40.0))
    return out


@st.composite
def random_log(draw, wear=False):
    """A random log; ``wear`` favours long tests past the baseline (many §5a windows)."""
    if wear:
        p = MethodParams(
            t_set=0.5, w_ss=draw(st.sampled_from([0.2, 0.4])), w_hold=draw(st.sampled_from([0.4, 1.0])),
            tau=draw(st.sampled_from([0.3, 2.0])), tau_g=draw(st.sampled_from([0.1, 1.0])),
            stop_after=draw(st.sampled_from([1.0, 10.0])), delta=draw(st.sampled_from([0.1, 0.25])),
            end_slot=draw(st.sampled_from([None, 2500, 4000])),
            h_warn=draw(st.sampled_from([0.5, 0.9])), n_warn=draw(st.sampled_from([1, 3, 5])),
            trend_windows=draw(st.sampled_from([10, 25, 60])), **draw(prior_params()))
        return _make_log(draw, p, n=draw(st.integers(1500, 6000)), max_events=6)
    p = MethodParams(
        t_set=0.5, w_ss=draw(st.sampled_from([0.6, 1.0])), w_hold=draw(st.sampled_from([1.0, 2.0, 3.0])),
        tau=draw(st.sampled_from([0.3, 0.5])), tau_g=draw(st.sampled_from([0.0, 0.1, 0.2, 1.0])),
        stop_after=draw(st.sampled_from([0.0, 0.2, 1.0])), delta=draw(st.sampled_from([0.1, 0.25])),
        t_end=draw(st.sampled_from([None, None, 60.0, 90.0])),
        end_slot=draw(st.sampled_from([None, None, None, 0, 1, 2000, 3001, 4500])),
        h_warn=draw(st.sampled_from([0.5, 0.9, 1.2])), n_warn=draw(st.sampled_from([1, 2, 5])),
        trend_windows=draw(st.sampled_from([10, 12, 60])), **draw(prior_params()),
    )
    return _make_log(draw, p, n=draw(st.integers(0, 5000)), max_events=25)


def _make_log(draw, p, n, max_events):
    seed = draw(st.integers(0, 2**32 - 1))
    rng = np.random.default_rng(seed)
    onset = draw(st.integers(0, 5000))
    k = np.arange(n)
    mu = 0.25 + draw(st.sampled_from([0.0005, 0.002, 0.006])) * rng.standard_normal(n)
    mu += np.where(k > onset, (k - onset) * draw(st.sampled_from([1e-5, 1e-4, 1e-3])), 0.0)
    mean = 0.5 + 0.01 * rng.standard_normal(n)
    theta = math.radians(105)
    e = np.exp(mu * theta)
    t1 = np.round(2 * mean / (1 + e), 3)
    t2 = np.round(t1 * e, 3)
    present = np.ones(n, dtype=bool)
    n_g, n_stop = p.n_g, p.n_stop
    for _ in range(draw(st.integers(0, max_events))):
        kind = draw(st.sampled_from(EVENT_KINDS))
        if n == 0:
            break
        at = draw(st.integers(0, n - 1))
        length = {"burst": draw(st.integers(1, 80)), "gap_ng": n_g, "gap_ng1": n_g + 1,
                  "gap_stop": n_stop, "gap_stop1": n_stop + 1}.get(kind, 1)
        sl = slice(at, min(n, at + max(length, 1)))
        if kind in ("dropout", "burst", "gap_ng", "gap_ng1", "gap_stop", "gap_stop1"):
            present[sl] = False
        elif kind == "spike":
            t2[sl] += draw(st.sampled_from([0.25, 0.2500001, 0.3, 1.0]))
        elif kind == "low":
            t1[sl] = draw(st.sampled_from([0.0, 0.01, 0.025, -0.1]))
        elif kind == "ratio_low":
            t2[sl] = t1[sl]
        elif kind == "ratio_high":
            t2[sl] = t1[sl] * 4.3
        elif kind == "saturation":
            t2[sl] = draw(st.sampled_from([4.9, 4.95, 5.0]))
        elif kind == "nan":
            t1[sl] = draw(st.sampled_from([math.nan, math.inf]))
    t1[~present] = np.nan
    t2[~present] = np.nan
    if p.n_grid is not None:
        # a planned end: the log may stop early (the rest is MISSING) or run past it (ignored)
        m = p.n_grid
        if n >= m:
            present, t1, t2 = present[:m], t1[:m], t2[:m]
        else:
            pad = m - n
            present = np.concatenate([present, np.zeros(pad, bool)])
            t1 = np.concatenate([t1, np.full(pad, np.nan)])
            t2 = np.concatenate([t2, np.full(pad, np.nan)])
    return p, present, t1, t2


@settings(max_examples=1500, deadline=None, suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
@given(random_log())
def test_streaming_equals_batch(case):
    _streaming_equals_batch(*case)


@settings(max_examples=400, deadline=None, suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
@given(random_log(wear=True))
def test_streaming_equals_batch_past_the_baseline(case):
    """end_slot, headroom, projection, forecast and warning (§3, §5a, §5b) on long tests with many
    windows."""
    _streaming_equals_batch(*case)


@st.composite
def log_with_lost_spans(draw):
    """A random log and LOST spans (a disk outage longer than the recorder's reserve, the
    gateway extension ``rules.LOST``): anywhere, also over gaps, unsafe runs and the baseline."""
    p, present, t1, t2 = draw(random_log(wear=draw(st.booleans())))
    n = len(present)
    spans = []
    for _ in range(draw(st.integers(1, 4)) if n else 0):
        a = draw(st.integers(0, n - 1))
        spans.append([a, a + draw(st.sampled_from([0, 1, p.n_stop, p.n_stop + 1, 40, 300, 2000]))])
    return p, present, t1, t2, spans


@settings(max_examples=600, deadline=None, suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
@given(log_with_lost_spans())
def test_streaming_equals_batch_with_lost_slots(case):
    """LOST slots fed one by one (as the station does when its recorder refuses them) give the
    batch form over the same slots marked from ``lost_spans`` (as ``hookwatch analyze`` does)."""
    p, present, t1, t2, spans = case
    s = mark_lost(SlotArrays(present, t1, t2), spans)
    n_lost = 0 if s.lost is None else int(s.lost.sum())
    res = _streaming_equals_batch(p, s.present, s.t1, s.t2, s.lost)
    counted = res.reasons.get("LOST", 0)
    assert ("LOST" in res.reasons) == (counted > 0)
    assert counted <= n_lost
    event(f"lost slots counted {min(counted, 1)}")


def test_lost_slots_neither_count_toward_nor_break_a_protection_stop():
    p = MethodParams(t_set=0.5, w_ss=0.6, w_hold=1.0, tau=0.3, tau_g=0.1, stop_after=0.2, delta=0.1)
    n = 400
    present = np.ones(n, dtype=bool)
    t1, t2 = np.full(n, 0.3), np.full(n, 0.6)
    # a MISSING run of n_stop slots, then LOST slots, then one more MISSING: the run goes on
    present[100:100 + p.n_stop] = False
    present[100 + p.n_stop + 50] = False
    lost = np.zeros(n, dtype=bool)
    lost[100 + p.n_stop:100 + p.n_stop + 50] = True
    t1[~present], t2[~present] = np.nan, np.nan
    s = SlotArrays(present & ~lost, t1, t2, lost=lost)
    r = _streaming_equals_batch(p, s.present, s.t1, s.t2, lost, stats=False)
    assert r.status == "aborted" and r.stop_slot == 100 + p.n_stop + 50, r
    assert r.stop_reasons == ["MISSING"] and r.reasons["LOST"] == 50
    # LOST slots alone (a long disk outage) never stop a test, however long
    lost2 = np.zeros(n, dtype=bool)
    lost2[50:350] = True
    r2 = _streaming_equals_batch(p, ~lost2, np.where(lost2, np.nan, 0.3), np.where(lost2, np.nan, 0.6), lost2,
                                stats=False)
    assert r2.stop_slot is None and r2.reasons["LOST"] == 300 and r2.reasons["MISSING"] == 0


def test_no_lost_slot_no_lost_key():
    """METHOD.md's reasons are unchanged for a test without LOST slots (the vectors compare them)."""
    p = MethodParams(t_set=0.5, w_ss=0.6, w_hold=1.0, tau=0.3, tau_g=0.1, stop_after=0.2, delta=0.1)
    n = 200
    r = _streaming_equals_batch(p, np.ones(n, dtype=bool), np.full(n, 0.3), np.full(n, 0.6), stats=False)
    assert "LOST" not in r.reasons


def _streaming_equals_batch(p, present, t1, t2, lost=None, stats=True):
    batch = analyze_slots(SlotArrays(present, t1, t2, lost=lost), p)
    mask, ratio, mu = gate_arrays(present, t1, t2, p, lost)
    lost_l = [False] * len(present) if lost is None else lost.tolist()
    mon = StreamingMonitor(p)
    windows = []
    forecasts = []
    warned = []
    for k in range(len(present)):
        if mon.finished:
            break
        out = mon.push(bool(present[k]), float(t1[k]), float(t2[k]), lost_l[k])
        assert out.mask == mask[k]
        assert out.q == (mask[k] == 0)
        if out.mu is None:
            assert math.isnan(mu[k])
        else:
            assert out.mu == mu[k]
        if out.ratio is None:
            assert math.isnan(ratio[k])
        else:
            assert out.ratio == ratio[k]
        if out.window is not None:
            assert "window" in out.events and out.window.last_slot == k
            windows.append(out.window)
        if out.forecast is not None:
            assert "forecast" in out.events and out.forecast.last_slot == k
            forecasts.append(out.forecast)
        if "wear_warning" in out.events:
            warned.append(k)
    stream = mon.close(len(present))
    assert stream.as_dict() == batch.as_dict()
    # §5a window by window: the streaming form published exactly the batch form's windows (those
    # the streaming form completed before close() padded the rest with MISSING slots)
    g = gate_and_baseline(SlotArrays(present, t1, t2, lost=lost), p)
    assert [(w.j, w.n_eff, w.value) for w in windows] == g.windows[:len(windows)]
    if windows:
        last = [w for w in windows if w.value is not None]
        if len(windows) == len(g.windows) and last:
            assert stream.headroom == last[-1].headroom and stream.t_cross == last[-1].t_cross
    assert warned == ([stream.warn_slot] if stream.warn_slot is not None and warned else [])
    # §5b at every forecast time: every key (e10/e50/e90, P, headroom, t_cross, due, reasons,
    # warning) of the streaming form equals the batch form's, bit for bit
    res, bwins, bfore = life_detail(g)
    assert res.as_dict() == batch.as_dict()
    assert windows == bwins[:len(windows)]
    assert forecasts == bfore[:len(forecasts)]
    assert [f.last_slot for f in bfore if f.warning] == ([] if batch.warn_slot is None else [batch.warn_slot])
    if batch.k_life is not None:
        assert all(f.last_slot < batch.k_life + p.n_tau - 1 for f in bfore)
    if bfore:
        last = bfore[-1]
        assert (batch.end_p10, batch.end_p50, batch.end_p90, batch.p_end) == (last.e10, last.e50, last.e90, last.p_end)
        if batch.warn_slot is not None:
            first_due = next(f for f in bfore if f.due)
            assert (first_due.last_slot, list(first_due.reasons)) == (batch.warn_slot, batch.warn_reasons)
    else:
        assert batch.warn_slot is None and batch.p_end is None
    if not stats:
        return stream
    event(f"forecast times {min(len(bfore), 3)}+, warn {batch.warn_reasons}")
    event(f"status {stream.status}{' STOPPED' if stream.stop_reasons == ['STOPPED'] else ''}")
    event(f"warning {stream.warn_slot is not None}, projection {stream.t_cross is not None}, "
          f"headroom {stream.headroom is not None}")
    if p.end_slot is not None and stream.status == "aborted" and stream.stop_reasons == ["STOPPED"]:
        assert stream.stop_slot == p.end_slot == stream.n_slots
    return stream


def test_gap_of_ng_keeps_count_and_ng_plus_one_resets():
    """§5 at the boundary: a gap of exactly N_g non-exceeding slots keeps c, N_g + 1 resets it."""
    p = MethodParams(t_set=0.5, w_ss=1.0, w_hold=1.0, tau=1.0, tau_g=0.1, stop_after=10.0)
    n_ss, n_tau, n_g = p.n_ss, p.n_tau, p.n_g
    theta = p.theta

    def run(gap):
        mu = [0.25] * n_ss + [0.4] * (n_tau - 10) + [0.25] * gap + [0.4] * 10 + [0.25] * 200
        t1 = np.full(len(mu), 0.4)
        t2 = np.round(t1 * np.exp(np.array(mu) * theta), 12)
        present = np.ones(len(mu), bool)
        r = analyze_slots(SlotArrays(present, t1, t2), p)
        mon = StreamingMonitor(p)
        for a, b in zip(t1, t2):
            mon.push(True, float(a), float(b))
        assert mon.result().as_dict() == r.as_dict()
        return r

    kept = run(n_g)
    assert kept.status == "failure"
    # c reached N_τ at the last exceeding slot; k_life = k − N_τ + 1
    assert kept.k_life == n_ss + n_tau - 10 + n_g + 10 - 1 - n_tau + 1
    reset = run(n_g + 1)
    assert reset.status == "no_failure"


def test_protection_stop_on_the_51st_missing_slot():
    p = MethodParams(t_set=0.5)
    n = 400
    t1 = np.full(n, 0.3)
    t2 = np.full(n, 0.6)
    for gap, expect_stop in ((50, False), (51, True)):
        present = np.ones(n, bool)
        present[100:100 + gap] = False
        r = analyze_slots(SlotArrays(present, t1.copy(), t2.copy()), p)
        if expect_stop:
            assert r.status == "aborted" and r.stop_slot == 150 and r.stop_reasons == ["MISSING"]
            assert r.n_slots == 151
        else:
            assert r.stop_slot is None and r.n_slots == n
