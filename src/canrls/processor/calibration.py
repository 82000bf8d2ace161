r"""Samples in, estimates out: :class:`SampleProcessor`, the calibration rule
(:func:`calibrate`, :class:`Calibration`, the defaults and noise measured on the window)
and the pipeline it starts. The rule is written out in docs/architecture.md, "The
calibration rule"."""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
import numpy.typing as npt

from canrls.can.protocol import Protocol
from canrls.core.checks import positive_period
from canrls.core.errors import CheckpointError, ConfigError
from canrls.core.samples import ROLES, Signals
from canrls.core.units import si_unit
from canrls.estimation.estimates import PipelineBlock
from canrls.estimation.model import DATA_OPTIONS, Model
from canrls.estimation.pipeline import Pipeline
from canrls.estimation.selection import SamplePolicy
from canrls.estimation.settings import MIN_ENERGY, RMS_HEADROOM, EstimatorSettings, exponent_for
from canrls.estimation.svf import SVF
from canrls.processor.period import (
    MIN_INTERVALS,
    PERIOD_FRAMES,
    estimate_period,
)

__all__ = ["RESTORE_PERIOD_TOLERANCE", "sample_period", "RangeScanner", "scan_ranges",
           "Calibration", "data_defaults", "measure_noise", "WindowScaling", "calibrate",
           "dbc_ranges", "SampleProcessor"]

#: Signals whose DBC range bounds the normalisation (position enters only through
#: periodic columns, bounded by 1, and is unwrapped beyond its DBC range).
_DBC_ROLES = ("current", "speed", "voltage", "torque")


_SIGNALS = ("t", "current", "speed", "position", "voltage", "torque")


#: Largest relative difference between the control period a restored state ran at and
#: the period of the frames it continues on (two measurements of one drive's period
#: agree far closer; the filters and the statistics of a state depend on the period).
RESTORE_PERIOD_TOLERANCE = 0.01


def sample_period(t: npt.ArrayLike, source: str = "the samples") -> float:
    """The control period of samples at times ``t`` [s], by the rule that measures it on
    frames (:func:`~canrls.processor.period.estimate_period` on the first
    :data:`~canrls.processor.period.PERIOD_FRAMES`): jitter, dropped samples and bursts do
    not move it."""
    times = np.asarray(t, dtype=np.float64)[:PERIOD_FRAMES]
    est = estimate_period({source: times})
    if est is None:
        raise ConfigError(f"{source}: cannot measure the sample period on {len(times)} "
                          f"samples (at least {MIN_INTERVALS + 1} are needed)")
    return positive_period(est.period, source)


class RangeScanner:
    """Accumulates the ranges of the signals (and filtered derivatives) over blocks.

    ``r_x = m max_k |x_k|``, ``r_dw = m max_k |sF[w]_k|`` with a headroom ``m`` (2: one
    bit). The front end does not use it: it builds a model whose ranges fit given
    samples, for a pipeline used on its own (tests, tools).
    """

    def __init__(self, dt: float, cutoff_hz: float, zeta: float, headroom: float = 2.0) -> None:
        self.svf = SVF(cutoff_hz, dt, zeta, ("foh", "zoh"))  # speed (sampled), current (held)
        self.headroom = float(headroom)
        self.peak: dict[str, float] = {}
        self.samples = 0

    def _put(self, key: str, v: float) -> None:
        if math.isfinite(v):
            self.peak[key] = max(self.peak.get(key, 0.0), v)

    def update(self, s: Signals) -> None:
        if len(s) == 0:
            return
        self.samples += len(s)
        for role in ("current", "speed", "voltage", "torque"):
            v = getattr(s, role)
            if v is not None:
                self._put(role, float(np.nanmax(np.abs(v))))
        # a drive reporting only its torque has no current rate (0: no range)
        i = s.current if s.current is not None else np.zeros(len(s))
        _, sf = self.svf.process(np.column_stack([s.speed, i]))
        self._put("acceleration", float(np.nanmax(np.abs(sf[:, 0]))))
        self._put("current_rate", float(np.nanmax(np.abs(sf[:, 1]))))

    def ranges(self) -> dict[str, list[float]]:
        """``{role: [-r, r]}`` for every signal seen with a non-zero peak."""
        out = {}
        for k, v in self.peak.items():
            if v > 0:
                r = self.headroom * v
                out[k] = [-r, r]
        return out


