r"""Diagnosis: compare the model with the measurements, see where it fails, name the missing effect.

:func:`diagnose` (samples in memory) and :func:`diagnose_log` (a recorded CAN log) run
the model through the same pipeline as ``canrls fit`` and return a
:class:`DiagnosisReport` that renders to text, JSON and an HTML page with figures. This
module holds the entry points; the steps (compare, where it fails, which effect is
missing, add it) live in the modules beside it and are described in docs/diagnose.md.
"""

from __future__ import annotations

import math
import os
from collections.abc import Callable, Iterable, Sequence
from typing import Any

import numpy as np
import numpy.typing as npt

from canrls.core.checks import positive_period
from canrls.core.errors import ConfigError, EffectError
from canrls.core.samples import Signals
from canrls.core.spill import ColumnLike, MaskPacker, PackedMask, SpilledSignals
from canrls.diagnosis.candidates import (
    DEFAULT_MAX_ORDER,
    MAX_ORDER_LIMIT,
    ResidualSummary,
    rank_candidates,
)
from canrls.diagnosis.record import RecordSamples
from canrls.diagnosis.report import DiagnosisReport
from canrls.diagnosis.residual import (
    WHITENESS_LAGS,
    all_bins,
    excitation_summary,
    find_regions,
    order_spectrum,
    whiteness,
)
from canrls.diagnosis.results import Analysis, EquationDiagnosis, Traces, decimation
from canrls.diagnosis.search import known_stribeck_speed
from canrls.estimation.effects import ELECTRICAL
from canrls.estimation.estimates import EquationFit, PipelineBlock
from canrls.estimation.fixed.estimator import FixedRLS
from canrls.estimation.model import Model
from canrls.estimation.pipeline import EquationEstimator
from canrls.estimation.rls import RLS
from canrls.estimation.settings import EstimatorSettings
from canrls.processor import (
    FrameCounts,
    PeriodInfo,
    SampleProcessor,
    StartInfo,
    sample_period,
)

__all__ = ["diagnose", "diagnose_log"]

F64 = npt.NDArray[np.float64]
B = npt.NDArray[np.bool_]

#: Samples per block fed to the pipeline (its working arrays are this long, not the
#: record's).
CHUNK = 65536


# ========================================================================= entry points
def diagnose(data: Signals | SpilledSignals | Iterable[Signals], model: Model,
             settings: EstimatorSettings | None = None, *, dt: float | None = None,
             add: Sequence[str] = (), max_order: int = DEFAULT_MAX_ORDER,
             source: str = "<signals>",
             frames: FrameCounts | None = None, period: PeriodInfo | None = None,
             start: StartInfo | None = None) -> DiagnosisReport:
    """Diagnose ``model`` on samples: compare, locate the failures, rank the missing effects.

    :param data: a :class:`~canrls.core.samples.Signals` block, or blocks (joined end to end),
        or a record in a temporary file (:class:`~canrls.core.spill.SpilledSignals`,
        read in slices).
    :param model: the model to diagnose.
    :param settings: estimator settings (default :class:`EstimatorSettings`).
    :param dt: sample period [s] (default: measured on ``t`` as the processor measures it).
    :param add: effects to add and refit (``after``); ``cogging`` without an order takes
        the order the search found.
    :param max_order: highest cogging order searched, and of the order spectrum
        (1 to :data:`~canrls.diagnosis.candidates.MAX_ORDER_LIMIT`).
    :param source: what the samples are, for the text.
    :param frames, period, start: what a log replay found, copied into the report.
    :raises ConfigError: no samples, a bad ``dt`` or ``max_order``; :class:`EffectError`
        for an effect in ``add`` that is unknown or already in the model.
    """
    signals = (data if isinstance(data, Signals | SpilledSignals)
               else Signals.concat(list(data)))
    n = len(signals)
    if n < 2:
        raise ConfigError(f"diagnose: {source}: {n} samples; need at least a few seconds")
    t = signals.t
    assert t is not None, "a record without rows"  # n >= 2
    dt = (sample_period(t, f"diagnose: {source}") if dt is None
          else positive_period(dt, "diagnose: dt"))
    if (isinstance(max_order, bool) or not isinstance(max_order, int)
            or not 1 <= max_order <= MAX_ORDER_LIMIT):
        raise ConfigError(f"diagnose: max_order = {max_order!r}: must be an integer in "
                          f"1..{MAX_ORDER_LIMIT}")
    settings = settings or EstimatorSettings()
    add = tuple(add)
    # validate the additions before the long part (cogging without K is resolved later)
    for a in add:
        if _bare_cogging(a):
            continue
        model.with_effects(add=[a])
    ctx = RecordSamples(model, signals, float(dt), settings, max_order)
    before = _analyse(ctx, model)
    added = tuple(_resolve_add(a, before) for a in add)
    after = _analyse(ctx, _with_found(model.with_effects(add=added), added, before)) \
        if added else None
    duration = float(t[-1] - t[0]) + float(dt) if n else 0.0
    return DiagnosisReport(source=source, dt=float(dt), samples=n, duration=duration,
                           before=before, after=after, added=added, settings=settings,
                           max_order=max_order, frames=frames, period=period,
                           start=start)


