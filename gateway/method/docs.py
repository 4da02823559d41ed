"""Generate docs/method.md from the one definition of the parameters: `python -m gateway.method.docs`."""
from __future__ import annotations

from .params import PARAMS, RESULT_KEYS
from .rules import REASONS, UNSAFE


def render() -> str:
    out = [
        "# The method's parameters and results",
        "",
        "Generated from `gateway/method/params.py` and `gateway/method/rules.py` "
        "(`python -m gateway.method.docs > docs/method.md`); do not edit by hand.",
        "The normative description of the signal chain is METHOD.md (shipped to the developers); "
        "these names are the keys of a station's `method:` section, of a log's sidecar and of "
        "`hookwatch analyze --set`.",
        "",
        "| name | default | unit | meaning |",
        "|---|---|---|---|",
    ]
    for p in PARAMS:
        d = "(required)" if p.required else ("(none)" if p.default is None else f"{p.default:g}")
        out.append(f"| `{p.name}` | {d} | {p.unit} | {p.doc} |")
    out += ["", "## Reason bits of a slot", "", "| bit | name | makes the slot unsafe (§3) |",
            "|---|---|---|"]
    for bit, name in REASONS:
        out.append(f"| 0x{bit:02X} | {name} | {'yes' if bit & UNSAFE else 'no'} |")
    out += ["", "## Result keys", "", ", ".join(f"`{k}`" for k in RESULT_KEYS), "",
            "`stop_reasons` lists the unsafe reasons (MISSING, SATURATED, LOW_TENSION) seen in the "
            "run of unsafe slots that triggered the protection stop.", ""]
    return "\n".join(out)


if __name__ == "__main__":
    print(render(), end="")
