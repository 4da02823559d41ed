"""The report's figures (PNG, matplotlib Agg, no pyplot state): the paper's Fig. 7 per sample,
Fig. 8 (open vs closed loop), Fig. 9 (t_life by grade and setpoint).

Every figure is :data:`WIDTH_PX` × :data:`HEIGHT_PX` pixels. Long logs are decimated for plotting
with a min/max envelope per pixel column (:func:`minmax_columns`): a single-slot spike in a 10-hour
log stays visible.
"""
from __future__ import annotations

import math
import os
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from ...core.method import rules as R
from .stats import group_stats

# (column centres, column minima, column maxima): what envelope_xy() draws
Envelope = tuple[np.ndarray, np.ndarray, np.ndarray]

WIDTH_PX = 1600
HEIGHT_PX = 1000
DPI = 100
#: envelope columns per plot (≥ the axes' width in pixels)
COLUMNS = 1600

GRADE_COLORS = ("#1f77b4", "#d62728", "#2ca02c", "#9467bd", "#8c564b", "#e377c2", "#7f7f7f")


# ---------------------------------------------------------------------------------------------
# Decimation (pure numpy)
# ---------------------------------------------------------------------------------------------

def minmax_columns(x: np.ndarray, y: np.ndarray, x0: float, x1: float, ncols: int = COLUMNS
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Min and max of the finite ``y`` in each of ``ncols`` equal columns of [x0, x1].
    ``x`` must be non-decreasing. Returns (column centre, min, max) for the non-empty columns."""
    x = np.asarray(x, dtype=np.float64)
    y = np.asarray(y, dtype=np.float64)
    ok = np.isfinite(y) & np.isfinite(x)
    if not ok.all():
        x, y = x[ok], y[ok]
    if x.size == 0 or not x1 > x0:
        return np.empty(0), np.empty(0), np.empty(0)
    w = (x1 - x0) / ncols
    col = np.clip(((x - x0) / w).astype(np.int64), 0, ncols - 1)
    starts = np.flatnonzero(np.r_[True, col[1:] != col[:-1]])
    lo = np.minimum.reduceat(y, starts)
    hi = np.maximum.reduceat(y, starts)
    xc = x0 + (col[starts] + 0.5) * w
    return xc, lo, hi


def grid_minmax(y: np.ndarray, dx: float, x_end: float, ncols: int = COLUMNS
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`minmax_columns` for samples on a uniform grid x = i·dx (slot arrays, NaN where
    there is no value): the column bounds are computed, not searched, and NaN is skipped by
    fmin/fmax without copying the finite values out first."""
    y = np.asarray(y, dtype=np.float64)
    n = y.size
    if n == 0 or not x_end > 0:
        return np.empty(0), np.empty(0), np.empty(0)
    w = x_end / ncols
    col = np.clip((np.arange(n) * dx / w).astype(np.int64), 0, ncols - 1)
    starts = np.flatnonzero(np.r_[True, col[1:] != col[:-1]])
    with np.errstate(invalid="ignore"):
        lo = np.fmin.reduceat(y, starts)
        hi = np.fmax.reduceat(y, starts)
    ok = np.isfinite(lo) & np.isfinite(hi)
    xc = (col[starts] + 0.5) * w
    return xc[ok], lo[ok], hi[ok]


def envelope_xy(xc: np.ndarray, lo: np.ndarray, hi: np.ndarray, max_gap: float
                ) -> tuple[np.ndarray, np.ndarray]:
    """A polyline that draws each column as a vertical stroke from min to max and joins
    neighbouring columns; it breaks (NaN) where columns are more than ``max_gap`` apart."""
    n = xc.size
    if n == 0:
        return np.empty(0), np.empty(0)
    x = np.repeat(xc, 2)
    y = np.empty(2 * n)
    y[0::2] = lo
    y[1::2] = hi
    gaps = np.flatnonzero(np.diff(xc) > max_gap)
    if gaps.size:
        ins = 2 * (gaps + 1)
        x = np.insert(x, ins, np.nan)
        y = np.insert(y, ins, np.nan)
    return x, y


def column_hits(x: np.ndarray, x0: float, x1: float, ncols: int = COLUMNS) -> np.ndarray:
    """Centres of the columns that hold at least one of the positions ``x``."""
    if x.size == 0 or not x1 > x0:
        return np.empty(0)
    w = (x1 - x0) / ncols
    col = np.unique(np.clip(((x - x0) / w).astype(np.int64), 0, ncols - 1))
    return x0 + (col + 0.5) * w


def time_unit(span_s: float) -> tuple[str, float]:
    if span_s > 3 * 3600:
        return "h", 3600.0
    if span_s > 300:
        return "min", 60.0
    return "s", 1.0


def fmt_s(x: float | None, nd: int = 1) -> str:
    return "—" if x is None else f"{x:,.{nd}f}"


# ---------------------------------------------------------------------------------------------
# matplotlib plumbing
# ---------------------------------------------------------------------------------------------

def _figure(nrows: int = 1, height_ratios: Sequence[float] | None = None, sharex: bool = False):
    import matplotlib
    matplotlib.use("Agg", force=False)
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(WIDTH_PX / DPI, HEIGHT_PX / DPI), dpi=DPI)
    FigureCanvasAgg(fig)
    kw = {"height_ratios": height_ratios} if height_ratios else {}
    axes = fig.subplots(nrows, 1, sharex=sharex, gridspec_kw=kw, squeeze=False)[:, 0]
    return fig, list(axes)


