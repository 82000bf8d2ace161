r"""Diagnosis: compare the model with the measurements, see where it fails, name the missing effect.

:func:`diagnose` (samples in memory) and :func:`diagnose_log` (a recorded CAN log) run
the model through the same :class:`~canrls.estimation.pipeline.Pipeline` as ``canrls fit`` and
return a :class:`DiagnosisReport`: a result object that renders to text
(:meth:`DiagnosisReport.format`), to a JSON-able dict (:meth:`DiagnosisReport.to_dict`)
and to an HTML page with figures (:meth:`DiagnosisReport.write_html`,
:mod:`canrls.diagnosis.report`). ``docs/diagnose.md`` documents the JSON and the figures.

Everything is computed on the *filtered* equation the estimators see (the state-variable
filter applied to target and columns, :mod:`canrls.estimation.svf`), over the samples the estimators
used (not in a filter warm-up), in the target's unit:

1. **Compare.** The residual of the final float estimate :math:`\hat\theta` over the
   whole record, :math:`r = y - \Phi\hat\theta`; fit and :math:`R^2` as MATLAB's
   ``compare`` (the values ``canrls fit`` prints); whiteness of the residual and its
   cross-correlation with the inputs (:class:`Whiteness`).
2. **Where it fails.** Residual mean and RMS binned by speed (both directions), position
   (one revolution, or the travel of a linear axis), current, acceleration and time
   (:class:`Binned`); the worst regions in words (:class:`Region`); the residual's
   rotation-order spectrum (:class:`OrderSpectrum`).
3. **Which effect is missing.** Every effect of the library that is not in the model is
   tried as an extra set of columns :math:`G`, built through the same
   :class:`~canrls.estimation.model.Model` / regressor path (``model.with_effects(add=[...])``).
   With :math:`r_0` the least-squares residual of the current columns :math:`\Phi` and
   :math:`\tilde G = (I - \Phi\Phi^+) G` the candidate orthogonalised against them,
   the *error-reduction ratio*

   .. math::

       \mathrm{ERR} = \frac{r_0^\top \tilde G (\tilde G^\top\tilde G)^{-1}
                            \tilde G^\top r_0}{r_0^\top r_0}

   is the share of the residual variance the candidate explains (one column:
   :math:`(\tilde g^\top r_0)^2 / (\tilde g^\top\tilde g\; r_0^\top r_0)`); the
   residual RMS after adding it is :math:`\sqrt{(1-\mathrm{ERR})\,r_0^\top r_0/N}` and
   the change of the Bayesian information criterion

   .. math::

       \Delta\mathrm{BIC} = N_e \ln(1 - \mathrm{ERR}) + p \ln N_e,
       \qquad N_e = N\,\lVert h\rVert_2^2

   counts the :math:`N_e` independent samples the filter's impulse response :math:`h`
   (DC gain 1) leaves of :math:`N` (white noise through :math:`F` is correlated over
   about :math:`1/\lVert h\rVert_2^2` samples, 18 at the defaults). All of it comes
   from the Gram matrix of ``[Phi, G, y]`` accumulated block by block, so memory
   does not grow with the number of candidates. The cogging order is searched over
   :math:`k = 2 \dots K_{max}` (order 1 is ``unbalance``). A greedy forward selection
   (orthogonal least squares) adds the best candidate, re-ranks the others against the
   enlarged model and stops when the next one explains less than
   :data:`MIN_EXPLAINED` of what is left or does not lower the BIC: that is the
   :class:`Suggestion`. A candidate whose column is not excited, or (nearly) collinear
   with the model's columns (less than :data:`MIN_INDEPENDENCE` of it outside their
   span: a variance inflation above 100), is *not identifiable from this data* and is
   never suggested; the reason is stated (one direction of motion only, nearly constant
   speed, less than a revolution covered, ...).
4. **Add it.** With ``add=[...]`` the model is refitted with the effects added and the
   report holds ``before`` and ``after`` side by side (``cogging`` without an order
   takes the order the search found).

The residual left after the suggestion is checked for structure no candidate explains
(:class:`StructureItem`: a constant offset, dependence on speed, position, current,
acceleration, drift in time, periodicity at a non-integer order); with a complete model
and no structure left, nothing is suggested.
"""

from __future__ import annotations

import math
import os
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numba
import numpy as np
import numpy.typing as npt

from canrls.errors import ConfigError, EffectError
from canrls.estimation.effects import ELECTRICAL, MECHANICAL, Cogging, Effect, UserTerm, library
from canrls.estimation.model import Equation, Model, PositionUnwrapper
from canrls.estimation.pipeline import (
    EquationBlock,
    EquationEstimator,
    EquationFit,
    Estimates,
    EstimatorSettings,
    Pipeline,
)
from canrls.estimation.rls import RLS
from canrls.estimation.svf import SVF
from canrls.signals import Signals

__all__ = [
    "DEFAULT_MAX_ORDER",
    "MIN_EXPLAINED",
    "MIN_INDEPENDENCE",
    "MIN_EXCITATION",
    "Whiteness",
    "Binned",
    "Region",
    "OrderSpectrum",
    "Candidate",
    "Step",
    "Suggestion",
    "StructureItem",
    "ExcitationSummary",
    "Traces",
    "EquationDiagnosis",
    "Analysis",
    "DiagnosisReport",
    "diagnose",
    "diagnose_log",
]

F64 = npt.NDArray[np.float64]
I64 = npt.NDArray[np.int64]
B = npt.NDArray[np.bool_]

#: Highest cogging order searched (``cogging:2`` ... ``cogging:K``).
DEFAULT_MAX_ORDER = 64
#: Share of the residual variance a candidate must explain to be suggested.
MIN_EXPLAINED = 0.05
#: Share of the residual variance a suggestion must explain in total when structure is
#: left after it; below, it is withdrawn (partial explainers of something outside the
#: library are not what is missing).
MIN_TOTAL = 0.8
#: Fraction of a candidate's column energy that must lie outside the span of the model's
#: columns (1/VIF) for it to be identifiable.
MIN_INDEPENDENCE = 0.01
#: RMS of a normalised column (fraction of its full scale) below which it is treated as
#: zero (not excited at all); the physical checks (acceleration against the speed-sensor
#: noise, time below the Stribeck speed, revolutions covered) come first.
MIN_EXCITATION = 1e-6
#: Coherence of a periodic column with a sinusoid in time above which a position-periodic
#: effect cannot be told from a disturbance periodic in time (see ``_Context.coherence``).
MAX_COHERENCE = 0.9
#: Share of the residual variance a binned mean or an order must explain to count as
#: structure.
MIN_STRUCTURE = 0.25
#: Two-sided 99 % point of the standard normal distribution.
Z99 = 2.5758293035489004
#: Lags of the whiteness test (in decimated samples).
WHITENESS_LAGS = 20
#: Orders per unit of the rotation-order spectrum.
ORDER_STEP = 0.25

_MIN_BIN = 20
_BLOCK = 32768


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
        return 0.5 * (self.edges[1:] + self.edges[:-1])  # type: ignore[no-any-return]

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
    ``amplitude`` is the fitted amplitude in the target unit, ``explained`` the share of
    the residual variance the pair explains. ``per`` says what one period of order 1 is
    (a revolution, or the pitch of a linear axis). ``peaks`` lists the orders that stand
    out (local maxima explaining at least 1 % and 5 times the median), strongest first.
    """

    orders: F64
    amplitude: F64
    explained: F64
    peaks: tuple[float, ...]
    unit: str
    per: str

    def at(self, order: float) -> tuple[float, float]:
        """(amplitude, explained) at the order nearest ``order``."""
        j = int(np.argmin(np.abs(self.orders - order)))
        return float(self.amplitude[j]), float(self.explained[j])

    def to_dict(self) -> dict[str, Any]:
        return {"orders": _floats(self.orders), "amplitude": _floats(self.amplitude),
                "explained": _floats(self.explained), "peaks": list(self.peaks),
                "unit": self.unit, "per": self.per}


@dataclass(frozen=True)
class Candidate:
    """One effect of the library that the model lacks, evaluated against the residual.

    ``explained`` (ERR), ``delta_bic`` and ``rms_after`` describe adding this effect
    alone to the current model (module docstring). ``parameters`` are the values its
    parameters would take (least squares, physical units). ``identifiable`` is False
    when its column is not excited or (nearly) collinear with the model's columns;
    ``reason`` then says why. ``independence`` is the fraction of its column energy
    outside the span of the model's columns (1/VIF), ``excitation`` the RMS of its
    normalised column.
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

    def to_dict(self) -> dict[str, Any]:
        return {"effect": self.effect, "equation": self.equation,
                "explained": self.explained, "delta_bic": self.delta_bic,
                "rms_after": self.rms_after, "identifiable": self.identifiable,
                "suggested": self.suggested, "reason": self.reason or None,
                "description": self.description, "signature": self.signature,
                "evidence": list(self.evidence),
                "parameters": {k: {"value": v, "unit": u}
                               for k, (v, u) in self.parameters.items()},
                "independence": self.independence, "excitation": self.excitation}


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
    spectrum explains ``share``). The equation's own target signal is not tested: the
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
    low_speed: float
    revolutions: float | None
    coverage: float | None
    speed_unit: str
    per: str

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
                "revolutions": self.revolutions, "coverage": self.coverage,
                "speed_unit": self.speed_unit, "per": self.per, "facts": self.facts()}


@dataclass(frozen=True)
class Traces:
    """Arrays for the figures (all samples; ``used`` marks the rows outside warm-ups).

    ``y``, ``yhat`` and ``residual`` are the filtered target, its model value with the
    final float estimate, and their difference, in the target unit. ``speed``,
    ``acceleration``, ``current`` and ``position`` are the measured signals through the
    same filter (aligned with the residual), ``angle`` the phase of periodic terms
    (``None`` without position). ``conv_t``, ``theta``, ``sigma`` and ``theta_fixed``
    sample the parameter convergence (physical units) at up to 400 instants.
    """

    t: F64
    used: B
    y: F64
    yhat: F64
    residual: F64
    speed: F64
    acceleration: F64
    current: F64
    position: F64 | None
    angle: F64 | None
    conv_t: F64
    theta: F64
    sigma: F64
    theta_fixed: F64
    names: tuple[str, ...]
    units: tuple[str, ...]


@dataclass(frozen=True)
class EquationDiagnosis:
    """The diagnosis of one equation of the model (mechanical or electrical)."""

    equation: str
    target: str
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
            "equation": self.equation, "target": self.target, "unit": self.unit,
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
        }


