"""Which effect is missing: the candidates, their ranking and identifiability.

Every effect of the library that the model lacks is tried as extra columns, built
through the same :class:`~canrls.estimation.model.Model` path, and ranked by the share
of the residual variance it explains; a greedy forward selection makes the
:class:`Suggestion`, and a candidate these data cannot identify is said so, with the
reason, never suggested. :func:`rank_candidates` also checks the model's own columns
and writes the verdict. The statistics: docs/diagnose.md, "Which effect is missing".
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from canrls.core.errors import ConfigError
from canrls.core.samples import Signals
from canrls.core.spill import PackedMask, Sliced, SpilledSignals
from canrls.diagnosis.record import BLOCK, RecordSamples
from canrls.diagnosis.residual import (
    MIN_BIN,
    MIN_EXPLAINED,
    excitation_summary,
    moments,
    residual_structure,
)
from canrls.diagnosis.results import (
    Binned,
    Candidate,
    ExcitationSummary,
    OrderSpectrum,
    SearchResult,
    Step,
    StructureItem,
    Suggestion,
    share_text,
    value_text,
)
from canrls.diagnosis.search import Gram, delta_bic, known_stribeck_speed, search_parameters
from canrls.estimation.effects import MECHANICAL, Cogging, Effect, UserTerm, library
from canrls.estimation.equation import Equation
from canrls.estimation.model import Model

__all__ = ["DEFAULT_MAX_ORDER", "MIN_TOTAL", "MIN_INDEPENDENCE", "MIN_EXPLAINED_SEARCHED",
           "MAX_COHERENCE", "MIN_PERIODS", "SIGN_PAIR", "SIGN_PAIR_TEXT", "CandidateResult",
           "ResidualSummary", "rank_candidates"]

F64 = npt.NDArray[np.float64]
B = npt.NDArray[np.bool_]

#: Coulomb friction and a constant offset: one column when the speed keeps one sign.
SIGN_PAIR = frozenset({"coulomb", "offset"})
SIGN_PAIR_TEXT = ("the speed never reverses: Coulomb friction and offset cannot be "
                  "separated; record a run in both directions")
#: Periods of a position harmonic the travel covered (span of the position) must hold for
#: it to be identifiable: with fewer, it fits any slow trend along the position.
MIN_PERIODS = 2.0
#: Share of the residual variance above which a candidate, identifiable or not, is named
#: by the verdict (a model is never called complete while one would cut this much).
MENTION_EXPLAINED = 0.2

#: Highest cogging order searched (``cogging:2`` ... ``cogging:K``).
DEFAULT_MAX_ORDER = 64
#: Largest ``max_order`` accepted: every order is two candidate columns, built in blocks
#: of rows (``BLOCK x (2 K + n)`` float64: 135 MB at K = 256), and the order spectrum
#: filters the record once per 32 orders.
MAX_ORDER_LIMIT = 256
#: Share of the residual variance a suggestion must explain in total when structure is
#: left after it; below, it is withdrawn (partial explainers of something outside the
#: library are not what is missing).
MIN_TOTAL = 0.8
#: Fraction of a candidate's column energy that must lie outside the span of the model's
#: columns (1/VIF) for it to be identifiable.
MIN_INDEPENDENCE = 0.01
#: Share of what is left of the residual variance a candidate with a searched parameter
#: must explain to be suggested: the search fits part of any smooth model error (the
#: complete model of the simulated drive, whose residual carries the filter's
#: errors-in-variables bias: 5 to 9 % at the value found), while a missing effect shows
#: as the bulk of the residual (96 to 99.98 %; docs/diagnose.md).
MIN_EXPLAINED_SEARCHED = 0.2
#: Coherence of a periodic column with a sinusoid in time above which a position-periodic
#: effect cannot be told from a disturbance periodic in time
#: (see :meth:`RecordSamples.coherence`).
MAX_COHERENCE = 0.9


def _eval_rows(ctx: RecordSamples, model: Model, eq: Equation, names: Sequence[str],
               used: PackedMask, periodic: bool = False) -> PackedMask:
    """The samples the candidates are compared on.

    The pipeline's own samples for the model (``used``), less those it would not use
    once the non-periodic candidates are added (e.g. near standstill when Coulomb or
    Stribeck friction joins the model): the rows the pipeline's sample policy uses for
    that model (:meth:`RecordSamples.used`). Periodic candidates are masked column by
    column instead (:meth:`RecordSamples.keep`), unless ``periodic``: then their limits
    count too (the samples of the refit with them). Packed, made block by block.
    """
    nonper = [nm for nm in names
              if periodic or not nm.startswith(("cogging:", "unbalance"))]
    m = model.with_effects(add=nonper) if nonper else model
    return used.intersect(ctx.used(m.equation(eq.name)))


@dataclass(frozen=True)
class ResidualSummary:
    """What the analysis knows of one equation's residual, for :func:`rank_candidates`.

    ``r`` the residual of the final estimate (output unit), ``used`` the rows the
    pipeline used for the equation, ``h2`` the squared norm of the filter's impulse
    response, ``bins`` and ``spectrum`` the residual binned and by rotation order,
    ``exc`` what the record excites, ``configured`` the model's options set in the
    configuration (kept, not searched).
    """

    r: Sliced
    used: PackedMask
    h2: float
    unit: str
    bins: Mapping[str, Binned]
    spectrum: OrderSpectrum | None
    exc: ExcitationSummary
    configured: frozenset[str] = frozenset()


@dataclass
class CandidateResult:
    """What :func:`rank_candidates` found for one equation."""

    candidates: tuple[Candidate, ...]
    not_applicable: tuple[tuple[str, str], ...]
    suggestion: Suggestion
    structure: tuple[StructureItem, ...]
    identifiable: bool
    identifiability: tuple[str, ...]
    verdict: str
    rms_ls: float
    #: the excitation the candidates were judged by (its low speed below the Stribeck
    #: speed the search found)
    excitation: ExcitationSummary


@dataclass
class _Comparison:
    """The model's columns and every candidate's, on the rows they are compared on.

    ``C`` the model's columns in the Gram matrix ``A`` (``G``), ``groups`` each
    candidate's columns, ``rss0`` and ``th0`` the least squares of the model alone,
    ``Ne`` the independent samples of ``N``.
    """

    names: list[str]
    not_applicable: list[tuple[str, str]]
    used: PackedMask
    N: int
    aug_model: Model
    aug: Equation
    A: F64
    G: Gram
    C: list[int]
    cur_names: list[str]
    groups: dict[str, list[int]]
    scale_y: float
    rss0: float
    th0: dict[int, float]
    Ne: float
    col_rms: F64
    model: Model
    search: dict[str, tuple[SearchResult, ...]]

    @property
    def rms_ls(self) -> float:
        """Residual RMS of the model's least squares (output unit)."""
        return self.rms_of(self.rss0)

    def rms_of(self, rss: float) -> float:
        return math.sqrt(rss / self.N) * self.scale_y if self.N else math.nan

    def parameters(self, name: str) -> int:
        """The parameters candidate ``name`` adds: its columns' and those searched."""
        return len(self.groups[name]) + sum(not r.kept for r in self.search.get(name, ()))

    def bic(self, rss_new: float, rss_old: float, p: int) -> float:
        """:func:`delta_bic` over these rows."""
        return delta_bic(self.Ne, rss_new, rss_old, p)


