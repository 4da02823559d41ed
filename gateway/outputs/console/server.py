"""The console's old import path: the console is now ``app.py`` (the app and its lifecycle) with
its settings (``settings.py``) and route modules by subject (``routes_*.py``)."""
from __future__ import annotations

from .app import ConsoleServer
from .common import FILE_READS_PER_MIN
from .settings import ConsoleSettings, parse_listen

__all__ = ["FILE_READS_PER_MIN", "ConsoleServer", "ConsoleSettings", "parse_listen"]
