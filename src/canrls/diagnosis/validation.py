"""Validation: a saved model predicts other logs, without estimating anything.

``canrls validate LOG [LOG ...] --model FILE`` (:mod:`canrls.cli.validate`). The logs are
decoded and paired as ``canrls fit`` does (:class:`canrls.processor.replay.LogFiles`: one record,
no segment bridged across files), the model's filtered columns are built with the
saved ranges and scaling (the same columns the estimator saw), and the saved physical
parameters predict the filtered output:

.. math::

    \\hat y = \\Phi \\theta_{saved}, \\qquad r = y - \\hat y, \\qquad
    \\mathrm{fit} = 100 \\left(1 - \\frac{\\lVert r \\rVert}{\\lVert y - \\bar y \\rVert}\\right)

on the rows the estimator would use (its warm-up, gap and speed rules). Where it fails
is told by the diagnosis's machinery (:func:`canrls.diagnosis.residual.find_regions`:
residual binned by speed, position, current, acceleration and time).

The report renders as the diagnosis's does: text (:meth:`ValidationReport.format`), a
dict of plain types (:meth:`ValidationReport.to_dict`) and a directory with
``index.html`` and SVG figures (:func:`write_html`, ``canrls validate --report DIR``),
drawn by the diagnosis's :class:`~canrls.diagnosis.figures.Figures` into the page
``templates/validate.html.j2``.
"""

from __future__ import annotations

import math
import os
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from canrls.can.protocol import Protocol
from canrls.core.checks import finite_or_none
from canrls.core.errors import ConfigError, EstimatorError
from canrls.core.files import atomic_writer, staged_dir
from canrls.core.samples import ROLES, Signals
from canrls.core.spill import ColumnLike, SpilledSignals
from canrls.diagnosis.figures import Figures, figures_in
from canrls.diagnosis.record import RecordSamples
from canrls.diagnosis.report import CAPTIONS, page_template
from canrls.diagnosis.residual import all_bins, find_regions
from canrls.diagnosis.results import Binned, Region, Traces, r2_text, share_text, value_text
from canrls.estimation.physics import Implausible, check_physics, describe
from canrls.processor import FrameCounts, PeriodInfo, StartInfo
from canrls.processor.modelfile import SavedModel
from canrls.processor.replay import read_logs

__all__ = ["HOLDS_WITHIN", "EquationValidation", "FileFit", "ValidationReport", "validate_logs",
           "validate_signals", "write_html"]

F64 = npt.NDArray[np.float64]

#: a saved model holds on other logs while their residual RMS is at most this much above
#: the RMS at identification (recordings of one drive differ in noise by about this)
HOLDS_WITHIN = 0.25


@dataclass(frozen=True)
class FileFit:
    """Fit of the saved model on one log."""

    source: str
    samples: int
    residual_rms: float
    fit_percent: float
    #: the output's standard deviation on this log: what its fit % is measured against
    output_sd: float = math.nan

    def to_dict(self) -> dict[str, Any]:
        return {"source": self.source, "samples": self.samples,
                "residual_rms": finite_or_none(self.residual_rms),
                "fit_percent": finite_or_none(self.fit_percent),
                "output_sd": finite_or_none(self.output_sd)}


