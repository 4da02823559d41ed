"""What a JSON document the box wrote holds: every number in it (to check none is non-finite)."""
from __future__ import annotations

from collections.abc import Iterator
from typing import Any


def numbers(v: Any) -> Iterator[float]:
    """Every number in a parsed JSON document (booleans are not numbers here)."""
    if isinstance(v, bool) or v is None or isinstance(v, str):
        return
    if isinstance(v, (int, float)):
        yield v
    elif isinstance(v, dict):
        for x in v.values():
            yield from numbers(x)
    elif isinstance(v, list):
        for x in v:
            yield from numbers(x)
