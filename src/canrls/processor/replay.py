"""Offline replay: a recorded CAN log through the same pipeline as the live daemon.

``frames (log) -> strict decode -> pairing -> calibration -> Pipeline -> FitResult``

The log is streamed in blocks (:func:`canrls.can.logs.read_frames`), so memory stays
flat in the log's length. :class:`FrameProcessor` is the part shared with the live
daemon: it takes :class:`~canrls.can.frameblock.FrameBlock` objects of any size, so a
log replayed here gives the same parameters as the daemon fed the same frames, bit
for bit.
"""

from __future__ import annotations

import dataclasses
import math
import os
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence

import numpy as np

from canrls.can.frameblock import FrameBlock
from canrls.can.logs import LogReadStats, empty_log_error, read_frames
from canrls.can.protocol import Protocol
from canrls.core.errors import ConfigError, EstimatorError
from canrls.core.files import ContentHash
from canrls.core.samples import Signals
from canrls.core.spill import SpilledSignals, join_blocks, spill_blocks
from canrls.estimation.estimates import Estimates, PipelineBlock
from canrls.estimation.model import Model
from canrls.estimation.selection import SamplePolicy
from canrls.estimation.settings import EstimatorSettings
from canrls.processor.fit_result import (
    FileShift,
    FitResult,
    FrameCounts,
    MachineFit,
    PeriodInfo,
    StartInfo,
)
from canrls.processor.frames import FrameProcessor, expected_messages

__all__ = ["FILE_GAP_S", "LogFiles", "LogsSamples", "MIN_SAMPLES_PER_PARAMETER", "fit_axes",
           "fit_frames", "fit_log", "fit_logs", "read_logs", "too_few_samples"]

#: Several logs are joined into one record with at least this gap [s] between the end of
#: one and the start of the next (:class:`LogFiles`): longer than any sample gap the
#: pipeline fills, so the filter restarts at every file and no segment is bridged.
FILE_GAP_S = 1.0


def fit_frames(blocks: Iterable[FrameBlock], protocol: Protocol, model: Model,
               settings: EstimatorSettings | None = None, *, source: str = "<frames>",
               on_block: Callable[[PipelineBlock], None] | None = None,
               record: bool = False) -> FitResult:
    """Run blocks of frames through decoder, pairer and pipeline."""
    proc = FrameProcessor(protocol, model, settings, relative_time=True)
    _estimate(proc, (proc.samples(b) for b in blocks), on_block, record)
    return proc.result(source)


def _estimate(proc: FrameProcessor, samples: Iterable[Signals],
              on_block: Callable[[PipelineBlock], None] | None, record: bool) -> None:
    """Estimate on ``samples`` (paired by ``proc`` as they are drawn), then the end of
    the stream; every block's output to ``on_block``."""
    for s in samples:
        out = proc.process_samples(s, record)
        if on_block is not None:
            on_block(out)
    out = proc.flush(record)
    if on_block is not None:
        on_block(out)


def fit_log(path: str | os.PathLike[str], protocol: Protocol, model: Model,
            settings: EstimatorSettings | None = None, *, chunk_size: int = 65536,
            progress: Callable[[int, int], None] | None = None,
            on_block: Callable[[PipelineBlock], None] | None = None,
            record: bool = False, skip_bad_lines: bool = False) -> FitResult:
    """Replay a log file (candump ``.log``, ``.asc``, ``.blf``, ``.trc``, ``.csv``):
    :func:`fit_logs` of one log.

    :raises LogFormatError: no CAN frame in the log.
    :raises EstimatorError: too few usable samples (:func:`too_few_samples`).
    """
    return fit_logs([path], protocol, model, settings, chunk_size=chunk_size,
                    progress=progress, on_block=on_block, record=record,
                    skip_bad_lines=skip_bad_lines)


#: Fewest used samples per parameter of an equation that a fit reports rather than refuses.
MIN_SAMPLES_PER_PARAMETER = 10


