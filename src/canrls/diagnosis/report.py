"""The report object and its renderings: text, JSON-able dict, HTML page with figures.

:class:`DiagnosisReport` is what :func:`canrls.diagnosis.analysis.diagnose` returns. It
renders to text (:meth:`DiagnosisReport.format`), to a dict of plain types
(:meth:`DiagnosisReport.to_dict`, documented in ``docs/diagnose.md``) and to a
directory with ``index.html`` and SVG figures (:func:`write_html`): the page comes from
the jinja2 template ``templates/report.html.j2`` shipped with the package, the figures
from :mod:`canrls.diagnosis.figures` (matplotlib, the ``report`` extra).
"""

from __future__ import annotations

import math
import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import numpy.typing as npt

from canrls.core.effect_names import EffectId, parse_effect_name
from canrls.core.errors import CanrlsError
from canrls.core.files import atomic_writer, staged_dir
from canrls.core.webpage import environment
from canrls.diagnosis.candidates import MENTION_EXPLAINED
from canrls.diagnosis.figures import (
    FIGURES,
    UNUSED_SLOW,
    UNUSED_WARMUP,
    Figures,
    figures_in,
    integer_orders,
)
from canrls.diagnosis.residual import PEAK_SHARE
from canrls.diagnosis.results import (
    Analysis,
    Candidate,
    EquationDiagnosis,
    Region,
    r2_text,
    share_text,
    value_text,
)
from canrls.estimation.estimates import ParameterEstimate
from canrls.estimation.model import Model
from canrls.estimation.physics import describe
from canrls.estimation.selection import SamplePolicy
from canrls.estimation.settings import EstimatorSettings
from canrls.processor import FrameCounts, PeriodInfo, StartInfo

if TYPE_CHECKING:  # imported when a page is rendered, not for the text report
    import jinja2

__all__ = ["CAPTIONS", "DiagnosisReport", "page_template", "white_caveat", "write_html"]


