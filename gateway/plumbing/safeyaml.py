"""Bounded, safe YAML reading: the one reader of every YAML file the gateway reads.

Station and fleet files, meter register maps, simulator scenarios and log sidecars all go
through :func:`read` (or :func:`gateway.config.yamlpos.load`, which adds the positions of keys).
A file is refused, with one line that says where, which limit and what is allowed, when it is:

- larger than :attr:`Limits.max_bytes` (checked before it is read: a 50 MB file costs nothing);
- not UTF-8, or holds a NUL byte or another control character YAML does not allow;
- nested deeper than :attr:`Limits.max_depth` lists/mappings (``[`` × 50,000 is refused at the
  65th ``[``, by the scanner, before the parser or the composer recurse);
- an alias bomb: more than :attr:`Limits.max_aliases` aliases, or more than
  :attr:`Limits.max_nodes` values once the aliases are expanded. The expanded size is counted
  on the composed node graph (each distinct node once, memoised), never by building the expansion,
  so a 600-byte "billion laughs" is refused in microseconds with a few kilobytes; a recursive
  alias (``&a [*a]``) is refused too;
- holding an integer longer than :attr:`Limits.max_int_digits` characters (Python refuses to
  convert more than 4,300 digits with a traceback; no setting needs more than 64 bits).

Only the YAML safe schema is read (no ``!!python`` tags). Differences from ``yaml.safe_load``
that matter for configuration files:

- keys are kept as written (``on:`` is the key ``"on"``, not ``True``);
- a key given twice in one mapping is an error (PyYAML would keep the last silently);
- ``1e-3`` is a float (YAML 1.1 needs ``1.0e-3``; a plain ``1e-3`` would be a string).

This module imports nothing of the project: drivers (meter maps, scenarios) and the gateway use
it alike without an import cycle.
"""
from __future__ import annotations

import os
import re
from dataclasses import dataclass
from typing import Any

import yaml

KeyPath = tuple[Any, ...]  # a key path: ("meter", "baud") or ("modbus_tcp", "writes", "allowed_clients", 0)


@dataclass(frozen=True)
class Limits:
    """Hard limits of one kind of file (see the module docstring)."""
    max_bytes: int = 1 << 20
    max_depth: int = 64
    max_aliases: int = 1_000
    max_nodes: int = 100_000
    max_int_digits: int = 32


#: station, fleet, meter map and scenario files: written by people, a few kilobytes
CONFIG = Limits()
#: log sidecars (log.meta.yaml): written by the recorder, hand-edited at most; a test's metadata
#: with its events summary stays far below this
SIDECAR = Limits(max_bytes=4 << 20, max_nodes=500_000)


@dataclass(frozen=True)
class Pos:
    file: str
    line: int  # 1-based

    def __str__(self) -> str:
        return f"{self.file}:{self.line}"


class YamlError(ValueError):
    """A file that cannot be read as YAML: not well-formed, not a mapping at the top, or beyond a
    limit. ``file``, ``line`` (None when unknown) and ``msg`` are the parts of the one-line message;
    ``column`` is known for syntax errors, whose ``problem`` is what the parser said."""

    def __init__(self, file: str, line: int | None, message: str, column: int | None = None,
                 problem: str | None = None):
        self.file, self.line, self.msg, self.column, self.problem = file, line, message, column, problem
        super().__init__(f"{file}:{line}: {message}" if line else f"{file}: {message}")

    def where(self) -> str:
        """`` (line 3, column 7)``, `` (line 3)`` or ``""``."""
        if self.line and self.column:
            return f" (line {self.line}, column {self.column})"
        return f" (line {self.line})" if self.line else ""

    def detail(self) -> str:
        """The message for a caller that names the file itself in its own style:
        ``not valid YAML (line 3, column 7): …`` or ``(line 1): the file is …; allowed: …``."""
        if self.problem is not None:
            return f"not valid YAML{self.where()}: {self.problem}"
        w = self.where()
        return f"{w[1:]}: {self.msg}" if w else self.msg


class YamlLimitError(YamlError):
    """A file refused by one of the :class:`Limits`; ``limit`` names the limit."""

    def __init__(self, file: str, line: int | None, message: str, limit: str):
        self.limit = limit
        super().__init__(file, line, message)


def _size(n: int) -> str:
    if n >= 1 << 20 and n % (1 << 20) == 0:
        return f"{n >> 20} MiB"
    if n >= 1 << 10 and n % (1 << 10) == 0:
        return f"{n >> 10} KiB"
    return f"{n} bytes"


# characters YAML 1.1 allows in a stream (tab, line breaks, printable Unicode)
_BAD_CHAR = re.compile("[^\x09\x0a\x0d\x20-\x7e\x85\xa0-\ud7ff\ue000-\ufffd\U00010000-\U0010ffff]")


def _line_col(text: str | bytes, index: int) -> tuple[int, int]:
    nl = "\n" if isinstance(text, str) else b"\n"
    line = text.count(nl, 0, index) + 1  # type: ignore[arg-type]
    start = text.rfind(nl, 0, index) + 1  # type: ignore[arg-type]
    return line, index - start + 1