def _save(fig, path: str) -> None:
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    tmp = path + ".tmp.png"
    # zlib level 3: a tenth of the time of the default 6 for ~10 % larger files
    fig.savefig(tmp, dpi=DPI, format="png", pil_kwargs={"compress_level": 3})
    os.replace(tmp, path)


def _literal_text(render):
    """Draw every text of a figure literally: sample ids, grades and titles come from operators
    (``S$1_^2``, ``\\x``) and are never TeX or mathtext (a ``$`` in a sample id must not change or
    break its figure). The figures' own labels use Unicode (μ, θ), no mathtext."""
    import functools

    @functools.wraps(render)
    def wrapped(*args, **kwargs):
        import matplotlib
        with matplotlib.rc_context({"text.usetex": False, "text.parse_math": False}):
            return render(*args, **kwargs)
    return wrapped


def _style(ax) -> None:
    ax.grid(True, alpha=0.3, lw=0.6)
    ax.tick_params(labelsize=12)


# ---------------------------------------------------------------------------------------------
# Fig. 7: μ(t) of one sample, tensions below
# ---------------------------------------------------------------------------------------------

@dataclass
class Fig7Data:
    """Everything Fig. 7 draws, already decimated (small: safe to send between processes)."""
    title: str
    unit: str
    scale: float
    x_end: float
    mu: Envelope             # (xc, lo, hi) valid μ
    bad: Envelope            # (xc, lo, hi) ln(R)/θ of gated-out slots where R is defined
    missing: np.ndarray      # column centres holding MISSING slots
    t1: Envelope
    t2: Envelope
    tm: Envelope             # (T1 + T2) / 2
    t_set: float
    mu_ss: float | None
    mu_th: float | None
    delta: float
    stable: tuple[float, float] | None     # (start, end) in plot units
    t_life: float | None     # in s
    stop: float | None       # protection stop, in s
    status: str
    valid_pct: float
    reasons: str
    stopped: bool = False    # ended on purpose (STOPPED, METHOD.md §3), not a protection stop
    windows: tuple = ()      # §5a post-baseline windows: (x0, x1, μ̃ with NaN = no value) in plot units
    h_warn: float = 0.5
    warn: float | None = None  # §5a early warning, in s


