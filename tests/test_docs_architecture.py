"""docs/architecture.md quotes the contracts from their source: every quoted block is still the
source's text, and every contract of gateway/ports.py is quoted."""
import ast
import os
import re

from conftest import ROOT

DOC = os.path.join(ROOT, "docs", "architecture.md")
QUOTE = re.compile(r"<!-- quoted from (\S+) -->\n```python\n(.*?)\n```", re.S)


def _quotes():
    with open(DOC, encoding="utf-8") as f:
        return QUOTE.findall(f.read())


def test_quoted_blocks_match_their_source():
    quotes = _quotes()
    assert len(quotes) >= 6
    for path, text in quotes:
        with open(os.path.join(ROOT, path), encoding="utf-8") as f:
            src = f.read()
        for part in text.split("\n\n\n"):        # several definitions per block, as in the source
            assert part in src, f"docs/architecture.md quotes {path} out of date:\n{part[:300]}"


def test_every_contract_is_quoted():
    with open(os.path.join(ROOT, "gateway", "ports.py"), encoding="utf-8") as f:
        tree = ast.parse(f.read())
    contracts = {n.name for n in tree.body if isinstance(n, ast.ClassDef)}
    quoted = "\n".join(t for p, t in _quotes() if p == "gateway/ports.py")
    assert contracts and all(f"class {c}(" in quoted or f"class {c}:" in quoted for c in contracts), (
        sorted(c for c in contracts if f"class {c}" not in quoted))
