"""Generate docs/method.md from the one definition of the parameters: `python -m gateway.core.method.docs`."""
from __future__ import annotations

from .params import PARAMS, RESULT_KEYS
from .prior import EARLY_FRACTION, MIN_HISTORY, MIN_LIVES_EARLY, MIN_REL_SD
from .rules import LOST, LOST_NAME, REASONS, UNSAFE


def render() -> str:
    out = [
        "# The method's parameters and results",
        "",
        "Generated from `gateway/core/method/params.py` and `gateway/core/method/rules.py` "
        "(`python -m gateway.core.method.docs > docs/method.md`); do not edit by hand.",
        "The normative description of the signal chain is METHOD.md (shipped to the developers); "
        "these names are the keys of a station's `method:` section, of a log's sidecar and of "
        "`hookwatch analyze --set`.",
        "",
        "Every value is a finite number (NaN and ±Infinity are refused wherever a parameter is read: "
        "a station file, a log's sidecar, `--set`), and at most the *largest* value below: "
        "plausible physical bounds, so that no derived figure (the §5b end quantiles, a window's "
        "length in slots) can overflow. The lower bounds and the rules between parameters are "
        "checked too; an error names the key, the value and what is allowed.",
        "",
        "| name | default | unit | largest | meaning |",
        "|---|---|---|---|---|",
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
        out.append(f"| `{p.name}` | {d} | {p.unit} | {p.bound() or '—'} | {p.doc} |")
    out += ["", "## Reason bits of a slot", "", "| bit | name | makes the slot unsafe (§3) |",
            "|---|---|---|"]
    for bit, name in REASONS:
        out.append(f"| 0x{bit:02X} | {name} | {'yes' if bit & UNSAFE else 'no'} |")
    out += [f"| 0x{LOST:02X} | {LOST_NAME} | no: transparent (gateway extension, below) |", "",
            f"`{LOST_NAME}` is a gateway extension, not part of METHOD.md: a slot whose reading the "
            "recorder could not take (a disk outage longer than its memory reserve; the slots are "
            "`lost_spans` in the sidecar). It is not valid (no μ; it counts against N_eff and as a "
            "non-exceeding slot for §5) and it neither counts toward nor breaks a run of unsafe "
            "slots (§3): a full disk says nothing about the yarn or the meter and does not stop a "
            "life test. Its reading is not the JUMP reference. The live station and `hookwatch "
            "analyze` (which reads `lost_spans`) feed exactly the same slots as LOST, so the "
            f"offline result equals the live one. `reasons` has a `{LOST_NAME}` count only when a "
            "test has LOST slots (a log without `lost_spans` gives METHOD.md's keys).",
            ]
    out += ["", "## Result keys", "", ", ".join(f"`{k}`" for k in RESULT_KEYS), "",
            "`stop_reasons` lists the unsafe reasons (MISSING, SATURATED, LOW_TENSION) seen in the "
            "run of unsafe slots that triggered the protection stop, or `STOPPED` for a test "
            "ended on purpose (METHOD.md §3): then `stop_slot` = `end_slot`, the first slot that "
            "is no longer part of the test (`n_slots` = `end_slot`), whereas after a protection "
            "stop `stop_slot` is the last analysed slot (`n_slots` = `stop_slot` + 1). A test "
            "that found t_life before either stays `failure` with `interrupted` true.", "",
            "## Wear headroom, headroom runs, projection (METHOD.md §5a)", "",
            "Informative: they never change `status`, `k_life` or `t_life`.", "",
            "- After the baseline, every complete window of `w_ss` (that ends before a protection "
            "stop, `end_slot` or the end of the log) *has a value* when at least "
            "`valid_ratio_min` of its slots are valid: the median μ̃ of its valid μ.",
            "- `headroom` h = (μ_th − μ̃) / (μ_th − μ_ss) of the last window with a value: 1 at "
            "the baseline, 0 at the threshold, negative above it (not clipped).",
            "- A window *completes a headroom run* when it and the `n_warn` − 1 windows before it "
            "all have a value and h < `h_warn` (a window without a value breaks the run): one of "
            "the reasons of the early warning (§5b).",
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
            "## Remaining life and the early warning (METHOD.md §5b)", "",
            "Informative: they never change `status`, `k_life` or `t_life`.", "",
            "- The *prior* (`prior_mean` m, `prior_sd` s) is the life of earlier hooks of the same "
            "grade at the same T_set, taken as normal. The gateway writes it into the sidecar when "
            "a test starts (`prior_source`: `config` — the station's `forecast:` entry or its "
            "`method:` section —, `history` with the counts `prior_n` of wear-out failures, "
            "`prior_n_censored` of right-censored lives and `prior_n_early` of early failures, or "
            "nothing; METHOD.md §7a). In a log's "
            "sidecar a prior with `prior_sd` ≤ 0 (or only one of the two) means no prior; in a "
            "station's configuration or `--set` it is an error.",
            "- The *history prior* (§7a v3), when the station's configuration has none for the "
            f"grade and T_set (±0.001 N) and the history holds at least {MIN_HISTORY} wear-out "
            "failures: its lives are the failures (observed, x = t_life) and the right-censored "
            "lives — a test that found its baseline (`k_b`) and then ended on purpose (`aborted`, "
            "`stop_reasons` = [`STOPPED`]: the hook was replaced or the test stopped) or at t_end "
            "(`no_failure`) lived at least c = `n_slots`·Ts; no baseline or a protection stop do "
            f"not count. *Early failures*: when the history holds at least {MIN_LIVES_EARLY} lives "
            "(observed and censored together), M is the median of all of them (each x and each c; "
            "an even count takes the mean of the two middle values), and an observed life "
            f"x < {EARLY_FRACTION:g}·M is an early failure — a defect (a burr, a crack, a bad "
            "batch), not wear: a competing risk, so for the wear-out prior the hook had not worn "
            "out by x and it counts as a right-censored life at x. The other failures are the "
            f"wear-out failures (n_w of them); with fewer than {MIN_LIVES_EARLY} lives there are "
            "no early failures. (m̂, ŝ) maximise "
            "ℓ(m, s) = Σ_x [−ln s − ½((x − m)/s)²] + Σ_c ln(1 − Φ((c − m)/s)) over the wear-out "
            "failures x and the censored lives with the early failures c; the prior is "
            f"m = m̂, s = max(ŝ·√(n_w/(n_w − 1)), {MIN_REL_SD:g}·m̂). Without censored lives and "
            "early failures that is exactly the failures' mean and sample SD; all wear-out "
            f"failures equal: m = their value, s = {MIN_REL_SD:g}·m; without an early failure it "
            "is the rule before v3 exactly. "
            "The fit (gateway/core/method/prior.py, pure Python) is Newton's method with a line search "
            "on ℓ in α = m/s, β = 1/s, where ℓ is strictly concave (one maximum, found from any "
            "start), to 1e-13 relative; ln(1 − Φ) far in the tail from Laplace's continued "
            "fraction (no log 0). It agrees with scipy.optimize to 1e-6 relative (tests). A fit "
            "that does not converge within 200 steps gives no prior from the history (the "
            "forecast then has no prior part), never a wrong one. Why the censored lives count: "
            "once hooks are replaced when they are due, the hooks that reach their end are mostly "
            "the early ones; a prior from failures alone would learn a shorter and shorter life. "
            "Why the early failures are censored: counted as wear-out failures, a few defects "
            "widen every hook's prior (simulated: 2–5 % defects gave an SD of 6,200–9,400 s "
            "against a true 489 s, a forecast band hours wide); censored, they barely move it. "
            "The history is the site's: every completed test this gateway recorded and every one "
            "the gateways of its `station.site` shared over MQTT (docs/mqtt.md, the site's life "
            "history; the lives are shared as they are, each gateway classes them), each test once "
            "(by test id); the sidecar says where the prior came from (`prior_stations`, "
            "`prior_station_ids`, `prior_from`) and from how many lives (`prior_n`, `prior_n_censored`, "
            "`prior_n_early`); the state, the console's station page and its due list say the "
            "same counts, and the station's life log (`hooks.jsonl`, `hookwatch hooks`) names a "
            "replaced hook's early failure as such.",
            "- *Forecast times*: the end t_j = (j + 1)·`w_ss` of every complete window j = 0, 1, … "
            "(also before the baseline) up to a protection stop, `end_slot` or the end of the log; "
            "once t_life is found only the windows that end before the detection slot "
            "k_det = k_life + N_τ − 1 (from there the end-of-life alarm speaks).",
            "- With a prior, at t = t_j, S = 1 − Φ((t − m)/s): the end quantiles "
            "e_p = max(m + s·Φ⁻¹(1 − S·(1 − p)), t) for p = 0.1, 0.5, 0.9 and the chance "
            "P = (Φ((t + `lead` − m)/s) − Φ((t − m)/s)) / S that the end comes within the lead; "
            "when S < 1e-12 e_p = t and P = 1 (Φ(x) = ½·erfc(−x/√2); Φ⁻¹: AS241, as Python's "
            "statistics.NormalDist; both agree with scipy.special.ndtr, ndtri to ≈ 1e-16).",
            "- A window is *due* when P ≥ `p_due` (reason `prior`), it completes a headroom run "
            "(`headroom`), or its t_cross − t_j ≤ `lead` (`trend`).",
            "- `warn_slot`, `warn_reasons`: the last slot of the first due window and the sorted "
            "reasons that hold there: at most once per test, never at or after k_det.",
            "- `end_p10`, `end_p50`, `end_p90`, `p_end`: e_p and P of the last forecast time "
            "(null without a prior or without a forecast time).", "",
            "What they do not promise: the prior is the spread of earlier hooks, not a measurement "
            "of this one; a hook that wears unlike its predecessors is caught by the headroom and "
            "trend reasons, and t_life remains the end-of-life decision.", "",
            "The start-sequence parameters (`zero_check`, `zero_tol`, `settle_band`, "
            "`settle_time`, `start_timeout`; METHOD.md §3a) act before slot 0 and never change "
            "the analysis of a recorded log.", ""]
    return "\n".join(out)


if __name__ == "__main__":
    print(render(), end="")
