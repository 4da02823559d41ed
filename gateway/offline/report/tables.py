"""The paper's Tables 3–6 for a campaign, from the per-test results (pure: no I/O).

A sample enters the statistics only when its status is ``failure``, it has a grade, and its
sample ID is not a duplicate; every other sample is listed apart with the reason.
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

from ...core.method.forecast import band_at_half_life
from ...core.method.params import STOPPED
from ...core.method.prior import PastTest, PriorEntry, priors_by_group
from . import stats as S

STATUS_ERROR = "error"          # the log could not be read or the method not set up


@dataclass
class Column:
    key: str
    label: str               # for Markdown / HTML
    fmt: str = "text"        # text | int | f0…f6 (decimals) | pct1 | g | yesno
    csv_nd: int | None = None  # decimals written to CSV (None: as is)
    show: bool = True        # False: CSV only


@dataclass
class Table:
    name: str                # CSV file stem
    title: str
    columns: list[Column]
    rows: list[dict[str, Any]]
    notes: list[str] = field(default_factory=list)
    intro: str = ""


@dataclass
class Sample:
    """One test of the campaign after analysis."""
    sample_id: str
    grade: str | None
    t_set: float | None
    t_end_s: float | None
    rel: str
    status: str
    results: dict[float, dict] | None     # δ factor -> method result keys (None: not analysed)
    note: str = ""
    apart: str | None = None              # why it is not in the statistics (None: it is)
    fig: str | None = None                # Fig. 7 path relative to the report folder
    delta0: float | None = None
    ts: float = 0.02                      # sampling period of the test (slot → s)
    lead: float | None = None             # the planner's lead time of the test (§5b), s
    prior: tuple[float, float] | None = None   # (prior_mean, prior_sd) of its sidecar (§5b)
    window_s: float | None = None         # w_ss as slots · ts: the forecast times' spacing
    duplicate: bool = False               # its sample_id came before (the first one counts)

    @property
    def warn_s(self) -> float | None:
        """METHOD.md §5b early warning: the end of the first due window, s."""
        w = self.result().get("warn_slot")
        return None if w is None else (w + 1) * self.ts

    @property
    def warn_reasons(self) -> list[str] | None:
        return self.result().get("warn_reasons")

    @property
    def warn_lead_s(self) -> float | None:
        """t_life − the warning's time: how long ahead of the end the warning came (§5b)."""
        w, t = self.warn_s, self.t_life
        return None if w is None or t is None else t - w

    @property
    def headroom(self) -> float | None:
        """h of the last post-baseline window with a value (§5a)."""
        return self.result().get("headroom")

    @property
    def in_stats(self) -> bool:
        return self.apart is None

    def result(self, factor: float = 1.0) -> dict:
        return (self.results or {}).get(factor) or {}

    @property
    def t_life(self) -> float | None:
        return self.result().get("t_life")

    @property
    def mu_ss(self) -> float | None:
        return self.result().get("mu_ss")


