"""`hookwatch analyze LOG... [--set NAME=VALUE]... [--json]`: the method over recorded logs."""
from __future__ import annotations

import sys

from ..cli import CliError
from ..core.method.params import PARAMS
from ..offline.analysis import AnalysisError, analyze_log, parse_overrides
from ..offline.logio import LogError, read_meta, sidecar_prior
from ..plumbing import safeout

HELP = "analyse recorded logs (METHOD.md §9 CSV) and print their wear-life results"
DESCRIPTION = (HELP + ". Parameters come from each log's NAME.meta.yaml sidecar (its method: "
               "section) and --set overrides. Parameters: "
               + ", ".join(f"{p.name} ({p.unit}, default {p.default})" for p in PARAMS))


def add_arguments(ap):
    ap.add_argument("logs", nargs="+", metavar="LOG", help="log file (.csv or .csv.gz)")
    ap.add_argument("--set", action="append", default=[], metavar="NAME=VALUE",
                    help="override a method parameter (repeatable)")
    ap.add_argument("--json", action="store_true", help="one JSON object per log per line")


def _fmt(v, nd=6):
    if v is None:
        return "-"
    if isinstance(v, float):
        return f"{v:.{nd}f}"
    return str(v)


def run(args) -> int:
    try:
        overrides = parse_overrides(args.set)
    except AnalysisError as e:
        raise CliError(str(e)) from None
    rows = []
    failed = 0
    for path in args.logs:
        try:
            res, p = analyze_log(path, overrides)
        except AnalysisError as e:
            print(f"hookwatch analyze: {e}", file=sys.stderr)
            failed += 1
            continue
        d = {"log": path, **res.as_dict()}
        if args.json:
            print(safeout.dumps(d, compact=False), flush=True)
        else:
            # display only: the warning's time (end of its last window), s from test start
            d["warn_s"] = None if res.warn_slot is None else (res.warn_slot + 1) * p.ts
            d["warn_by"] = None if res.warn_reasons is None else "+".join(res.warn_reasons)
            d["lead"] = p.lead
            d["prior"] = sidecar_prior({**log_meta(path), "method": {
                "prior_mean": p.prior_mean, "prior_sd": p.prior_sd}})
            rows.append(d)
    if rows:
        _table(rows)
    return 2 if failed else 0


#: (heading, result key, decimals) of the human table
COLUMNS = (("log", "log", 0), ("status", "status", 0), ("mu_ss", "mu_ss", 6), ("mu_th", "mu_th", 6),
           ("k_b", "k_b", 0), ("t_life", "t_life", 2), ("n_slots", "n_slots", 0),
           ("n_valid", "n_valid", 0), ("stop_slot", "stop_slot", 0), ("headroom", "headroom", 3),
           ("warn_s", "warn_s", 2), ("warn_by", "warn_by", 0), ("t_cross_s", "t_cross", 0),
           ("end_p50_s", "end_p50", 0), ("p_end", "p_end", 3))


def _table(rows) -> None:
    table = [[_fmt(r[key], nd) for _, key, nd in COLUMNS] for r in rows]
    w = [max(len(h), *(len(t[i]) for t in table)) for i, (h, _, _) in enumerate(COLUMNS)]
    print("  ".join(h.ljust(w[i]) for i, (h, _, _) in enumerate(COLUMNS)))
    for t in table:
        print("  ".join(c.ljust(w[i]) for i, c in enumerate(t)))
    for r in rows:
        reasons = ", ".join(f"{k}={v}" for k, v in r["reasons"].items() if v)
        extra = ""
        if r["stop_reasons"] == ["STOPPED"]:
            extra = f"; ended on purpose at slot {r['stop_slot']} (STOPPED)"
        elif r["stop_slot"] is not None:
            extra = f"; protection stop at slot {r['stop_slot']} ({', '.join(r['stop_reasons'])})"
        print(f"  {r['log']}: invalid slots by reason: {reasons or 'none'}{extra}")
        if r["k_b"] is not None:
            print(f"  {r['log']}: {_wear_line(r)}")
        print(f"  {r['log']}: {_forecast_line(r)}")


def _wear_line(r) -> str:
    """METHOD.md §5a in words (informative: never the status)."""
    if r["headroom"] is None:
        return "wear: no complete window with a value after the baseline"
    out = [f"wear: headroom {r['headroom']:.3f} (last window; 1 = baseline, 0 = threshold)"]
    out.append("no projection (trend flat or falling, past the threshold, or < 10 windows)"
               if r["t_cross"] is None else
               f"projection: the recent trend reaches mu_th at {r['t_cross']:.0f} s "
               f"({r['t_cross'] / 3600:.1f} h; the accelerated stage usually comes sooner)")
    return "; ".join(out)


def _forecast_line(r) -> str:
    """METHOD.md §5b in words (informative: never the status)."""
    out = ["no early warning" if r["warn_slot"] is None else
           f"early warning at {r['warn_s']:.2f} s (slot {r['warn_slot']}; due by "
           f"{', '.join(r['warn_reasons'])})"]
    if r["end_p50"] is None:
        out.append("no forecast from a prior (no prior_mean/prior_sd, or no complete window)")
    else:
        pr = r["prior"]
        lives = pr.lives_words()
        src = "" if pr.source is None else f", from {pr.source}" + ("" if lives is None else f" ({lives})")
        out.append(f"prior {pr.mean:.0f} ± {pr.sd:.0f} s{src}")
        out.append(f"forecast at the last window: end {r['end_p10']:.0f} / {r['end_p50']:.0f} / "
                   f"{r['end_p90']:.0f} s (10/50/90 %), P(end within {r['lead']:g} s) "
                   f"{r['p_end']:.3f}")
    return "; ".join(out)


def log_meta(path: str) -> dict:
    """The sidecar for display (the analysis has read it already; {} when it cannot be read)."""
    try:
        return read_meta(path)
    except LogError:
        return {}