def too_few_samples(model: Model, estimates: Estimates, frames: FrameCounts,
                    dt: float | None, settings: EstimatorSettings | None = None) -> str | None:
    """Why ``estimates`` rest on too few usable samples to be an answer (fewer than
    :data:`MIN_SAMPLES_PER_PARAMETER` per parameter in an equation), or None; ``dt`` is
    the control period."""
    st = settings or EstimatorSettings()
    dt = dt if dt else math.nan
    for eq, fit in zip(model.equations, estimates.equations, strict=False):
        need = MIN_SAMPLES_PER_PARAMETER * len(eq.parameters)
        if fit.samples >= need:
            continue
        if frames.missing:
            return frames.missing
        paired = frames.pairing.get("samples", 0)
        lost = {k: v for k, v in frames.pairing.items() if v and k != "samples"}
        rej = {k: v for k, v in frames.rejected.items() if v}
        foreign = frames.foreign
        text = (f"{frames.total} frames gave {paired} samples"
                  + (f" (frames rejected: {', '.join(f'{k} {v}' for k, v in rej.items())})"
                     if rej else "")
                  + (f" (pairing: {', '.join(f'{k} {v}' for k, v in lost.items())})"
                     if lost else "")
                  + (f"; {foreign} frames of other messages" if foreign else ""))
        why = ""
        if math.isfinite(dt):
            pol = SamplePolicy.for_equation(eq, dt, st)
            u = "m/s" if model.axis == "linear" else "rad/s"
            why = (f"; the others are left out in the filter's warm-up ({pol.warmup} samples "
                   f"after the start, after each gap over {pol.gap * 1e3:.3g} ms and after "
                   f"each sample outside the speed limits)"
                   + (f", below the minimum speed {pol.min_speed:.4g} {u} (sign-dependent "
                      f"friction)" if pol.min_speed > 0 else "")
                   + (f", above {pol.max_speed:.4g} {u} (periodic terms)"
                      if math.isfinite(pol.max_speed) else ""))
        return (f"too few usable samples: the {eq.name} equation used {fit.samples}, its "
                f"{len(eq.parameters)} parameters need at least {need}; {text}{why}")
    return None


class LogFiles:
    """The samples of several logs, in turn, through one :class:`FrameProcessor`.

    Segments are never bridged across files: before each file the processor restarts
    (:meth:`FrameProcessor.restart`), and a file that does not start at least
    :data:`FILE_GAP_S` after the previous one ended is moved in time to start exactly
    that much later, so the estimator restarts its filter there and the joined record's
    time stays increasing. The calibration window is the start of the first file.
    """

    def __init__(self, paths: Sequence[str | os.PathLike[str]], proc: FrameProcessor, *,
                 chunk_size: int = 65536, progress: Callable[[int, int], None] | None = None,
                 skip_bad_lines: bool = False,
                 digests: Sequence[ContentHash] | None = None) -> None:
        self.paths = [str(p) for p in paths]
        if digests is not None and len(digests) != len(self.paths):
            raise ValueError(f"LogFiles: {len(digests)} digests for {len(self.paths)} logs")
        self.digests = digests
        self.proc = proc
        self.chunk_size = chunk_size
        self.progress = progress
        self.skip_bad_lines = skip_bad_lines
        self.stats = LogReadStats()
        #: time shift of each file read so far [s]
        self.shifts: list[float] = []
        #: samples of each file read so far (in the order of the joined record)
        self.sizes: list[int] = []
        self._end: float | None = None
        self._file = 0
        self._frames_before = 0
        self._mapped_before = 0

    def _shifted(self, s: Signals) -> Signals:
        self.sizes[-1] += len(s)
        if not len(s):
            return s
        if len(self.shifts) < self._file:
            t0 = float(s.t[0])
            shift = 0.0 if self._end is None or t0 >= self._end + FILE_GAP_S \
                else self._end + FILE_GAP_S - t0
            self.shifts.append(shift)
        shift = self.shifts[-1]
        if shift:
            s = dataclasses.replace(s, t=s.t + shift)
        self._end = float(s.t[-1])
        return s

    def samples(self) -> Iterator[Signals]:
        """Every file's samples in turn (the caller estimates on them)."""
        for k in range(len(self.paths)):
            self.start_file(k)
            for block in self.blocks(k):
                yield self.block(block)
            yield self.end_file(k)

    def blocks(self, k: int) -> Iterator[FrameBlock]:
        """The frames of file ``k``, read in blocks."""
        return read_frames(self.paths[k], self.chunk_size, skip_bad_lines=self.skip_bad_lines,
                           stats=self.stats, progress=self.progress,
                           digest=None if self.digests is None else self.digests[k])

    def start_file(self, k: int) -> None:
        """File ``k`` begins: the processor restarts (from the second file on)."""
        self._file = k + 1
        self.sizes.append(0)
        if k:
            self.proc.restart()
        self.proc.source = self.paths[k]
        self._frames_before = self.proc.frames
        self._mapped_before = sum(self.proc.message_frames.values())

    def block(self, block: FrameBlock) -> Signals:
        """The samples of one block of the current file."""
        return self._shifted(self.proc.samples(block))

    def end_file(self, k: int) -> Signals:
        """The end of file ``k``: the period is decided with what came (the first file
        measures it), and the samples still open are paired."""
        if self.proc.frames == self._frames_before:
            raise empty_log_error(self.paths[k], self.stats.bad_lines)
        out = self._shifted(self.proc.flush_samples())
        if sum(self.proc.message_frames.values()) == self._mapped_before:
            # (the first log's own error names the IDs seen; a later one would add nothing)
            raise self._unmapped(k)
        if len(self.shifts) < self._file:
            self.shifts.append(0.0)  # a file without samples
        return out

    def _unmapped(self, k: int) -> ConfigError:
        """Log ``k`` holds frames but none of a mapped message: it would add nothing."""
        pr = self.proc.protocol
        return ConfigError(
            f"{self.paths[k]}: none of the mapped messages occurs in its "
            f"{self.proc.frames - self._frames_before} frames (expected "
            f"{expected_messages(pr)}, DBC {pr.dbc_path.name}): it would add no sample; "
            f"leave it out, or fit it with its own DBC and --signal mapping")

    def frames(self) -> FrameCounts:
        """The frame counts over the files, with the log lines skipped."""
        return dataclasses.replace(self.proc.frame_counts(), bad_lines=self.stats.bad_lines)

    def files(self) -> tuple[FileShift, ...]:
        """Each log with its time shift (none for a single log)."""
        if len(self.paths) < 2:
            return ()
        return tuple(FileShift(p, sh) for p, sh in zip(self.paths, self.shifts, strict=True))