def make_sample(spec, outcome: dict | None, factors: Sequence[float]) -> Sample:
    """Combine a test's sidecar description (campaign.TestSpec) and its worker outcome."""
    p = spec.params
    notes = list(spec.notes)
    results = None
    apart: str | None
    if p is None:
        status, apart = STATUS_ERROR, "method parameters unusable (see problems)"
    elif outcome is None or outcome.get("error"):
        status = STATUS_ERROR
        apart = "log unreadable (see problems)"
    else:
        results = outcome["results"]
        method_status = results[1.0]["status"]
        status = method_status
        r = results[1.0]
        stopped = r.get("stop_reasons") == [STOPPED]
        if spec.gateway_status == "aborted" and method_status == "failure":
            # METHOD.md §3: t_life found before the test was cut short stands
            why = spec.gateway_reason or "no reason given"
            notes.append(f"gateway: test aborted after t_life ({why}); t_life stands (METHOD.md §3)")
        elif spec.gateway_status == "aborted":
            status = "aborted"
            why = spec.gateway_reason or "no reason given"
            notes.append(f"gateway: test aborted ({why}); method: {method_status}")
        elif method_status == "failure" and r.get("interrupted"):
            what = "ended on purpose" if stopped else "protection stop"
            notes.append(f"{what} after t_life (interrupted); t_life stands (METHOD.md §3)")
        if method_status == "aborted" and stopped:
            notes.append(f"ended on purpose at {r['stop_slot'] * p.ts:,.2f} s (STOPPED) before any "
                         "t_life: the life is longer than that (censored), not in the statistics")
        elif method_status == "aborted" and r.get("stop_reasons"):
            notes.append(f"protection stop at {r['stop_slot'] * p.ts:,.2f} s "
                         f"({', '.join(r['stop_reasons'])})")
        apart = None if status == "failure" else status
        if status == "aborted" and stopped:
            apart = "aborted (STOPPED: ended on purpose before t_life)"
    if spec.duplicate_of is not None:
        notes.append(f"duplicate sample_id (first: {spec.duplicate_of})")
        apart = apart or "duplicate sample_id"
    if spec.grade is None and apart is None:
        apart = "no grade in the sidecar"
    prior = None
    if p is not None and p.prior_mean is not None and p.prior_sd is not None and p.prior_sd > 0:
        prior = (p.prior_mean, p.prior_sd)
    return Sample(spec.sample_id, spec.grade, None if p is None else p.t_set,
                  None if p is None else p.t_end, spec.rel, status, results,
                  note="; ".join(notes), apart=apart, delta0=None if p is None else p.delta,
                  ts=0.02 if p is None else p.ts, lead=None if p is None else p.lead,
                  prior=prior, window_s=None if p is None else p.n_ss * p.ts,
                  duplicate=spec.duplicate_of is not None)


def _sort_key(s: Sample):
    return (s.t_set if s.t_set is not None else float("inf"),
            (1, ("",)) if s.grade is None else (0, S.grade_sort_key(s.grade)), s.sample_id)


def sort_samples(samples: Sequence[Sample]) -> list[Sample]:
    return sorted(samples, key=_sort_key)


def _grades(samples: Sequence[Sample]) -> list[str]:
    return sorted({s.grade for s in samples if s.grade is not None}, key=S.grade_sort_key)


def _setpoints(samples: Sequence[Sample]) -> list[float]:
    return sorted({s.t_set for s in samples if s.t_set is not None})


# ---------------------------------------------------------------------------------------------
# Table 3 and the samples listed apart
# ---------------------------------------------------------------------------------------------

def table3(samples: Sequence[Sample]) -> Table:
    rows = []
    for s in sort_samples(samples):
        r = s.result()
        rows.append({"sample_id": s.sample_id, "grade": s.grade or "—", "t_set_N": s.t_set,
                     "t_end_h": None if s.t_end_s is None else s.t_end_s / 3600.0,
                     "t_life_s": s.t_life, "mu_ss": s.mu_ss, "status": s.status,
                     "warn_s": s.warn_s, "warn_lead_s": s.warn_lead_s,
                     "warn_reasons": "+".join(s.warn_reasons or []), "headroom": s.headroom,
                     "valid_pct": (100.0 * r["n_valid"] / r["n_slots"]) if r.get("n_slots") else None,
                     "note": s.note, "log": s.rel})
    return Table("table3_samples", "Table 3 — online wear life per sample", [
        Column("sample_id", "Sample ID"), Column("grade", "Grade"),
        Column("t_set_N", "T_set (N)", "g"), Column("t_end_h", "t_end (h)", "g", 4),
        Column("t_life_s", "t_life (s)", "f1", 2), Column("mu_ss", "μ_ss", "f4", 6),
        Column("status", "status"), Column("warn_s", "early warning (s)", "f1", 2),
        Column("warn_lead_s", "warning lead (s)", "f1", 2), Column("warn_reasons", "warned by"),
        Column("headroom", "last headroom", "f3", 6),
        Column("valid_pct", "valid slots (%)", "pct1", 2),
        Column("note", "note"), Column("log", "log"),
    ], rows, intro="Every test of the campaign at δ0 (the sidecar's δ). t_life exists only for "
                   "status failure. Early warning, its lead and last headroom (METHOD.md §5a, §5b, "
                   "informative): the end of the first due window (due by the life prior, a "
                   "headroom run or the trend), t_life minus that time, the reasons that held "
                   "there, and h = (μ_th − μ̃)/(μ_th − μ_ss) of the last window after the "
                   "baseline (1 at the baseline, 0 at the threshold).")


