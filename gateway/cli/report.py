"""`hookwatch report CAMPAIGN --out DIR`: the paper's tables and figures for a test campaign."""
from __future__ import annotations

import json
import os
import sys

from ..cli import CliError
from ..offline.analysis import AnalysisError, parse_overrides
from ..offline.report.pipeline import build_report
from ..offline.report.tables import campaign_priors, priors_document
from ..plumbing.safeout import write_atomic

HELP = "tables (CSV), figures (PNG) and a Markdown/HTML report for a campaign of recorded tests"
DESCRIPTION = (
    "Analyse every recorded test under CAMPAIGN (log.csv[.gz] + log.meta.yaml folders as the "
    "gateway records them, or NAME.csv[.gz] + NAME.meta.yaml pairs; sidecar keys sample_id, grade, "
    "t_set / method.t_set) in parallel, and write to DIR: per-sample results (Table 3), mean/SD/CV "
    "and grade ranking per setpoint (Table 4), δ sensitivity (Table 5), the wear table joined with "
    "t_life and its rank correlations (Table 6, from CAMPAIGN/wear.csv or --wear), Fig. 7 per "
    "sample, Fig. 8 (open vs closed loop), Fig. 9, the prognosis table (early warning lead, "
    "forecast band; METHOD.md §5b), report.md and report.html; with --priors the per-grade/T_set "
    "life priors in the station configuration's forecast: form. Problems with the "
    "input are warnings: the rest of the report is still written (exit 0); exit 1 when no test "
    "could be analysed, 2 on usage errors. See docs/report.md.")


def add_arguments(ap):
    ap.add_argument("campaign", metavar="CAMPAIGN", help="folder of recorded tests")
    ap.add_argument("--out", required=True, metavar="DIR", help="report folder (created)")
    ap.add_argument("--wear", metavar="FILE", help="offline wear table (default: CAMPAIGN/wear.csv if present)")
    ap.add_argument("--jobs", "-j", type=int, default=None, metavar="N",
                    help=f"analyse on N processes (default: the number of cores, {os.cpu_count() or 1})")
    ap.add_argument("--set", action="append", default=[], metavar="NAME=VALUE",
                    help="override a method parameter for every test (repeatable)")
    ap.add_argument("--open-loop", metavar="LOG", help="open-loop log for Fig. 8 (default: the "
                    "campaign log whose sidecar says role: open_loop)")
    ap.add_argument("--closed-loop", metavar="LOG", help="closed-loop log for Fig. 8 (default: "
                    "role: closed_loop)")
    ap.add_argument("--no-figures", action="store_true", help="tables and report only")
    ap.add_argument("--priors", metavar="FILE", help="also write the life prior (mean, SD, n "
                    "wear-out failures, n_censored right-censored lives, n_early early failures) "
                    "of every grade and T_set with at least 3 wear-out failures, as a station "
                    "configuration's forecast: section (METHOD.md §7a), to FILE")
    ap.add_argument("--quiet", "-q", action="store_true", help="no progress bar, no warnings on stderr")


def run(args) -> int:

    if not os.path.isdir(args.campaign):
        raise CliError(f"{args.campaign}: not a folder (CAMPAIGN is a folder of recorded tests)")
    if os.path.exists(args.out) and not os.path.isdir(args.out):
        raise CliError(f"--out {args.out}: exists and is not a folder")
    if os.path.realpath(args.out) == os.path.realpath(args.campaign):
        raise CliError(f"--out {args.out}: is the campaign folder itself; give a new folder "
                       "(a subfolder of the campaign is fine)")
    if args.priors is not None and os.path.isdir(args.priors):
        raise CliError(f"--priors {args.priors}: is a folder; give a file name")
    if args.wear is not None and not os.path.isfile(args.wear):
        raise CliError(f"--wear {args.wear}: no such file")
    jobs = args.jobs if args.jobs is not None else (os.cpu_count() or 1)
    if jobs < 1:
        raise CliError(f"--jobs {args.jobs}: must be at least 1")
    try:
        overrides = parse_overrides(args.set)
    except AnalysisError as e:
        raise CliError(str(e)) from None
    out = build_report(args.campaign, args.out, wear=args.wear, jobs=jobs, overrides=overrides,
                       open_loop=args.open_loop, closed_loop=args.closed_loop,
                       progress=False if args.quiet else None, figures=not args.no_figures)
    if not args.quiet:
        for p in out.problems:
            print(f"hookwatch report: warning: {p}", file=sys.stderr)
    n_stats = sum(1 for s in out.samples if s.in_stats)
    print(f"{len(out.samples)} tests, {out.n_analysed} analysed, {n_stats} in the statistics, "
          f"{len(out.problems)} problem(s); {len(out.figures)} figures; {out.seconds:.1f} s "
          f"on {out.workers} process(es), analysis CPU {out.analysis_cpu_s:.1f} s")
    print(f"report: {os.path.join(out.out_dir, 'report.html')}")
    if args.priors is not None:
        _write_priors(args.priors, out.samples, args.campaign)
    if out.n_analysed == 0:
        print("hookwatch report: no test could be analysed", file=sys.stderr)
        return 1
    return 0


def _write_priors(path: str, samples, campaign: str) -> None:
    import yaml

    entries = campaign_priors(samples)
    doc = priors_document(entries, campaign)
    # the folder's name is written as a JSON string (every control and non-ASCII character
    # escaped): a newline in it cannot end the comment and inject YAML (issue 27)
    head = (f"# life priors from the campaign {json.dumps(os.path.abspath(campaign))} (hookwatch "
            "report --priors; METHOD.md §7a: per grade and T_set with n ≥ 3 wear-out failures, "
            "the maximum-likelihood normal of the wear-out failures (n), the right-censored "
            "lives (n_censored) and the early failures (n_early: below 0.75 × the median of at "
            "least 5 lives, censored at their life), SD ≥ 2 % of the mean)\n"
            "# paste into a station file (or fleet.yaml) as its forecast: section\n")
    try:
        text = head + yaml.safe_dump(doc, sort_keys=False, default_flow_style=None)
        write_atomic(os.path.abspath(path), text.encode("utf-8"))
    except OSError as e:
        raise CliError(f"--priors {path}: cannot write: {e.strerror or e}") from None
    print(f"priors: {path} ({len(entries)} grade/T_set group(s) with at least 3 wear-out failures)")
