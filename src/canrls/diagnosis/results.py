"""The diagnosis's result objects: plain frozen values, each with ``to_dict()``.

:class:`Analysis` is one model fitted and diagnosed (one :class:`EquationDiagnosis` per
equation); the values inside it say how well the model fits (:class:`Whiteness`), where
it fails (:class:`Binned`, :class:`Region`, :class:`OrderSpectrum`,
:class:`StructureItem`), how the data excite it (:class:`ExcitationSummary`) and which
effect is missing (:class:`Candidate`, :class:`Suggestion`). :func:`share_text` and
:func:`value_text` format numbers the same way in every sentence of the report.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt

from canrls.core.checks import finite_or_none
from canrls.core.spill import ColumnLike, PackedMask
from canrls.estimation.estimates import EquationFit, Estimates
from canrls.estimation.model import Model

__all__ = [
    "FIGURE_POINTS",
    "decimation",
    "Whiteness",
    "Binned",
    "Region",
    "OrderSpectrum",
    "Candidate",
    "SearchResult",
    "Step",
    "Suggestion",
    "StructureItem",
    "ExcitationSummary",
    "Traces",
    "EquationDiagnosis",
    "Analysis",
    "r2_text",
    "share_text",
    "value_text",
]

F64 = npt.NDArray[np.float64]
I64 = npt.NDArray[np.int64]
B = npt.NDArray[np.bool_]


def _floats(a: Iterable[float]) -> list[float | None]:
    """An array for JSON (:func:`~canrls.core.checks.finite_or_none` of each entry)."""
    return [finite_or_none(x) for x in np.asarray(a, dtype=float).ravel().tolist()]


def share_text(x: float) -> str:
    """A share as a percentage with two or three significant digits (no exponent)."""
    v = 100.0 * x
    if not math.isfinite(v):
        return "n/a"
    if abs(v) >= 10:
        return f"{v:.0f} %"
    if abs(v) >= 1:
        return f"{v:.1f} %"
    return f"{v:.2g} %"


def r2_text(r2: float, digits: int = 4) -> str:
    """R² with ``digits`` decimals, never rounded up to 1: "> 0.9999" where it would."""
    if not math.isfinite(r2):
        return "n/a"
    text = f"{r2:.{digits}f}"
    if r2 < 1.0 and float(text) >= 1.0:
        return f"> {1.0 - 10.0 ** -digits:.{digits}f}"
    return text


def value_text(x: float, unit: str = "", sign: bool = False) -> str:
    s = f"{x:+.2g}" if sign else f"{x:.3g}"
    return f"{s} {unit}".rstrip()


# =================================================================== result objects
@dataclass(frozen=True)
class Whiteness:
    r"""Residual whiteness and independence from the inputs.

    The filtered residual is correlated over the filter's impulse response even when the
    equation error is white, so the test runs on the residual taken every
    ``decimation`` samples: the lag after which the autocorrelation of the filter's
    impulse response stays below 0.02. The 99 % bound of a white sequence's
    autocorrelation is :math:`\pm z_{0.995}/\sqrt{N_D}`; ``q`` is the Ljung-Box
    statistic :math:`Q = N_D(N_D+2)\sum_k \hat\rho_k^2/(N_D-k)` over ``lags`` lags and
    ``p_value`` its :math:`\chi^2` tail (Wilson-Hilferty). ``white``: ``p_value >= 0.01``.
    ``cross`` holds the cross-correlation :math:`\hat\rho_{ru}(k)` of the residual with
    each input at lags ``-lags .. lags`` (``k > 0``: the input leads); the same bound
    applies when the residual is white, whatever the input's colour.
    """

    decimation: int
    lags: int
    samples: int
    autocorr: F64
    bound: float
    outside: int
    q: float
    p_value: float
    white: bool
    cross: Mapping[str, F64]
    cross_outside: Mapping[str, int]

    @property
    def independent(self) -> bool:
        """No input's cross-correlation leaves the bound at more than 1 % of the lags."""
        allowed = max(1, int(math.ceil(0.01 * (2 * self.lags + 1))))
        return all(v <= allowed for v in self.cross_outside.values())

    def describe(self) -> str:
        w = "white" if self.white else "NOT white"
        p = "< 1e-6" if self.p_value < 1e-6 else f"{self.p_value:.2g}"
        text = (f"{w}: {self.outside} of {self.lags} autocorrelation lags outside "
                f"±{self.bound:.3f} (99 %), Ljung-Box p {p} (every {self.decimation} "
                f"samples, {self.samples} values)")
        if self.cross_outside:
            text += "; cross-correlation lags outside: " + ", ".join(
                f"{k} {v}/{2 * self.lags + 1}" for k, v in self.cross_outside.items())
        return text

    def to_dict(self) -> dict[str, Any]:
        return {"white": self.white, "p_value": self.p_value, "q": self.q,
                "lags": self.lags, "decimation": self.decimation, "samples": self.samples,
                "bound": self.bound, "outside": self.outside,
                "autocorr": _floats(self.autocorr),
                "independent": self.independent,
                "cross": {k: _floats(v) for k, v in self.cross.items()},
                "cross_outside": dict(self.cross_outside)}