# ---------------------------------------------------------------------------------------------
# Prognosis (METHOD.md §5b)
# ---------------------------------------------------------------------------------------------

@dataclass
class Prognosis:
    """The §5b figures of one group of failures (or of all of them)."""
    n: int = 0                  # failures
    warned: int = 0             # with an early warning
    warned_lead: int = 0        # warned at least `lead` ahead of t_life
    late: int = 0               # warned after t_life (before the detection slot)
    with_prior: int = 0         # with a prior and a forecast time at half-life
    in_band: int = 0            # t_life inside [e10, e90] of the forecast at half-life

    def add(self, s: Sample) -> None:
        t = s.t_life
        if t is None:
            return
        self.n += 1
        lead_s = s.warn_lead_s
        if lead_s is not None:
            self.warned += 1
            if s.lead is not None and lead_s >= s.lead:
                self.warned_lead += 1
            if lead_s < 0:
                self.late += 1
        if s.prior is not None and s.lead is not None and s.window_s is not None:
            f = band_at_half_life(t, s.prior[0], s.prior[1], s.lead, s.window_s)
            if f is not None:
                self.with_prior += 1
                if f.e10 <= t <= f.e90:
                    self.in_band += 1

    @staticmethod
    def pct(k: int, n: int) -> float | None:
        return None if n == 0 else 100.0 * k / n


def prognosis(samples: Sequence[Sample]) -> dict[tuple[float, str] | None, Prognosis]:
    """Per (T_set, grade) over the samples in the statistics, and for all of them (key None)."""
    out: dict[tuple[float, str] | None, Prognosis] = {None: Prognosis()}
    for s in sort_samples(samples):
        if not s.in_stats or s.t_set is None or s.grade is None:
            continue
        out.setdefault((s.t_set, s.grade), Prognosis()).add(s)
        out[None].add(s)
    return out


def table_prognosis(samples: Sequence[Sample]) -> Table:
    rows = []
    leads = sorted({s.lead for s in samples if s.in_stats and s.lead is not None})
    for key, g in prognosis(samples).items():
        if key is None and g.n == 0:
            continue
        rows.append({"t_set_N": None if key is None else key[0],
                     "grade": "all" if key is None else key[1], "n": g.n, "warned": g.warned,
                     "warned_lead": g.warned_lead, "warned_lead_pct": Prognosis.pct(g.warned_lead, g.n),
                     "late": g.late, "with_prior": g.with_prior, "in_band": g.in_band,
                     "in_band_pct": Prognosis.pct(g.in_band, g.with_prior)})
    all_row = rows.pop(0) if rows and rows[0]["grade"] == "all" else None
    if all_row is not None:
        rows.append(all_row)
    lead_txt = ", ".join(f"{x:g} s" for x in leads) or "the sidecar's lead"
    return Table("table_prognosis", "Prognosis — early warning and forecast per setpoint and grade", [
        Column("t_set_N", "T_set (N)", "g"), Column("grade", "Grade"), Column("n", "failures", "int"),
        Column("warned", "warned", "int"), Column("warned_lead", "warned ≥ lead ahead", "int"),
        Column("warned_lead_pct", "≥ lead (%)", "pct1", 1),
        Column("late", "warned after t_life", "int"),
        Column("with_prior", "with a prior", "int"), Column("in_band", "t_life in [e10, e90]", "int"),
        Column("in_band_pct", "in band (%)", "pct1", 1),
    ], rows, intro=(f"Over the failures in the statistics (METHOD.md §5b, informative). Lead: "
                    f"{lead_txt}. \"Warned ≥ lead ahead\": t_life − the warning's time ≥ the "
                    "test's lead; \"warned after t_life\": the warning came between t_life and "
                    "the detection slot. \"In band\": t_life inside [e10, e90] of the forecast "
                    "from the test's prior at the last forecast time at or before t_life / 2 "
                    "(tests without a prior in their sidecar are not counted there; the band is "
                    "an 80 % interval when the prior matches the hooks)."))


