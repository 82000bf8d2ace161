"""The search of the parameters the regression cannot estimate linearly.

Each effect names its own (:meth:`~canrls.estimation.effects.Effect.search_space`: the
Stribeck speed, the Coulomb band, a user term's free parameter) with a grid over what
the record covers; :func:`search_parameters` fits the candidate at every value by batch
least squares on the rows the candidates are compared on, keeps the value of the
smallest residual (refined between its neighbours) and returns the model with it. A
value set in the configuration is kept. The rule: docs/diagnose.md, "Nonlinear
parameters".
"""

from __future__ import annotations

import functools
import math
import os
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import numpy as np
import numpy.typing as npt

from canrls.core.spill import PackedMask
from canrls.diagnosis.record import BLOCK, RecordSamples
from canrls.diagnosis.results import SearchResult
from canrls.estimation.model import DATA_OPTIONS, Equation, Model
from canrls.estimation.nonlinear import RecordSpan, minimise_on_grid, record_span
from canrls.estimation.pipeline import EstimatorSettings
from canrls.processor import measure_noise

__all__ = ["Gram", "delta_bic", "known_stribeck_speed", "search_parameters", "search_model"]

F64 = npt.NDArray[np.float64]


def delta_bic(Ne: float, rss_new: float, rss_old: float, p: int) -> float:
    """The change of the Bayesian information criterion when ``p`` parameters take the
    RSS from ``rss_old`` to ``rss_new``, over the ``Ne = N ||h||^2`` independent
    samples the filter leaves."""
    # dBIC = Ne ln(RSS'/RSS) + p ln Ne
    if rss_old <= 0:
        return math.inf
    return Ne * math.log(max(rss_new, 1e-300 * rss_old) / rss_old) + p * math.log(Ne)


class Gram:
    r"""Least squares from the Gram matrix of ``[columns..., y]`` (columns equilibrated).

    ``rss(S)`` is the residual sum of squares of y regressed on the columns ``S``
    (normalised units); pseudo-inverses drop directions below 1e-12 of the largest.
    A column is ``zero`` when it has no non-zero value on the rows summed.
    """

    def __init__(self, A: F64) -> None:
        self.m = A.shape[0] - 1
        d = np.sqrt(np.maximum(np.diag(A), 0.0))
        self.zero = d[: self.m] <= 1e-300
        d = np.where(d > 1e-300, d, 1.0)
        self.d = d
        self.An = A / np.outer(d, d)
        self.yy = float(A[-1, -1])

    def solve(self, S: Sequence[int]) -> tuple[float, dict[int, float]]:
        """(RSS, {column: coefficient in the column's units}) of y on columns S."""
        S = [j for j in S if not self.zero[j]]
        if not S:
            return self.yy, {}
        Ass = self.An[np.ix_(S, S)]
        b = self.An[S, -1]
        w, V = np.linalg.eigh(Ass)
        keep = w > 1e-12 * max(float(w[-1]), 1e-300)
        x = V[:, keep] @ ((V[:, keep].T @ b) / w[keep])
        rss = (float(self.An[-1, -1]) - float(b @ x)) * self.d[-1] ** 2
        coef = x * self.d[-1] / self.d[S]
        return max(rss, 0.0), {j: float(c) for j, c in zip(S, coef, strict=True)}

    def independence(self, S: Sequence[int], C: Sequence[int]) -> float:
        """Smallest eigenvalue of the equilibrated Schur complement of C in [C, S]: the
        fraction of the worst direction of S outside the span of C (1/VIF)."""
        S = [j for j in S if not self.zero[j]]
        if not S:
            return 0.0
        Ass = self.An[np.ix_(S, S)]
        C = [j for j in C if not self.zero[j]]
        if C:
            Acc = self.An[np.ix_(C, C)]
            Acs = self.An[np.ix_(C, S)]
            w, V = np.linalg.eigh(Acc)
            keep = w > 1e-12 * max(float(w[-1]), 1e-300)
            X = V[:, keep] @ ((V[:, keep].T @ Acs) / w[keep][:, None])
            Ass = Ass - Acs.T @ X
        # relative to the columns' own energy (their equilibrated Gram)
        w0 = np.linalg.eigvalsh(self.An[np.ix_(S, S)])
        ws = np.linalg.eigvalsh(0.5 * (Ass + Ass.T))
        return float(max(ws[0], 0.0) / max(w0[-1], 1e-300))

    def corr(self, i: int, j: int) -> float:
        return float(self.An[i, j])


def _span(ctx: RecordSamples, used: PackedMask, model: Model) -> RecordSpan:
    """What the compared rows cover (:func:`~canrls.estimation.nonlinear.record_span`), the
    speed noise measured on the record's first block."""
    parts = []
    for a in range(0, len(ctx.signals), BLOCK):
        u = used[a:a + BLOCK]
        parts.append(np.asarray(ctx.signals.slice(a, a + BLOCK).speed, np.float64)[u])
    first = ctx.signals.slice(0, min(len(ctx.signals), BLOCK))
    return record_span(np.concatenate([np.zeros(0), *parts]),
                       measure_noise(first, model).get("speed", 0.0), ctx.speed_unit)


def _reads(model: Model, key: str, value: float) -> bool:
    """One of the model's own effects reads the option ``key`` (now ``value``): its
    columns would change with it."""
    if key not in DATA_OPTIONS:
        return False
    return model.with_search_value(key, 2.0 * value).effects != model.effects


