"""`hookwatch report`: a campaign folder → tables (CSV), figures (PNG), report.md + report.html."""
from __future__ import annotations

import glob
import os
import re
import time
from dataclasses import dataclass, field
from typing import Any

from ... import __version__
from ..logio import LogError, read_meta
from . import tables as T
from .campaign import (
    DELTA_FACTORS,
    REPORT_MARKER,
    ROLE_CLOSED,
    ROLE_OPEN,
    Campaign,
    ControlLog,
    Problem,
    Progress,
    TestSpec,
    discover,
    run_parallel,
)
from .per_log import run_task
from .plots import render_fig9
from .render import Document, Figure, Section, write_csvs, write_document


@dataclass
class ReportOutcome:
    out_dir: str
    samples: list[T.Sample]
    problems: list[Problem]
    tables: dict[str, T.Table]
    figures: list[str]
    seconds: float
    n_analysed: int
    files: list[str] = field(default_factory=list)
    analysis_cpu_s: float = 0.0      # CPU time the workers spent on the logs (all processes)
    workers: int = 1


def _safe(name: str) -> str:
    return re.sub(r"[^A-Za-z0-9._-]+", "_", name).strip("._") or "sample"


def _sample_title(spec) -> str:
    g = f"Grade {spec.grade}" if spec.grade else "no grade"
    return f"Sample {spec.sample_id} — {g}, T_set {spec.t_set:g} N"


def _control_pair(camp: Campaign, open_loop: str | None, closed_loop: str | None,
                  problems: list[Problem], notes: list[str]) -> dict[str, Any] | None:
    """The two logs of Fig. 8: given on the command line, or marked in their sidecars."""

    def from_cli(path: str, role: str) -> ControlLog | None:
        if not os.path.isfile(path):
            problems.append(Problem(path, f"--{role.replace('_', '-')}: no such log file; Fig. 8 not drawn"))
            return None
        t_set = None
        try:
            meta = read_meta(path)
            m = meta.get("method") or {}
            t_set = m.get("t_set", meta.get("t_set"))
            t_set = float(t_set) if t_set is not None else None
        except (LogError, TypeError, ValueError):
            t_set = None
        return ControlLog(path, path, role, t_set, os.path.getsize(path))

    opens = [c for c in camp.control if c.role == ROLE_OPEN]
    closes = [c for c in camp.control if c.role == ROLE_CLOSED]
    o = from_cli(open_loop, ROLE_OPEN) if open_loop else (opens[0] if opens else None)
    c = from_cli(closed_loop, ROLE_CLOSED) if closed_loop else (closes[0] if closes else None)
    if open_loop and o is None or closed_loop and c is None:
        return None
    # extra logs of a role exist only besides its first one, the log that is used
    for extras, used in (([] if open_loop else opens[1:], o), ([] if closed_loop else closes[1:], c)):
        for extra in extras:
            if used is not None:
                problems.append(Problem(extra.rel, f"another {extra.role} log; Fig. 8 uses {used.rel}"))
    if o is None and c is None:
        notes.append("Fig. 8 (open loop vs closed loop) needs two comparison logs: mark them with "
                     "`role: open_loop` / `role: closed_loop` in their sidecars or give "
                     "--open-loop/--closed-loop.")
        return None
    if o is None or c is None:
        for have in (o, c):     # the one that is there
            if have is not None:
                problems.append(Problem(have.rel, f"{have.role} log without its "
                                        f"{ROLE_CLOSED if have.role == ROLE_OPEN else ROLE_OPEN} counterpart; "
                                        "Fig. 8 not drawn"))
        return None
    t_set = c.t_set if c.t_set is not None else o.t_set
    if t_set is None:
        problems.append(Problem(c.rel, "no t_set for the open/closed-loop logs (sidecar "
                                "method.t_set); Fig. 8 not drawn"))
        return None
    if o.t_set is not None and c.t_set is not None and o.t_set != c.t_set:
        problems.append(Problem(o.rel, f"open-loop log at T_set {o.t_set:g} N, closed-loop log at "
                                f"{c.t_set:g} N; Fig. 8 shows both against {t_set:g} N"))
    return {"kind": "control", "open": o.log, "closed": c.log, "t_set": t_set,
            "labels": {"open": "open loop", "closed": "closed loop"},
            "rels": (o.rel, c.rel), "size": o.size + c.size}