@dataclass(frozen=True)
class Binned:
    """Residual statistics in bins of one quantity.

    ``edges`` has one more entry than ``count``/``mean``/``rms``; bins with fewer than
    20 samples have ``nan`` mean and RMS. ``share`` is the part of the residual's
    variance (about its mean) that the bin means explain (the correlation ratio
    :math:`\\eta^2`).
    """

    quantity: str
    label: str
    unit: str
    edges: F64
    count: I64
    mean: F64
    rms: F64
    share: float

    @property
    def centers(self) -> F64:
        return 0.5 * (self.edges[1:] + self.edges[:-1])

    def to_dict(self) -> dict[str, Any]:
        return {"quantity": self.quantity, "unit": self.unit, "edges": _floats(self.edges),
                "count": [int(c) for c in self.count], "mean": _floats(self.mean),
                "rms": _floats(self.rms), "share": self.share}


@dataclass(frozen=True)
class Region:
    """A region where the residual's mean stands out, in words and numbers.

    ``share`` is the part of the residual's energy (sum of squares) the region's mean
    accounts for. Speed regions give the mean moving forward and backward.
    """

    quantity: str
    text: str
    lo: float
    hi: float
    share: float
    samples: int
    mean: float | None = None
    mean_forward: float | None = None
    mean_backward: float | None = None

    def to_dict(self) -> dict[str, Any]:
        d: dict[str, Any] = {"quantity": self.quantity, "text": self.text, "lo": self.lo,
                             "hi": self.hi, "share": self.share, "samples": self.samples}
        if self.quantity == "speed":
            d["mean_forward"] = self.mean_forward
            d["mean_backward"] = self.mean_backward
        else:
            d["mean"] = self.mean
        return d


@dataclass(frozen=True)
class OrderSpectrum:
    r"""The residual against rotation order (multiples of the rotation frequency).

    For every order ``q`` (steps of 1/4 up to the maximum order) the residual is fitted
    by least squares with :math:`F[\sin q\vartheta]` and :math:`F[\cos q\vartheta]`
    (the same filter as the equation, so periodic terms are seen at every speed):
    ``amplitude`` is the fitted amplitude in the output unit, ``explained`` the share of
    the residual variance the pair explains. ``per`` says what one period of order 1 is
    (a revolution, or the pitch of a linear axis). ``peaks`` lists the orders that stand
    out (local maxima explaining at least 1 % and 5 times the median), strongest first;
    ``shares`` what each explains beyond the ones before it, all of them fitted together.
    """

    orders: F64
    amplitude: F64
    explained: F64
    peaks: tuple[float, ...]
    unit: str
    per: str
    #: per peak, the share it explains beyond the peaks before it (fitted together:
    #: they add up to at most 1; leakage of a stronger order gets next to nothing)
    shares: tuple[float, ...] = ()

    def share(self, order: float) -> float:
        """The share of peak ``order`` beyond the stronger peaks (``explained`` alone
        when the sequential shares were not computed)."""
        if order in self.peaks and len(self.shares) == len(self.peaks):
            return self.shares[self.peaks.index(order)]
        return self.at(order)[1]

    def at(self, order: float) -> tuple[float, float]:
        """(amplitude, explained) at the order nearest ``order``."""
        j = int(np.argmin(np.abs(self.orders - order)))
        return float(self.amplitude[j]), float(self.explained[j])

    def to_dict(self) -> dict[str, Any]:
        return {"orders": _floats(self.orders), "amplitude": _floats(self.amplitude),
                "explained": _floats(self.explained), "peaks": list(self.peaks),
                "peak_shares": list(self.shares),
                "unit": self.unit, "per": self.per}


