"""YAML with positions: every key of a configuration file remembers its file and line, so a
validation error can say ``config/stations/loom-02.yaml:14: meter.baud: …``.

Plain PyYAML (safe loader) parses; this module only walks the composed node tree. Differences
from ``yaml.safe_load`` that matter for configuration files:

- keys are kept as written (``on:`` is the key ``"on"``, not ``True``);
- a key given twice in one mapping is an error (PyYAML would keep the last silently);
- ``1e-3`` is a float (YAML 1.1 needs ``1.0e-3``; a plain ``1e-3`` would be a string).
"""
from __future__ import annotations

import re
from dataclasses import dataclass
from typing import Any

import yaml

Path = tuple  # a key path: ("meter", "baud") or ("modbus_tcp", "writes", "allowed_clients", 0)


@dataclass(frozen=True)
class Pos:
    file: str
    line: int  # 1-based

    def __str__(self) -> str:
        return f"{self.file}:{self.line}"


class YamlError(ValueError):
    """A file that is not well-formed YAML (or not a mapping at the top)."""

    def __init__(self, file: str, line: int | None, message: str):
        self.file, self.line, self.msg = file, line, message
        super().__init__(f"{file}:{line}: {message}" if line else f"{file}: {message}")


class _Loader(yaml.SafeLoader):
    pass


_Loader.add_implicit_resolver(
    "tag:yaml.org,2002:float",
    re.compile(r"^[-+]?(?:[0-9][0-9_]*)(?:\.[0-9_]*)?[eE][-+]?[0-9]+$"),
    list("-+0123456789"),
)


@dataclass
class Doc:
    """A parsed file: the plain value tree and the position of every key path."""
    file: str
    data: dict
    pos: dict  # Path -> Pos (of the key; for list items, of the item)


def load(file: str, text: str | None = None) -> Doc:
    """Parse ``file`` (or ``text`` attributed to ``file``). An empty file is an empty mapping."""
    if text is None:
        with open(file, encoding="utf-8") as f:
            text = f.read()
    loader = _Loader(text)
    try:
        node = loader.get_single_node()
        pos: dict = {}
        data = {} if node is None else _value(loader, node, (), pos, file)
    except yaml.MarkedYAMLError as e:
        mark = e.problem_mark or e.context_mark
        what = " ".join(x for x in (e.context, e.problem) if x)
        if e.context_mark and mark and e.context_mark.line != mark.line:
            what += f" (opened at line {e.context_mark.line + 1})"
        raise YamlError(file, mark.line + 1 if mark else None, f"not valid YAML: {what}") from None
    except yaml.YAMLError as e:
        raise YamlError(file, None, f"not valid YAML: {e}") from None
    finally:
        loader.dispose()
    if not isinstance(data, dict):
        raise YamlError(file, node.start_mark.line + 1,
                        f"the file must be a mapping of sections (key: value), not a {_kind(data)}")
    return Doc(file, data, pos)


def _kind(v: Any) -> str:
    return {list: "list", str: "string", int: "number", float: "number", bool: "boolean"}.get(type(v), type(v).__name__)


def _value(loader: _Loader, node: yaml.Node, path: Path, pos: dict, file: str) -> Any:
    if isinstance(node, yaml.MappingNode):
        loader.flatten_mapping(node)  # `<<: *anchor` merge keys
        out: dict = {}
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
