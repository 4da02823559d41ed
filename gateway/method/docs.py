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
        if p.required:
            d = "(required)"
        elif p.default is None:
            d = "(none)"
        elif p.kind == "bool":
            d = "true" if p.default else "false"
        else:
            d = f"{p.default:g}"
        out.append(f"| `{p.name}` | {d} | {p.unit} | {p.doc} |")
    out += ["", "## Reason bits of a slot", "", "| bit | name | makes the slot unsafe (§3) |",
            "|---|---|---|"]
    for bit, name in REASONS:
        out.append(f"| 0x{bit:02X} | {name} | {'yes' if bit & UNSAFE else 'no'} |")
    out += ["", "## Result keys", "", ", ".join(f"`{k}`" for k in RESULT_KEYS), "",
            "`stop_reasons` lists the unsafe reasons (MISSING, SATURATED, LOW_TENSION) seen in the "
            "run of unsafe slots that triggered the protection stop, or `STOPPED` for a test "
            "ended on purpose (METHOD.md §3): then `stop_slot` = `end_slot`, the first slot that "
            "is no longer part of the test (`n_slots` = `end_slot`), whereas after a protection "
            "stop `stop_slot` is the last analysed slot (`n_slots` = `stop_slot` + 1). A test "
            "that found t_life before either stays `failure` with `interrupted` true.", "",
            "## Wear headroom, early warning, projection (METHOD.md §5a)", "",
            "Informative: they never change `status`, `k_life` or `t_life`.", "",
            "- After the baseline, every complete window of `w_ss` (that ends before a protection "
            "stop, `end_slot` or the end of the log) *has a value* when at least "
            "`valid_ratio_min` of its slots are valid: the median μ̃ of its valid μ.",
            "- `headroom` h = (μ_th − μ̃) / (μ_th − μ_ss) of the last window with a value: 1 at "
            "the baseline, 0 at the threshold, negative above it (not clipped).",
            "- `warn_slot`: the last slot of the first run of `n_warn` consecutive windows with a "
            "value and h < `h_warn` (a window without a value breaks the run); once per test, "
            "also when t_life came first.",
            "- `t_cross`: where the Theil–Sen slope s of the last up to `trend_windows` window "
            "values (at least 10) would take μ̃ to μ_th, in s from the test start: the end of "
            "the last window with a value + (μ_th − μ̃) / s; none when s ≤ 0, h ≤ 0 or fewer "
            "than 10 windows.",
            "",
            "What they do not promise: the projection extends the recent, roughly linear trend; "
            "the accelerated wear stage that ends a hook usually comes sooner than `t_cross`, so "
            "it is an upper estimate for planning, not a guaranteed life. The headroom is a "
            "one-window median and moves with the load; the early warning is the signal to plan "
            "a change, t_life remains the end-of-life decision.", "",
            "The start-sequence parameters (`zero_check`, `zero_tol`, `settle_band`, "
            "`settle_time`, `start_timeout`; METHOD.md §3a) act before slot 0 and never change "
            "the analysis of a recorded log.", ""]
    return "\n".join(out)


if __name__ == "__main__":
    print(render(), end="")
