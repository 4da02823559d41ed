"""YAML with positions: every key of a configuration file remembers its file and line, so a
validation error can say ``config/stations/loom-02.yaml:14: meter.baud: …``.

The reading itself — size, encoding, nesting, alias and integer limits, the safe schema — is
:mod:`gateway.plumbing.safeyaml`, the one reader of every YAML file the gateway reads; this module names
what the configuration loader uses of it.
"""
from __future__ import annotations

from ..plumbing.safeyaml import CONFIG, Doc, KeyPath, Limits, Pos, YamlError, YamlLimitError, kind, load

Path = KeyPath

__all__ = ["CONFIG", "Doc", "Limits", "Path", "Pos", "YamlError", "YamlLimitError", "kind", "load"]