@dataclass(frozen=True)
class SearchResult:
    """A parameter of a candidate the regression cannot estimate linearly (a Stribeck
    speed, a Coulomb band, a user term's free parameter): the value found by the search
    over ``grid`` (``lo`` .. ``hi``, ``points`` values) and the ΔBIC of the candidate
    there, or the value set in the configuration, kept (``kept``)."""

    key: str
    label: str
    unit: str
    value: float
    kept: bool
    lo: float = math.nan
    hi: float = math.nan
    points: int = 0
    delta_bic: float = math.nan

    def text(self) -> str:
        """``Stribeck speed 0.81 rad/s (searched 0.02..40 rad/s, 16 values: ΔBIC -3581)``."""
        u = f" {self.unit}" if self.unit else ""
        if self.kept:
            return f"{self.label} {self.value:.4g}{u} (set in the configuration: kept)"
        return (f"{self.label} {self.value:.4g}{u} (searched {self.lo:.4g}..{self.hi:.4g}{u}, "
                f"{self.points} values: ΔBIC {self.delta_bic:.4g})")

    def to_dict(self) -> dict[str, Any]:
        return {"key": self.key, "label": self.label, "unit": self.unit,
                "value": self.value, "kept": self.kept,
                "searched": None if self.kept else [self.lo, self.hi, self.points],
                "delta_bic": None if self.kept else self.delta_bic}


@dataclass(frozen=True)
class Candidate:
    """One effect of the library that the model lacks, evaluated against the residual.

    ``explained`` (ERR), ``delta_bic`` and ``rms_after`` describe adding this effect
    alone to the current model (module docstring). ``parameters`` are the values its
    parameters would take (least squares, physical units). ``identifiable`` is False
    when its column is not excited or (nearly) collinear with the model's columns;
    ``reason`` then says why. ``independence`` is the fraction of its column energy
    outside the span of the model's columns (1/VIF), ``excitation`` the RMS of its
    filtered column over the compared rows, in the column's own unit (from the data: no
    declared range enters it). ``search`` holds its nonlinear parameters, searched or kept.
    """

    effect: str
    equation: str
    description: str
    signature: str
    explained: float
    delta_bic: float
    rms_after: float
    identifiable: bool
    suggested: bool
    reason: str
    evidence: tuple[str, ...]
    parameters: Mapping[str, tuple[float, str]]
    independence: float
    excitation: float
    search: tuple[SearchResult, ...] = ()

    def to_dict(self) -> dict[str, Any]:
        return {"effect": self.effect, "equation": self.equation,
                "explained": self.explained, "delta_bic": self.delta_bic,
                "rms_after": self.rms_after, "identifiable": self.identifiable,
                "suggested": self.suggested, "reason": self.reason or None,
                "description": self.description, "signature": self.signature,
                "evidence": list(self.evidence),
                "parameters": {k: {"value": v, "unit": u}
                               for k, (v, u) in self.parameters.items()},
                "independence": self.independence, "excitation": self.excitation,
                "search": [r.to_dict() for r in self.search]}


@dataclass(frozen=True)
class Step:
    """One step of the forward selection: the effect, and what it explains of what is left."""

    effect: str
    explained: float
    delta_bic: float
    rms_after: float

    def to_dict(self) -> dict[str, Any]:
        return {"effect": self.effect, "explained": self.explained,
                "delta_bic": self.delta_bic, "rms_after": self.rms_after}


@dataclass(frozen=True)
class Suggestion:
    """The effects to add, in the order the forward selection chose them (may be empty).

    ``rms_before`` is the least-squares residual RMS of the model as it is on the
    compared samples; ``rms_after`` the least-squares residual RMS with the suggestion
    added, on the samples the pipeline will use for that model (what the refit should
    reach).
    """

    steps: tuple[Step, ...]
    rms_before: float
    predicted: float | None = None

    @property
    def add(self) -> tuple[str, ...]:
        return tuple(s.effect for s in self.steps)

    @property
    def rms_after(self) -> float:
        if self.predicted is not None:
            return self.predicted
        return self.steps[-1].rms_after if self.steps else self.rms_before

    def __bool__(self) -> bool:
        return bool(self.steps)

    def to_dict(self) -> dict[str, Any]:
        return {"add": list(self.add), "rms_before": self.rms_before,
                "rms_after": self.rms_after, "steps": [s.to_dict() for s in self.steps]}


