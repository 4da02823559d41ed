"""METHOD.md §7a: where a new test's life prior (§5b) comes from. Pure: entries in, a prior out.

In this order: (1) the station's configuration (a fixed ``prior_mean``/``prior_sd`` in its
``method:`` section wins; else its ``forecast:`` entry for the test's grade and T_set); (2) the
completed tests recorded with the same grade and the same T_set (±0.001 N) that ended in
``failure``, when there are at least 3: their mean t_life and sample SD (n − 1), the SD at least
0.02 · mean; (3) none.
"""
from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any

#: two setpoints are the same within this much (N)
T_SET_TOL = 0.001
#: the history needs at least this many failures of the grade at the T_set
MIN_HISTORY = 3
#: the SD from the history is at least this fraction of the mean
MIN_REL_SD = 0.02

SOURCE_CONFIG = "config"
SOURCE_HISTORY = "history"


@dataclass(frozen=True)
class PriorEntry:
    """A configured prior: the life (mean and SD, s) of hooks of ``grade`` at ``t_set`` (N); ``n``
    (informative) is the count of tests it was computed from, when known."""
    grade: str
    t_set: float
    mean: float
    sd: float
    n: int | None = None

    def as_config(self) -> dict[str, Any]:
        """The entry in the configuration's ``forecast.priors`` form."""
        out: dict[str, Any] = {"grade": self.grade, "t_set_n": self.t_set, "mean_s": self.mean,
                               "sd_s": self.sd}
        if self.n is not None:
            out["n"] = self.n
        return out


@dataclass(frozen=True)
class PastTest:
    """One completed test as the history sees it (its result file)."""
    grade: str | None
    t_set: float | None
    status: str | None
    t_life: float | None


@dataclass(frozen=True)
class Prior:
    """The prior of a new test: mean and SD (s), where it came from and from how many tests (None
    for a configured prior without a count)."""
    mean: float | None
    sd: float | None
    source: str | None
    n: int | None = None

    def sidecar(self) -> dict[str, Any]:
        """What the gateway writes into a new test's sidecar: ``method.prior_mean``/``prior_sd``
        go in its ``method:`` section, ``prior_source``/``prior_n`` beside it."""
        return {"prior_mean": self.mean, "prior_sd": self.sd, "prior_source": self.source,
                "prior_n": self.n}


NO_PRIOR = Prior(None, None, None, None)


def same_t_set(a: float, b: float) -> bool:
    return abs(a - b) <= T_SET_TOL + 1e-12


def _usable(t: PastTest, grade: str, t_set: float) -> bool:
    return (t.status == "failure" and t.grade == grade and t.t_set is not None
            and same_t_set(t.t_set, t_set) and t.t_life is not None and math.isfinite(t.t_life)
            and t.t_life > 0)


def history_prior(lives: list[float]) -> tuple[float, float] | None:
    """Mean and sample SD (n − 1) of at least MIN_HISTORY lives, the SD at least 0.02 · mean."""
    n = len(lives)
    if n < MIN_HISTORY:
        return None
    m = math.fsum(lives) / n
    sd = math.sqrt(math.fsum((x - m) ** 2 for x in lives) / (n - 1))
    return m, max(sd, MIN_REL_SD * m)


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
            return Prior(e.mean, e.sd, SOURCE_CONFIG, e.n)
    lives = [t.t_life for t in history if _usable(t, grade, t_set) and t.t_life is not None]
    h = history_prior(lives)
    if h is None:
        return NO_PRIOR
    return Prior(h[0], h[1], SOURCE_HISTORY, len(lives))


def priors_by_group(history: Iterable[PastTest]) -> list[PriorEntry]:
    """Every (grade, T_set) group with at least MIN_HISTORY failures, as configuration entries
    (the §7a history rule per group; T_set within ±0.001 N of the group's first test), sorted by
    grade then T_set."""
    groups: list[tuple[str, float, list[float]]] = []
    for t in history:
        grade, t_set, life = t.grade, t.t_set, t.t_life
        if grade is None or t_set is None or life is None or not _usable(t, grade, t_set):
            continue
        for g, ts, lives in groups:
            if g == grade and same_t_set(ts, t_set):
                lives.append(life)
                break
        else:
            groups.append((grade, t_set, [life]))
    out = []
    for g, ts, lives in sorted(groups, key=lambda x: (x[0], x[1])):
        h = history_prior(lives)
        if h is not None:
            out.append(PriorEntry(g, ts, h[0], h[1], len(lives)))
    return out
