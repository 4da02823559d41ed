"""The one validation style of hookwatch: a problem is data, not text to be parsed back.

Station configuration (:mod:`gateway.config.loader`), meter register maps
(:mod:`drivers.meter.meter_map`), simulator scenarios (:mod:`drivers.sim.scenario`) and the method's
parameters (:mod:`gateway.core.method.params`) all report a bad value as a :class:`Problem` — the key
path, the value, what is allowed, a did-you-mean suggestion, and the file and line when known —
raised in a :class:`ValidationError` (``ParamError``, ``MapError``, ``ScenarioError`` are its
kinds). The message a person reads is made from those fields; a program reads the fields.

This module imports nothing of the project (drivers and gateway use it alike, without a cycle).
"""
from __future__ import annotations

import difflib
from collections.abc import Iterable
from dataclasses import dataclass, field
from typing import Any


class _Missing:
    def __repr__(self) -> str:
        return "MISSING"


#: ``Problem.value`` of a problem that is not about one value (a missing key, a rule)
MISSING: Any = _Missing()

KeyPath = tuple[Any, ...]  # ("meter", "baud"), ("channels", "ch1", "address"), ("faults", 0, "at_s")


def dotted(path: Iterable[Any]) -> str:
    return ".".join(str(p) for p in path)


@dataclass(frozen=True)
class Problem:
    """One thing wrong with one field.

    ``message`` is the sentence after ``key:`` (it says the value and what is allowed, as the
    user reads it); ``value``, ``allowed`` and ``suggestion`` are the same facts as data.
    ``related`` names other fields a rule between several fields involves (``r_min`` for a
    problem on ``r_max``), in the order the message names them."""
    path: KeyPath
    message: str
    value: Any = field(default=MISSING, compare=False)
    allowed: str | None = field(default=None, compare=False)
    suggestion: str | None = field(default=None, compare=False)
    file: str | None = None
    line: int | None = None
    related: tuple[KeyPath, ...] = field(default=(), compare=False)
    severity: str = "error"

    @property
    def key(self) -> str:
        return dotted(self.path)

    @property
    def fields(self) -> tuple[KeyPath, ...]:
        """Every field the problem involves, in the order its message names them."""
        return self.related + (self.path,)

    def __str__(self) -> str:
        where = f"{self.file}:{self.line}" if self.file and self.line else (self.file or "")
        return ": ".join(p for p in (where, self.key, self.message) if p)


class ValidationError(ValueError):
    """One or more problems. ``str()`` is one line per problem unless a kind of error keeps its
    established wording (``text``)."""

    def __init__(self, problems: Problem | list[Problem], text: str | None = None):
        self.problems = [problems] if isinstance(problems, Problem) else list(problems)
        super().__init__(text if text is not None else "\n".join(str(p) for p in self.problems))

    @property
    def problem(self) -> Problem:
        return self.problems[0]


def did_you_mean(name: Any, options: Iterable[str]) -> str | None:
    """The option closest to ``name`` (a typo), or None."""
    if not isinstance(name, str):
        return None
    m = difflib.get_close_matches(name, list(options), n=1, cutoff=0.6)
    return m[0] if m else None


def suggestion_text(suggestion: str | None) -> str:
    return f"; did you mean {suggestion!r}?" if suggestion else ""


def key_text(k: Any) -> str:
    """An unknown key as a message shows it: a name as written, anything else not at all (the
    file may not be what it should be — its text is never echoed)."""
    if isinstance(k, str) and 0 < len(k) <= 40 and k.replace("_", "").replace("-", "").isalnum():
        return k
    return "(a key that is not a name, not shown)"


def show_yaml(v: Any) -> str:
    """A value as it would be written in YAML."""
    if v is None:
        return "null"
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, float):
        return f"{v:g}"
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(show_yaml(x) for x in v) + "]"
    return str(v)


def show_value(v: Any) -> str:
    """A bad value in an error message (strings quoted so that '' and ' 9600' are visible)."""
    if isinstance(v, str):
        return repr(v)
    if isinstance(v, dict):
        return "a mapping"
    return show_yaml(v)
