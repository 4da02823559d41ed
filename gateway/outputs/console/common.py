"""What every room of the console shares: its bounds, the strict JSON reply, the client error.

The app (``app.py``), its context (``context.py``) and the route modules (``routes_*.py``) take
these from here, so no route module imports the app back.
"""
from __future__ import annotations

import ipaddress
import os
from typing import Any

from aiohttp import web

from ...plumbing import safeout


def json_reply(data: Any, **kw: Any) -> web.Response:
    """A JSON response, strict: never NaN/Infinity (a non-finite number is null; gateway.plumbing.safeout)."""
    return web.json_response(data, dumps=safeout.dumps, **kw)

STATIC = os.path.join(os.path.dirname(os.path.abspath(__file__)), "static")
#: largest request body accepted
MAX_BODY = 16 * 1024
#: messages queued per live client before it is dropped as too slow
CLIENT_QUEUE = 64
#: a client that cannot take one message within this long is dropped
WRITE_TIMEOUT_S = 10.0
#: kernel send buffer and transport high-water mark of a live client, bytes
SEND_BUFFER = 16 * 1024
#: most live (SSE) clients at once
MAX_CLIENTS = 64
#: deepest JSON nesting ([ and {) a request body may have
MAX_JSON_DEPTH = 16
#: how often the console drains the hand-overs and sends changes
TICK_S = 0.25
#: reads from disk (a station's hooks, the due list as CSV) a minute from one address
FILE_READS_PER_MIN = 60
#: longest line / area filter of the due list, characters
FILTER_MAX = 64
COOKIE = "hw_session"


def is_loopback(remote: str | None) -> bool:
    try:
        return ipaddress.ip_address(remote or "").is_loopback
    except ValueError:
        return False


class HttpError(Exception):
    def __init__(self, status: int, reason: str):
        super().__init__(reason)
        self.status, self.reason = status, reason


def cut(text: str, n: int = 60) -> str:
    """Client text quoted in a log line: at most ``n`` characters, no control characters."""
    t = "".join(ch if ch.isprintable() else "?" for ch in str(text)[:n])
    return t if len(text) <= n else f"{t}… ({len(text)} chars)"


def err(status: int, reason: str, headers: dict | None = None) -> web.Response:
    return json_reply({"ok": False, "reason": reason}, status=status, headers=headers)
