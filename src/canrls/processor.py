r"""The front end shared by the live daemon and the offline replay.

``frames -> strict decode -> pairing -> samples -> calibration -> Pipeline``

:class:`FrameProcessor` takes :class:`~canrls.can.frameblock.FrameBlock` objects of any
size, so a log replayed offline (``canrls fit``, ``canrls diagnose``) gives the same
parameters as the daemon (``canrls run``, ``canrls demo``) fed the same frames, bit for
bit. It is the one place that decides the signal ranges, the normalisation of the
regressors and the scale of the ridge prior, by one causal rule that a live stream
follows as well as a log:

The calibration rule
--------------------
1. The first ``calibration_s`` seconds of samples (``[estimator] calibration_s``,
   default 2 s; counted in control periods) are held back: the *calibration window*.
2. Signal ranges: a range given in the configuration (``[model.ranges]``; the model's
   :attr:`~canrls.estimation.model.Model.ranges_given`) is kept; every other range is
   measured on the window by :class:`RangeScanner` (below); a signal the window does not
   show keeps its default. The normalisation of every column follows from the ranges.
3. Column energies: the mean square :math:`\bar e_j` of every normalised column over
   the window's rows that the pipeline uses (:func:`column_energy`). The ridge prior is
   scaled with them, :math:`P_0 = \mathrm{diag}(1/(\alpha\,\bar e_j))`
   (:meth:`~canrls.estimation.pipeline.EstimatorSettings.ridge`): its penalty
   :math:`\alpha\sum_j \bar e_j\theta_j^2` is ``alpha`` times the mean square of each
   term :math:`\theta_j\varphi_j`, the same in any normalisation. So the ranges, whoever
   chose them, change rounding, never the answer; and the prior weighs like ``alpha``
   samples of data (default 0.01) whatever the run length.
4. The result (:class:`Calibration`) is frozen and recorded: in ``canrls fit``'s text
   and JSON, in the daemon's checkpoint. The estimators then start on the held
   samples, so none is lost. A model changed later (an effect added live) gets the
   energies of its columns on the same stored window.

Measuring ranges on samples
---------------------------
:class:`RangeScanner` (and :func:`scan_ranges`) measure the ranges a block of samples
reaches, including the filtered derivatives (acceleration, current rate):
``r_x = m max_k |x_k|``, ``r_dw = m max_k |sF[w]_k|`` with a headroom ``m`` (2: one
bit). The front end does not use them (its rule above needs no pass over the data);
they build a model whose ranges fit given samples, for a pipeline used on its own
(tests, tools).
"""

from __future__ import annotations

import dataclasses
import datetime
import logging
import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt

from canrls.can.frameblock import FrameBlock
from canrls.can.pairing import Pairer, PairingCounts
from canrls.can.period import (
    MIN_INTERVALS,
    PERIOD_FRAMES,
    PeriodEstimate,
    PeriodMeter,
    check_period,
    estimate_period,
    positive_period,
)
from canrls.can.protocol import DecodedFrames, Protocol, RejectCounts
from canrls.can.reorder import Reorderer
from canrls.can.times import TimeJudge
from canrls.can.units import Ratings
from canrls.errors import CheckpointError, ConfigError
from canrls.estimation.model import DATA_OPTIONS, Model
from canrls.estimation.pipeline import (
    MIN_ENERGY,
    RMS_HEADROOM,
    Estimates,
    EstimatorSettings,
    Pipeline,
    PipelineBlock,
    exponent_for,
)
from canrls.estimation.selection import SamplePolicy
from canrls.estimation.svf import SVF
from canrls.signals import ROLES, Signals

__all__ = ["AxisInfo", "Calibration", "FileShift", "FitResult", "FrameCounts", "FrameProcessor",
           "MIN_ENERGY", "PeriodInfo", "RESTORE_PERIOD_TOLERANCE", "RMS_HEADROOM", "RangeScanner",
           "SEEN_IDS", "SampleProcessor", "StartInfo", "WindowScaling", "calibrate",
           "data_defaults", "dbc_ranges", "epoch_date", "measure_noise", "positive_period",
           "sample_period", "scan_ranges"]

log = logging.getLogger(__name__)

#: Signals whose DBC range bounds the normalisation (position enters only through
#: periodic columns, bounded by 1, and is unwrapped beyond its DBC range).
_DBC_ROLES = ("current", "speed", "voltage", "torque")

_SIGNALS = ("t", "current", "speed", "position", "voltage", "torque")


#: The period of the placeholder estimator of a :class:`FrameProcessor` whose period is
#: still being measured (no sample ever reaches it).
_PLACEHOLDER_DT = 1e-3

