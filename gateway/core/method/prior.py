"""METHOD.md §7a (v3): where a new test's life prior (§5b) comes from. Pure: entries in, a prior out.

In this order: (1) the station's configuration (a fixed ``prior_mean``/``prior_sd`` in its
``method:`` section wins; else its ``forecast:`` entry for the test's grade and T_set); (2) its
history: the completed tests of the same grade at the same T_set (±0.001 N), when at least 3 of
them are wear-out failures (below); (3) none.

A history holds observed lives (``failure``: x = t_life) and right-censored lives (a test that found
its baseline and then ended on purpose — ``aborted`` with ``stop_reasons`` = [``STOPPED``] — or at
t_end — ``no_failure`` —: it lived at least c = n_slots · Ts); other tests do not enter it.
**Early failures** (v3, :func:`split_early`): with at least :data:`MIN_LIVES_EARLY` lives (observed
and censored together), an observed life x < 0.75 · M, M the median of all of them (an even count:
the mean of the two middle ones), is an early failure (a defect, not wear): a competing risk, so
for the wear-out prior it is a right-censored life at x. The other observed lives are the wear-out
failures. The prior is the maximum-likelihood normal of the wear-out failures and the censored
lives with the early failures (:func:`censored_normal_mle`), the SD scaled by √(n_w / (n_w − 1))
(n_w wear-out failures) and at least 0.02 · mean; without censored lives and early failures exactly
the failures' mean and sample SD; all wear-out failures equal: their value and 0.02 · it. Without
an early failure v3 is v2 (:func:`wear_out_prior` of all the failures) exactly.

The maximisation is pure Python (the standard library's ``math.erfc``; no scipy on the product's
path): Newton's method with a backtracking line search on ℓ in Olsen's parameters α = m/s,
β = 1/s, where ℓ is strictly concave (each observed term is concave in (α, β), each censored term is
ln Φ of a linear form of them, and ln Φ is concave), so the one maximum is found from any start. The
log-survival ln Φ̄(a) of a censored life far beyond the mean is taken from Laplace's continued
fraction of Mills' ratio (never log(0)). Bounded: at most :data:`MAX_NEWTON` steps of at most
:data:`MAX_HALVINGS` halvings each. A fit that does not converge (not seen; a safety net) gives no
prior from the history, as fewer than 3 wear-out failures do: the test's forecast then has no prior
part (§5b), never a wrong one.
"""
from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from typing import Any

from .params import TEN_YEARS

#: two setpoints are the same within this much (N)
T_SET_TOL = 0.001
#: the history needs at least this many wear-out failures of the grade at the T_set
MIN_HISTORY = 3
#: early failures (v3) are classed in a history of at least this many lives (observed and censored)
MIN_LIVES_EARLY = 5
#: an observed life below this fraction of the median of all lives is an early failure (v3)
EARLY_FRACTION = 0.75
#: the SD from the history is at least this fraction of the mean
MIN_REL_SD = 0.02
#: Newton steps of the maximum-likelihood fit, at most (it converges in ≈ 5–15)
MAX_NEWTON = 200
#: halvings of one Newton step, at most
MAX_HALVINGS = 80
#: the fit has converged when a step changes α and β by less than this, relative
CONVERGED = 1e-13

SOURCE_CONFIG = "config"
SOURCE_HISTORY = "history"

#: the §7a kinds of a life
OBSERVED = "failure"
CENSORED = "censored"
#: … and of an observed life in its history (v3): a wear-out failure or an early one
WEAR_OUT = "wear_out"
EARLY = "early"
STOPPED = "STOPPED"


@dataclass(frozen=True)
class PriorEntry:
    """A configured prior: the life (mean and SD, s) of hooks of ``grade`` at ``t_set`` (N); ``n``
    (informative) is the count of wear-out failures it was computed from, ``n_censored`` the count
    of right-censored lives and ``n_early`` of early failures (§7a v3), when known."""
    grade: str
    t_set: float
    mean: float
    sd: float
    n: int | None = None
    n_censored: int | None = None
    n_early: int | None = None

    def as_config(self) -> dict[str, Any]:
        """The entry in the configuration's ``forecast.priors`` form."""
        out: dict[str, Any] = {"grade": self.grade, "t_set_n": self.t_set, "mean_s": self.mean,
                               "sd_s": self.sd}
        if self.n is not None:
            out["n"] = self.n
        if self.n_censored is not None:
            out["n_censored"] = self.n_censored
        if self.n_early is not None:
            out["n_early"] = self.n_early
        return out