@dataclass
class _Evaluation:
    """One candidate added alone to the model: its columns, the share of the residual
    variance it explains, the RSS and ΔBIC after it, its independence of the model's
    columns (1/VIF) and excitation, why it is not identifiable ("" when it is) and its
    parameters (name -> (value, unit))."""

    cols: list[int]
    explained: float
    rss: float
    dbic: float
    ind: float
    exc: float
    reason: str
    params: dict[str, tuple[float, str]]


@dataclass(frozen=True)
class _Outcome:
    """What the selection leaves: the suggestion (empty when withdrawn), the structure left
    in the residual, the suggestion withdrawn (``partial``) and the effects chosen."""

    suggestion: Suggestion
    structure: tuple[StructureItem, ...]
    partial: Suggestion | None
    chosen: list[str]


@dataclass(frozen=True)
class _Selection:
    """The greedy forward selection: its steps, the effects chosen and the RSS after them."""

    steps: tuple[Step, ...]
    chosen: list[str]
    rss: float


def _candidate_names(model: Model, eq: Equation, signals: Signals | SpilledSignals,
                     max_order: int) -> tuple[list[str], list[tuple[str, str]]]:
    """The library effects (and configured user terms) not in the model, for this equation."""
    have = set(model.effect_names)
    names: list[str] = []
    na: list[tuple[str, str]] = []
    has_pos = signals.position is not None
    for cls in library():
        base = cls.NAME
        if base == "user":
            for term, t in sorted(model.terms.items()):
                nm = f"user:{term}"
                if nm in have or t.get("equation", MECHANICAL) != eq.name:
                    continue
                names.append(nm)
            continue
        if cls.EQUATION != eq.name:
            if base == "electrical" and "electrical" not in have:
                if signals.voltage is None:
                    na.append((base, "needs the voltage signal, which the data do not carry"))
                else:
                    na.append((base, "a second (voltage) equation: it cannot explain the "
                                     "mechanical residual; add it to identify R, L and Ke"))
            continue
        if base == "cogging":
            if not has_pos:
                na.append(("cogging:K", "needs the position, which the data do not carry"))
                continue
            names.extend(f"cogging:{k}" for k in range(2, max_order + 1)
                         if f"cogging:{k}" not in have)
            continue
        if base in have:
            continue
        if "position" in cls.REQUIRES and not has_pos:
            na.append((base, "needs the position, which the data do not carry"))
            continue
        names.append(base)
    # drop what the model cannot take (e.g. a signal the drive does not send)
    ok: list[str] = []
    tried_cog: bool | None = None
    for nm in names:
        if nm.startswith("cogging:"):
            if tried_cog is None:
                try:
                    model.with_effects(add=[nm])
                    tried_cog = True
                except ConfigError as e:
                    tried_cog = False
                    na.append(("cogging:K", str(e)))
            if tried_cog:
                ok.append(nm)
            continue
        try:
            model.with_effects(add=[nm])
        except ConfigError as e:
            na.append((nm, str(e)))
            continue
        if nm.startswith("user:"):
            eff = model.with_effects(add=[nm]).effects[-1]
            miss = [r for r in eff.requires if getattr(signals, r, None) is None]
            if miss:
                na.append((nm, f"reads {', '.join(miss)}, which the data do not carry"))
                continue
        ok.append(nm)
    return ok, na