def scan_ranges(blocks: Iterable[Signals], dt: float, cutoff_hz: float, zeta: float,
                headroom: float = 2.0) -> dict[str, list[float]]:
    """Scan blocks of samples and return their ranges (see :class:`RangeScanner`)."""
    sc = RangeScanner(dt, cutoff_hz, zeta, headroom)
    for b in blocks:
        sc.update(b)
    return sc.ranges()


@dataclass(frozen=True)
class Calibration:
    """The front end's one decision about ranges and scaling, frozen after the window.

    Attributes
    ----------
    t_start, t_end : time of the first and last sample of the window [s]
    samples : samples in the window
    ranges : the signal ranges that bound the signals, ``{role: (lo, hi)}``
    sources : where each range comes from: ``"config"``, ``"dbc"`` or ``"default"``
    scaling : ``{equation: {"output": s_y, parameter: s_j}}``, the normalisation's
        exponents
    energy : ``{equation: mean square of each normalised column}`` on the window
    alpha : the ridge weight ``alpha`` (samples' worth of each column in the prior)
    defaults : the model's options scaled from the window (:func:`data_defaults`)
    pending : ``{equation: names}`` the window showed nothing of (:class:`WindowScaling`)
    noise : the measurement noise of each signal on the window (:func:`measure_noise`)
    peaks : the largest magnitude of each signal on the window (SI units of ``axis``):
        what the data showed, from which the scaling comes
    axis : the model's axis (``"rotary"`` or ``"linear"``), for the units of ``peaks``
    """

    t_start: float
    t_end: float
    samples: int
    ranges: dict[str, tuple[float, float]]
    sources: dict[str, str]
    scaling: dict[str, dict[str, int]]
    energy: dict[str, tuple[float, ...]]
    alpha: float
    defaults: dict[str, float] = field(default_factory=dict)
    pending: dict[str, tuple[str, ...]] = field(default_factory=dict)
    noise: dict[str, float] = field(default_factory=dict)
    peaks: dict[str, float] = field(default_factory=dict)
    axis: str = "rotary"

    def to_dict(self) -> dict[str, Any]:
        return {"window": {"t_start": self.t_start, "t_end": self.t_end,
                           "samples": self.samples},
                "ranges": {k: {"range": list(v), "source": self.sources.get(k, "default")}
                           for k, v in self.ranges.items()},
                "scaling": {k: dict(v) for k, v in self.scaling.items()},
                "energy": {k: list(v) for k, v in self.energy.items()},
                "alpha": self.alpha, "defaults": dict(self.defaults),
                "pending": {k: list(v) for k, v in self.pending.items()},
                "noise": dict(self.noise), "peaks": dict(self.peaks), "axis": self.axis}

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> Calibration:
        """Inverse of :meth:`to_dict` (a checkpoint)."""
        w = d["window"]
        return cls(t_start=float(w["t_start"]), t_end=float(w["t_end"]),
                   samples=int(w["samples"]),
                   ranges={k: (float(v["range"][0]), float(v["range"][1]))
                           for k, v in d["ranges"].items()},
                   sources={k: str(v["source"]) for k, v in d["ranges"].items()},
                   scaling={k: {n: int(s) for n, s in v.items()}
                            for k, v in d["scaling"].items()},
                   energy={k: tuple(float(e) for e in v) for k, v in d["energy"].items()},
                   alpha=float(d["alpha"]),
                   defaults={k: float(v) for k, v in d.get("defaults", {}).items()},
                   pending={k: tuple(str(n) for n in v)
                            for k, v in d.get("pending", {}).items()},
                   noise={k: float(v) for k, v in d.get("noise", {}).items()},
                   peaks={k: float(v) for k, v in d.get("peaks", {}).items()},
                   axis=str(d.get("axis", "rotary")))

    def format(self) -> str:
        # what the window showed (the scaling's source), never a DBC's declared limits;
        # ranges stated in the configuration are said as such
        seen = ", ".join(f"{k} ±{v:.4g} {si_unit(k, self.axis)}" for k, v in self.peaks.items())
        given = ", ".join(f"{k} ±{max(abs(lo), abs(hi)):.4g}"
                          for k, (lo, hi) in self.ranges.items()
                          if self.sources.get(k) == "config")
        text = (f"calibration: first {self.samples} samples ({self.t_end - self.t_start:.3g} s)"
                + (f", where the data reach {seen}" if seen else "")
                + (f"; configured ranges {given}" if given else "")
                + f"; ridge alpha {self.alpha:g} x column energy")
        if self.defaults:
            names = {"coulomb_band": "Coulomb band", "stribeck_speed": "Stribeck speed",
                     "pitch": "pitch"}
            text += ("\ndefaults from the data: "
                     + ", ".join(f"{names.get(k, k)} {v:.4g}" for k, v in self.defaults.items())
                     + ("" if "coulomb_band" not in self.defaults else
                        f" (minimum speed 5 bands = {5 * self.defaults['coulomb_band']:.4g})"))
        return text


