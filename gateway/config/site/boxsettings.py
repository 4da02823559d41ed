"""The box's own settings: ``/etc/hookwatch/box.yaml`` (``$HOOKWATCH_BOX_FILE``, ``--box-file``).

They are not in the site repository — a commit must not be able to widen what the box accepts::

    name: box-1                       # its folder boxes/<name>/ in the site repository
    state_dir: /var/lib/hookwatch     # versions, current, verified, journal (STATE/config/…)
    allowed_signers: /etc/hookwatch/allowed_signers   # ssh-keygen's ALLOWED SIGNERS format
    allow_unsigned: false             # true on a lab box only: unsigned commits are applied
    health_timeout_s: 60              # the health gate's bound after an apply

A missing file means every default (the name then comes from ``$HOOKWATCH_BOX``).
"""
from __future__ import annotations

import os
from dataclasses import dataclass

from ...plumbing.safeyaml import YamlError, load
from .repository import BOX_NAME_RE

__all__ = ["DEFAULT_FILE", "BoxSettings", "BoxSettingsError", "load_box"]

DEFAULT_FILE = "/etc/hookwatch/box.yaml"
KEYS = ("name", "state_dir", "allowed_signers", "allow_unsigned", "health_timeout_s")


class BoxSettingsError(ValueError):
    """The box file is broken (``FILE:LINE: message``)."""


@dataclass(frozen=True)
class BoxSettings:
    name: str | None = None
    state_dir: str = "/var/lib/hookwatch"
    allowed_signers: str = "/etc/hookwatch/allowed_signers"
    allow_unsigned: bool = False
    health_timeout_s: float = 60.0
    file: str | None = None


def load_box(path: str | None = None) -> BoxSettings:
    """The box's settings from ``path`` (None: ``$HOOKWATCH_BOX_FILE``, else the default file)."""
    path = path or os.environ.get("HOOKWATCH_BOX_FILE") or DEFAULT_FILE
    env_name = os.environ.get("HOOKWATCH_BOX") or None
    if not os.path.isfile(path):
        return BoxSettings(name=env_name)
    try:
        doc = load(path)
    except (YamlError, OSError, UnicodeDecodeError) as e:
        raise BoxSettingsError(str(e)) from None
    d = doc.data
    base = os.path.dirname(os.path.abspath(path))

    def bad(k: str, msg: str) -> BoxSettingsError:
        p = doc.pos.get((k,))
        return BoxSettingsError(f"{path}:{p.line if p else 1}: {k}: {msg}")
    for k in d:
        if k not in KEYS:
            raise bad(k, f"unknown key; the box file has: {', '.join(KEYS)}")
    name = d.get("name", env_name)
    if name is not None and (not isinstance(name, str) or not BOX_NAME_RE.match(name)):
        raise bad("name", "a box name: letters, digits, _ . - (at most 64)")
    out: dict[str, object] = {"name": name, "file": path}
    for k in ("state_dir", "allowed_signers"):
        if k in d:
            if not isinstance(d[k], str) or not d[k].strip():
                raise bad(k, "a path")
            out[k] = os.path.normpath(os.path.join(base, d[k]))
    if "allow_unsigned" in d:
        if not isinstance(d["allow_unsigned"], bool):
            raise bad("allow_unsigned", "true or false")
        out["allow_unsigned"] = d["allow_unsigned"]
    if "health_timeout_s" in d:
        v = d["health_timeout_s"]
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not 1 <= v <= 3600:
            raise bad("health_timeout_s", "1 … 3600 s")
        out["health_timeout_s"] = float(v)
    return BoxSettings(**out)  # type: ignore[arg-type]