class DiagnosisReport:
    """What :func:`diagnose` found: ``before`` (the model as given), ``after`` (with
    ``added`` effects, or None), the candidates and the verdict.

    Renders to text (:meth:`format`), to a JSON-able dict (:meth:`to_dict`) and to an
    HTML page with SVG figures (:meth:`write_html`, needs matplotlib).
    """

    def __init__(self, *, source: str, dt: float, samples: int, duration: float,
                 before: Analysis, after: Analysis | None, added: tuple[str, ...],
                 settings: EstimatorSettings, max_order: int,
                 frames: FrameCounts | None = None, period: PeriodInfo | None = None,
                 start: StartInfo | None = None) -> None:
        self.source = source
        self.dt = dt
        self.samples = samples
        self.duration = duration
        self.before = before
        self.after = after
        self.added = added
        self.settings = settings
        #: the frames of the replayed logs, their period and start (None: samples given)
        self.frames = frames
        self.period = period
        self.start = start
        self.max_order = max_order
        #: what compensating the final model's position terms would leave of their
        #: ripple, (line, JSON), set by ``canrls diagnose`` from ``canrls.control``
        #: (a layer beside this one); None: not computed or no position term
        self.compensation: tuple[str, dict[str, Any]] | None = None

    # -- shortcuts ----------------------------------------------------------------------
    @property
    def model(self) -> Model:
        return self.before.model

    @property
    def unit(self) -> str:
        return self.before.primary.unit

    @property
    def candidates(self) -> tuple[Candidate, ...]:
        """The before model's candidates, best first (identifiable ones first)."""
        return self.before.candidates

    @property
    def suggestion(self) -> tuple[str, ...]:
        """The effects the forward selection suggests adding (empty: nothing to add)."""
        return self.before.suggestion

    @property
    def verdict(self) -> str:
        return " ".join(e.verdict for e in self.before.equations)

    @property
    def identifiable(self) -> bool:
        return all(e.identifiable for e in self.before.equations)

    def __repr__(self) -> str:
        after = f", after={list(self.after.effects)}" if self.after else ""
        return (f"<DiagnosisReport {self.source}: {self.samples} samples, "
                f"before={list(self.before.effects)}{after}, "
                f"suggestion={list(self.suggestion)}>")

    # -- JSON ---------------------------------------------------------------------------
    def to_dict(self) -> dict[str, Any]:
        """Everything as plain types (``docs/diagnose.md`` documents every key)."""
        p = self.before.primary
        d: dict[str, Any] = {
            "source": self.source,
            "samples": self.samples,
            "duration": self.duration,
            "dt": self.dt,
            "axis": self.model.axis,
            "unit": p.unit,
            "per_ampere": self.model.per_ampere_text if self.model.per_ampere else None,
            "max_order": self.max_order,
            "before": self.before.to_dict(),
            "added": list(self.added),
            "after": None if self.after is None else self.after.to_dict(),
            "candidates": [c.to_dict() for c in self.candidates],
            "not_applicable": [{"effect": e, "reason": r}
                               for q in self.before.equations for e, r in q.not_applicable],
            "suggestion": p.suggestion.to_dict(),
            "regions": [r.to_dict() for r in p.regions],
            "orders": None if p.spectrum is None else p.spectrum.to_dict(),
            "structure": [s.to_dict() for s in p.structure],
            "excitation": p.excitation.to_dict(),
            "identifiable": self.identifiable,
            "identifiability": [r for q in self.before.equations for r in q.identifiability],
            "implausible": [i.to_dict() for i in self.before.estimates.implausible],
            "verdict": self.verdict,
            "compensation": None if self.compensation is None else self.compensation[1],
        }
        if self.frames is not None:
            d["frames"] = self.frames.to_dict(True, self.period, self.start)
        return d

    # -- text ---------------------------------------------------------------------------
    @property
    def answer(self) -> str:
        """The report's answer in one line, what its text opens with: the verdict, or with
        ``--add`` how far the residual fell and what the model still misses."""
        if self.after is None:
            return "Verdict: " + self.verdict
        bq, aq = self.before.primary, self.after.primary
        rb, ra = bq.residual_rms, aq.residual_rms
        fall = f" ({100 * (ra - rb) / rb:+.0f} %)" if rb > 0 else ""
        return (f"After --add {' --add '.join(self.added)}: residual RMS "
                f"{value_text(rb, bq.unit)} -> {value_text(ra, aq.unit)}{fall}; "
                + " ".join(e.verdict for e in self.after.equations))

    def format(self, notes: Sequence[str] = ()) -> str:
        """The report as text: the answer first, ``notes`` (what the command read: the
        control period, the values used) under it, then the evidence: compare, where it
        fails, candidates, verdict, before/after."""
        out: list[str] = [self.answer, *notes]
        b = self.before
        out.append(f"{self.source}: {self.samples} samples ({self.duration:.1f} s), "
                   f"model {', '.join(b.effects)}")
        if self.model.per_ampere:
            out.append(self.model.per_ampere_text)
        out.extend(describe(b.estimates.implausible))
        if self.after is not None:
            out.extend(f"after adding: {line}"
                       for line in describe(self.after.estimates.implausible))
        for q in b.equations:
            out.extend(_format_equation(q, self.model.axis))
        if self.after is not None:
            out.append("")
            out.extend(_format_before_after(self.before, self.after, self.added))
        if self.compensation is not None:
            out.append(self.compensation[0])
        return "\n".join(out)

    __str__ = format

    # -- figures ------------------------------------------------------------------------
    def write_html(self, directory: str | os.PathLike[str]) -> Path:
        """Write ``index.html`` and its SVG figures into ``directory`` (created).

        :raises ConfigError: matplotlib (the ``report`` extra) is not installed.
        :returns: the path of ``index.html``.
        """
        return write_html(self, directory)