def fig7_data(*, title: str, ts: float, mask: np.ndarray, mu: np.ndarray, ratio: np.ndarray,
              t1: np.ndarray, t2: np.ndarray, p, result: dict, windows=()) -> Fig7Data:
    """Decimate one analysed test for Fig. 7. ``mask``/``mu``/``ratio`` from the method core's
    gating (cut at a protection stop), ``t1``/``t2`` on the slot grid (NaN where absent),
    ``windows`` the §5a windows after the baseline as (j, N_eff, μ̃ or None)."""
    n_grid = max(t1.size, mask.size, p.n_grid or 0)
    span = max(n_grid * ts, ts)
    unit, scale = time_unit(span)
    x_end = span / scale
    dx = ts / scale
    mu_env = grid_minmax(mu, dx, x_end)
    with np.errstate(invalid="ignore", divide="ignore"):
        diag = np.where((mask != 0) & (ratio > 0), np.log(ratio) / p.theta, np.nan)
    bad_env = grid_minmax(diag, dx, x_end)
    missing = column_hits(np.flatnonzero((mask & R.MISSING) != 0) * dx, 0.0, x_end)
    with np.errstate(invalid="ignore"):
        tm = (t1 + t2) / 2.0
    stable = None
    if result.get("k_b") is not None and result.get("stable_first") is not None:
        stable = (result["stable_first"] * ts / scale, (result["k_b"] + 1) * ts / scale)
    reasons = ", ".join(f"{k} {v:,}" for k, v in (result.get("reasons") or {}).items() if v)
    n_slots = result.get("n_slots") or 0
    w_s = p.n_ss * ts / scale
    wins = (np.array([j * w_s for j, _, _ in windows]), np.array([(j + 1) * w_s for j, _, _ in windows]),
            np.array([np.nan if v is None else v for _, _, v in windows], dtype=np.float64))
    warn_slot = result.get("warn_slot")
    return Fig7Data(
        title=title, unit=unit, scale=scale, x_end=x_end, mu=mu_env, bad=bad_env, missing=missing,
        t1=grid_minmax(t1, dx, x_end), t2=grid_minmax(t2, dx, x_end), tm=grid_minmax(tm, dx, x_end),
        t_set=p.t_set, mu_ss=result.get("mu_ss"),
        mu_th=result.get("mu_th"), delta=p.delta, stable=stable, t_life=result.get("t_life"),
        stop=None if result.get("stop_slot") is None else result["stop_slot"] * ts,
        status=result.get("status", "?"),
        valid_pct=100.0 * (result.get("n_valid") or 0) / n_slots if n_slots else 0.0,
        reasons=reasons or "none", stopped=result.get("stop_reasons") == ["STOPPED"],
        windows=wins if windows else (), h_warn=p.h_warn,
        warn=None if warn_slot is None else (warn_slot + 1) * ts)


def _draw_headroom(ax, d: Fig7Data) -> None:
    """§5a on the μ axis: each post-baseline window's median μ̃ as a segment over the window
    (those under h_warn in another colour), and a headroom scale on the right (h is linear in μ̃:
    1 at μ_ss, 0 at μ_th)."""
    if d.mu_ss is None or d.mu_th is None or d.mu_th == d.mu_ss:
        return
    from matplotlib import patheffects as pe

    mu_ss, mu_th = d.mu_ss, d.mu_th
    if len(d.windows):
        x0, x1, v = d.windows
        ok = np.isfinite(v)
        h = (mu_th - v[ok]) / (mu_th - mu_ss)
        low = h < d.h_warn
        for sel, color, label in ((~low, "#8c564b", "window median μ̃ (headroom windows)"),
                                  (low, "#e377c2", f"window median μ̃ with headroom < {d.h_warn:g}")):
            if sel.any():
                ax.hlines(v[ok][sel], x0[ok][sel], x1[ok][sel], color=color, lw=3.0, label=label,
                          zorder=4, path_effects=[pe.withStroke(linewidth=5.0, foreground="white")])
    ax.axhline(mu_th - d.h_warn * (mu_th - mu_ss), color="#e377c2", lw=0.8, ls=":", alpha=0.8)
    sec = ax.secondary_yaxis("right", functions=(lambda m: (mu_th - m) / (mu_th - mu_ss),
                                                 lambda hh: mu_th - hh * (mu_th - mu_ss)))
    sec.set_ylabel("headroom h", fontsize=13)
    sec.tick_params(labelsize=11)


