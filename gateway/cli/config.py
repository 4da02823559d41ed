"""`hookwatch config SUBCOMMAND`: the site's configuration on this box (docs/deploy.md, "A site of
many boxes"). Each subcommand is one row of :data:`SUBCOMMANDS`: name → (help, add_arguments, run).

- ``check ROOT [--site] [--box NAME] [--version ID]`` — a box's candidate tree, or the whole site;
- ``plan ROOT [--box NAME] [--version ID] [--json]`` — per station what an apply would do;
- ``apply ROOT --version ID [--interrupt-tests --by NAME] [--health-timeout S] [--json]``;
- ``rollback [--to ID]`` — back to the last verified version;
- ``restart [--wait S] [--all]`` — new software installed: each station's worker restarts once
  idle (a test running: when it ends, never before);
- ``status [--json]`` — the box's config report.

Exit codes (what Ansible's ``changed_when``/``failed_when`` read): 0 nothing to change / ok,
1 error, 2 usage, 3 changes (plan: would be made; apply: made), 4 refused (check failed, unsigned),
5 rolled back (the health gate failed), 6 still waiting (restart: a test runs).

- ``acl`` (:mod:`.config_acl`): the broker's permissions generated from the station files.

Each subcommand is one :class:`Subcommand` row; adding one is adding its row.
"""
from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from .. import __version__
from ..cli import CliError
from ..config.site.boxreport import build_report
from ..config.site.boxsettings import BoxSettings, BoxSettingsError, load_box
from ..config.site.repository import GitError, checkout, commit_of
from ..config.site.siteapply import EXIT, apply_version, restart, rollback
from ..config.site.sitecheck import check_box, check_site
from ..config.site.siteplan import make_plan, plan_text
from ..config.site.versions import StateDir
from ..plumbing import safeout
from . import config_acl

HELP = ("the configuration of a box and its site: check, plan, apply, rollback, restart, status; "
        "acl (the broker's permissions from the station files)")
DESCRIPTION = (HELP + " (docs/deploy.md, \"A site of many boxes\"). Exit codes: 0 ok / nothing to "
               "change, 1 error, 2 usage, 3 changes, 4 refused, 5 rolled back.")


def _common(ap: argparse.ArgumentParser, state: bool = True) -> None:
    ap.add_argument("--box-file", metavar="PATH",
                    help="the box's own settings (default $HOOKWATCH_BOX_FILE, else /etc/hookwatch/box.yaml)")
    if state:
        ap.add_argument("--state-dir", metavar="DIR", help="the box's state folder (default: the box file's "
                        "state_dir, /var/lib/hookwatch)")


def _settings(args: argparse.Namespace) -> BoxSettings:
    try:
        return load_box(args.box_file)
    except BoxSettingsError as e:
        raise CliError(str(e), 1) from None


def _box(args: argparse.Namespace, s: BoxSettings) -> str:
    box = getattr(args, "box", None) or s.name
    if not box:
        raise CliError("which box? --box NAME, `name:` in the box file or $HOOKWATCH_BOX", 2)
    return str(box)


def _state(args: argparse.Namespace, s: BoxSettings) -> StateDir:
    return StateDir(getattr(args, "state_dir", None) or s.state_dir)


def _print_json(v: dict[str, Any]) -> None:
    print(safeout.dumps(v))


# ---------------------------------------------------------------------------------- check
def _check_args(ap: argparse.ArgumentParser) -> None:
    ap.add_argument("root", metavar="ROOT", help="the site repository (a Git checkout)")
    ap.add_argument("--site", action="store_true", help="every box of the site, and the rules across boxes")
    ap.add_argument("--box", metavar="NAME", help="the box (default: the box file's name)")
    ap.add_argument("--version", metavar="ID", help="a commit of ROOT (default: its working tree)")
    _common(ap, state=False)