def window_peaks(window: Signals) -> dict[str, float]:
    """The largest magnitude of each signal the window carries (its finite values)."""
    out = {}
    for role in ROLES:
        v = getattr(window, role)
        if v is not None and len(v) and np.isfinite(v).any():
            out[role] = float(np.max(np.abs(v[np.isfinite(v)])))
    return out


def _round_up_125(x: float) -> float:
    """The smallest of 1, 2, 5 times a power of ten that is at least ``x`` (> 0)."""
    e = math.floor(math.log10(x))
    for m in (1.0, 2.0, 5.0, 10.0):
        if m * 10.0 ** e >= x * (1 - 1e-12):
            return m * 10.0 ** e
    return 10.0 ** (e + 1)  # pragma: no cover


def data_defaults(window: Signals, model: Model) -> tuple[Model, dict[str, float]]:
    r"""The model's options that its configuration does not give
    (:data:`~canrls.estimation.model.DATA_OPTIONS`), scaled from the calibration window
    rather than set in a unit: the defaults of a rotary servo in rad/s would discard a
    linear axis's samples in m/s, and the other way round.

    * Speed noise :math:`\sigma_\omega`: from the second difference of the speed, which
      removes the motion (:math:`\Delta^2\omega` of white noise has variance
      :math:`6\sigma^2`), robustly,
      :math:`\sigma_\omega = 1.4826\,\mathrm{median}|\Delta^2\omega| / \sqrt 6`.
    * Coulomb band (``sgn_e(w) = tanh(w/e)``): :math:`e = 2\sigma_\omega`, at least the
      speed's resolution (the smallest step seen): below it the sign of a measured speed
      is noise. The minimum speed of sign-dependent friction follows (5 bands,
      :class:`~canrls.estimation.selection.SamplePolicy`).
    * Stribeck speed: 1 % of the window's peak speed, at least 2 bands.
    * Pitch (linear axis: metres per period of unbalance and cogging, the longest period
      searched for harmonics): the window's travel rounded up to 1, 2 or 5 times a
      power of ten.

    Returns the model with those options (:meth:`Model.with_options`, now given) and
    ``{option: value}`` of the ones set (recorded in :class:`Calibration`).
    """
    todo = [k for k in DATA_OPTIONS if k not in model.options_given]
    w = window.speed[np.isfinite(window.speed)] if len(window) else np.zeros(0)
    if not todo or len(w) < 16:
        return model, {}
    out: dict[str, float] = {}
    sigma = _robust_noise(np.diff(w))
    steps = np.abs(np.diff(w))
    steps = steps[steps > 0]
    resolution = float(steps.min()) if len(steps) else 0.0
    band = max(2.0 * sigma, resolution)
    if "coulomb_band" in todo and band > 0:
        out["coulomb_band"] = band
    band_used = out.get("coulomb_band", model.coulomb_band)
    peak = float(np.max(np.abs(w)))
    if "stribeck_speed" in todo and peak > 0:
        out["stribeck_speed"] = max(0.01 * peak, 2.0 * band_used)
    if "pitch" in todo and model.axis == "linear" and window.position is not None:
        x = window.position[np.isfinite(window.position)]
        travel = float(np.ptp(x)) if len(x) else 0.0
        if travel > 0:
            out["pitch"] = _round_up_125(travel)
    return (model.with_options(**out) if out else model), out


