"""`hookwatch config SUBCOMMAND`: the configuration of a box and of its site.

The subcommands are the rows of :data:`SUBCOMMANDS`, each a :class:`Subcommand` — its name, one
line of help, its description, ``add_arguments(parser)`` and ``run(args) -> int`` — kept in a
module of its own (``gateway/cli/config_<name>.py``); adding one is adding its row. Today:

- ``acl`` (:mod:`.config_acl`): the broker's permissions generated from the station files.
"""
from __future__ import annotations

import argparse
from collections.abc import Callable
from dataclasses import dataclass

from . import config_acl

HELP = "the configuration of a box and its site: acl (the broker's permissions from the station files)"
DESCRIPTION = HELP + ". `hookwatch config SUBCOMMAND --help` says more of each."


@dataclass(frozen=True)
class Subcommand:
    """One ``hookwatch config`` subcommand."""
    name: str
    help: str
    description: str
    add_arguments: Callable[[argparse.ArgumentParser], None]
    run: Callable[[argparse.Namespace], int]


#: the subcommands, in the order `hookwatch config --help` lists them
SUBCOMMANDS: tuple[Subcommand, ...] = (
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