@dataclass(frozen=True)
class EquationValidation:
    """The saved model against the data, for one equation."""

    equation: str
    unit: str
    samples: int
    residual_rms: float
    fit_percent: float
    r2: float
    #: residual RMS when the model was identified (the saved file's), for comparison
    identified_rms: float | None
    files: tuple[FileFit, ...]
    regions: tuple[Region, ...]
    #: the filtered output's name, and the arrays and bins the figures draw (not in JSON)
    output: str = ""
    traces: Traces | None = field(default=None, repr=False, compare=False)
    bins: Mapping[str, Binned] = field(default_factory=dict, repr=False, compare=False)
    #: first row of each file in ``traces`` (and the end)
    bounds: tuple[int, ...] = ()
    #: the output's standard deviation over all the logs (what fit % is measured against)
    output_sd: float = math.nan

    @property
    def holds(self) -> bool | None:
        """True when the residual RMS stays within :data:`HOLDS_WITHIN` of the RMS at
        identification, False beyond it, None when the file has no RMS to compare."""
        if self.identified_rms is None or not self.identified_rms > 0:
            return None
        return self.residual_rms <= (1.0 + HOLDS_WITHIN) * self.identified_rms

    @property
    def verdict(self) -> str:
        """The answer in one line: does the saved model hold on these logs."""
        rms = value_text(self.residual_rms, self.unit)
        if self.holds is None:
            return (f"{self.equation}: residual RMS {rms}, fit {self.fit_percent:.1f} % "
                    f"(the model file has no RMS at identification to compare with)")
        assert self.identified_rms is not None
        change = self.residual_rms / self.identified_rms - 1.0
        sign = "+" if change >= 0 else ""
        return (f"{self.equation}: the model {'holds' if self.holds else 'does not hold'}: "
                f"residual RMS {rms}, {sign}{share_text(change)} against the "
                f"{value_text(self.identified_rms, self.unit)} at identification "
                f"(it holds within +{share_text(HOLDS_WITHIN)})")

    def to_dict(self) -> dict[str, Any]:
        return {"equation": self.equation, "unit": self.unit, "samples": self.samples,
                "residual_rms": finite_or_none(self.residual_rms),
                "fit_percent": finite_or_none(self.fit_percent), "r2": finite_or_none(self.r2),
                "identified_rms": finite_or_none(self.identified_rms),
                "output_sd": finite_or_none(self.output_sd),
                "files": [f.to_dict() for f in self.files],
                "regions": [r.to_dict() for r in self.regions]}


@dataclass(frozen=True)
class ValidationReport:
    """What ``canrls validate`` prints (text with :meth:`format`, JSON with :meth:`to_dict`)."""

    model_file: str
    sources: tuple[str, ...]
    identified_on: tuple[str, ...]
    parameters: dict[str, dict[str, Any]]
    equations: tuple[EquationValidation, ...]
    #: the frames of the logs, their period and start
    frames: FrameCounts | None = None
    period: PeriodInfo | None = None
    start: StartInfo | None = None
    #: saved parameters physics rules out (:func:`canrls.estimation.physics.check_physics`)
    implausible: tuple[Implausible, ...] = ()

    @property
    def fit_percent(self) -> float:
        return self.equations[0].fit_percent if self.equations else math.nan

    @property
    def residual_rms(self) -> float:
        return self.equations[0].residual_rms if self.equations else math.nan

    def to_dict(self) -> dict[str, Any]:
        return {"model_file": self.model_file, "sources": list(self.sources),
                "identified_on": list(self.identified_on),
                "parameters": self.parameters,
                "fit_percent": finite_or_none(self.fit_percent),
                "residual_rms": finite_or_none(self.residual_rms),
                "equations": {e.equation: e.to_dict() for e in self.equations},
                "frames": {} if self.frames is None else self.frames.to_dict(True, self.period,
                                                                             self.start),
                "implausible": [i.to_dict() for i in self.implausible]}

    def format(self) -> str:
        """The report as text, the answer first: per equation, whether the model holds."""
        lines = [e.verdict for e in self.equations]
        lines += [f"model {self.model_file} (identified on {', '.join(self.identified_on) or '?'})",
                  f"validated on {', '.join(self.sources)} without re-estimating:"]
        for name, p in self.parameters.items():
            sigma = p.get("sigma")  # a model file may leave it out: unknown, not 0
            sd = f"{'—':>9}" if sigma is None else f"{sigma:9.3g}"
            lines.append(f"  {name:<14} {p['value']:12.6g} ± {sd} "
                         f"{p.get('unit', '')}"
                         + ("  NOT IDENTIFIABLE from the logs it was identified on"
                            if p.get("identifiable") is False else ""))
        lines.extend(describe(self.implausible))
        for e in self.equations:
            ident = "" if e.identified_rms is None else \
                f" (identification: {e.identified_rms:.4g} {e.unit})"
            lines.append(f"{e.equation}: fit {e.fit_percent:.2f} %, residual RMS "
                         f"{e.residual_rms:.4g} {e.unit}{ident}, R² {r2_text(e.r2)}, "
                         f"{e.samples} samples")
            if len(e.files) > 1:
                lines.append(f"  per log, fit % is against that log's own spread of the "
                             f"output (SD); a log that spreads less than all of them together "
                             f"(SD {e.output_sd:.4g} {e.unit}) fits less at the same residual "
                             f"RMS:")
                for f in e.files:
                    lines.append(f"  {f.source}: fit {f.fit_percent:.2f} %, residual RMS "
                                 f"{f.residual_rms:.4g} {e.unit}, output SD {f.output_sd:.4g} "
                                 f"{e.unit}, {f.samples} samples")
            if e.regions:
                lines.append("  where it fails:")
                lines.extend(f"    - {r.text} ({share_text(r.share)} of the residual energy)"
                             for r in e.regions)
            else:
                lines.append("  no region where the residual's mean stands out")
        return "\n".join(lines)

    __str__ = format

    def write_html(self, directory: str | os.PathLike[str]) -> Path:
        """Write ``index.html`` and its SVG figures into ``directory`` (created).

        :raises ConfigError: matplotlib (the ``report`` extra) is not installed.
        :returns: the path of ``index.html``.
        """
        return write_html(self, directory)



