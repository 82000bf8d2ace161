"""What the daemon says on the bus, on schedule: parameters, status, parameter info.

Every ``publish_interval`` (0: after every block): ``RlsEstimate``/``RlsSigma``/
``RlsReference`` (every parameter: fixed point, sigma, float), then ``RlsStatus`` and
``RlsHealth``; every ``info_interval`` (and at once after a model change) also
``RlsParamInfo``, ``RlsCounters`` and ``RlsRejects``. Everything comes from the public
results of the pipeline (:meth:`~canrls.estimation.pipeline.Pipeline.estimates`) and of each block
(:class:`~canrls.estimation.pipeline.PipelineBlock`); the frames go out through
:meth:`canrls.live.bus_link.BusLink.send`, which never blocks.
"""

from __future__ import annotations

import logging
import math
import time
import typing
from collections.abc import Callable

from canrls.can.estimator_frames import (
    ParameterReport,
    StatusReport,
    encode_param_info,
    encode_parameters,
    encode_status,
    frame_ids,
)
from canrls.can.frameblock import FrameBlock
from canrls.core.effect_names import EffectId, EquationId
from canrls.core.errors import CanrlsError, ConfigError
from canrls.estimation.estimates import (
    Estimates,
    ParameterEstimate,
    PipelineBlock,
    divergence,
)
from canrls.estimation.model import Model
from canrls.estimation.physics import check_physics
from canrls.estimation.pipeline import Pipeline
from canrls.estimation.rls import RLSFlag
from canrls.live.bus_link import BusLink
from canrls.live.daemon_settings import DaemonSettings
from canrls.processor import FrameProcessor

__all__ = ["Publisher", "FixedPath", "check_publishable", "model_layout", "parameter_layout"]

log = logging.getLogger(__name__)

_COUNTERS_ID = frame_ids().counters
_REJECTS_ID = frame_ids().rejects
_WINDUP = int(RLSFlag.WINDUP)
#: the longest the estimator sleeps without a publication due [s]
_IDLE_S = 0.25


class FixedPath(typing.Protocol):
    """The fixed-point column computed from the frames themselves (``canrls run``: the
    target's integer path, :class:`canrls.firmware.target_live.LiveTarget`)."""

    def feed(self, block: FrameBlock, proc: FrameProcessor) -> None:
        """The frames of a block the processor has processed."""

    def restart(self, float_kept: bool = False) -> None:
        """A new model runs (``float_kept``: the float estimate keeps its values), or
        the estimators were reset."""

    def settling(self) -> frozenset[str]:
        """The equations whose path, started again while the float kept its values, has
        not caught up yet: their float-vs-fixed divergence is not judged."""

    def state(self) -> dict[str, typing.Any] | None:
        """What a checkpoint keeps to continue the path (None: nothing to keep)."""

    def resume(self, saved: typing.Any, proc: FrameProcessor) -> str | None:
        """Continue from a checkpoint's :meth:`state` on ``proc``, the processor restored
        from it; why it starts again instead (None: it continues)."""

    def fixed(self) -> dict[str, tuple[float, bool]] | None:
        """``{parameter: (fixed value in SI, valid)}``; None: the kernel's column stands."""


def parameter_layout(pipeline: Pipeline) -> tuple[tuple[ParameterReport, ...], ...]:
    """The pipeline's parameters as reports without estimates, a tuple per equation."""
    return model_layout(pipeline.model)


def model_layout(model: Model) -> tuple[tuple[ParameterReport, ...], ...]:
    """A model's parameters as reports without estimates, a tuple per equation."""
    rows: list[tuple[ParameterReport, ...]] = []
    i = 0
    for eq in model.equations:
        params = eq.parameters
        rows.append(tuple(
            ParameterReport(index=i + k, name=p.name, effect_id=EffectId(p.effect_id),
                            component=p.component, order=p.order,
                            equation=EquationId(p.equation_index), unit=p.unit)
            for k, p in enumerate(params)))
        i += len(params)
    return tuple(rows)


def check_publishable(model: Model, max_parameters: int, what: str = "the model") -> None:
    """Raise :class:`~canrls.core.errors.ConfigError` unless the daemon can publish ``model``:
    at most ``max_parameters`` parameters (``[daemon] max_parameters``), and every frame
    it would send encodes (a rehearsal with made-up values; nothing is sent).

    Called before a model becomes the running one (start, command, reload, resume from
    a checkpoint) and before a checkpoint is written, so that a model that cannot be
    published never runs, nor comes back at the next start.
    """
    n = len(model.parameters)
    if n > max_parameters:
        raise ConfigError(f"{what} ({','.join(model.effect_names)}) has {n} parameters, more "
                          f"than [daemon] max_parameters = {max_parameters}")
    reports: list[ParameterReport] = []
    for blanks in model_layout(model):
        reports += [r.with_estimates(0.0, 0.0, 0.0, True) for r in blanks]
    try:
        encode_parameters(reports, 0)
        encode_param_info(reports)
        encode_status(StatusReport(active_effects=model.active_effects), 0)
    except CanrlsError as e:
        raise ConfigError(f"{what} ({','.join(model.effect_names)}) cannot be published: "
                          f"{e}") from e


