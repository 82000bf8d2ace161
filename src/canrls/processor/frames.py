"""Frames in, estimates out: :class:`FrameProcessor` judges times, reorders, decodes,
measures the period and pairs, then hands the samples to a
:class:`~canrls.processor.calibration.SampleProcessor`."""

from __future__ import annotations

import dataclasses
import logging
import threading
from collections.abc import Mapping
from typing import Any

import numpy as np

from canrls.can.codec import MessageCodec
from canrls.can.decoder import DecodedFrames, Decoder, RejectCounts
from canrls.can.frameblock import FrameBlock
from canrls.can.protocol import Protocol
from canrls.core.checks import positive_period
from canrls.core.errors import CheckpointError, ConfigError
from canrls.core.samples import Signals
from canrls.estimation.estimates import PipelineBlock
from canrls.estimation.model import Model
from canrls.estimation.pipeline import Pipeline
from canrls.estimation.settings import EstimatorSettings
from canrls.processor.calibration import Calibration, SampleProcessor, dbc_ranges
from canrls.processor.fit_result import (
    AxisInfo,
    FitResult,
    FrameCounts,
    PeriodInfo,
    StartInfo,
    epoch_date,
)
from canrls.processor.pairing import Pairer, PairingCounts
from canrls.processor.period import (
    MIN_INTERVALS,
    PeriodEstimate,
    PeriodMeter,
    check_period,
)
from canrls.processor.reorder import Reorderer
from canrls.processor.times import TimeJudge

__all__ = ["SEEN_IDS", "FrameProcessor", "expected_messages", "unmapped_error"]

log = logging.getLogger(__name__)


#: The period of the placeholder estimator of a :class:`FrameProcessor` whose period is
#: still being measured (no sample ever reaches it).
_PLACEHOLDER_DT = 1e-3


#: Most distinct frame IDs counted while none of the mapped messages has come (for the
#: error that names the most frequent ones): beyond, the rarest are forgotten, so a bus
#: of random IDs cannot grow the daemon's memory.
SEEN_IDS = 1024


def expected_messages(protocol: Protocol) -> str:
    """The mapped messages as an error names them: ``0x101 (DriveCurrent), ...``."""
    return ", ".join(f"0x{m.frame_id:X} ({m.name})" for m in protocol.messages)


def unmapped_error(protocol: Protocol, frames: int, seen: list[tuple[int, int]],
                   rejected: Mapping[str, int] | None = None, source: str | None = None
                   ) -> ConfigError:
    """The error of frames none of which is a mapped message (``canrls fit`` and
    ``export-c --vectors`` alike): what was expected, the most frequent IDs ``seen``
    (``[(id, frames)]``) and the ``rejected`` frames by reason; ``source`` names the log
    they came from (None: a bus)."""
    want = expected_messages(protocol)
    seen_text = ", ".join(f"0x{i:X} ({n})" for i, n in seen) if seen else "none"
    rej = {k: v for k, v in (rejected or {}).items() if v}
    why = ("; rejected: " + ", ".join(f"{k} {v}" for k, v in rej.items())) if rej else ""
    return ConfigError(
        (f"{source}: " if source else "")
        + f"none of the mapped messages occurs in the {frames} frames read: expected "
        f"{want} (DBC {protocol.dbc_path.name}); most frequent IDs seen "
        f"(frames): {seen_text}{why}. Map the right messages with --signal "
        f"ROLE=MESSAGE.SIGNAL or give the drive's DBC with --dbc")


#: configurations whose start (:meth:`FrameProcessor._sampler`) is kept per process
STARTS_KEPT = 16


@dataclasses.dataclass(frozen=True)
class _Start:
    """What a configuration's sample processor starts from (:meth:`FrameProcessor._sampler`)."""

    #: the protocol, model and settings it was built for (held: their ids are the key)
    config: tuple[Protocol, Model, EstimatorSettings | None]
    sources: Mapping[str, str]
    pipeline: Pipeline