def table_apart(samples: Sequence[Sample]) -> Table:
    rows = [{"sample_id": s.sample_id, "grade": s.grade or "—", "t_set_N": s.t_set,
             "status": s.status, "reason": s.apart, "note": s.note, "log": s.rel}
            for s in sort_samples(samples) if not s.in_stats]
    return Table("samples_apart", "Samples listed apart (not in any mean, SD or correlation)", [
        Column("sample_id", "Sample ID"), Column("grade", "Grade"), Column("t_set_N", "T_set (N)", "g"),
        Column("status", "status"), Column("reason", "why apart"), Column("note", "note"),
        Column("log", "log"),
    ], rows, intro="Tests that ended no_failure, no_baseline or aborted, tests that could not be "
                   "analysed, tests without a grade and repeated sample IDs.")


# ---------------------------------------------------------------------------------------------
# Table 4
# ---------------------------------------------------------------------------------------------

def life_groups(samples: Sequence[Sample], factor: float = 1.0, only: set[str] | None = None
                ) -> dict[tuple[float, str], list[float]]:
    """t_life per (setpoint, grade) over the samples in the statistics (at δ = factor·δ0)."""
    g: dict[tuple[float, str], list[float]] = {}
    for s in sort_samples(samples):
        if not s.in_stats or (only is not None and s.sample_id not in only):
            continue
        t = s.result(factor).get("t_life")
        if t is not None and s.t_set is not None and s.grade is not None:  # both set when in_stats
            g.setdefault((s.t_set, s.grade), []).append(t)
    return g


def rankings_by_setpoint(groups: dict[tuple[float, str], list[float]], setpoints: Sequence[float],
                         grades: Sequence[str]) -> dict[float, str]:
    out = {}
    for sp in setpoints:
        means = {g: S.mean(groups[(sp, g)]) for g in grades if groups.get((sp, g))}
        out[sp] = S.ranking(means)
    return out


def table4(samples: Sequence[Sample]) -> Table:
    grades = _grades(samples)
    setpoints = _setpoints(samples)
    groups = life_groups(samples)
    ranks = rankings_by_setpoint(groups, setpoints, grades)
    rows, notes = [], []
    for sp in setpoints:
        for g in grades:
            vals = groups.get((sp, g), [])
            st = S.group_stats(vals).rounded()
            rows.append({"t_set_N": sp, "grade": g, "n": st.n, "t_life_avg_s": st.mean,
                         "sd_s": st.sd, "cv_pct": st.cv, "ranking": ranks.get(sp, "")})
            if not vals:
                n_all = sum(1 for s in samples if s.t_set == sp and s.grade == g)
                notes.append(f"T_set {sp:g} N, grade {g}: " + (
                    "no test in the campaign" if n_all == 0 else
                    f"none of its {n_all} test(s) gave a t_life (see samples listed apart)")
                    + "; the ranking at this setpoint leaves the grade out")
            elif len(vals) == 1:
                notes.append(f"T_set {sp:g} N, grade {g}: one sample only, no SD")
    return Table("table4_summary", "Table 4 — summary per setpoint and grade", [
        Column("t_set_N", "T_set (N)", "g"), Column("grade", "Grade"), Column("n", "n", "int"),
        Column("t_life_avg_s", "mean t_life (s)", "f1", 1), Column("sd_s", "SD (s)", "f1", 1),
        Column("cv_pct", "CV (%)", "f2", 2), Column("ranking", "grade ranking"),
    ], rows, notes, intro="Mean t_life over the samples with status failure, sample standard "
                          "deviation (n − 1), CV = SD / mean; ranking by mean t_life, longest first.")


# ---------------------------------------------------------------------------------------------
# Table 5
# ---------------------------------------------------------------------------------------------

def delta_label(f: float) -> str:
    return "delta0" if f == 1.0 else f"{f:g}*delta0"


