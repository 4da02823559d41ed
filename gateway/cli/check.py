"""`hookwatch check PATH...`: validate station files and fleet folders and check that they can
work before anything runs (bus time at the configured baud, clashes across the fleet, physical
sense). ``--probe`` then asks the hardware and services themselves (gateway/commission/probe.py:
the meter through pymodbus' client, the STM32, the brokers, the listening ports; ``--scan`` finds
a meter's baud and unit ID). Exit 0: no errors (warnings allowed); 1: errors or a failed probe;
2: usage (no such path, no stations)."""
from __future__ import annotations

import os
import sys

from ..cli import CliError
from ..commission.probe import probe_station
from ..config import cross_issues, station_files, validate_fleet, validate_station
from ..config.checks import budget_text, bus_budget, feasibility
from ..plumbing.ratelog import safe

HELP = "validate station files / fleet folders and check their feasibility (exit 0 ok, 1 errors)"
DESCRIPTION = (HELP + ". Everything named in one call is checked as one box: station IDs, serial "
               "ports, Modbus TCP units and MQTT client IDs must not be used twice. "
               "Keys and checks: docs/configuration.md.")


def add_arguments(ap):
    ap.add_argument("paths", nargs="+", metavar="PATH",
                    help="a station file, or a fleet folder (fleet.yaml + stations/*.yaml)")
    ap.add_argument("--strict", action="store_true", help="warnings fail the check too (exit 1)")
    ap.add_argument("--skip-local", action="store_true",
                    help="skip the checks that depend on this machine (serial ports present, folders "
                         "writable, secrets set): for checking a configuration elsewhere than where it runs")
    ap.add_argument("-q", "--quiet", action="store_true", help="print problems and the summary only")
    ap.add_argument("--probe", action="store_true",
                    help="also ask the hardware and services: read both meter channels once (pymodbus' "
                         "client), PING the STM32, connect and log in to each broker, check that the "
                         "Modbus TCP, console and metrics ports are free; a serial port a running station "
                         "holds is named and left alone")
    ap.add_argument("--scan", action="store_true",
                    help="with --probe: when the meter does not answer, try the usual bauds and unit "
                         "IDs and say where it answered")


def _collect(paths):

    loaded, seen, fleets = [], set(), []
    for p in paths:
        if os.path.isdir(p):
            files = station_files(p)
            if not files:
                raise CliError(f"{p}: no station files (expected {os.path.join(p, 'stations', '*.yaml')})", 2)
            ff = os.path.join(p, "fleet.yaml")
            fleets.append(ff if os.path.isfile(ff) else None)
            items = validate_fleet(p)
        elif os.path.isfile(p):
            items = [validate_station(p)]
        else:
            raise CliError(f"{p}: no such file or folder", 2)
        for ld in items:
            key = os.path.realpath(ld.path)
            if key not in seen:
                seen.add(key)
                loaded.append(ld)
    return loaded


def _sorted(issues):
    return sorted(issues, key=lambda i: (i.severity != "error", i.file or "", i.line or 0))


def run(args) -> int:

    loaded = _collect(args.paths)
    per: list[list] = [list(ld.issues) for ld in loaded]
    for i, ld in enumerate(loaded):
        if ld.cfg is not None:
            per[i].extend(feasibility(ld, local=not args.skip_local))
    for i, issue in cross_issues(loaded):
        per[i].append(issue)

    had_errors = [any(x.severity == "error" for x in lst) for lst in per]
    # an issue that every station of a fleet file has, located in that file, is shown once
    by_fleet: dict[str, list[int]] = {}
    for i, ld in enumerate(loaded):
        if ld.fleet_file:
            by_fleet.setdefault(ld.fleet_file, []).append(i)
    shared: dict[str, list] = {}
    for ff, idx in by_fleet.items():
        # (a station with errors skipped the feasibility checks: it is not asked)
        cands = [x for j in idx for x in per[j] if x.file == ff]
        common = []
        for x in cands:
            if x in common:
                continue
            having = [j for j in idx if x in per[j]]
            asked = [j for j in idx if x in per[j] or loaded[j].cfg is not None]
            if having == asked and (len(having) > 1 or len(idx) == 1):
                common.append(x)
        if common:
            shared[ff] = common
            for j in idx:
                per[j] = [x for x in per[j] if x not in common]
    for i in range(len(per)):
        uniq: list = []
        for x in per[i]:
            if x not in uniq:
                uniq.append(x)
        per[i] = uniq

    fleet_bad = {j for ff, idx in by_fleet.items() for j in idx
                 if any(x.severity == "error" for x in shared.get(ff, ()))}
    out = sys.stdout
    n_err = n_warn = 0
    bad_stations = 0
    for ff, issues in shared.items():
        e = sum(1 for x in issues if x.severity == "error")
        w = len(issues) - e
        n_err, n_warn = n_err + e, n_warn + w
        print(f"{ff} (fleet defaults): {_counts(e, w)}", file=out)
        for x in _sorted(issues):
            print(f"  {x.severity}: {x}", file=out)
    for i, ld in enumerate(loaded):
        issues = per[i]
        e = sum(1 for x in issues if x.severity == "error")
        w = len(issues) - e
        n_err, n_warn = n_err + e, n_warn + w
        station_bad = had_errors[i] or ld.cfg is None
        bad_stations += station_bad
        name = f"station {safe(ld.name, 64)}" if ld.name else "station"
        if args.quiet and not issues and not station_bad:
            continue
        head = f"{ld.path} ({name}): "
        if station_bad:
            head += (_counts(e, w) + (" (and the fleet defaults' errors above)" if i in fleet_bad else "")
                     if e else "errors in the fleet defaults (above)")
        else:
            b = bus_budget(ld.cfg)
            head += "OK" + (f", {w} warning{'s' * (w != 1)}" if w else "")
            if b is not None:
                head += f" — {budget_text(b)}"
        print(head, file=out)
        for x in _sorted(issues):
            print(f"  {x.severity}: {x}", file=out)
    n = len(loaded)
    print(f"{n} station{'s' * (n != 1)}: {n - bad_stations} OK, {bad_stations} with errors; "
          f"{n_err} error{'s' * (n_err != 1)}, {n_warn} warning{'s' * (n_warn != 1)}", file=out)
    probe_failed = _probe(loaded, args, out) if args.probe or args.scan else 0
    if n_err or bad_stations or probe_failed or (args.strict and n_warn):
        return 1
    return 0


def _probe(loaded, args, out) -> int:
    """Probe every station whose file is valid; the failures' count."""
    failed = 0
    seen: set = set()
    for ld in loaded:
        name = f"station {safe(ld.name, 64)}" if ld.name else ld.path
        if ld.cfg is None:
            print(f"probe {name}: skipped (the file has errors)", file=out)
            continue
        print(f"probe {name}:", file=out)
        for f in probe_station(ld.cfg, scan=args.scan, seen=seen):
            failed += not f.ok
            if f.ok and args.quiet:
                continue
            print(f"  {f}", file=out)
    print(f"probe: {'all OK' if not failed else f'{failed} failed'}", file=out)
    return failed


def _counts(e: int, w: int) -> str:
    parts = []
    if e:
        parts.append(f"{e} error{'s' * (e != 1)}")
    if w:
        parts.append(f"{w} warning{'s' * (w != 1)}")
    return ", ".join(parts) or "OK"