def rank_candidates(ctx: RecordSamples, model: Model, eq: Equation,
                    res: ResidualSummary) -> CandidateResult:
    """Rank the library's effects that ``model`` lacks against the residual of ``eq``.

    The steps: compare every candidate on the same rows (:func:`_compare`), check the
    model's own columns, evaluate each candidate alone, mark the pairs that cannot be
    told apart, select greedily, look at what structure is left, list the candidates
    and write the verdict.
    """
    cmp = _compare(ctx, model, eq, res)
    ws = known_stribeck_speed(cmp.model, res.configured, cmp.search)
    if ws != res.exc.stribeck_speed:
        # the time below the Stribeck speed found, not below the library's default
        res = dataclasses.replace(res, exc=excitation_summary(ctx, cmp.model, res.used, ws))
    model = cmp.model  # with the values the search found
    model_issues = _model_issues(cmp, res.exc, model)
    evaluated = _evaluate(cmp, ctx, model, res.exc)
    inseparable = _inseparable(evaluated, cmp.G, cmp.C, res.exc, cmp.bic)
    cog = [nm for nm in evaluated if nm.startswith("cogging:")]
    best_cog = max(cog, key=lambda nm: (evaluated[nm].explained, -int(nm[8:]))) \
        if cog else None
    sel = _forward_select(cmp, evaluated)
    if sel.chosen and any(ev.reason and ev.explained > 1.0 - sel.rss / cmp.rss0
                          for ev in evaluated.values()):
        # a candidate these data cannot identify would explain more: the selection is
        # a partial explainer, not what is missing (the verdict names the other)
        sel = _Selection((), [], cmp.rss0)
    out = _what_is_left(ctx, model, eq, res, cmp, sel)
    ev_ctx = _EvidenceContext(ctx, res.bins, res.spectrum, res.unit, cmp.used, cmp.A, cmp.G,
                              cmp.C, cmp.aug, evaluated, best_cog, cog, model)
    cands = _listed(cmp, evaluated, out.chosen, best_cog, cog, ev_ctx, eq)
    not_ident = [c for c in cands if not c.identifiable]
    reasons = [*model_issues, *(f"{c.effect}: {c.reason}" for c in not_ident)]
    verdict = _verdict(eq, out.suggestion, cands, out.structure, model_issues, not_ident,
                       res.exc, res.unit, cmp.rms_ls, out.partial, inseparable,
                       cmp.not_applicable)
    verdict += _convergence_note(res, cmp.rms_ls)
    return CandidateResult(tuple(cands), tuple(cmp.not_applicable), out.suggestion,
                           out.structure, not model_issues and not not_ident, tuple(reasons),
                           verdict, cmp.rms_ls, res.exc)


def _compare(ctx: RecordSamples, model: Model, eq: Equation,
             res: ResidualSummary) -> _Comparison:
    """The model with every candidate, on the samples the pipeline would use with them."""
    names, na = _candidate_names(model, eq, ctx.signals, ctx.max_order)
    used = _eval_rows(ctx, model, eq, names, res.used)
    N = used.count()
    n = eq.n
    Ne = max(N * res.h2, 2.0)
    model, search = search_parameters(
        ctx, model, eq, names, used, res.configured,
        lambda new, old, p: delta_bic(Ne, new, old, p), MIN_INDEPENDENCE)
    cur_names = [p.name for p in eq.parameters]
    aug_model = model.with_effects(add=names) if names else model
    aug = aug_model.equation(eq.name)
    if [p.name for p in aug.parameters[:n]] != cur_names:  # pragma: no cover - contract
        raise AssertionError("with_effects did not keep the model's columns first")
    A = ctx.gram(aug, used, n)
    G = Gram(A)
    C = list(range(n))
    # groups of columns per candidate effect
    groups: dict[str, list[int]] = {}
    for j, p in enumerate(aug.parameters[n:], start=n):
        groups.setdefault(p.effect, []).append(j)
    rss0, th0 = G.solve(C)
    # RMS of each filtered column in its own unit: phi_j 2**s_j (from the data alone)
    col_rms = np.sqrt(np.maximum(np.diag(A)[:-1], 0.0) / max(N, 1)) \
        * np.ldexp(1.0, np.array(aug.scaling.columns))
    return _Comparison(names, na, used, N, aug_model, aug, A, G, C, cur_names, groups,
                       math.ldexp(1.0, aug.scaling.output), rss0, th0, Ne, col_rms,
                       model, search)


def _model_issues(cmp: _Comparison, exc: ExcitationSummary, model: Model) -> list[str]:
    """The model's own columns that are not excited or (nearly) collinear, and why."""
    G, C, cur_names = cmp.G, cmp.C, cmp.cur_names
    issues: list[str] = []
    for j in C:
        others = [i for i in C if i != j]
        ind = G.independence([j], others) if others else 1.0
        why = _unexcited_reason(cur_names[j], exc)
        if G.zero[j] or why:
            issues.append(f"{cur_names[j]} is "
                          + (why or "not excited: its column is practically zero"))
        elif ind < MIN_INDEPENDENCE:
            partners = sorted(others, key=lambda i: -abs(G.corr(i, j)))[:2]
            pair = {cur_names[j].split(".")[0], cur_names[partners[0]].split(".")[0]}
            experiment = (f"; {SIGN_PAIR_TEXT}" if pair == SIGN_PAIR and exc.one_direction
                          else "")
            issues.append(
                f"{cur_names[j]} is (nearly) collinear with "
                f"{' and '.join(cur_names[i] for i in partners)} "
                f"({share_text(ind)} of its column independent){experiment}")
    return issues


