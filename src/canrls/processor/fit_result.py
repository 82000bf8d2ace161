"""What a replay produced: the estimates with the frame counts (:class:`FrameCounts`),
the control period, the start and the axis, as :class:`FitResult` renders them."""

from __future__ import annotations

import dataclasses
import datetime
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

from canrls.core.checks import is_epoch
from canrls.core.units import Ratings
from canrls.estimation.estimates import Estimates
from canrls.estimation.model import Model
from canrls.processor.calibration import Calibration

__all__ = ["FrameCounts", "PeriodInfo", "StartInfo", "AxisInfo", "FileShift", "FitResult",
           "KernelFallback", "MachineFit", "TargetRun", "epoch_date"]


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
    #: the pairing's counts (:meth:`~canrls.processor.pairing.PairingCounts.as_dict`)
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
    to and, on a drive that reports its torque, the mechanical output."""

    axis: str
    dbc_axis: str | None = None
    units: dict[str, str | None] = field(default_factory=dict)
    ratings: dict[str, float] = field(default_factory=dict)
    output: str | None = None
    #: :attr:`~canrls.estimation.model.Model.per_ampere_text` when the mechanical
    #: parameters are per ampere, else None
    per_ampere: str | None = None

    def to_dict(self) -> dict[str, Any]:
        d = dataclasses.asdict(self)
        if self.output is None:
            del d["output"]
        return d

    def format(self) -> list[str]:
        units = ", ".join(f"{r} {u}" for r, u in self.units.items() if u)
        lines = [f"axis {self.axis}" + (f" (DBC units: {units})" if units else "")]
        if self.ratings:
            lines.append("ratings: " + Ratings(**self.ratings).describe(self.axis))
        if self.output:
            lines.append(f"mechanical output: {self.output}")
        if self.per_ampere:
            lines.append(self.per_ampere)
        return lines


@dataclass(frozen=True)
class FileShift:
    """One log of several fitted as one record, and the time it was moved by [s]."""

    path: str
    time_shift_s: float


@dataclass(frozen=True)
class TargetRun:
    """What the target's integer path ran when it gave a fit's fixed column
    (``canrls fit`` by default, :mod:`canrls.firmware.target_fit`)."""

    samples: int
    #: updates and rescales of each equation's estimator
    updates: dict[str, int] = field(default_factory=dict)
    rescales: dict[str, int] = field(default_factory=dict)
    #: frames it rejected or dropped, by reason
    rejected: dict[str, int] = field(default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        return {"path": "target", **dataclasses.asdict(self)}

    def format(self) -> str:
        parts = [f"{self.samples} samples", f"updates: {_by_name(self.updates)}",
                 f"rescales: {_by_name(self.rescales)}"]
        if self.rejected:
            parts.append(f"frames rejected or dropped: {_by_name(self.rejected)}")
        return f"fixed point: the target's integer path from the frames on ({'; '.join(parts)})"


def _by_name(counts: dict[str, int]) -> str:
    """``counts`` as a person reads them: "mechanical 19935, electrical 19935"."""
    return ", ".join(f"{name} {count}" for name, count in counts.items()) or "none"


@dataclass(frozen=True)
class KernelFallback:
    """The fit's fixed column is the kernel's on the float front end: the target's
    integer path, the default, does not run this model (``why``)."""

    why: str

    def to_dict(self) -> dict[str, Any]:
        return {"path": "kernel", "why": self.why}

    def format(self) -> str:
        return (f"fixed point: the kernel on the float front end (the target's integer path "
                f"does not run this model: {self.why})")


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
    #: the target's run, when it gave the fixed column; why not, when it could not (None:
    #: the kernel's, asked for by name)
    fixed: TargetRun | KernelFallback | None = None

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
        if self.fixed is not None:
            d["fixed"] = self.fixed.to_dict()
        return d

    def format(self) -> str:
        """The answer first (every parameter with sigma, then each equation's fit), then
        what the replay read: the frames, the axis and units, the period, the calibration."""
        fr = self.frames
        lines = [self.estimates.format(),
                 f"{self.source}: {fr.total} frames, {self.estimates.samples} samples used"]
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
        return "\n".join(lines)

    __str__ = format


@dataclass(frozen=True)
class MachineFit:
    """Every axis of a machine fitted in one pass over its bus's logs
    (:func:`canrls.processor.replay.fit_axes`): each axis's :class:`FitResult`, the
    frames read and those of no axis (counted, never decoded into one)."""

    source: str
    total: int
    #: frames whose ID is no axis's feedback message (error frames aside)
    unknown: int
    fits: dict[str, FitResult]
    #: axes whose fit is no answer, with why (too few usable samples)
    errors: dict[str, str] = field(default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        return {"source": self.source,
                "frames": {"total": self.total, "unknown_axis": self.unknown},
                "axes": {n: ({"error": self.errors[n]} if n in self.errors else f.to_dict())
                         for n, f in self.fits.items()}}

    def format(self) -> str:
        ok = len(self.fits) - len(self.errors)
        lines = [f"{self.source}: {ok} of {len(self.fits)} axes identified, {self.total} "
                 f"frames, {self.unknown} of no axis"]
        for n, f in self.fits.items():
            lines += ["", f"== axis {n} ==",
                      f"error: {self.errors[n]}" if n in self.errors else f.format()]
            if n not in self.errors and f.fixed is not None:
                lines.append(f.fixed.format())
        return "\n".join(lines)


def epoch_date(t: float | None) -> str | None:
    """``"2023-11-14 22:13:20.123456 UTC"`` for a timestamp that is an epoch time (after
    1973), else None (a log whose times start near zero)."""
    if t is None or not is_epoch(t):
        return None
    d = datetime.datetime.fromtimestamp(t, tz=datetime.UTC)
    return d.strftime("%Y-%m-%d %H:%M:%S.%f UTC")
