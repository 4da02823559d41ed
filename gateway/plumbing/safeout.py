"""What leaves the box as text: the one strict JSON encoder and the one spreadsheet-safe CSV writer.

JSON (every door: the console's API and event stream, MQTT payloads, the supervisor's frames,
``result.json`` and the other recorded JSON files, ``analyze --json``, ``hooks``):

- :func:`plain` turns a value into plain JSON values: numpy scalars and arrays into Python numbers
  and lists, enums into their value, tuples and sets into lists, dataclasses into objects, and
  **a number that is not finite (NaN, ±Infinity) into null** — JSON has no such numbers and a
  strict parser (a browser's ``JSON.parse``, most MES) refuses the whole document for one of them.
  Every number the box publishes is documented as "a number, or null when it has no value";
  a non-finite one has none.
- :func:`dumps` / :func:`dump` write :func:`plain` of the value with ``allow_nan=False``: should a
  non-finite number ever slip past :func:`plain`, the write fails loudly instead of emitting
  ``Infinity``.

CSV (the console's due list, ``regmap --format csv``, the report's tables): :func:`csv_cell` makes
a cell safe to open in any spreadsheet, whatever list separator its locale uses (``,`` in en,
``;`` in de/fr/it/es, TAB when pasted), and :func:`csv_text` writes the rows:

- every *piece* of a cell — the cell itself and each part that follows a ``,`` ``;`` TAB, CR or LF
  inside it — that starts, after any leading blanks and quotes, with ``=`` ``+`` ``-`` ``@`` (or
  a TAB / CR) gets a leading ``'`` — unless the whole cell is a plain decimal number (``-0.1`` is
  a number to every spreadsheet, not a formula). So even a reader that splits the line on ``;`` or
  TAB without honouring the quotes sees no cell that starts a formula (CSV injection, OWASP);
- a cell that holds a ``,`` ``;`` TAB, quote, CR or LF, or starts or ends with a blank, is quoted
  (RFC 4180, quotes doubled).

Files (:func:`write_atomic`): a file the box rewrites whole (the site's lives, …) is written
beside itself under ``<name>.tmp``, opened exclusively and without following a link
(``O_CREAT | O_EXCL | O_NOFOLLOW``: a planted link or file there is removed first, never written
through), synced, then renamed over the file (``rename`` replaces a link at the file's own name,
it never writes through it) and the folder synced: a reader sees the old file or the new one,
never a part, and nothing outside the folder is ever written. The folder is made when missing.

This module imports nothing of the project.
"""
from __future__ import annotations

import contextlib
import dataclasses
import enum
import json
import math
import os
import re
import urllib.parse
from collections.abc import Iterable, Sequence
from typing import IO, Any

import numpy as np


def plain(v: Any) -> Any:
    """Plain JSON values: non-finite numbers → null, numpy → Python, enums → value, tuples/sets →
    lists, dataclasses → objects, keys → strings; anything else → its ``str``."""
    if v is None or isinstance(v, (bool, str)):
        return v
    if isinstance(v, int):
        return int(v)
    if isinstance(v, float):
        return float(v) if math.isfinite(v) else None
    if isinstance(v, enum.Enum):
        return plain(v.value)
    if isinstance(v, dict):
        return {str(plain(k)) if not isinstance(k, str) else k: plain(x) for k, x in v.items()}
    if isinstance(v, (list, tuple, set, frozenset)):
        return [plain(x) for x in v]
    if dataclasses.is_dataclass(v) and not isinstance(v, type):
        return plain(dataclasses.asdict(v))
    if isinstance(v, (np.generic, np.ndarray)):
        return plain(v.tolist())
    return str(v)


def dumps(v: Any, *, indent: int | None = None, compact: bool = True, sort_keys: bool = False,
          ensure_ascii: bool = True) -> str:
    """Strict JSON text of ``plain(v)`` (never NaN/Infinity; ``compact``: no blanks after ``,``/``:``
    unless ``indent`` is given)."""
    sep = (",", ":") if compact and indent is None else None
    return json.dumps(plain(v), indent=indent, separators=sep, sort_keys=sort_keys,
                      ensure_ascii=ensure_ascii, allow_nan=False)


def dump(v: Any, f: IO[str], *, indent: int | None = None, sort_keys: bool = False) -> None:
    """:func:`dumps` into an open text file."""
    f.write(dumps(v, indent=indent, sort_keys=sort_keys))


#: the suffix of the temporary file :func:`write_atomic` writes beside the file
TMP_SUFFIX = ".tmp"


