"""docs/architecture.md quotes the contracts from their source: every quoted block is still the
source's text, and every contract of gateway/core/ports.py is quoted."""
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
    with open(os.path.join(ROOT, "gateway", "core", "ports.py"), encoding="utf-8") as f:
        tree = ast.parse(f.read())
    contracts = {n.name for n in tree.body if isinstance(n, ast.ClassDef)}
    quoted = "\n".join(t for p, t in _quotes() if p == "gateway/core/ports.py")
    assert contracts and all(f"class {c}(" in quoted or f"class {c}:" in quoted for c in contracts), (
        sorted(c for c in contracts if f"class {c}" not in quoted))


def _tree_rows():
    """The rows of the doc's "tree at a glance" table: (first cell, whole row)."""
    with open(DOC, encoding="utf-8") as f:
        text = f.read()
    section = text.split("## The tree at a glance", 1)[1].split("\n## ", 1)[0]
    return [(r.split("|")[1], r) for r in section.splitlines() if r.startswith("| `")]


def test_the_tree_names_every_package_and_module():
    """Every package of gateway/ and drivers/ has its row, naming each of its modules; every
    module directly in gateway/ is named in a row's first cell."""
    rows = _tree_rows()
    missing = []
    for top in ("gateway", "drivers"):
        for d, _, files in os.walk(os.path.join(ROOT, top)):
            if "__init__.py" not in files or "__pycache__" in d:
                continue
            rel = os.path.relpath(d, ROOT).replace(os.sep, "/")
            mods = sorted(f for f in files if f.endswith(".py") and f != "__init__.py")
            if rel == "gateway":
                for m in mods:
                    if not any(f"`gateway/{m}`" in cell for cell, _ in rows):
                        missing.append(f"gateway/{m}")
                continue
            row = next((r for cell, r in rows if f"`{rel}/`" in cell), None)
            if row is None:
                missing.append(f"{rel}/")
                continue
            missing += [f"{rel}/{m}" for m in mods if f"`{m}`" not in row]
    assert missing == [], f"docs/architecture.md's tree leaves out {missing}"


def test_the_tree_names_nothing_that_is_not_there():
    """The other way round (issue 35): every folder and module a row of the tree names exists —
    a row's first cell is a package (``gateway/outputs/mqtt/``) or a module directly in gateway/,
    and every bare module name in a package's row (`` `pump.py` ``) is a module of that package."""
    extra = []
    for cell, row in _tree_rows():
        where = cell.strip().strip("`")
        if where.endswith("/"):
            if not os.path.isfile(os.path.join(ROOT, where, "__init__.py")):
                extra.append(where)
                continue
            have = set(os.listdir(os.path.join(ROOT, where)))
            named = set(re.findall(r"`(\w+\.py)`", row.split("|", 2)[2]))
            extra += [f"{where}{m}" for m in sorted(named - have)]
        elif not os.path.isfile(os.path.join(ROOT, where)):
            extra.append(where)
    assert extra == [], f"docs/architecture.md's tree names what is not in the code: {extra}"