# ================================================================== the report object
class DiagnosisReport:
    """What :func:`diagnose` found: ``before`` (the model as given), ``after`` (with
    ``added`` effects, or None), the candidates and the verdict.

    Renders to text (:meth:`format`), to a JSON-able dict (:meth:`to_dict`) and to an
    HTML page with PNG figures (:meth:`write_html`, needs matplotlib).
    """

    def __init__(self, *, source: str, dt: float, samples: int, duration: float,
                 before: Analysis, after: Analysis | None, added: tuple[str, ...],
                 settings: EstimatorSettings, frames: Mapping[str, Any] | None = None,
                 max_order: int = DEFAULT_MAX_ORDER) -> None:
        self.source = source
        self.dt = dt
        self.samples = samples
        self.duration = duration
        self.before = before
        self.after = after
        self.added = added
        self.settings = settings
        self.frames = dict(frames) if frames is not None else None
        self.max_order = max_order

    # -- shortcuts ----------------------------------------------------------------------
    @property
    def model(self) -> Model:
        return self.before.model

    @property
    def unit(self) -> str:
        return self.before.primary.unit

    @property
    def candidates(self) -> tuple[Candidate, ...]:
        """The before model's candidates, best first (identifiable ones first)."""
        return self.before.candidates

    @property
    def suggestion(self) -> tuple[str, ...]:
        """The effects the forward selection suggests adding (empty: nothing to add)."""
        return self.before.suggestion

    @property
    def verdict(self) -> str:
        return " ".join(e.verdict for e in self.before.equations)

    @property
    def identifiable(self) -> bool:
        return all(e.identifiable for e in self.before.equations)

    def __repr__(self) -> str:
        after = f", after={list(self.after.effects)}" if self.after else ""
        return (f"<DiagnosisReport {self.source}: {self.samples} samples, "
                f"before={list(self.before.effects)}{after}, "
                f"suggestion={list(self.suggestion)}>")

    # -- JSON ---------------------------------------------------------------------------
    def to_dict(self) -> dict[str, Any]:
        """Everything as plain types (``docs/diagnose.md`` documents every key)."""
        p = self.before.primary
        d: dict[str, Any] = {
            "source": self.source,
            "samples": self.samples,
            "duration": self.duration,
            "dt": self.dt,
            "axis": self.model.axis,
            "unit": p.unit,
            "max_order": self.max_order,
            "before": self.before.to_dict(),
            "added": list(self.added),
            "after": None if self.after is None else self.after.to_dict(),
            "candidates": [c.to_dict() for c in self.candidates],
            "not_applicable": [{"effect": e, "reason": r}
                               for q in self.before.equations for e, r in q.not_applicable],
            "suggestion": p.suggestion.to_dict(),
            "regions": [r.to_dict() for r in p.regions],
            "orders": None if p.spectrum is None else p.spectrum.to_dict(),
            "structure": [s.to_dict() for s in p.structure],
            "excitation": p.excitation.to_dict(),
            "identifiable": self.identifiable,
            "identifiability": [r for q in self.before.equations for r in q.identifiability],
            "verdict": self.verdict,
        }
        if self.frames is not None:
            d["frames"] = self.frames
        return d

    # -- text ---------------------------------------------------------------------------
    def format(self) -> str:
        """The report as text: compare, where it fails, candidates, verdict, before/after."""
        out: list[str] = []
        b = self.before
        out.append(f"{self.source}: {self.samples} samples ({self.duration:.1f} s), "
                   f"model {', '.join(b.effects)}")
        for q in b.equations:
            out.extend(_format_equation(q, self.model.axis))
        if self.after is not None:
            out.append("")
            out.extend(_format_before_after(self.before, self.after, self.added))
        return "\n".join(out)

    __str__ = format

    # -- figures ------------------------------------------------------------------------
    def write_html(self, directory: str | os.PathLike[str]) -> Path:
        """Write ``index.html`` and its PNG figures into ``directory`` (created).

        :raises ConfigError: matplotlib (the ``report`` extra) is not installed.
        :returns: the path of ``index.html``.
        """
        from canrls.diagnosis.report import write_html

        return write_html(self, directory)


# ========================================================================= entry points
def diagnose(data: Signals | Iterable[Signals], model: Model,
             settings: EstimatorSettings | None = None, *, dt: float | None = None,
             add: Sequence[str] = (), max_order: int = DEFAULT_MAX_ORDER,
             source: str = "<signals>",
             frames: Mapping[str, Any] | None = None) -> DiagnosisReport:
    """Diagnose ``model`` on samples: compare, locate the failures, rank the missing effects.

    :param data: a :class:`~canrls.signals.Signals` block, or blocks (joined end to end).
    :param model: the model to diagnose.
    :param settings: estimator settings (default :class:`EstimatorSettings`).
    :param dt: sample period [s] (default: the median step of ``t``).
    :param add: effects to add and refit (``after``); ``cogging`` without an order takes
        the order the search found.
    :param max_order: highest cogging order searched, and of the order spectrum.
    :param source: what the samples are, for the text.
    :param frames: frame statistics of a log replay, copied into the report.
    :raises ConfigError: no samples, a bad ``dt`` or ``max_order``; :class:`EffectError`
        for an effect in ``add`` that is unknown or already in the model.
    """
    signals = data if isinstance(data, Signals) else Signals.concat(list(data))
    n = len(signals)
    if n < 2:
        raise ConfigError(f"diagnose: {source}: {n} samples; need at least a few seconds")
    if dt is None:
        steps = np.diff(signals.t)
        steps = steps[np.isfinite(steps) & (steps > 0)]
        if not len(steps):
            raise ConfigError(f"diagnose: {source}: cannot infer the sample period from t")
        dt = float(np.median(steps))
    if not (isinstance(dt, int | float) and math.isfinite(dt) and dt > 0):
        raise ConfigError(f"diagnose: dt = {dt!r}: must be > 0 s")
    if isinstance(max_order, bool) or not isinstance(max_order, int) or max_order < 1:
        raise ConfigError(f"diagnose: max_order = {max_order!r}: must be an integer >= 1")
    settings = settings or EstimatorSettings()
    add = tuple(add)
    # validate the additions before the long part (cogging without K is resolved later)
    for a in add:
        if _bare_cogging(a):
            continue
        model.with_effects(add=[a])
    ctx = _Context(model, signals, float(dt), settings, max_order)
    before = _analyse(ctx, model)
    added = tuple(_resolve_add(a, before) for a in add)
    after = _analyse(ctx, model.with_effects(add=added)) if added else None
    t = signals.t
    duration = float(t[-1] - t[0]) + float(dt) if n else 0.0
    return DiagnosisReport(source=source, dt=float(dt), samples=n, duration=duration,
                           before=before, after=after, added=added, settings=settings,
                           frames=frames, max_order=max_order)


def diagnose_log(path: str | os.PathLike[str], protocol: Any, model: Model,
                 settings: EstimatorSettings | None = None, *, add: Sequence[str] = (),
                 progress: Callable[[int, int], None] | None = None,
                 max_order: int = DEFAULT_MAX_ORDER, chunk_size: int = 65536,
                 skip_bad_lines: bool = False) -> DiagnosisReport:
    """Diagnose ``model`` on a recorded CAN log (``.log`` candump, ``.asc``, ``.blf``, ...).

    The frames are decoded and paired exactly as ``canrls fit`` does
    (:class:`~canrls.processor.FrameProcessor`), so ``before`` holds the same parameters as
    ``canrls fit`` prints, bit for bit. The samples are kept in memory (five float64
    arrays) for the second pass that ``add`` needs.
    """
    from canrls.can.logs import LogReadStats, read_frames
    from canrls.processor import FrameProcessor

    # validate the additions before reading
    for a in add:
        if not _bare_cogging(a):
            model.with_effects(add=[a])
    stats = LogReadStats()
    proc = FrameProcessor(protocol, model, settings)
    parts = []
    for block in read_frames(path, chunk_size, skip_bad_lines=skip_bad_lines, stats=stats,
                             progress=progress):
        parts.append(proc.samples(block))
    parts.append(proc.pairer.flush())
    signals = Signals.concat([p for p in parts if len(p)]) if any(len(p) for p in parts) \
        else Signals.concat([])
    rej = proc.rejected
    frames: dict[str, Any] = {
        "total": proc.frames,
        "rejected": {k: int(v) for k, v in rej.items()},
        "lost": {k: int(v) for k, v in proc.decoder.lost.items()},
        "foreign": int(proc.decoder.foreign),
        "pairing": proc.pairing.as_dict(),
    }
    if stats.bad_lines:
        frames["bad_lines"] = stats.bad_lines
    if len(signals) < 2:
        raise ConfigError(f"{path}: {len(signals)} samples after decoding and pairing "
                          f"{proc.frames} frames; nothing to diagnose")
    return diagnose(signals, model, settings, dt=proc.pairer.period, add=add,
                    max_order=max_order, source=str(path), frames=frames)


# ============================================================================ internals
def _floats(a: Iterable[float]) -> list[float | None]:
    return [float(x) if math.isfinite(x) else None for x in np.asarray(a, dtype=float).ravel()]


def _bare_cogging(spec: str) -> bool:
    return isinstance(spec, str) and spec.strip().lower() == "cogging"


def _resolve_add(spec: str, before: Analysis) -> str:
    """``cogging`` alone: the order the search found."""
    if not _bare_cogging(spec):
        return spec
    for q in before.equations:
        orders = [c.effect for c in q.candidates if c.effect.startswith("cogging:")]
        if orders:
            return orders[0]
    raise EffectError("--add cogging: no cogging order could be searched (the data carry "
                      "no position, or the model has every order); give cogging:K")


