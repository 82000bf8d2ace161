"""Feedforward from an identified model: the torque its effects need at a position and speed.

:func:`feedforward` keeps the mechanical effects a drive can compensate from position and
speed alone (Coulomb, viscous, Stribeck, offset, unbalance, cogging, user terms of
position or speed), only where the data support them (identifiable, sigma within a
stated share), and gives the anticogging map, the harmonics and the ripple before and
after compensation with its uncertainty. Formulas and assumptions: docs/tune.md.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt

from canrls.control.tune_limits import DEFAULT_SHARE, MAX_POINTS
from canrls.core.checks import in_range, is_real
from canrls.core.errors import ConfigError
from canrls.estimation.effects import MECHANICAL, Effect, Frame
from canrls.estimation.model import Model

__all__ = ["Term", "Harmonic", "Ripple", "Feedforward",
           "feedforward", "check_points"]

F64 = npt.NDArray[np.float64]

#: Points per revolution on which the ripple of the position terms is computed.
RIPPLE_POINTS = 4096
#: The signal roles a feedforward may read: the drive's own position and speed.
FEEDFORWARD_ROLES = frozenset({"position", "speed"})


def check_points(n: Any, what: str = "--points") -> int:
    """``n``, the points of a map per revolution: an integer in [2, :data:`MAX_POINTS`]."""
    if isinstance(n, bool) or not isinstance(n, int) or not 2 <= n <= MAX_POINTS:
        raise ConfigError(f"{what} {n!r}: the points of a map per revolution must be an "
                          f"integer from 2 to {MAX_POINTS}")
    return n


@dataclass(frozen=True)
class Term:
    """One effect of the model, compensated or left out (``reason`` says why)."""

    effect: str
    parameters: tuple[str, ...]
    values: tuple[float, ...]
    sigmas: tuple[float, ...]
    reads: frozenset[str]
    used: bool
    reason: str = ""

    @property
    def of_position(self) -> bool:
        """Its torque depends on the position alone (or on nothing: the offset)."""
        return "speed" not in self.reads

    def to_dict(self) -> dict[str, Any]:
        return {"effect": self.effect, "used": self.used, "reason": self.reason,
                "reads": sorted(self.reads),
                "parameters": {p: {"value": v, "sigma": s} for p, v, s in
                               zip(self.parameters, self.values, self.sigmas, strict=True)}}


@dataclass(frozen=True)
class Harmonic:
    """``a_sin sin(k phi) + a_cos cos(k phi)`` of the position map; ``phi`` the angle."""

    order: int
    sin: float
    cos: float

    @property
    def amplitude(self) -> float:
        # A_k = sqrt(a_sin^2 + a_cos^2)
        return math.hypot(self.sin, self.cos)

    @property
    def phase(self) -> float:
        """``A_k sin(k phi + phase)`` [rad]."""
        # a_sin sin + a_cos cos = A sin(k phi + atan2(a_cos, a_sin))
        return math.atan2(self.cos, self.sin)

    def to_dict(self) -> dict[str, Any]:
        return {"order": self.order, "sin": self.sin, "cos": self.cos,
                "amplitude": self.amplitude, "phase": self.phase}


@dataclass(frozen=True)
class Ripple:
    """RMS over a revolution of the position-dependent torque, before and after
    compensation, each with its standard deviation from the parameters' sigma."""

    before: float
    before_sigma: float
    after: float
    after_sigma: float

    @property
    def reduction(self) -> float:
        """Share of the ripple the compensation removes (0..1; nan without ripple)."""
        return 1.0 - self.after / self.before if self.before > 0 else math.nan

    def describe(self, unit: str) -> str:
        """``0.00238 ± 3.5e-06 -> 4.88e-06 ± 2.4e-06 N·m RMS (-99.8 %)``"""
        return (f"{self.before:.3g} ± {self.before_sigma:.2g} -> {self.after:.3g} ± "
                f"{self.after_sigma:.2g} {unit} RMS ({-100 * self.reduction:+.1f} %)")

    def to_dict(self) -> dict[str, Any]:
        return {"before": self.before, "before_sigma": self.before_sigma,
                "after": self.after, "after_sigma": self.after_sigma,
                "reduction": self.reduction}