def _fit(r: F64, y: F64) -> tuple[float, float, float, float]:
    """(rms, fit %, R², the output's standard deviation) of residual ``r`` against output
    ``y``."""
    if not len(r):
        return math.nan, math.nan, math.nan, math.nan
    dev = y - np.mean(y)
    nd = float(np.sqrt(np.dot(dev, dev)))
    nr = float(np.sqrt(np.dot(r, r)))
    rms = nr / math.sqrt(len(r))
    fit = 100.0 * (1.0 - nr / nd) if nd > 0 else math.nan
    r2 = 1.0 - (nr * nr) / (nd * nd) if nd > 0 else math.nan
    return rms, fit, r2, nd / math.sqrt(len(r))


def validate_signals(signals: Signals | SpilledSignals, saved: SavedModel, dt: float, *,
                     sizes: Sequence[int] = (), sources: Sequence[str] = (),
                     model_file: str = "<model>", frames: FrameCounts | None = None,
                     period: PeriodInfo | None = None, start: StartInfo | None = None
                     ) -> ValidationReport:
    """Predict ``signals`` with ``saved`` (no estimation); ``sizes``/``sources`` split
    the record into its files for the per-file fit."""
    if len(signals) < 2:
        raise ConfigError(f"validate: {len(signals)} samples; nothing to validate")
    model = saved.build_model([r for r in ROLES if signals.has(r)])
    settings = saved.config().settings()
    ctx = RecordSamples(model, signals, dt, settings, 1)
    bounds = np.cumsum([0, *sizes]) if sizes else np.array([0, len(signals)])
    names = list(sources) if sources else ["<signals>"]
    out = []
    for eq in model.equations:
        try:
            theta = np.array([float(saved.parameters[p.name]["value"])
                              for p in eq.parameters])
        except KeyError as e:
            raise ConfigError(f"{model_file}: no value for parameter {e.args[0]}") from None
        if not np.all(np.isfinite(theta)):  # a SavedModel built in code, not read
            bad = [p.name for p, v in zip(eq.parameters, theta, strict=True)
                   if not math.isfinite(v)]
            raise ConfigError(f"{model_file}: parameters {', '.join(bad)}: not finite; "
                              f"nothing can be predicted with them")
        phi, y = ctx.columns(eq)
        used = ctx.used(eq) & np.isfinite(y) & np.all(np.isfinite(phi), axis=1)
        if not used.any():
            raise EstimatorError(
                f"validate: {', '.join(names)}: no usable sample for the {eq.name} "
                f"equation ({len(signals)} samples, every one left out: the filter's "
                f"warm-up after the start and after each gap, the speed limits of the "
                f"model, non-finite values); nothing to validate")
        # r = y - Phi theta, normalised columns and parameters, then in the output unit
        with np.errstate(over="ignore", invalid="ignore"):
            r = eq.output_to_physical(y - phi @ eq.to_normalised(theta))
        yt = eq.output_to_physical(y)
        with np.errstate(over="ignore"):
            energy = float(np.dot(r[used], r[used]))
        if not math.isfinite(energy):  # a value or its square beyond a double
            raise EstimatorError(
                f"{model_file}: the saved parameters predict values of the {eq.name} "
                f"equation's output too large for a double (parameters of absurd size?)")
        rms, fit, r2, sd = _fit(r[used], yt[used])
        files = []
        for k, name in enumerate(names):
            a, b = int(bounds[k]), int(bounds[k + 1])
            u = used[a:b]
            f_rms, f_fit, _, f_sd = _fit(r[a:b][u], yt[a:b][u])
            files.append(FileFit(name, int(u.sum()), f_rms, f_fit, f_sd))
        unit = eq.output.unit
        regions: tuple[Region, ...] = ()
        if used.any():
            bins = all_bins(ctx, r, used, unit)
            h = ctx.impulse(eq.holds[0])
            h2 = float(np.sum(h * h))
            regions = find_regions(bins, r[used], 1.0 / h2 if h2 > 0 else 1.0, unit, ctx)
        else:
            bins = {}
        ident = saved.fit.get(eq.name, {}).get("residual_rms")
        traces = Traces(
            t=ctx.t, used=used, y=yt, yhat=yt - r, residual=r, speed=ctx.speed,
            acceleration=ctx.acceleration, current=ctx.current, position=ctx.position,
            angle=ctx.angle, conv_t=np.zeros(0), theta=np.zeros((0, 0)),
            sigma=np.zeros((0, 0)), theta_fixed=np.zeros((0, 0)),
            names=tuple(p.name for p in eq.parameters),
            units=tuple(p.unit for p in eq.parameters))
        out.append(EquationValidation(
            equation=eq.name, unit=unit, samples=int(used.sum()), residual_rms=rms,
            fit_percent=fit, r2=r2, identified_rms=None if ident is None else float(ident),
            files=tuple(files), regions=tuple(regions), output=eq.output.description,
            traces=traces, bins=bins, bounds=tuple(int(b) for b in bounds), output_sd=sd))
    return ValidationReport(model_file=model_file, sources=tuple(names),
                            identified_on=tuple(saved.sources), parameters=saved.parameters,
                            equations=tuple(out), frames=frames, period=period, start=start,
                            implausible=saved_physics(saved))


