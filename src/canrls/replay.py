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
import itertools
import logging
import math
import os
import tempfile
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from typing import TYPE_CHECKING, Any

import numpy as np
import numpy.typing as npt

from canrls.can.frameblock import FrameBlock
from canrls.can.logs import LogReadStats, read_frames
from canrls.can.pairing import Pairer
from canrls.can.protocol import Protocol
from canrls.can.reorder import Reorderer
from canrls.can.times import TimeJudge
from canrls.errors import ConfigError, EstimatorError, LogFormatError
from canrls.estimation.model import Model
from canrls.estimation.pipeline import Estimates, EstimatorSettings, PipelineBlock
from canrls.estimation.selection import SamplePolicy
from canrls.processor import FitResult, FrameProcessor
from canrls.signals import ROLES, Signals, SpilledSignals

if TYPE_CHECKING:
    from canrls.config import AppConfig

F64 = npt.NDArray[np.float64]

log = logging.getLogger(__name__)

__all__ = ["FILE_GAP_S", "FitResult", "FrameProcessor", "LogFiles", "LogsSamples",
           "MIN_SAMPLES_PER_PARAMETER", "fit_frames", "fit_log", "fit_logs", "prepare",
           "read_logs", "too_few_samples"]

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


def too_few_samples(model: Model, estimates: Estimates, frames: Mapping[str, Any],
                    dt: float | None, settings: EstimatorSettings | None = None) -> str | None:
    """Why ``estimates`` rest on too few usable samples to be an answer (fewer than
    :data:`MIN_SAMPLES_PER_PARAMETER` per parameter in an equation), or None.
    ``frames``: the frame counts of a fit's or a diagnosis's JSON (``total``,
    ``rejected``, ``pairing``, ``foreign``, ``missing``: a mapped message that never
    occurred, :meth:`FrameProcessor.missing_messages`); ``dt`` the control period."""
    st = settings or EstimatorSettings()
    dt = dt if dt else math.nan
    for eq, fit in zip(model.equations, estimates.equations, strict=False):
        need = MIN_SAMPLES_PER_PARAMETER * len(eq.parameters)
        if fit.samples >= need:
            continue
        if frames.get("missing"):
            return str(frames["missing"])
        pairing = frames.get("pairing") or {}
        paired = pairing.get("samples", 0)
        lost = {k: v for k, v in pairing.items() if v and k != "samples"}
        rej = {k: v for k, v in (frames.get("rejected") or {}).items() if v}
        foreign = frames.get("foreign", 0)
        text = (f"{frames.get('total', 0)} frames gave {paired} samples"
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


def prepare(cfg: AppConfig) -> tuple[Protocol, Model, EstimatorSettings]:
    """Protocol, model and settings from a configuration. The ranges it does not give
    are measured by the front end on the calibration window (:mod:`canrls.processor`),
    as the live daemon does: no first pass over the log."""
    protocol = cfg.protocol()
    return protocol, cfg.model_for(protocol), cfg.settings()


class LogFiles:
    """The samples of several logs, in turn, through one :class:`FrameProcessor`.

    Segments are never bridged across files: before each file the processor's decoder
    and pairer restart (no counter or pairing state carried over), and a file that does
    not start at least :data:`FILE_GAP_S` after the previous one ended (the same time,
    earlier, or straight after) is moved in time to start exactly that much later, so
    the estimator sees a gap and restarts its filter there, and the joined record's time
    stays increasing. The calibration window is the start of the first file (the first
    ``calibration_s`` of samples; when the first file is shorter, it continues into the
    next). The frame counts of :meth:`frames` are the totals over the files.
    """

    def __init__(self, paths: Sequence[str | os.PathLike[str]], proc: FrameProcessor, *,
                 chunk_size: int = 65536, progress: Callable[[int, int], None] | None = None,
                 skip_bad_lines: bool = False) -> None:
        self.paths = [str(p) for p in paths]
        self.proc = proc
        self.chunk_size = chunk_size
        self.progress = progress
        self.skip_bad_lines = skip_bad_lines
        self.stats = LogReadStats()
        #: time shift of each file read so far [s]
        self.shifts: list[float] = []
        #: samples of each file read so far (in the order of the joined record)
        self.sizes: list[int] = []
        self._counts: list[dict[str, Any]] = []
        self._end: float | None = None
        self._file = 0

    def _file_counts(self) -> dict[str, Any]:
        p = self.proc
        return {"rejected": {k: int(v) for k, v in p.rejected.items()},
                "examples": dict(getattr(p.rejected, "examples", {}) or {}),
                "lost": {k: int(v) for k, v in p.decoder.lost.items()},
                "foreign": int(p.decoder.foreign), "pairing": p.pairing.as_dict()}

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
        for k, path in enumerate(self.paths):
            self._file = k + 1
            self.sizes.append(0)
            if k:
                self._counts.append(self._file_counts())
                proc = self.proc
                proc.decoder = proc.protocol.decoder()
                proc.reorder = Reorderer(proc.protocol.messages)
                proc.times = TimeJudge()
                if proc.pairer is not None:
                    proc.pairer = Pairer(proc.protocol, period=proc.pairer.period)
            frames = self.proc.frames
            for block in read_frames(path, self.chunk_size, skip_bad_lines=self.skip_bad_lines,
                                     stats=self.stats, progress=self.progress):
                yield self._shifted(self.proc.samples(block))
            if self.proc.frames == frames:
                raise LogFormatError(f"{path}: no CAN frames in the log"
                                     + (f" ({self.stats.bad_lines} unparsable lines skipped)"
                                        if self.stats.bad_lines else ""))
            # the end of the file: the period is decided with what came (the first file
            # measures it), and the samples still open are paired
            yield self._shifted(self.proc.flush_samples())
            if len(self.shifts) < self._file:
                self.shifts.append(0.0)  # a file without samples

    def frames(self) -> dict[str, Any]:
        """Frame statistics summed over the files (as :meth:`FitResult.to_dict` has them)."""
        parts = [*self._counts, self._file_counts()]

        def total(key: str) -> dict[str, int]:
            out: dict[str, int] = {}
            for c in parts:
                for k, v in c[key].items():
                    out[k] = out.get(k, 0) + int(v)
            return out

        examples: dict[str, str] = {}
        for c in parts:
            for k, v in c["examples"].items():
                examples.setdefault(k, v)
        d: dict[str, Any] = {"total": self.proc.frames, "rejected": total("rejected"),
                             "examples": examples, "lost": total("lost"),
                             "foreign": sum(c["foreign"] for c in parts),
                             "pairing": total("pairing"),
                             "messages": dict(self.proc.message_frames)}
        missing = self.proc.missing_messages()
        if missing:
            d["missing"] = missing
        if self.stats.bad_lines:
            d["bad_lines"] = self.stats.bad_lines
        return d


@dataclasses.dataclass(frozen=True)
class LogsSamples:
    """The samples of several logs as one record (:class:`LogFiles`): in memory, or in
    a temporary file (:class:`~canrls.signals.SpilledSignals`) when read with
    ``spill=True`` (:meth:`close` frees it)."""

    signals: Signals | SpilledSignals
    #: sample period [s] (the pairer's)
    dt: float
    #: frame statistics summed over the files (total, rejected, lost, foreign, pairing)
    frames: dict[str, Any]
    #: the model with the ranges the front end gives it (the DBC's where not configured)
    model: Model
    #: samples of each file, in order
    sizes: tuple[int, ...]

    def close(self) -> None:
        """Free the temporary file of spilled samples (nothing for samples in memory)."""
        if isinstance(self.signals, SpilledSignals):
            self.signals.close()


def _join(blocks: Iterable[Signals]) -> Signals:
    """:meth:`Signals.concat` of ``blocks`` (the same values), without keeping the larger
    arrays the blocks' columns are views of, one channel's blocks joined at a time and
    freed once joined: the peak is the samples and one channel more."""
    cols: dict[str, list[F64 | None]] = {r: [] for r in ("t", *ROLES)}
    for b in blocks:
        for r, parts in cols.items():
            v = getattr(b, r)
            # a copy: the block's columns are views of larger arrays, kept alive by them
            parts.append(None if v is None else np.array(v, dtype=np.float64))
    if not cols["t"]:
        return Signals.concat([])
    out: dict[str, F64 | None] = {}
    for r in list(cols):
        parts = cols.pop(r)
        out[r] = None if any(v is None for v in parts) else np.concatenate(parts)
        del parts
    return Signals.from_roles(out)


def _spill(blocks: Iterable[Signals]) -> Signals | SpilledSignals:
    """``blocks`` joined in a temporary file (:class:`SpilledSignals`), or in memory
    (:func:`_join`) with one warning line when the file cannot be made or written (a
    read-only or full temporary directory): the rows written so far are read back,
    none is lost."""
    blocks = iter(blocks)
    try:
        rec = SpilledSignals()
    except OSError as e:
        log.warning("cannot make a temporary file for the samples in %s (%s): they are "
                    "kept in memory", tempfile.gettempdir(), e)
        return _join(blocks)
    try:
        for b in blocks:
            try:
                rec.append(b)
            except OSError as e:
                log.warning("cannot write the temporary file of the samples in %s (%s): "
                            "they are kept in memory", tempfile.gettempdir(), e)
                kept = rec.in_memory()
                rec.close()
                return _join(itertools.chain([kept, b], blocks))
    except BaseException:
        rec.close()  # a log that cannot be read: the file goes at once
        raise
    return rec


def read_logs(paths: Sequence[str | os.PathLike[str]], protocol: Protocol, model: Model,
              settings: EstimatorSettings | None = None, *, chunk_size: int = 65536,
              progress: Callable[[int, int], None] | None = None,
              skip_bad_lines: bool = False, spill: bool = False) -> LogsSamples:
    """Decode and pair several logs as :func:`fit_logs` does, keeping the samples (for a
    diagnosis of them all: :func:`canrls.diagnosis.analysis.diagnose`).

    ``spill=True`` keeps them in an anonymous temporary file instead of memory
    (:class:`~canrls.signals.SpilledSignals`, 8 bytes per sample and channel, read back
    in slices; :meth:`LogsSamples.close` frees it); if the file cannot be made or
    written, in memory after one warning line.

    :raises LogFormatError: a log without any CAN frame.
    :raises ConfigError: fewer than two samples in all.
    """
    proc = FrameProcessor(protocol, model, settings, relative_time=True)
    files = LogFiles(paths, proc, chunk_size=chunk_size, progress=progress,
                     skip_bad_lines=skip_bad_lines)
    blocks = (s for s in files.samples() if len(s))
    signals = _spill(blocks) if spill else _join(blocks)
    if len(signals) < 2:
        if isinstance(signals, SpilledSignals):
            signals.close()
        raise ConfigError(f"{', '.join(files.paths)}: {len(signals)} samples after decoding "
                          f"and pairing {proc.frames} frames; nothing to analyse")
    frames = files.frames()
    frames.pop("examples", None)
    frames["period"] = proc.period_info()
    frames["start"] = proc.start_info()
    assert proc.period is not None  # decided at the end of the first file
    return LogsSamples(signals, proc.period, frames, proc.model, tuple(files.sizes))


def fit_logs(paths: Sequence[str | os.PathLike[str]], protocol: Protocol, model: Model,
             settings: EstimatorSettings | None = None, *, chunk_size: int = 65536,
             progress: Callable[[int, int], None] | None = None,
             on_block: Callable[[PipelineBlock], None] | None = None,
             record: bool = False, skip_bad_lines: bool = False) -> FitResult:
    """One model from several logs (:class:`LogFiles`: no segment bridged across files).

    The result's ``source`` is the logs joined by ``", "``; ``extra["files"]`` lists each
    log with its time shift.

    :raises LogFormatError: a log without any CAN frame.
    :raises EstimatorError: too few usable samples (:func:`too_few_samples`).
    """
    if not paths:
        raise ValueError("fit_logs: no log given")
    proc = FrameProcessor(protocol, model, settings, relative_time=True)
    files = LogFiles(paths, proc, chunk_size=chunk_size, progress=progress,
                     skip_bad_lines=skip_bad_lines)
    _estimate(proc, files.samples(), on_block, record)
    res = proc.result(", ".join(files.paths))
    fr = files.frames()
    extra = dict(res.extra)
    if fr.get("bad_lines"):
        extra["bad_lines"] = fr["bad_lines"]
    if len(files.paths) > 1:
        extra["files"] = [{"path": p, "time_shift_s": sh}
                          for p, sh in zip(files.paths, files.shifts, strict=True)]
    res = dataclasses.replace(res, frames=fr["total"], rejected=fr["rejected"],
                              rejected_examples=fr["examples"], pairing=fr["pairing"],
                              foreign=fr["foreign"], lost=fr["lost"], extra=extra)
    few = too_few_samples(res.model, res.estimates, fr, res.extra["period"]["value"], settings)
    if few is not None:
        raise EstimatorError(f"{res.source}: {few}")
    return res