def _check(args: argparse.Namespace) -> int:
    s = _settings(args)
    try:
        with checkout(args.root, args.version) as tree:
            if args.site:
                checks, across = check_site(tree)
            else:
                box = _box(args, s)
                checks, across = {box: check_box(tree, box)}, []
    except GitError as e:
        raise CliError(str(e), 1) from None
    errors = [x for c in checks.values() for x in c.errors] + across
    for c in checks.values():
        for w in c.warnings:
            print(f"warning: {w}", file=sys.stderr)
    for line in errors:
        print(line)
    n = sum(len(c.stations) for c in checks.values())
    print(f"{len(checks)} box(es), {n} station(s): " + (f"{len(errors)} error(s)" if errors else "ok"),
          file=sys.stderr)
    return 1 if errors else 0


# ---------------------------------------------------------------------------------- plan
def _plan_args(ap: argparse.ArgumentParser) -> None:
    ap.add_argument("root", metavar="ROOT", help="the site repository (a Git checkout)")
    ap.add_argument("--box", metavar="NAME", help="the box (default: the box file's name)")
    ap.add_argument("--version", metavar="ID", help="a commit of ROOT (default: its working tree)")
    ap.add_argument("--json", action="store_true", help="the plan as one JSON object")
    _common(ap)


def _plan(args: argparse.Namespace) -> int:
    s = _settings(args)
    box, state = _box(args, s), _state(args, s)
    try:
        with checkout(args.root, args.version) as tree:
            plan = make_plan(tree, box, state, args.version and _sha(args.root, args.version))
    except GitError as e:
        raise CliError(str(e), 1) from None
    if plan.errors:
        for line in plan.errors:
            print(line, file=sys.stderr)
        return EXIT["error"]
    if args.json:
        _print_json(plan.as_dict())
    else:
        print(plan_text(plan))
    return EXIT["changed"] if plan.changed else EXIT["nothing"]


def _sha(root: str, version: str) -> str:
    return commit_of(root, version)


# ---------------------------------------------------------------------------------- apply
def _apply_args(ap: argparse.ArgumentParser) -> None:
    ap.add_argument("root", metavar="ROOT", help="the site repository (a Git checkout)")
    ap.add_argument("--version", metavar="ID", required=True, help="the commit to apply (signed)")
    ap.add_argument("--box", metavar="NAME", help="the box (default: the box file's name)")
    ap.add_argument("--interrupt-tests", action="store_true",
                    help="stop the running tests of the changed stations (journaled, published) "
                         "instead of deferring them; needs --by")
    ap.add_argument("--by", metavar="NAME", help="who interrupts the tests (with --interrupt-tests)")
    ap.add_argument("--health-timeout", type=float, metavar="S",
                    help="the health gate's bound (default: the box file's health_timeout_s, 60 s)")
    ap.add_argument("--json", action="store_true", help="the outcome as one JSON line on stdout")
    _common(ap)


def _apply(args: argparse.Namespace) -> int:
    if args.interrupt_tests and not args.by:
        raise CliError("--interrupt-tests needs --by NAME (who interrupts the tests)", 2)
    if args.health_timeout is not None and not 1 <= args.health_timeout <= 3600:
        raise CliError("--health-timeout: 1 … 3600 s", 2)
    s = _settings(args)
    box, state = _box(args, s), _state(args, s)
    quiet = args.json
    out = apply_version(args.root, args.version, box, s, state,
                        interrupt_by=args.by if args.interrupt_tests else None,
                        health_timeout=args.health_timeout,
                        say=(lambda t: None) if quiet else (lambda t: print(t, file=sys.stderr)))
    for line in out.errors:
        print(line, file=sys.stderr)
    if args.json:
        _print_json(out.as_dict())
    else:
        if out.plan is not None:
            print(plan_text(out.plan))
        word = {0: "nothing to do", 1: "error", 3: "applied", 4: "refused", 5: "rolled back"}[out.code]
        v = (out.version or "?")[:12]
        print(f"{v}: {word}" + (f": {out.why}" if out.why else "")
              + (f"; deferred until their tests end: {', '.join(out.deferred)}" if out.deferred else ""))
    return out.code


