"""What one Sparkplug edge node needs, built from a station's ``sparkplug:`` section (output.py).

The broker connection is the shared :class:`~gateway.outputs.broker.settings.BrokerSettings`
(``servers``, the Sparkplug server set, defaults to its host and port); the rest names the node
and its device, its store, and the bounds on what it receives.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

from ..broker.settings import BrokerSettings


@dataclass
class SparkplugSettings(BrokerSettings):
    """What an edge node needs (built from a station's `sparkplug:` section by output.py); the broker
    connection is the shared :class:`BrokerSettings` (``servers`` defaults to its host and port)."""
    group_id: str
    edge_node_id: str
    device_id: str
    primary_host_id: str | None = None
    data_interval_s: float = 1.0
    store_path: str = "sparkplug.sqlite"
    history_budget_bytes: int = 50 * 1024 * 1024
    #: the first CONNECT waits this long after the first station attached, so that the stations of
    #: a fleet starting together get their DBIRTHs right after the NBIRTH
    gather_s: float = 0.5
    #: at most one birth per this interval; Rebirth requests inside it are coalesced into one
    rebirth_min_interval_s: float = 2.0
    max_command_bytes: int = 16384
    max_command_metrics: int = 64
    max_string_chars: int = 256
    state_max_bytes: int = 1024
    #: a STATE timestamp further ahead of this node's clock is taken as "now" (docs/sparkplug.md)
    state_future_skew_s: float = 300.0

    section: ClassVar[str] = "sparkplug"

    def node_key(self) -> tuple:
        return (tuple(self.servers), self.group_id, self.edge_node_id)
