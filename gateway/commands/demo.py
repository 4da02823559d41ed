"""`hookwatch demo`: the main job on its built-in default.

Until the simulated station exists, this analyses the bundled example logs."""
from __future__ import annotations

import glob
import os

HELP = "run hookwatch on its built-in default (no hardware needed)"


def add_arguments(ap):
    pass


def run(args) -> int:
    from . import analyze

    here = os.path.dirname(os.path.abspath(__file__))
    logs = sorted(glob.glob(os.path.join(here, "..", "..", "tests", "vectors", "*.csv.gz")))
    if not logs:
        print("hookwatch demo: no example logs found")
        return 1
    ns = type("A", (), {"logs": [os.path.relpath(p) for p in logs], "set": [], "json": False})
    return analyze.run(ns)
