"""The primary host application as the edge node follows it: its STATE and the timestamp rule. Pure.

With a primary host (``sparkplug.primary_host_id``) the node publishes its births only while the
host's ``spBv1.0/STATE/<host_id>`` says it is online, and ends its session when it goes offline
(tck-id-message-flow-edge-node-birth-publish-phid-wait,
tck-id-operational-behavior-edge-node-termination-host-offline). Without one the host counts as
always online.
"""
from __future__ import annotations

from .inbound import BadInput, BadInputs, InboundLimits, parse_state


class PrimaryHost:
    """Whether the primary host is online, from its STATE messages of the current MQTT session."""

    def __init__(self, host_id: str | None, limits: InboundLimits, bad: BadInputs,
                 future_skew_ms: int = 300_000) -> None:
        self.host_id = host_id
        self.limits = limits
        self.bad = bad
        self.counters = bad.counters
        self.future_skew_ms = int(future_skew_ms)
        self.online = host_id is None
        #: the timestamp of the last STATE accepted in this MQTT session
        self.ts = -1

    def session_start(self) -> None:
        """A CONNECT was accepted: STATE timestamps are compared within one MQTT session only;
        with a primary host, it is offline until its retained STATE says otherwise."""
        self.ts = -1
        if self.host_id is not None:
            self.online = False

    def state(self, payload: bytes, now_ms: int) -> bool | None:
        """A STATE in the 3.0 form ``{"online": bool, "timestamp": ms}``: True when the host came
        online with it, False when it went offline, None when nothing changed (or the STATE is
        bad: counted and noted, or stale: counted).

        The timestamp rule (docs/sparkplug.md "STATE timestamps"):

        - timestamps are compared with the last STATE accepted **in this MQTT session** only (reset
          at each CONNECT: the retained STATE a server delivers after SUBSCRIBE is that server's
          current word, so nothing seen before a reconnect or on another server can lock the host
          out);
        - a STATE older than the last one accepted in the session is ignored (counted
          ``stale_state``): tck-id-message-flow-edge-node-birth-publish-phid-wait-timestamp and
          tck-id-operational-behavior-edge-node-termination-host-offline-timestamp;
        - a timestamp more than ``future_skew_ms`` ahead of the node's clock is accepted
          (counted ``future_state``) but remembered as the node's clock at receipt, so that it
          cannot make the host's later, correctly dated STATE look stale.
        """
        try:
            online, ts = parse_state(payload, self.limits)
        except BadInput as e:
            self.bad.refused(e)
            return None
        if ts < self.ts:
            self.counters["stale_state"] += 1
            return None            # an older STATE than one already seen: ignored
        if ts > now_ms + self.future_skew_ms:
            self.counters["future_state"] += 1
            self.bad.note("future_state", f"STATE timestamp {ts} is more than {self.future_skew_ms} ms "
                          f"ahead of this node's clock {now_ms}; taken as now")
            ts = max(int(now_ms), self.ts)
        self.ts = ts
        if online and not self.online:
            self.online = True
            return True
        if not online and self.online:
            self.online = False
            return False
        return None