def read_text(file: str, limits: Limits = CONFIG) -> str:
    """The text of ``file``: size checked before reading, strict UTF-8, no control characters.
    OSError (missing, a folder, no permission) passes through; everything else is YamlError."""
    st = os.stat(file)
    if st.st_size > limits.max_bytes:
        raise YamlLimitError(file, None, f"the file is {st.st_size} bytes; allowed: at most "
                             f"{_size(limits.max_bytes)}", "max_bytes")
    with open(file, "rb") as f:
        raw = f.read(limits.max_bytes + 1)    # a device or a growing file: read no more than this
    if len(raw) > limits.max_bytes:
        raise YamlLimitError(file, None, f"the file is larger than {_size(limits.max_bytes)}; "
                             f"allowed: at most {_size(limits.max_bytes)}", "max_bytes")
    return decode(file, raw)


def decode(file: str, raw: bytes) -> str:
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as e:
        line, col = _line_col(raw, e.start)
        raise YamlError(file, line, f"not UTF-8 text: byte 0x{raw[e.start]:02x} at column {col}; "
                        "allowed: UTF-8 text (save the file as UTF-8)") from None
    return check_chars(file, text)


def check_chars(file: str, text: str) -> str:
    if text.startswith("\ufeff"):
        text = text[1:]
    m = _BAD_CHAR.search(text)
    if m:
        line, col = _line_col(text, m.start())
        c = m.group()
        what = "a NUL byte (\\0)" if c == "\0" else f"the control character U+{ord(c):04X}"
        raise YamlError(file, line, f"{what} at column {col}; allowed: text without control "
                        "characters (tab and line breaks only)")
    return text


# ---------------------------------------------------------------------------------------------
# the loader: safe schema, limits enforced while scanning and composing


class _Loader(yaml.SafeLoader):
    limits: Limits = CONFIG
    file: str = "<yaml>"

    def __init__(self, text: str, file: str, limits: Limits):
        super().__init__(text)
        self.file, self.limits = file, limits
        self._depth = 0
        self._aliases = 0

    def _limit(self, mark: Any, message: str, limit: str) -> YamlLimitError:
        return YamlLimitError(self.file, mark.line + 1 if mark is not None else None, message, limit)

    # flow collections ([ and {) are counted by the scanner itself: PyYAML's scanner keeps a
    # possible simple key per flow level, so 50,000 unclosed '[' would cost O(n²) before the
    # composer is ever asked for a node
    def fetch_flow_collection_start(self, TokenClass):  # type: ignore[no-untyped-def]
        if self.flow_level >= self.limits.max_depth:
            raise self._too_deep(self.get_mark())
        super().fetch_flow_collection_start(TokenClass)

    def _too_deep(self, mark: Any) -> YamlLimitError:
        n = self.limits.max_depth
        return self._limit(mark, f"lists/mappings nested deeper than {n} levels; allowed: at "
                           f"most {n} levels", "max_depth")

    def _next_mark(self) -> Any:
        return self.peek_event().start_mark  # type: ignore[no-untyped-call]

    def compose_node(self, parent, index):  # type: ignore[no-untyped-def]
        if self.check_event(yaml.AliasEvent):
            self._aliases += 1
            if self._aliases > self.limits.max_aliases:
                n = self.limits.max_aliases
                raise self._limit(self._next_mark(), f"more than {n} aliases (*name); "
                                  f"allowed: at most {n}", "max_aliases")
            return super().compose_node(parent, index)
        self._depth += 1
        try:
            if self._depth > self.limits.max_depth:
                raise self._too_deep(self._next_mark())
            return super().compose_node(parent, index)
        finally:
            self._depth -= 1


_Loader.add_implicit_resolver(
    "tag:yaml.org,2002:float",
    re.compile(r"^[-+]?(?:[0-9][0-9_]*)(?:\.[0-9_]*)?[eE][-+]?[0-9]+$"),
    list("-+0123456789"),
)


def _construct_int(loader: _Loader, node: yaml.ScalarNode) -> int:
    n = loader.limits.max_int_digits
    if len(node.value) > n:
        raise loader._limit(node.start_mark, f"an integer of {len(node.value)} characters; "
                            f"allowed: at most {n}", "max_int_digits")
    return yaml.SafeLoader.construct_yaml_int(loader, node)


_Loader.add_constructor("tag:yaml.org,2002:int", _construct_int)


