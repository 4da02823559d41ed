"""The console's Boxes page (issue 37): every box of the site as its retained config report says
it — the version of the site's configuration it runs, the stations whose new configuration waits
for their test to end, drift (a hand edit of its tree), its last rollback and why, online or not.

The reports arrive with the site view (gateway/outputs/console/site.py): ``<prefix>/<site>/box/+/config``
(:func:`gateway.outputs.mqtt.schema.box_config_topic`), on the same MQTT session. A report goes
through the one bounded JSON reader, every kept field is type-checked and every string clipped to
printable ASCII; at most :data:`MAX_BOXES` boxes are kept. A Will (``online: false``, few fields)
updates the box's last report rather than replacing it. Read-only.
"""
from __future__ import annotations

import threading
import time
from typing import Any

from ...core.command_intake import Refused, bounded_pairs, read_bounded_json
from ...plumbing.ratelog import clip
from ..mqtt.schema import BOX_CONFIG, BOX_LEVEL

__all__ = ["MAX_BOXES", "BoxReports", "box_filter"]

#: boxes kept at most
MAX_BOXES = 256
#: one report, bytes (stations of a box and their versions: a few KB)
MAX_REPORT_BYTES = 64 * 1024
#: stations of one box listed at most; drift files at most
MAX_LIST = 256
MAX_TEXT = 80

_pairs = bounded_pairs(MAX_LIST, 64, 400)
_TEXT = ("box", "site", "time", "version", "sha256", "verified", "applied_at", "applying")
_REC = {"last_rollback": ("from", "to", "why", "time"), "last_interrupt": ("by", "version", "time")}


def box_filter(base: str) -> str:
    """``<prefix>/<site>/box/+/config`` of a station's base topic."""
    return "/".join(base.split("/")[:-3] + [BOX_LEVEL, "+", BOX_CONFIG])


def _text(v: Any, n: int = MAX_TEXT) -> str | None:
    if v is None:
        return None
    if not isinstance(v, str):
        raise Refused(f"{clip(v, 20)} is not a string")
    return "".join(c if 0x20 <= ord(c) <= 0x7E else "?" for c in v[:n])


def _names(v: Any) -> list[str]:
    if v is None:
        return []
    if not isinstance(v, list) or len(v) > MAX_LIST:
        raise Refused("not a list of names")
    return [str(_text(x, 64)) for x in v]


def parse_report(obj: Any, box: str) -> dict[str, Any]:
    """A report (or a Will) → the fields kept, or :class:`Refused`."""
    if not isinstance(obj, dict) or obj.get("box") != box:
        raise Refused(f"a report of box {clip(obj.get('box') if isinstance(obj, dict) else obj, 40)} "
                      f"on the topic of {clip(box, 40)}")
    out: dict[str, Any] = {}
    for k in _TEXT:
        if k in obj:
            out[k] = _text(obj[k])
    for k in ("online", "drift"):
        if k in obj:
            if not isinstance(obj[k], bool):
                raise Refused(f"{k}: not true/false")
            out[k] = obj[k]
    for k in ("deferred", "pending", "drift_files"):
        if k in obj:
            out[k] = _names(obj[k])
    for k, keys in _REC.items():
        if k in obj:
            v = obj[k]
            if v is not None and not isinstance(v, dict):
                raise Refused(f"{k}: not an object")
            out[k] = None if v is None else {x: _text(v.get(x), 300 if x == "why" else MAX_TEXT)
                                             if not isinstance(v.get(x), (int, float)) else v.get(x)
                                             for x in keys}
            if v is not None and k == "last_interrupt":
                out[k]["stations"] = _names(v.get("stations"))
    st = obj.get("stations")
    if st is not None:
        if not isinstance(st, dict):
            raise Refused("stations: not an object")
        out["stations"] = {str(_text(n, 64)): {"version": _text((s or {}).get("version")),
                                               "pending": _text((s or {}).get("pending")),
                                               "in_test": bool((s or {}).get("in_test")),
                                               "running": bool((s or {}).get("running")),
                                               "refused": _text((s or {}).get("refused"), 200)}
                           for n, s in st.items() if isinstance(s, dict)}
    return out


class BoxReports:
    """The site's boxes as their reports last said (pump thread writes, console loop reads)."""

    def __init__(self, log_refused: Any) -> None:
        self._boxes: dict[str, dict[str, Any]] = {}
        self._lock = threading.Lock()
        self._refused = log_refused
        self.counters = {"reports": 0, "refused": 0, "over_bound": 0}

    @staticmethod
    def box_of(topic: str) -> str | None:
        parts = topic.split("/")
        if len(parts) >= 4 and parts[-1] == BOX_CONFIG and parts[-3] == BOX_LEVEL:
            return parts[-2]
        return None

    def receive(self, topic: str, payload: bytes, now: float | None = None) -> bool:
        box = self.box_of(topic)
        if box is None:
            return False
        self.counters["reports"] += 1
        if not payload:                 # a retired box's report cleared
            with self._lock:
                return self._boxes.pop(box, None) is not None
        try:
            rep = parse_report(read_bounded_json(payload, max_bytes=MAX_REPORT_BYTES, max_depth=5,
                                                 pairs=_pairs), box)
        except Refused as e:
            self.counters["refused"] += 1
            self._refused.warning(("box", "config"), "console: the config report of box %s refused: %s",
                                  clip(box, 40), e)
            return False
        with self._lock:
            cur = self._boxes.get(box)
            if cur is None and len(self._boxes) >= MAX_BOXES:
                self.counters["over_bound"] += 1
                return False
            cur = cur if cur is not None else {}
            cur.update(rep, heard_at=time.time() if now is None else now)
            self._boxes[box] = cur
        return True

    def rows(self) -> list[dict[str, Any]]:
        """One row per box, by name."""
        with self._lock:
            return [dict(v, box=k) for k, v in sorted(self._boxes.items())]