@dataclass(frozen=True)
class PastTest:
    """One completed test as the history sees it (its result): the method's ``status``,
    ``t_life``, ``k_b``, ``stop_reasons`` and ``n_slots``, the test's ``ts`` (s), and who it was
    (``test_id``, ``station``: each test counts once)."""
    grade: str | None
    t_set: float | None
    status: str | None
    t_life: float | None
    k_b: int | None = None
    stop_reasons: tuple[str, ...] | None = None
    n_slots: int | None = None
    ts: float | None = None
    test_id: str | None = None
    station: str | None = None
    #: the planned duration (s) and why the test ended (the gateway's end_reason): what the site
    #: shares beside the life (issue 29), not used by the prior
    t_end: float | None = None
    end_reason: str | None = None

    def life(self) -> tuple[str, float] | None:
        """What the test gives the §7a history: (``failure``, x = t_life), (``censored``,
        c = n_slots · Ts) or None (no baseline, a protection stop, or figures that are not
        plausible: a life must be a finite number > 0 and at most 10 years, so that a forged
        ``ts`` or ``n_slots`` in a result cannot carry a huge censored life into the fit)."""
        if self.status == "failure":
            x = self.t_life
            return (OBSERVED, x) if _positive(x) and x is not None else None
        ended = (self.status == "no_failure"
                 or (self.status == "aborted" and self.stop_reasons == (STOPPED,)))
        if not ended or self.k_b is None or self.n_slots is None or self.ts is None:
            return None
        c = self.n_slots * self.ts
        return (CENSORED, c) if _positive(c) else None


def _positive(v: float | None) -> bool:
    return v is not None and math.isfinite(v) and 0 < v <= TEN_YEARS


@dataclass(frozen=True)
class Prior:
    """The prior of a new test: mean and SD (s), where it came from and from how many wear-out
    failures (``n``), right-censored lives (``n_censored``) and early failures (``n_early``, §7a
    v3) — None for a configured prior without counts."""
    mean: float | None
    sd: float | None
    source: str | None
    n: int | None = None
    n_censored: int | None = None
    n_early: int | None = None
    #: the source as the station's state publishes it (``method``, ``config``, ``history:N``;
    #: None: ``source``)
    label: str | None = field(default=None, compare=False)
    #: a history prior: the stations its tests came from, and in words where it came from
    #: (``this station: …``, ``the site: N tests from K stations``)
    n_stations: int | None = field(default=None, compare=False)
    origin: str | None = field(default=None, compare=False)
    #: a history prior: the stations its tests came from by name (bounded; the sidecar's
    #: ``prior_station_ids``)
    station_ids: tuple[str, ...] | None = field(default=None, compare=False)

    def sidecar(self) -> dict[str, Any]:
        """What the gateway writes into a new test's sidecar: ``method.prior_mean``/``prior_sd``
        go in its ``method:`` section, ``prior_source``/``prior_n``/``prior_n_censored``/
        ``prior_n_early`` beside it."""
        out: dict[str, Any] = {"prior_mean": self.mean, "prior_sd": self.sd, "prior_source": self.source,
                               "prior_n": self.n, "prior_n_censored": self.n_censored,
                               "prior_n_early": self.n_early}
        if self.origin is not None:
            out["prior_stations"], out["prior_from"] = self.n_stations, self.origin
            if self.station_ids is not None:
                out["prior_station_ids"] = list(self.station_ids)
        return out

    def lives_words(self) -> str | None:
        """How many lives the prior came from, in words (None without counts): ``4 wear-out
        failures, 3 censored, 1 early failure``."""
        if self.n is None:
            return None
        out = [f"{self.n} wear-out failure{'' if self.n == 1 else 's'}"]
        if self.n_censored is not None:
            out.append(f"{self.n_censored} censored")
        if self.n_early is not None:
            out.append(f"{self.n_early} early failure{'' if self.n_early == 1 else 's'}")
        return ", ".join(out)