def diagnose_log(paths: str | os.PathLike[str] | Sequence[str | os.PathLike[str]],
                 protocol: Any, model: Model, settings: EstimatorSettings | None = None, *,
                 add: Sequence[str] = (), progress: Callable[[int, int], None] | None = None,
                 max_order: int = DEFAULT_MAX_ORDER, chunk_size: int = 65536,
                 skip_bad_lines: bool = False) -> DiagnosisReport:
    """Diagnose ``model`` on one recorded CAN log or several (``.log`` candump, ``.asc``,
    ``.blf``, ...; several are one record, no segment bridged:
    :class:`canrls.processor.replay.LogFiles`).

    The frames are decoded and paired exactly as ``canrls fit`` does
    (:func:`canrls.processor.replay.read_logs`), so ``before`` holds the same parameters as
    ``canrls fit`` prints, bit for bit. The samples are kept in an anonymous temporary
    file (:class:`~canrls.core.spill.SpilledSignals`: the statistics read them again in
    slices, the refit of ``add`` too), freed on return; in memory if the file cannot
    be made.
    """
    from canrls.processor.replay import read_logs

    if isinstance(paths, str | os.PathLike):
        paths = [paths]
    # validate the additions before reading
    for a in add:
        if not _bare_cogging(a):
            model.with_effects(add=[a])
    log = read_logs(paths, protocol, model, settings, progress=progress,
                    chunk_size=chunk_size, skip_bad_lines=skip_bad_lines, spill=True)
    try:
        return diagnose(log.signals, log.model, settings, dt=log.dt, add=add,
                        max_order=max_order, source=", ".join(str(p) for p in paths),
                        frames=log.frames, period=log.period, start=log.start)
    finally:
        log.close()


# ============================================================================ internals
def _bare_cogging(spec: str) -> bool:
    return isinstance(spec, str) and spec.strip().lower() == "cogging"


def _resolve_add(spec: str, before: Analysis) -> str:
    """``cogging`` alone: the order the search found."""
    if not _bare_cogging(spec):
        return spec
    for q in before.equations:
        orders = [c.effect for c in q.candidates if c.effect.startswith("cogging:")]
        if orders:
            return orders[0]
    raise EffectError("--add cogging: no cogging order could be searched (the data carry "
                      "no position, or the model has every order); give cogging:K")


def _with_found(model: Model, added: Sequence[str], before: Analysis) -> Model:
    """``model`` with the nonlinear parameters the search found for the effects added
    (those set in the configuration were kept, and stay)."""
    for q in before.equations:
        for c in q.candidates:
            if c.effect in added:
                for r in c.search:
                    if not r.kept:
                        model = model.with_search_value(r.key, r.value)
    return model


# ------------------------------------------------------------------------- the analysis
def _analyse(ctx: RecordSamples, model: Model) -> Analysis:
    # the front end's calibration rule, as canrls fit and the daemon follow it
    proc = SampleProcessor(model, ctx.dt, ctx.settings)
    blocks = _run_in_chunks(proc, ctx)
    configured = model.options_given  # before the calibration scales the others
    pipe, model = proc.pipeline, proc.model
    est = pipe.estimates()
    eqs = []
    for e, fit in zip(pipe.estimators, est.equations, strict=True):
        # popped: each equation's mask is freed once it is analysed
        eqs.append(_analyse_equation(ctx, model, e, blocks.pop(0), fit, configured))
    return Analysis(model=model, estimates=est, equations=tuple(eqs))