class _Context:
    """What both analyses (before and after) share: samples, restarts, filtered signals."""

    def __init__(self, model: Model, signals: Signals, dt: float,
                 settings: EstimatorSettings, max_order: int) -> None:
        self.signals = signals
        self.dt = dt
        self.settings = settings
        self.max_order = max_order
        self.axis = model.axis
        self.pitch = model.pitch
        t = np.ascontiguousarray(signals.t, dtype=np.float64)
        n = len(t)
        gap = settings.gap_periods * dt
        # the pipeline restarts the filter at the first sample, at gaps and when time
        # goes backwards (canrls.estimation.pipeline._warmup_mask)
        restart = np.zeros(n, np.bool_)
        if n:
            restart[0] = True
            d = np.diff(t)
            restart[1:] = (d > gap) | (d < 0)
        self.starts = [int(k) for k in np.flatnonzero(restart)]
        self.speed_unit = "rad/s" if model.axis == "rotary" else "m/s"
        self.position_unit = "rad" if model.axis == "rotary" else "m"
        self.acc_unit = "rad/s²" if model.axis == "rotary" else "m/s²"
        self.per = "revolution" if model.axis == "rotary" else "pitch"
        held = model.held
        hold = {r: ("zoh" if r in held else "foh") for r in ("speed", "current", "position")}
        self.speed_hold = hold["speed"]
        self.cutoff_hz, self.zeta = model.cutoff_hz, model.zeta
        # F[speed], sF[speed], F[current]
        raw = np.column_stack([signals.speed, signals.current]).astype(np.float64)
        svf = SVF(model.cutoff_hz, dt, model.zeta, (hold["speed"], hold["current"]))
        f, sf = self._filter(svf, raw)
        self.speed = f[:, 0]
        self.acceleration = sf[:, 0]
        self.current = f[:, 1]
        # the unwrapped position (as the model unwraps it) and the phase of periodic terms
        self.position: F64 | None = None
        self.angle_raw: F64 | None = None
        self.angle: F64 | None = None
        if signals.position is not None:
            period = 2.0 * math.pi if model.axis == "rotary" else model.wrap
            unw = PositionUnwrapper(period)
            pos = np.empty(n)
            for a, b in self._segments():
                unw.reset()
                pos[a:b] = unw.process(np.asarray(signals.position[a:b], dtype=np.float64))
            k = 1.0 if model.axis == "rotary" else 2.0 * math.pi / model.pitch
            self.angle_raw = k * pos
            self.position_hold = hold["position"]
            svp = SVF(model.cutoff_hz, dt, model.zeta, hold["position"])
            fp, _ = self._filter(svp, pos.reshape(-1, 1))
            self.position = fp[:, 0]
            self.angle = k * self.position
        # impulse response of F for the target's hold -> effective samples, decimation
        self._h: dict[str, F64] = {}
        self._keep: dict[tuple[float, float, int], B] = {}
        self._coh: dict[tuple[int, int], tuple[F64, float]] = {}

    def _segments(self) -> list[tuple[int, int]]:
        n = len(self.signals)
        ends = self.starts[1:] + [n]
        return [(a, b) for a, b in zip(self.starts, ends, strict=True) if b > a]

    def _filter(self, svf: SVF, raw: F64) -> tuple[F64, F64]:
        f = np.empty_like(raw)
        sf = np.empty_like(raw)
        for a, b in self._segments():
            svf.reset()
            f[a:b], sf[a:b] = svf.process(raw[a:b])
        return f, sf

    def impulse(self, hold: str, derivative: bool = False) -> F64:
        """Impulse response of F (DC gain 1), or of sF, for a hold, long enough to decay."""
        key = hold + ("/s" if derivative else "")
        if key not in self._h:
            svf = SVF(self.cutoff_hz, self.dt, self.zeta, hold)
            wc = 2 * math.pi * self.cutoff_hz
            m = int(math.ceil(40.0 / (min(self.zeta, 1.0) * wc * self.dt))) + 8
            u = np.zeros(m + 2)
            u[2] = 1.0  # the filter starts at rest on u[0] = 0
            f, sf = svf.process(u)
            self._h[hold] = f[2:]
            self._h[hold + "/s"] = sf[2:]
        return self._h[key]

    def segments(self) -> list[tuple[int, int]]:
        return self._segments()

    def coherence(self, order: int, used: B) -> tuple[float, float]:
        r"""How much a periodic column of ``order`` looks like a sinusoid in time.

        :math:`c_k = |\overline{e^{ik(\vartheta - \bar\omega t)}}|` with
        :math:`\bar\omega` the least-squares slope of the angle against time: 1 when the
        axis turns at a constant speed (order ``k`` in position is then the frequency
        :math:`k\bar\omega/2\pi` in time), near 0 when the speed varies. Returns
        ``(c_k, frequency [Hz])``.
        """
        assert self.angle_raw is not None
        key = (int(used.sum()), hash(used.tobytes()))
        if key not in self._coh:
            a = self.angle_raw[used]
            t = self.signals.t[used]
            c = np.ones(self.max_order + 1)
            w = 0.0
            if len(a) >= 3:
                tc = t - t.mean()
                den = float(np.dot(tc, tc))
                w = float(np.dot(tc, a - a.mean())) / den if den > 0 else 0.0
                z1 = np.exp(1j * (a - w * t))
                zk = np.ones_like(z1)
                for k in range(1, self.max_order + 1):
                    zk *= z1
                    c[k] = abs(complex(np.mean(zk)))
            self._coh[key] = (c, w)
        c, w = self._coh[key]
        cc = float(c[order]) if order < len(c) else 0.0
        return cc, abs(order * w) / (2 * math.pi)

    def speed_keep(self, lo: float, hi: float, warm: int) -> B:
        """Rows with ``lo <= |omega| <= hi`` and not within ``warm`` samples after one
        outside (the pipeline's rule for the samples it uses, :mod:`canrls.estimation.pipeline`)."""
        key = (float(lo), float(hi), int(warm))
        if key not in self._keep:
            n = len(self.signals)
            w = np.abs(np.asarray(self.signals.speed, dtype=np.float64))
            bad = (w > hi) | (w < lo)
            if not bad.any():
                self._keep[key] = np.ones(n, np.bool_)
            else:
                idx = np.arange(n)
                last_bad = np.maximum.accumulate(np.where(bad, idx, -(10 ** 12)))
                self._keep[key] = (idx - last_bad) > warm
        return self._keep[key]

    @property
    def warm(self) -> int:
        s = self.settings
        wc = 2 * math.pi * self.cutoff_hz
        warm_s = 5.0 / (self.zeta * wc) if s.warmup_s is None else s.warmup_s
        return int(math.ceil(warm_s / self.dt))

    def keep(self, order: int) -> B:
        """Rows where a periodic column of ``order`` is sampled finely enough.

        The pipeline skips the samples where the fastest periodic column advances more
        than ``max_phase_step`` rad per sample (and the filter warm-up after them): the
        straight line between samples no longer follows ``sin(k theta)`` there, and near
        ``k omega dt = 2 pi`` the samples alias to low frequencies that pass the filter.
        A candidate periodic column is set to zero on those rows (not the rows dropped:
        the other candidates are compared on the same samples).
        """
        thr = self.settings.max_phase_step / (order * self.dt) if order else math.inf
        if self.axis == "linear":
            thr *= self.pitch / (2 * math.pi)
        return self.speed_keep(0.0, thr, self.warm)


def _eval_rows(ctx: _Context, model: Model, eq: Equation, names: Sequence[str],
               used: B, periodic: bool = False) -> B:
    """The samples the candidates are compared on.

    The pipeline's own samples for the model (``used``), less those it would not use
    once the non-periodic candidates are added (e.g. near standstill when Coulomb or
    Stribeck friction joins the model): the limits are read from the estimator the
    pipeline would build for that model. Periodic candidates are masked column by
    column instead (:meth:`_Context.keep`), unless ``periodic``: then their limits
    count too (the samples of the refit with them).
    """
    nonper = [nm for nm in names
              if periodic or not nm.startswith(("cogging:", "unbalance"))]
    m = model.with_effects(add=nonper) if nonper else model
    est = EquationEstimator(m.equation(eq.name), ctx.dt, ctx.settings)
    lo = float(getattr(est, "min_speed", 0.0) or 0.0)
    hi = float(getattr(est, "max_speed", math.inf))
    warm = int(getattr(est, "warmup", ctx.warm))
    return used & ctx.speed_keep(lo, hi, warm)


# ------------------------------------------------------------------------- the analysis
def _analyse(ctx: _Context, model: Model) -> Analysis:
    pipe = Pipeline(model, ctx.dt, ctx.settings)
    block = pipe.process(ctx.signals, record=True)
    est = pipe.estimates()
    eqs = []
    for e, eb, fit in zip(pipe.estimators, block.equations, est.equations, strict=True):
        eqs.append(_analyse_equation(ctx, model, e, eb, fit))
    return Analysis(model=model, estimates=est, equations=tuple(eqs))


def _analyse_equation(ctx: _Context, model: Model, est: EquationEstimator,
                      eb: EquationBlock, fit: EquationFit) -> EquationDiagnosis:
    eq = est.equation
    assert eb.phi is not None and eb.theta_fixed is not None
    used = eb.used
    N = int(used.sum())
    unit = eq.target.unit
    phi = eb.phi
    s_y = eq.scaling.target
    y_n = np.ldexp(eb.y, -s_y)  # normalised target (exact)
    th = np.array(est.rls.theta, dtype=np.float64)
    th_fx = np.asarray(est.frls.theta_float, dtype=np.float64)
    # r = y - Phi theta (final float estimate), in the target unit
    r = eq.target_to_physical(y_n - phi @ th)
    r_fx = eq.target_to_physical(y_n - phi @ th_fx)
    r_u = r[used]
    rms_fixed = float(np.sqrt(np.mean(r_fx[used] ** 2))) if N else math.nan
    hold = eq.holds[0]
    h = ctx.impulse(hold)
    h2 = float(np.sum(h * h))
    tau = 1.0 / h2 if h2 > 0 else 1.0  # correlation length of filtered white noise
    # -- inputs of this equation, for cross-correlation --------------------------------
    if eq.name == ELECTRICAL:
        inputs = {"current": ctx.current, "speed": ctx.speed}
    else:
        inputs = {"speed": ctx.speed, "acceleration": ctx.acceleration}
    wht = _whiteness(r, used, inputs, ctx.impulse(hold), WHITENESS_LAGS)
    bins = _all_bins(ctx, r, used, unit)
    regions = _regions(bins, r_u, tau, unit, ctx)
    spectrum = _order_spectrum(ctx, r, used, unit) if ctx.angle_raw is not None else None
    exc = _excitation(ctx, model, used)
    cand = _candidates(ctx, model, eq, eb, r, used, N, h2, unit, bins, spectrum, exc)
    traces = _traces(ctx, est, eb, r, used)
    return EquationDiagnosis(
        equation=eq.name, target=eq.target.description, unit=unit, fit=fit,
        residual_rms_ls=cand.rms_ls, residual_rms_fixed=rms_fixed, whiteness=wht,
        bins=bins, regions=regions, spectrum=spectrum, candidates=cand.candidates,
        not_applicable=cand.not_applicable, suggestion=cand.suggestion,
        structure=cand.structure, excitation=exc, identifiable=cand.identifiable,
        identifiability=cand.identifiability, verdict=cand.verdict, traces=traces)


# ----------------------------------------------------------------------------- whiteness
def _chi2_sf(q: float, k: int) -> float:
    """Upper tail of chi-square with k degrees of freedom (Wilson-Hilferty)."""
    if k <= 0 or not math.isfinite(q):
        return math.nan
    if q <= 0:
        return 1.0
    c = 2.0 / (9.0 * k)
    z = ((q / k) ** (1.0 / 3.0) - (1.0 - c)) / math.sqrt(c)
    return 0.5 * math.erfc(z / math.sqrt(2.0))


def _whiteness(r: F64, used: B, inputs: Mapping[str, F64], h: F64,
               lags: int) -> Whiteness | None:
    # decimation: the lag after which |rho_h| stays below 0.02
    hh = float(np.dot(h, h))
    if hh <= 0:
        return None
    m = len(h)
    rho = np.array([float(np.dot(h[: m - k], h[k:])) / hh for k in range(m)])
    big = np.flatnonzero(np.abs(rho) >= 0.02)
    D = int(big[-1]) + 1 if len(big) else 1
    x = r[used][::D]
    N = len(x)
    if N < 3 * lags + 10:
        return None
    x = x - x.mean()
    den = float(np.dot(x, x))
    if den <= 0:
        return None
    ac = np.array([float(np.dot(x[: N - k], x[k:])) / den for k in range(1, lags + 1)])
    bound = Z99 / math.sqrt(N)
    q = float(N * (N + 2) * np.sum(ac * ac / (N - np.arange(1, lags + 1))))
    p = _chi2_sf(q, lags)
    cross: dict[str, F64] = {}
    outside: dict[str, int] = {}
    for name, sig in inputs.items():
        u = sig[used][::D]
        u = u - u.mean()
        du = float(np.dot(u, u))
        if du <= 0:
            continue
        norm = math.sqrt(den * du)
        cc = np.empty(2 * lags + 1)
        for j, k in enumerate(range(-lags, lags + 1)):
            # rho_ru(k) = sum r[i] u[i - k] / sqrt(sum r^2 sum u^2)
            cc[j] = (float(np.dot(x[k:], u[: N - k])) if k >= 0
                     else float(np.dot(x[: N + k], u[-k:]))) / norm
        cross[name] = cc
        outside[name] = int(np.sum(np.abs(cc) > bound))
    return Whiteness(decimation=D, lags=lags, samples=N, autocorr=ac, bound=bound,
                     outside=int(np.sum(np.abs(ac) > bound)), q=q, p_value=p,
                     white=bool(p >= 0.01), cross=cross, cross_outside=outside)


