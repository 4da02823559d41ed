import os
import sys

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
VECTORS = os.path.join(HERE, "vectors")
VENV_BIN = os.path.join(ROOT, ".venv", "bin")


def hookwatch_cmd() -> list[str]:
    """The console command as a user runs it (the venv's, else the one on PATH)."""
    exe = os.path.join(os.path.dirname(sys.executable), "hookwatch")
    if os.path.exists(exe):
        return [exe]
    return [sys.executable, "-m", "gateway.cli"]