@_literal_text
def render_fig7(d: Fig7Data, path: str):
    """Draw and save Fig. 7; returns the figure (its texts, for checks)."""
    fig, (ax, axt) = _figure(2, (2.2, 1.0), sharex=True)
    col_w = d.x_end / COLUMNS
    gap = 3 * col_w
    # --- μ
    x, y = envelope_xy(*d.mu, gap)
    ax.plot(x, y, color="#1f77b4", lw=0.8, label="μ (valid slots)")
    lo_parts = [d.mu[1]] if d.mu[1].size else []
    hi_parts = [d.mu[2]] if d.mu[2].size else []
    for v in (d.mu_ss, d.mu_th):
        if v is not None:
            lo_parts.append(np.array([v]))
            hi_parts.append(np.array([v]))
    if lo_parts:
        ylo = float(min(a.min() for a in lo_parts))
        yhi = float(max(a.max() for a in hi_parts))
    else:
        ylo, yhi = 0.0, 1.0
    pad = 0.06 * max(yhi - ylo, 0.02)
    ylo, yhi = ylo - pad, yhi + pad
    if d.bad[0].size:
        bl = np.clip(d.bad[1], ylo, yhi)
        bh = np.clip(d.bad[2], ylo, yhi)
        ax.scatter(np.r_[d.bad[0], d.bad[0]], np.r_[bl, bh], s=6, color="#d62728", alpha=0.6,
                   lw=0, label="gated out (invalid, shown as ln(R)/θ, clipped)", zorder=3)
    if d.missing.size:
        ax.vlines(d.missing, 0.0, 0.035, transform=ax.get_xaxis_transform(), color="#7f0000",
                  lw=1.0, label="missing slots")
    if d.stable is not None:
        a, b = (x * d.scale for x in d.stable)
        span = (f"{a / 3600:,.2f}–{b / 3600:,.2f} h" if d.unit == "h" else f"{a:,.1f}–{b:,.1f} s")
        ax.axvspan(d.stable[0], d.stable[1], color="#2ca02c", alpha=0.15,
                   label=f"stable segment ({span})")
    if d.mu_ss is not None and d.stable is not None:
        ax.hlines(d.mu_ss, d.stable[0], d.x_end, color="#2ca02c", lw=2.0,
                  label=f"baseline μ_ss = {d.mu_ss:.4f}")
    if d.mu_th is not None and d.stable is not None:
        ax.hlines(d.mu_th, d.stable[1], d.x_end, color="#ff7f0e", lw=2.0, ls="--",
                  label=f"threshold μ_th = (1 + {d.delta:g})·μ_ss = {d.mu_th:.4f}")
    _draw_headroom(ax, d)
    for a in (ax, axt):
        if d.warn is not None:
            a.axvline(d.warn / d.scale, color="#e377c2", lw=2.0, ls="-.",
                      label=f"early warning at {d.warn:,.1f} s" if a is ax else None)
        if d.t_life is not None:
            a.axvline(d.t_life / d.scale, color="#d62728", lw=2.0,
                      label=f"t_life = {d.t_life:,.1f} s" if a is ax else None)
        if d.stop is not None:
            what = "ended on purpose (STOPPED)" if d.stopped else "protection stop"
            a.axvline(d.stop / d.scale, color="black", lw=1.5, ls=":",
                      label=f"{what} at {d.stop:,.1f} s" if a is ax else None)
    ax.set_ylim(ylo, yhi)
    ax.set_xlim(0.0, d.x_end)
    ax.set_ylabel("equivalent friction coefficient μ", fontsize=14)
    ax.set_title(d.title, fontsize=17)
    ax.text(0.005, 0.97, f"status: {d.status}    valid slots: {d.valid_pct:.1f} %\n"
            f"invalid by reason: {d.reasons}", transform=ax.transAxes, va="top", ha="left",
            fontsize=11, bbox={"boxstyle": "round", "fc": "white", "ec": "#999999", "alpha": 0.85})
    ax.legend(loc="upper left", bbox_to_anchor=(0.0, 0.86), fontsize=11, framealpha=0.85)
    _style(ax)
    # --- tensions
    for env, color, label in ((d.t1, "#17becf", "T1 (slack side)"), (d.t2, "#9467bd", "T2 (tight side)"),
                              (d.tm, "black", "(T1 + T2)/2")):
        x, y = envelope_xy(*env, gap)
        axt.plot(x, y, color=color, lw=0.7, label=label)
    axt.axhline(d.t_set, color="#7f7f7f", ls="--", lw=1.2, label=f"T_set = {d.t_set:g} N")
    tops = [e[2].max() for e in (d.t1, d.t2, d.tm) if e[2].size]
    bots = [e[1].min() for e in (d.t1, d.t2, d.tm) if e[1].size]
    if tops:   # headroom for the legend above the curves
        lo, hi = min(min(bots), 0.0), max(max(tops), d.t_set)
        axt.set_ylim(lo, hi + 0.3 * (hi - lo))
    axt.set_ylabel("tension (N)", fontsize=14)
    axt.set_xlabel(f"time ({d.unit})", fontsize=14)
    axt.legend(loc="upper right", fontsize=11, ncol=4, framealpha=0.85)
    _style(axt)
    # room on the right for the headroom scale (§5a) when there is a baseline
    right = 0.94 if d.mu_ss is not None and d.mu_th is not None else 0.985
    fig.subplots_adjust(left=0.07, right=right, top=0.95, bottom=0.07, hspace=0.08)
    _save(fig, path)
    return fig


