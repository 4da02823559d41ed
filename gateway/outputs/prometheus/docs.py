"""Renders the gauges of the station's state in docs/metrics.md from the catalog of published
values (gateway/core/catalog.py): ``python -m gateway.outputs.prometheus.docs docs/metrics.md``
rewrites the generated table between its two marker lines (the rest of the page is written by
hand); a test checks it is current."""
from __future__ import annotations

import sys

from ...core import catalog
from .exposition import PREFIX
from .figures import GAUGES, SLOT_GAUGES

BEGIN = "<!-- generated from gateway/core/catalog.py: python -m gateway.outputs.prometheus.docs docs/metrics.md -->"
END = "<!-- end of the generated table -->"


def _unit(v: catalog.Value | catalog.SlotValue) -> str:
    if v.base_type == "bool" or (v.prometheus is not None and v.prometheus.label):
        return "0/1"
    return v.unit or "1"


def table(values: tuple[catalog.Value | catalog.SlotValue, ...] = GAUGES + SLOT_GAUGES) -> list[str]:
    """The table of the catalog's gauges (the state's, then the latest slot's), one row each."""
    out = ["| metric | type | labels | unit | meaning |", "|---|---|---|---|---|"]
    for v in values:
        g = v.prometheus
        assert g is not None
        labels = "station" + (f", {g.label}" if g.label else "")
        out.append(f"| `{PREFIX}_{g.name}` | gauge | {labels} | {_unit(v)} | {g.doc or g.help} |")
    return out


def render(page: str) -> str:
    """``page`` (docs/metrics.md) with its generated table made current."""
    head, sep, rest = page.partition(BEGIN + "\n")
    _old, sep2, tail = rest.partition(END + "\n")
    if not sep or not sep2:
        raise ValueError(f"docs/metrics.md has no generated table between {BEGIN!r} and {END!r}")
    return head + BEGIN + "\n" + "\n".join(table()) + "\n" + END + "\n" + tail


def main(argv: list[str]) -> int:
    if len(argv) != 1:
        print("usage: python -m gateway.outputs.prometheus.docs docs/metrics.md", file=sys.stderr)
        return 2
    with open(argv[0], encoding="utf-8") as f:
        page = f.read()
    new = render(page)
    if new != page:
        with open(argv[0], "w", encoding="utf-8") as f:
            f.write(new)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