def _expanded_size(loader: _Loader, root: yaml.Node) -> None:
    """Refuse a node graph whose expansion (aliases copied out) exceeds the limits. Each distinct
    node is visited once: its expanded size is memoised; a node reached through itself is a
    recursive alias. The path length is bounded by ``max_depth``, so is the recursion here."""
    lim = loader.limits
    memo: dict[int, int] = {}
    active: set[int] = set()

    def size(node: yaml.Node, depth: int) -> int:
        if depth > lim.max_depth:
            raise loader._too_deep(node.start_mark)
        if not isinstance(node, (yaml.SequenceNode, yaml.MappingNode)):
            return 1
        key = id(node)
        if key in memo:
            return memo[key]
        if key in active:
            raise loader._limit(node.start_mark, "an alias refers to the list/mapping that holds "
                                "it (a recursive alias); allowed: aliases to finished nodes only",
                                "recursive_alias")
        active.add(key)
        total = 1
        children = (node.value if isinstance(node, yaml.SequenceNode)
                    else [c for kv in node.value for c in kv])
        for child in children:
            total += size(child, depth + 1)
            if total > lim.max_nodes:
                raise loader._limit(child.start_mark, f"more than {lim.max_nodes} values once "
                                    "the aliases are expanded (an alias bomb?); allowed: at most "
                                    f"{lim.max_nodes}", "max_nodes")
        active.discard(key)
        memo[key] = total
        return total

    size(root, 1)


@dataclass
class Doc:
    """A parsed file: the plain value tree and the position of every key path."""
    file: str
    data: Any
    pos: dict[KeyPath, Pos]  # of the key; for list items, of the item
    line: int = 1  # where the top-level value starts


def read(file: str, text: str | None = None, limits: Limits = CONFIG) -> Doc:
    """Parse ``file`` (or ``text`` attributed to ``file``) within ``limits``. The data may be any
    YAML value (None for an empty file). OSError passes through; any other problem is YamlError."""
    if text is None:
        text = read_text(file, limits)
    else:
        if len(text.encode("utf-8", "surrogatepass")) > limits.max_bytes:
            raise YamlLimitError(file, None, f"the text is larger than {_size(limits.max_bytes)}; "
                                 f"allowed: at most {_size(limits.max_bytes)}", "max_bytes")
        text = check_chars(file, text)
    loader = _Loader(text, file, limits)
    node = None
    try:
        node = loader.get_single_node()
        pos: dict[KeyPath, Pos] = {}
        if node is None:
            data = None
        else:
            _expanded_size(loader, node)
            data = _value(loader, node, (), pos, file)
    except YamlError:
        raise
    except yaml.MarkedYAMLError as e:
        mark = e.problem_mark or e.context_mark
        what = " ".join(x for x in (e.context, e.problem) if x)
        if e.context_mark and mark and e.context_mark.line != mark.line:
            what += f" (opened at line {e.context_mark.line + 1})"
        raise YamlError(file, mark.line + 1 if mark else None, f"not valid YAML: {what}",
                        mark.column + 1 if mark else None, what) from None
    except yaml.YAMLError as e:
        raise YamlError(file, None, f"not valid YAML: {_first_line(e)}",
                        problem=_first_line(e)) from None
    except RecursionError:                  # belt and braces: the limits above come first
        raise YamlLimitError(file, None, "nested too deeply; allowed: at most "
                             f"{limits.max_depth} levels", "max_depth") from None
    finally:
        loader.dispose()
    return Doc(file, data, pos, node.start_mark.line + 1 if node is not None else 1)


def _first_line(e: BaseException) -> str:
    s = str(e).strip().splitlines()
    return s[0] if s else type(e).__name__


def load(file: str, text: str | None = None, limits: Limits = CONFIG) -> Doc:
    """Like :func:`read`, for a file that must be a mapping of sections (empty: an empty mapping)."""
    doc = read(file, text, limits)
    if doc.data is None:
        doc.data = {}
    if not isinstance(doc.data, dict):
        raise YamlError(file, doc.line, "the file must be a mapping of sections (key: value), "
                        f"not {kind(doc.data)}")
    return doc


def kind(v: Any) -> str:
    """What a YAML value is, in words, without quoting it (a file's content is never echoed:
    ``meter.map: /etc/shadow`` must not print the first line of /etc/shadow)."""
    return {list: "a list", str: "a string", int: "a number", float: "a number",
            bool: "a boolean", dict: "a mapping"}.get(type(v), type(v).__name__)


def _value(loader: _Loader, node: yaml.Node, path: KeyPath, pos: dict[KeyPath, Pos], file: str) -> Any:
    if isinstance(node, yaml.MappingNode):
        loader.flatten_mapping(node)  # `<<: *anchor` merge keys (counted by _expanded_size)
        out: dict[Any, Any] = {}
        for knode, vnode in node.value:
            if not isinstance(knode, yaml.ScalarNode):
                raise YamlError(file, knode.start_mark.line + 1, "a key must be a plain name")
            key = knode.value
            kpath = path + (key,)
            if key in out:
                first = pos[kpath].line
                dotted = ".".join(str(p) for p in kpath)
                raise YamlError(file, knode.start_mark.line + 1,
                                f"{dotted}: key given twice (first at line {first})")
            pos[kpath] = Pos(file, knode.start_mark.line + 1)
            out[key] = _value(loader, vnode, kpath, pos, file)
        return out
    if isinstance(node, yaml.SequenceNode):
        items = []
        for i, item in enumerate(node.value):
            ipath = path + (i,)
            pos[ipath] = Pos(file, item.start_mark.line + 1)
            items.append(_value(loader, item, ipath, pos, file))
        return items
    return loader.construct_object(node, deep=True)
