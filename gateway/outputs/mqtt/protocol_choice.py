"""MQTT 5 or 3.1.1: the protocol choice of the MQTT pump's session (``mqtt.protocol``).

``5`` and ``3.1.1`` are fixed. ``auto`` starts with MQTT 5 and falls back to 3.1.1, for good and
with one log line saying what that costs, when the broker refuses it: a CONNACK with 132
(Unsupported Protocol Version; a 3.1.1 broker answers 1, unacceptable version), or — a broker
that does not speak MQTT 5 may just close the connection, and so may one going down — a
connection closed before its CONNACK twice in a row. A broker that accepted MQTT 5 once is never
left for 3.1.1. :class:`ProtocolChoice` holds that state; the pump (:mod:`.pump`) asks it
which protocol to connect with and tells it how each connection went.

Used from the pump thread only.
"""
from __future__ import annotations

import logging

from .settings import MqttSettings

log = logging.getLogger("hookwatch.mqtt")

#: what MQTT 3.1.1 costs against MQTT 5 (the one log line of a fallback; docs/mqtt.md says the same)
V311_COSTS = ("no Response Topic / Correlation Data (command replies go to `reply`, matched by "
              "`request_id`), no user properties, no message expiry")
#: CONNACK reason codes that refuse the protocol version: 1 (MQTT 3.1.1, unacceptable protocol
#: version), 132 (MQTT 5, Unsupported Protocol Version)
VERSION_REFUSED = (1, 132)


class ProtocolChoice:
    """The protocol of the next connection (:attr:`v5`) and the fallback of ``auto`` (see the
    module docstring); ``counters`` are the pump's (``mqtt311_fallbacks``)."""

    def __init__(self, settings: MqttSettings, counters: dict[str, int]) -> None:
        self.s = settings
        self.counters = counters
        #: MQTT 5 for the next connection (auto: until the broker refuses it)
        self.v5 = settings.protocol in ("auto", "5")
        self._connack = False
        self._v5_ok = False         # the broker accepted MQTT 5 once: never fall back
        self._v5_closed = 0         # MQTT 5 connections closed before their CONNACK, in a row

    def connecting(self) -> None:
        """A CONNECT is on its way: no CONNACK yet."""
        self._connack = False

    def version_refused(self, failure: bool, reason: int) -> bool:
        """Whether a CONNACK (``failure``, its reason code) refused MQTT 5 itself."""
        return failure and self.v5 and reason in VERSION_REFUSED

    def connack(self) -> None:
        """A CONNACK that did not refuse the version came."""
        self._connack = True
        self._v5_closed = 0

    def accepted(self) -> None:
        """The broker accepted the session: if MQTT 5, it is never left for 3.1.1."""
        self._v5_ok = self._v5_ok or self.v5

    def closed(self, why: str) -> str | None:
        """The connection was lost (``why``): the reason to fall back when it counts as the
        broker's refusal of MQTT 5 (closed before CONNACK the second time in a row), else None."""
        if not self._connack and self.v5:
            self._v5_closed += 1
            if self._v5_closed >= 2:
                return f"connection closed before CONNACK twice ({why})"
        return None

    def fall_back(self, why: str, server: tuple[str, int]) -> bool:
        """``protocol: auto`` and ``server`` did not take an MQTT 5 CONNECT (``why``): use 3.1.1
        from now on (logged once, counted). False when there is nothing to fall back from (3.1.1
        already, ``protocol: 5``, or MQTT 5 was accepted before)."""
        if not (self.v5 and self.s.protocol == "auto") or self._v5_ok:
            return False
        host, port = server
        log.warning("%s: MQTT broker %s:%s refused MQTT 5 (%s); using MQTT 3.1.1 from now on, which "
                    "costs: %s", self.s.station_id, host, port, why, V311_COSTS)
        self.counters["mqtt311_fallbacks"] += 1
        self.v5 = False
        return True
