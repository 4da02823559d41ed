"""`hookwatch analyze LOG... [--set NAME=VALUE]... [--json]`: the method over recorded logs."""
from __future__ import annotations

import json
import sys

from ..analysis import AnalysisError, analyze_file, parse_overrides
from ..cli import CliError
from ..method.params import PARAMS

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
            res = analyze_file(path, overrides)
        except AnalysisError as e:
            print(f"hookwatch analyze: {e}", file=sys.stderr)
            failed += 1
            continue
        d = {"log": path, **res.as_dict()}
        if args.json:
            print(json.dumps(d), flush=True)
        else:
            rows.append(d)
    if rows:
        hdr = ("log", "status", "mu_ss", "mu_th", "k_b", "t_life", "n_slots", "n_valid", "stop_slot")
        table = [[_fmt(r[h]) if h not in ("t_life",) else _fmt(r[h], 2) for h in hdr] for r in rows]
        w = [max(len(h), *(len(t[i]) for t in table)) for i, h in enumerate(hdr)]
        print("  ".join(h.ljust(w[i]) for i, h in enumerate(hdr)))
        for t in table:
            print("  ".join(c.ljust(w[i]) for i, c in enumerate(t)))
        for r in rows:
            reasons = ", ".join(f"{k}={v}" for k, v in r["reasons"].items() if v)
            extra = f"; protection stop at slot {r['stop_slot']} ({', '.join(r['stop_reasons'])})" \
                if r["stop_slot"] is not None else ""
            print(f"  {r['log']}: invalid slots by reason: {reasons or 'none'}{extra}")
    return 2 if failed else 0