# ----------------------------------------------------------------------------- binning
def _nice_magnitudes(vmax: float) -> F64:
    """Bin edges in |value|: 0, 1-2-5 steps from vmax/300 to vmax, closed at the top."""
    if not (vmax > 0 and math.isfinite(vmax)):
        return np.array([0.0, 1.0])
    out = [0.0]
    lo = vmax / 300.0
    e = math.floor(math.log10(lo))
    while True:
        for m in (1.0, 2.0, 5.0):
            v = m * 10.0 ** e
            if v <= lo:
                continue
            if v >= vmax * 0.8:
                out.append(vmax * (1 + 1e-9))
                return np.array(out)
            out.append(v)
        e += 1


def _bin(values: F64, r: F64, edges: F64, quantity: str, label: str,
         unit: str) -> Binned:
    nb = len(edges) - 1
    idx = np.searchsorted(edges, values, side="right") - 1
    # the end bins are closed at the extremes
    idx = np.where(values == edges[-1], nb - 1, idx)
    ok = (idx >= 0) & (idx < nb) & np.isfinite(values)
    idx = idx[ok]
    rr = r[ok]
    cnt = np.bincount(idx, minlength=nb).astype(np.int64)
    s1 = np.bincount(idx, weights=rr, minlength=nb)
    s2 = np.bincount(idx, weights=rr * rr, minlength=nb)
    good = cnt >= _MIN_BIN
    mean = np.full(nb, np.nan)
    rms = np.full(nb, np.nan)
    mean[good] = s1[good] / cnt[good]
    rms[good] = np.sqrt(s2[good] / cnt[good])
    tot = int(cnt[good].sum())
    share = 0.0
    if tot > 1:
        mu = float(s1[good].sum()) / tot
        ss = float(s2[good].sum()) - tot * mu * mu
        between = float(np.sum(cnt[good] * (mean[good] - mu) ** 2))
        share = between / ss if ss > 0 else 0.0
    return Binned(quantity, label, unit, edges, cnt, mean, rms, min(max(share, 0.0), 1.0))


def _edges_linear(v: F64, nb: int) -> F64:
    lo, hi = np.percentile(v, [0.5, 99.5])
    vmin, vmax = float(np.min(v)), float(np.max(v))
    if not hi > lo:
        lo, hi = vmin, vmax
    if not hi > lo:
        return np.array([vmin - 0.5, vmin + 0.5])
    inner = np.linspace(lo, hi, nb + 1)
    inner[0] = min(vmin, lo)
    inner[-1] = max(vmax, hi)
    return inner


def _all_bins(ctx: _Context, r: F64, used: B, unit: str) -> dict[str, Binned]:
    ru = r[used]
    out: dict[str, Binned] = {}
    if not len(ru):
        return out
    sp = ctx.speed[used]
    vmax = float(np.max(np.abs(sp)))
    mags = _nice_magnitudes(vmax)
    edges = np.concatenate([-mags[:0:-1], mags])
    out["speed"] = _bin(sp, ru, edges, "speed", "speed", ctx.speed_unit)
    if ctx.position is not None:
        if ctx.axis == "rotary":
            pos = np.mod(ctx.position[used], 2.0 * math.pi)
            pe = np.linspace(0.0, 2.0 * math.pi, 37)
            out["position"] = _bin(pos, ru, pe, "position", "position in the revolution",
                                   "rad")
        else:
            pos = ctx.position[used]
            out["position"] = _bin(pos, ru, _edges_linear(pos, 40), "position",
                                   "position along the travel", "m")
    out["current"] = _bin(ctx.current[used], ru, _edges_linear(ctx.current[used], 20),
                          "current", "current", "A")
    out["acceleration"] = _bin(ctx.acceleration[used], ru,
                               _edges_linear(ctx.acceleration[used], 20), "acceleration",
                               "acceleration", ctx.acc_unit)
    t = ctx.signals.t[used]
    te = np.linspace(float(t[0]), float(t[-1]), 21) if len(t) > 1 else np.array([0.0, 1.0])
    if not te[-1] > te[0]:
        te = np.array([te[0] - 0.5, te[0] + 0.5])
    out["time"] = _bin(t, ru, te, "time", "time", "s")
    return out


def _pct(x: float) -> str:
    """A share as a percentage with two or three significant digits (no exponent)."""
    v = 100.0 * x
    if not math.isfinite(v):
        return "n/a"
    if abs(v) >= 10:
        return f"{v:.0f} %"
    if abs(v) >= 1:
        return f"{v:.1f} %"
    return f"{v:.2g} %"


def _fmt(x: float, unit: str = "", sign: bool = False) -> str:
    s = f"{x:+.2g}" if sign else f"{x:.3g}"
    return f"{s} {unit}".rstrip()


def _range_text(quantity: str, lo: float, hi: float, full_lo: float, full_hi: float,
                unit: str) -> str:
    lo_end = lo <= full_lo
    hi_end = hi >= full_hi
    if quantity == "time":
        if lo_end and hi_end:
            return "over the whole record"
        return f"from {lo:.3g} s to {hi:.3g} s"
    noun = {"speed": "speed", "position": "position", "current": "current",
            "acceleration": "acceleration"}[quantity]
    if lo_end and hi_end:
        return f"at every {noun}"
    if quantity == "speed":
        if lo <= 0.0:
            return f"below {hi:.3g} {unit}"
        if hi_end:
            return f"above {lo:.3g} {unit}"
        return f"between {lo:.3g} and {hi:.3g} {unit}"
    plural = {"position": "positions", "current": "currents",
              "acceleration": "accelerations"}[quantity]
    if lo_end:
        return f"at {plural} below {hi:.3g} {unit}"
    if hi_end:
        return f"at {plural} above {lo:.3g} {unit}"
    return f"at {plural} between {lo:.3g} and {hi:.3g} {unit}"


def _notable(mean: float, n: int, sd: float, rms: float, tau: float) -> bool:
    """A bin mean that stands out: large against the residual and not noise."""
    if not (n >= _MIN_BIN and math.isfinite(mean)):
        return False
    se = sd / math.sqrt(max(n / tau, 1.0))
    return abs(mean) >= 0.2 * rms and abs(mean) >= 4.0 * se


def _regions(bins: Mapping[str, Binned], ru: F64, tau: float, unit: str,
             ctx: _Context) -> tuple[Region, ...]:
    if not len(ru):
        return ()
    energy = float(np.dot(ru, ru))
    rms = math.sqrt(energy / len(ru))
    if energy <= 0:
        return ()
    sd = float(np.std(ru))
    found: list[Region] = []
    # speed: magnitude bands with the mean forward and backward
    sb = bins.get("speed")
    if sb is not None:
        nm = (len(sb.edges) - 1) // 2
        mags = sb.edges[nm:]
        bands = []
        for j in range(nm):
            f = nm + j
            bk = nm - 1 - j
            nf, nb_ = int(sb.count[f]), int(sb.count[bk])
            mf, mb = float(sb.mean[f]), float(sb.mean[bk])
            sig_f = _notable(mf, nf, sd, rms, tau)
            sig_b = _notable(mb, nb_, sd, rms, tau)
            key = (int(np.sign(mf)) if sig_f else 0, int(np.sign(mb)) if sig_b else 0)
            bands.append((j, key, nf, mf, nb_, mb))
        groups: list[list[tuple[int, tuple[int, int], int, float, int, float]]] = []
        for band in bands:
            if band[1] == (0, 0):
                continue
            if groups and groups[-1][-1][0] == band[0] - 1 and groups[-1][-1][1] == band[1]:
                groups[-1].append(band)
            else:
                groups.append([band])
        for g in groups:
            nf = sum(x[2] for x in g if x[2] >= _MIN_BIN)
            nb_ = sum(x[4] for x in g if x[4] >= _MIN_BIN)
            mf = (sum(x[2] * x[3] for x in g if x[2] >= _MIN_BIN) / nf) if nf else math.nan
            mb = (sum(x[4] * x[5] for x in g if x[4] >= _MIN_BIN) / nb_) if nb_ else math.nan
            share = ((nf * mf * mf if nf else 0.0) + (nb_ * mb * mb if nb_ else 0.0)) / energy
            lo, hi = float(mags[g[0][0]]), float(mags[g[-1][0] + 1])
            rt = _range_text("speed", lo, hi, 0.0, float(mags[-1]), ctx.speed_unit)
            parts = []
            parts.append(f"{_fmt(mf, unit, True)} moving forward" if nf
                         else "no samples moving forward")
            parts.append(f"{_fmt(mb, unit, True)} moving backward" if nb_
                         else "no samples moving backward")
            text = f"{rt} the residual is {parts[0]} and {parts[1]}"
            found.append(Region("speed", text, lo, hi, share, nf + nb_,
                                mean_forward=None if not nf else mf,
                                mean_backward=None if not nb_ else mb))
    # the other quantities: runs of notable bins of the same sign
    for qn in ("position", "current", "acceleration", "time"):
        bq = bins.get(qn)
        if bq is None:
            continue
        nbins = len(bq.count)
        runs: list[list[int]] = []
        for j in range(nbins):
            m = float(bq.mean[j])
            if not _notable(m, int(bq.count[j]), sd, rms, tau):
                continue
            if runs and runs[-1][-1] == j - 1 and np.sign(bq.mean[runs[-1][-1]]) == np.sign(m):
                runs[-1].append(j)
            else:
                runs.append([j])
        qr = []
        for run in runs:
            n = int(sum(bq.count[j] for j in run))
            m = float(sum(bq.count[j] * bq.mean[j] for j in run)) / n
            lo, hi = float(bq.edges[run[0]]), float(bq.edges[run[-1] + 1])
            rt = _range_text(qn, lo, hi, float(bq.edges[0]), float(bq.edges[-1]), bq.unit)
            text = f"{rt} the residual is {_fmt(m, unit, True)}"
            if qn == "position" and ctx.axis == "rotary":
                text = text.replace("at positions", "at angles")
            qr.append(Region(qn, text, lo, hi, n * m * m / energy, n, mean=m))
        qr.sort(key=lambda x: -x.share)
        found.extend(qr[:3])
    found.sort(key=lambda x: -x.share)
    # one whole-range statement is enough (an offset shows in every quantity)
    out: list[Region] = []
    whole = False
    for reg in found:
        is_whole = ("every" in reg.text or "whole record" in reg.text)
        if is_whole and whole:
            continue
        whole = whole or is_whole
        out.append(reg)
    return tuple(out[:6])