def table5(samples: Sequence[Sample], factors: Sequence[float]) -> tuple[Table, Table]:
    """(the summary as the paper prints it, the per-sample t_life at every δ)."""
    grades = _grades(samples)
    setpoints = _setpoints(samples)
    notes = []
    keep = set()
    for s in sort_samples(samples):
        if not s.in_stats:
            continue
        bad = [f for f in factors if s.result(f).get("t_life") is None]
        if bad:
            notes.append(f"{s.sample_id}: " + ", ".join(
                f"{s.result(f).get('status', '?')} at δ = {delta_label(f)}" for f in bad)
                + " — left out of the sensitivity means at every δ")
        else:
            keep.add(s.sample_id)
    deltas0 = {s.delta0 for s in samples if s.in_stats}
    ref = life_groups(samples, 1.0, keep)
    ref_rank = rankings_by_setpoint(ref, setpoints, grades)
    rows = []
    for sp in setpoints:
        for f in factors:
            gr = life_groups(samples, f, keep)
            rank = rankings_by_setpoint(gr, setpoints, grades)[sp]
            for g in grades:
                vals = gr.get((sp, g), [])
                m = S.mean(vals)
                ch = S.change_pct(m, S.mean(ref.get((sp, g), [])))
                rows.append({"t_set_N": sp, "delta": delta_label(f), "factor": f, "grade": g,
                             "n": len(vals), "t_life_avg_s": S.round_half_up(m, S.DIGITS["t_life"]),
                             "change_vs_delta0_pct": 0.0 if f == 1.0 and m is not None else
                             S.round_half_up(ch, S.DIGITS["change"]),
                             "ranking": rank,
                             "ranking_kept": None if not rank else rank == ref_rank.get(sp)})
    intro = ("t_life recomputed with δ = 0.9 δ0, δ0 and 1.1 δ0 from the same gated slots and "
             "baseline; change of the mean relative to δ0; whether the grade ranking stays as at δ0.")
    if len(deltas0) == 1 and None not in deltas0:
        intro += f" δ0 = {deltas0.pop():g}."
    summary = Table("table5_sensitivity", "Table 5 — sensitivity to the threshold increment δ", [
        Column("t_set_N", "T_set (N)", "g"), Column("delta", "δ"), Column("grade", "Grade"),
        Column("n", "n", "int"), Column("t_life_avg_s", "mean t_life (s)", "f1", 1),
        Column("change_vs_delta0_pct", "change vs δ0 (%)", "f2", 2),
        Column("ranking", "grade ranking"), Column("ranking_kept", "ranking kept", "yesno"),
    ], rows, notes, intro)
    prow = []
    for s in sort_samples(samples):
        if s.results is None:
            continue
        row = {"sample_id": s.sample_id, "grade": s.grade or "—", "t_set_N": s.t_set}
        for f in factors:
            r = s.result(f)
            row[f"t_life_{delta_label(f)}"] = r.get("t_life")
            row[f"status_{delta_label(f)}"] = r.get("status")
        prow.append(row)
    cols = [Column("sample_id", "Sample ID"), Column("grade", "Grade"), Column("t_set_N", "T_set (N)", "g")]
    for f in factors:
        cols.append(Column(f"t_life_{delta_label(f)}", f"t_life at {delta_label(f)} (s)", "f1", 2))
    for f in factors:
        cols.append(Column(f"status_{delta_label(f)}", f"status at {delta_label(f)}"))
    per_sample = Table("table5_samples", "t_life per sample at each δ", cols, prow)
    return summary, per_sample


# ---------------------------------------------------------------------------------------------
# Table 6
# ---------------------------------------------------------------------------------------------

def pretty_indicator(name: str) -> str:
    """``dw1_um`` → ``Δw1 (µm)``; other names as they are."""
    import re

    m = re.fullmatch(r"(?i)d(?:elta)?_?w_?(\w+?)(?:_(um|µm|mm))?", name.strip())
    if not m:
        return name
    unit = {"um": "µm", "µm": "µm", "mm": "mm"}.get((m.group(2) or "").lower())
    return f"Δw{m.group(1)}" + (f" ({unit})" if unit else "")