def _run_in_chunks(proc: SampleProcessor, ctx: RecordSamples) -> list[PackedMask]:
    """Run the record (``ctx.signals``) through ``proc`` in blocks of :data:`CHUNK`
    samples and keep, of each equation's recorded block, what the diagnosis reads: the
    used rows, packed as they come (:class:`~canrls.core.spill.MaskPacker`: one bit a
    row, in a temporary file past a few hundred thousand rows); the times are the
    samples' own, ``ctx.t`` (checked block by block).

    The pipeline carries its state from block to block bit for bit (``canrls fit``
    replays a log in blocks too), so the result is the one of a single run; but the
    pipeline's working arrays (errors, flags, running RMS, the estimates after each
    sample, the regressor buffer) stay the size of one block instead of the record's
    (:func:`_traces` re-runs the estimators for the convergence figure).
    """
    signals, t = ctx.signals, ctx.t
    kept: list[MaskPacker] = []
    rows: list[int] = []  # rows of each equation so far

    def keep(block: PipelineBlock) -> None:
        if not kept:
            kept.extend(MaskPacker() for _ in block.equations)
            rows.extend(0 for _ in block.equations)
        for j, (packer, eb) in enumerate(zip(kept, block.equations, strict=True)):
            # the pipeline's rows are the samples given (their times: ctx.t, not kept)
            a = rows[j]
            if not np.array_equal(eb.t, t[a:a + len(eb.t)]):  # pragma: no cover
                raise AssertionError(f"{eb.equation}: the pipeline's rows {a}.. are not "
                                     f"the samples")
            rows[j] += len(eb.t)
            packer.append(eb.used)

    n = len(signals)
    for a in range(0, n, CHUNK):
        keep(proc.process(signals.slice(a, min(n, a + CHUNK)), record=True))
    if proc.calibration is None:  # a record shorter than the calibration window
        keep(proc.finish(record=True))
    if not kept:
        keep(proc.process(signals.slice(0, 0), record=True))
    return [packer.mask() for packer in kept]


def _analyse_equation(ctx: RecordSamples, model: Model, est: EquationEstimator,
                      used: PackedMask, fit: EquationFit,
                      configured: frozenset[str]) -> EquationDiagnosis:
    """``used``: the rows the pipeline used for the equation (packed, read in blocks)."""
    eq = est.equation
    N = used.count()
    unit = eq.output.unit
    th = np.array(est.rls.theta, dtype=np.float64)
    th_fx = np.asarray(est.frls.theta_float, dtype=np.float64)
    # r = y - Phi theta (final float estimate), in the output unit; Phi and y built
    # again block by block (the pipeline's, bit for bit), not kept from the run
    r = ctx.residual(eq, th)
    # the fixed-point estimate's residual: only its mean square over the used rows
    rms_fixed = math.sqrt(ctx.mean_square(eq, th_fx, used)) if N else math.nan
    hold = eq.holds[0]
    h = ctx.impulse(hold)
    h2 = float(np.sum(h * h))
    tau = 1.0 / h2 if h2 > 0 else 1.0  # correlation length of filtered white noise
    # -- inputs of this equation, for cross-correlation --------------------------------
    if eq.name == ELECTRICAL:
        inputs = {"current": ctx.current, "speed": ctx.speed}
    else:
        inputs = {"speed": ctx.speed, "acceleration": ctx.acceleration}
    wht = whiteness(r, used, inputs, ctx.impulse(hold), WHITENESS_LAGS)
    bins = all_bins(ctx, r, used, unit)
    regions = find_regions(bins, r, tau, unit, ctx, rows=used)
    spectrum = order_spectrum(ctx, r, used, unit) if ctx.angle_raw is not None else None
    exc = excitation_summary(ctx, model, used, known_stribeck_speed(model, configured))
    cand = rank_candidates(ctx, model, eq,
                           ResidualSummary(r, used, h2, unit, bins, spectrum, exc, configured))
    traces = _traces(ctx, est, r, used)
    return EquationDiagnosis(
        equation=eq.name, output=eq.output.description, unit=unit, fit=fit,
        residual_rms_ls=cand.rms_ls, residual_rms_fixed=rms_fixed, whiteness=wht,
        bins=bins, regions=regions, spectrum=spectrum, candidates=cand.candidates,
        not_applicable=cand.not_applicable, suggestion=cand.suggestion,
        structure=cand.structure, excitation=cand.excitation, identifiable=cand.identifiable,
        identifiability=cand.identifiability, verdict=cand.verdict, traces=traces)