#: Largest relative difference between the control period a restored state ran at and
#: the period of the frames it continues on (two measurements of one drive's period
#: agree far closer; the filters and the statistics of a state depend on the period).
RESTORE_PERIOD_TOLERANCE = 0.01

#: Most distinct frame IDs counted while none of the mapped messages has come (for the
#: error that names the most frequent ones): beyond, the rarest are forgotten, so a bus
#: of random IDs cannot grow the daemon's memory.
SEEN_IDS = 1024


@dataclass(frozen=True)
class FrameCounts:
    """What became of the frames of a stream: how many, rejected by reason, lost,
    foreign, and the pairing's counts (running totals over every restart)."""

    total: int = 0
    #: frames rejected, by reason (every reason), and the earliest example of each
    rejected: dict[str, int] = field(default_factory=dict)
    examples: dict[str, str] = field(default_factory=dict)
    #: frames lost (counter gaps), by message
    lost: dict[str, int] = field(default_factory=dict)
    #: frames of messages the mapping does not use
    foreign: int = 0
    #: the pairing's counts (:meth:`~canrls.can.pairing.PairingCounts.as_dict`)
    pairing: dict[str, int] = field(default_factory=dict)
    #: decoded frames of each mapped message
    messages: dict[str, int] = field(default_factory=dict)
    #: a mapped message that never came, said (:meth:`FrameProcessor.missing_messages`)
    missing: str | None = None
    #: unparsable log lines skipped (``--skip-bad-lines``)
    bad_lines: int = 0

    def __add__(self, other: FrameCounts) -> FrameCounts:
        """The counts of two parts of a stream; the first part's examples first."""
        def add(a: Mapping[str, int], b: Mapping[str, int]) -> dict[str, int]:
            out = dict(a)
            for k, v in b.items():
                out[k] = out.get(k, 0) + int(v)
            return out

        examples = dict(self.examples)
        for k, v in other.examples.items():
            examples.setdefault(k, v)
        return FrameCounts(self.total + other.total, add(self.rejected, other.rejected),
                           examples, add(self.lost, other.lost),
                           self.foreign + other.foreign, add(self.pairing, other.pairing),
                           add(self.messages, other.messages), self.missing or other.missing,
                           self.bad_lines + other.bad_lines)

    def to_dict(self, detail: bool = False, period: PeriodInfo | None = None,
                start: StartInfo | None = None) -> dict[str, Any]:
        """As ``canrls fit --json`` has them (``detail``: also the frames of each
        message, a missing message and the lines skipped, and with the ``period`` and
        ``start`` given, as a diagnosis and a validation have them)."""
        d: dict[str, Any] = {"total": self.total, "rejected": dict(self.rejected),
                             "lost": dict(self.lost), "foreign": self.foreign,
                             "pairing": dict(self.pairing)}
        if detail:
            d["messages"] = dict(self.messages)
            if self.missing:
                d["missing"] = self.missing
            if self.bad_lines:
                d["bad_lines"] = self.bad_lines
        if period is not None:
            d["period"] = period.to_dict()
        if start is not None:
            d["start"] = start.to_dict()
        return d


@dataclass(frozen=True)
class PeriodInfo:
    """The control period used, who stated it and what the frames measured."""

    value: float | None
    #: ``"measured"``, or who stated it (``"--period 0.001"``, the DBC)
    source: str = "measured"
    measured: float | None = None
    jitter: float | None = None
    intervals: int | None = None

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    def format(self) -> str | None:
        """``control period 1 ms (measured on the timestamps)`` (None: no period)."""
        if not self.value:
            return None
        how = ("measured on the timestamps" if self.source == "measured" else
               f"from {self.source}"
               + (f", timestamps say {self.measured * 1e3:.6g} ms" if self.measured else ""))
        return f"control period {self.value * 1e3:.6g} ms ({how})"


@dataclass(frozen=True)
class StartInfo:
    """The first frame's timestamp, its date (UTC) when it is an epoch time, and whether
    the times reported are relative to it."""

    t0: float | None = None
    date: str | None = None
    relative: bool = False

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    def format(self) -> str | None:
        return (f"log starts {self.date}; times below are from that start"
                if self.date else None)