def _evaluate(cmp: _Comparison, ctx: RecordSamples, model: Model,
              exc: ExcitationSummary) -> dict[str, _Evaluation]:
    r"""Every candidate added alone to the model.

    With :math:`r_0` the least-squares residual of the model's columns and
    :math:`\tilde G` the candidate's columns orthogonalised against them, the share of
    the residual variance it explains is the error-reduction ratio

    .. math::

        \mathrm{ERR} = \frac{r_0^\top \tilde G (\tilde G^\top\tilde G)^{-1}
                             \tilde G^\top r_0}{r_0^\top r_0}

    (from the Gram matrix: :math:`1 - \mathrm{RSS}/\mathrm{RSS}_0`). A candidate not
    excited, (nearly) collinear with the model's columns (less than
    :data:`MIN_INDEPENDENCE` outside their span) or periodic in time as much as in
    position is not identifiable, and the reason is kept.
    """
    G, C, aug = cmp.G, cmp.C, cmp.aug
    factors = aug.scaling.factors
    evaluated: dict[str, _Evaluation] = {}
    for name, cols in cmp.groups.items():
        exc_c = float(np.max(cmp.col_rms[cols]))
        ind = G.independence(cols, C)
        rss, x = G.solve(C + cols)
        expl = (cmp.rss0 - rss) / cmp.rss0 if cmp.rss0 > 0 else 0.0
        expl = min(max(expl, 0.0), 1.0)
        reason = ""
        order = aug.parameters[cols[0]].order
        unexcited = _unexcited_reason(name, exc)
        if all(G.zero[j] for j in cols):
            reason = unexcited or "not excited: its column is zero over the record"
        elif unexcited:
            reason = unexcited
        elif ind < MIN_INDEPENDENCE:
            reason = _collinear_reason(name, cols, C, G, cmp.cur_names, ind, exc)
        elif order > 0 and ctx.angle_raw is not None:
            coh, f_hz = ctx.coherence(order, cmp.used)
            if coh >= MAX_COHERENCE:
                reason = (f"not identifiable from this data: the speed is nearly constant, so "
                          f"order {order} in position is a sinusoid of {f_hz:.3g} Hz in time "
                          f"(coherence {coh:.2f}); it cannot be told from a disturbance "
                          f"periodic in time: vary the speed")
        params = {aug.parameters[j].name: (float(x.get(j, 0.0) * factors[j]),
                                           aug.parameters[j].unit) for j in cols}
        evaluated[name] = _Evaluation(cols, expl, rss, cmp.bic(rss, cmp.rss0,
                                                               cmp.parameters(name)), ind,
                                      exc_c, reason, params)
    return evaluated


def _forward_select(cmp: _Comparison, evaluated: Mapping[str, _Evaluation]) -> _Selection:
    """Orthogonal least squares: add the best identifiable candidate, re-rank the others
    against the enlarged model, stop when the next explains less than
    :data:`MIN_EXPLAINED` of what is left or does not lower the BIC (at most 8)."""
    G, C = cmp.G, cmp.C
    steps: list[Step] = []
    sel: list[int] = []
    chosen: list[str] = []
    rss_cur = cmp.rss0
    pool = [nm for nm, ev in evaluated.items() if not ev.reason]
    for _ in range(8):
        best = None
        for nm in pool:
            if nm in chosen:
                continue
            cols = evaluated[nm].cols
            if G.independence(cols, C + sel) < MIN_INDEPENDENCE:
                continue
            rss, _ = G.solve(C + sel + cols)
            if best is None or rss < best[1]:
                best = (nm, rss)
        if best is None or rss_cur <= 0:
            break
        nm, rss = best
        expl = (rss_cur - rss) / rss_cur
        db = cmp.bic(rss, rss_cur, cmp.parameters(nm))
        searched = cmp.parameters(nm) > len(evaluated[nm].cols)
        if expl < (MIN_EXPLAINED_SEARCHED if searched else MIN_EXPLAINED) or db >= 0:
            break
        chosen.append(nm)
        sel += evaluated[nm].cols
        steps.append(Step(nm, float(expl), float(db), cmp.rms_of(rss)))
        rss_cur = rss
    return _Selection(tuple(steps), chosen, rss_cur)