NO_PRIOR = Prior(None, None, None, None)


def same_t_set(a: float, b: float) -> bool:
    return abs(a - b) <= T_SET_TOL + 1e-12


# ---------------------------------------------------------------------------------------------
# The censored normal's likelihood
# ---------------------------------------------------------------------------------------------

_SQRT1_2 = math.sqrt(0.5)
_LN_SQRT_2PI = 0.5 * math.log(2.0 * math.pi)
#: from here on, ln Φ̄ and the hazard come from the continued fraction (erfc would underflow
#: near 38)
_TAIL_FROM = 20.0
#: terms of the continued fraction (at a ≥ 20 it has converged to the last bit long before)
_TAIL_TERMS = 60


def log_sf(a: float) -> tuple[float, float, float]:
    """ln Φ̄(a) (Φ̄ = 1 − Φ, the standard normal's survival), the hazard φ(a)/Φ̄(a) and
    hazard − a (> 0), stable for every finite a: no log(0) far in the upper tail, no cancellation
    far in the lower one."""
    if a >= _TAIL_FROM:
        # Laplace: Φ̄(a)/φ(a) = 1/(a + 1/(a + 2/(a + 3/(a + …)))); g = the tail after "a +"
        g = a
        for k in range(_TAIL_TERMS, 1, -1):
            g = a + k / g
        rest = 1.0 / g                            # hazard − a
        hz = a + rest
        return -0.5 * a * a - _LN_SQRT_2PI - math.log(hz), hz, rest
    sf = 0.5 * math.erfc(a * _SQRT1_2)
    ln_sf = math.log1p(-0.5 * math.erfc(-a * _SQRT1_2)) if a < 0 else math.log(sf)
    hz = math.exp(-0.5 * a * a - _LN_SQRT_2PI) / sf
    return ln_sf, hz, hz - a


def log_likelihood(xs: Sequence[float], cs: Sequence[float], m: float, s: float) -> float:
    """§7a's ℓ(m, s) = Σ_x [−ln s − ½((x − m)/s)²] + Σ_c ln(1 − Φ((c − m)/s))."""
    return (math.fsum(-math.log(s) - 0.5 * ((x - m) / s) ** 2 for x in xs)
            + math.fsum(log_sf((c - m) / s)[0] for c in cs))


def _ell(ys: Sequence[float], ws: Sequence[float], al: float, be: float) -> float:
    """ℓ in Olsen's parameters (α = m/s, β = 1/s) on the standardised lives."""
    return (len(ys) * math.log(be) - 0.5 * math.fsum((be * y - al) ** 2 for y in ys)
            + math.fsum(log_sf(be * w - al)[0] for w in ws))


def censored_normal_mle(xs: Sequence[float], cs: Sequence[float]) -> tuple[float, float] | None:
    """(m̂, ŝ) maximising §7a's ℓ for the observed lives ``xs`` (at least two different) and the
    right-censored ones ``cs``; None when the fit does not converge within its bounds (or the
    figures are not finite). Newton with a line search on the strictly concave ℓ(α, β)."""
    n = len(xs)
    if n < 2:
        return None
    x0 = math.fsum(xs) / n
    d = math.sqrt(math.fsum((x - x0) ** 2 for x in xs) / (n - 1))
    if not (math.isfinite(d) and d > 0):
        return None
    ys = [(x - x0) / d for x in xs]
    ws = [(c - x0) / d for c in cs]
    sy = math.fsum(ys)
    syy = math.fsum(y * y for y in ys)
    al, be = 0.0, math.sqrt(n / (n - 1))          # the failures-only maximum
    f = _ell(ys, ws, al, be)
    for _ in range(MAX_NEWTON):
        ga = math.fsum(be * y - al for y in ys)
        gb = n / be - math.fsum((be * y - al) * y for y in ys)
        haa, hab, hbb = -float(n), sy, -n / (be * be) - syy
        for w in ws:
            _, hz, rest = log_sf(be * w - al)
            r = hz * rest                           # −(ln Φ̄)'' ∈ (0, 1)
            ga += hz
            gb -= hz * w
            haa -= r
            hab += r * w
            hbb -= r * w * w
        det = haa * hbb - hab * hab
        if not (math.isfinite(det) and det > 0):
            return None
        da = -(hbb * ga - hab * gb) / det
        db = -(haa * gb - hab * ga) / det
        step = 1.0
        for _h in range(MAX_HALVINGS):
            na, nb = al + step * da, be + step * db
            if nb > 0:
                nf = _ell(ys, ws, na, nb)
                if nf >= f - 1e-12 * abs(f):
                    break
            step *= 0.5
        else:
            return None
        done = abs(na - al) <= CONVERGED * max(1.0, abs(al)) and abs(nb - be) <= CONVERGED * be
        al, be, f = na, nb, nf
        if done:
            m, s = x0 + d * al / be, d / be
            return (m, s) if math.isfinite(m) and math.isfinite(s) and s > 0 else None
    return None


