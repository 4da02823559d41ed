"""What a station's MQTT output needs, built from its ``mqtt:`` section (gateway/outputs/registry.py).

One definition read by the output (:mod:`.output`) and by each room of its transport: the pump
(:mod:`.pump`), its delivery side (:mod:`.delivery`), what it receives
(:mod:`.router`) and the MQTT 5 / 3.1.1 choice (:mod:`.protocol_choice`).
"""
from __future__ import annotations

from dataclasses import dataclass

from ..broker.settings import BrokerSettings

__all__ = ["PROTOCOLS", "MqttSettings"]

#: values of ``mqtt.protocol``
PROTOCOLS = ("auto", "5", "3.1.1")


@dataclass
class MqttSettings(BrokerSettings):
    """What the MQTT output needs (built from a station's `mqtt:` section by gateway/outputs/registry.py); the broker
    connection (host, port, credentials, TLS, back-off) is the shared :class:`BrokerSettings`."""
    station_id: str
    base_topic: str
    protocol: str = "auto"            # auto (MQTT 5, 3.1.1 if the broker refuses it), 5, 3.1.1
    telemetry_interval_s: float = 1.0
    outbox_path: str = "outbox.sqlite"
    telemetry_budget_bytes: int = 50 * 1024 * 1024
    window: int = 16                  # messages in flight at most
    drain_on_stop_s: float = 2.0      # on a clean stop, time allowed to deliver what is pending
    #: MQTT 5 Response Topics are obeyed only below this (``mqtt.reply_prefix``); None: ``<base>/reply``
    reply_prefix: str | None = None
    #: share the station's lives with its site and receive theirs (``mqtt.share_lives``;
    #: gateway/outputs/mqtt/sitelives.py), and the station's records folder (its own lives)
    share_lives: bool = False
    records_dir: str | None = None
    #: the named command doors the station listens on besides the default (``mqtt.command_doors``):
    #: ``<base>/cmd/<door>/<command>``, each with its own source ``mqtt:<door>`` and command budget
    command_doors: tuple[str, ...] = ()