def _what_is_left(ctx: RecordSamples, model: Model, eq: Equation, res: ResidualSummary,
                  cmp: _Comparison, sel: _Selection) -> _Outcome:
    """The suggestion and the structure left after it; the suggestion is withdrawn when
    it explains less than :data:`MIN_TOTAL` of structure that stays."""
    suggestion = Suggestion(sel.steps, cmp.rms_ls)
    chosen = list(sel.chosen)
    partial: Suggestion | None = None
    structure: tuple[StructureItem, ...] = ()
    if chosen:
        # the model with the suggestion, on the samples the pipeline will use for it
        # (periodic effects drop the fast samples there, instead of being masked)
        eq2 = model.with_effects(add=chosen).equation(eq.name)
        rows2 = _eval_rows(ctx, model, eq, chosen, res.used, periodic=True)
        # r = y - Phi theta, theta the least squares on rows2 (block by block)
        r_left = ctx.fit_residual(eq2, rows2)
        n2, _, e2, _ = moments(r_left, rows2)
        if n2:
            suggestion = Suggestion(suggestion.steps, suggestion.rms_before,
                                    math.sqrt(e2 / n2))
        structure = residual_structure(ctx, r_left, rows2, res.unit, res.h2, None,
                                       eq.output.signal)
        total = 1.0 - sel.rss / cmp.rss0 if cmp.rss0 > 0 else 0.0
        if structure and total < MIN_TOTAL:
            # the best candidates explain part of the structure and leave the rest: they
            # are not what is missing; say so instead of suggesting them
            partial, suggestion, chosen = suggestion, Suggestion((), cmp.rms_ls), []
    if not chosen:
        # nothing to add: the least-squares residual of the model as it is (structure the
        # model's own columns can absorb is the estimator's, not a missing effect)
        th_ls = np.array([cmp.th0.get(j, 0.0) for j in cmp.C])
        r_ls = ctx.residual(eq, th_ls)  # block by block
        # the displayed spectrum (of r) serves when r_ls is practically r
        dd = el = 0.0
        for a in range(0, len(res.r), BLOCK):
            u = cmp.used[a:a + BLOCK]
            x, d = r_ls[a:a + BLOCK][u], (r_ls[a:a + BLOCK] - res.r[a:a + BLOCK])[u]
            dd += float(np.dot(d, d))
            el += float(np.dot(x, x))
        same = dd <= 0.01 * el and cmp.N == res.used.count()
        structure = residual_structure(ctx, r_ls, cmp.used, res.unit, res.h2,
                                       res.spectrum if same else None, eq.output.signal)
    return _Outcome(suggestion, structure, partial, chosen)


def _listed(cmp: _Comparison, evaluated: Mapping[str, _Evaluation], chosen: Sequence[str],
            best_cog: str | None, cog: Sequence[str], ev_ctx: _EvidenceContext,
            eq: Equation) -> list[Candidate]:
    """The candidates to show, best first: every effect once and, of the cogging orders,
    the best one and those suggested; the suggestion in the order it was chosen, then by
    share explained (identifiable ones before the others)."""
    listed = [nm for nm in evaluated if not nm.startswith("cogging:")]
    extra_cog = [nm for nm in cog if nm in chosen]
    if best_cog is not None and best_cog not in extra_cog:
        extra_cog.insert(0, best_cog)
    listed += extra_cog
    effects: dict[str, Effect] = {}
    for e in cmp.aug_model.effects:
        effects.setdefault(e.name, e)
    cands = []
    for nm in listed:
        ev = evaluated[nm]
        eff = effects[nm]
        cands.append(Candidate(
            effect=nm, equation=eq.name, description=_description(eff),
            signature=type(eff).RESIDUAL_SIGNATURE, explained=float(ev.explained),
            delta_bic=float(ev.dbic), rms_after=cmp.rms_of(ev.rss),
            identifiable=not ev.reason, suggested=nm in chosen, reason=ev.reason,
            evidence=tuple(_evidence(nm, ev_ctx)), parameters=ev.params,
            independence=float(ev.ind), excitation=float(ev.exc),
            search=cmp.search.get(nm, ())))
    cands.sort(key=lambda c: (chosen.index(c.effect) if c.suggested else len(chosen),
                              0 if c.identifiable else 1, -c.explained))
    return cands


def _convergence_note(res: ResidualSummary, rms_ls: float) -> str:
    """A note when the final estimate's residual is 10 % above the least squares' ("" else)."""
    n_f, _, e_f, _ = moments(res.r, res.used)
    rms_final = math.sqrt(e_f / n_f) if n_f else math.nan
    if not rms_final > 1.1 * rms_ls:
        return ""
    return (f" Note: the final estimate leaves a residual RMS of "
            f"{value_text(rms_final, res.unit)}"
            f", {100 * (rms_final / rms_ls - 1):.0f} % more than the least-squares fit "
            f"of the same model over the whole record ({value_text(rms_ls, res.unit)}): the "
            f"estimator has not converged, or forgetting or the ridge prior bias it "
            f"(see the parameter convergence).")


def _one_tells(G: Gram, C: Sequence[int], ca: Sequence[int], cb: Sequence[int],
               bic: Callable[[float, float, int], float]) -> bool:
    """The data tell one of two nearly collinear candidates from the other: added on top
    of the other, it still explains :data:`MIN_EXPLAINED` of what is left and lowers the
    information criterion (what little of its column lies outside the other's span
    carries much of the residual)."""
    both = G.solve([*C, *ca, *cb])[0]
    for alone, p in ((G.solve([*C, *ca])[0], len(cb)), (G.solve([*C, *cb])[0], len(ca))):
        if alone > 0 and (alone - both) / alone >= MIN_EXPLAINED and bic(both, alone, p) < 0:
            return True
    return False