# ---------------------------------------------------------------------------------- rollback, status
def _rollback_args(ap: argparse.ArgumentParser) -> None:
    ap.add_argument("--to", metavar="ID", help="a staged version (default: the last verified one)")
    ap.add_argument("--json", action="store_true", help="the outcome as one JSON line")
    _common(ap)


def _rollback(args: argparse.Namespace) -> int:
    s = _settings(args)
    out = rollback(_state(args, s), args.to)
    if args.json:
        _print_json(out.as_dict())
    else:
        print(f"{(out.version or '?')[:12]}: {out.why}")
    return 0 if out.code in (0, 3) else out.code


def _restart_args(ap: argparse.ArgumentParser) -> None:
    ap.add_argument("--wait", type=float, default=0.0, metavar="S",
                    help="wait up to S s for every station to run this software (default 0: ask and report)")
    ap.add_argument("--all", action="store_true",
                    help="restart every station's worker, also those already on this version")
    ap.add_argument("--request", metavar="NAME",
                    help="name the request: asked again with the same NAME (a retry), the request "
                         "made first is awaited, not made again (Ansible: the release's fingerprint)")
    ap.add_argument("--json", action="store_true", help="the outcome as one JSON line")
    _common(ap)


def _restart(args: argparse.Namespace) -> int:
    if not 0 <= args.wait <= 86400:
        raise CliError("--wait: 0 … 86400 s", 2)
    if args.request is not None and not (0 < len(args.request) <= 128 and args.request.isprintable()):
        raise CliError("--request: 1 … 128 printable characters", 2)
    s = _settings(args)
    out = restart(_state(args, s), __version__, every=args.all, wait=args.wait, request=args.request)
    if args.json:
        _print_json(out.as_dict())
    else:
        print(f"{__version__}: " + ("every station runs it" if out.code == 0 else str(out.why)))
    return out.code


def _status_args(ap: argparse.ArgumentParser) -> None:
    ap.add_argument("--json", action="store_true", help="the report as one JSON object")
    _common(ap)


def _status(args: argparse.Namespace) -> int:
    s = _settings(args)
    rep = build_report(_state(args, s))
    if args.json:
        _print_json(rep)
        return 0
    print(json.dumps(rep, indent=2, ensure_ascii=False))
    return 0


@dataclass(frozen=True)
class Subcommand:
    """One ``hookwatch config`` subcommand."""
    name: str
    help: str
    description: str
    add_arguments: Callable[[argparse.ArgumentParser], None]
    run: Callable[[argparse.Namespace], int]


def _row(name: str, help_: str, add: Callable[[argparse.ArgumentParser], None],
         run_: Callable[[argparse.Namespace], int]) -> Subcommand:
    return Subcommand(name, help_, help_, add, run_)


#: the subcommands, in the order `hookwatch config --help` lists them
SUBCOMMANDS: tuple[Subcommand, ...] = (
    _row("check", "check a box's candidate tree, or the whole site (--site): FILE:LINE: message",
         _check_args, _check),
    _row("plan", "per station what an apply would do (exit 0 nothing, 3 changes)", _plan_args, _plan),
    _row("apply", "stage, switch, reload, health gate, rollback (exit 0 nothing, 3 applied, 4 refused, "
         "5 rolled back)", _apply_args, _apply),
    _row("rollback", "back to the last verified version", _rollback_args, _rollback),
    _row("restart", "new software installed: each station's worker restarts once idle (a test "
         "running: when it ends); exit 0 done, 6 still waiting", _restart_args, _restart),
    _row("status", "the box's config report", _status_args, _status),
    Subcommand("acl", config_acl.HELP, config_acl.DESCRIPTION, config_acl.add_arguments, config_acl.run),
)


def add_arguments(ap: argparse.ArgumentParser) -> None:
    sub = ap.add_subparsers(dest="config_command", metavar="SUBCOMMAND", required=True)
    for s in SUBCOMMANDS:
        p = sub.add_parser(s.name, help=s.help, description=s.description)
        s.add_arguments(p)
        p.set_defaults(_config_run=s.run)


def run(args: argparse.Namespace) -> int:
    return int(args._config_run(args) or 0)