# ------------------------------------------------------------------------------ HTML
#: What each figure shows, under it on the page.
CAPTIONS = {
    "timeline.svg": "Measured against model over time: the filtered output (black, drawn "
                    "above the model) and the model's value with the final float estimate; "
                    "below, the residual.",
    "speed.svg": "Residual against speed, both directions (symmetric-log axis, negative: "
                 "moving backward). Grey: every sample; dots: bin means, bars: the spread in the "
                 "bin. A missing Coulomb friction is a step at zero, viscous a slope, "
                 "Stribeck a bump near zero, an offset a constant shift.",
    "position.svg": "Residual against position (in the revolution, or along a linear "
                    "axis). A missing unbalance is one period per revolution, cogging k "
                    "periods.",
    "candidates.svg": "Every effect of the library that the model lacks, with the share of "
                      "the residual variance it explains when added alone (orthogonalised: "
                      "error-reduction ratio).",
    "orders.svg": "The residual's rotation-order spectrum at the integer orders: amplitude "
                  "of sin/cos of order q times the angle fitted to the residual (filtered "
                  "like the equation). Each peak's share is what it explains beyond the "
                  "stronger peaks, all fitted together, so the shares add up to at most "
                  "100 %. Peaks sit at the orders of position-periodic effects.",
    "convergence.svg": "Parameter convergence: float estimate with its ±σ band, fixed-point "
                       "estimate dashed.",
    "fixed.svg": "Fixed point against float: the difference relative to the float value "
                 "(or σ when larger), on a log axis; the dotted line is 0.1 %.",
}


def page_template(name: str) -> jinja2.Template:
    """The jinja2 template ``name`` shipped under ``diagnosis/templates``, with the
    report's filters (``num``, ``fmt``, ``r2``); also the page of ``canrls validate``."""
    return environment("canrls.diagnosis", white_caveat=white_caveat,
                       r2=r2_text).get_template(name)


def _parameter_rows(before: Analysis, after: Analysis | None
                    ) -> list[tuple[str, list[ParameterEstimate | None], str]]:
    """(name, [estimate before, estimate after], unit) of every parameter of either model."""
    pb = {p.name: p for p in before.estimates.parameters}
    pa = {p.name: p for p in after.estimates.parameters} if after is not None else {}
    rows = []
    for n in list(pb) + [n for n in pa if n not in pb]:
        b, a = pb.get(n), pa.get(n)
        unit = next(p.unit for p in (a, b) if p is not None)  # n is in one of them
        rows.append((n, [b, a] if after is not None else [b], unit))
    return rows


def _quantity(effect: str) -> str:
    """The figure that shows ``effect`` missing: "position" for a position-periodic
    effect, "speed" for friction and an offset, "timeline" for the others."""
    try:
        e = parse_effect_name(effect).effect
    except CanrlsError:
        return "timeline"
    if e in (EffectId.COGGING, EffectId.UNBALANCE):
        return "position"
    if e in (EffectId.VISCOUS, EffectId.COULOMB, EffectId.STRIBECK, EffectId.OFFSET):
        return "speed"
    return "timeline"


def proof_figures(b: EquationDiagnosis, written: Mapping[str, str]) -> tuple[str, ...]:
    """The figures that prove the verdict (shown right under it): the residual against
    the quantity of the first suggested effect (and, for a position-periodic one, the
    order spectrum that names its order), else the timeline."""
    q = _quantity(b.suggestion.steps[0].effect) if b.suggestion.steps else "timeline"
    names = (f"{q}.svg", "orders.svg") if q == "position" else (f"{q}.svg",)
    return tuple(n for n in names if n in written) or ("timeline.svg",)


def split_regions(b: EquationDiagnosis) -> tuple[tuple[Region, ...], tuple[Region, ...]]:
    """The regions where it fails: (in the quantity of the first suggested effect, in
    the others); a position effect's regions are position ranges first."""
    q = _quantity(b.suggestion.steps[0].effect) if b.suggestion.steps else ""
    lead = tuple(r for r in b.regions if r.quantity == q)
    if not lead:
        return b.regions, ()
    return lead, tuple(r for r in b.regions if r.quantity != q)


