"""Figures: min/max decimation keeps spikes; Figs. 7–9 are PNGs of the stated size."""
import os

import numpy as np
import pytest

from gateway.core.method.core import gate_and_baseline, life_result, to_slots
from gateway.core.method.params import MethodParams
from gateway.offline.report import plots as F
from kit.images import png_info


def test_minmax_columns_keeps_a_single_spike_in_a_ten_hour_series():
    n = 1_800_000
    rng = np.random.default_rng(1)
    x = np.arange(n) * 0.02
    y = 0.26 + 0.002 * rng.standard_normal(n)
    y[1_234_567] = 0.9                       # one slot
    y[::997] = np.nan                        # gaps are skipped
    xc, lo, hi = F.minmax_columns(x, y, 0.0, n * 0.02, 1600)
    assert xc.size == 1600
    assert hi.max() == 0.9
    col = int(1_234_567 * 0.02 / (n * 0.02 / 1600))
    assert hi[col] == 0.9
    assert np.nanmin(y) == lo.min()
    # the grid form gives the same envelope
    g = F.grid_minmax(y, 0.02, n * 0.02, 1600)
    for a, b in zip(g, (xc, lo, hi)):
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-9)


def test_minmax_columns_equals_brute_force():
    rng = np.random.default_rng(2)
    x = np.sort(rng.uniform(0, 100, 5000))
    y = rng.standard_normal(5000)
    y[rng.random(5000) < 0.1] = np.nan
    xc, lo, hi = F.minmax_columns(x, y, 0.0, 100.0, 37)
    w = 100.0 / 37
    for c, a, b in zip(xc, lo, hi):
        j = int(c / w)
        sel = (np.clip((x / w).astype(int), 0, 36) == j) & np.isfinite(y)
        assert a == y[sel].min() and b == y[sel].max()
    # envelope polyline breaks at gaps
    ex, ey = F.envelope_xy(np.array([0.5, 1.5, 9.5]), np.zeros(3), np.ones(3), max_gap=2.0)
    assert np.isnan(ex).sum() == 1 and ex.size == 7


def _slots(n=20_000, seed=0):
    rng = np.random.default_rng(seed)
    p = MethodParams(t_set=0.5, w_ss=5, w_hold=20, tau=5, t_end=n * 0.02)
    k = np.arange(n)
    mu = 0.26 + 0.002 * rng.standard_normal(n) + np.where(k > 15000, 0.2 * ((k - 15000) / 5000) ** 2, 0)
    e = np.exp(mu * p.theta)
    t1 = np.round(1.0 / (1 + e), 3)
    t2 = np.round(t1 * e, 3)
    t2[9000] += 0.4                                   # a spike
    keep = rng.random(n) > 0.01
    keep[12000:12020] = False
    return p, to_slots(k[keep] * 0.02, t1[keep], t2[keep], p)


def test_fig7_png_size_and_content(tmp_path):
    p, s = _slots()
    g = gate_and_baseline(s, p)
    r = life_result(g).as_dict()
    assert r["status"] == "failure"
    d = F.fig7_data(title="Sample T-1 — Grade I, T_set 0.5 N", ts=p.ts, mask=g.mask, mu=g.mu,
                    ratio=g.ratio, t1=s.t1, t2=s.t2, p=p, result=r)
    assert d.bad[0].size > 0 and d.missing.size > 0 and d.stable is not None
    out = tmp_path / "f7.png"
    F.render_fig7(d, str(out))
    w, h, sd = png_info(out)
    assert (w, h) == (F.WIDTH_PX, F.HEIGHT_PX) == (1600, 1000)
    assert sd > 10


def test_fig7_without_baseline_and_fig9_fig8(tmp_path):
    p, s = _slots()
    g = gate_and_baseline(s, p.__class__(**{**p.as_dict(), "sigma_max": 1e-6}))
    r = life_result(g).as_dict()
    assert r["status"] == "no_baseline"
    d = F.fig7_data(title="no baseline", ts=p.ts, mask=g.mask, mu=g.mu, ratio=g.ratio,
                    t1=s.t1, t2=s.t2, p=p, result=r)
    F.render_fig7(d, str(tmp_path / "a.png"))
    F.render_fig9({(0.5, "I"): [300.0, 310.0, 320.0], (0.5, "II"): [200.0], (0.9, "I"): [250.0, 255.0]},
                  ["I", "II"], [0.5, 0.9], {0.5: "I > II", 0.9: "I"}, str(tmp_path / "b.png"), "Fig. 9")
    t = np.arange(5000) * 0.02
    edges = np.linspace(-0.1, 0.1, 41)
    o = F.loop_series("open loop", t, 0.2 + 0.01 * np.sin(t), 0.8 + 0.01 * np.sin(t), 0.5, 60.0, t[-1] / 60, edges)
    c = F.loop_series("closed loop", t, np.full(t.size, 0.19), np.full(t.size, 0.81), 0.5, 60.0, t[-1] / 60, edges)
    assert c.sd == pytest.approx(0.0, abs=1e-12) and c.within_pct == 100.0
    F.render_fig8(o, c, 0.5, "min", t[-1] / 60, str(tmp_path / "c.png"), "Fig. 8")
    for name in ("a.png", "b.png", "c.png"):
        w, h, sd = png_info(tmp_path / name)
        assert (w, h) == (1600, 1000) and sd > 10, name
    assert not [f for f in os.listdir(tmp_path) if f.endswith(".tmp.png")]


@pytest.mark.parametrize("sample", ["$x$", r"S$1_^2\frac{", "a_b^c\\d$", "$$"])
def test_fig7_and_fig9_draw_sample_ids_and_grades_literally(tmp_path, sample):
    """A sample id (or grade) is operator text, never mathtext or TeX: `$x$` is drawn as the four
    characters `$x$`, and `S$1_^2\\frac{` (unbalanced mathtext) still gives its figure."""
    import matplotlib

    p, s = _slots()
    g = gate_and_baseline(s, p)
    r = life_result(g).as_dict()
    title = f"Sample {sample} — Grade {sample}, T_set 0.5 N"
    d = F.fig7_data(title=title, ts=p.ts, mask=g.mask, mu=g.mu, ratio=g.ratio, t1=s.t1, t2=s.t2,
                    p=p, result=r)
    fig = F.render_fig7(d, str(tmp_path / "f7.png"))
    w, h, sd = png_info(tmp_path / "f7.png")
    assert (w, h) == (1600, 1000) and sd > 10
    t = fig.axes[0].title
    assert t.get_text() == title
    assert t.get_usetex() is False and t._parse_math is False    # the Text as it is drawn
    # the drawn text itself: an SVG with real <text> elements carries the characters as given
    svg = tmp_path / "f7.svg"
    with matplotlib.rc_context({"svg.fonttype": "none"}):
        fig.savefig(svg, format="svg")
    from xml.sax.saxutils import escape
    assert escape(title) in svg.read_text(encoding="utf-8")
    # Fig. 9 with the same text as a grade (legend) and in the rankings
    F.render_fig9({(0.5, sample): [300.0, 310.0], (0.5, "II"): [200.0]}, [sample, "II"], [0.5],
                  {0.5: f"{sample} > II"}, str(tmp_path / "f9.png"), f"Fig. 9 {sample}")
    w, h, sd = png_info(tmp_path / "f9.png")
    assert (w, h) == (1600, 1000) and sd > 10
