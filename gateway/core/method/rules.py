"""The rules of METHOD.md, each defined once and used by both the streaming and the batch form.

Pure: numbers in, numbers out. Functions here accept numpy scalars or arrays alike, so that the
per-slot path and the vectorised path evaluate the very same floating-point expressions.
"""
from __future__ import annotations

import functools
import math

import numpy as np

# np.median loads numpy.ma when it first runs: loaded here, at start-up, not on a station's slot
# thread (tests/test_architecture.py: nothing imports while a life runs)
import numpy.ma  # noqa: F401
from numpy.typing import ArrayLike, NDArray

from .params import MethodParams

# ---- reason bits (METHOD.md §2) ----
MISSING = 0x01
SATURATED = 0x02
LOW_TENSION = 0x04
JUMP = 0x08
RATIO_LOW = 0x10
RATIO_HIGH = 0x20

REASONS: tuple[tuple[int, str], ...] = (
    (MISSING, "MISSING"),
    (SATURATED, "SATURATED"),
    (LOW_TENSION, "LOW_TENSION"),
    (JUMP, "JUMP"),
    (RATIO_LOW, "RATIO_LOW"),
    (RATIO_HIGH, "RATIO_HIGH"),
)
REASON_NAMES = tuple(n for _, n in REASONS)
#: reasons that make a slot unsafe for the protection stop (§3)
UNSAFE = MISSING | LOW_TENSION | SATURATED

#: gateway extension (not METHOD.md): the slot's reading could not be recorded (the recorder's
#: memory reserve was full during a disk outage, ``lost_spans`` in the sidecar). A LOST slot is
#: not valid (no μ; it counts against N_eff and as a non-exceeding slot for §5) and is
#: transparent to the protection stop (§3): it neither counts toward an unsafe run nor breaks
#: one — a full disk says nothing about the yarn or the meter and must not stop a life test. Its
#: reading does not update the JUMP reference (as MISSING). Not one of ``REASONS`` (the §2 reason
#: bits, the register map, the METHOD vectors): counted in a result's ``reasons`` as ``LOST`` only
#: when a test has lost slots.
LOST = 0x40
LOST_NAME = "LOST"

MAD_SCALE = 1.4826


def reason_names(mask: int) -> list[str]:
    return [name for bit, name in REASONS if mask & bit] + ([LOST_NAME] if mask & LOST else [])


def slot_index(t: ArrayLike, ts: float) -> NDArray[np.int64]:
    """Slot of a reading at time t (s from test start): round(t / Ts), halves rounded up.
    Works on floats and arrays."""
    return np.floor(np.asarray(t, dtype=np.float64) / ts + 0.5).astype(np.int64)


def log_ratio_mu(r: ArrayLike, theta: float) -> NDArray[np.float64]:
    """μ = ln(R) / θ. Always evaluated through numpy's log so that the scalar and the
    vectorised paths give bit-identical values."""
    return np.log(r) / theta


def window_steady(mu_valid: np.ndarray, p: MethodParams) -> bool:
    """§4: is a complete window with these valid μ values steady?"""
    n = mu_valid.size
    if n < n_eff_required(p):
        return False
    med = np.median(mu_valid)
    sigma = MAD_SCALE * np.median(np.abs(mu_valid - med))
    if not sigma < p.sigma_max:
        return False
    g = mu_valid.max() - mu_valid.min()
    return bool(g <= p.g_max)


def n_eff_required(p: MethodParams) -> int:
    """Smallest whole number of valid slots with N_eff ≥ valid_ratio_min · N_ss
    (computed so that float noise in 0.9 · N_ss cannot move it)."""
    return int(math.ceil(p.valid_ratio_min * p.n_ss - 1e-9))


def baseline_value(mu_valid_all: np.ndarray) -> float:
    """μ_ss = median of all valid μ of the stable segment (even count: mean of the middle two)."""
    return float(np.median(mu_valid_all))


def threshold(mu_ss: float, p: MethodParams) -> float:
    return (1.0 + p.delta) * mu_ss


# ---- §5a: wear headroom, early warning, projection ----

def window_value(mu_valid: np.ndarray, p: MethodParams) -> float | None:
    """μ̃ of a complete post-baseline window: the median of its valid μ (even count: mean of the
    middle two), or None when N_eff < valid_ratio_min · N_ss (the window has no value)."""
    if mu_valid.size < n_eff_required(p):
        return None
    return float(np.median(mu_valid))


def headroom(value: float, mu_ss: float, mu_th: float) -> float:
    """h = (μ_th − μ̃) / (μ_th − μ_ss): 1 at the baseline, 0 at the threshold, not clipped."""
    return (mu_th - value) / (mu_th - mu_ss)


def window_mid_time(j: int, p: MethodParams) -> float:
    """t_j = (j + 0.5) · N_ss · Ts, the middle of window j (s from test start)."""
    return (j + 0.5) * p.n_ss * p.ts


@functools.lru_cache(maxsize=8)
def _pairs(n: int) -> tuple[np.ndarray, np.ndarray]:
    return np.triu_indices(n, 1)


def theil_sen_slope(values: np.ndarray, times: np.ndarray) -> float:
    """Median over all pairs a < b of (v_b − v_a) / (t_b − t_a) (even count: mean of the middle
    two)."""
    a, b = _pairs(values.size)
    return float(np.median((values[b] - values[a]) / (times[b] - times[a])))