def samples_text(report: DiagnosisReport) -> str:
    """How many samples the equation used of the record, and why the others were not."""
    b = report.before.primary
    used = b.fit.samples
    left = report.samples - used
    part = used / report.samples
    # a share never rounded up to 100 % while samples were left out
    pct = share_text(part) if part < 0.995 or left <= 0 else \
        f"{math.floor(1000 * part) / 10:.1f} %"
    text = f"{used:,} of {report.samples:,} samples used ({pct})"
    if left <= 0:
        return text + "."
    policy = SamplePolicy.for_equation(report.model.equations[0], report.dt, report.settings)
    why = UNUSED_WARMUP
    if policy.min_speed > 0:
        why += ", and " + UNUSED_SLOW.replace(
            "near reversals", f"near reversals (below {policy.min_speed:.3g} "
                              f"{b.excitation.speed_unit})")
    return f"{text}; the other {left:,} were left out: {why}."


def _extent(x: npt.NDArray[np.float64]) -> float:
    x = x[np.isfinite(x)]
    return float(np.max(np.abs(x))) if len(x) else math.nan


def alt_text(name: str, report: DiagnosisReport) -> str:
    """What figure ``name`` shows, in one sentence with its numbers (the image's alt)."""
    b = report.before.primary
    a = report.after.primary if report.after is not None else None
    u = b.unit
    after = ""
    if name == "timeline.svg":
        if a is not None:
            after = f", {a.fit_percent:.1f} % after adding {', '.join(report.added)}"
        return (f"{b.output} measured against the model over {report.duration:.0f} s: fit "
                f"{b.fit_percent:.1f} % before{after}; the residual below")
    if name in ("speed.svg", "position.svg"):
        q = name.split(".")[0]

        def swing(e: EquationDiagnosis) -> str:
            bn = e.bins.get(q)
            return "—" if bn is None else value_text(_extent(bn.mean), u)
        if a is not None:
            after = f", {swing(a)} after"
        return (f"Residual against {q}: the bin means reach {swing(b)} before{after} "
                f"(residual RMS {value_text(b.residual_rms, u)} before"
                + (f", {value_text(a.residual_rms, u)} after)" if a is not None else ")"))
    if name == "candidates.svg":
        best = ", ".join(f"{c.effect} {share_text(c.explained)}" for c in b.candidates[:4])
        return f"Share of the residual variance each missing effect explains alone: {best}"
    if name == "orders.svg":
        def peak(e: EquationDiagnosis) -> str:
            if e.spectrum is None:
                return "—"
            _, amp, _, peaks = integer_orders(e.spectrum)
            if peaks:
                return (f"order {peaks[0]:g} at {value_text(e.spectrum.at(peaks[0])[0], u)}")
            return f"no order stands out (largest {value_text(_extent(amp), u)})"
        if a is not None:
            after = f"; after: {peak(a)}"
        return f"Residual amplitude per integer rotation order: before, {peak(b)}{after}"
    final = report.after if report.after is not None else report.before
    names = ", ".join(final.primary.traces.names)
    if name == "convergence.svg":
        return f"Each parameter's float estimate over time with its ±σ band and the " \
               f"fixed-point estimate: {names}"
    return f"Relative difference of the fixed-point and float estimates over time: {names}"


def render_html(report: DiagnosisReport, written: Mapping[str, str],
                notes: Mapping[str, str] | None = None) -> str:
    """The page of ``report`` with the figures ``written`` (``{figure: file name}``) and
    the ``notes`` their captions add (clipped axes, shaded spans)."""
    notes = notes or {}
    b = report.before.primary
    proof = proof_figures(b, written)

    def fig(name: str) -> tuple[str, str, str]:
        cap = CAPTIONS[name] + (" " + notes[name] if name in notes else "")
        return written[name], cap, alt_text(name, report)
    figures = [fig(name) for name in FIGURES if name in written and name not in proof]
    lead, rest = split_regions(b)
    return page_template("report.html.j2").render(
        r=report, b=b, proof=[fig(name) for name in proof], figures=figures,
        lead=lead, rest=rest, samples=samples_text(report),
        params=_parameter_rows(report.before, report.after))