def table6(samples: Sequence[Sample], wear) -> tuple[Table, Table]:
    """(wear joined with t_life, ρ(t_life, indicator) with the expected sign)."""
    by_id: dict[str, Sample] = {}
    for first in sort_samples(samples):
        by_id.setdefault(first.sample_id, first)
    rows = []
    for sid in wear.order:
        s = by_id.get(sid)
        if s is None:
            continue
        row = {"sample_id": sid, "grade": s.grade or "—", "t_set_N": s.t_set,
               "t_life_s": s.t_life if s.in_stats else None, "status": s.status}
        row.update(wear.rows[sid])
        rows.append(row)
    rows.sort(key=lambda r: _sort_key(by_id[r["sample_id"]]))
    cols = [Column("sample_id", "Sample ID"), Column("grade", "Grade"), Column("t_set_N", "T_set (N)", "g"),
            Column("t_life_s", "t_life (s)", "f1", 2), Column("status", "status")]
    cols += [Column(ind, pretty_indicator(ind), f"f{wear.decimals.get(ind, 1)}") for ind in wear.indicators]
    joined = Table("table6_wear", "Table 6 — offline wear with the online wear life", cols, rows,
                   intro=f"Offline wear measurements ({len(wear.order)} rows) joined with t_life at δ0.")
    notes = []
    scopes: list[tuple[str, list[dict]]] = [("all samples", [r for r in rows if r["t_life_s"] is not None])]
    sps = sorted({r["t_set_N"] for r in scopes[0][1]})
    if len(sps) > 1:
        scopes += [(f"T_set {sp:g} N", [r for r in scopes[0][1] if r["t_set_N"] == sp]) for sp in sps]
    corr_rows = []
    for scope, rs in scopes:
        cs = S.wear_correlations([r["t_life_s"] for r in rs], {i: [r[i] for r in rs] for i in wear.indicators})
        for c in cs:
            corr_rows.append({"scope": scope, "indicator": c.indicator,
                              "indicator_label": pretty_indicator(c.indicator), "n": c.n,
                              "rho": c.rho, "expected": "negative",
                              "agrees": c.agrees})
            if c.rho is None:
                notes.append(f"{scope}, {pretty_indicator(c.indicator)}: ρ undefined "
                             f"({'fewer than 3 samples' if c.n < 3 else 'constant values'})")
    n_apart = sum(1 for r in rows if r["t_life_s"] is None)
    if n_apart:
        notes.append(f"{n_apart} wear row(s) belong to samples listed apart; not in the correlation")
    corr = Table("table6_correlation", "Rank correlation of t_life with each wear indicator", [
        Column("scope", "samples"), Column("indicator", "indicator", show=False),
        Column("indicator_label", "indicator"), Column("n", "n", "int"),
        Column("rho", "Spearman ρ", "f3", 6), Column("expected", "expected sign"),
        Column("agrees", "agrees", "yesno"),
    ], corr_rows, notes, intro="Spearman's ρ between t_life and each wear indicator (average ranks "
                               "for ties). The method expects a negative ρ: shorter life goes with "
                               "larger wear.")
    return joined, corr


# ---------------------------------------------------------------------------------------------
# Priors for the configuration (METHOD.md §7a)
# ---------------------------------------------------------------------------------------------

#: decimals of a prior's mean and SD in the `--priors` file (s): §7a's agreement is 1e-6 relative
PRIOR_DECIMALS = 6


def campaign_priors(samples: Sequence[Sample]) -> list[PriorEntry]:
    """The life prior of every (grade, T_set) group with at least 3 wear-out failures: the §7a
    history rule (failures and right-censored lives: a test that found its baseline and ended on
    purpose or at t_end; v3: an early failure is a censored life at its x; the maximum-likelihood
    normal, SD at least 2 % of the mean), with ``n`` wear-out failures, ``n_censored`` and
    ``n_early``. A test counts once: a duplicate sample ID and a test without analysis do not."""
    past = []
    for s in sort_samples(samples):
        if s.results is None or s.duplicate:
            continue
        r = s.result()
        reasons = r.get("stop_reasons")
        past.append(PastTest(s.grade, s.t_set, r.get("status"), r.get("t_life"), k_b=r.get("k_b"),
                             stop_reasons=None if reasons is None else tuple(reasons),
                             n_slots=r.get("n_slots"), ts=s.ts))
    return priors_by_group(past)


def priors_document(entries: Sequence[PriorEntry], source: str) -> dict[str, Any]:
    """The configuration's ``forecast:`` section holding these priors (s to 1e-6 s)."""
    out = []
    for e in entries:
        d = e.as_config()
        d["mean_s"] = round(e.mean, PRIOR_DECIMALS)
        d["sd_s"] = round(e.sd, PRIOR_DECIMALS)
        out.append(d)
    return {"forecast": {"priors": out}}