@dataclass(frozen=True)
class Feedforward:
    """The compensation a model supports: its terms, evaluated at a position and speed."""

    model: Model
    terms: tuple[Term, ...]
    unit: str
    share: float
    ripple: Ripple | None
    _effects: Mapping[str, Effect] = field(repr=False, compare=False)

    @property
    def used(self) -> tuple[Term, ...]:
        return tuple(t for t in self.terms if t.used)

    @property
    def left_out(self) -> tuple[Term, ...]:
        return tuple(t for t in self.terms if not t.used)

    @property
    def has_map(self) -> bool:
        """There is a position term to put in a map (the model reads the position)."""
        return any(t.of_position and "position" in t.reads for t in self.terms)

    @property
    def period(self) -> float:
        """The position of one turn of the map: 2 pi rad, or the pitch [m] (linear)."""
        return 2.0 * math.pi if self.model.axis == "rotary" else float(self.model.pitch)

    def _signals_at(self, position: npt.ArrayLike, speed: F64) -> Frame:
        pos = np.ascontiguousarray(position, dtype=np.float64)
        return Frame(t=np.zeros(len(pos)), current=None, speed=speed, position=pos,
                     angle=Frame.phase(pos, self.model.axis, self.model.pitch))

    def _sum(self, terms: tuple[Term, ...], position: npt.ArrayLike, speed: F64) -> F64:
        frame = self._signals_at(position, speed)
        out = np.zeros(len(frame.t))
        for t in terms:
            for col, v in zip(self._effects[t.effect].columns(), t.values, strict=True):
                # tau_ff += theta_j * phi_j(position, speed)
                out = out + v * col.raw(frame)
        return out

    def torque(self, position: npt.ArrayLike, speed: npt.ArrayLike) -> F64:
        r"""The feedforward :math:`\tau_{ff}(\vartheta, \omega) = \sum_j \theta_j
        \phi_j(\vartheta, \omega)` over the compensated terms, in :attr:`unit`."""
        p, w = np.broadcast_arrays(np.asarray(position, dtype=np.float64),
                                   np.asarray(speed, dtype=np.float64))
        return self._sum(self.used, p.ravel(), w.ravel()).reshape(p.shape)

    def position_map(self, points: int) -> tuple[F64, F64]:
        """The anticogging map: ``points`` positions over one revolution (pitch) from 0
        and the torque of the compensated position terms there (offset included)."""
        check_points(points)
        if not self.has_map:
            raise ConfigError("no anticogging map: " + self.no_map_reason())
        pos = np.arange(points, dtype=np.float64) * (self.period / points)
        terms = tuple(t for t in self.used if t.of_position)
        return pos, self._sum(terms, pos, np.zeros(points))

    def no_map_reason(self) -> str:
        return ("the model has no term of the position (the log had no position signal, "
                "or no unbalance, cogging or position user term was identified)")

    def harmonics(self) -> tuple[Harmonic, ...]:
        """The compensated position terms as harmonics of the angle (unbalance: order 1,
        cogging:k: order k; a user term of the position by its Fourier series on
        :data:`RIPPLE_POINTS` points, orders whose amplitude is at least 1e-6 of the
        largest). The offset is order 0 (``cos`` holds it)."""
        acc: dict[int, list[float]] = {}
        for t in self.used:
            if not t.of_position:
                continue
            name = t.effect.split(":", 1)[0]
            if name in ("unbalance", "cogging"):
                k = 1 if name == "unbalance" else int(t.effect.split(":", 1)[1])
                a = acc.setdefault(k, [0.0, 0.0])
                a[0] += t.values[0]
                a[1] += t.values[1]
            elif name == "offset":
                acc.setdefault(0, [0.0, 0.0])[1] += t.values[0]
            else:
                n = RIPPLE_POINTS
                ang = np.arange(n) * (2.0 * math.pi / n)
                pos = ang * (self.period / (2.0 * math.pi))
                f = self._sum((t,), pos, np.zeros(n))
                c = np.fft.rfft(f) / n  # f = sum_k 2 Re(c_k e^{i k ang}), c_0 once
                big = float(np.max(np.abs(c))) if len(c) else 0.0
                for k, ck in enumerate(c[: n // 2]):
                    if big > 0 and abs(ck) >= 1e-6 * big:
                        a = acc.setdefault(k, [0.0, 0.0])
                        a[0] += 0.0 if k == 0 else -2.0 * float(ck.imag)
                        a[1] += float(ck.real) * (1.0 if k == 0 else 2.0)
        return tuple(Harmonic(k, s, c) for k, (s, c) in sorted(acc.items()))

    def to_dict(self, points: int | None = None) -> dict[str, Any]:
        """The feedforward file (``canrls tune --out``): what ``canrls sim --feedforward``
        and a drive load; the map when ``points`` is given and the model has one."""
        m = self.model
        # the speed terms, and the offset when there is no map to hold it
        speed_terms = {p: v for t in self.used
                       if not t.of_position or (t.effect == "offset" and not self.has_map)
                       for p, v in zip(t.parameters, t.values, strict=True)}
        d: dict[str, Any] = {
            "format": "canrls-feedforward", "version": 1, "unit": self.unit,
            "axis": m.axis, "pitch": float(m.pitch), "kt": m.kt, "share": self.share,
            "speed": {"parameters": speed_terms, "coulomb_band": float(m.coulomb_band),
                      "stribeck_speed": float(m.stribeck_speed),
                      "user": [t.effect for t in self.used
                               if not t.of_position and t.effect.startswith("user:")]},
            "harmonics": [h.to_dict() for h in self.harmonics()],
            "terms": [t.to_dict() for t in self.terms],
            "ripple": None if self.ripple is None else self.ripple.to_dict()}
        if points is not None and self.has_map:
            pos, tau = self.position_map(points)
            d["map"] = {"points": points, "period": self.period,
                        "position": pos.tolist(), "torque": tau.tolist()}
        return d


def _judge(eff: Effect, params: Mapping[str, Mapping[str, Any]], share: float,
           source: str) -> Term:
    """One effect of a saved model, used or left out with the reason."""
    names = tuple(p.name for p in eff.parameters(True))
    for n in names:
        if n not in params:
            raise ConfigError(f"{source}: parameters.{n}: missing (the model's effect "
                              f"{eff.name} has it)")
    values = tuple(float(params[n]["value"]) for n in names)
    sigmas = tuple(math.nan if params[n].get("sigma") is None else float(params[n]["sigma"])
                   for n in names)
    reads = frozenset(r for c in eff.columns() for r in c.reads)

    def term(used: bool, reason: str = "") -> Term:
        return Term(eff.name, names, values, sigmas, reads, used, reason)

    other = reads - FEEDFORWARD_ROLES
    if other:
        return term(False, f"depends on {', '.join(sorted(other))}, not on position or "
                           f"speed alone")
    bad = [n for n in names if params[n].get("identifiable") is False]
    if bad:
        return term(False, f"{', '.join(bad)} NOT IDENTIFIABLE")
    # the size of a term and its sigma: sqrt(sum theta_j^2), sqrt(sum sigma_j^2)
    size = math.sqrt(sum(v * v for v in values))
    sigma = math.sqrt(sum(s * s for s in sigmas))
    if not math.isfinite(sigma):
        return term(False, "no sigma in the model file")
    if not sigma <= share * size:
        rel = sigma / size if size > 0 else math.inf
        return term(False, f"sigma {sigma:.3g} is {rel:.0%} of its size {size:.3g}, "
                           f"above the share {share:.0%}")
    return term(True)


def _ripple(ff: Feedforward) -> Ripple | None:
    r"""RMS of the AC part of the position torque over a revolution, before (every
    identified position term) and after compensation (the terms left out, plus the
    estimation error of those used): :math:`E[r^2] = \overline{(\sum_{out} \theta_j
    g_j)^2} + \sum_{used} \sigma_j^2 \overline{g_j^2}` (sigma independent)."""
    terms = [t for t in ff.terms if t.of_position and "position" in t.reads
             and not t.effect.startswith("offset")]
    if not terms:
        return None
    n = RIPPLE_POINTS
    pos = np.arange(n) * (ff.period / n)
    frame = ff._signals_at(pos, np.zeros(n))
    cols: list[tuple[Term, float, float, F64]] = []
    for t in terms:
        for col, v, s in zip(ff._effects[t.effect].columns(), t.values, t.sigmas,
                             strict=True):
            g = col.raw(frame)
            cols.append((t, v, 0.0 if math.isnan(s) else s, g - g.mean()))
    total = sum((v * g for _, v, _, g in cols), np.zeros(n))
    out = sum((v * g for t, v, _, g in cols if not t.used), np.zeros(n))
    before = float(np.sqrt(np.mean(total**2)))
    out_ms = float(np.mean(out**2))
    err_ms = sum(s * s * float(np.mean(g**2)) for t, _, s, g in cols if t.used)
    after = math.sqrt(out_ms + err_ms)

    def sigma_of(rms: float, signal: F64, which: list[tuple[Term, float, float, F64]]) -> float:
        # R = sqrt(mean(s^2)): dR/dtheta_j = mean(g_j s) / R
        if rms <= 0:
            return 0.0
        return math.sqrt(sum((float(np.mean(g * signal)) / rms * s) ** 2
                             for _, _, s, g in which))

    before_sigma = sigma_of(before, total, cols)
    out_cols = [c for c in cols if not c[0].used]
    # the left-out part's uncertainty, and the spread of the error term (half its size)
    after_sigma = math.hypot(sigma_of(math.sqrt(out_ms), out, out_cols) if out_ms > 0
                             else 0.0, 0.5 * math.sqrt(err_ms))
    return Ripple(before, before_sigma, after, after_sigma)


def feedforward(model: Model, parameters: Mapping[str, Mapping[str, Any]], *,
                share: float = DEFAULT_SHARE, source: str = "model") -> Feedforward:
    """The feedforward a model's parameters (name -> ``value``, ``sigma``,
    ``identifiable``, as a saved model holds them) support; ``share`` the largest
    sigma of a compensated term as a share of its size."""
    if not in_range(share, 0, 1, lo_open=True):
        raise ConfigError(f"--share {share!r}: must be a number in (0, 1]")
    for name, p in parameters.items():
        for key in ("value", "sigma"):
            v = p.get(key)
            if v is not None and not is_real(v):
                raise ConfigError(f"{source}: parameters.{name}.{key} = {v!r}: must be a "
                                  f"finite number")
    effects = {e.name: e for e in model.effects
               if e.equation == MECHANICAL and e.name != "inertia"}
    terms = tuple(_judge(e, parameters, share, source) for e in effects.values())
    unit = "N·m" if model.axis == "rotary" else "N"
    if not model.torque_known:
        unit = "A"
    ff = Feedforward(model, terms, unit, share, None, effects)
    return Feedforward(model, terms, unit, share, _ripple(ff), effects)
