"""The configuration sections of plug-in outputs (``$HOOKWATCH_OUTPUTS``): the output registry's
configuration half, which the loader reads.

A plug-in output is one row of the output registry (:mod:`gateway.outputs.registry`), registered
by a module that ``$HOOKWATCH_OUTPUTS`` names (``module[,module]``). Its row carries the schema of
its own section (a frozen dataclass of :func:`gateway.config.sections.key` fields, ``enabled``
among them); registering the row adds that section here, so every reader of a station file
(``hookwatch run``, a fleet's workers and supervisor, ``hookwatch check``, the commissioning
probe) accepts it, checks it like any other and hands it to the output on
``StationConfig.plugins``; the doors the row listens on join the clash checks between stations.
The built-in outputs' sections are fields of :class:`~gateway.config.sections.StationConfig`.
"""
from __future__ import annotations

import importlib
import os
import re
from collections.abc import Callable
from dataclasses import dataclass
from typing import TypeVar

from . import sections as S

__all__ = ["PLUGINS_ENV", "Door", "PluginSection", "add_section", "load_plugins", "plugin_config",
           "sections"]

#: the modules that register plug-in outputs, ``module[,module]`` (each imported once per process)
PLUGINS_ENV = "HOOKWATCH_OUTPUTS"
#: the outputs shipped with hookwatch as registered rows (python-can's ``BACKENDS``): a new output
#: of the product is its module under gateway/outputs/ (the output, its section's schema and its
#: :func:`~gateway.outputs.registry.register` call), one line here and its docs entry. Named, not
#: imported: the configuration layer never imports an output; they load with the plug-ins.
IN_TREE: tuple[str, ...] = ()
_MODULE_RE = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*(\.[A-Za-z_][A-Za-z0-9_]*)*$")

#: (configuration key, host, port) an output listens on
Door = tuple[str, str, int]
T = TypeVar("T")


@dataclass(frozen=True)
class PluginSection:
    """The configuration half of a plug-in output's row."""
    spec: S.Section                                  # its keys (checked like any section)
    doors: Callable[[S.StationConfig], list[Door]]   # the doors it listens on, when enabled
    shared: bool                                     # a fleet shares one listener (stations may name the same door)


_SECTIONS: dict[str, PluginSection] = {}
_LOADED: set[str] = set()


def add_section(name: str, cls: type, doc: str, doors: Callable[[S.StationConfig], list[Door]],
                shared: bool) -> None:
    """The section ``name:`` of a plug-in output (its row's registration). A name the station
    file already has, or one registered with another schema, is refused (ValueError)."""
    if S.lookup((name,)) is not None or name in ("plugins", "source", "fleet_file"):
        raise ValueError(f"{name!r} is a section of every station file: a plug-in output needs a "
                         "section of its own")
    old = _SECTIONS.get(name)
    if old is not None and old.spec.cls is not cls:
        raise ValueError(f"{name!r}: a plug-in section of that name is registered already")
    if "enabled" not in {e.name for e in S.section_spec(name, cls, doc).entries}:
        raise ValueError(f"{name!r}: a plug-in section needs an `enabled` key")
    _SECTIONS[name] = PluginSection(S.section_spec(name, cls, doc), doors, shared)


def sections() -> tuple[PluginSection, ...]:
    """The registered plug-in sections (after :func:`load_plugins`)."""
    return tuple(_SECTIONS.values())


def load_plugins() -> None:
    """Import the modules of :data:`IN_TREE`, then those ``$HOOKWATCH_OUTPUTS`` names (each once):
    their rows register their outputs and sections. A name that does not import is an error at
    start-up (ImportError, ValueError), not a silently missing output."""
    named = (x.strip() for x in os.environ.get(PLUGINS_ENV, "").split(","))
    for mod in filter(None, (*IN_TREE, *named)):
        if mod in _LOADED:
            continue
        if not _MODULE_RE.match(mod):
            raise ValueError(f"{PLUGINS_ENV}: {mod!r} is not a module name (module[,module])")
        importlib.import_module(mod)
        _LOADED.add(mod)


def plugin_config(cfg: S.StationConfig, name: str, cls: type[T]) -> T:
    """The section ``name:`` of a plug-in output in ``cfg``, as its schema ``cls``."""
    v = cfg.plugins.get(name)
    if not isinstance(v, cls):
        raise LookupError(f"station {cfg.station.id}: no plug-in section {name!r} of {cls.__name__}")
    return v