@dataclass(frozen=True)
class AxisInfo:
    """The model's axis, the DBC units it was read from, the ratings relative units refer
    to and, on a drive that reports its torque, the target."""

    axis: str
    dbc_axis: str | None = None
    units: dict[str, str | None] = field(default_factory=dict)
    ratings: dict[str, float] = field(default_factory=dict)
    target: str | None = None

    def to_dict(self) -> dict[str, Any]:
        d = dataclasses.asdict(self)
        if self.target is None:
            del d["target"]
        return d

    def format(self) -> list[str]:
        units = ", ".join(f"{r} {u}" for r, u in self.units.items() if u)
        lines = [f"axis {self.axis}" + (f" (DBC units: {units})" if units else "")]
        if self.ratings:
            lines.append("ratings: " + Ratings(**self.ratings).describe(self.axis))
        if self.target:
            lines.append(f"mechanical target: {self.target}")
        return lines


@dataclass(frozen=True)
class FileShift:
    """One log of several fitted as one record, and the time it was moved by [s]."""

    path: str
    time_shift_s: float


@dataclass(frozen=True)
class FitResult:
    """What a replay produced: the estimates and what happened to the frames."""

    estimates: Estimates
    frames: FrameCounts
    source: str
    model: Model
    period: PeriodInfo
    start: StartInfo
    axis: AxisInfo
    calibration: Calibration | None = None
    #: the logs of a fit of several, each with its time shift
    files: tuple[FileShift, ...] = ()

    @property
    def parameters(self) -> Any:
        return self.estimates.parameters

    @property
    def residual_rms(self) -> float:
        return self.estimates.residual_rms

    @property
    def fit_percent(self) -> float:
        return self.estimates.fit_percent

    def to_dict(self) -> dict[str, Any]:
        d = self.estimates.to_dict()
        d.update({
            "source": self.source,
            "frames": self.frames.to_dict(),
            "unit": self.estimates.equations[0].unit if self.estimates.equations else None,
            "calibration": None if self.calibration is None else self.calibration.to_dict(),
            "period": self.period.to_dict(), "start": self.start.to_dict(),
            "axis": self.axis.to_dict(),
        })
        if self.frames.bad_lines:
            d["bad_lines"] = self.frames.bad_lines
        if self.files:
            d["files"] = [dataclasses.asdict(f) for f in self.files]
        return d

    def format(self) -> str:
        fr = self.frames
        lines = [f"{self.source}: {fr.total} frames, {self.estimates.samples} samples used"]
        lines += [x for x in (self.start.format(),) if x]
        lines += self.axis.format()
        lines += [x for x in (self.period.format(),) if x]
        rej = sum(fr.rejected.values())
        if rej:
            lines.append(f"rejected frames: {rej} ("
                         + ", ".join(f"{k} {v}" for k, v in fr.rejected.items() if v) + ")")
            for k, ex in fr.examples.items():
                lines.append(f"  e.g. {k}: {ex}")
        if any(fr.lost.values()):
            lines.append("lost frames (counter gaps): "
                         + ", ".join(f"{k} {v}" for k, v in fr.lost.items() if v))
        odd = {k: v for k, v in fr.pairing.items() if v and k != "samples"}
        if odd:
            lines.append("pairing: " + ", ".join(f"{k} {v}" for k, v in odd.items()))
        if self.calibration is not None:
            lines.append(self.calibration.format())
        lines.append(self.estimates.format())
        return "\n".join(lines)

    __str__ = format


def epoch_date(t: float | None) -> str | None:
    """``"2023-11-14 22:13:20.123456 UTC"`` for a timestamp that is an epoch time (after
    1973), else None (a log whose times start near zero)."""
    if t is None or not (1e8 < t < 1e11):
        return None
    d = datetime.datetime.fromtimestamp(t, tz=datetime.UTC)
    return d.strftime("%Y-%m-%d %H:%M:%S.%f UTC")


def sample_period(t: npt.ArrayLike, source: str = "the samples") -> float:
    """The control period of samples at times ``t`` [s], by the rule that measures it on
    frames (:func:`~canrls.can.period.estimate_period` on the first
    :data:`~canrls.can.period.PERIOD_FRAMES`): jitter, dropped samples and bursts do
    not move it."""
    times = np.asarray(t, dtype=np.float64)[:PERIOD_FRAMES]
    est = estimate_period({source: times})
    if est is None:
        raise ConfigError(f"{source}: cannot measure the sample period on {len(times)} "
                          f"samples (at least {MIN_INTERVALS + 1} are needed)")
    return positive_period(est.period, source)