class Publisher:
    """Parameter and status frames of one processor, on schedule.

    :param processor: whose pipeline is published (its model may change).
    :param config: ``publish_interval``, ``info_interval``, ``divergence_limit``.
    :param link: sends the frames and tells whether transmission is paused.
    :param counters: the wire counters (``frames_rejected``, ``frames_lost``,
        ``saturations``, ``tx_dropped``) as ``RlsCounters`` carries them.
    :param on_publish: called after each publication with ``(frames processed so far,
        time.monotonic() when its parameter frames had been sent)`` (benchmarks).
    :param fixed_path: where the fixed column comes from (None: the pipeline's kernel).
    """

    def __init__(self, processor: FrameProcessor, config: DaemonSettings, link: BusLink,
                 counters: Callable[[], dict[str, int]],
                 on_publish: Callable[[int, float], None] | None = None,
                 fixed_path: FixedPath | None = None) -> None:
        self.processor = processor
        self.fixed_path = fixed_path
        self.config = config
        self.link = link
        self.counters = counters
        self.on_publish = on_publish
        #: publications sent
        self.publications = 0
        #: the status of the last publication
        self.last_status: StatusReport | None = None
        self.next_at = 0.0
        self.info_due = 0.0
        self._asap = False
        self._counter = 0
        self._online_rms = [math.nan] * len(processor.model.equations)
        self._window_windup = False
        self._low_excitation = False
        self._last_lost = 0
        self._last_sat = 0
        self._last_clock = 0  # clock steps and time rejects as the last RlsRejects had them
        #: (pipeline, parameter_layout, active effects), made again when the model changes
        self._layout: tuple[Pipeline | None, tuple[tuple[ParameterReport, ...], ...], int] = (
            None, (), 0)
        #: (pipeline, equations whose non-finite samples were logged)
        self._warned: tuple[Pipeline | None, set[str]] = (None, set())

    # ------------------------------------------------------------------ schedule
    def start(self, now: float) -> None:
        """The first publication after one interval, then every interval on a fixed grid
        (``now + k publish_interval``; publications forced by a model change come in
        between and never move it); the parameter info at once."""
        self.next_at = now + self.config.publish_interval
        self.info_due = now

    def deadline(self, now: float) -> float:
        """When the next publication is due, at the latest: a time at which :meth:`due`
        holds, never one before it (the estimator sleeps until then).

        The parameter info rides on a publication: on the grid (``publish_interval``
        > 0) it goes with the first publication at or after ``info_due``, so that time
        is no deadline of its own (it would wake the estimator with nothing due, again
        and again until the next publication). With ``publish_interval = 0`` every
        wake-up publishes, so the info's time is one."""
        if self.config.publish_interval > 0:
            return self.next_at if not self._asap else now
        return min(now + _IDLE_S, self.info_due)

    def due(self, now: float) -> bool:
        return self.config.publish_interval == 0 or now >= self.next_at or self._asap

    # ------------------------------------------------------------------ inputs
    def absorb(self, out: PipelineBlock) -> None:
        """Keep what the status carries from a processed block: online RMS, windup."""
        for k, eb in enumerate(out.equations):
            if len(eb.online_rms):
                self._online_rms[k] = float(eb.online_rms[-1])
            if len(eb.flags) and (eb.flags & _WINDUP).any():
                self._window_windup = True

    def clear_rms(self) -> None:
        """The estimators restarted (reset): no online RMS yet."""
        self._online_rms = [math.nan] * len(self.processor.model.equations)

    def model_changed(self) -> None:
        """A new model runs: publish, with its parameter info, at once."""
        self.clear_rms()
        self.info_due = time.monotonic()
        self._asap = True

    # ------------------------------------------------------------------ content
    def _layout_of(self, pipe: Pipeline
                   ) -> tuple[Pipeline | None, tuple[tuple[ParameterReport, ...], ...], int]:
        layout = self._layout
        if layout[0] is not pipe:
            layout = (pipe, parameter_layout(pipe), pipe.model.active_effects)
            self._layout = layout
        return layout

    def reports(self, params: tuple[tuple[ParameterEstimate, ...], ...] | None = None
                ) -> tuple[list[ParameterReport], float]:
        """The parameters as published, and the largest float-vs-fixed divergence;
        ``params``: the pipeline's :meth:`~canrls.estimation.pipeline.Pipeline.parameters`
        if known (a publication computes them once)."""
        pipe = self.processor.pipeline
        if params is None:
            params = pipe.parameters()
        out: list[ParameterReport] = []
        divs: list[float] = []
        path, settling = None, frozenset[str]()
        if self.fixed_path is not None:
            path = self.fixed_path.fixed()
            settling = self.fixed_path.settling() if path is not None else settling
        for equation, blanks, eq, (_, fixed_updates) in zip(
                pipe.model.equations, self._layout_of(pipe)[1], params, pipe.update_counts(),
                strict=True):
            fixed = [(p.fixed, fixed_updates > 0) if path is None
                     else path.get(p.name, (math.nan, False)) for p in eq]
            out += [b.with_estimates(f, p.sigma, p.value, ok and math.isfinite(f))
                    for b, p, (f, ok) in zip(blanks, eq, fixed, strict=True)]
            if equation.name in settling:
                continue  # the path started again from its prior: not caught up yet
            # in physical units: the same as in normalised ones (powers of two apart)
            divs.append(divergence([p.value for p in eq], [f for f, _ in fixed],
                                   [p.sigma for p in eq]))
        return out, max(divs, default=0.0)

    def status(self, now: float, div: float | None = None,
               params: tuple[tuple[ParameterEstimate, ...], ...] | None = None) -> StatusReport:
        """The status as the next publication would carry it (no side effect);
        ``div``: the divergence if known (:meth:`reports`), ``params`` the parameters."""
        pipe = self.processor.pipeline
        counters = self.counters()
        rejects = self.processor.reject_counts()
        if params is None:
            params = pipe.parameters()
        if div is None:
            div = self.reports(params)[1]
        return StatusReport(
            residual_rms=self._online_rms[0],
            update_count=pipe.update_counts()[0][0],
            windup=self._window_windup,
            low_excitation=self._low_excitation,
            saturation=counters["saturations"] > self._last_sat,
            frame_loss=counters["frames_lost"] > self._last_lost,
            frozen=pipe.frozen,
            diverged=div > self.config.divergence_limit,
            bus_fault=self.link.paused(now),
            # since the last RlsRejects: a clock step, or a frame rejected for its time
            clock_fault=rejects["clock_steps"] + rejects["time"] > self._last_clock,
            implausible=bool(check_physics([p for eq in params for p in eq], pipe.model.kt)),
            active_effects=self._layout_of(pipe)[2],
            divergence=div if math.isfinite(div) else 0.0,
            rejects=rejects, **counters)

    def _warn_nonfinite(self, est: Estimates) -> None:
        pipe = self.processor.pipeline
        if self._warned[0] is not pipe:
            self._warned = (pipe, set())
        warned = self._warned[1]
        for fit in est.equations:
            if fit.nonfinite_rows and fit.equation not in warned:
                warned.add(fit.equation)
                log.warning("the %s equation met a non-finite term value (a user term "
                            "outside its domain?): such samples, and the filter's warm-up "
                            "after each, are left out", fit.equation)

    # ------------------------------------------------------------------ sending
    def publish(self, now: float) -> None:
        """Send the parameter frames, then the status frames (and, every
        ``info_interval``, RlsParamInfo, RlsCounters and RlsRejects)."""
        info = now >= self.info_due
        self.link.settle(now)
        params = self.processor.pipeline.parameters()
        reports, div = self.reports(params)
        ts = time.time()
        self._counter = (self._counter + 1) % 16
        self.link.send(encode_parameters(reports, self._counter, timestamp=ts))
        sent = time.monotonic()
        if info:
            est = self.processor.pipeline.estimates()  # the fit statistics, once in a while
            self._low_excitation = any(f.low_excitation for f in est.equations)
            self._warn_nonfinite(est)
        status = self.status(now, div, params)
        self._window_windup = False
        self._last_lost = status.frames_lost
        self._last_sat = status.saturations
        self.last_status = status
        msgs = [m for m in encode_status(status, self._counter, timestamp=ts)
                if info or m.arbitration_id not in (_COUNTERS_ID, _REJECTS_ID)]
        if info:
            self._last_clock = status.rejects["clock_steps"] + status.rejects["time"]
            msgs += encode_param_info(reports, timestamp=ts)
            self.info_due = now + self.config.info_interval
        self.link.send(msgs)
        self.publications += 1
        self._asap = False
        step = self.config.publish_interval
        if step > 0 and now >= self.next_at:
            # the regular schedule is a fixed grid, start + k step: a publication forced
            # by a model change (before next_at) leaves it alone, and a slot missed by a
            # long block is skipped, never shifted
            # next_at <- next_at + (floor((now - next_at) / step) + 1) step
            self.next_at += (math.floor((now - self.next_at) / step) + 1) * step
        if self.on_publish is not None:
            self.on_publish(self.processor.frames, sent)
