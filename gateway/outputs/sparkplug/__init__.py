"""Sparkplug B 3.0 edge node: each station a device of its node (docs/sparkplug.md).

- :mod:`.metrics`  — the one definition of node and device metrics (names, types, units, aliases);
- :mod:`.node`     — the pure state machine (births, deaths, seq, bdSeq, STATE, store and forward,
  commands), on :mod:`.sparkplug_b_pb2` (generated from sparkplug_b.proto; see :mod:`.gen`);
- :mod:`.runtime`   — the paho-mqtt client and the node's thread (one per edge node);
- :mod:`.output`   — a station's Output feeding its node.
"""
