"""Offline replay: a recorded CAN log through the same pipeline as the live daemon.

``frames (log) -> strict decode -> pairing -> Pipeline -> FitResult``

The log is streamed in blocks (:func:`canrls.logs.read_frames`), so memory stays
flat in the log's length. :class:`FrameProcessor` is the part shared with the live
daemon: it takes :class:`~canrls.frameblock.FrameBlock` objects of any size, so a
log replayed here gives the same parameters as the daemon fed the same frames, bit
for bit.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

from canrls.frameblock import FrameBlock
from canrls.logs import LogReadStats, read_frames
from canrls.model import Model
from canrls.pairing import Pairer, PairingCounts
from canrls.pipeline import Estimates, EstimatorSettings, Pipeline, PipelineBlock
from canrls.protocol import Protocol, RejectCounts
from canrls.ranges import RangeScanner
from canrls.signals import Signals

if TYPE_CHECKING:
    from canrls.config import AppConfig

__all__ = ["FrameProcessor", "FitResult", "fit_frames", "fit_log", "scan_log_ranges",
           "prepare"]


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


class FrameProcessor:
    """Frames in, estimates out: decoder + pairer + pipeline, all stateful.

    Used by the offline replay (blocks of a log) and by the daemon (blocks of the frames
    that arrived).

    Parameters
    ----------
    protocol, model, settings : what to decode and estimate
    period : control period [s] (default: the DBC's cycle time)
    calibrate : ``ranges -> Model``; when given, the first ``calibrate_s`` seconds of
        samples are held back, their ranges measured (:mod:`canrls.ranges`), the model
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


def fit_frames(blocks: Iterable[FrameBlock], protocol: Protocol, model: Model,
               settings: EstimatorSettings | None = None, *, source: str = "<frames>",
               on_block: Callable[[PipelineBlock], None] | None = None,
               record: bool = False) -> FitResult:
    """Run blocks of frames through decoder, pairer and pipeline."""
    proc = FrameProcessor(protocol, model, settings)
    for b in blocks:
        out = proc.process(b, record)
        if on_block is not None:
            on_block(out)
    out = proc.flush(record)
    if on_block is not None:
        on_block(out)
    return proc.result(source)


def fit_log(path: str | os.PathLike[str], protocol: Protocol, model: Model,
            settings: EstimatorSettings | None = None, *, chunk_size: int = 65536,
            progress: Callable[[int, int], None] | None = None,
            on_block: Callable[[PipelineBlock], None] | None = None,
            record: bool = False, skip_bad_lines: bool = False) -> FitResult:
    """Replay a log file (candump ``.log``, ``.asc``, ``.blf``, ``.trc``, ``.csv``)."""
    stats = LogReadStats()
    blocks = read_frames(path, chunk_size, skip_bad_lines=skip_bad_lines, stats=stats,
                         progress=progress)
    res = fit_frames(blocks, protocol, model, settings, source=str(path), on_block=on_block,
                     record=record)
    if stats.bad_lines:
        res.extra["bad_lines"] = stats.bad_lines
    return res


def scan_log_ranges(path: str | os.PathLike[str], protocol: Protocol, model: Model,
                    *, chunk_size: int = 65536, headroom: float = 2.0,
                    skip_bad_lines: bool = False) -> dict[str, list[float]]:
    """First pass over a log: the ranges its samples reach (:mod:`canrls.ranges`).

    Decodes and pairs only (no estimation); memory stays flat.
    """
    decoder = protocol.decoder()
    pairer = Pairer(protocol)
    sc = RangeScanner(pairer.period, model.cutoff_hz, model.zeta, headroom)
    for block in read_frames(path, chunk_size, skip_bad_lines=skip_bad_lines):
        sc.update(pairer.push(decoder.decode(block)))
    sc.update(pairer.flush())
    return sc.ranges()


def prepare(cfg: AppConfig, log: str | os.PathLike[str] | None = None,
            skip_bad_lines: bool = False) -> tuple[Protocol, Model, EstimatorSettings]:
    """Protocol, model and settings from a configuration; with ``log``, the signal ranges
    the configuration does not give are measured on the log (a first pass)."""
    protocol = cfg.protocol()
    model = cfg.model_for(protocol)
    if log is not None:
        ranges = scan_log_ranges(log, protocol, model, skip_bad_lines=skip_bad_lines)
        model = cfg.model_for(protocol, ranges)
    return protocol, model, cfg.settings()