@dataclass(frozen=True)
class _Saved:
    """A saved parameter as :func:`check_physics` reads it."""

    name: str
    value: float
    sigma: float
    identifiable: bool


def saved_physics(saved: SavedModel) -> tuple[Implausible, ...]:
    """The saved parameters physics rules out (the file's own verdicts on
    identifiability)."""
    items = [_Saved(n, float(p.get("value", math.nan)), float(p.get("sigma") or 0.0),
                    p.get("identifiable") is not False)
             for n, p in saved.parameters.items()]
    kt = saved.model.get("kt")
    return check_physics(items, float(kt) if isinstance(kt, int | float) else None)


def validate_logs(paths: Sequence[str | os.PathLike[str]], saved: SavedModel,
                  protocol: Protocol, *, model_file: str = "<model>",
                  progress: Callable[[int, int], None] | None = None,
                  chunk_size: int = 65536, skip_bad_lines: bool = False) -> ValidationReport:
    """Decode and pair the logs as ``canrls fit`` does, then :func:`validate_signals`."""
    available = [r for r in ROLES if protocol.has(r)]
    model = saved.build_model(available)
    log = read_logs(paths, protocol, model, saved.config().settings(), progress=progress,
                    chunk_size=chunk_size, skip_bad_lines=skip_bad_lines)
    return validate_signals(log.signals, saved, log.dt, sizes=log.sizes,
                            sources=[str(p) for p in paths], model_file=model_file,
                            frames=log.frames, period=log.period, start=log.start)


# ------------------------------------------------------------------------------ HTML
@dataclass(frozen=True)
class _Panel:
    """What :class:`~canrls.diagnosis.figures.Figures` draws of one equation (the
    diagnosis's figures take any object with these attributes)."""

    equation: str
    output: str
    unit: str
    fit_percent: float
    residual_rms: float
    traces: Traces
    bins: Mapping[str, Binned]