class RangeScanner:
    """Accumulates the ranges of the signals (and filtered derivatives) over blocks."""

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
    scaling : ``{equation: {"target": s_y, parameter: s_j}}``, the normalisation's
        exponents
    energy : ``{equation: mean square of each normalised column}`` on the window
    alpha : the ridge weight ``alpha`` (samples' worth of each column in the prior)
    defaults : the model's options scaled from the window (:func:`data_defaults`)
    pending : ``{equation: names}`` the window showed nothing of (:class:`WindowScaling`)
    noise : the measurement noise of each signal on the window (:func:`measure_noise`)
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

    def to_dict(self) -> dict[str, Any]:
        return {"window": {"t_start": self.t_start, "t_end": self.t_end,
                           "samples": self.samples},
                "ranges": {k: {"range": list(v), "source": self.sources.get(k, "default")}
                           for k, v in self.ranges.items()},
                "scaling": {k: dict(v) for k, v in self.scaling.items()},
                "energy": {k: list(v) for k, v in self.energy.items()},
                "alpha": self.alpha, "defaults": dict(self.defaults),
                "pending": {k: list(v) for k, v in self.pending.items()},
                "noise": dict(self.noise)}

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
                   noise={k: float(v) for k, v in d.get("noise", {}).items()})

    def format(self) -> str:
        rng = ", ".join(f"{k} ±{max(abs(lo), abs(hi)):.4g} ({self.sources.get(k, 'default')})"
                        for k, (lo, hi) in self.ranges.items()
                        if self.sources.get(k) != "default")
        text = (f"calibration: first {self.samples} samples ({self.t_end - self.t_start:.3g} s)"
                f"; ranges {rng or 'all default'}; ridge alpha {self.alpha:g} x column energy")
        if self.defaults:
            names = {"coulomb_band": "Coulomb band", "stribeck_speed": "Stribeck speed",
                     "pitch": "pitch"}
            text += ("\ndefaults from the data: "
                     + ", ".join(f"{names.get(k, k)} {v:.4g}" for k, v in self.defaults.items())
                     + ("" if "coulomb_band" not in self.defaults else
                        f" (minimum speed 5 bands = {5 * self.defaults['coulomb_band']:.4g})"))
        return text


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
    pending : ``{equation: names}`` of the target (``"target"``) and the columns the
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

    The columns and the target are filtered as the pipeline does (same gap filling and
    sample selection) and measured over the rows it uses (all rows where it uses none).
    The exponent of each (``phi_j = F[.] 2**-s_j``), unless the model gives it
    (``[model.scaling]``, or frozen by an earlier calibration):

    * a column bounded by its own function (``tanh``, ``sin``, a constant, a user term
      with a configured range; :attr:`Equation.intrinsic`): the exponent of its bound, so that
      no value can saturate, whatever the window showed;
    * the target and every other column: the smallest exponent that puts the window's
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
        # the target and every column in physical units, on the rows used
        y = b.y[rows]
        cols = np.ldexp(phi[rows], np.array(sc.columns, dtype=np.int64))
        # exponents the model gives (configured, or frozen by an earlier calibration) stay
        given = model.exponents.get(eq.name, {})
        waiting: list[str] = []
        if "target" in given:
            s_y = sc.target
        else:
            s = _scale_exponent(y)
            s_y = sc.target if s is None else s
            if s is None:
                waiting.append("target")
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
        exponents[eq.name] = {"target": s_y,
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
    """Samples in, estimates out: the calibration rule (module docstring) and the pipeline.

    :class:`FrameProcessor` feeds it the samples it decodes and pairs; a diagnosis or a
    simulation feeds it samples directly, with the same result for the same samples.

    Parameters
    ----------
    model, dt, settings : the model (its ranges not in
        :attr:`~canrls.estimation.model.Model.ranges_given` are measured on the window),
        the control period [s] and the estimator settings
    """

    def __init__(self, model: Model, dt: float, settings: EstimatorSettings | None = None,
                 sources: Mapping[str, str] | None = None) -> None:
        self._sources = dict(sources) if sources is not None else {
            k: ("config" if k in model.ranges_given else "default") for k in model.ranges}
        self.pipeline = Pipeline(model, dt, settings or EstimatorSettings())
        #: the frozen calibration (None while the window is being collected)
        self.calibration: Calibration | None = None
        self._held: list[Signals] = []
        self._held_n = 0
        self._window: Signals | None = None
        self._calibrate_n = max(1, int(round(self.settings.calibration_s / self.pipeline.dt)))

    @property
    def settings(self) -> EstimatorSettings:
        """The estimator settings: the pipeline's, which a command may change (lambda)."""
        return self.pipeline.settings

    @property
    def calibrating(self) -> bool:
        """True while samples are held back for the calibration window."""
        return self.calibration is None

    @property
    def dt(self) -> float:
        return self.pipeline.dt

    @property
    def model(self) -> Model:
        return self.pipeline.model

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
            pending=ws.pending, noise=noise)
        self._window = window
        self.pipeline = Pipeline(model, self.dt, self.settings, energy, ws.pending, ws.noise)
        return self.pipeline.process(held, record)