def build_report(campaign_dir: str, out_dir: str, *, wear: str | None = None, jobs: int = 1,
                 overrides: dict[str, Any] | None = None, open_loop: str | None = None,
                 closed_loop: str | None = None, progress: bool | None = None,
                 figures: bool = True) -> ReportOutcome:
    t0 = time.perf_counter()
    out_dir = os.path.abspath(out_dir)
    os.makedirs(out_dir, exist_ok=True)
    fig_dir = os.path.join(out_dir, "figures")
    if os.path.exists(os.path.join(out_dir, REPORT_MARKER)):
        for old in glob.glob(os.path.join(fig_dir, "*.png")):  # a previous report's figures
            os.remove(old)
    with open(os.path.join(out_dir, REPORT_MARKER), "w", encoding="utf-8") as f:
        f.write("written by hookwatch report; this folder is skipped when looking for logs\n")
    os.makedirs(fig_dir, exist_ok=True)

    camp = discover(campaign_dir, wear_path=wear, overrides=overrides, skip={out_dir})
    problems = camp.problems
    fig_notes: list[str] = []

    # ---- tasks: one per analysable test, plus Fig. 8
    tasks: list[dict[str, Any]] = []
    owners: list[TestSpec | None] = []      # None: the Fig. 8 task
    used_names: set[str] = set()
    for spec in camp.tests:
        if spec.params is None:
            continue
        fig = None
        if figures:
            base = "fig7_" + _safe(spec.sample_id)
            name, i = base, 2
            while name in used_names:
                name, i = f"{base}_{i}", i + 1
            used_names.add(name)
            fig = os.path.join(fig_dir, name + ".png")
        tasks.append({"kind": "test", "log": spec.log, "params": spec.params, "factors": DELTA_FACTORS,
                      "fig": fig, "title": _sample_title(spec), "size": spec.size})
        owners.append(spec)
    ctl = _control_pair(camp, open_loop, closed_loop, problems, fig_notes) if figures else None
    if ctl is not None:
        ctl["fig"] = os.path.join(fig_dir, "fig8_open_vs_closed_loop.png")
        ctl["title"] = "Fig. 8 — tension under open-loop and closed-loop operation"
        tasks.append(ctl)
        owners.append(None)
    # largest logs first: the pool ends with the short ones and no core idles long
    order = sorted(range(len(tasks)), key=lambda i: -tasks[i]["size"])
    n_workers = max(1, min(jobs, len(tasks)))
    bar = Progress(len(tasks), "analysing", enabled=progress)
    try:
        res_sorted = run_parallel(run_task, [tasks[i] for i in order], jobs, bar.advance)
    finally:
        bar.close()
    results: list[dict | None] = [None] * len(tasks)
    for j, i in enumerate(order):
        results[i] = res_sorted[j]

    # ---- per-test outcomes
    outcome_by_log: dict[str, dict] = {}
    fig8 = None
    for _task, owner, res in zip(tasks, owners, results):
        res = res or {"error": "no result"}
        if owner is None:
            if res.get("error"):
                problems.append(Problem("Fig. 8", res["error"]))
            else:
                fig8 = res
            continue
        if res.get("error"):
            problems.append(Problem(owner.rel, res["error"].replace(owner.log + ": ", "")
                                    + "; listed apart"))
        else:
            if res.get("fig_error"):
                problems.append(Problem(owner.rel, res["fig_error"]))
            for key, what in (("duplicates", "readings landed in an already filled slot (the later won)"),
                              ("out_of_grid", "readings outside the test's slot grid (ignored)")):
                if res.get(key):
                    owner.notes.append(f"{res[key]:,} {what}")
        outcome_by_log[owner.log] = res
    samples = []
    for spec in camp.tests:
        s = T.make_sample(spec, outcome_by_log.get(spec.log), DELTA_FACTORS)
        res = outcome_by_log.get(spec.log) or {}
        if res.get("fig"):
            s.fig = os.path.relpath(res["fig"], out_dir)
        samples.append(s)
    n_analysed = sum(1 for s in samples if s.results is not None)

    # ---- tables
    t3 = T.table3(samples)
    t4 = T.table4(samples)
    t5, t5s = T.table5(samples, DELTA_FACTORS)
    tp = T.table_prognosis(samples)
    apart = T.table_apart(samples)
    tables = [t3, t4, t5, t5s, tp]
    t6 = t6c = None
    if camp.wear is not None:
        t6, t6c = T.table6(samples, camp.wear)
        tables += [t6, t6c]
    tables.append(apart)
    for n in t4.notes:
        if "no test in the campaign" in n:
            problems.append(Problem("campaign", n))

    # ---- Fig. 9 (needs the statistics)
    fig9 = None
    if figures and n_analysed:
        groups = T.life_groups(samples)
        if groups:
            grades = T._grades(samples)
            sps = T._setpoints(samples)
            try:
                fig9 = os.path.join(fig_dir, "fig9_life_by_grade.png")
                render_fig9(groups, grades, sps, T.rankings_by_setpoint(groups, sps, grades), fig9,
                            "Fig. 9 — online wear life by grade and tension setpoint")
            except Exception as e:  # noqa: BLE001
                problems.append(Problem("Fig. 9", f"not drawn: {type(e).__name__}: {e}"))
                fig9 = None
        else:
            fig_notes.append("Fig. 9 not drawn: no sample with a t_life and a grade.")

    # ---- document
    elapsed = time.perf_counter() - t0
    doc_sections = []
    prob_lines = [str(p) for p in problems]
    doc_sections.append(Section("Problems with the input", [] if prob_lines else
                                ["None: every log had a usable sidecar and was analysed."],
                                prob_lines, anchor="problems"))
    doc_sections.append(Section("Per sample (Table 3)", tables=[t3], anchor="table3"))
    doc_sections.append(Section("Per setpoint and grade (Table 4)", tables=[t4], anchor="table4"))
    doc_sections.append(Section("Sensitivity to δ (Table 5)", tables=[t5, t5s], anchor="table5"))
    doc_sections.append(Section("Prognosis (METHOD.md §5b)", tables=[tp], anchor="prognosis"))
    if t6 is not None and t6c is not None:
        doc_sections.append(Section("Consistency with offline wear (Table 6)", tables=[t6, t6c],
                                    anchor="table6"))
    else:
        doc_sections.append(Section("Consistency with offline wear (Table 6)", [
            "No wear table: put the offline measurements in wear.csv in the campaign folder (a "
            "sample_id column and one column per wear indicator) or give --wear FILE."],
            anchor="table6"))
    doc_sections.append(Section("Samples listed apart", tables=[apart], anchor="apart"))
    figs = []
    if fig9:
        figs.append(Figure(os.path.relpath(fig9, out_dir), "Fig. 9 — t_life by grade and setpoint: "
                           "bars are the mean over the samples in the statistics, whiskers ± one "
                           "sample SD, dots the samples (samples listed apart are not shown)."))
    if fig8 is not None and ctl is not None:     # fig8 is the result of the ctl task
        st = fig8["stats"]
        figs.append(Figure(os.path.relpath(fig8["fig"], out_dir),
                           f"Fig. 8 — open loop ({ctl['rels'][0]}) vs closed loop ({ctl['rels'][1]}): "
                           f"mean tension SD {st['open']['sd_N']:.3f} N vs {st['closed']['sd_N']:.3f} N, "
                           f"mean {st['open']['mean_N']:.3f} vs {st['closed']['mean_N']:.3f} N "
                           f"(T_set {ctl['t_set']:g} N), readings within ±5 % of T_set "
                           f"{st['open']['within_5pct']:.1f} % vs {st['closed']['within_5pct']:.1f} % "
                           "(statistics after the start-up)."))
    for s in T.sort_samples(samples):
        if s.fig:
            tl = f"t_life {s.t_life:,.1f} s" if s.t_life is not None else s.status
            figs.append(Figure(s.fig, f"Fig. 7 — {s.sample_id} ({'Grade ' + s.grade if s.grade else 'no grade'}, "
                               f"T_set {s.t_set:g} N): μ(t) with baseline, threshold, stable segment "
                               f"and {tl}; tensions below."))
    if figures:
        doc_sections.append(Section("Figures", fig_notes, figures=figs, anchor="figures"))
    n_stats = sum(1 for s in samples if s.in_stats)
    info = [("campaign", os.path.abspath(campaign_dir)),
            ("tests", f"{len(camp.tests)} found, {n_analysed} analysed, {n_stats} in the statistics, "
                      f"{len(samples) - n_stats} listed apart"),
            ("wear table", os.path.relpath(camp.wear.path, campaign_dir) if camp.wear else "none"),
            ("problems", str(len(problems))),
            ("generated", time.strftime("%Y-%m-%d %H:%M:%S UTC", time.gmtime())
             + f" by hookwatch {__version__} in {elapsed:.1f} s on {n_workers} process(es)")]
    doc = Document(f"Campaign report — {os.path.basename(os.path.abspath(campaign_dir))}", info, doc_sections)
    files = write_csvs(tables, out_dir)
    prob_path = os.path.join(out_dir, "problems.txt")
    with open(prob_path, "w", encoding="utf-8") as f:
        f.write("".join(p + "\n" for p in prob_lines))
    files += [prob_path, *write_document(doc, out_dir)]
    all_figs = [os.path.join(out_dir, f.path) for f in figs]
    cpu = sum((r or {}).get("cpu_s", 0.0) for r in results)
    return ReportOutcome(out_dir, samples, problems, {t.name: t for t in tables}, all_figs,
                         time.perf_counter() - t0, n_analysed, files, cpu, n_workers)