# ---------------------------------------------------------------------------------------------
# Fig. 8: open loop vs closed loop
# ---------------------------------------------------------------------------------------------

@dataclass
class LoopSeries:
    label: str
    x: Envelope       # envelope of (T1 + T2)/2 over time (plot units)
    smooth: tuple     # (x, running mean over ≥ 1 s) for a line
    hist: tuple       # (bin edges, counts) of the deviation from T_set
    mean: float
    sd: float
    drift_per_h: float
    within_pct: float  # share of readings within ±5 % of T_set


def loop_series(label: str, t: np.ndarray, t1: np.ndarray, t2: np.ndarray, t_set: float,
                scale: float, x_end: float, edges: np.ndarray, settled: float = -math.inf) -> LoopSeries:
    """The mean tension of one log for Fig. 8; statistics over the readings from ``settled`` on
    (after the start-up)."""
    ok = np.isfinite(t) & np.isfinite(t1) & np.isfinite(t2)
    t, tm = t[ok], (t1[ok] + t2[ok]) / 2.0
    order = np.argsort(t, kind="stable")
    t, tm = t[order], tm[order]
    env = minmax_columns(t / scale, tm, 0.0, x_end)
    keep = t >= settled
    t, tm = t[keep], tm[keep]
    if t.size:
        win = max(1.0, (t[-1] - t[0]) / 600.0)      # ~600 points of running mean per plot
        sec = np.floor(t / win).astype(np.int64)
        starts = np.flatnonzero(np.r_[True, sec[1:] != sec[:-1]])
        counts = np.diff(np.r_[starts, t.size])
        sm = np.add.reduceat(tm, starts) / counts
        smooth = ((sec[starts] + 0.5) * win / scale, sm)
        mean = float(tm.mean())
        sd = float(tm.std(ddof=1)) if t.size > 1 else 0.0
        drift = float(np.polyfit(t / 3600.0, tm, 1)[0]) if t.size > 2 and t[-1] > t[0] else 0.0
        within = float(np.mean(np.abs(tm - t_set) <= 0.05 * t_set) * 100.0)
    else:
        smooth, mean, sd, drift, within = (np.empty(0), np.empty(0)), math.nan, math.nan, math.nan, math.nan
    hist = (edges, np.histogram(tm - t_set, bins=edges)[0])
    return LoopSeries(label, env, smooth, hist, mean, sd, drift, within)