@dataclasses.dataclass(frozen=True)
class LogsSamples:
    """The samples of several logs as one record (:class:`LogFiles`): in memory, or in
    a temporary file (:class:`~canrls.core.spill.SpilledSignals`) when read with
    ``spill=True`` (:meth:`close` frees it)."""

    signals: Signals | SpilledSignals
    #: sample period [s] (the pairer's)
    dt: float
    #: the frames of every file
    frames: FrameCounts
    #: the model with the ranges the front end gives it (the DBC's where not configured)
    model: Model
    #: samples of each file, in order
    sizes: tuple[int, ...]
    period: PeriodInfo
    start: StartInfo

    def close(self) -> None:
        """Free the temporary file of spilled samples (nothing for samples in memory)."""
        if isinstance(self.signals, SpilledSignals):
            self.signals.close()


def read_logs(paths: Sequence[str | os.PathLike[str]], protocol: Protocol, model: Model,
              settings: EstimatorSettings | None = None, *, chunk_size: int = 65536,
              progress: Callable[[int, int], None] | None = None,
              skip_bad_lines: bool = False, spill: bool = False) -> LogsSamples:
    """Decode and pair several logs as :func:`fit_logs` does, keeping the samples (for a
    diagnosis of them all: :func:`canrls.diagnosis.analysis.diagnose`).

    ``spill=True`` keeps them in an anonymous temporary file instead of memory
    (:class:`~canrls.core.spill.SpilledSignals`, 8 bytes per sample and channel, read back
    in slices; :meth:`LogsSamples.close` frees it); if the file cannot be made or
    written, in memory after one warning line.

    :raises LogFormatError: a log without any CAN frame.
    :raises ConfigError: fewer than two samples in all.
    """
    proc = FrameProcessor(protocol, model, settings, relative_time=True)
    files = LogFiles(paths, proc, chunk_size=chunk_size, progress=progress,
                     skip_bad_lines=skip_bad_lines)
    blocks = (s for s in files.samples() if len(s))
    signals = spill_blocks(blocks) if spill else join_blocks(blocks)
    if len(signals) < 2:
        if isinstance(signals, SpilledSignals):
            signals.close()
        raise ConfigError(f"{', '.join(files.paths)}: {len(signals)} samples after decoding "
                          f"and pairing {proc.frames} frames; nothing to analyse")
    assert proc.period is not None  # decided at the end of the first file
    return LogsSamples(signals, proc.period, files.frames(), proc.model, tuple(files.sizes),
                       proc.period_info(), proc.start_info())