class FrameProcessor:
    """Frames in, estimates out: decoder, pairer and :class:`SampleProcessor`, all stateful.

    Used by the offline replay (blocks of a log) and by the daemon (blocks of the frames
    that arrived), with the same calibration rule (module docstring) and the same
    control period rule (docs/architecture.md, "Control period"): the period is measured
    on the first :data:`~canrls.can.period.PERIOD_FRAMES` frames of each mapped message
    (:class:`~canrls.can.period.PeriodMeter`); a stated period (``period``, else the
    protocol's: ``[can] period``/``--period``, else the DBC's ``GenMsgCycleTime``) is used
    from the first frame and must agree with the measured one within 10 %; without one
    the decoded frames are held until the period is measured, then paired. This is the
    one place that decides the period.

    Parameters
    ----------
    protocol, model, settings : what to decode and estimate
    period : control period [s] (default: the protocol's, else measured)
    period_source : who states ``period`` (named in errors; default the protocol's)
    relative_time : times relative to the first frame's (:attr:`origin`): a log of
        ``candump -l`` carries epoch timestamps (1.7e9 s), which text and figures would
        show as such. The subtraction is exact (two doubles within a factor of two), so
        the estimates are the same either way.
    """

    def __init__(self, protocol: Protocol, model: Model,
                 settings: EstimatorSettings | None = None,
                 period: float | None = None, period_source: str | None = None, *,
                 relative_time: bool = False) -> None:
        self.protocol = protocol
        self.relative_time = bool(relative_time)
        #: the first frame's timestamp [s] (None before it; with ``relative_time`` the
        #: times of samples and results are relative to it)
        self.origin: float | None = None
        self.decoder = protocol.decoder()
        #: judges every frame's receive time first (:mod:`canrls.can.times`): frames
        #: without a time, or out of line with the stream, are rejected (``time``)
        self.times = TimeJudge()
        #: puts frames swapped on the way back in counter order before the decoder
        #: (:mod:`canrls.can.reorder`; ``reorder.moved`` counts them)
        self.reorder = Reorderer(protocol.messages)
        self.frames = 0
        #: frames of each mapped message that decoded, so far
        self.message_frames: dict[str, int] = {m.name: 0 for m in protocol.messages}
        stated = period if period is not None else protocol.period
        #: who states the period (None: measured)
        self.period_source: str | None = (
            (period_source or "the period given") if period is not None
            else protocol.period_source if stated is not None else None)
        if period is not None:  # the protocol's own was checked when it was loaded
            stated = positive_period(period, str(self.period_source))
        self._model0, self._settings0 = model, settings
        self._meter: PeriodMeter | None = PeriodMeter([m.name for m in protocol.messages])
        #: the period measured on the first frames (None until then, or too few frames)
        self.period_estimate: PeriodEstimate | None = None
        self._held: list[DecodedFrames] = []
        self._seen_ids: dict[int, int] = {}
        #: the counts of the parts before the last :meth:`restart`
        self._past = FrameCounts()
        self._restore: tuple[Mapping[str, Any], Model, Model] | None = None
        #: why a state restored before the period was measured was dropped once it was
        #: (it ran at another period); None: none was
        self.restore_refused: str | None = None
        self.pairer: Pairer | None = None
        if stated is not None:
            self._start(float(stated))
        else:
            # a placeholder until the period is measured: no sample reaches it, so its
            # period is never used (the daemon may publish its empty state meanwhile)
            self.sampler = SampleProcessor(model, _PLACEHOLDER_DT, settings)

    def _sampler(self, model: Model, period: float) -> SampleProcessor:
        dbc = dbc_ranges(model, self.protocol)
        sources = {k: ("config" if k in model.ranges_given else "dbc" if k in dbc else
                       "default") for k in model.ranges}
        return SampleProcessor(model.with_ranges(dbc) if dbc else model, period,
                               self._settings0, sources)

    def _start(self, period: float) -> None:
        """Pairer and sample processor for the decided period."""
        self.pairer = Pairer(self.protocol, period=period)
        if self._restore is not None:  # a checkpoint restored while the period was measured
            state, model, before = self._restore
            self._restore = None
            self.sampler = self._sampler(model, self.pairer.period)
            try:
                self.sampler.restore(state, model)
                return
            except CheckpointError as e:  # another period: as if there were no checkpoint
                self.restore_refused = str(e)
                log.warning("restored state dropped, estimation starts afresh with the "
                            "configured model: %s", e)
                self._model0 = before
        self.sampler = self._sampler(self._model0, self.pairer.period)

    @property
    def period(self) -> float | None:
        """The control period [s] pairing uses (None while it is being measured)."""
        return None if self.pairer is None else self.pairer.period

    def _measured(self) -> None:
        """The meter has its frames (or the stream ended): check or adopt the period."""
        assert self._meter is not None
        est = self._meter.estimate()
        counts = self._meter.counts()
        self._meter = None
        self.period_estimate = est
        if self.pairer is not None:
            if est is not None:
                check_period(self.pairer.period, self.period_source or "the period", est)
            return
        if est is None:
            if not any(counts.values()):
                raise self._foreign_error()
            raise ConfigError(
                "cannot measure the control period: the log has only "
                + ", ".join(f"{n} frames of {m}" for m, n in counts.items())
                + f" (at least {MIN_INTERVALS + 1} of one message are needed); "
                  "state it with --period SECONDS")
        self._start(est.period)

    def missing_messages(self) -> str | None:
        """What to say when some mapped messages decoded frames and others none (a
        sample needs them all): each missing one with its ID and roles, and the frames
        of the others; None when every mapped message occurred (or none did)."""
        counts = self.message_frames
        if not any(counts.values()):
            return None
        missing = [m for m in self.protocol.messages if counts[m.name] == 0]
        if not missing:
            return None
        roles = {m.name: [r for r, i in self.protocol.roles.items() if i.message == m.name]
                 for m in missing}
        what = ", ".join(f"{m.name} (0x{m.frame_id:X}: {', '.join(roles[m.name])})"
                         for m in missing)
        seen = ", ".join(f"{n} {c} frames" for n, c in counts.items() if c)
        return (f"mapped message{'s' if len(missing) > 1 else ''} {what} never "
                f"occur{'' if len(missing) > 1 else 's'} in the {self.frames} frames read "
                f"(seen: {seen}): a sample needs every mapped message; map the signal to "
                f"a message the drive sends, or leave its role out")

    def _count_ids(self, block: FrameBlock) -> None:
        """Frames of each ID, while no mapped message has come; at most :data:`SEEN_IDS`
        IDs are kept (the most frequent: the rarest are forgotten when twice as many)."""
        ids, n = np.unique(block.arbitration_id, return_counts=True)
        seen = self._seen_ids
        for i, k in zip(ids.tolist(), n.tolist(), strict=True):
            seen[i] = seen.get(i, 0) + k
        if len(seen) > 2 * SEEN_IDS:
            keep = sorted(seen.items(), key=lambda kv: -kv[1])[:SEEN_IDS]
            self._seen_ids = dict(keep)

    def seen_ids(self, most: int = 8) -> list[tuple[int, int]]:
        """The most frequent frame IDs counted while no mapped message has come, with
        their frames: ``[(id, frames), ...]`` (at most ``most``; of at most
        :data:`SEEN_IDS` IDs kept)."""
        return sorted(self._seen_ids.items(), key=lambda kv: (-kv[1], kv[0]))[:most]

    def _foreign_error(self) -> ConfigError:
        """None of the mapped messages was decoded: name what was expected and seen."""
        want = ", ".join(f"0x{m.frame_id:X} ({m.name})" for m in self.protocol.messages)
        seen = self.seen_ids()
        seen_text = ", ".join(f"0x{i:X} ({n})" for i, n in seen) if seen else "none"
        rej = {k: int(v) for k, v in self.decoder.rejected.items() if v}
        why = ("; rejected: " + ", ".join(f"{k} {v}" for k, v in rej.items())) if rej else ""
        return ConfigError(
            f"none of the mapped messages occurs in the {self.frames} frames read: expected "
            f"{want} (DBC {self.protocol.dbc_path.name}); most frequent IDs seen "
            f"(frames): {seen_text}{why}. Map the right messages with --signal "
            f"ROLE=MESSAGE.SIGNAL or give the drive's DBC with --dbc")

    @property
    def pipeline(self) -> Pipeline:
        return self.sampler.pipeline

    @property
    def settings(self) -> EstimatorSettings:
        return self.sampler.settings

    @property
    def calibration(self) -> Calibration | None:
        return self.sampler.calibration

    @property
    def calibrating(self) -> bool:
        return self.sampler.calibrating

    @property
    def dt(self) -> float:
        return self.sampler.dt

    @property
    def model(self) -> Model:
        return self.sampler.model

    def with_model(self, model: Model) -> Pipeline:
        """:meth:`SampleProcessor.with_model` (before the period is known: the model the
        sample processor will start with, once the switch succeeded)."""
        pipeline = self.sampler.with_model(model)
        if self.pairer is None:
            self._model0 = model
        return pipeline

    def state(self) -> dict[str, Any]:
        """:meth:`SampleProcessor.state` (the decoder and pairer restart after a restore)."""
        return self.sampler.state()

    def restore(self, state: Mapping[str, Any], model: Model) -> None:
        """:meth:`SampleProcessor.restore`. Before the period is known, the state is
        restored at the period it records (its estimates are published meanwhile), and
        again once the period is measured; a state that ran at another period is then
        dropped with a warning (:attr:`restore_refused`) and estimation starts afresh
        with the model given before the restore, as without a checkpoint."""
        if self.pairer is None:
            dt = state.get("dt")
            placeholder = SampleProcessor(model, _PLACEHOLDER_DT if dt is None else dt,
                                          self._settings0)
            placeholder.restore(state, model)
            before = self._restore[2] if self._restore is not None else self._model0
            self._restore = (state, model, before)
            self._model0 = model
            self.sampler = placeholder
            return
        self.sampler.restore(state, model)

    def samples(self, block: FrameBlock) -> Signals:
        """Decode and pair one block of frames (no estimation)."""
        base = self.frames
        self.frames += len(block)
        judged = self.times.push(block)  # first: a frame without a time is no frame
        self._count_time_rejects(base)
        return self._through(judged)

    def _through(self, block: FrameBlock) -> Signals:
        """Frames whose times were judged: reordered, decoded and paired."""
        if self.origin is None and len(block):
            self.origin = float(block.t[0])
        if self.relative_time and self.origin:
            block = dataclasses.replace(block, t=block.t - self.origin)
        # frames swapped on the way put back in counter order, before the strict checks
        return self._paired(self.decoder.decode(self.reorder.push(block)), block)

    def _count_time_rejects(self, key: int) -> None:
        """Count the frames :attr:`times` rejected last, under ``time``, per mapped
        message (other frames under ``*``); ``key``: the stream position for the example."""
        bad = self.times.rejected()
        if bad is None:
            return
        example = self.times.counts.example
        rej = self.decoder.rejected
        left = np.ones(len(bad), np.bool_)
        for m in self.protocol.messages:
            mine = (left & (bad.arbitration_id == m.frame_id) & (bad.is_extended == m.is_extended)
                    & ~bad.is_error)
            if mine.any():
                rej.add("time", m.name, int(mine.sum()), example, key)
                left &= ~mine
        if left.any():
            rej.add("time", "*", int(left.sum()), example, key)

    def _paired(self, decoded: DecodedFrames, block: FrameBlock) -> Signals:
        """The period meter, then pairing, of one decoded ``block``."""
        for name, m in decoded.messages.items():
            self.message_frames[name] += len(m.t)
        if self._meter is not None:
            times = {name: decoded.messages[name].t for name in decoded.messages}
            self._meter.add(times)
            if not any(self._meter.counts().values()) and len(block):
                self._count_ids(block)
            if self._meter.done:
                self._measured()
        if self.pairer is None:
            if any(len(m.t) for m in decoded.messages.values()):  # a foreign bus: nothing
                self._held.append(decoded)
            return Signals.concat([])
        return self._push(decoded)

    def _push(self, decoded: DecodedFrames | None) -> Signals:
        """Pair the held blocks (if any), then ``decoded`` (None: the end of stream)."""
        assert self.pairer is not None
        held, self._held = self._held, []
        parts = [self.pairer.push(d) for d in held]
        parts.append(self.pairer.push(decoded) if decoded is not None else self.pairer.flush())
        if len(parts) == 1:
            return parts[0]
        return Signals.concat([p for p in parts if len(p)]) if any(len(p) for p in parts) \
            else parts[-1]

    def flush_samples(self) -> Signals:
        """End of stream, no estimation: the period decided with what came (an error if
        it cannot be, or if none of the mapped messages came), and the samples still open."""
        parts = []
        tail = self.times.flush()  # a departure from the time base nothing came back from
        if len(tail):
            parts.append(self._through(tail))
        held = self.reorder.flush()  # a frame held for its neighbour in a next block
        if len(held):
            parts.append(self._paired(self.decoder.decode(held), held))
        rest = self._flush_samples()
        head = [p for p in parts if len(p)]
        return Signals.concat([*head, rest]) if head else rest

    def _flush_samples(self) -> Signals:
        if self._meter is not None and self.frames:
            if not any(self._meter.counts().values()):
                raise self._foreign_error()
            self._measured()
        if self.pairer is None:  # no frame at all (samples fed directly, or none yet)
            return Signals.concat([])
        return self._push(None)

    def process(self, block: FrameBlock, record: bool = False) -> PipelineBlock:
        samples = self.samples(block)  # first: it may start the sample processor
        return self.sampler.process(samples, record)

    def process_samples(self, samples: Signals, record: bool = False) -> PipelineBlock:
        """Samples already paired (a simulation) through the same rule."""
        return self.sampler.process(samples, record)

    def flush(self, record: bool = False) -> PipelineBlock:
        """End of stream: complete periods still waiting for a partner go through, and a
        calibration still collecting uses what it has."""
        samples = self.flush_samples()  # first: it may start the sample processor
        out = self.sampler.process(samples, record)
        if self.sampler.calibrating:
            out = self.sampler.finish(record)
        return out

    @property
    def rejected(self) -> RejectCounts:
        return self.decoder.rejected

    @property
    def pairing(self) -> PairingCounts:
        return self.pairer.counts if self.pairer is not None else PairingCounts()

    def reject_counts(self) -> dict[str, int]:
        """Frames rejected or put back, by reason, and clock events, as ``RlsRejects``
        carries them (:data:`canrls.can.frames.REJECT_FIELDS`; running totals)."""
        r, c = self.rejected, self.pairing
        return {"crc": r["crc"], "malformed": r["remote"] + r["length"],
                "repeated": r["repeated"], "stale": r["stale"] + r["sequence"],
                "range": r["range"] + r["nan"], "time": r["time"],
                "unpaired": c.unpaired + c.late + c.duplicated,
                "reordered": self.reorder.moved,
                "clock_steps": c.clock["step_back"] + c.clock["step_forward"],
                "gaps": c.clock["gap"]}

    def frame_counts(self) -> FrameCounts:
        """The frames seen so far (running totals over every :meth:`restart`)."""
        rej = self.rejected
        now = FrameCounts(
            total=self.frames - self._past.total,
            rejected={k: int(v) for k, v in rej.items()},
            examples=dict(getattr(rej, "examples", {}) or {}),
            lost={k: int(v) for k, v in self.decoder.lost.items()},
            foreign=int(self.decoder.foreign), pairing=self.pairing.as_dict())
        counts = self._past + now
        return dataclasses.replace(counts, messages=dict(self.message_frames),
                                   missing=self.missing_messages())

    def restart(self) -> None:
        """A new stream (the next log): time judge, reorderer, decoder and pairer start
        afresh, none of their state carried over; the period stays decided, and the
        frame counts go on (:meth:`frame_counts`)."""
        self._past = dataclasses.replace(self.frame_counts(), messages={}, missing=None)
        self.decoder = self.protocol.decoder()
        self.reorder = Reorderer(self.protocol.messages)
        self.times = TimeJudge()
        if self.pairer is not None:
            self.pairer = Pairer(self.protocol, period=self.pairer.period)

    def period_info(self) -> PeriodInfo:
        """The period used, who stated it and what the frames measured."""
        est = self.period_estimate
        return PeriodInfo(self.period, self.period_source or "measured",
                          None if est is None else est.period,
                          None if est is None else est.jitter,
                          None if est is None else sum(est.intervals.values()))

    def axis_info(self) -> AxisInfo:
        """The model's axis, the DBC units of the signals it was read from, the ratings
        relative units refer to and, on a torque-reporting drive, the target."""
        target = None
        if self.model.target == "torque":
            t = self.protocol.roles["torque"]
            lin = self.model.axis == "linear"
            target = (f"the {'force' if lin else 'torque'} the drive reports, "
                      f"{t.message}.{t.signal} [{'N' if lin else 'N·m'}], no Kt")
        return AxisInfo(self.model.axis, self.protocol.axis,
                        {r: i.unit for r, i in self.protocol.roles.items()},
                        self.protocol.mapping.ratings.as_dict(), target)

    def start_info(self) -> StartInfo:
        """The first frame's timestamp and, for an epoch time, its date (UTC)."""
        return StartInfo(self.origin, epoch_date(self.origin), self.relative_time)

    def result(self, source: str) -> FitResult:
        """The estimates so far, with the frames, period, start and axis."""
        return FitResult(estimates=self.pipeline.estimates(), frames=self.frame_counts(),
                         source=source, model=self.model, period=self.period_info(),
                         start=self.start_info(), axis=self.axis_info(),
                         calibration=self.calibration)
