"""Statistics across tests (METHOD.md §7, the paper's Tables 4–6): pure functions, numbers in,
numbers out.

Rounding follows the paper's tables: mean and SD to 0.1 s, CV to 0.01 %, change vs δ0 to 0.01 %
(:data:`DIGITS`). Values are rounded half-up on their shortest decimal form, as a person rounds
the printed number.
"""
from __future__ import annotations

import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from decimal import ROUND_HALF_UP, Decimal

#: decimals the paper prints
DIGITS = {"t_life": 1, "sd": 1, "cv": 2, "change": 2, "mu_ss": 4, "rho": 3}

#: the sign a wear indicator's rank correlation with t_life should have: shorter life ↔ more wear
EXPECTED_SIGN = -1


def round_half_up(x: float | None, nd: int) -> float | None:
    """``x`` rounded to ``nd`` decimals, half away from zero, on its shortest repr
    (``round_half_up(0.125, 2) == 0.13``, where ``round`` gives 0.12)."""
    if x is None or not math.isfinite(x):
        return None
    q = Decimal(1).scaleb(-nd)
    return float(Decimal(repr(float(x))).quantize(q, rounding=ROUND_HALF_UP))


def mean(xs: Sequence[float]) -> float | None:
    return math.fsum(xs) / len(xs) if xs else None


def sample_sd(xs: Sequence[float]) -> float | None:
    """Sample standard deviation (n − 1); None for fewer than two values."""
    n = len(xs)
    if n < 2:
        return None
    m = math.fsum(xs) / n
    return math.sqrt(math.fsum((x - m) ** 2 for x in xs) / (n - 1))


def cv_pct(sd: float | None, m: float | None) -> float | None:
    if sd is None or m is None or m == 0:
        return None
    return sd / m * 100.0


@dataclass(frozen=True)
class GroupStats:
    n: int
    mean: float | None
    sd: float | None
    cv: float | None

    def rounded(self) -> GroupStats:
        return GroupStats(self.n, round_half_up(self.mean, DIGITS["t_life"]),
                          round_half_up(self.sd, DIGITS["sd"]), round_half_up(self.cv, DIGITS["cv"]))


def group_stats(xs: Sequence[float]) -> GroupStats:
    m = mean(xs)
    sd = sample_sd(xs)
    return GroupStats(len(xs), m, sd, cv_pct(sd, m))


def grade_sort_key(grade: str):
    """Grades in a natural order: I, II, III, … (Roman numerals), then numbers, then text."""
    roman = {"I": 1, "V": 5, "X": 10, "L": 50, "C": 100}
    g = str(grade).strip()
    if g and all(c in roman for c in g.upper()):
        total, prev = 0, 0
        for c in reversed(g.upper()):
            v = roman[c]
            total += -v if v < prev else v
            prev = max(prev, v)
        return (0, total, g)
    try:
        return (1, float(g), g)
    except ValueError:
        return (2, 0, g)


def ranking(means: Mapping[str, float | None]) -> str:
    """Grade ranking by mean t_life, longest first: ``"I > II"``; equal means (after the paper's
    rounding) are joined with ``=``. Grades without a mean are left out; "" if none."""
    rounded = ((g, round_half_up(m, DIGITS["t_life"])) for g, m in means.items())
    items = [(g, m) for g, m in rounded if m is not None]
    items.sort(key=lambda gm: (-gm[1], grade_sort_key(gm[0])))
    out = ""
    for i, (g, m) in enumerate(items):
        if i:
            out += " = " if m == items[i - 1][1] else " > "
        out += str(g)
    return out


def change_pct(x: float | None, ref: float | None) -> float | None:
    """Relative change of ``x`` against ``ref`` in %."""
    if x is None or ref is None or ref == 0:
        return None
    return (x - ref) / ref * 100.0


# ---------------------------------------------------------------------------------------------
# Rank correlation
# ---------------------------------------------------------------------------------------------

def average_ranks(xs: Sequence[float]) -> list[float]:
    """Ranks 1..n; tied values share the mean of the ranks they span."""
    order = sorted(range(len(xs)), key=lambda i: xs[i])
    ranks = [0.0] * len(xs)
    i = 0
    while i < len(order):
        j = i
        while j + 1 < len(order) and xs[order[j + 1]] == xs[order[i]]:
            j += 1
        r = (i + j) / 2.0 + 1.0
        for k in range(i, j + 1):
            ranks[order[k]] = r
        i = j + 1
    return ranks


def pearson(x: Sequence[float], y: Sequence[float]) -> float | None:
    n = len(x)
    if n != len(y) or n < 2:
        return None
    mx, my = math.fsum(x) / n, math.fsum(y) / n
    sxy = math.fsum((a - mx) * (b - my) for a, b in zip(x, y))
    sxx = math.fsum((a - mx) ** 2 for a in x)
    syy = math.fsum((b - my) ** 2 for b in y)
    if sxx == 0 or syy == 0:
        return None
    return sxy / math.sqrt(sxx * syy)


def spearman(x: Sequence[float], y: Sequence[float]) -> float | None:
    """Spearman's ρ: Pearson's r of the average ranks (exact with ties). None when fewer than
    three pairs or when either side is constant."""
    if len(x) != len(y):
        raise ValueError("spearman: x and y differ in length")
    if len(x) < 3:
        return None
    return pearson(average_ranks(x), average_ranks(y))


@dataclass(frozen=True)
class Correlation:
    indicator: str
    n: int
    rho: float | None

    @property
    def agrees(self) -> bool | None:
        """Whether ρ has the sign the method expects (negative), None when undefined."""
        if self.rho is None:
            return None
        return self.rho * EXPECTED_SIGN > 0


def wear_correlations(t_life: Sequence[float], wear: Mapping[str, Sequence[float | None]]
                      ) -> list[Correlation]:
    """ρ(t_life, indicator) for each wear indicator over the pairs where both are known."""
    out = []
    for name, vals in wear.items():
        pairs = [(t, v) for t, v in zip(t_life, vals) if t is not None and v is not None]
        out.append(Correlation(name, len(pairs),
                               spearman([p[0] for p in pairs], [p[1] for p in pairs])
                               if len(pairs) >= 3 else None))
    return out


def finite(xs: Iterable[float | None]) -> list[float]:
    return [x for x in xs if x is not None and math.isfinite(x)]