@dataclass(frozen=True)
class StructureItem:
    """Structure in the residual that the model (with the suggestion) leaves.

    ``kind`` is ``offset`` (a constant mean), ``speed``, ``position``, ``current``,
    ``acceleration`` (the bin means of that quantity explain ``share`` of the residual
    variance; ``time``: a drift) or ``periodic`` (an order of the rotation-order
    spectrum explains ``share``). The equation's own output signal is not tested: the
    residual carries its noise.
    """

    kind: str
    text: str
    share: float

    def to_dict(self) -> dict[str, Any]:
        return {"kind": self.kind, "text": self.text, "share": self.share}


@dataclass(frozen=True)
class ExcitationSummary:
    """What the data excite: directions of motion, speed spread, revolutions covered."""

    forward: float
    backward: float
    reversals: int
    speed_mean: float
    speed_std: float
    speed_max: float
    acceleration_rms: float
    acceleration_noise: float
    #: the share of the samples below twice :attr:`stribeck_speed` (None: no speed known)
    low_speed: float | None
    revolutions: float | None
    coverage: float | None
    speed_unit: str
    per: str
    #: the Stribeck speed ``low_speed`` refers to: the model's, or the one the search
    #: found (None: neither)
    stribeck_speed: float | None = None

    @property
    def accelerating(self) -> bool:
        """The acceleration stands above what the speed-sensor noise makes of it."""
        return self.acceleration_rms > 3.0 * self.acceleration_noise

    @property
    def one_direction(self) -> bool:
        return min(self.forward, self.backward) < 0.01

    @property
    def constant_speed(self) -> bool:
        return self.speed_std < 0.05 * max(abs(self.speed_mean), 1e-300)

    def facts(self) -> list[str]:
        """The excitation problems, in words (empty when there are none)."""
        u = self.speed_unit
        out = []
        if self.one_direction:
            way = "forward" if self.forward >= self.backward else "backward"
            out.append(f"the axis moves {way} only ({100 * self.forward:.0f} % of the "
                       f"samples forward, {100 * self.backward:.0f} % backward)")
        if self.constant_speed:
            out.append(f"the speed is nearly constant ({self.speed_mean:.3g} ± "
                       f"{self.speed_std:.2g} {u})")
        if self.revolutions is not None and self.revolutions < 1.0:
            out.append(f"the position covers only {self.revolutions:.2f} {self.per}s")
        if not self.accelerating:
            out.append(f"the acceleration is at the level of the speed-sensor noise (RMS "
                       f"{self.acceleration_rms:.3g} {u}/s against {self.acceleration_noise:.3g}"
                       f" {u}/s from the noise)")
        return out

    def to_dict(self) -> dict[str, Any]:
        return {"forward": self.forward, "backward": self.backward,
                "reversals": self.reversals, "speed_mean": self.speed_mean,
                "speed_std": self.speed_std, "speed_max": self.speed_max,
                "acceleration_rms": self.acceleration_rms,
                "acceleration_noise": self.acceleration_noise, "low_speed": self.low_speed,
                "stribeck_speed": self.stribeck_speed, "revolutions": self.revolutions,
                "coverage": self.coverage,
                "speed_unit": self.speed_unit, "per": self.per, "facts": self.facts()}


#: Most points a figure draws of the record (the traces keep no more).
FIGURE_POINTS = 20000


def decimation(n: int) -> int:
    """Every how many of ``n`` samples the figures draw one (at most
    :data:`FIGURE_POINTS`)."""
    return max(1, int(math.ceil(n / FIGURE_POINTS)))


@dataclass(frozen=True)
class Traces:
    """Arrays for the figures: the samples at the points the figures draw (``timeline``
    marks those of the timeline, every k-th sample, ``scatter`` those of the residual
    scatter plots, every k-th used sample; both ``None``: every sample, the figures
    decimate), ``used`` marks the points outside warm-ups; ``record_used`` is the
    mask of used samples over the whole record, packed (one bit a sample: slice it, or
    ``np.asarray``; ``None``: not kept).

    ``y``, ``yhat`` and ``residual`` are the filtered output, its model value with the
    final float estimate, and their difference, in the output unit. ``speed``,
    ``acceleration``, ``current`` and ``position`` are the measured signals through the
    same filter (aligned with the residual), ``angle`` the phase of periodic terms
    (``None`` without position). ``conv_t``, ``theta``, ``sigma`` and ``theta_fixed``
    sample the parameter convergence (physical units) at up to 400 instants.
    """

    t: ColumnLike
    used: B
    y: F64
    yhat: F64
    residual: F64
    speed: ColumnLike
    acceleration: ColumnLike
    current: ColumnLike
    position: ColumnLike | None
    angle: ColumnLike | None
    conv_t: F64
    theta: F64
    sigma: F64
    theta_fixed: F64
    names: tuple[str, ...]
    units: tuple[str, ...]
    timeline: B | None = None
    scatter: B | None = None
    record_used: PackedMask | None = None