# --------------------------------------------------------------------- order spectrum
def _order_spectrum(ctx: _Context, r: F64, used: B, unit: str) -> OrderSpectrum:
    assert ctx.angle_raw is not None
    K = ctx.max_order
    orders = _spectrum_orders(K)
    amp, expl = _harmonic_fit(ctx, r, used, orders)
    peaks = _peaks(orders, expl)
    return OrderSpectrum(orders, amp, expl, peaks, unit, ctx.per)


@numba.njit(cache=True)
def _sincos(a: F64, qs: F64, out: F64) -> None:  # pragma: no cover - compiled
    """out[i, 2j] = sin(q_j a_i), out[i, 2j + 1] = cos(q_j a_i)."""
    for i in range(a.shape[0]):
        for j in range(qs.shape[0]):
            x = qs[j] * a[i]
            out[i, 2 * j] = math.sin(x)
            out[i, 2 * j + 1] = math.cos(x)


def _spectrum_orders(max_order: int) -> F64:
    """Steps of 1/4 up to order 16 (fractional orders: gears, belts), integers above."""
    fine = np.arange(1, int(round(min(max_order, 16) / ORDER_STEP)) + 1) * ORDER_STEP
    coarse = np.arange(17, max_order + 1, dtype=np.float64)
    return np.concatenate([fine, coarse])


def _harmonic_fit(ctx: _Context, r: F64, used: B, orders: F64) -> tuple[F64, F64]:
    """Per order q: LS fit of r by a constant, F[sin q a] and F[cos q a].

    Returns the amplitude of the sine/cosine pair (target unit) and the share of the
    residual's variance (about its mean) it explains. The columns are built and filtered
    in blocks of rows (the filter's state carried), so memory does not grow with the
    record; only sums over the used rows are kept.
    """
    assert ctx.angle_raw is not None
    n_used = int(used.sum())
    amp = np.zeros(len(orders))
    expl = np.zeros(len(orders))
    if n_used < 3:
        return amp, expl
    rc = r - float(np.mean(r[used]))  # centred on the used rows
    den = float(np.dot(rc[used], rc[used]))
    if den <= 0:
        return amp, expl
    a = np.ascontiguousarray(ctx.angle_raw, dtype=np.float64)
    chunk = 32
    for c0 in range(0, len(orders), chunk):
        qs = np.ascontiguousarray(orders[c0:c0 + chunk], dtype=np.float64)
        m = len(qs)
        # sums over the used rows: g, g g' (per order: ss, cc, sc), g r
        s1 = np.zeros(2 * m)
        ss = np.zeros(m)
        cc = np.zeros(m)
        sc = np.zeros(m)
        sr = np.zeros(m)
        cr = np.zeros(m)
        svf = SVF(ctx.cutoff_hz, ctx.dt, ctx.zeta, ctx.position_hold)
        for sa, sb in ctx.segments():
            svf.reset()
            for b0 in range(sa, sb, _BLOCK):
                b1 = min(sb, b0 + _BLOCK)
                raw = np.empty((b1 - b0, 2 * m))
                _sincos(a[b0:b1], qs, raw)
                f, _ = svf.process(raw)
                u = used[b0:b1]
                if not u.any():
                    continue
                G = f[u]
                ru = rc[b0:b1][u]
                gs, gc = G[:, 0::2], G[:, 1::2]
                s1 += G.sum(axis=0)
                ss += np.einsum("ij,ij->j", gs, gs)
                cc += np.einsum("ij,ij->j", gc, gc)
                sc += np.einsum("ij,ij->j", gs, gc)
                sr += gs.T @ ru
                cr += gc.T @ ru
        # centre the columns: sum (g - mean g)(h - mean h) = sum g h - n mean g mean h
        ms, mc = s1[0::2] / n_used, s1[1::2] / n_used
        ss -= n_used * ms * ms
        cc -= n_used * mc * mc
        sc -= n_used * ms * mc
        # normal equations per order: [[ss sc] [sc cc]] x = [sr cr]
        det = ss * cc - sc * sc
        ok = det > 1e-12 * np.maximum(ss * cc, 1e-300)
        xs = np.zeros(m)
        xc = np.zeros(m)
        xs[ok] = (cc[ok] * sr[ok] - sc[ok] * cr[ok]) / det[ok]
        xc[ok] = (ss[ok] * cr[ok] - sc[ok] * sr[ok]) / det[ok]
        amp[c0:c0 + chunk] = np.hypot(xs, xc)
        expl[c0:c0 + chunk] = np.clip((xs * sr + xc * cr) / den, 0.0, 1.0)
    return amp, expl


def _peaks(orders: F64, expl: F64, limit: int = 5) -> tuple[float, ...]:
    if not len(expl):
        return ()
    med = float(np.median(expl))
    out = []
    for j in range(len(expl)):
        e = expl[j]
        left = expl[j - 1] if j > 0 else -1.0
        right = expl[j + 1] if j + 1 < len(expl) else -1.0
        if e >= left and e >= right and e >= 0.01 and e >= 10.0 * med:
            out.append((float(e), float(orders[j])))
    out.sort(reverse=True)
    return tuple(o for _, o in out[:limit])


# ------------------------------------------------------------------------- excitation
def _excitation(ctx: _Context, model: Model, used: B) -> ExcitationSummary:
    sp = ctx.speed[used]
    if not len(sp):
        return ExcitationSummary(0.0, 0.0, 0, math.nan, math.nan, math.nan, math.nan,
                                 math.nan, math.nan, None, None, ctx.speed_unit, ctx.per)
    vmax = float(np.percentile(np.abs(sp), 99.0))
    eps = max(model.coulomb_band, 0.01 * vmax)
    fwd = float(np.mean(sp > eps))
    bwd = float(np.mean(sp < -eps))
    s = np.sign(sp[np.abs(sp) > eps])
    rev = int(np.sum(s[1:] != s[:-1])) if len(s) > 1 else 0
    # samples where the Stribeck shape exp(-(w/ws)^2) is more than e^-4
    low = float(np.mean(np.abs(sp) < 2.0 * model.stribeck_speed))
    # speed-sensor noise from the second differences of the measured speed (robust:
    # var(w[k+1] - 2 w[k] + w[k-1]) = 6 sigma^2 for white noise), through sF
    w = np.asarray(ctx.signals.speed, dtype=np.float64)
    d2 = w[2:] - 2.0 * w[1:-1] + w[:-2]
    sigma_w = 1.4826 * float(np.median(np.abs(d2))) / math.sqrt(6.0) if len(d2) else 0.0
    h_sf = ctx.impulse(ctx.speed_hold, derivative=True)
    acc_noise = sigma_w * float(np.sqrt(np.dot(h_sf, h_sf)))
    revs = cov = None
    if ctx.angle is not None:
        a = ctx.angle[used]
        revs = float(np.sum(np.abs(np.diff(a)))) / (2 * math.pi) if len(a) > 1 else 0.0
        cov = float(np.max(a) - np.min(a)) / (2 * math.pi)
    return ExcitationSummary(
        forward=fwd, backward=bwd, reversals=rev, speed_mean=float(np.mean(sp)),
        speed_std=float(np.std(sp)), speed_max=float(np.max(np.abs(sp))),
        acceleration_rms=float(np.sqrt(np.mean(ctx.acceleration[used] ** 2))),
        acceleration_noise=acc_noise, low_speed=low, revolutions=revs, coverage=cov,
        speed_unit=ctx.speed_unit, per=ctx.per)


# ------------------------------------------------------------------------- candidates
@dataclass
class _CandidateResult:
    candidates: tuple[Candidate, ...]
    not_applicable: tuple[tuple[str, str], ...]
    suggestion: Suggestion
    structure: tuple[StructureItem, ...]
    identifiable: bool
    identifiability: tuple[str, ...]
    verdict: str
    rms_ls: float


class _Gram:
    r"""Least squares from the Gram matrix of ``[columns..., y]`` (columns equilibrated).

    ``rss(S)`` is the residual sum of squares of y regressed on the columns ``S``
    (normalised units); pseudo-inverses drop directions below 1e-12 of the largest.
    """

    def __init__(self, A: F64) -> None:
        self.m = A.shape[0] - 1
        d = np.sqrt(np.maximum(np.diag(A), 0.0))
        self.zero = d[: self.m] <= 1e-300
        d = np.where(d > 1e-300, d, 1.0)
        self.d = d
        self.An = A / np.outer(d, d)
        self.yy = float(A[-1, -1])

    def solve(self, S: Sequence[int]) -> tuple[float, dict[int, float]]:
        """(RSS, {column: coefficient in the column's units}) of y on columns S."""
        S = [j for j in S if not self.zero[j]]
        if not S:
            return self.yy, {}
        Ass = self.An[np.ix_(S, S)]
        b = self.An[S, -1]
        w, V = np.linalg.eigh(Ass)
        keep = w > 1e-12 * max(float(w[-1]), 1e-300)
        x = V[:, keep] @ ((V[:, keep].T @ b) / w[keep])
        rss = (float(self.An[-1, -1]) - float(b @ x)) * self.d[-1] ** 2
        coef = x * self.d[-1] / self.d[S]
        return max(rss, 0.0), {j: float(c) for j, c in zip(S, coef, strict=True)}

    def independence(self, S: Sequence[int], C: Sequence[int]) -> float:
        """Smallest eigenvalue of the equilibrated Schur complement of C in [C, S]: the
        fraction of the worst direction of S outside the span of C (1/VIF)."""
        S = [j for j in S if not self.zero[j]]
        if not S:
            return 0.0
        Ass = self.An[np.ix_(S, S)]
        C = [j for j in C if not self.zero[j]]
        if C:
            Acc = self.An[np.ix_(C, C)]
            Acs = self.An[np.ix_(C, S)]
            w, V = np.linalg.eigh(Acc)
            keep = w > 1e-12 * max(float(w[-1]), 1e-300)
            X = V[:, keep] @ ((V[:, keep].T @ Acs) / w[keep][:, None])
            Ass = Ass - Acs.T @ X
        # relative to the columns' own energy (their equilibrated Gram)
        w0 = np.linalg.eigvalsh(self.An[np.ix_(S, S)])
        ws = np.linalg.eigvalsh(0.5 * (Ass + Ass.T))
        return float(max(ws[0], 0.0) / max(w0[-1], 1e-300))

    def corr(self, i: int, j: int) -> float:
        return float(self.An[i, j])