_STARTS: dict[tuple[int, int, int, float], _Start] = {}
_STARTS_LOCK = threading.Lock()


class FrameProcessor:
    """Frames in, estimates out: decoder, pairer and :class:`SampleProcessor`, all stateful.

    Used by the offline replay (blocks of a log) and by the daemon (blocks of the frames
    that arrived), with the same calibration rule (docs/architecture.md) and the same
    control period rule (docs/architecture.md, "Control period"): the period is measured
    on the first :data:`~canrls.processor.period.PERIOD_FRAMES` frames of each mapped message
    (:class:`~canrls.processor.period.PeriodMeter`); a stated period (``period``, else the
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
        self.decoder = Decoder(protocol)
        #: judges every frame's receive time first (:mod:`canrls.processor.times`): frames
        #: without a time, or out of line with the stream, are rejected (``time``)
        self.times = TimeJudge()
        #: puts frames swapped on the way back in counter order before the decoder
        #: (:mod:`canrls.processor.reorder`; ``reorder.moved`` counts them)
        self.reorder = Reorderer(protocol.messages)
        self.frames = 0
        #: the log being read, which an error of its frames names (None: a bus)
        self.source: str | None = None
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
        #: the rejections of the streams before this one, by message (:meth:`restart`)
        self._past_rejects = RejectCounts()
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
        """The sample processor of ``model`` at ``period``: its model with the DBC's
        ranges, where they come from, and its pipeline before any sample depend on the
        configuration alone, so they are built once for it (:data:`STARTS_KEPT`) and
        shared, never run (:class:`SampleProcessor`'s ``start``)."""
        config = (self.protocol, model, self._settings0)
        key = (id(self.protocol), id(model), id(self._settings0), period)
        got = _STARTS.get(key)
        if got is None or any(a is not b for a, b in zip(got.config, config, strict=True)):
            dbc = dbc_ranges(model, self.protocol)
            sources = {k: ("config" if k in model.ranges_given else "dbc" if k in dbc else
                           "default") for k in model.ranges}
            start = Pipeline(model.with_ranges(dbc) if dbc else model, period,
                             self._settings0 or EstimatorSettings())
            got = _Start(config, sources, start)
            with _STARTS_LOCK:
                _STARTS.pop(key, None)
                while len(_STARTS) >= STARTS_KEPT:
                    del _STARTS[next(iter(_STARTS))]
                _STARTS[key] = got
        return SampleProcessor(got.pipeline.model, period, got.pipeline.settings,
                               got.sources, start=got.pipeline)

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
        try:  # what the frames' times say, of the log being read
            est = self._meter.estimate()
            counts = self._meter.counts()
            self._meter = None
            self.period_estimate = est
            if est is not None and self.pairer is not None:
                check_period(self.pairer.period, self.period_source or "the period", est)
        except ConfigError as e:
            raise self._of_source(e) from e
        if self.pairer is not None:
            return
        if est is None:
            if not any(counts.values()):
                raise self._foreign_error()
            raise self._of_source(ConfigError(
                "cannot measure the control period: the log has only "
                + ", ".join(f"{n} frames of {m}" for m, n in counts.items())
                + f" (at least {MIN_INTERVALS + 1} of one message are needed); "
                  "state it with --period SECONDS"))
        self._start(est.period)

    def _of_source(self, e: ConfigError) -> ConfigError:
        """``e`` naming the log being read (:attr:`source`), if any."""
        return e if self.source is None else type(e)(f"{self.source}: {e}")

    def missing_messages(self) -> str | None:
        """What to say when some mapped messages decoded frames and others none (a
        sample needs them all): each missing one with its ID and roles, whether it never
        came or came and was rejected (its frames by reason, an example naming the
        signal), and the frames of the others; None when every mapped message decoded
        frames (or none did)."""
        counts = self.message_frames
        if not any(counts.values()):
            return None
        missing = [m for m in self.protocol.messages if counts[m.name] == 0]
        if not missing:
            return None
        rej = RejectCounts()
        rej.merge(self._past_rejects)
        rej.merge(self.decoder.rejected)

        def named(m: MessageCodec) -> str:
            roles = [r for r, i in self.protocol.roles.items() if i.message == m.name]
            return f"{m.name} (0x{m.frame_id:X}: {', '.join(roles)})"

        never = [m for m in missing if not sum(rej.per_message.get(m.name, {}).values())]
        said = []
        if never:
            said.append(f"mapped message{'s' if len(never) > 1 else ''} "
                        f"{', '.join(named(m) for m in never)} never "
                        f"occur{'' if len(never) > 1 else 's'}")
        for m in missing:
            if m in never:
                continue
            per = {r: n for r, n in rej.per_message[m.name].items() if n}
            # the earliest example of its first reason, where it is this message's
            ex = rej.examples.get(next(iter(per)), "")
            said.append(f"mapped message {named(m)} arrives but decodes no frame: every "
                        f"one of its {sum(per.values())} frames is rejected ("
                        + ", ".join(f"{r} {n}" for r, n in per.items())
                        + (f"; e.g. {ex}" if ex.startswith(f"{m.name}.") else "") + ")")
        seen = ", ".join(f"{n} {c} frames" for n, c in counts.items() if c)
        fix = (["map the signal to a message the drive sends, or leave its role out"]
               if never else [])
        if len(never) < len(missing):
            fix.append("check the DBC's scale and range of its signals against the drive's")
        return (f"{'; '.join(said)} in the {self.frames} frames read (seen: {seen}): a "
                f"sample needs every mapped message; {'; '.join(fix)}")

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
        rej = {k: int(v) for k, v in self.decoder.rejected.items() if v}
        return unmapped_error(self.protocol, self.frames, self.seen_ids(), rej, self.source)

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
        carries them (:data:`canrls.can.estimator_frames.REJECT_FIELDS`; running totals)."""
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

    def frames_rejected(self) -> int:
        """Frames rejected so far, every reason: the sum of :meth:`frame_counts`'s
        ``rejected``, without building the counts (each publication asks)."""
        return sum(self._past.rejected.values()) + sum(int(v) for v in self.rejected.values())

    def frames_lost(self) -> int:
        """Frames lost so far (counter gaps): the sum of :meth:`frame_counts`'s ``lost``."""
        return sum(self._past.lost.values()) + sum(int(v) for v in self.decoder.lost.values())

    def restart(self) -> None:
        """A new stream (the next log): time judge, reorderer, decoder and pairer start
        afresh, none of their state carried over; the period stays decided, and the
        frame counts go on (:meth:`frame_counts`)."""
        self._past = dataclasses.replace(self.frame_counts(), messages={}, missing=None)
        self._past_rejects.merge(self.decoder.rejected)
        self.decoder = Decoder(self.protocol)
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
        relative units refer to and, on a torque-reporting drive, the output."""
        output = None
        if self.model.output == "torque":
            t = self.protocol.roles["torque"]
            lin = self.model.axis == "linear"
            output = (f"the {'force' if lin else 'torque'} the drive reports, "
                      f"{t.message}.{t.signal} [{'N' if lin else 'N·m'}], no Kt")
        return AxisInfo(self.model.axis, self.protocol.axis,
                        {r: i.unit for r, i in self.protocol.roles.items()},
                        self.protocol.mapping.ratings.as_dict(), output,
                        self.model.per_ampere_text if self.model.per_ampere else None)

    def start_info(self) -> StartInfo:
        """The first frame's timestamp and, for an epoch time, its date (UTC)."""
        return StartInfo(self.origin, epoch_date(self.origin), self.relative_time)

    def result(self, source: str) -> FitResult:
        """The estimates so far, with the frames, period, start and axis."""
        return FitResult(estimates=self.pipeline.estimates(), frames=self.frame_counts(),
                         source=source, model=self.model, period=self.period_info(),
                         start=self.start_info(), axis=self.axis_info(),
                         calibration=self.calibration)