def _robust_noise(d: npt.NDArray[np.float64]) -> float:
    """The standard deviation of white noise on a signal from its first differences
    ``d``, robust to the signal's own motion: ``1.4826 median|diff(d)| / sqrt(6)`` (the
    second difference of white noise has variance ``6 sigma^2``)."""
    d2 = np.diff(d)
    d2 = d2[np.isfinite(d2)]
    return 1.4826 * float(np.median(np.abs(d2))) / math.sqrt(6.0) if len(d2) else 0.0


def measure_noise(window: Signals, model: Model) -> dict[str, float]:
    """The measurement noise of every signal of the calibration window (standard
    deviation, SI units): :func:`_robust_noise`, at least the rounding of the
    signal's resolution (``q / sqrt(12)``, ``q`` its smallest step) where it is
    quantised. A position is taken across its wrap (the shorter way round)."""
    out: dict[str, float] = {}
    if len(window) < 16:
        return out
    wrap = 2.0 * math.pi if model.axis == "rotary" else model.wrap
    for role in ROLES:
        x = getattr(window, role, None)
        if x is None:
            continue
        d = np.diff(np.asarray(x, dtype=np.float64))
        if role == "position" and wrap:
            d = (d + 0.5 * wrap) % wrap - 0.5 * wrap
        steps = np.abs(d[np.isfinite(d)])
        steps = steps[steps > 0]
        q = float(steps.min()) if len(steps) else 0.0
        out[role] = max(_robust_noise(d), q / math.sqrt(12.0))
    return out


def _frozen_defaults(model: Model, cal: Calibration) -> Model:
    """``model`` with the options a calibration scaled from the data, where not given."""
    todo = {k: v for k, v in cal.defaults.items() if k not in model.options_given}
    return model.with_options(**todo) if todo else model


@dataclass(frozen=True)
class WindowScaling:
    """What :func:`calibrate` decides on a window.

    Attributes
    ----------
    model : the model with the exponents (:meth:`Model.with_scaling`)
    energy : ``{equation: mean square of each normalised column}`` (the prior's scale)
    pending : ``{equation: names}`` of the output (``"output"``) and the columns the
        window shows nothing of (no value other than zero): their exponents and prior
        are provisional, set by the pipeline when the data first show them
    """

    model: Model
    energy: dict[str, tuple[float, ...]]
    pending: dict[str, tuple[str, ...]]
    #: ``{equation: covariance of the noise of the filtered columns}`` (unnormalised;
    #: :meth:`~canrls.estimation.model.RegressorBuilder.noise_covariance`)
    noise: dict[str, npt.NDArray[np.float64]] = field(default_factory=dict)