def _inseparable(evaluated: Mapping[str, _Evaluation], G: Gram, C: Sequence[int],
                 exc: ExcitationSummary, bic: Callable[[float, float, int], float]
                 ) -> list[tuple[str, str, float]]:
    """Pairs of candidates, each identifiable against the model alone, that cannot be
    told apart from one another on these data (less than :data:`MIN_INDEPENDENCE` of
    one outside the span of the model and the other). Both are marked not identifiable,
    with the experiment that would separate them; returns ``(a, b, explained)`` with
    the share of the residual variance the pair explains together. Cogging orders are
    compared with the other effects only (orders are orthogonal to one another)."""
    names = [nm for nm, ev in evaluated.items() if not ev.reason]
    out: list[tuple[str, str, float]] = []
    for i, a in enumerate(names):
        for b in names[i + 1:]:
            if a.startswith("cogging:") and b.startswith("cogging:"):
                continue
            ca, cb = evaluated[a].cols, evaluated[b].cols
            ind = min(G.independence(ca, [*C, *cb]), G.independence(cb, [*C, *ca]))
            if ind >= MIN_INDEPENDENCE or _one_tells(G, C, ca, cb, bic):
                continue
            expl = max(evaluated[a].explained, evaluated[b].explained)
            out.append((a, b, expl))
            for x, y in ((a, b), (b, a)):
                if {x, y} == SIGN_PAIR and exc.one_direction:
                    why = f"not identifiable from this data: {SIGN_PAIR_TEXT}"
                else:
                    why = (f"not identifiable from this data: it cannot be told apart from "
                           f"{y} ({share_text(ind)} independent)")
                    facts = exc.facts()
                    if facts:
                        why += "; " + "; ".join(facts)
                if not evaluated[x].reason or x == a:
                    evaluated[x].reason = why
    return out


def _description(eff: Effect) -> str:
    doc = (type(eff).__doc__ or "").strip().splitlines()
    first = doc[0].strip() if doc else eff.name
    if isinstance(eff, UserTerm):
        return f"user term {eff.term}: c * ({eff.expr})"
    if isinstance(eff, Cogging):
        k = str(eff.k)
        return f"{first.replace('``k``', k)} ({eff.EQUATION_TEXT.replace('k', k)})"
    return f"{first} ({type(eff).EQUATION_TEXT})"


def _unexcited_reason(name: str, exc: ExcitationSummary) -> str:
    """Why an effect's column is not excited by these data ("" when it is)."""
    u = exc.speed_unit
    base = name.split(":")[0].split(".")[0]
    if base == "stribeck":
        ws, low = exc.stribeck_speed, exc.low_speed
        if ws is None or low is None:  # no speed set and none searched: no room for one
            return ("not excited: no speed of the record lies where a Stribeck speed could "
                    "be searched (above the Coulomb band, below a third of the median speed)")
        if low < 0.005:
            return (f"not excited: the speed is below twice the Stribeck speed "
                    f"({2 * ws:g} {u}) in only {share_text(low)} of the samples")
    if base == "inertia" and not exc.accelerating:
        return (f"not excited: the acceleration is at the level of the speed-sensor noise "
                f"(RMS {exc.acceleration_rms:.3g} {u}/s against {exc.acceleration_noise:.3g} "
                f"{u}/s)")
    if base in ("unbalance", "cogging") and exc.revolutions is not None \
            and exc.revolutions < 1.0 and exc.coverage is None:
        return f"not excited: the position covers only {exc.revolutions:.2f} {exc.per}s"
    if base in ("unbalance", "cogging") and exc.coverage is not None:
        k = 1 if base == "unbalance" else int(name.split(".")[0].split(":")[1])
        if exc.coverage * k < MIN_PERIODS:
            period = f"one {exc.per}" if k == 1 else f"1/{k} {exc.per}"
            longer = "longer than" if exc.coverage * k < 1.0 else \
                f"not short against (fewer than {MIN_PERIODS:g} periods in)"
            return (f"not identifiable from this data: its period ({period}) is {longer} "
                    f"the travel covered ({exc.coverage:.3g} {exc.per}s), so it fits any slow "
                    f"trend along the position; record more travel (at least "
                    f"{MIN_PERIODS / k:.3g} {exc.per}{'' if MIN_PERIODS == k else 's'})")
    return ""


def _collinear_reason(name: str, cols: Sequence[int], C: Sequence[int], G: Gram,
                      cur: Sequence[str], ind: float, exc: ExcitationSummary) -> str:
    partners = sorted(C, key=lambda i: -max(abs(G.corr(i, j)) for j in cols))
    strong = [cur[i] for i in partners if max(abs(G.corr(i, j)) for j in cols) > 0.9][:2]
    if exc.one_direction and strong and {name, strong[0].split(".")[0]} == SIGN_PAIR:
        return (f"not identifiable from this data: its column is (nearly) collinear with "
                f"{strong[0]} ({share_text(ind)} independent): {SIGN_PAIR_TEXT}")
    what = (f"(nearly) collinear with {' and '.join(strong)}" if strong
            else "(nearly) collinear with the model's columns")
    why = exc.facts()
    text = f"not identifiable from this data: its column is {what} ({share_text(ind)} " \
           f"independent)"
    if why:
        text += "; " + "; ".join(why)
    # the experiment that would separate it
    todo = (["record a run in both directions"] if exc.one_direction and name in SIGN_PAIR
            else []) + (["vary the speed"] if exc.constant_speed else [])
    if todo:
        text += "; " + " and ".join(todo)
    return text


@dataclass
class _EvidenceContext:
    ctx: RecordSamples
    bins: Mapping[str, Binned]
    spectrum: OrderSpectrum | None
    unit: str
    used: PackedMask
    A: F64
    G: Gram
    C: list[int]
    aug: Equation
    evaluated: Mapping[str, _Evaluation]
    best_cog: str | None
    cog: list[str]
    model: Model


