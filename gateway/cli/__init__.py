"""The `hookwatch` console command. Each subcommand lives in ``gateway/cli/<name>.py`` and
provides ``HELP`` (one line), ``add_arguments(parser)`` and ``run(args) -> int``."""
from __future__ import annotations

import argparse
import importlib
import sys

from .. import __version__

#: subcommands in the order `hookwatch --help` lists them
COMMANDS = ("run", "sim", "analyze", "report", "check", "config", "regmap", "demo", "user", "hooks")

EXIT_OK = 0
EXIT_USAGE = 2


class CliError(Exception):
    """A user-facing error: printed as one line on stderr, exit code ``code``."""

    def __init__(self, message: str, code: int = EXIT_USAGE):
        super().__init__(message)
        self.code = code


def _load(name: str):
    try:
        return importlib.import_module(f"gateway.cli.{name}")
    except ModuleNotFoundError as e:
        if e.name == f"gateway.cli.{name}":
            return None
        raise


def build_parser(only: str | None = None) -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog="hookwatch", description="Needle-hook wear-life gateway "
                                 "(yarn tension → capstan friction μ → wear-life endpoint).")
    ap.add_argument("--version", action="version", version=f"hookwatch {__version__}")
    sub = ap.add_subparsers(dest="command", metavar="COMMAND")
    for name in COMMANDS:
        if only is not None and name != only:
            # register a placeholder so `--help` of the one command stays cheap to build
            continue
        mod = _load(name)
        if mod is None:
            continue
        sp = sub.add_parser(name, help=mod.HELP, description=getattr(mod, "DESCRIPTION", mod.HELP))
        mod.add_arguments(sp)
        sp.set_defaults(_module=mod)
    return ap


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    # import only the subcommand asked for: `hookwatch analyze` must not pay for the runtime
    only = argv[0] if argv and argv[0] in COMMANDS else None
    ap = build_parser(only)
    args = ap.parse_args(argv)
    if not getattr(args, "_module", None):
        ap.print_help()
        return EXIT_USAGE
    try:
        return int(args._module.run(args) or 0)
    except CliError as e:
        print(f"hookwatch {args.command}: {e}", file=sys.stderr)
        return e.code
    except KeyboardInterrupt:
        return 130
    except BrokenPipeError:
        return 0


if __name__ == "__main__":
    sys.exit(main())