@dataclass(frozen=True)
class EquationDiagnosis:
    """The diagnosis of one equation of the model (mechanical or electrical)."""

    equation: str
    output: str
    unit: str
    fit: EquationFit
    residual_rms_ls: float
    residual_rms_fixed: float
    whiteness: Whiteness | None
    bins: Mapping[str, Binned]
    regions: tuple[Region, ...]
    spectrum: OrderSpectrum | None
    candidates: tuple[Candidate, ...]
    not_applicable: tuple[tuple[str, str], ...]
    suggestion: Suggestion
    structure: tuple[StructureItem, ...]
    excitation: ExcitationSummary
    identifiable: bool
    identifiability: tuple[str, ...]
    verdict: str
    traces: Traces = field(repr=False, compare=False)

    @property
    def residual_rms(self) -> float:
        return self.fit.residual_rms

    @property
    def fit_percent(self) -> float:
        return self.fit.fit_percent

    def candidate(self, effect: str) -> Candidate:
        for c in self.candidates:
            if c.effect == effect:
                return c
        raise KeyError(f"no candidate {effect!r} (have: {[c.effect for c in self.candidates]})")

    def to_dict(self) -> dict[str, Any]:
        return {
            "equation": self.equation, "output": self.output, "unit": self.unit,
            "residual_rms": self.fit.residual_rms, "fit_percent": self.fit.fit_percent,
            "r2": self.fit.r2, "samples": self.fit.samples,
            "residual_rms_ls": self.residual_rms_ls,
            "residual_rms_fixed": self.residual_rms_fixed,
            "whiteness": None if self.whiteness is None else self.whiteness.to_dict(),
            "regions": [r.to_dict() for r in self.regions],
            "bins": {k: b.to_dict() for k, b in self.bins.items()},
            "orders": None if self.spectrum is None else self.spectrum.to_dict(),
            "candidates": [c.to_dict() for c in self.candidates],
            "not_applicable": [{"effect": e, "reason": r} for e, r in self.not_applicable],
            "suggestion": self.suggestion.to_dict(),
            "structure": [s.to_dict() for s in self.structure],
            "excitation": self.excitation.to_dict(),
            "identifiable": self.identifiable,
            "identifiability": list(self.identifiability),
            "verdict": self.verdict,
        }


@dataclass(frozen=True)
class Analysis:
    """One model fitted to the data and diagnosed: the estimates and each equation's diagnosis."""

    model: Model
    estimates: Estimates
    equations: tuple[EquationDiagnosis, ...]

    @property
    def primary(self) -> EquationDiagnosis:
        """The mechanical equation's diagnosis (the electrical one if there is no other)."""
        return self.equations[0]

    @property
    def effects(self) -> tuple[str, ...]:
        return self.model.effect_names

    @property
    def residual_rms(self) -> float:
        return self.primary.residual_rms

    @property
    def fit_percent(self) -> float:
        return self.primary.fit_percent

    @property
    def candidates(self) -> tuple[Candidate, ...]:
        """Candidates of every equation (mechanical first), each equation's best first:
        the suggestion in the order the forward selection chose it, then by the share of
        the residual variance explained (identifiable ones before the others)."""
        return tuple(c for e in self.equations for c in e.candidates)

    @property
    def suggestion(self) -> tuple[str, ...]:
        return tuple(a for e in self.equations for a in e.suggestion.add)

    def to_dict(self) -> dict[str, Any]:
        p = self.primary
        est = self.estimates.to_dict()
        return {
            "effects": list(self.effects),
            "residual_rms": p.fit.residual_rms,
            "fit_percent": p.fit.fit_percent,
            "r2": p.fit.r2,
            "samples": p.fit.samples,
            "unit": p.unit,
            "residual_rms_fixed": p.residual_rms_fixed,
            "whiteness": None if p.whiteness is None else p.whiteness.to_dict(),
            "parameters": est["parameters"],
            "equations": {e.equation: e.to_dict() for e in self.equations},
            "candidates": [c.to_dict() for c in self.candidates],
            "suggestion": list(self.suggestion),
            "verdict": " ".join(e.verdict for e in self.equations),
            "implausible": est["implausible"],
        }