def _candidate_names(model: Model, eq: Equation, signals: Signals,
                     max_order: int) -> tuple[list[str], list[tuple[str, str]]]:
    """The library effects (and configured user terms) not in the model, for this equation."""
    have = set(model.effect_names)
    names: list[str] = []
    na: list[tuple[str, str]] = []
    has_pos = signals.position is not None
    for cls in library():
        base = cls.NAME
        if base == "user":
            for term, t in sorted(model.terms.items()):
                nm = f"user:{term}"
                if nm in have or t.get("equation", MECHANICAL) != eq.name:
                    continue
                names.append(nm)
            continue
        if cls.EQUATION != eq.name:
            if base == "electrical" and "electrical" not in have:
                if signals.voltage is None:
                    na.append((base, "needs the voltage signal, which the data do not carry"))
                else:
                    na.append((base, "a second (voltage) equation: it cannot explain the "
                                     "mechanical residual; add it to identify R, L and Ke"))
            continue
        if base == "cogging":
            if not has_pos:
                na.append(("cogging:K", "needs the position, which the data do not carry"))
                continue
            names.extend(f"cogging:{k}" for k in range(2, max_order + 1)
                         if f"cogging:{k}" not in have)
            continue
        if base in have:
            continue
        if "position" in cls.REQUIRES and not has_pos:
            na.append((base, "needs the position, which the data do not carry"))
            continue
        names.append(base)
    # drop what the model cannot take (e.g. a signal the drive does not send)
    ok: list[str] = []
    tried_cog: bool | None = None
    for nm in names:
        if nm.startswith("cogging:"):
            if tried_cog is None:
                try:
                    model.with_effects(add=[nm])
                    tried_cog = True
                except ConfigError as e:
                    tried_cog = False
                    na.append(("cogging:K", str(e)))
            if tried_cog:
                ok.append(nm)
            continue
        try:
            model.with_effects(add=[nm])
        except ConfigError as e:
            na.append((nm, str(e)))
            continue
        if nm.startswith("user:"):
            eff = model.with_effects(add=[nm]).effects[-1]
            miss = [r for r in eff.requires if getattr(signals, r, None) is None]
            if miss:
                na.append((nm, f"reads {', '.join(miss)}, which the data do not carry"))
                continue
        ok.append(nm)
    return ok, na


def _mask_periodic(ctx: _Context, eq: Equation, first: int, phi: F64, a: int) -> None:
    """Zero candidate periodic columns (index >= ``first``) where ``ctx.keep`` says so."""
    for j in range(first, eq.n):
        k = eq.parameters[j].order
        if k > 0:
            keep = ctx.keep(k)[a:a + len(phi)]
            if not keep.all():
                phi[~keep, j] = 0.0


def _gram_matrix(ctx: _Context, eq: Equation, used: B, first: int) -> F64:
    """Gram matrix of [phi, y] over the used rows, block by block (candidate periodic
    columns from ``first`` on masked by :meth:`_Context.keep`)."""
    builder = eq.builder(ctx.dt)
    m = eq.n + 1
    A = np.zeros((m, m))
    for a, b in ctx.segments():
        builder.reset()
        for c0 in range(a, b, _BLOCK):
            c1 = min(b, c0 + _BLOCK)
            rb = builder.process(ctx.signals.slice(c0, c1))
            phi = rb.phi
            _mask_periodic(ctx, eq, first, phi, c0)
            u = used[c0:c1]
            Z = np.column_stack([phi[u], rb.y[u]])
            A += Z.T @ Z
    return A


def _columns(ctx: _Context, eq: Equation, first: int) -> tuple[F64, F64]:
    """All rows of (phi, y) of an equation (normalised), with the pipeline's restarts."""
    builder = eq.builder(ctx.dt)
    n = len(ctx.signals)
    phi = np.empty((n, eq.n))
    y = np.empty(n)
    for a, b in ctx.segments():
        builder.reset()
        rb = builder.process(ctx.signals.slice(a, b))
        phi[a:b] = rb.phi
        y[a:b] = rb.y
    _mask_periodic(ctx, eq, first, phi, 0)
    return phi, y


def _candidates(ctx: _Context, model: Model, eq: Equation, eb: EquationBlock, r: F64,
                used: B, N: int, h2: float, unit: str, bins: Mapping[str, Binned],
                spectrum: OrderSpectrum | None,
                exc: ExcitationSummary) -> _CandidateResult:
    names, na = _candidate_names(model, eq, ctx.signals, ctx.max_order)
    # compare on the samples the pipeline would use with the candidates
    used = _eval_rows(ctx, model, eq, names, used)
    N = int(used.sum())
    n = eq.n
    cur_names = [p.name for p in eq.parameters]
    aug_model = model.with_effects(add=names) if names else model
    aug = aug_model.equation(eq.name)
    if [p.name for p in aug.parameters[:n]] != cur_names:  # pragma: no cover - contract
        raise AssertionError("with_effects did not keep the model's columns first")
    A = _gram_matrix(ctx, aug, used, n)
    G = _Gram(A)
    C = list(range(n))
    # groups of columns per candidate effect
    groups: dict[str, list[int]] = {}
    for j, p in enumerate(aug.parameters[n:], start=n):
        groups.setdefault(p.effect, []).append(j)
    factors = aug.scaling.factors
    scale_y = math.ldexp(1.0, aug.scaling.target)
    rss0, th0 = G.solve(C)
    Ne = max(N * h2, 2.0)
    rms_ls = math.sqrt(rss0 / N) * scale_y if N else math.nan

    def rms_of(rss: float) -> float:
        return math.sqrt(rss / N) * scale_y if N else math.nan

    def bic(rss_new: float, rss_old: float, p: int) -> float:
        # dBIC = Ne ln(RSS'/RSS) + p ln Ne
        if rss_old <= 0:
            return math.inf
        return Ne * math.log(max(rss_new, 1e-300 * rss_old) / rss_old) + p * math.log(Ne)

    col_rms = np.sqrt(np.maximum(np.diag(A)[:-1], 0.0) / max(N, 1))
    # -- the model's own columns -------------------------------------------------------
    model_issues: list[str] = []
    for j in C:
        others = [i for i in C if i != j]
        ind = G.independence([j], others) if others else 1.0
        why = _unexcited_reason(cur_names[j], exc, model)
        if col_rms[j] < MIN_EXCITATION or why:
            model_issues.append(f"{cur_names[j]} is " + (why or "not excited: its column is "
                                                          "practically zero").replace(
                "not excited", "not excited", 1))
        elif ind < MIN_INDEPENDENCE:
            partners = sorted(others, key=lambda i: -abs(G.corr(i, j)))[:2]
            model_issues.append(
                f"{cur_names[j]} is (nearly) collinear with "
                f"{' and '.join(cur_names[i] for i in partners)} "
                f"({_pct(ind)} of its column independent)")
    # -- every candidate alone ---------------------------------------------------------
    evaluated: dict[str, dict[str, Any]] = {}
    for name, cols in groups.items():
        exc_c = float(np.max(col_rms[cols]))
        ind = G.independence(cols, C)
        rss, x = G.solve(C + cols)
        expl = (rss0 - rss) / rss0 if rss0 > 0 else 0.0
        expl = min(max(expl, 0.0), 1.0)
        reason = ""
        order = aug.parameters[cols[0]].order
        unexcited = _unexcited_reason(name, exc, model)
        if exc_c < MIN_EXCITATION:
            reason = unexcited or "not excited: its column is practically zero over the record"
        elif unexcited:
            reason = unexcited
        elif ind < MIN_INDEPENDENCE:
            reason = _collinear_reason(name, cols, C, G, cur_names, ind, exc)
        elif order > 0 and ctx.angle_raw is not None:
            coh, f_hz = ctx.coherence(order, used)
            if coh >= MAX_COHERENCE:
                reason = (f"not identifiable from this data: the speed is nearly constant, so "
                          f"order {order} in position is a sinusoid of {f_hz:.3g} Hz in time "
                          f"(coherence {coh:.2f}); it cannot be told from a disturbance "
                          f"periodic in time: vary the speed")
        th = {}
        for j in cols:
            p = aug.parameters[j]
            th[p.name] = (float(x.get(j, 0.0) * factors[j]), p.unit)
        evaluated[name] = dict(cols=cols, explained=expl, rss=rss,
                               dbic=bic(rss, rss0, len(cols)), ind=ind, exc=exc_c,
                               reason=reason, params=th)
    # -- the cogging order -------------------------------------------------------------
    cog = [nm for nm in evaluated if nm.startswith("cogging:")]
    best_cog = max(cog, key=lambda nm: (evaluated[nm]["explained"], -int(nm[8:]))) \
        if cog else None
    # -- forward selection ---------------------------------------------------------------
    steps: list[Step] = []
    sel: list[int] = []
    chosen: list[str] = []
    rss_cur = rss0
    pool = [nm for nm, ev in evaluated.items() if not ev["reason"]]
    for _ in range(8):
        best = None
        for nm in pool:
            if nm in chosen:
                continue
            cols = evaluated[nm]["cols"]
            if G.independence(cols, C + sel) < MIN_INDEPENDENCE:
                continue
            rss, _ = G.solve(C + sel + cols)
            if best is None or rss < best[1]:
                best = (nm, rss)
        if best is None or rss_cur <= 0:
            break
        nm, rss = best
        expl = (rss_cur - rss) / rss_cur
        db = bic(rss, rss_cur, len(evaluated[nm]["cols"]))
        if expl < MIN_EXPLAINED or db >= 0:
            break
        chosen.append(nm)
        sel += evaluated[nm]["cols"]
        steps.append(Step(nm, float(expl), float(db), rms_of(rss)))
        rss_cur = rss
    suggestion = Suggestion(tuple(steps), rms_ls)
    # -- what structure is left after the suggestion ---------------------------------------
    partial: Suggestion | None = None
    structure: tuple[StructureItem, ...] = ()
    if chosen:
        # the model with the suggestion, on the samples the pipeline will use for it
        # (periodic effects drop the fast samples there, instead of being masked)
        m2 = model.with_effects(add=chosen)
        eq2 = m2.equation(eq.name)
        rows2 = _eval_rows(ctx, model, eq, chosen, eb.used, periodic=True)
        phi2, y2 = _columns(ctx, eq2, eq2.n)
        theta2 = np.linalg.lstsq(phi2[rows2], y2[rows2], rcond=None)[0]
        r_left = eq2.target_to_physical(y2 - phi2 @ theta2)
        if int(rows2.sum()):
            suggestion = Suggestion(suggestion.steps, suggestion.rms_before,
                                    float(np.sqrt(np.mean(r_left[rows2] ** 2))))
        structure = _structure(ctx, r_left, rows2, unit, h2, None, eq.target.signal)
        total = 1.0 - rss_cur / rss0 if rss0 > 0 else 0.0
        if structure and total < MIN_TOTAL:
            # the best candidates explain part of the structure and leave the rest: they
            # are not what is missing; say so instead of suggesting them
            partial, suggestion, chosen = suggestion, Suggestion((), rms_ls), []
    if not chosen:
        # nothing to add: the least-squares residual of the model as it is (structure the
        # model's own columns can absorb is the estimator's, not a missing effect)
        assert eb.phi is not None
        th_ls = np.array([th0.get(j, 0.0) for j in C])
        r_ls = eq.target_to_physical(np.ldexp(eb.y, -eq.scaling.target) - eb.phi @ th_ls)
        d = (r_ls - r)[used]
        # the displayed spectrum (of r) serves when r_ls is practically r
        same = (float(np.dot(d, d)) <= 0.01 * float(np.dot(r_ls[used], r_ls[used]))
                and N == int(eb.used.sum()))
        structure = _structure(ctx, r_ls, used, unit, h2, spectrum if same else None,
                               eq.target.signal)
    # -- which candidates to list --------------------------------------------------------
    # every effect once; of the cogging orders the best one and those suggested
    listed = [nm for nm in evaluated if not nm.startswith("cogging:")]
    extra_cog = [nm for nm in cog if nm in chosen]
    if best_cog is not None and best_cog not in extra_cog:
        extra_cog.insert(0, best_cog)
    listed += extra_cog
    ev_ctx = _EvidenceContext(ctx, bins, spectrum, unit, eb, used, A, G, C, aug, evaluated,
                              best_cog, cog, model)
    cands = []
    for nm in listed:
        ev = evaluated[nm]
        eff = aug_model.effects[[e.name for e in aug_model.effects].index(nm)]
        cands.append(Candidate(
            effect=nm, equation=eq.name, description=_description(eff),
            signature=type(eff).RESIDUAL_SIGNATURE, explained=float(ev["explained"]),
            delta_bic=float(ev["dbic"]), rms_after=rms_of(ev["rss"]),
            identifiable=not ev["reason"], suggested=nm in chosen, reason=ev["reason"],
            evidence=tuple(_evidence(nm, ev_ctx)), parameters=ev["params"],
            independence=float(ev["ind"]), excitation=float(ev["exc"])))
    # best first: the suggestion in the order it was chosen, then by share explained
    # (identifiable ones before the others)
    cands.sort(key=lambda c: (chosen.index(c.effect) if c.suggested else len(chosen),
                              0 if c.identifiable else 1, -c.explained))
    # -- identifiability and verdict -------------------------------------------------------
    not_ident = [c for c in cands if not c.identifiable]
    reasons = list(model_issues)
    for c in not_ident:
        reasons.append(f"{c.effect}: {c.reason}")
    identifiable = not model_issues and not not_ident
    rms_final = math.sqrt(float(np.mean(r[used] ** 2))) if N else math.nan
    verdict = _verdict(eq, suggestion, cands, structure, model_issues, not_ident, exc, unit,
                       rms_ls, partial)
    if rms_final > 1.1 * rms_ls:
        verdict += (f" Note: the final estimate leaves a residual RMS of {_fmt(rms_final, unit)}"
                    f", {100 * (rms_final / rms_ls - 1):.0f} % more than the least-squares fit "
                    f"of the same model over the whole record ({_fmt(rms_ls, unit)}): the "
                    f"estimator has not converged, or forgetting or the ridge prior bias it "
                    f"(see the parameter convergence).")
    return _CandidateResult(tuple(cands), tuple(na), suggestion, structure, identifiable,
                            tuple(reasons), verdict, rms_ls)


