"""The box's configuration report: one definition of its content (:func:`build_report`), what
``hookwatch config status`` prints and what the box's supervisor publishes, retained with a Will,
on ``<prefix>/<site>/box/<box>/config`` (gateway/supervisor/boxpublish.py; its fields:
``BOX_CONFIG_FIELDS`` of gateway/outputs/mqtt/schema.py, docs/mqtt.md).
"""
from __future__ import annotations

import datetime as _dt
import os
import time
from typing import Any

from .versions import StateDir, read_json

__all__ = ["REPORT_SCHEMA", "build_report", "iso_ms", "supervisor_alive"]

REPORT_SCHEMA = 1
#: drift files named in a report at most
MAX_DRIFT_FILES = 50


def supervisor_alive(state: StateDir) -> int | None:
    """The pid of the box's running supervisor (from its pid file), or None."""
    try:
        with open(state.path("supervisor.pid"), encoding="ascii") as f:
            pid = int(f.read(32).strip())
        os.kill(pid, 0)
    except (OSError, ValueError):
        return None
    return pid


def iso_ms(t: float) -> str:
    """UTC ISO 8601 with milliseconds and Z (as every MQTT payload of the gateway)."""
    d = _dt.datetime.fromtimestamp(round(float(t), 3), tz=_dt.UTC)
    return d.strftime("%Y-%m-%dT%H:%M:%S.") + f"{d.microsecond // 1000:03d}Z"


def _iso(t: Any) -> str | None:
    return iso_ms(float(t)) if isinstance(t, (int, float)) and not isinstance(t, bool) else None


def build_report(state: StateDir, status: dict[str, Any] | None = None,
                 online: bool | None = None) -> dict[str, Any]:
    """The report from the state folder and the supervisor's status (``supervisor.json`` when
    ``status`` is None)."""
    cur, ver = state.current(), state.verified()
    man = state.manifest(cur) if cur else None
    st = status if status is not None else (read_json(state.path("supervisor.json")) or {})
    raw = st.get("stations")
    stations: dict[str, Any] = raw if isinstance(raw, dict) else {}
    applied_at = None
    if cur and cur == ver:
        try:
            applied_at = iso_ms(os.path.getmtime(state.path("verified")))
        except OSError:
            pass
    ap = state.applying()
    uv = state.unverified()
    rb = state.last_rollback()
    drift = [str(x) for x in st.get("drift_files") or []][:MAX_DRIFT_FILES]
    pending = sorted(n for n, s in stations.items() if isinstance(s, dict) and s.get("pending"))
    deferred = sorted(n for n in pending if stations[n].get("in_test"))
    interrupt = st.get("last_interrupt")
    return {
        "schema": REPORT_SCHEMA, "box": (man or {}).get("box") or st.get("box"),
        "site": (man or {}).get("site") or st.get("site"),
        "online": bool(supervisor_alive(state)) if online is None else online,
        "time": iso_ms(time.time()), "version": cur, "sha256": (man or {}).get("sha256"),
        "verified": ver, "applied_at": applied_at,
        "applying": ap.get("version") if ap else None,
        "unverified": ({"version": uv.get("version"), "why": uv.get("why")} if uv else None),
        "supervisor": ({"pid": st.get("pid"), "software": st.get("software"),
                        "started": _iso(st.get("started"))} if st.get("pid") else None),
        "deferred": deferred, "pending": pending, "stations": stations,
        "last_rollback": (dict(rb, time=_iso(rb.get("time"))) if rb else None),
        "last_interrupt": (dict(interrupt, time=_iso(interrupt.get("time")))
                           if isinstance(interrupt, dict) else None),
        "drift": bool(drift), "drift_files": drift,
    }
