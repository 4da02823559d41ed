"""scripts/setup.sh on a stock Debian (issue 28 item 1): a half-made `.venv` (made by `python3 -m venv`
without Debian's python3-venv: no pip) is detected, said, removed and made anew, and the product's
own set-up (`scripts/setup.sh`, `--demo`) installs the runtime dependencies alone, not the test tools.
Runs on a git clone of this checkout, with the interpreter this venv was made from."""
from __future__ import annotations

import os
import subprocess
import sys

from conftest import ROOT
from kit.tools import require_tool


def _run(argv, cwd, **kw):
    return subprocess.run(argv, cwd=cwd, capture_output=True, text=True, timeout=900, **kw)


def test_a_half_made_venv_is_rebuilt_with_the_product_alone(tmp_path):
    git = require_tool("git")
    clone = tmp_path / "hookwatch"
    r = _run([git, "clone", "-q", "--no-hardlinks", ROOT, str(clone)], cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    base = getattr(sys, "_base_executable", sys.executable)
    # what `python3 -m venv` leaves when Debian's ensurepip is missing: a venv without pip
    r = _run([base, "-m", "venv", "--without-pip", ".venv"], cwd=clone)
    assert r.returncode == 0, r.stderr
    assert _run([".venv/bin/python", "-m", "pip", "--version"], cwd=clone).returncode != 0

    env = {k: v for k, v in os.environ.items() if k != "VIRTUAL_ENV"}
    r = _run(["scripts/setup.sh"], cwd=clone, env={**env, "PYTHON": base})
    assert r.returncode == 0, r.stdout + r.stderr
    assert ".venv is not usable, it has no pip" in r.stderr and "making it anew" in r.stderr
    assert (clone / ".venv" / ".hookwatch-installed").read_text().strip() == "runtime"
    py = str(clone / ".venv" / "bin" / "python")
    assert _run([py, "-m", "pip", "--version"], cwd=clone).returncode == 0
    # the product imports and its command runs; the test tool chain is not there
    r = _run([str(clone / ".venv" / "bin" / "hookwatch"), "--help"], cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    r = _run([py, "-c", "import importlib.util as u, sys; "
              "print(*[m for m in ('pytest', 'playwright', 'mypy', 'ruff', 'grpc_tools', 'scipy') "
              "if u.find_spec(m)])"], cwd=tmp_path)
    assert r.returncode == 0 and r.stdout.split() == [], r.stdout + r.stderr

    # a second run finds the venv usable and installs nothing
    r = _run(["scripts/setup.sh"], cwd=clone, env={**env, "PYTHON": base})
    assert r.returncode == 0 and r.stderr == "", r.stderr
