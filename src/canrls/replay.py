"""Offline replay: a recorded CAN log through the same pipeline as the live daemon.

``frames (log) -> strict decode -> pairing -> calibration -> Pipeline -> FitResult``

The log is streamed in blocks (:func:`canrls.can.logs.read_frames`), so memory stays
flat in the log's length. :class:`FrameProcessor` is the part shared with the live
daemon: it takes :class:`~canrls.can.frameblock.FrameBlock` objects of any size, so a
log replayed here gives the same parameters as the daemon fed the same frames, bit
for bit.
"""

from __future__ import annotations

import math
import os
from collections.abc import Callable, Iterable, Mapping
from typing import TYPE_CHECKING, Any

from canrls.can.frameblock import FrameBlock
from canrls.can.logs import LogReadStats, read_frames
from canrls.can.protocol import Protocol
from canrls.errors import EstimatorError, LogFormatError
from canrls.estimation.model import Model
from canrls.estimation.pipeline import Estimates, EstimatorSettings, PipelineBlock
from canrls.estimation.selection import SamplePolicy
from canrls.processor import FitResult, FrameProcessor

if TYPE_CHECKING:
    from canrls.config import AppConfig

__all__ = ["FitResult", "FrameProcessor", "MIN_SAMPLES_PER_PARAMETER", "fit_frames", "fit_log",
           "prepare", "too_few_samples"]


def fit_frames(blocks: Iterable[FrameBlock], protocol: Protocol, model: Model,
               settings: EstimatorSettings | None = None, *, source: str = "<frames>",
               on_block: Callable[[PipelineBlock], None] | None = None,
               record: bool = False) -> FitResult:
    """Run blocks of frames through decoder, pairer and pipeline."""
    proc = FrameProcessor(protocol, model, settings, relative_time=True)
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
    if res.frames == 0:
        raise LogFormatError(f"{path}: no CAN frames in the log"
                             + (f" ({stats.bad_lines} unparsable lines skipped)"
                                if stats.bad_lines else ""))
    few = too_few_samples(res.model, res.estimates, res.to_dict()["frames"],
                          res.extra["period"]["value"], settings)
    if few is not None:
        raise EstimatorError(f"{path}: {few}")
    return res


#: Fewest used samples per parameter of an equation that a fit reports rather than refuses.
MIN_SAMPLES_PER_PARAMETER = 10


def too_few_samples(model: Model, estimates: Estimates, frames: Mapping[str, Any],
                    dt: float | None, settings: EstimatorSettings | None = None) -> str | None:
    """Why ``estimates`` rest on too few usable samples to be an answer (fewer than
    :data:`MIN_SAMPLES_PER_PARAMETER` per parameter in an equation), or None.
    ``frames``: the frame counts of a fit's or a diagnosis's JSON (``total``,
    ``rejected``, ``pairing``, ``foreign``); ``dt`` the control period."""
    st = settings or EstimatorSettings()
    dt = dt if dt else math.nan
    for eq, fit in zip(model.equations, estimates.equations, strict=False):
        need = MIN_SAMPLES_PER_PARAMETER * len(eq.parameters)
        if fit.samples >= need:
            continue
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