def wear_out_prior(xs: Sequence[float], cs: Sequence[float] = ()) -> tuple[float, float] | None:
    """The §7a prior (mean, SD) of the wear-out failures ``xs`` and the right-censored lives ``cs``
    as they are given (no early failure classed: §7a v2 when ``xs`` are all the failures): None
    with fewer than MIN_HISTORY failures (or a fit that does not converge); without censored lives
    the mean and sample SD (n − 1); all failures equal: that value and 0.02 · it; else the
    maximum-likelihood (m̂, ŝ), SD ŝ · √(n_w / (n_w − 1)), at least 0.02 · m̂."""
    n = len(xs)
    if n < MIN_HISTORY:
        return None
    if all(x == xs[0] for x in xs):
        return xs[0], MIN_REL_SD * xs[0]
    if not cs:
        m = math.fsum(xs) / n
        sd = math.sqrt(math.fsum((x - m) ** 2 for x in xs) / (n - 1))
        return m, max(sd, MIN_REL_SD * m)
    fit = censored_normal_mle(xs, cs)
    if fit is None or not fit[0] > 0:
        return None
    m, s = fit
    return m, max(s * math.sqrt(n / (n - 1)), MIN_REL_SD * m)


def median_life(xs: Sequence[float], cs: Sequence[float]) -> float:
    """M of §7a v3: the median of all lives, each x and each c (an even count: the mean of the two
    middle values). ``xs`` and ``cs`` must not both be empty."""
    v = sorted([*xs, *cs])
    k = len(v) // 2
    return v[k] if len(v) % 2 else (v[k - 1] + v[k]) / 2


def early_fence(xs: Sequence[float], cs: Sequence[float]) -> float | None:
    """The life below which an observed life of this history is an early failure (§7a v3):
    0.75 · M with at least MIN_LIVES_EARLY lives (observed and censored together), else None (no
    early failures)."""
    if len(xs) + len(cs) < MIN_LIVES_EARLY:
        return None
    return EARLY_FRACTION * median_life(xs, cs)


def split_early(xs: Sequence[float], cs: Sequence[float] = ()) -> tuple[list[float], list[float]]:
    """The observed lives ``xs`` of a history with the right-censored ``cs`` as (wear-out failures,
    early failures), each in the order given (§7a v3: x < 0.75 · M is early, with at least 5 lives)."""
    fence = early_fence(xs, cs)
    if fence is None:
        return list(xs), []
    return [x for x in xs if not x < fence], [x for x in xs if x < fence]


def history_prior(xs: Sequence[float], cs: Sequence[float] = ()) -> tuple[float, float] | None:
    """§7a's prior (mean, SD) from the observed lives ``xs`` and the right-censored ``cs``: the early
    failures (:func:`split_early`) count as right-censored lives at their x, and
    :func:`wear_out_prior` of the wear-out failures and them; None with fewer than MIN_HISTORY
    wear-out failures (or a fit that does not converge)."""
    pr = prior_of_lives(xs, cs)
    return None if pr.mean is None or pr.sd is None else (pr.mean, pr.sd)


# ---------------------------------------------------------------------------------------------
# A new test's prior
# ---------------------------------------------------------------------------------------------

