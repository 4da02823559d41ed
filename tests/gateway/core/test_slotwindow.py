"""The one slot-window accumulator (gateway/core/slotwindow.py): its figures equal those computed from
the whole list of records afterwards, for any records (NaN readings, missing slots, masks), and
splitting a stream into windows loses or counts twice no slot."""
import math

from hypothesis import given, settings
from hypothesis import strategies as st

from gateway.core.method.rules import REASONS
from gateway.core.records import SlotRecord
from gateway.core.slotwindow import SlotWindow

ALL_BITS = sum(bit for bit, _ in REASONS)
_tension = st.one_of(st.floats(-10.0, 10.0, allow_nan=False), st.just(math.nan))


@st.composite
def records(draw, k: int = 0) -> SlotRecord:
    present = draw(st.booleans())
    q = draw(st.integers(0, 1))
    return SlotRecord(
        k=k, t=k * 0.02, present=present,
        t1=draw(_tension) if present else math.nan, t2=draw(_tension) if present else math.nan,
        q=q, mask=draw(st.integers(0, ALL_BITS)), ratio=None,
        mu=draw(st.one_of(st.none(), st.floats(0.0, 1.0))) if q else None, mean_filt=0.0,
        speed_cmd=draw(st.floats(0.0, 300.0)), speed_act=draw(st.floats(0.0, 300.0)),
        saturated=draw(st.booleans()), lateness_s=draw(st.floats(0.0, 0.1)),
        rtt_s=draw(st.one_of(st.just(math.nan), st.floats(0.0, 0.05))))


def _reference(recs: list[SlotRecord]) -> dict:
    """The figures computed from the whole list, the plain way."""
    read = [r for r in recs if r.present and not math.isnan(r.t1) and not math.isnan(r.t2)]
    means = [(r.t1 + r.t2) * 0.5 for r in read]
    mus = [r.mu for r in recs if r.q and r.mu is not None]
    rtts = [r.rtt_s for r in recs if r.present and not math.isnan(r.rtt_s)]
    return {
        "n": len(recs), "n_present": sum(r.present for r in recs), "n_read": len(read),
        "t1": math.fsum(r.t1 for r in read) / len(read) if read else None,
        "t2": math.fsum(r.t2 for r in read) / len(read) if read else None,
        "mean": math.fsum(means) / len(means) if means else None,
        "min": min(means) if means else None, "max": max(means) if means else None,
        "n_valid": sum(1 for r in recs if r.q), "n_mu": len(mus),
        "mu": math.fsum(mus) / len(mus) if mus else None,
        "counts": {name: sum(1 for r in recs if r.mask & bit) for bit, name in REASONS},
        "n_sat": sum(r.saturated for r in recs),
        "late_max": max([0.0, *(r.lateness_s for r in recs)]), "rtt_max": max([0.0, *rtts]),
        "speed": (recs[-1].speed_cmd, recs[-1].speed_act) if recs else None,
    }


def _close(a: float | None, b: float | None) -> bool:
    return (a is None) == (b is None) and (a is None or math.isclose(a, b, rel_tol=1e-9, abs_tol=1e-9))


@settings(max_examples=200, deadline=None)
@given(st.lists(records(), max_size=60))
def test_a_window_holds_what_the_whole_list_says(recs):
    w = SlotWindow(5.0)
    for r in recs:
        w.add(r)
    ref = _reference(recs)
    assert w.t0 == 5.0
    assert (w.n, w.n_present, w.n_read, w.n_valid, w.n_mu, w.n_sat) == (
        ref["n"], ref["n_present"], ref["n_read"], ref["n_valid"], ref["n_mu"], ref["n_sat"])
    assert _close(w.t1_mean, ref["t1"]) and _close(w.t2_mean, ref["t2"])
    assert _close(w.tension_mean, ref["mean"]) and _close(w.mu_mean, ref["mu"])
    if ref["n_read"]:
        assert (w.mn, w.mx) == (ref["min"], ref["max"])
    assert w.reason_counts() == ref["counts"]
    assert list(w.reason_counts()) == [name for _, name in REASONS]
    assert (w.late_max, w.rtt_max) == (ref["late_max"], ref["rtt_max"])
    assert w.valid_ratio == (ref["n_valid"] / ref["n"] if recs else None)
    if recs:
        assert (w.speed_cmd, w.speed_act) == ref["speed"]
    # a NaN reading never reaches a sum
    assert not any(math.isnan(x) for x in (w.s1, w.s2, w.sm, w.s_mu))


@settings(max_examples=100, deadline=None)
@given(st.lists(records(), max_size=60), st.integers(1, 12))
def test_windows_of_a_stream_lose_and_double_no_slot(recs, every):
    """Closing a window every ``every`` slots (as a fleet worker's SLOTS frames do): the windows'
    counts add up to the whole stream's."""
    windows, w = [], SlotWindow()
    for r in recs:
        w.add(r)
        if w.n >= every:
            windows.append(w)
            w = SlotWindow()
    if w.n:
        windows.append(w)
    ref = _reference(recs)
    assert sum(x.n for x in windows) == ref["n"]
    assert sum(x.n_valid for x in windows) == ref["n_valid"]
    assert sum(x.n_read for x in windows) == ref["n_read"]
    assert {name: sum(x.reason_counts()[name] for x in windows) for _, name in REASONS} == ref["counts"]
    assert _close(math.fsum(x.s_mu for x in windows) / ref["n_mu"] if ref["n_mu"] else None, ref["mu"])


def test_an_empty_window_has_nothing_to_average():
    w = SlotWindow()
    assert (w.n, w.t1_mean, w.tension_mean, w.mu_mean, w.valid_ratio) == (0, None, None, None, None)
    assert w.reason_counts() == {name: 0 for _, name in REASONS}
    assert (w.speed_cmd, w.late_max, w.rtt_max) == (0.0, 0.0, 0.0) and math.isnan(w.speed_act)
