r"""The front end shared by the live daemon and the offline replay.

``frames -> strict decode -> pairing -> samples -> Pipeline``

:class:`FrameProcessor` takes :class:`~canrls.can.frameblock.FrameBlock` objects of any
size, so a log replayed offline gives the same parameters as the daemon fed the same
frames, bit for bit. It is the one place that decides the signal ranges (and with them
the normalisation of the regressors).

Signal ranges from the data
---------------------------
The normalisation (:attr:`canrls.estimation.model.Equation.scaling`) is chosen from signal ranges.
The DBC's min/max are the protocol's limits, often far wider than the drive ever
goes (±800 A for a 10 A servo), and the bound of a derivative column derived from
the speed range alone is the worst case of the filter; both leave the regressors
small, which costs resolution in the fixed-point kernel and lets the ridge prior
:math:`\alpha` weigh on the weakly scaled parameters. :class:`RangeScanner` measures
the ranges the filtered signals actually reach, including the filtered derivatives
(acceleration, current rate), so that the normalisation uses the data:

.. math::

    r_x = m \cdot \max_k |x_k|, \qquad
    r_{\dot\omega} = m \cdot \max_k |sF[\omega]_k|

with a headroom factor ``m`` (default 2: one bit). Signals beyond the scanned range
later are not clipped in float; in fixed point they saturate and are counted.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from canrls.can.frameblock import FrameBlock
from canrls.can.pairing import Pairer, PairingCounts
from canrls.can.protocol import Protocol, RejectCounts
from canrls.estimation.model import Model
from canrls.estimation.pipeline import Estimates, EstimatorSettings, Pipeline, PipelineBlock
from canrls.estimation.svf import SVF
from canrls.signals import Signals

__all__ = ["FitResult", "FrameProcessor", "RangeScanner", "scan_ranges"]


@dataclass(frozen=True)
class FitResult:
    """What a replay produced: the estimates and what happened to the frames."""

    estimates: Estimates
    frames: int
    rejected: dict[str, int]
    rejected_examples: dict[str, str]
    pairing: dict[str, int]
    foreign: int
    lost: dict[str, int]
    source: str
    model: Model
    extra: dict[str, Any] = field(default_factory=dict)

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
            "frames": {"total": self.frames, "rejected": self.rejected,
                       "lost": self.lost, "foreign": self.foreign,
                       "pairing": self.pairing},
            "unit": self.estimates.equations[0].unit if self.estimates.equations else None,
        })
        d.update(self.extra)
        return d

    def format(self) -> str:
        lines = [f"{self.source}: {self.frames} frames, {self.estimates.samples} samples used"]
        rej = sum(self.rejected.values())
        if rej:
            lines.append(f"rejected frames: {rej} ("
                         + ", ".join(f"{k} {v}" for k, v in self.rejected.items() if v) + ")")
            for k, ex in self.rejected_examples.items():
                lines.append(f"  e.g. {k}: {ex}")
        if any(self.lost.values()):
            lines.append("lost frames (counter gaps): "
                         + ", ".join(f"{k} {v}" for k, v in self.lost.items() if v))
        odd = {k: v for k, v in self.pairing.items() if v and k != "samples"}
        if odd:
            lines.append("pairing: " + ", ".join(f"{k} {v}" for k, v in odd.items()))
        lines.append(self.estimates.format())
        return "\n".join(lines)

    __str__ = format



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
        for role in ("current", "speed", "voltage"):
            v = getattr(s, role)
            if v is not None:
                self._put(role, float(np.nanmax(np.abs(v))))
        _, sf = self.svf.process(np.column_stack([s.speed, s.current]))
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


class FrameProcessor:
    """Frames in, estimates out: decoder + pairer + pipeline, all stateful.

    Used by the offline replay (blocks of a log) and by the daemon (blocks of the frames
    that arrived).

    Parameters
    ----------
    protocol, model, settings : what to decode and estimate
    period : control period [s] (default: the DBC's cycle time)
    calibrate : ``ranges -> Model``; when given, the first ``calibrate_s`` seconds of
        samples are held back, their ranges measured (:class:`canrls.processor.RangeScanner`), the model
        rebuilt with them, and estimation starts on those samples. This is how the
        daemon normalises from the data when the configuration gives no ranges; an
        offline replay measures the whole log instead (:func:`scan_log_ranges`).
    calibrate_s : seconds of samples the calibration uses (default 2)
    """

    def __init__(self, protocol: Protocol, model: Model,
                 settings: EstimatorSettings | None = None, period: float | None = None,
                 calibrate: Callable[[dict[str, list[float]]], Model] | None = None,
                 calibrate_s: float = 2.0) -> None:
        self.protocol = protocol
        self.decoder = protocol.decoder()
        self.pairer = Pairer(protocol, period=period)
        self.pipeline = Pipeline(model, self.pairer.period, settings)
        self.frames = 0
        self._calibrate = calibrate
        self._held: list[Signals] = []
        self._held_n = 0
        self._calibrate_n = max(1, int(round(calibrate_s / self.pairer.period)))

    @property
    def calibrating(self) -> bool:
        """True while samples are held back for the range calibration."""
        return self._calibrate is not None

    def with_model(self, model: Model) -> Pipeline:
        """Switch to a new pipeline for ``model`` (starting from the prior); returns it."""
        self.pipeline = self.pipeline.with_model(model)
        return self.pipeline

    def _feed(self, samples: Signals, record: bool) -> PipelineBlock:
        if self._calibrate is None:
            return self.pipeline.process(samples, record)
        if len(samples):
            self._held.append(samples)
            self._held_n += len(samples)
        if self._held_n < self._calibrate_n:
            return self.pipeline.process(samples.slice(0, 0), record)
        return self._finish_calibration(record)

    def _finish_calibration(self, record: bool) -> PipelineBlock:
        held = Signals.concat(self._held)
        model = self.model
        sc = RangeScanner(self.pipeline.dt, model.cutoff_hz, model.zeta)
        sc.update(held)
        calibrate, self._calibrate, self._held = self._calibrate, None, []
        assert calibrate is not None
        self.pipeline = Pipeline(calibrate(sc.ranges()), self.pipeline.dt,
                                 self.pipeline.settings)
        return self.pipeline.process(held, record)

    @property
    def model(self) -> Model:
        return self.pipeline.model

    def samples(self, block: FrameBlock) -> Signals:
        """Decode and pair one block of frames (no estimation)."""
        self.frames += len(block)
        return self.pairer.push(self.decoder.decode(block))

    def process(self, block: FrameBlock, record: bool = False) -> PipelineBlock:
        return self._feed(self.samples(block), record)

    def flush(self, record: bool = False) -> PipelineBlock:
        """End of stream: complete periods still waiting for a partner go through
        (and a calibration still collecting uses what it has)."""
        out = self._feed(self.pairer.flush(), record)
        if self._calibrate is not None and self._held:
            out = self._finish_calibration(record)
        return out

    @property
    def rejected(self) -> RejectCounts:
        return self.decoder.rejected

    @property
    def pairing(self) -> PairingCounts:
        return self.pairer.counts

    def result(self, source: str) -> FitResult:
        rej = self.rejected
        return FitResult(
            estimates=self.pipeline.estimates(), frames=self.frames,
            rejected={k: int(v) for k, v in rej.items()},
            rejected_examples=dict(getattr(rej, "examples", {}) or {}),
            pairing=self.pairing.as_dict(), foreign=int(self.decoder.foreign),
            lost={k: int(v) for k, v in self.decoder.lost.items()},
            source=source, model=self.model)