@_literal_text
def render_fig8(open_s: LoopSeries, closed_s: LoopSeries, t_set: float, unit: str, x_end: float,
                path: str, title: str) -> None:
    fig, (ax, axh) = _figure(2, (1.6, 1.0))
    gap = 3 * x_end / COLUMNS
    for s, color in ((open_s, "#ff7f0e"), (closed_s, "#1f77b4")):
        x, y = envelope_xy(*s.x, gap)
        ax.plot(x, y, color=color, lw=0.5, alpha=0.35)
        ax.plot(s.smooth[0], s.smooth[1], color=color, lw=2.0,
                label=f"{s.label}: mean {s.mean:.3f} N, SD {s.sd:.3f} N, drift {s.drift_per_h:+.3f} N/h, "
                      f"{s.within_pct:.1f} % within ±5 %")
    ax.axhline(t_set, color="#7f7f7f", ls="--", lw=1.2, label=f"T_set = {t_set:g} N")
    edges = open_s.hist[0]
    if edges.size >= 2:   # the settled range (start-up clipped), with headroom for the legend
        ax.set_ylim(t_set + 1.3 * edges[0], t_set + 2.2 * edges[-1])
    ax.set_xlim(0.0, x_end)
    ax.set_xlabel(f"time ({unit})", fontsize=14)
    ax.set_ylabel("mean tension (T1 + T2)/2 (N)", fontsize=14)
    ax.set_title(title, fontsize=17)
    ax.legend(loc="upper right", fontsize=12, framealpha=0.85)
    _style(ax)
    for s, color in ((open_s, "#ff7f0e"), (closed_s, "#1f77b4")):
        edges, counts = s.hist
        tot = counts.sum()
        frac = counts / tot * 100.0 if tot else counts.astype(float)
        axh.stairs(frac, edges, color=color, lw=2.0, fill=False, label=s.label)
    axh.axvline(0.0, color="#7f7f7f", ls="--", lw=1.2)
    axh.set_xlabel("deviation from T_set (N)", fontsize=14)
    axh.set_ylabel("share of readings (%)", fontsize=14)
    axh.legend(loc="upper right", fontsize=12)
    _style(axh)
    fig.subplots_adjust(left=0.07, right=0.985, top=0.95, bottom=0.07, hspace=0.28)
    _save(fig, path)


# ---------------------------------------------------------------------------------------------
# Fig. 9: t_life by grade and setpoint
# ---------------------------------------------------------------------------------------------

@_literal_text
def render_fig9(points: dict[tuple[float, str], list[float]], grades: list[str],
                setpoints: list[float], rankings: dict[float, str], path: str, title: str) -> None:
    """Bars: mean t_life per (setpoint, grade) with ± one sample SD; dots: the samples."""

    fig, (ax,) = _figure(1)
    ng = max(1, len(grades))
    width = 0.8 / ng
    ymax = 0.0
    rng = np.random.default_rng(0)
    for gi, g in enumerate(grades):
        color = GRADE_COLORS[gi % len(GRADE_COLORS)]
        xs, means, sds = [], [], []
        for si, sp in enumerate(setpoints):
            vals = points.get((sp, g), [])
            if not vals:
                continue
            st = group_stats(vals)
            if st.mean is None:     # not reached: vals is not empty
                continue
            x = si - 0.4 + width * (gi + 0.5)
            xs.append(x)
            means.append(st.mean)
            sds.append(st.sd or 0.0)
            jit = (rng.random(len(vals)) - 0.5) * width * 0.5
            ax.scatter(x + jit, vals, s=60, color="white", edgecolor="black", zorder=4, lw=1.2)
            ymax = max(ymax, max(vals), st.mean + (st.sd or 0.0))
            top = max(st.mean + (st.sd or 0.0), max(vals))
            ax.text(x, top + 0.01 * top, f"{st.mean:,.0f} s\n(n = {st.n})", ha="center",
                    va="bottom", fontsize=12)
        if xs:
            ax.bar(xs, means, width * 0.92, yerr=sds, capsize=8, color=color, alpha=0.75,
                   label=f"Grade {g}", error_kw={"lw": 1.8, "ecolor": "black"})
    for si, sp in enumerate(setpoints):
        r = rankings.get(sp)
        if r:
            ax.text(si, ymax * 1.16, r, ha="center", va="bottom", fontsize=14, fontweight="bold")
    ax.set_xticks(range(len(setpoints)))
    ax.set_xticklabels([f"T_set = {sp:g} N" for sp in setpoints], fontsize=14)
    ax.set_xlim(-0.6, len(setpoints) - 0.4)
    ax.set_ylim(0.0, ymax * 1.28 if ymax > 0 else 1.0)
    ax.set_ylabel("online wear life t_life (s)", fontsize=14)
    ax.set_title(title, fontsize=17)
    ax.scatter([], [], s=60, color="white", edgecolor="black", label="samples")
    ax.legend(loc="upper right", fontsize=13)
    _style(ax)
    ax.grid(False, axis="x")
    fig.subplots_adjust(left=0.07, right=0.985, top=0.94, bottom=0.07)
    _save(fig, path)