def calibrate(window: Signals, model: Model, dt: float, settings: EstimatorSettings,
              noise: Mapping[str, float] | None = None) -> WindowScaling:
    r"""The normalisation and the column energies of ``model`` on ``window``.

    The columns and the output are filtered as the pipeline does (same gap filling and
    sample selection) and measured over the rows it uses (all rows where it uses none).
    The exponent of each (``phi_j = F[.] 2**-s_j``), unless the model gives it
    (``[model.scaling]``, or frozen by an earlier calibration):

    * a column bounded by its own function (``tanh``, ``sin``, a constant, a user term
      with a configured range; :attr:`Equation.intrinsic`): the exponent of its bound, so that
      no value can saturate, whatever the window showed;
    * the output and every other column: the smallest exponent that puts the window's
      RMS at most 1/:data:`RMS_HEADROOM` of full scale, from the data alone (a declared
      range never enters); one the window shows nothing of (only zeros) is *pending*:
      the pipeline sets its exponent and prior where it first sees a value
      (:class:`~canrls.estimation.pipeline.EquationEstimator`), and rescales any column
      exactly when it later outgrows its exponent.

    The energy :math:`\bar e_j` is the window's mean square of the normalised column:
    in :math:`(2^{-10}, 2^{-8}]` for a data-scaled column; at least :data:`MIN_ENERGY`
    for a column bounded by its own function (which data never exceed) or pending;
    configured exponents take the energy as it is. With ``noise`` (the signals'
    measurement noise, :func:`measure_noise`), each equation's column noise covariance
    on the window (the estimator's errors-in-variables bias, :mod:`canrls.estimation.pipeline`).
    """
    probe = Pipeline(model, dt, settings, adapt=False)
    block = probe.process(window, record=True)
    exponents: dict[str, dict[str, int]] = {}
    energy: dict[str, tuple[float, ...]] = {}
    pending: dict[str, tuple[str, ...]] = {}
    for eq, b in zip(model.equations, block.equations, strict=True):
        sc = eq.scaling
        phi = b.phi if b.phi is not None else np.zeros((0, eq.n))
        rows = b.used if np.any(b.used) else np.ones(len(phi), np.bool_)
        # the output and every column in physical units, on the rows used
        y = b.y[rows]
        cols = np.ldexp(phi[rows], np.array(sc.columns, dtype=np.int64))
        # exponents the model gives (configured, or frozen by an earlier calibration) stay
        given = model.exponents.get(eq.name, {})
        waiting: list[str] = []
        if "output" in given:
            s_y = sc.output
        else:
            s = _scale_exponent(y)
            s_y = sc.output if s is None else s
            if s is None:
                waiting.append("output")
        own = eq.intrinsic
        s_cols, e_cols = [], []
        for j, par in enumerate(eq.parameters):
            c = cols[:, j]
            floor = MIN_ENERGY
            if par.name in given:
                s, floor = sc.columns[j], 0.0
            elif own[j]:
                s = sc.columns[j]
            else:
                found = _scale_exponent(c)
                s = sc.columns[j] if found is None else found
                if found is None:
                    waiting.append(par.name)
            # e_j = mean_k (c_kj 2**-s_j)^2
            e = float(np.mean(np.ldexp(c, -s) ** 2)) if len(c) else 0.0
            s_cols.append(s)
            e_cols.append(max(e, floor))
        exponents[eq.name] = {"output": s_y,
                              **{p.name: s for p, s in zip(eq.parameters, s_cols, strict=True)}}
        energy[eq.name] = tuple(e_cols)
        pending[eq.name] = tuple(waiting)
    cov = {}
    if noise:
        w = np.abs(window.speed)
        for eq in model.equations:
            pol = SamplePolicy.for_equation(eq, dt, settings)
            cov[eq.name] = eq.builder(dt).noise_covariance(
                window, noise, (w >= pol.min_speed) & (w <= pol.max_speed))
    return WindowScaling(model.with_scaling(exponents), energy, pending, cov)


def _scale_exponent(x: npt.NDArray[np.float64]) -> int | None:
    """Smallest s with RMS_HEADROOM rms(x) <= 2**s; None when ``x`` holds no value
    other than zero (nothing to scale from)."""
    rms = float(np.sqrt(np.mean(x * x))) if len(x) else 0.0
    if not (rms > 0 and math.isfinite(rms)):
        return None
    return exponent_for(rms, RMS_HEADROOM)