def _description(eff: Effect) -> str:
    doc = (type(eff).__doc__ or "").strip().splitlines()
    first = doc[0].strip() if doc else eff.name
    if isinstance(eff, UserTerm):
        return f"user term {eff.term}: c * ({eff.expr})"
    if isinstance(eff, Cogging):
        k = str(eff.k)
        return f"{first.replace('``k``', k)} ({eff.EQUATION_TEXT.replace('k', k)})"
    return f"{first} ({type(eff).EQUATION_TEXT})"


def _unexcited_reason(name: str, exc: ExcitationSummary, model: Model) -> str:
    """Why an effect's column is not excited by these data ("" when it is)."""
    u = exc.speed_unit
    base = name.split(":")[0].split(".")[0]
    if base == "stribeck" and exc.low_speed < 0.005:
        return (f"not excited: the speed is below twice the Stribeck speed "
                f"({2 * model.stribeck_speed:g} {u}) in only {_pct(exc.low_speed)} of "
                f"the samples")
    if base == "inertia" and not exc.accelerating:
        return (f"not excited: the acceleration is at the level of the speed-sensor noise "
                f"(RMS {exc.acceleration_rms:.3g} {u}/s against {exc.acceleration_noise:.3g} "
                f"{u}/s)")
    if base in ("unbalance", "cogging") and exc.revolutions is not None \
            and exc.revolutions < 1.0:
        return f"not excited: the position covers only {exc.revolutions:.2f} {exc.per}s"
    return ""


def _collinear_reason(name: str, cols: Sequence[int], C: Sequence[int], G: _Gram,
                      cur: Sequence[str], ind: float, exc: ExcitationSummary) -> str:
    partners = sorted(C, key=lambda i: -max(abs(G.corr(i, j)) for j in cols))
    strong = [cur[i] for i in partners if max(abs(G.corr(i, j)) for j in cols) > 0.9][:2]
    what = (f"(nearly) collinear with {' and '.join(strong)}" if strong
            else "(nearly) collinear with the model's columns")
    why = exc.facts()
    text = f"not identifiable from this data: its column is {what} ({_pct(ind)} " \
           f"independent)"
    if why:
        text += "; " + "; ".join(why)
    return text


@dataclass
class _EvidenceContext:
    ctx: _Context
    bins: Mapping[str, Binned]
    spectrum: OrderSpectrum | None
    unit: str
    eb: EquationBlock
    used: B
    A: F64
    G: _Gram
    C: list[int]
    aug: Equation
    evaluated: Mapping[str, Mapping[str, Any]]
    best_cog: str | None
    cog: list[str]
    model: Model


def _speed_sides(b: Binned) -> list[tuple[float, float, float, int, float, int]]:
    """(lo, hi, mean forward, n forward, mean backward, n backward) per magnitude band."""
    nm = (len(b.edges) - 1) // 2
    out = []
    for j in range(nm):
        f, bk = nm + j, nm - 1 - j
        out.append((float(b.edges[f]), float(b.edges[f + 1]), float(b.mean[f]),
                    int(b.count[f]), float(b.mean[bk]), int(b.count[bk])))
    return out


def _pooled(rows: Sequence[tuple[float, float, float, int, float, int]],
            side: int) -> float:
    m_i, n_i = (2, 3) if side > 0 else (4, 5)
    tot = sum(r[n_i] for r in rows if r[n_i] >= _MIN_BIN)
    if not tot:
        return math.nan
    return sum(r[m_i] * r[n_i] for r in rows if r[n_i] >= _MIN_BIN) / tot


def _evidence(name: str, ec: _EvidenceContext) -> list[str]:
    ev = ec.evaluated[name]
    u = ec.unit
    su = ec.ctx.speed_unit
    out: list[str] = []
    base = name.split(":")[0]
    sb = ec.bins.get("speed")
    rows = _speed_sides(sb) if sb is not None else []
    if base in ("coulomb", "viscous", "stribeck", "offset") and rows:
        vmax = rows[-1][1]
        ws = ec.model.stribeck_speed
        if base == "coulomb":
            far = [r for r in rows if r[0] >= min(3 * ws, 0.3 * vmax)]
            mf, mb = _pooled(far, 1), _pooled(far, -1)
            out.append(f"above {min(3 * ws, 0.3 * vmax):.3g} {su} the residual is "
                       f"{_fmt(mf, u, True)} moving forward and {_fmt(mb, u, True)} moving "
                       f"backward: a step at zero speed, signed with the direction")
        elif base == "stribeck":
            near = [r for r in rows if r[1] <= ws * 1.0001]
            far = [r for r in rows if r[0] >= 3 * ws]
            out.append(f"below {ws:g} {su}: {_fmt(_pooled(near, 1), u, True)} forward, "
                       f"{_fmt(_pooled(near, -1), u, True)} backward; above {3 * ws:g} {su}: "
                       f"{_fmt(_pooled(far, 1), u, True)} forward, "
                       f"{_fmt(_pooled(far, -1), u, True)} backward")
        elif base == "viscous":
            top = [r for r in rows if r[0] >= 0.3 * vmax]
            lowr = [r for r in rows if r[1] <= 0.1 * vmax]
            out.append(f"above {0.3 * vmax:.3g} {su}: {_fmt(_pooled(top, 1), u, True)} forward,"
                       f" {_fmt(_pooled(top, -1), u, True)} backward; below "
                       f"{0.1 * vmax:.3g} {su}: {_fmt(_pooled(lowr, 1), u, True)} forward, "
                       f"{_fmt(_pooled(lowr, -1), u, True)} backward (linear and odd in "
                       f"speed)")
        elif base == "offset":
            out.append(f"mean residual {_fmt(_pooled(rows, 1), u, True)} moving forward and "
                       f"{_fmt(_pooled(rows, -1), u, True)} moving backward")
    if base in ("unbalance", "cogging") and ec.spectrum is not None:
        k = 1 if base == "unbalance" else int(name.split(":")[1])
        a, e = ec.spectrum.at(k)
        txt = (f"order {k} of the rotation-order spectrum: amplitude {_fmt(a, u)} "
               f"({_pct(e)} of the residual variance)")
        if base == "cogging" and name == ec.best_cog:
            others = sorted((nm for nm in ec.cog if nm != name),
                            key=lambda nm: -ec.evaluated[nm]["explained"])
            if others:
                o = others[0]
                txt += (f"; the strongest order of the search k = 2..{ec.ctx.max_order}, next "
                        f"{o.split(':')[1]} ({_pct(ec.evaluated[o]['explained'])})")
        out.append(txt)
    if base == "inertia":
        ab = ec.bins.get("acceleration")
        if ab is not None:
            ok = ab.count >= _MIN_BIN
            if np.any(ok):
                lo_j = int(np.flatnonzero(ok)[0])
                hi_j = int(np.flatnonzero(ok)[-1])
                out.append(f"at {ab.centers[hi_j]:.3g} {ab.unit} the residual is "
                           f"{_fmt(float(ab.mean[hi_j]), u, True)}, at "
                           f"{ab.centers[lo_j]:.3g} {ab.unit} "
                           f"{_fmt(float(ab.mean[lo_j]), u, True)}")
    # the candidate's own column against the residual
    if ev["explained"] > 0:
        out.append(f"explains {100 * ev['explained']:.3g} % of the residual variance "
                   f"(correlation {math.sqrt(ev['explained']):.2f} with its orthogonalised "
                   f"column)")
    vals = ", ".join(f"{k} ≈ {v:.4g} {un}" for k, (v, un) in ev["params"].items())
    if vals:
        out.append(f"would be {vals}")
    return out


