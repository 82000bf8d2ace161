"""The search of a parameter the regression cannot estimate linearly: what a record
covers, the grid an effect asks for (:meth:`~canrls.estimation.effects.Effect.search_space`)
and the minimum of a cost over it. The diagnosis searches every candidate's on the
record, ``canrls fit`` a model's Stribeck speed on the whole record
(docs/diagnose.md, "Nonlinear parameters")."""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

__all__ = ["SEARCH_POINTS", "REFINE_STEPS", "RecordSpan", "SearchSpace", "log_grid",
           "record_span", "minimise_on_grid"]

#: Values tried by a search of a nonlinear parameter (:meth:`Effect.search_space`).
SEARCH_POINTS = 16


@dataclass(frozen=True)
class RecordSpan:
    """What a record covers, for the grids of :meth:`Effect.search_space`: the speeds
    moved at (``speed_low``, ``speed_mid``, ``speed_high``: the 2nd, 50th and 98th
    percentiles of the non-zero ``|speed|``) and the speed noise (standard deviation),
    in the speed unit."""

    speed_low: float
    speed_high: float
    speed_noise: float
    speed_unit: str
    #: the median of the non-zero ``|speed|``
    speed_mid: float = math.nan


@dataclass(frozen=True)
class SearchSpace:
    """A parameter the regression cannot estimate linearly and the values to try.

    ``key`` names it for :meth:`canrls.estimation.model.Model.with_search_value`
    (``stribeck_speed``, ``coulomb_band``, ``user:NAME:PARAM``), ``label`` for a
    person, ``grid`` the values (empty: the record covers nothing to search), ``value``
    the one the effect has now, ``kept`` True when the effect itself fixes it (a user
    term's ``search = { c = 0.05 }``)."""

    key: str
    label: str
    unit: str
    grid: tuple[float, ...]
    value: float
    kept: bool = False


def log_grid(lo: float, hi: float, n: int = SEARCH_POINTS) -> tuple[float, ...]:
    """``n`` values spaced evenly in log from ``lo`` to ``hi`` (both > 0); linear when
    the interval holds zero or negative values."""
    if not (math.isfinite(lo) and math.isfinite(hi)) or hi < lo:
        return ()
    if lo > 0 or hi < 0:
        s = 1.0 if lo > 0 else -1.0
        a, b = sorted((abs(lo), abs(hi)))
        return tuple(s * float(v) for v in np.geomspace(a, b, n)) if b > a else (lo,)
    return tuple(float(v) for v in np.linspace(lo, hi, n))


#: Golden-section steps between the best grid value's neighbours (in log).
REFINE_STEPS = 6


def record_span(speeds: npt.ArrayLike, noise: float, unit: str) -> RecordSpan:
    """The :class:`RecordSpan` of the speeds a search compares on (``speeds``: the
    rows' ``|speed|`` or speed) with the speed ``noise`` measured on the record."""
    w = np.abs(np.asarray(speeds, dtype=np.float64))
    w = w[np.isfinite(w) & (w > 0)]
    lo, mid, hi = (float(x) for x in np.percentile(w, [2, 50, 98])) if len(w) \
        else (0.0, 0.0, 0.0)
    return RecordSpan(lo, hi, float(noise), unit, mid)


def minimise_on_grid(f: Callable[[float], float],
                     grid: Sequence[float]) -> tuple[float, float]:
    """The value of ``grid`` where ``f`` is smallest, refined by golden section between
    its neighbours (in log when they keep one sign); ``(value, f there)``."""
    vals = [f(v) for v in grid]
    k = int(np.argmin(vals))
    best, f_best = float(grid[k]), float(vals[k])
    if len(grid) < 3 or not math.isfinite(f_best):
        return best, f_best
    a, b = float(grid[max(k - 1, 0)]), float(grid[min(k + 1, len(grid) - 1)])
    logs = a * b > 0
    s = math.copysign(1.0, a)

    def to(v: float) -> float:
        return math.log(abs(v)) if logs else v

    def back(x: float) -> float:
        return s * math.exp(x) if logs else x

    g = (math.sqrt(5.0) - 1.0) / 2.0
    lo, hi = sorted((to(a), to(b)))
    x1, x2 = hi - g * (hi - lo), lo + g * (hi - lo)
    f1, f2 = f(back(x1)), f(back(x2))
    for _ in range(REFINE_STEPS):
        if f1 <= f2:
            hi, x2, f2 = x2, x1, f1
            x1 = hi - g * (hi - lo)
            f1 = f(back(x1))
        else:
            lo, x1, f1 = x1, x2, f2
            x2 = lo + g * (hi - lo)
            f2 = f(back(x2))
    for x, fx in ((x1, f1), (x2, f2)):
        if fx < f_best:
            best, f_best = back(x), fx
    return best, f_best
