r"""The control period from the frames' timestamps.

:class:`PeriodMeter` measures it on the first :data:`PERIOD_FRAMES` frames of each
mapped message, causally, so the daemon and the offline replay measure the same period;
:func:`estimate_period` counts whole periods over the span, robust to jitter, dropped
frames, bursts and relayed groups. The front end (:class:`canrls.processor.FrameProcessor`)
is the one place that runs it (docs/architecture.md, "Control period").
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt

from canrls.core.checks import positive_period
from canrls.core.errors import ConfigError

__all__ = ["ControlPeriod", "DEFAULT_PERIOD", "control_period", "PERIOD_FRAMES",
           "PERIOD_TOLERANCE", "MIN_INTERVALS", "BURST_SHARE", "PeriodEstimate", "PeriodMeter",
           "estimate_period", "check_period", "STEP_BACK", "STEP_FORWARD"]

#: Frames of each mapped message the period is measured on (the first ones).
PERIOD_FRAMES = 256

#: Largest relative difference between a stated period and the measured one.
PERIOD_TOLERANCE = 0.10

#: Fewest intervals of a message that give it a measured period.
MIN_INTERVALS = 8

#: Share of intervals shorter than half the mean interval above which a message's frames
#: are taken as relayed in groups: the period is then the slope of the times against the
#: frame index (docs/architecture.md, "Control period").
BURST_SHARE = 0.05

#: An interval back by more than this many times the 90th percentile of the intervals'
#: sizes, or forward by more than :data:`STEP_FORWARD` times, is a clock step: the
#: meter measures on either side of it and never across (:func:`_segments`).
STEP_BACK = 4.0
STEP_FORWARD = 100.0

F64 = npt.NDArray[np.float64]


@dataclass(frozen=True)
class PeriodEstimate:
    """The measured period [s], its jitter (RMS of the intervals' deviation from whole
    periods, [s]) and what it was measured on (``{message: intervals}``)."""

    period: float
    jitter: float
    intervals: Mapping[str, int] = field(default_factory=dict)
    per_message: Mapping[str, float] = field(default_factory=dict)

    def format(self) -> str:
        n = sum(self.intervals.values())
        return (f"{self.period * 1e3:.6g} ms (measured on {n} frame intervals of "
                f"{', '.join(self.intervals)}; jitter {self.jitter * 1e6:.3g} µs RMS)")


def _segments(t: F64) -> list[F64]:
    """A message's frame times in stream order, split at clock steps, each piece sorted.

    A step is an interval back by more than :data:`STEP_BACK` times, or forward by more
    than :data:`STEP_FORWARD` times, the 90th percentile of the intervals' sizes (a scale
    that jitter, drops and bursts leave near the period): a clock stepped by NTP or a
    merged log, measured across, would give the step as a span of periods. Sorting
    within a piece keeps frames reordered by a period or so measurable."""
    if len(t) < 2:
        return [np.sort(t)]
    d = np.diff(t)
    q = float(np.quantile(np.abs(d), 0.9))
    cut = np.flatnonzero((d < -STEP_BACK * q) | (d > STEP_FORWARD * q)) + 1
    if not len(cut) or not q > 0:
        return [np.sort(t)]
    return [np.sort(piece) for piece in np.split(t, cut) if len(piece)]


def _one(t: F64) -> tuple[float, float] | None:
    r"""(period, jitter) of one message's frame times (stream order), None if too few or
    no span. With the intervals :math:`d_i` and the span, from the mean interval,

    .. math::

        k_i = \operatorname{round}(d_i / p), \qquad p = \mathrm{span} / \textstyle\sum_i k_i

    iterated: jitter rounds to one period, a dropped frame to two, a burst to zero and
    the gap before it to several. The pieces between clock steps (:func:`_segments`)
    are measured together: their intervals pooled, their spans summed, the slope
    fitted within each."""
    t = np.asarray(t, np.float64)
    t = t[np.isfinite(t)]  # a frame without a time says nothing of the period
    if len(t) < MIN_INTERVALS + 1:
        return None
    parts = [piece for piece in _segments(t) if len(piece) >= 2]
    if not parts:
        return None
    if len(parts) == 1:
        t = parts[0]
        d = np.diff(t)
        span = float(t[-1] - t[0])
    else:
        d = np.concatenate([np.diff(piece) for piece in parts])
        span = float(sum(float(piece[-1] - piece[0]) for piece in parts))
    if len(d) < MIN_INTERVALS or not span > 0:
        return None
    p = span / len(d)
    if float(np.mean(d < 0.5 * p)) > BURST_SHARE:
        # relayed in groups: one period per frame, p the slope of the times against the
        # frame index (least squares: a group's frames wait for its last, a saw tooth
        # that the slope averages out, where the end points alone would carry it);
        # pooled over the pieces, each about its own mean
        num = den = 0.0
        devs = []
        cen = []
        for piece in parts:
            i = np.arange(len(piece), dtype=np.float64)
            i -= i.mean()
            tc = piece - piece.mean()
            num += float(np.dot(i, tc))
            den += float(np.dot(i, i))
            cen.append((i, tc))
        p = num / den
        for i, tc in cen:
            devs.append(tc - p * i)  # the relay's latency: the jitter
        dev = np.concatenate(devs)
        return p, float(np.sqrt(np.mean(dev * dev)))
    for _ in range(20):
        k = np.rint(d / p)
        total = float(k.sum())
        if total <= 0:
            return None
        p_new = span / total
        if p_new == p:
            break
        p = p_new
    k = np.rint(d / p)
    jitter = float(np.sqrt(np.mean((d - k * p) ** 2)))
    return p, jitter


def estimate_period(times: Mapping[str, Sequence[float] | F64]) -> PeriodEstimate | None:
    """The period of frames ``{message: times}``: the shortest of the messages' (a
    :class:`ConfigError` when one is over 1.5 times it); None when no message has
    :data:`MIN_INTERVALS` intervals over a span (docs/architecture.md, "Control
    period")."""
    got = {name: r for name, t in times.items() if (r := _one(np.asarray(t))) is not None}
    if not got:
        return None
    periods = {name: r[0] for name, r in got.items()}
    p = min(periods.values())
    if max(periods.values()) > 1.5 * p:
        raise ConfigError(
            "the mapped messages come at different periods ("
            + ", ".join(f"{name} every {v * 1e3:.4g} ms" for name, v in periods.items())
            + "); pairing needs one frame of each per control period: map signals of "
              "messages sent at the control period")
    jit = float(max(r[1] for r in got.values()))
    return PeriodEstimate(p, jit, {name: len(times[name]) - 1 for name in got}, periods)


def check_period(stated: float, source: str, measured: PeriodEstimate) -> None:
    """Raise :class:`ConfigError` naming ``source`` (``--period``, the DBC...) when the
    stated period and the measured one differ by more than :data:`PERIOD_TOLERANCE`."""
    rel = abs(stated - measured.period) / measured.period
    if rel > PERIOD_TOLERANCE:
        raise ConfigError(
            f"{source} gives a control period of {stated * 1e3:.6g} ms but the log's "
            f"timestamps say {measured.format()}: they differ by {rel:.0%} (more than "
            f"{PERIOD_TOLERANCE:.0%}); state the right period (--period SECONDS) or leave it "
            f"out to use the measured one")


class PeriodMeter:
    """Collects the times of the first :data:`PERIOD_FRAMES` frames of each message.

    :meth:`add` takes a block's frame times per message; :attr:`done` once every message
    has its frames (or one of them has, and a message that never came is not waited
    for past ``4 * PERIOD_FRAMES`` frames of the others); :meth:`estimate` measures.
    """

    def __init__(self, messages: Sequence[str], frames: int = PERIOD_FRAMES) -> None:
        self.frames = int(frames)
        self._t: dict[str, list[F64]] = {m: [] for m in messages}
        self._n: dict[str, int] = dict.fromkeys(messages, 0)

    @property
    def done(self) -> bool:
        n = self._n.values()
        return all(k >= self.frames for k in n) or max(n, default=0) >= 4 * self.frames

    def add(self, times: Mapping[str, F64]) -> None:
        for m, t in times.items():
            if m in self._n and self._n[m] < self.frames and len(t):
                take = np.asarray(t[: self.frames - self._n[m]], np.float64)
                self._t[m].append(take)
                self._n[m] += len(take)
            elif m in self._n:
                self._n[m] += len(t)  # counted for the cut-off of `done`

    def estimate(self) -> PeriodEstimate | None:
        return estimate_period({m: np.concatenate(v) for m, v in self._t.items() if v})

    def counts(self) -> dict[str, int]:
        """Frames seen per message (measured or not)."""
        return dict(self._n)


#: The control period [s] of a model exported without one stated, measured or in the DBC.
DEFAULT_PERIOD = 1e-3


@dataclass(frozen=True)
class ControlPeriod:
    """The control period a model runs at outside a stream of frames, and who said so."""

    value: float
    #: ``"--dt"``, ``"the fit's"`` (measured on the log), ``"the DBC's cycle time"`` or
    #: ``"the default"``
    source: str


def control_period(*, given: float | None = None, given_by: str = "--dt",
                   measured: float | None = None, dbc: float | None = None) -> ControlPeriod:
    """The one decision of the period of an export and of a fit's target path: the period
    ``given`` (``given_by`` names it), else the one ``measured`` on the log (a fit's),
    else the DBC's cycle time, else :data:`DEFAULT_PERIOD`; each checked by
    :func:`~canrls.core.checks.positive_period`. (On a stream of frames the processor
    measures it: :class:`~canrls.processor.frames.FrameProcessor`.)"""
    for value, source in ((given, given_by), (measured, "the fit's"),
                          (dbc, "the DBC's cycle time")):
        if value is not None:
            return ControlPeriod(positive_period(value, source), source)
    return ControlPeriod(DEFAULT_PERIOD, "the default")