def _speed_sides(b: Binned) -> list[tuple[float, float, float, int, float, int]]:
    """(lo, hi, mean forward, n forward, mean backward, n backward) per magnitude band."""
    nm = (len(b.edges) - 1) // 2
    out = []
    for j in range(nm):
        f, bk = nm + j, nm - 1 - j
        out.append((float(b.edges[f]), float(b.edges[f + 1]), float(b.mean[f]),
                    int(b.count[f]), float(b.mean[bk]), int(b.count[bk])))
    return out


def _pooled(rows: Sequence[tuple[float, float, float, int, float, int]],
            side: int) -> float:
    m_i, n_i = (2, 3) if side > 0 else (4, 5)
    tot = sum(r[n_i] for r in rows if r[n_i] >= MIN_BIN)
    if not tot:
        return math.nan
    return sum(r[m_i] * r[n_i] for r in rows if r[n_i] >= MIN_BIN) / tot


def _side(mean: float, unit: str, way: str) -> str:
    """``+0.0051 N·m forward``, or ``no samples forward`` where that side has none."""
    return f"{value_text(mean, unit, True)} {way}" if math.isfinite(mean) \
        else f"no samples {way}"


def _evidence(name: str, ec: _EvidenceContext) -> list[str]:
    ev = ec.evaluated[name]
    u = ec.unit
    su = ec.ctx.speed_unit
    out: list[str] = []
    base = name.split(":")[0]
    sb = ec.bins.get("speed")
    rows = _speed_sides(sb) if sb is not None else []
    if base in ("coulomb", "viscous", "stribeck", "offset") and rows:
        vmax = rows[-1][1]
        ws = ec.model.stribeck_speed
        if base == "coulomb":
            far = [r for r in rows if r[0] >= min(3 * ws, 0.3 * vmax)]
            mf, mb = _pooled(far, 1), _pooled(far, -1)
            both = math.isfinite(mf) and math.isfinite(mb)
            out.append(f"above {min(3 * ws, 0.3 * vmax):.3g} {su} the residual is "
                       f"{_side(mf, u, 'moving forward')} and "
                       f"{_side(mb, u, 'moving backward')}: "
                       + ("a step at zero speed, signed with the direction" if both else
                          "one direction only, where a step signed with the direction "
                          "cannot be told from an offset"))
        elif base == "stribeck":
            near = [r for r in rows if r[1] <= ws * 1.0001]
            far = [r for r in rows if r[0] >= 3 * ws]
            out.append(f"below {ws:g} {su}: {_side(_pooled(near, 1), u, 'forward')}, "
                       f"{_side(_pooled(near, -1), u, 'backward')}; above {3 * ws:g} {su}: "
                       f"{_side(_pooled(far, 1), u, 'forward')}, "
                       f"{_side(_pooled(far, -1), u, 'backward')}")
        elif base == "viscous":
            top = [r for r in rows if r[0] >= 0.3 * vmax]
            lowr = [r for r in rows if r[1] <= 0.1 * vmax]
            out.append(f"above {0.3 * vmax:.3g} {su}: "
                       f"{_side(_pooled(top, 1), u, 'forward')},"
                       f" {_side(_pooled(top, -1), u, 'backward')}; below "
                       f"{0.1 * vmax:.3g} {su}: {_side(_pooled(lowr, 1), u, 'forward')}, "
                       f"{_side(_pooled(lowr, -1), u, 'backward')} (linear and odd in "
                       f"speed)")
        elif base == "offset":
            out.append(f"mean residual {_side(_pooled(rows, 1), u, 'moving forward')} and "
                       f"{_side(_pooled(rows, -1), u, 'moving backward')}")
    if base in ("unbalance", "cogging") and ec.spectrum is not None:
        k = 1 if base == "unbalance" else int(name.split(".")[0].split(":")[1])
        a, e = ec.spectrum.at(k)
        txt = (f"order {k} of the rotation-order spectrum: amplitude {value_text(a, u)} "
               f"({share_text(e)} of the residual variance)")
        if base == "cogging" and name == ec.best_cog:
            others = sorted((nm for nm in ec.cog if nm != name),
                            key=lambda nm: -ec.evaluated[nm].explained)
            if others:
                o = others[0]
                txt += (f"; the strongest order of the search k = 2..{ec.ctx.max_order}, next "
                        f"{o.split(':')[1]} ({share_text(ec.evaluated[o].explained)})")
        out.append(txt)
    if base == "inertia":
        ab = ec.bins.get("acceleration")
        if ab is not None:
            ok = ab.count >= MIN_BIN
            if np.any(ok):
                lo_j = int(np.flatnonzero(ok)[0])
                hi_j = int(np.flatnonzero(ok)[-1])
                out.append(f"at {ab.centers[hi_j]:.3g} {ab.unit} the residual is "
                           f"{value_text(float(ab.mean[hi_j]), u, True)}, at "
                           f"{ab.centers[lo_j]:.3g} {ab.unit} "
                           f"{value_text(float(ab.mean[lo_j]), u, True)}")
    # the candidate's own column against the residual
    if ev.explained > 0:
        out.append(f"explains {100 * ev.explained:.3g} % of the residual variance "
                   f"(correlation {math.sqrt(ev.explained):.2f} with its orthogonalised "
                   f"column)")
    vals = ", ".join(f"{k} ≈ {v:.4g} {un}" for k, (v, un) in ev.params.items())
    if vals:
        out.append(f"would be {vals}")
    return out


