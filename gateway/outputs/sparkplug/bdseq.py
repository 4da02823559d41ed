"""The node's birth/death sequence number (bdSeq): one per MQTT CONNECT. Pure.

Each CONNECT carries the next bdSeq (0 … 255, then 0 again) in its Will, the NDEATH, and the
session's NBIRTH carries the same one (tck-id-topics-nbirth-bdseq-increment, -matching). The caller
persists :meth:`BdSeq.last_used` after :meth:`BdSeq.next_connect` and before it connects, so that a
restart after kill -9 continues from it; a TCP connection that failed sent no CONNECT, so its bdSeq
is not used up (:meth:`BdSeq.not_sent`).
"""
from __future__ import annotations


class BdSeq:
    """bdSeq of the current session (the last one used before a restart until the first
    :meth:`next_connect`)."""

    def __init__(self, last_used: int | None = None) -> None:
        self.value = 0 if last_used is None else int(last_used) % 256
        self._fresh = last_used is None
        self._before_connect = (self.value, self._fresh)

    @property
    def fresh(self) -> bool:
        """No bdSeq used yet (the first CONNECT will carry 0)."""
        return self._fresh

    def next_connect(self) -> int:
        """Before each CONNECT: the bdSeq it carries."""
        self._before_connect = (self.value, self._fresh)
        if self._fresh:
            self._fresh = False
        else:
            self.value = (self.value + 1) % 256
        return self.value

    def not_sent(self) -> None:
        """No CONNECT packet went out (the TCP connection failed): the bdSeq is not used up."""
        self.value, self._fresh = self._before_connect

    def last_used(self) -> int | None:
        """What to persist for the next process: the bdSeq of the coming (or last) CONNECT, None
        while none was used."""
        return self.value if not self._fresh else None