def fit_logs(paths: Sequence[str | os.PathLike[str]], protocol: Protocol, model: Model,
             settings: EstimatorSettings | None = None, *, chunk_size: int = 65536,
             progress: Callable[[int, int], None] | None = None,
             on_block: Callable[[PipelineBlock], None] | None = None,
             record: bool = False, skip_bad_lines: bool = False,
             digests: Sequence[ContentHash] | None = None) -> FitResult:
    """One model from several logs (:class:`LogFiles`: no segment bridged across files).

    The result's ``source`` is the logs joined by ``", "``; its ``files`` list each log
    with its time shift. ``digests``: one per log, each fed that log's bytes as they are
    read (the hash without a second read: :class:`~canrls.core.files.ContentHash`).

    :raises LogFormatError: a log without any CAN frame.
    :raises EstimatorError: too few usable samples (:func:`too_few_samples`).
    """
    if not paths:
        raise ValueError("fit_logs: no log given")
    proc = FrameProcessor(protocol, model, settings, relative_time=True)
    files = LogFiles(paths, proc, chunk_size=chunk_size, progress=progress,
                     skip_bad_lines=skip_bad_lines, digests=digests)
    _estimate(proc, files.samples(), on_block, record)
    res = _result(files, settings)
    if res.error is not None:
        raise EstimatorError(res.error)
    return res.fit


@dataclasses.dataclass(frozen=True)
class _Outcome:
    fit: FitResult
    error: str | None


def _result(files: LogFiles, settings: EstimatorSettings | None) -> _Outcome:
    """The fit of ``files`` after the last sample, and why it is no answer (too few
    samples), if so."""
    res = dataclasses.replace(files.proc.result(", ".join(files.paths)), frames=files.frames(),
                              files=files.files())
    few = too_few_samples(res.model, res.estimates, res.frames, res.period.value, settings)
    return _Outcome(res, None if few is None else f"{res.source}: {few}")


def fit_axes(paths: Sequence[str | os.PathLike[str]],
             axes: Mapping[str, tuple[Protocol, Model, EstimatorSettings]], *,
             chunk_size: int = 65536, progress: Callable[[int, int], None] | None = None,
             skip_bad_lines: bool = False) -> MachineFit:
    """Every axis of a machine from the logs of its bus, in one pass: each block read
    goes to each axis's :class:`FrameProcessor`, which decodes its own IDs only (the
    others it counts as foreign); frames of no axis are counted. Each axis's fit equals
    :func:`fit_logs` of that axis alone."""
    if not paths or not axes:
        raise ValueError("fit_axes: no log or no axis given")
    files = {name: LogFiles(paths, FrameProcessor(p, m, s, relative_time=True),
                            chunk_size=chunk_size, skip_bad_lines=skip_bad_lines)
             for name, (p, m, s) in axes.items()}
    # frame ID | extended << 31 of every axis's messages
    known = np.array(sorted({m.frame_id | (m.is_extended << 31)
                             for p, _, _ in axes.values() for m in p.messages}), np.int64)
    first = next(iter(files.values()))
    first.progress = progress
    total = unknown = 0
    for k in range(len(first.paths)):
        for f in files.values():
            f.start_file(k)
        for block in first.blocks(k):
            key = block.arbitration_id.astype(np.int64) | (block.is_extended.astype(np.int64)
                                                            << 31)
            total += len(block)
            unknown += int(np.count_nonzero(~np.isin(key, known) & ~block.is_error))
            for f in files.values():
                f.proc.process_samples(f.block(block))
        for f in files.values():
            f.proc.process_samples(f.end_file(k))
    outcomes = {}
    for name, f in files.items():
        f.proc.flush()
        f.stats = first.stats
        outcomes[name] = _result(f, axes[name][2])
    return MachineFit(", ".join(first.paths), total, unknown,
                      {n: o.fit for n, o in outcomes.items()},
                      {n: o.error for n, o in outcomes.items() if o.error is not None})
