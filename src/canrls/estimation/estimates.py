"""What the pipeline returns: the estimates of the parameters and the fit of each
equation (:class:`Estimates`), and what one block did (:class:`PipelineBlock`)."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt

from canrls.estimation.physics import Implausible, check_physics, describe
from canrls.estimation.sigma_inflation import MAX_PRIOR_SHARE

__all__ = [
    "DIVERGENCE_TOL",
    "Rescale",
    "used_rows",
    "ParameterEstimate",
    "EquationFit",
    "Estimates",
    "EquationBlock",
    "PipelineBlock",
    "divergence",
]

F64 = npt.NDArray[np.float64]


#: default tolerance of ``canrls fixed-sweep``); beyond it ``canrls fit`` says so.
DIVERGENCE_TOL = 1e-3


def divergence(theta: Sequence[float], fixed: Sequence[float], sigma: Sequence[float]) -> float:
    """Fixed point against float: ``max_j |fixed_j - theta_j| / max(|theta_j|, 3 sigma_j)``.

    A NaN sigma (not known yet) counts as 0, a zero or NaN reference as 1; a NaN
    difference makes the result NaN; no parameter gives 0. Pure Python: for the few
    parameters of a model this is several times faster than numpy.
    """
    worst = 0.0
    for th, fx, sd in zip(theta, fixed, sigma, strict=True):
        ref = abs(th)
        if 3.0 * sd > ref:
            ref = 3.0 * sd
        if not ref > 0:
            ref = 1.0
        d = abs(fx - th) / ref
        if math.isnan(d):
            return math.nan
        worst = max(worst, d)
    return worst


@dataclass(frozen=True)
class ParameterEstimate:
    """One physical parameter: float reference, fixed point, standard deviation."""

    name: str
    unit: str
    effect: str
    equation: str
    description: str
    value: float
    sigma: float
    fixed: float
    #: share of the variance the ridge prior still holds (:func:`~canrls.estimation.
    #: colour.prior_share`): above :data:`~canrls.estimation.sigma_inflation.MAX_PRIOR_SHARE` the
    #: data cannot tell the parameter from the others, and value and sigma are the prior's
    prior_share: float = 0.0
    #: how far the model's errors (noise in the columns' signals, the hold between
    #: samples, reversals) can pull the estimate
    #: (:meth:`~canrls.estimation.pipeline.EquationEstimator.bias`): part of ``sigma``,
    #: ``sigma**2 = (statistical sigma)**2 + bias**2``
    bias: float = 0.0
    #: the measurement noise could explain what the data show of the parameter's columns:
    #: the data cannot identify it
    #: (:meth:`~canrls.estimation.pipeline.EquationEstimator.bias`)
    noise_bound: bool = False

    @property
    def identifiable(self) -> bool:
        return self.prior_share <= MAX_PRIOR_SHARE and not self.noise_bound

    @property
    def why_not(self) -> str:
        """Why the data cannot identify it ("" when they can)."""
        if self.prior_share > MAX_PRIOR_SHARE:
            return f"{100 * self.prior_share:.0f} % prior"
        return "noise explains it" if self.noise_bound else ""

    def to_dict(self) -> dict[str, Any]:
        return {"value": self.value, "sigma": self.sigma, "unit": self.unit,
                "fixed": self.fixed, "effect": self.effect, "equation": self.equation,
                "description": self.description, "identifiable": self.identifiable,
                "prior_share": self.prior_share, "bias": self.bias,
                "noise_bound": self.noise_bound}


@dataclass(frozen=True)
class Rescale:
    """One change of an equation's normalisation during a run: a column or the output
    outgrew its exponent (``grew``), or a pending one showed its first value (``first``)."""

    t: float
    name: str
    old: int
    new: int
    why: str

    def to_dict(self) -> dict[str, Any]:
        return {"t": self.t, "name": self.name, "old": self.old, "new": self.new,
                "why": self.why}


@dataclass(frozen=True)
class EquationFit:
    """How well one equation fits, with the final estimate over all used samples."""

    equation: str
    output: str
    unit: str
    samples: int
    residual_rms: float
    fit_percent: float
    r2: float
    output_rms: float
    online_rms: float
    divergence: float
    saturations: Mapping[str, int]
    windup_steps: int
    low_excitation: bool
    condition: float
    #: samples whose output or a column was not finite: left out, with the filter's
    #: warm-up after each (see :class:`~canrls.estimation.model.RegressorBuilder`)
    nonfinite_rows: int = 0
    #: factor the residual's colour puts on the variances (kappa >= 1; the sigmas
    #: reported are multiplied by its square root; :mod:`canrls.estimation.sigma_inflation`)
    sigma_inflation: float = 1.0
    #: the normalisation's exponents at the end (``{"output": s_y, parameter: s_j}``)
    exponents: Mapping[str, int] = field(default_factory=dict)
    #: how often the normalisation changed during the run, and the first changes
    rescale_count: int = 0
    rescales: tuple[Rescale, ...] = ()
    #: the output and columns the data have not shown yet (exponent and prior provisional)
    pending: tuple[str, ...] = ()
    #: the fixed point's word lengths (``W32/A64/I32``)
    fixed_config: str = ""

    def to_dict(self) -> dict[str, Any]:
        return {"equation": self.equation, "output": self.output, "unit": self.unit,
                "samples": self.samples, "residual_rms": self.residual_rms,
                "fit_percent": self.fit_percent, "r2": self.r2,
                "output_rms": self.output_rms, "online_rms": self.online_rms,
                "divergence": self.divergence, "saturations": dict(self.saturations),
                "windup_steps": self.windup_steps, "low_excitation": self.low_excitation,
                "condition": self.condition, "nonfinite_rows": self.nonfinite_rows,
                "sigma_inflation": self.sigma_inflation, "exponents": dict(self.exponents),
                "rescale_count": self.rescale_count,
                "rescales": [r.to_dict() for r in self.rescales],
                "pending": list(self.pending), "fixed_config": self.fixed_config}


@dataclass(frozen=True)
class Estimates:
    """The estimates of every parameter and the fit of every equation."""

    parameters: tuple[ParameterEstimate, ...]
    equations: tuple[EquationFit, ...]
    effects: tuple[str, ...]
    #: the torque constant the model was given (checked against a back-EMF constant)
    kt: float | None = None

    @property
    def implausible(self) -> tuple[Implausible, ...]:
        """Parameters physics rules out, with the likely cause (:func:`check_physics`)."""
        return check_physics(self.parameters, self.kt)

    @property
    def residual_rms(self) -> float:
        """Residual RMS of the first (mechanical) equation, in its output unit."""
        return self.equations[0].residual_rms if self.equations else math.nan

    @property
    def fit_percent(self) -> float:
        return self.equations[0].fit_percent if self.equations else math.nan

    @property
    def samples(self) -> int:
        return self.equations[0].samples if self.equations else 0

    def with_fixed(self, fixed: Mapping[str, float],
                   saturations: Mapping[str, Mapping[str, int]] | None = None) -> Estimates:
        """These estimates with another fixed-point column (``fixed``: by parameter name,
        NaN for one it lacks; ``canrls fit``'s and the daemon's from the target's integer
        path): each equation's divergence from the float again, and its ``saturations``
        where given (by equation)."""
        params = tuple(dataclasses.replace(p, fixed=fixed.get(p.name, math.nan))
                       for p in self.parameters)
        fits = []
        for fit in self.equations:
            mine = [p for p in params if p.equation == fit.equation]
            div = divergence([p.value for p in mine], [p.fixed for p in mine],
                             [p.sigma if math.isfinite(p.sigma) else 0.0 for p in mine])
            sat = fit.saturations if saturations is None else saturations.get(
                fit.equation, fit.saturations)
            fits.append(dataclasses.replace(fit, divergence=div, saturations=sat))
        return dataclasses.replace(self, parameters=params, equations=tuple(fits))

    def __getitem__(self, name: str) -> ParameterEstimate:
        for p in self.parameters:
            if p.name == name:
                return p
        raise KeyError(f"no parameter {name!r} (have: {[p.name for p in self.parameters]})")

    def to_dict(self) -> dict[str, Any]:
        return {
            "effects": list(self.effects),
            "parameters": {p.name: p.to_dict() for p in self.parameters},
            "residual_rms": self.residual_rms,
            "fit_percent": self.fit_percent,
            "samples": self.samples,
            "equations": {e.equation: e.to_dict() for e in self.equations},
            "implausible": [i.to_dict() for i in self.implausible],
        }

    def format(self) -> str:
        """A text table: every parameter with float value, sigma, fixed value and unit."""
        lines = []
        w = max([len(p.name) for p in self.parameters] + [9])
        lines.append(f"{'parameter':<{w}}  {'float':>13}  {'± sigma':>11}  {'fixed':>13}  unit")
        for p in self.parameters:
            lines.append(f"{p.name:<{w}}  {p.value:>13.6g}  {p.sigma:>11.3g}  {p.fixed:>13.6g}"
                         f"  {p.unit}"
                         + ("" if p.identifiable else f"  NOT IDENTIFIABLE ({p.why_not})"))
        weak = [p.name for p in self.parameters if p.prior_share > MAX_PRIOR_SHARE]
        if weak:
            lines.append(f"not identifiable from these data: {', '.join(weak)}: the data "
                         f"cannot tell {'them' if len(weak) > 1 else 'it'} from the other "
                         f"parameters, value and sigma are the prior's (e.g. Coulomb "
                         f"friction and an offset while the speed never reverses; "
                         f"'canrls diagnose' names the experiment)")
        noisy = [p.name for p in self.parameters
                 if p.noise_bound and p.prior_share <= MAX_PRIOR_SHARE]
        if noisy:
            lines.append(f"not identifiable from these data: {', '.join(noisy)}: the "
                         f"measurement noise of the signals could explain what the data "
                         f"show of {'them' if len(noisy) > 1 else 'it'} (too little motion "
                         f"for the noise: a longer or faster run)")
        lines.extend(describe(self.implausible))
        for e in self.equations:
            lines.append(
                f"{e.equation}: residual RMS {e.residual_rms:.4g} {e.unit}, "
                f"fit {e.fit_percent:.2f} %,"
                f" R² {e.r2:.5f}, {e.samples} samples, fixed-vs-float divergence "
                f"{e.divergence:.2e}"
                + (", saturations " + ", ".join(f"{k} {v}" for k, v in e.saturations.items())
                   if e.saturations else "")
                + (", LOW EXCITATION" if e.low_excitation else "")
                + (f", {e.nonfinite_rows} samples with a non-finite term left out "
                   f"(with the filter's warm-up after each)" if e.nonfinite_rows else ""))
            if e.divergence > DIVERGENCE_TOL:
                lines.append(
                    f"{e.equation}: the fixed point ({e.fixed_config or 'its words'}) is "
                    f"{e.divergence:.2g} from the float, more than {DIVERGENCE_TOL:g}: these "
                    f"word lengths cannot follow the float on these data; 'canrls "
                    f"fixed-sweep' with the same log and options names the configuration "
                    f"that does")
        return "\n".join(lines)

    __str__ = format


@dataclass(frozen=True)
class EquationBlock:
    """What one block did to one equation (recorded with ``record=True``).

    ``y`` and ``eps``/``eps_fixed`` are in the output unit; ``theta``/``theta_fixed``
    are physical parameters after each sample; ``used`` marks the rows that updated
    the estimators (not in a warm-up).
    """

    equation: str
    t: F64
    y: F64
    eps: F64
    eps_fixed: F64
    used: npt.NDArray[np.bool_]
    online_rms: F64
    flags: npt.NDArray[np.uint8]
    theta: F64 | None
    theta_fixed: F64 | None
    phi: F64 | None
    #: where the normalisation changed in the block: ``(row, d_columns, d_target)``;
    #: ``phi`` rows from ``row`` on are in the new one (:func:`used_rows`)
    changes: tuple[tuple[int, tuple[int, ...], int], ...] = ()


def used_rows(blocks: Sequence[EquationBlock], output: int) -> tuple[F64, F64]:
    """The used rows ``(phi, y)`` of one equation's recorded blocks, normalised as at
    the end of the last block (``output``: the output's exponent then)."""
    n = next((b.phi.shape[1] for b in blocks if b.phi is not None), 0)
    later = np.zeros(n, np.int64)  # the column exponents' change after a row
    parts = []
    for b in reversed(blocks):
        if b.phi is None:
            continue
        phi = b.phi.copy()
        end = len(phi)
        for row, d, _ in reversed(b.changes):
            np.ldexp(phi[row:end], -later, out=phi[row:end])
            later = later + np.asarray(d, np.int64)
            end = row
        np.ldexp(phi[:end], -later, out=phi[:end])
        parts.append((phi[b.used], np.ldexp(b.y[b.used], -output)))
    parts.reverse()
    if not parts:
        return np.zeros((0, n)), np.zeros(0)
    return np.concatenate([p for p, _ in parts]), np.concatenate([y for _, y in parts])


@dataclass(frozen=True)
class PipelineBlock:
    """Per-equation results of one :meth:`~canrls.estimation.pipeline.Pipeline.process` call."""

    samples: int
    equations: tuple[EquationBlock, ...]