def _slice(tr: Traces, a: int, b: int) -> Traces:
    """The rows ``a:b`` (one log), its time counted from the log's first sample."""
    def cut(x: ColumnLike | None) -> F64 | None:
        return None if x is None else x[a:b]
    t = tr.t[a:b]
    return Traces(t=t - (t[0] if len(t) else 0.0), used=tr.used[a:b], y=tr.y[a:b],
                  yhat=tr.yhat[a:b], residual=tr.residual[a:b], speed=tr.speed[a:b],
                  acceleration=tr.acceleration[a:b], current=tr.current[a:b],
                  position=cut(tr.position), angle=cut(tr.angle), conv_t=tr.conv_t,
                  theta=tr.theta, sigma=tr.sigma, theta_fixed=tr.theta_fixed,
                  names=tr.names, units=tr.units)


#: What each figure of the validation page shows.
VALIDATE_CAPTIONS = {
    "timeline": "Measured against the saved model's prediction over time (no "
                "re-estimation): the filtered output (black) and the prediction; below, the "
                "residual. Time from the log's first sample.",
    "speed": CAPTIONS["speed.svg"],
    "position": CAPTIONS["position.svg"],
}


def write_html(report: ValidationReport, directory: str | os.PathLike[str]) -> Path:
    """Write ``index.html`` and the SVG figures of ``report`` into ``directory``: per
    equation, per log the measured output against the prediction and the residual over
    time, and over all logs the residual binned by speed and (where logged) by position.

    :raises ConfigError: matplotlib is missing, or the directory cannot be written.
    :returns: the path of ``index.html``.
    """
    # staged: a report that fails leaves the directory as it was
    with staged_dir(directory, f"--report {directory}", last="index.html") as stage:
        return _write_html(report, figures_in(stage, directory), Path(directory))


def _write_html(report: ValidationReport, figs: Figures, dest: Path) -> Path:
    sections = []

    def add(figures: list[tuple[str, str, str]], name: str, caption: str, alt: str) -> None:
        note = figs.notes.get(name)
        figures.append((name, caption + (" " + note if note else ""), alt))
    for e in report.equations:
        if e.traces is None:
            continue
        figures: list[tuple[str, str, str]] = []
        for k, f in enumerate(e.files):
            a, b = e.bounds[k], e.bounds[k + 1]
            if not f.samples:
                continue
            p = _Panel(e.equation, e.output, e.unit, f.fit_percent, f.residual_rms,
                       _slice(e.traces, a, b), e.bins)
            # a _Panel, not an EquationDiagnosis: it has what the figures read of it
            name = figs.timeline(p, None, name=f"{e.equation}-timeline-{k + 1}.svg",  # type: ignore[arg-type]
                                 label="saved, not re-estimated")
            add(figures, name, f"{f.source}: {VALIDATE_CAPTIONS['timeline']}",
                f"{e.output} measured against the saved model's prediction over "
                f"{f.source}: fit {f.fit_percent:.1f} %, residual RMS "
                f"{value_text(f.residual_rms, e.unit)}; the residual below")
        whole = _Panel(e.equation, e.output, e.unit, e.fit_percent, e.residual_rms,
                       e.traces, e.bins)
        for q in ("speed", "position"):
            if q not in e.bins or (q == "position" and e.traces.position is None):
                continue
            # a _Panel (no excitation: its traces are not decimated, so none is read)
            name = figs.binned(whole, None, q, name=f"{e.equation}-{q}.svg",  # type: ignore[arg-type]
                               label="saved model")
            mean = e.bins[q].mean
            swing = float(np.nanmax(np.abs(mean))) if np.isfinite(mean).any() else math.nan
            add(figures, name, VALIDATE_CAPTIONS[q],
                f"Residual of the saved model against {q} over every log: the bin means "
                f"reach {value_text(swing, e.unit)} (residual RMS "
                f"{value_text(e.residual_rms, e.unit)})")
        sections.append((e, figures))
    with atomic_writer(figs.out / "index.html", f"--report {dest}: index.html") as fh:
        fh.write(page_template("validate.html.j2").render(r=report, sections=sections)
                 .encode("utf-8"))
    return dest / "index.html"