def write_html(report: DiagnosisReport, directory: str | os.PathLike[str]) -> Path:
    """Write ``index.html`` and the SVG figures of ``report`` into ``directory``.

    :raises ConfigError: matplotlib is missing, or the directory cannot be written.
    :returns: the path of ``index.html``.
    """
    # staged: a report that fails leaves the directory as it was
    with staged_dir(directory, f"--report {directory}", last="index.html") as stage:
        return _write_html(report, figures_in(stage, directory), Path(directory))


def _write_html(report: DiagnosisReport, figs: Figures, dest: Path) -> Path:
    b = report.before.primary
    a = report.after.primary if report.after is not None else None
    written: dict[str, str] = {}
    written["timeline.svg"] = figs.timeline(b, a)
    written["speed.svg"] = figs.binned(b, a, "speed")
    if b.traces.position is not None:
        written["position.svg"] = figs.binned(b, a, "position")
    if b.candidates:
        written["candidates.svg"] = figs.candidates(b)
    if b.spectrum is not None:
        written["orders.svg"] = figs.orders(b, a)
    final = report.after if report.after is not None else report.before
    written["convergence.svg"] = figs.convergence(final.primary, final is report.after)
    written["fixed.svg"] = figs.fixed(final.primary)
    with atomic_writer(figs.out / "index.html", f"--report {dest}: index.html") as f:
        f.write(render_html(report, written, figs.notes).encode("utf-8"))
    return dest / "index.html"


# ------------------------------------------------------------------------------ text
def white_caveat(q: EquationDiagnosis) -> str:
    """What a white residual does not show ("" when nothing to say): a candidate that
    would explain much of a residual the whiteness test passes (a hidden effect whose
    filtered column is itself white, such as Coulomb friction when the speed's sign
    flips faster than the test's decimation). The verdict follows the candidates."""
    w = q.whiteness
    if w is None or not w.white:
        return ""
    big = [c for c in q.candidates if c.explained >= MENTION_EXPLAINED]
    if not big:
        return ""
    best = max(big, key=lambda c: c.explained)
    return (f"white, yet not complete: {best.effect} would explain "
            f"{share_text(best.explained)} of this residual (see the verdict)")