def dbc_ranges(model: Model, protocol: Protocol) -> dict[str, tuple[float, float]]:
    """The DBC's range (:meth:`Protocol.signal_range`) of every mapped signal whose
    range the model's configuration does not give."""
    dbc: dict[str, tuple[float, float]] = {}
    for role in _DBC_ROLES:
        if protocol.has(role) and role not in model.ranges_given:
            r = protocol.signal_range(role)
            if r is not None and r[0] < r[1]:
                dbc[role] = r
    return dbc


class SampleProcessor:
    """Samples in, estimates out: the calibration rule (docs/architecture.md) and the pipeline.

    :class:`FrameProcessor` feeds it the samples it decodes and pairs; a diagnosis or a
    simulation feeds it samples directly, with the same result for the same samples.

    Parameters
    ----------
    model, dt, settings : the model (its ranges not in
        :attr:`~canrls.estimation.model.Model.ranges_given` are measured on the window),
        the control period [s] and the estimator settings
    start : ``Pipeline(model, dt, settings)`` as built for an earlier stream and never
        run, shared (:meth:`FrameProcessor._sampler`): this processor builds its own
        only when it first runs one (a stream whose first block fills the window never
        does: the calibration builds the pipeline it runs)
    """

    def __init__(self, model: Model, dt: float, settings: EstimatorSettings | None = None,
                 sources: Mapping[str, str] | None = None, *,
                 start: Pipeline | None = None) -> None:
        self._sources = dict(sources) if sources is not None else {
            k: ("config" if k in model.ranges_given else "default") for k in model.ranges}
        self._start = start
        self._pipeline = Pipeline(model, dt, settings or EstimatorSettings()) \
            if start is None else None
        #: the frozen calibration (None while the window is being collected)
        self.calibration: Calibration | None = None
        self._held: list[Signals] = []
        self._held_n = 0
        self._window: Signals | None = None
        self._calibrate_n = max(1, int(round(self.settings.calibration_s / self.dt)))

    @property
    def pipeline(self) -> Pipeline:
        """The pipeline samples run through (built from the shared start when first
        asked for)."""
        if self._pipeline is None:
            s = self._start
            assert s is not None
            self._pipeline = Pipeline(s.model, s.dt, s.settings)
        return self._pipeline

    @pipeline.setter
    def pipeline(self, pipeline: Pipeline) -> None:
        self._pipeline = pipeline

    @property
    def _current(self) -> Pipeline:
        """The pipeline, or the shared start it would be built from (read only)."""
        p = self._pipeline if self._pipeline is not None else self._start
        assert p is not None
        return p

    @property
    def settings(self) -> EstimatorSettings:
        """The estimator settings: the pipeline's, which a command may change (lambda)."""
        return self._current.settings

    @property
    def calibrating(self) -> bool:
        """True while samples are held back for the calibration window."""
        return self.calibration is None

    @property
    def dt(self) -> float:
        return self._current.dt

    @property
    def model(self) -> Model:
        return self._current.model

    @property
    def window(self) -> Signals | None:
        """The calibration window's samples (None before the calibration)."""
        return self._window

    def with_model(self, model: Model) -> Pipeline:
        """Switch to ``model`` (an effect added or removed): its ranges are the frozen
        ones, its column energies measured on the stored window, and the parameters both
        models share start from their estimates (:meth:`Pipeline.with_model`)."""
        if self.calibration is None or self._window is None:
            self.pipeline = self.pipeline.with_model(model, warm=False)
            return self.pipeline
        model = _frozen_defaults(model, self.calibration)
        ws = calibrate(self._window, model.with_ranges(self.calibration.ranges),
                       self.dt, self.settings, self.calibration.noise)
        # the ranges stay frozen; the scaling, energies and pending columns are the new
        # model's (what the target's path and a checkpoint take from the calibration)
        self.calibration = replace(
            self.calibration, scaling={k: dict(v) for k, v in ws.model.exponents.items()},
            energy=ws.energy, pending=ws.pending)
        self.pipeline = self.pipeline.with_model(ws.model, energy=ws.energy,
                                                 pending=ws.pending, noise=ws.noise)
        return self.pipeline

    def state(self) -> dict[str, Any]:
        """What a checkpoint needs to continue: the control period ``dt`` [s] the state
        ran at, the frozen calibration and its window (or the samples held so far), and
        the pipeline's state."""
        window = self._window if self.calibration is not None else Signals.concat(self._held)
        return {"dt": self.dt,
                "calibration": None if self.calibration is None else self.calibration.to_dict(),
                "window": {k: v for k in _SIGNALS if (v := getattr(window, k)) is not None},
                "pipeline": self.pipeline.state()}

    def restore(self, state: Mapping[str, Any], model: Model) -> None:
        """Continue from :meth:`state` with ``model`` (the model that was running).

        :raises CheckpointError: the state ran at another control period (its ``dt``
            differs from this processor's by more than :data:`RESTORE_PERIOD_TOLERANCE`).
        """
        dt = state.get("dt")  # None: a state of canrls 0.1, which did not record it
        if dt is not None and not (
                isinstance(dt, int | float) and dt > 0
                and abs(dt - self.dt) <= RESTORE_PERIOD_TOLERANCE * self.dt):
            raise CheckpointError(f"the state ran at a control period of {dt!r} s, the frames "
                                  f"give {self.dt * 1e3:.6g} ms")
        w = state["window"]
        window = Signals.from_roles({k: np.asarray(w[k], dtype=np.float64)
                                     for k in _SIGNALS if k in w})
        cal = state.get("calibration")
        if cal is None:
            self.calibration, self._window = None, None
            self._held, self._held_n = ([window], len(window)) if len(window) else ([], 0)
            self.pipeline = Pipeline(model, self.dt, self.settings)
        else:
            self.calibration, self._window = Calibration.from_dict(cal), window
            model = _frozen_defaults(model, self.calibration)
            self._held, self._held_n = [], 0
            self.pipeline = Pipeline(model, self.dt, self.settings, self.calibration.energy,
                                     self.calibration.pending)
        self.pipeline.restore(state["pipeline"])

    def process(self, samples: Signals, record: bool = False) -> PipelineBlock:
        """Feed a block of samples (any size); held back while the window fills."""
        if self.calibration is not None:
            return self.pipeline.process(samples, record)
        if len(samples):
            self._held.append(samples)
            self._held_n += len(samples)
        if self._held_n < self._calibrate_n:
            return self.pipeline.process(samples.slice(0, 0), record)
        return self._finish_calibration(record)

    def finish(self, record: bool = False) -> PipelineBlock:
        """End of stream: a calibration still collecting uses what it has."""
        if self.calibration is None and self._held:
            return self._finish_calibration(record)
        return self.pipeline.process(Signals.concat([]), record)

    def run(self, samples: Signals, record: bool = False) -> PipelineBlock:
        """A whole stream at once (calibration included): one block of every sample."""
        out = self.process(samples, record)
        return self.finish(record) if self.calibration is None else out

    def _finish_calibration(self, record: bool) -> PipelineBlock:
        held = Signals.concat(self._held)
        self._held, self._held_n = [], 0
        window = held.slice(0, min(len(held), self._calibrate_n))
        model, defaults = data_defaults(window, self.model)
        noise = measure_noise(window, model)
        ws = calibrate(window, model, self.dt, self.settings, noise)
        model, energy = ws.model, ws.energy
        t = window.t
        self.calibration = Calibration(
            t_start=float(t[0]) if len(t) else math.nan,
            t_end=float(t[-1]) if len(t) else math.nan, samples=len(window),
            ranges={k: (float(lo), float(hi)) for k, (lo, hi) in model.ranges.items()},
            sources=dict(self._sources),
            scaling={k: dict(v) for k, v in model.exponents.items()},
            energy=energy, alpha=float(self.settings.alpha), defaults=defaults,
            pending=ws.pending, noise=noise, peaks=window_peaks(window), axis=model.axis)
        self._window = window
        self.pipeline = Pipeline(model, self.dt, self.settings, energy, ws.pending, ws.noise)
        return self.pipeline.process(held, record)