def write_atomic(path: str, data: bytes, *, mode: int = 0o644, make_dir: bool = True,
                 tmp_suffix: str = TMP_SUFFIX) -> None:
    """Replace ``path`` with ``data`` atomically (module docstring); raises :class:`OSError` (the
    file is then unchanged; the temporary file is removed). Writers in several processes give
    each its own ``tmp_suffix`` (e.g. with the pid)."""
    folder = os.path.dirname(path) or "."
    if make_dir:
        os.makedirs(folder, exist_ok=True)
    tmp = path + tmp_suffix
    try:
        os.unlink(tmp)                     # a leftover or a planted link: the link goes, not its target
    except FileNotFoundError:
        pass
    flags = os.O_WRONLY | os.O_CREAT | os.O_EXCL | getattr(os, "O_NOFOLLOW", 0) | getattr(os, "O_CLOEXEC", 0)
    fd = os.open(tmp, flags, mode)
    try:
        try:
            view = memoryview(data)
            while view:
                view = view[os.write(fd, view):]
            os.fsync(fd)
        finally:
            os.close(fd)
        os.replace(tmp, path)
    except BaseException:
        try:
            os.unlink(tmp)
        except OSError:
            pass
        raise
    with contextlib.suppress(OSError):      # the file is whole; the rename's durability is best effort
        fsync_dir(folder)


def fsync_dir(path: str) -> None:
    """Make the entries of the folder ``path`` durable (a rename, a new file); raises OSError."""
    fd = os.open(path, os.O_RDONLY | getattr(os, "O_DIRECTORY", 0))
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def loads_strict(text: str | bytes) -> Any:
    """JSON as a strict parser reads it: ``NaN``/``Infinity`` are an error (as in a browser)."""
    def refuse(name: str) -> Any:
        raise ValueError(f"non-standard JSON constant {name}")
    return json.loads(text, parse_constant=refuse)


# ----------------------------------------------------------------------------------------- CSV
#: characters that make a spreadsheet read a piece of a cell as a formula (OWASP CSV injection)
FORMULA_START = ("=", "+", "-", "@", "\t", "\r")
#: list separators of any locale, and line breaks: a piece of a cell starts after each of them
SEPARATORS = ",;\t\r\n"
_PIECE = re.compile(r"([,;\t\r\n])")
_LEAD = re.compile(r"[ \t\r\n\"'\u00a0]*")
_NUMBER = re.compile(r"[+-]?(?:\d+(?:\.\d*)?|\.\d+)(?:[eE][+-]?\d+)?")
_QUOTE_IF = re.compile(r"[,;\t\r\n\"]|^\s|\s$")


def _defuse_piece(p: str) -> str:
    if not p:
        return p
    lead = _LEAD.match(p)
    rest = p[lead.end():] if lead else p
    return "'" + p if p.startswith(FORMULA_START) or rest.startswith(FORMULA_START) else p


def defuse(t: str) -> str:
    """``t`` with every piece that a spreadsheet could start a formula with prefixed by ``'``."""
    if not t or _NUMBER.fullmatch(t):
        return t
    parts = _PIECE.split(t)
    # parts: piece, sep, piece, sep, …, piece; a piece is checked together with the separator
    # before it only for the cell's own start (a leading TAB/CR is itself a formula start)
    out = [_defuse_piece(parts[0])]
    for i in range(1, len(parts), 2):
        out.append(parts[i])
        out.append(_defuse_piece(parts[i + 1]))
    s = "".join(out)
    if t.startswith(("\t", "\r")) and not s.startswith("'"):
        s = "'" + s
    return s


def csv_text_of(v: Any) -> str:
    """A value as the text of one CSV cell (None → empty, bool → true/false, a list → its items
    separated by blanks, a non-finite number → empty), not yet defused."""
    if v is None:
        return ""
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, (list, tuple)):
        return " ".join(csv_text_of(x) for x in v)
    if isinstance(v, float):
        return repr(round(v, 6)) if math.isfinite(v) else ""
    return str(v)


def csv_cell(v: Any) -> str:
    """One CSV cell as text, defused (:func:`defuse`); quoting is :func:`csv_text`'s."""
    return defuse(csv_text_of(v))


def _quoted(cell: str) -> str:
    return '"' + cell.replace('"', '""') + '"' if _QUOTE_IF.search(cell) else cell


def csv_row(cells: Sequence[Any]) -> str:
    """One CSV line without the line end: each cell defused and quoted when it holds a separator
    of any locale."""
    line = ",".join(_quoted(csv_cell(c)) for c in cells)
    return '""' if line == "" and len(cells) == 1 else line     # one empty cell is not an empty line


def csv_text(rows: Iterable[Sequence[Any]], *, line_end: str = "\r\n") -> str:
    """The rows (the first usually the header) as CSV text, every cell defused and quoted."""
    return "".join(csv_row(r) + line_end for r in rows)


# ------------------------------------------------------------------------------------ Markdown
_MD_SPECIAL = re.compile(r"([\\`<>\[\]|])")
_LINE_BREAK = re.compile(r"[\r\n\u2028\u2029\x0b\x0c\x85]+")


def md_text(s: Any) -> str:
    """Text from outside (a sample ID, a folder name, a message that quotes a file) as one line of
    Markdown that reads as the text itself: line breaks become a blank (no new heading, list item
    or table row), and ``\\ ` < > [ ] |`` are backslash-escaped (no raw HTML, link, image, code
    span or table cell)."""
    return _MD_SPECIAL.sub(r"\\\1", _LINE_BREAK.sub(" ", str(s)))


def md_link_target(path: str) -> str:
    """A relative path as a Markdown link target: percent-encoded (a blank, ``)`` or ``<`` cannot
    end or leave the link)."""
    return urllib.parse.quote(path, safe="/._-~")
