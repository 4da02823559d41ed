"""The rate limits of the node controls: Rebirth, Reboot and Next Server. Pure: the time is given.

A host (or anyone who may publish on the broker) can send ``Node Control/Rebirth``, ``Reboot`` or
``Next Server`` as often as it likes; each costs every birth, or a whole session. So at most one
birth per ``interval_ms`` (a Rebirth inside it is coalesced into one pending rebirth), and at most
one session end per ``interval_ms`` after the session's birth and after the last end (a Reboot or
Next Server inside it is coalesced into one pending end, Next Server over Reboot). The node carries
the pending ones out from its ``tick`` once they are due (docs/sparkplug.md, "Limits").
"""
from __future__ import annotations

from .actions import Disconnect


class Pacing:
    """When a birth or a session end may go out, and the pending (coalesced) ones."""

    def __init__(self, interval_ms: int, counters: dict[str, int]) -> None:
        self.interval_ms = int(interval_ms)
        self.counters = counters
        self._last_birth_ms: int | None = None
        self._last_end_ms: int | None = None
        self.rebirth_pending = False
        #: a Reboot / Next Server asked within the interval: carried out by the node's tick
        self.disconnect_pending: Disconnect | None = None

    # ------------------------------------------------------------------ births
    def born(self, now_ms: int) -> None:
        """An NBIRTH went out: it carries everything a pending rebirth asked for."""
        self._last_birth_ms = int(now_ms)
        self.rebirth_pending = False

    def birth_due(self, now_ms: int) -> bool:
        last = self._last_birth_ms
        return last is None or now_ms < last or now_ms - last >= self.interval_ms

    def ask_rebirth(self, now_ms: int) -> bool:
        """A Rebirth: True when it may go out now; otherwise it is pending (coalesced, counted)."""
        if self.birth_due(now_ms):
            return True
        if self.rebirth_pending:
            self.counters["rebirths_coalesced"] += 1
        self.rebirth_pending = True
        return False

    def due_rebirth(self, now_ms: int, live: bool) -> bool:
        """The pending rebirth may go out now; dropped when the session is not ``live`` (connected,
        host online, born): the next session's births carry everything."""
        if not self.rebirth_pending:
            return False
        if not live:
            self.rebirth_pending = False
            return False
        return self.birth_due(now_ms)

    # ------------------------------------------------------------------ session ends
    def end_due(self, now_ms: int) -> bool:
        """A Reboot / Next Server may end the session now: the interval has passed since the
        session's birth and since the last one (a reconnect is a birth too)."""
        for last in (self._last_birth_ms, self._last_end_ms):
            if last is not None and last <= now_ms and now_ms - last < self.interval_ms:
                return False
        return True

    def ask_end(self, d: Disconnect, now_ms: int) -> bool:
        """A Reboot / Next Server: True when it may end the session now; otherwise it is pending
        (coalesced, counted; Next Server over Reboot)."""
        if self.end_due(now_ms):
            return True
        if self.disconnect_pending is not None:
            self.counters["reboots_coalesced"] += 1
        if self.disconnect_pending is None or d.next_server:
            self.disconnect_pending = d
        return False

    def ended(self, now_ms: int) -> None:
        """A Reboot / Next Server ends the session now (counted)."""
        self.disconnect_pending = None
        self._last_end_ms = int(now_ms)
        self.counters["reboots"] += 1

    def due_end(self, now_ms: int, connected: bool) -> Disconnect | None:
        """The pending session end, once due (dropped when there is no session to end; a due one
        drops the pending rebirth too: the next session's births carry everything)."""
        d = self.disconnect_pending
        if d is None:
            return None
        if not connected:
            self.disconnect_pending = None
            return None
        if not self.end_due(now_ms):
            return None
        self.rebirth_pending = False
        return d

    def session_gone(self) -> None:
        """The session ended otherwise: the end it asked for is done."""
        self.disconnect_pending = None