def known_stribeck_speed(model: Model, configured: frozenset[str],
                         search: Mapping[str, Sequence[SearchResult]] | None = None
                         ) -> float | None:
    """The Stribeck speed ``ws`` the data are judged by: the model's when set in the
    configuration (``configured``) or read by one of its effects, else the value the
    search found (``search``: :func:`search_parameters`' results, ``model`` the model it
    returned), else None (the library's default is no finding)."""
    key = "stribeck_speed"
    if key in configured or _reads(model, key, model.stribeck_speed):
        return model.stribeck_speed
    if search is not None and any(r.key == key for rs in search.values() for r in rs):
        return model.stribeck_speed
    return None


def search_parameters(ctx: RecordSamples, model: Model, eq: Equation, names: Sequence[str],
                      used: PackedMask, configured: frozenset[str],
                      bic: Callable[[float, float, int], float], min_independence: float
                      ) -> tuple[Model, dict[str, tuple[SearchResult, ...]]]:
    """Search every candidate's nonlinear parameters on the rows ``used``.

    For a candidate ``c`` and a grid value ``v``: the batch least squares of the model
    with ``c`` at ``v`` (its Gram matrix on ``used``); the value of the smallest residual
    sum of squares wins among the values where the candidate's columns keep at least
    ``min_independence`` of their energy outside the span of the model's (a value the
    data cannot tell from the model is no finding), refined by a golden-section search
    (in log) between its grid neighbours. An option one of the model's own effects reads
    is the model's and not searched here; one set in the configuration (``configured``;
    a term's fixed value) is kept. ``bic(rss_new, rss_old, p)`` gives the ΔBIC of the
    candidate at the value found against the model without it. Returns the model with
    the values found and ``{candidate: results}``.
    """
    span = _span(ctx, used, model)
    out: dict[str, tuple[SearchResult, ...]] = {}
    done: set[str] = set()
    rss_model: float | None = None
    # the band first: Stribeck's column reads it too, and is searched with the band found
    order = sorted((nm for nm in names if not nm.startswith("cogging:")),
                   key=lambda nm: nm != "coulomb")
    for nm in order:
        eff = model.with_effects(add=[nm]).effects[-1]
        found: list[SearchResult] = []
        for sp in eff.search_space(span):
            if sp.key in done or _reads(model, sp.key, sp.value):
                continue
            done.add(sp.key)
            if sp.kept or sp.key in configured:
                found.append(SearchResult(sp.key, sp.label, sp.unit, sp.value, True))
                continue
            if not sp.grid:
                continue

            def rss(v: float, key: str = sp.key, name: str = nm, base: Model = model,
                    tellable: bool = True) -> float:
                # the RSS at v; inf where the candidate cannot be told from the model
                m = base.with_search_value(key, v).with_effects(add=[name])
                G = Gram(ctx.gram(m.equation(eq.name), used, eq.n))
                if tellable and G.independence(range(eq.n, G.m), range(eq.n)) \
                        < min_independence:
                    return math.inf
                return G.solve(range(G.m))[0]

            best, r_best = minimise_on_grid(rss, sp.grid)
            if not math.isfinite(r_best):
                # no value these data tell from the model: the best of all, said so by
                # the candidate's identifiability
                best, r_best = minimise_on_grid(functools.partial(rss, tellable=False),
                                                sp.grid)
            if rss_model is None:
                G0 = Gram(ctx.gram(eq, used, eq.n))
                rss_model = G0.solve(range(G0.m))[0]
            p = len(eff.parameters()) + 1  # the searched parameter is one too
            found.append(SearchResult(sp.key, sp.label, sp.unit, best, False,
                                      min(sp.grid), max(sp.grid), len(sp.grid),
                                      bic(r_best, rss_model, p)))
            model = model.with_search_value(sp.key, best)
        if found:
            out[nm] = tuple(found)
    return model, out


def search_model(paths: Sequence[str | os.PathLike[str]], protocol: Any, model: Model,
                 settings: EstimatorSettings | None = None, *,
                 skip_bad_lines: bool = False) -> tuple[Model, tuple[SearchResult, ...]]:
    """The Stribeck speed of a model with Stribeck friction whose configuration does not
    give one, searched on the whole record of ``paths`` as the diagnosis searches a
    candidate's (:func:`search_parameters`, the model's other
    columns with it, on the rows the pipeline uses): ``canrls fit``'s search. Returns
    the model with the values found (given from then on) and what was found."""
    from canrls.processor.replay import read_logs

    settings = settings or EstimatorSettings()
    if "stribeck" not in model.effect_names or "stribeck_speed" in model.options_given:
        return model, ()
    names = ["stribeck"]
    log = read_logs(paths, protocol, model, settings, skip_bad_lines=skip_bad_lines,
                    spill=True)
    try:
        found: list[SearchResult] = []
        base = log.model.with_effects(remove=names)
        ctx = RecordSamples(base, log.signals, log.dt, settings, 1)  # the record, once
        for eq_name in sorted({e.equation for e in model.effects if e.name in names}):
            eq = base.equation(eq_name)
            full = model.equation(eq_name)
            used = ctx.used(full)
            h = ctx.impulse(full.holds[0])
            Ne = max(used.count() * float(np.sum(h * h)), 2.0)
            # independence 0: the model's own column, whose identifiability is the
            # estimator's to judge (prior share, noise), not the search's
            _, out = search_parameters(ctx, base, eq, names, used, model.options_given,
                                       functools.partial(delta_bic, Ne), 0.0)
            found += [r for rs in out.values() for r in rs if r.key == "stribeck_speed"]
        for r in found:
            model = model.with_search_value(r.key, r.value)
        return model, tuple(found)
    finally:
        log.close()