def _untested(na: Sequence[tuple[str, str]]) -> str:
    """The effects no test could reach, grouped by reason (the electrical equation is
    another equation's business and left out)."""
    by: dict[str, list[str]] = {}
    for nm, why in na:
        if nm != "electrical":
            by.setdefault(why, []).append(nm)
    if not by:
        return ""
    return " Untested: " + "; ".join(f"{', '.join(v)} ({k})" for k, v in by.items()) + "."


def _verdict(eq: Equation, suggestion: Suggestion, cands: Sequence[Candidate],
             structure: Sequence[StructureItem], model_issues: Sequence[str],
             not_ident: Sequence[Candidate], exc: ExcitationSummary, unit: str,
             rms_ls: float, partial: Suggestion | None = None,
             inseparable: Sequence[tuple[str, str, float]] = (),
             na: Sequence[tuple[str, str]] = ()) -> str:
    name = eq.name
    if (not model_issues and not structure and not suggestion and not_ident
            and all(c.explained < MENTION_EXPLAINED and SIGN_PAIR_TEXT not in c.reason
                    for c in not_ident)):
        # the model's own parameters are identified and nothing is left: the candidates
        # these data could not test (not excited, too little travel) are untested, named
        # as such beside "complete", not a verdict of "not identifiable"
        na = [*na, *((c.effect, c.reason.removeprefix("not identifiable from this data: "))
                     for c in not_ident)]
        not_ident = []
    tail = _untested(na)
    # what cannot be separated but would explain much: always said, with the experiment
    pairs = [(a, b, e) for a, b, e in inseparable if e >= MENTION_EXPLAINED]
    pair_text = ""
    for a, b, e in pairs:
        how = SIGN_PAIR_TEXT if {a, b} == SIGN_PAIR and exc.one_direction else \
            f"these data cannot tell {a} from {b}; vary the excitation"
        pair_text += (f" {a} or {b} would explain {share_text(e)} of the residual variance, "
                      f"but {how}.")
    if suggestion:
        adds = " ".join(f"--add {a}" for a in suggestion.add)
        first = suggestion.steps[0]
        text = (f"{name}: missing {', '.join(suggestion.add)}; {first.effect} explains "
                f"{100 * first.explained:.3g} % of the residual variance. Add it: {adds} "
                f"(predicted residual RMS {value_text(rms_ls, unit)} -> "
                f"{value_text(suggestion.rms_after, unit)}).")
        if structure:
            text += " Left after that: " + "; ".join(s.text for s in structure[:2]) + "."
        return text + pair_text + tail
    parts = []
    if pair_text:
        parts.append(f"{name}:{pair_text}")
    if model_issues or not_ident:
        why = list(model_issues)
        paired = {x for a, b, _ in pairs for x in (a, b)}
        rest = [c for c in not_ident if c.effect not in paired]
        for c in [c for c in rest if SIGN_PAIR_TEXT in c.reason]:
            why.append(f"{c.effect} is collinear with the model's "
                       f"{next(iter(SIGN_PAIR - {c.effect}))}: {SIGN_PAIR_TEXT}")
        rest = [c for c in rest if SIGN_PAIR_TEXT not in c.reason]
        for c in [c for c in rest if c.explained >= MENTION_EXPLAINED]:
            reason = c.reason.removeprefix("not identifiable from this data: ")
            why.append(f"{c.effect} would explain {share_text(c.explained)} of the residual "
                       f"variance, but {reason}")
        rest = [c for c in rest if c.explained < MENTION_EXPLAINED]
        if rest:
            why.append(f"{', '.join(c.effect for c in rest)} cannot be told apart from "
                       f"the model's columns or are not excited")
        facts = exc.facts()
        if why:
            lead = "Also not" if parts else f"{name}: not"
            parts.append(f"{lead} identifiable from this data: {'; '.join(why)}"
                         + (f" ({'; '.join(facts)})" if facts else "") + ".")
    if structure:
        what = "; ".join(s.text for s in structure[:3])
        if model_issues or not_ident:
            parts.append(f"Structure left in the residual: {what}; it may come from an "
                         f"effect that these data cannot identify.")
        else:
            parts.append(f"{name}: no effect of the library explains the structure left: "
                         f"{what}.")
        if partial:
            tot = 1.0 - (partial.rms_after / partial.rms_before) ** 2 \
                if partial.rms_before > 0 else 0.0
            parts.append(f"The closest candidates ({', '.join(partial.add)}) would explain "
                         f"only {share_text(tot)} of it together.")
    if not parts:
        best = next((c for c in cands if c.identifiable), None)
        large = (f" (largest: {best.effect}, {share_text(best.explained)})" if best else "")
        tested = "no effect of the library that these data could test" if tail else \
            "no effect of the library"
        parts.append(f"{name}: the model is complete for this data: {tested} explains a "
                     f"significant share of the residual{large}.")
        big = [c for c in cands if c.explained >= MENTION_EXPLAINED]
        if big:
            parts[-1] = (f"{name}: no effect to add, yet "
                         + ", ".join(f"{c.effect} would explain {share_text(c.explained)}"
                                     for c in big)
                         + " of the residual variance (not suggested: it does not lower the "
                           "information criterion enough).")
    return " ".join(parts) + tail