def group_tests(history: Iterable[PastTest], grade: str, t_set: float) -> list[tuple[PastTest, str, float]]:
    """The tests of ``grade`` at ``t_set`` (±0.001 N) that give the history a life, with it (kind,
    value), each test once (a test id seen again is skipped; tests without an id all count)."""
    out: list[tuple[PastTest, str, float]] = []
    seen: set[str] = set()
    for t in history:
        if t.grade != grade or t.t_set is None or not same_t_set(t.t_set, t_set):
            continue
        if t.test_id is not None:
            if t.test_id in seen:
                continue
            seen.add(t.test_id)
        lf = t.life()
        if lf is not None:
            out.append((t, lf[0], lf[1]))
    return out


def group_lives(history: Iterable[PastTest], grade: str, t_set: float) -> tuple[list[float], list[float]]:
    """The observed and right-censored lives of ``grade`` at ``t_set`` (±0.001 N), each test once."""
    g = group_tests(history, grade, t_set)
    return [v for _, k, v in g if k == OBSERVED], [v for _, k, v in g if k == CENSORED]


def prior_of_lives(xs: Sequence[float], cs: Sequence[float]) -> Prior:
    """The §7a history prior of these observed and right-censored lives (NO_PRIOR when there is
    none), with its counts: ``n`` wear-out failures, ``n_censored`` censored lives, ``n_early``
    early failures."""
    wear, early = split_early(xs, cs)
    h = wear_out_prior(wear, [*cs, *early])
    if h is None:
        return NO_PRIOR
    return Prior(h[0], h[1], SOURCE_HISTORY, len(wear), len(cs), len(early))


def kind_in_history(test: PastTest, history: Iterable[PastTest]) -> str | None:
    """What ``test`` is in the §7a history of its grade and T_set (v3), ``history`` with it:
    ``early`` or ``wear_out`` (an observed life below the early fence or not), ``censored``, or
    None (it gives the history no life)."""
    lf = test.life()
    if lf is None or test.grade is None or test.t_set is None:
        return None
    if lf[0] == CENSORED:
        return CENSORED
    xs, cs = group_lives([test, *history], test.grade, test.t_set)   # the test itself counts once
    fence = early_fence(xs, cs)
    return EARLY if fence is not None and lf[1] < fence else WEAR_OUT


def resolve_prior(config_entries: Iterable[PriorEntry], history: Iterable[PastTest],
                  grade: str | None, t_set: float, *,
                  fixed: tuple[float | None, float | None] = (None, None)) -> Prior:
    """§7a: the prior of a new test of ``grade`` at ``t_set``. ``fixed``: the station's
    ``method.prior_mean``/``prior_sd`` (both or neither, validated by the configuration), which
    wins over the others. A test without a grade gets a prior only from ``fixed``."""
    fm, fs = fixed
    if fm is not None and fs is not None and fs > 0:
        return Prior(fm, fs, SOURCE_CONFIG, None)
    if grade is None:
        return NO_PRIOR
    for e in config_entries:
        if e.grade == grade and same_t_set(e.t_set, t_set) and e.sd > 0:
            return Prior(e.mean, e.sd, SOURCE_CONFIG, e.n, e.n_censored, e.n_early)
    return prior_of_lives(*group_lives(history, grade, t_set))


def priors_by_group(history: Iterable[PastTest]) -> list[PriorEntry]:
    """Every (grade, T_set) group with at least MIN_HISTORY wear-out failures, as configuration
    entries (the §7a history rule per group; T_set within ±0.001 N of the group's first test),
    sorted by grade then T_set; ``n`` wear-out failures, ``n_censored`` right-censored lives and
    ``n_early`` early failures."""
    groups: list[tuple[str, float, list[PastTest]]] = []
    for t in history:
        if t.grade is None or t.t_set is None or t.life() is None:
            continue
        for g, ts, members in groups:
            if g == t.grade and same_t_set(ts, t.t_set):
                members.append(t)
                break
        else:
            groups.append((t.grade, t.t_set, [t]))
    out = []
    for g, ts, members in sorted(groups, key=lambda x: (x[0], x[1])):
        pr = prior_of_lives(*group_lives(members, g, ts))
        if pr.mean is not None and pr.sd is not None:
            out.append(PriorEntry(g, ts, pr.mean, pr.sd, pr.n, pr.n_censored, pr.n_early))
    return out
