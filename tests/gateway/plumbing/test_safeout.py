"""The one strict JSON encoder, CSV writer and Markdown escaping (gateway/plumbing/safeout.py) against many
seeded random hostile values: what every door relies on holds for all of them, not only for the
examples of the door tests (issue 27, items 4 and 5)."""
from __future__ import annotations

import csv
import io
import math
import random
import re

import numpy as np

from gateway.plumbing.safeout import csv_text, dumps, loads_strict, md_text

ALPHABET = list("=+-@;,\t\r\n \"'ab1.e|<>[]()`\\#*_") + ["\u00a0", "é", "\u2028"]
FORMULA = ("=", "+", "-", "@")
_NUMBER = re.compile(r"[+-]?(?:\d+(?:\.\d*)?|\.\d+)(?:[eE][+-]?\d+)?")


def _word(rng: random.Random) -> str:
    return "".join(rng.choice(ALPHABET) for _ in range(rng.randint(0, 12)))


def _starts_formula(piece: str) -> bool:
    """Whether a spreadsheet could read the piece as a formula: after blanks and quotes it starts
    with = + - @ (a leading ' makes it text; a plain number is a number)."""
    c = piece.lstrip(" \t\"\u00a0")
    return c.startswith(FORMULA) and not _NUMBER.fullmatch(c.rstrip(' "'))


def test_no_csv_piece_starts_a_formula_whatever_the_separator():
    rng = random.Random(27)
    rows = [[_word(rng) for _ in range(rng.randint(1, 5))] for _ in range(3000)]
    text = csv_text(rows)
    # an RFC 4180 reader gets every row back with its cell count
    back = list(csv.reader(io.StringIO(text, newline="")))
    assert [len(r) for r in back] == [len(r) for r in rows]
    for r_in, r_out in zip(rows, back, strict=True):
        for a, b in zip(r_in, r_out, strict=True):
            # the text is kept; at most a "'" is added before a piece
            assert b.replace("'", "") == a.replace("'", "")
    # a reader that splits on any locale's separator or a line break, quotes or not
    pieces = re.split(r"[,;\t\r\n]", text)
    bad = [p for p in pieces if _starts_formula(p)]
    assert bad == []


def test_plain_numbers_stay_numbers():
    assert csv_text([[-0.1, "-0.1", 3, "+2", "1e5", None, math.inf, True]]) == \
        "-0.1,-0.1,3,+2,1e5,,,true\r\n"


def test_strict_json_of_hostile_nested_values():
    rng = random.Random(5)
    specials = [math.inf, -math.inf, math.nan, np.float64("inf"), np.float32("nan"), np.int64(7),
                1e308, -0.0, np.array([1.0, np.inf]), (1, math.nan), {3: math.nan}]

    def value(depth: int):
        k = rng.randint(0, 4 if depth < 3 else 2)
        if k == 0:
            return rng.choice(specials)
        if k == 1:
            return _word(rng)
        if k == 2:
            return rng.uniform(-1e300, 1e300)
        if k == 3:
            return [value(depth + 1) for _ in range(rng.randint(0, 4))]
        return {_word(rng): value(depth + 1) for _ in range(rng.randint(0, 4))}

    for _ in range(500):
        v = value(0)
        for text in (dumps(v), dumps(v, indent=1), dumps(v, ensure_ascii=False)):
            assert "NaN" not in text and "Infinity" not in text
            loads_strict(text)


def test_markdown_text_is_one_line_without_live_specials():
    rng = random.Random(9)
    for _ in range(3000):
        s = _word(rng)
        m = md_text(s)
        assert "\n" not in m and "\r" not in m and "\u2028" not in m
        # every special is preceded by an odd number of backslashes (escaped)
        for i, ch in enumerate(m):
            if ch in "`<>[]|":
                j = i
                while j > 0 and m[j - 1] == "\\":
                    j -= 1
                assert (i - j) % 2 == 1, (s, m)


def test_write_atomic_never_writes_through_a_link_and_makes_the_folder(tmp_path):
    """Issue 34: a planted link at the temporary name (or the name) is replaced, its target kept."""
    import os

    from gateway.plumbing.safeout import TMP_SUFFIX, write_atomic

    outside = tmp_path / "outside.txt"
    outside.write_text("precious")
    target = tmp_path / "new" / "folder" / "f.json"
    write_atomic(str(target), b"{}")                      # the folder is made
    assert target.read_bytes() == b"{}"
    os.symlink(outside, str(target) + TMP_SUFFIX)
    write_atomic(str(target), b'{"a":1}')
    assert outside.read_text() == "precious" and target.read_bytes() == b'{"a":1}'
    assert not os.path.lexists(str(target) + TMP_SUFFIX)
    target.unlink()
    os.symlink(outside, target)                           # the file itself a link: the link goes
    write_atomic(str(target), b"[]")
    assert outside.read_text() == "precious" and not target.is_symlink() and target.read_bytes() == b"[]"