def _format_equation(q: EquationDiagnosis, axis: str) -> list[str]:
    u = q.unit
    f = q.fit
    out = ["", f"== {q.equation} equation: {q.output} [{u}]", "",
           "Compare (final float estimate over the whole record, filtered equation)",
           f"  residual RMS {value_text(f.residual_rms, u)}, fit {f.fit_percent:.2f} %, "
           f"R² {f.r2:.5f}, {f.samples} samples"
           f" (fixed point: residual RMS {value_text(q.residual_rms_fixed, u)})"]
    if q.whiteness is not None:
        out.append(f"  whiteness: {q.whiteness.describe()}")
        caveat = white_caveat(q)
        if caveat:
            out.append(f"  {caveat}")
    out += ["", "Where it fails"]
    if q.regions:
        lead, rest = split_regions(q)
        for k, reg in enumerate(lead + rest):
            if k == len(lead) and lead:
                out.append("  also in other quantities:")
            out.append(f"  - {reg.text} ({share_text(reg.share)} of the residual energy)")
    else:
        out.append("  no region stands out: the binned means of the residual are small")
    # the peaks with a share of their own beyond the stronger ones (not their leakage)
    sp = q.spectrum
    own = [p for p in sp.peaks if sp.share(p) >= PEAK_SHARE] if sp is not None else []
    if sp is not None and own:
        pk = ", ".join(f"{p:g} ({value_text(sp.at(p)[0], u)}, {share_text(sp.share(p))})"
                       for p in own[:3])
        out.append(f"  rotation-order spectrum peaks (order per {sp.per}; each share beyond "
                   f"the stronger ones): {pk}")
    facts = q.excitation.facts()
    if facts:
        out.append("  excitation: " + "; ".join(facts))
    out += ["", "Which effect is missing (adding each alone to the model)"]
    if q.candidates:
        w = max(len(c.effect) for c in q.candidates)
        out.append(f"  {'rank':<4}  {'effect':<{w}}  {'explained':>9}  {'ΔBIC':>9}  "
                   f"{'RMS after':>11}")
        steps = {st.effect: (i, st) for i, st in enumerate(q.suggestion.steps)}
        for i, c in enumerate(q.candidates, 1):
            flag = "" if c.identifiable else "  (not identifiable)"
            if c.effect in steps:
                k, st = steps[c.effect]
                flag = "  <- suggested" + (f" (step {k + 1}: {100 * st.explained:.3g} % of what "
                                           f"the steps before leave)" if k else "")
            out.append(f"  {i:<4}  {c.effect:<{w}}  {100 * c.explained:>8.2f}%  "
                       f"{c.delta_bic:>9.4g}  {c.rms_after:>11.4g}{flag}")
            out.append(f"        {c.description}")
            if not c.identifiable:
                out.append(f"        {c.reason}")
            for r in c.search:
                out.append(f"        {r.text()}")
            for e in c.evidence[:3]:
                out.append(f"        evidence: {e}")
    else:
        out.append("  no candidate: every effect of the library is in the model")
    for e, why in q.not_applicable:
        out.append(f"  ({e}: {why})")
    if q.structure:
        out += ["", "Structure left " + ("after the suggestion" if q.suggestion else "")]
        for s in q.structure:
            out.append(f"  - {s.text}")
    out += ["", "Verdict: " + q.verdict]
    return out


def _format_before_after(before: Analysis, after: Analysis,
                         added: Sequence[str]) -> list[str]:
    out = [f"== Before and after --add {' --add '.join(added)}", ""]
    bq, aq = before.primary, after.primary
    u = bq.unit

    def white(q: EquationDiagnosis) -> str:
        if q.whiteness is None:
            return "n/a"
        return f"{'white' if q.whiteness.white else 'not white'} ({q.whiteness.outside}/" \
               f"{q.whiteness.lags})"

    rows = [("residual RMS", value_text(bq.residual_rms, u), value_text(aq.residual_rms, u)),
            ("fit", f"{bq.fit_percent:.2f} %", f"{aq.fit_percent:.2f} %"),
            ("R²", f"{bq.fit.r2:.5f}", f"{aq.fit.r2:.5f}"),
            ("whiteness", white(bq), white(aq)),
            ("fixed-point RMS", value_text(bq.residual_rms_fixed, u),
             value_text(aq.residual_rms_fixed, u))]
    out.append(f"  {'':<16}  {'before':>24}  {'after':>24}")
    for name, x, y in rows:
        out.append(f"  {name:<16}  {x:>24}  {y:>24}")
    out.append("")
    pb = {p.name: p for p in before.estimates.parameters}
    pa = {p.name: p for p in after.estimates.parameters}
    names = list(pb) + [n for n in pa if n not in pb]
    w = max([len(n) for n in names] + [9])
    out.append(f"  {'parameter':<{w}}  {'before ± σ':>26}  {'after ± σ':>26}  "
               f"{'fixed after':>12}  unit")
    for n in names:
        b = pb.get(n)
        a = pa.get(n)
        bs = f"{b.value:.6g} ± {b.sigma:.2g}" if b else "—"
        as_ = f"{a.value:.6g} ± {a.sigma:.2g}" if a else "—"
        fx = f"{a.fixed:.6g}" if a else "—"
        unit = next(p.unit for p in (a, b) if p is not None)  # n is in one of them
        out.append(f"  {n:<{w}}  {bs:>26}  {as_:>26}  {fx:>12}  {unit}")
    out += ["", "After: " + " ".join(e.verdict for e in after.equations)]
    return out
