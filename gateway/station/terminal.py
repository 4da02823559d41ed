"""A human-readable output for a terminal: one progress line every few seconds and a line per event
(`hookwatch demo`; not the web console, which is `gateway/outputs/console/`)."""
from __future__ import annotations

import math
import sys
import time

from ..core.records import Event, EventType, SlotRecord, StationState


def fmt(v: object) -> str:
    """A value as a person reads it: floats to 5 significant digits (0.00618, 240, 208.14), also
    inside dicts and lists (no 0.006180000000000004)."""
    if isinstance(v, bool) or v is None:
        return str(v)
    if isinstance(v, float):
        return f"{v:.5g}"
    if isinstance(v, dict):
        return "{" + ", ".join(f"{k}: {fmt(x)}" for k, x in v.items()) + "}"
    if isinstance(v, list | tuple):
        return "[" + ", ".join(fmt(x) for x in v) + "]"
    return str(v)


class TerminalOutput:
    def __init__(self, every_s: float = 5.0, stream=None):
        self.every = every_s
        self.stream = stream or sys.stdout
        self._last = 0.0
        self._state: StationState | None = None
        self._n = self._valid = 0
        self._mu = 0.0
        self._tm = 0.0
        self._tm_n = 0
        self._rec: SlotRecord | None = None

    async def start(self) -> None:
        pass

    async def stop(self) -> None:
        pass

    def _print(self, text: str) -> None:
        print(text, file=self.stream, flush=True)

    def on_record(self, rec: SlotRecord) -> None:
        self._n += 1
        self._rec = rec
        if rec.q and rec.mu is not None:
            self._valid += 1
            self._mu += rec.mu
        if rec.present:
            self._tm += (rec.t1 + rec.t2) / 2
            self._tm_n += 1
        now = time.monotonic()
        if now - self._last >= self.every and self._state is not None and self._state.test_id:
            self._last = now
            st = self._state
            mu = self._mu / self._valid if self._valid else math.nan
            tm = self._tm / self._tm_n if self._tm_n else math.nan
            base = f"μ_ss {st.mu_ss:.4f} μ_th {st.mu_th:.4f}" if st.mu_ss is not None else "baseline search"
            self._print(f"[{st.station}] t={rec.t:7.1f} s  {st.state.name.lower():15s} T̄={tm:.3f} N "
                        f"μ={mu:.4f} valid {self._valid}/{self._n}  n_cmd={rec.speed_cmd:6.1f} rpm  {base}")
            self._n = self._valid = self._tm_n = 0
            self._mu = self._tm = 0.0

    def on_event(self, ev: Event) -> None:
        d = {k: v for k, v in ev.data.items() if k != "result"}
        if ev.type == EventType.TEST_ENDED and "result" in ev.data and ev.data["result"]:
            r = ev.data["result"]
            d["status"] = r.get("status")
            if r.get("stop_reasons"):                # e.g. STOPPED for a test ended on purpose (§3)
                d["stop_reasons"] = "+".join(r["stop_reasons"])
            d["t_life"] = r.get("t_life")
        detail = ", ".join(f"{k}={fmt(v)}" for k, v in d.items())
        self._print(f"[{ev.station}] EVENT {ev.type.value}: {detail}")

    def on_state(self, st: StationState) -> None:
        self._state = st