# -------------------------------------------------------------------------- traces
def _traces(ctx: RecordSamples, est: EquationEstimator, r: ColumnLike,
            used: PackedMask) -> Traces:
    eq = est.equation
    n_used = used.count()
    n = eq.n
    npts = min(400, n_used)
    conv_t = np.zeros(0)
    theta = np.zeros((0, n))
    sigma = np.zeros((0, n))
    tfx = np.zeros((0, n))
    if npts:
        # re-run the pipeline's float RLS, back at its prior, on the same rows
        # (bit-identical) and sample theta and sigma = sqrt(kappa sigma2 diag P + bias^2)
        # at npts instants (kappa: the colour of the final residual, as the estimates
        # report it)
        root_kappa = math.sqrt(est.sigma_inflation())
        # the bound of the model errors' bias, as the final estimate reports it, in every
        # point of the band (it does not shrink with the run)
        bias = np.array([p.bias for p in est.parameters()], dtype=np.float64)
        rls = RLS.from_state(est.rls.state())
        rls.reset()
        # the fixed-point RLS too, on the same quantised inputs: its estimate at the
        # instants, instead of a record-long recording of it after every sample
        frls = FixedRLS.from_state(est.frls.state())
        frls.reset()
        cuts = np.unique(np.linspace(0, n_used, npts + 1).astype(np.int64))[1:]
        th_l, sd_l, fx_l, t_l = [], [], [], []
        k = 0  # used rows fed to the estimators so far
        ci = 0  # next instant
        # the used rows block by block (the estimators carry their state bit for bit)
        for m, phi, y in ctx.measured_blocks(eq):
            u = used[m:m + len(y)]
            if ci >= len(cuts) or not u.any():
                continue
            at = np.flatnonzero(u)
            phi_u = np.ascontiguousarray(phi[at])
            y_u = np.ascontiguousarray(y[at])
            a = 0
            while a < len(y_u) and ci < len(cuts):
                c = min(len(y_u), a + int(cuts[ci]) - k)
                rls.run(phi_u[a:c], y_u[a:c], record=False)
                Pq, Yq = frls.quantize_block(phi_u[a:c], np.ascontiguousarray(y_u[a:c]))
                frls.run_block(Pq, Yq, False)
                k += c - a
                a = c
                if k == cuts[ci]:
                    th_l.append(eq.to_physical(np.array(rls.theta)))
                    sd_l.append(np.hypot(eq.sigma_to_physical(rls.std() * root_kappa), bias))
                    fx_l.append(eq.to_physical(frls.theta_float))
                    t_l.append(ctx.t[m + int(at[c - 1])])
                    ci += 1
        conv_t = np.array(t_l)
        theta = np.array(th_l)
        sigma = np.array(sd_l)
        tfx = np.array(fx_l)
    # the points the figures draw, not the record: every k-th sample for the timeline,
    # every k-th used sample for the scatter plots (found block by block)
    n_rows = len(used)
    k_t, k_s = decimation(n_rows), decimation(n_used)
    parts: list[npt.NDArray[np.intp]] = []
    tl_parts: list[B] = []
    sc_parts: list[B] = []
    seen = 0  # used rows before the block
    for a, u in used.blocks(CHUNK):
        tl = np.zeros(len(u), np.bool_)
        tl[(-a) % k_t::k_t] = True
        idx = np.flatnonzero(u)
        sc = np.zeros(len(u), np.bool_)
        sc[idx[(-seen) % k_s::k_s]] = True
        seen += len(idx)
        at_b = np.flatnonzero(tl | sc)
        parts.append(a + at_b)
        tl_parts.append(tl[at_b])
        sc_parts.append(sc[at_b])
    pts = np.concatenate([np.zeros(0, np.intp), *parts])
    timeline = np.concatenate([np.zeros(0, np.bool_), *tl_parts])
    scatter = np.concatenate([np.zeros(0, np.bool_), *sc_parts])
    y = ctx.output_at(eq, pts)
    res = r[pts]

    def at_points(x: ColumnLike | None) -> F64 | None:
        return None if x is None else x[pts]

    return Traces(
        t=ctx.t[pts], used=used[pts], y=y, yhat=y - res, residual=res, speed=ctx.speed[pts],
        acceleration=ctx.acceleration[pts], current=ctx.current[pts],
        position=at_points(ctx.position), angle=at_points(ctx.angle), conv_t=conv_t, theta=theta,
        sigma=sigma, theta_fixed=tfx, names=tuple(p.name for p in eq.parameters),
        units=tuple(p.unit for p in eq.parameters), timeline=timeline,
        scatter=scatter, record_used=used)
