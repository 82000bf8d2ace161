"""Offline replay: a recorded CAN log through the same pipeline as the live daemon.

``frames (log) -> strict decode -> pairing -> calibration -> Pipeline -> FitResult``

The log is streamed in blocks (:func:`canrls.can.logs.read_frames`), so memory stays
flat in the log's length. :class:`FrameProcessor` is the part shared with the live
daemon: it takes :class:`~canrls.can.frameblock.FrameBlock` objects of any size, so a
log replayed here gives the same parameters as the daemon fed the same frames, bit
for bit.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Iterable
from typing import TYPE_CHECKING

from canrls.can.frameblock import FrameBlock
from canrls.can.logs import LogReadStats, read_frames
from canrls.can.protocol import Protocol
from canrls.estimation.model import Model
from canrls.estimation.pipeline import EstimatorSettings, PipelineBlock
from canrls.processor import FitResult, FrameProcessor

if TYPE_CHECKING:
    from canrls.config import AppConfig

__all__ = ["FitResult", "FrameProcessor", "fit_frames", "fit_log", "prepare"]


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


def prepare(cfg: AppConfig) -> tuple[Protocol, Model, EstimatorSettings]:
    """Protocol, model and settings from a configuration. The ranges it does not give
    are measured by the front end on the calibration window (:mod:`canrls.processor`),
    as the live daemon does: no first pass over the log."""
    protocol = cfg.protocol()
    return protocol, cfg.model_for(protocol), cfg.settings()