# ------------------------------------------------------------------------- structure
def _structure(ctx: _Context, r: F64, used: B, unit: str, h2: float,
               spectrum: OrderSpectrum | None,
               target: str = "current") -> tuple[StructureItem, ...]:
    """Structure of the residual ``r`` (``spectrum``: its order spectrum, if computed).

    The residual is not tested against the equation's own target signal (``target``):
    it holds the target's noise, so its bin means follow the target trivially.
    """
    ru = r[used]
    out: list[StructureItem] = []
    if not len(ru):
        return ()
    energy = float(np.dot(ru, ru))
    if energy <= 0:
        return ()
    mu = float(np.mean(ru))
    tau = 1.0 / h2 if h2 > 0 else 1.0
    sd = float(np.std(ru))
    share_mean = len(ru) * mu * mu / energy
    if share_mean >= MIN_STRUCTURE and abs(mu) >= 4 * sd / math.sqrt(len(ru) / tau):
        out.append(StructureItem("offset", f"a constant offset: mean residual "
                                           f"{_fmt(mu, unit, True)}", share_mean))
    bins = _all_bins(ctx, r, used, unit)
    words = {"speed": "speed-dependent", "position": "position-dependent",
             "current": "current-dependent", "acceleration": "acceleration-dependent",
             "time": "drifting in time"}
    for qn, b in bins.items():
        if b.share < MIN_STRUCTURE or qn == target:
            continue
        ok = b.count >= _MIN_BIN
        c = b.centers[ok]
        m = b.mean[ok]
        jmin, jmax = int(np.argmin(m)), int(np.argmax(m))
        text = (f"{words[qn]}: the mean residual ranges from {_fmt(float(m[jmin]), unit, True)}"
                f" (at {c[jmin]:.3g} {b.unit}) to {_fmt(float(m[jmax]), unit, True)} (at "
                f"{c[jmax]:.3g} {b.unit}); {_pct(b.share)} of the variance")
        out.append(StructureItem(qn, text, b.share))
    if ctx.angle_raw is not None:
        if spectrum is not None:
            orders, expl = spectrum.orders, spectrum.explained
        else:
            orders = _spectrum_orders(ctx.max_order)
            _, expl = _harmonic_fit(ctx, r, used, orders)
        for q in _peaks(orders, expl, 3):
            e = float(expl[int(np.argmin(np.abs(orders - q)))])
            if e < MIN_EXPLAINED:
                continue
            integer = abs(q - round(q)) < 1e-9
            tag = "" if not integer else (
                " (unbalance)" if round(q) == 1 else f" (cogging:{int(round(q))})")
            out.append(StructureItem(
                "periodic", f"periodic at order {q:g} per {ctx.per}{tag}: "
                            f"{_pct(e)} of the variance", e))
    out.sort(key=lambda s: -s.share)
    return tuple(out)


def _verdict(eq: Equation, suggestion: Suggestion, cands: Sequence[Candidate],
             structure: Sequence[StructureItem], model_issues: Sequence[str],
             not_ident: Sequence[Candidate], exc: ExcitationSummary, unit: str,
             rms_ls: float, partial: Suggestion | None = None) -> str:
    name = eq.name
    if suggestion:
        adds = " ".join(f"--add {a}" for a in suggestion.add)
        first = suggestion.steps[0]
        text = (f"{name}: missing {', '.join(suggestion.add)}; {first.effect} explains "
                f"{100 * first.explained:.3g} % of the residual variance. Add it: {adds} "
                f"(predicted residual RMS {_fmt(rms_ls, unit)} -> "
                f"{_fmt(suggestion.rms_after, unit)}).")
        if structure:
            text += " Left after that: " + "; ".join(s.text for s in structure[:2]) + "."
        return text
    parts = []
    if model_issues or not_ident:
        why = list(model_issues)
        if not_ident:
            why.append(f"{', '.join(c.effect for c in not_ident)} cannot be told apart from "
                       f"the model's columns or are not excited")
        facts = exc.facts()
        parts.append(f"{name}: not identifiable from this data: {'; '.join(why)}"
                     + (f" ({'; '.join(facts)})" if facts else "") + ".")
    if structure:
        what = "; ".join(s.text for s in structure[:3])
        if model_issues or not_ident:
            parts.append(f"Structure left in the residual: {what}; it may come from an "
                         f"effect that these data cannot identify.")
        else:
            parts.append(f"{name}: no effect of the library explains the structure left: "
                         f"{what}.")
        if partial:
            tot = 1.0 - (partial.rms_after / partial.rms_before) ** 2 \
                if partial.rms_before > 0 else 0.0
            parts.append(f"The closest candidates ({', '.join(partial.add)}) would explain "
                         f"only {_pct(tot)} of it together.")
    if not parts:
        best = next((c for c in cands if c.identifiable), None)
        tail = (f" (largest: {best.effect}, {_pct(best.explained)})" if best else "")
        parts.append(f"{name}: the model is complete for this data: no effect of the library "
                     f"explains a significant share of the residual{tail}.")
    return " ".join(parts)


# -------------------------------------------------------------------------- traces
def _traces(ctx: _Context, est: EquationEstimator, eb: EquationBlock, r: F64,
            used: B) -> Traces:
    eq = est.equation
    assert eb.phi is not None and eb.theta_fixed is not None
    rows = np.flatnonzero(used)
    n = eq.n
    npts = min(400, len(rows))
    conv_t = np.zeros(0)
    theta = np.zeros((0, n))
    sigma = np.zeros((0, n))
    tfx = np.zeros((0, n))
    if npts:
        # re-run the float RLS on the same rows (bit-identical to the pipeline's) and
        # sample theta and sigma = sqrt(sigma2 diag P) at npts instants
        s = est.settings
        rls = RLS(n, lam=s.lam, alpha=s.alpha, trace_max=s.trace_max)
        phi_u = np.ascontiguousarray(eb.phi[rows])
        y_u = np.ldexp(eb.y[rows], -eq.scaling.target)
        cuts = np.unique(np.linspace(0, len(rows), npts + 1).astype(np.int64))[1:]
        th_l, sd_l = [], []
        a = 0
        for c in cuts:
            rls.run(phi_u[a:c], y_u[a:c], record=False)
            th_l.append(eq.to_physical(np.array(rls.theta)))
            sd_l.append(eq.sigma_to_physical(rls.std()))
            a = int(c)
        k = rows[cuts - 1]
        conv_t = eb.t[k]
        theta = np.array(th_l)
        sigma = np.array(sd_l)
        tfx = eb.theta_fixed[k]
    return Traces(
        t=eb.t, used=used, y=eb.y, yhat=eb.y - r, residual=r, speed=ctx.speed,
        acceleration=ctx.acceleration, current=ctx.current, position=ctx.position,
        angle=ctx.angle, conv_t=conv_t, theta=theta, sigma=sigma, theta_fixed=tfx,
        names=tuple(p.name for p in eq.parameters),
        units=tuple(p.unit for p in eq.parameters))


# ------------------------------------------------------------------------------ text
def _format_equation(q: EquationDiagnosis, axis: str) -> list[str]:
    u = q.unit
    f = q.fit
    out = ["", f"== {q.equation} equation: {q.target} [{u}]", "",
           "Compare (final float estimate over the whole record, filtered equation)",
           f"  residual RMS {_fmt(f.residual_rms, u)}, fit {f.fit_percent:.2f} %, "
           f"R² {f.r2:.5f}, {f.samples} samples"
           f" (fixed point: residual RMS {_fmt(q.residual_rms_fixed, u)})"]
    if q.whiteness is not None:
        out.append(f"  whiteness: {q.whiteness.describe()}")
    out += ["", "Where it fails"]
    if q.regions:
        for reg in q.regions:
            out.append(f"  - {reg.text} ({_pct(reg.share)} of the residual energy)")
    else:
        out.append("  no region stands out: the binned means of the residual are small")
    if q.spectrum is not None and q.spectrum.peaks:
        pk = ", ".join(f"{p:g} ({_fmt(q.spectrum.at(p)[0], u)}, "
                       f"{_pct(q.spectrum.at(p)[1])})" for p in q.spectrum.peaks[:3])
        out.append(f"  rotation-order spectrum peaks (order per {q.spectrum.per}): {pk}")
    facts = q.excitation.facts()
    if facts:
        out.append("  excitation: " + "; ".join(facts))
    out += ["", "Which effect is missing (adding each alone to the model)"]
    if q.candidates:
        w = max(len(c.effect) for c in q.candidates)
        out.append(f"  {'rank':<4}  {'effect':<{w}}  {'explained':>9}  {'ΔBIC':>9}  "
                   f"{'RMS after':>11}")
        steps = {st.effect: (i, st) for i, st in enumerate(q.suggestion.steps)}
        for i, c in enumerate(q.candidates, 1):
            flag = "" if c.identifiable else "  (not identifiable)"
            if c.effect in steps:
                k, st = steps[c.effect]
                flag = "  <- suggested" + (f" (step {k + 1}: {100 * st.explained:.3g} % of what "
                                           f"the steps before leave)" if k else "")
            out.append(f"  {i:<4}  {c.effect:<{w}}  {100 * c.explained:>8.2f}%  "
                       f"{c.delta_bic:>9.4g}  {c.rms_after:>11.4g}{flag}")
            out.append(f"        {c.description}")
            if not c.identifiable:
                out.append(f"        {c.reason}")
            for e in c.evidence[:3]:
                out.append(f"        evidence: {e}")
    else:
        out.append("  no candidate: every effect of the library is in the model")
    for e, r in q.not_applicable:
        out.append(f"  ({e}: {r})")
    if q.structure:
        out += ["", "Structure left " + ("after the suggestion" if q.suggestion else "")]
        for s in q.structure:
            out.append(f"  - {s.text}")
    out += ["", "Verdict: " + q.verdict]
    return out


def _format_before_after(before: Analysis, after: Analysis,
                         added: Sequence[str]) -> list[str]:
    out = [f"== Before and after --add {' --add '.join(added)}", ""]
    bq, aq = before.primary, after.primary
    u = bq.unit

    def white(q: EquationDiagnosis) -> str:
        if q.whiteness is None:
            return "n/a"
        return f"{'white' if q.whiteness.white else 'not white'} ({q.whiteness.outside}/" \
               f"{q.whiteness.lags})"

    rows = [("residual RMS", _fmt(bq.residual_rms, u), _fmt(aq.residual_rms, u)),
            ("fit", f"{bq.fit_percent:.2f} %", f"{aq.fit_percent:.2f} %"),
            ("R²", f"{bq.fit.r2:.5f}", f"{aq.fit.r2:.5f}"),
            ("whiteness", white(bq), white(aq)),
            ("fixed-point RMS", _fmt(bq.residual_rms_fixed, u),
             _fmt(aq.residual_rms_fixed, u))]
    out.append(f"  {'':<16}  {'before':>24}  {'after':>24}")
    for name, x, y in rows:
        out.append(f"  {name:<16}  {x:>24}  {y:>24}")
    out.append("")
    pb = {p.name: p for p in before.estimates.parameters}
    pa = {p.name: p for p in after.estimates.parameters}
    names = list(pb) + [n for n in pa if n not in pb]
    w = max([len(n) for n in names] + [9])
    out.append(f"  {'parameter':<{w}}  {'before ± σ':>26}  {'after ± σ':>26}  "
               f"{'fixed after':>12}  unit")
    for n in names:
        b = pb.get(n)
        a = pa.get(n)
        bs = f"{b.value:.6g} ± {b.sigma:.2g}" if b else "—"
        as_ = f"{a.value:.6g} ± {a.sigma:.2g}" if a else "—"
        fx = f"{a.fixed:.6g}" if a else "—"
        unit = (a or b).unit  # type: ignore[union-attr]
        out.append(f"  {n:<{w}}  {bs:>26}  {as_:>26}  {fx:>12}  {unit}")
    out += ["", "After: " + " ".join(e.verdict for e in after.equations)]
    return out
