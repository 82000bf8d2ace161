"""The figures of the HTML report (``canrls diagnose --report DIR``), as SVG files.

:class:`Figures` draws each figure of a diagnosis (timeline, speed, position,
candidates, orders, convergence, fixed point; docs/diagnose.md, "The figures") into a
directory as SVG with matplotlib's object API (no pyplot, no global state). matplotlib
is the optional ``report`` extra: :func:`~canrls.core.webpage.require_matplotlib`
imports it when a report is written, and its absence is a
:class:`~canrls.core.errors.ConfigError` naming the package.
"""

from __future__ import annotations

import math
import os
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from canrls.core.errors import ConfigError
from canrls.core.figtext import plain
from canrls.core.webpage import require_matplotlib, save_svg
from canrls.diagnosis.residual import PEAK_SHARE
from canrls.diagnosis.results import (
    EquationDiagnosis,
    OrderSpectrum,
    Traces,
    decimation,
    share_text,
)

__all__ = ["FIGURES", "UNUSED_REASONS", "UNUSED_SLOW", "UNUSED_WARMUP", "Figures",
           "MATPLOTLIB", "figures_in", "integer_orders", "unused_spans"]

#: The figures a report holds (without an ``after`` some show ``before`` only).
FIGURES: tuple[str, ...] = ("timeline.svg", "speed.svg", "position.svg", "candidates.svg",
                            "orders.svg", "convergence.svg", "fixed.svg")

_BEFORE = "#c0392b"
_AFTER = "#1f6fb4"
_GREY = "#9a9a9a"


#: the page and extra the diagnosis and validation name when matplotlib is missing
MATPLOTLIB = ("the HTML report", "report")


def figures_in(directory: str | os.PathLike[str],
               shown: str | os.PathLike[str] | None = None) -> Figures:
    """:class:`Figures` drawing into ``directory`` (created), for a report's page;
    ``shown`` is the directory an error names (the report's, when ``directory`` is its
    staging: :func:`~canrls.core.files.staged_dir`).

    :raises ConfigError: matplotlib is missing, or the directory cannot be created.
    """
    Figure, Canvas = require_matplotlib(*MATPLOTLIB)
    out = Path(directory)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise ConfigError(f"--report {shown or out}: cannot create the directory: {e}") from e
    return Figures(Figure, Canvas, out, Path(shown) if shown is not None else out)


def _decimate(n: int) -> slice:
    return slice(None, None, decimation(n))


def _timeline(tr: Traces) -> slice | npt.NDArray[np.bool_]:
    return _decimate(len(tr.t)) if tr.timeline is None else tr.timeline


class Figures:
    """Draws the figures into ``out`` with matplotlib's ``Figure`` and canvas classes
    (:func:`~canrls.core.webpage.require_matplotlib`); each method returns the file name it
    wrote."""

    def __init__(self, Figure: Any, Canvas: Any, out: Path, shown: Path | None = None
                 ) -> None:
        self.Figure = Figure
        self.Canvas = Canvas
        self.out = out
        #: the directory an error names
        self.shown = shown if shown is not None else out
        #: what a figure's caption must add, by file name (clipped axes, shaded spans)
        self.notes: dict[str, str] = {}

    def _save(self, fig: Any, name: str) -> str:
        return save_svg(fig, self.Canvas, self.out / name, f"--report {self.shown}: {name}")

    def timeline(self, b: EquationDiagnosis, a: EquationDiagnosis | None, *,
                 name: str = "timeline.svg", label: str = "before") -> str:
        """Measured against model, residual below; ``label`` names ``b``'s model (a
        saved model's prediction for ``canrls validate``), ``name`` the file. The
        measurement is drawn last, above the model; the spans of samples the estimator
        does not use are shaded and counted in :attr:`notes`."""
        tr = b.traces
        fig = self.Figure(figsize=(11, 6.4), layout="constrained")
        ax1, ax2 = fig.subplots(2, 1, sharex=True, height_ratios=[3, 2])
        s = _timeline(tr)
        u = b.unit
        models = [(label, b, _BEFORE)] + ([("after", a, _AFTER)] if a is not None else [])
        for lab, q, color in models:
            tq = q.traces
            sq = _timeline(tq)
            ax1.plot(tq.t[sq], np.where(tq.used, tq.yhat, np.nan)[sq], color=color, lw=2.2,
                     alpha=0.55, label=plain(f"model {lab}"), rasterized=True)
            ax2.plot(tq.t[sq], np.where(tq.used, tq.residual, np.nan)[sq], color=color,
                     lw=0.6, label=plain(f"residual {lab} (RMS {q.residual_rms:.3g} {u})"),
                     rasterized=True)
        # the measurement above the model: drawn last, thin and black
        ax1.plot(tr.t[s], np.where(tr.used, tr.y, np.nan)[s], color="black", lw=0.7,
                 label="measured (filtered output)", rasterized=True)
        spans = unused_spans(tr.t[s], tr.used[s])
        for ax in (ax1, ax2):
            for k, (t0, t1) in enumerate(spans):
                ax.axvspan(t0, t1, color=_GREY, alpha=0.18, lw=0,
                           label="not used (see the caption)" if k == 0 and ax is ax1
                           else None)
        if spans:
            self.notes[name] = (f"Shaded: {len(spans)} spans the estimator does not use "
                                f"({UNUSED_REASONS}).")
        ax1.set_ylabel(plain(f"{b.output} [{u}]"))
        ax1.set_title(plain(f"{b.equation} equation: measured against model "
                            f"(fit {b.fit_percent:.1f} %"
                            + (f" {label}, {a.fit_percent:.1f} % after)" if a is not None
                               else ")")))
        ax1.legend(loc="upper right", fontsize=8)
        ax1.grid(alpha=0.3)
        ax2.axhline(0.0, color="black", lw=0.5)
        ax2.set_xlabel("time [s]")
        ax2.set_ylabel(plain(f"residual [{u}]"))
        ax2.legend(loc="upper right", fontsize=8)
        ax2.grid(alpha=0.3)
        return self._save(fig, name)

    def binned(self, b: EquationDiagnosis, a: EquationDiagnosis | None,
               quantity: str, *, name: str | None = None, label: str = "before") -> str:
        """Residual against ``quantity`` ("speed" or "position"), in ``name``
        (default ``{quantity}.svg``); ``label`` names ``b``'s panel."""
        panels = [(label, b, _BEFORE)] + ([("after", a, _AFTER)] if a is not None else [])
        fig = self.Figure(figsize=(11 if a is not None else 7, 4.4), layout="constrained")
        axes = fig.subplots(1, len(panels), sharey=True, sharex=True, squeeze=False)[0]
        from matplotlib.lines import Line2D

        handles = [Line2D([], [], marker="o", ls="", ms=4, color=_GREY, label="samples")]
        if quantity != "speed" or not b.traces.used.any():
            vmax = 1.0
        elif b.traces.scatter is not None:  # the points are decimated: the record's max
            vmax = float(b.excitation.speed_max)
        else:
            vmax = float(np.nanmax(np.abs(b.traces.speed[b.traces.used])))
        u = b.unit
        lim = 0.0
        clouds: list[npt.NDArray[np.float64]] = []
        for ax, (label, q, color) in zip(axes, panels, strict=True):
            tr = q.traces
            if quantity == "speed":
                x = tr.speed
            elif tr.position is None:
                continue
            elif q.bins.get("position") is not None and q.bins["position"].unit == "rad":
                x = np.mod(tr.position, 2 * math.pi)
            else:
                x = tr.position
            if tr.scatter is None:
                used = tr.used
                xs, rs = x[used], tr.residual[used]
                s = _decimate(len(xs))
                xs, rs = xs[s], rs[s]
            else:
                xs, rs = x[tr.scatter], tr.residual[tr.scatter]
            clouds.append(rs)
            ax.scatter(xs, rs, s=1, color=_GREY, alpha=0.25, rasterized=True)
            bn = q.bins.get(quantity)
            if bn is not None:
                ok = np.isfinite(bn.mean)
                # bars: the spread in the bin, sqrt(RMS^2 - mean^2)
                sd = np.sqrt(np.maximum(bn.rms[ok] ** 2 - bn.mean[ok] ** 2, 0.0))
                ax.errorbar(bn.centers[ok], bn.mean[ok], yerr=sd, fmt="o-", ms=3,
                            lw=1.2, color=color, ecolor=color, elinewidth=0.6, capsize=2)
                handles.append(Line2D([], [], marker="o", ms=4, color=color,
                                      label=f"{label}: bin mean ± spread"))
                if np.any(ok):
                    lim = max(lim, float(np.nanmax(np.abs(bn.mean[ok]) + sd)))
            ax.axhline(0.0, color="black", lw=0.5)
            if quantity == "speed":
                _symlog_speed(ax, vmax)
                ax.set_xlabel(plain(f"speed (filtered) [{bn.unit if bn else ''}], "
                                    f"negative: moving backward"))
            else:
                ax.set_xlabel(plain(f"{bn.label if bn else 'position'} "
                                    f"[{bn.unit if bn else ''}]"))
            ax.set_title(plain(f"{label}: residual RMS {q.residual_rms:.3g} {u}"), fontsize=10)
            ax.grid(alpha=0.3)
            ax.legend(handles=[handles[0], handles[-1]], loc="upper left", fontsize=8)
        axes[0].set_ylabel(plain(f"residual [{u}]"))
        name = name or f"{quantity}.svg"
        if lim > 0:
            top = 1.6 * lim
            axes[0].set_ylim(-top, top)
            out = [float(np.mean(np.abs(r) > top)) for r in clouds if len(r)]
            if out and max(out) > 0:
                note = (f"y axis clipped at ±{top:.3g} {u}: {share_text(max(out))} of the "
                        f"samples lie beyond it")
                self.notes[name] = note[0].upper() + note[1:] + "."
                fig.text(0.99, 0.005, plain(note), ha="right", va="bottom", fontsize=8,
                         color="#555")
        what = "speed (both directions)" if quantity == "speed" else (
            "position in the revolution" if b.traces.angle is not None and
            (b.bins.get("position") is not None and b.bins["position"].unit == "rad")
            else "position along the travel")
        fig.suptitle(f"Residual against {what}")
        return self._save(fig, name)

    def candidates(self, q: EquationDiagnosis) -> str:
        cands = list(q.candidates[:12])
        fig = self.Figure(figsize=(11, 0.45 * len(cands) + 1.6), layout="constrained")
        ax = fig.subplots()
        ypos = np.arange(len(cands))[::-1]
        vals = [100 * c.explained for c in cands]
        colors = [_AFTER if c.suggested else (_GREY if not c.identifiable else "#7fa7cf")
                  for c in cands]
        ax.barh(ypos, vals, color=colors)
        ax.set_yticks(ypos, [plain(c.effect) for c in cands])
        ax.set_xlim(0, 150)
        ax.set_xticks([0, 20, 40, 60, 80, 100])
        steps = {st.effect: (i, st) for i, st in enumerate(q.suggestion.steps)}
        for y0, c, v in zip(ypos, cands, vals, strict=True):
            note = ("not identifiable" if not c.identifiable else "")
            if c.effect in steps:
                i, st = steps[c.effect]
                note = (f"suggested, step {i + 1}: {100 * st.explained:.1f} % of what is left"
                        if i else "suggested, step 1")
            ax.text(v + 1, y0, plain(f"{v:.1f} %  ΔBIC {c.delta_bic:.3g}  RMS after "
                                      f"{c.rms_after:.3g} {q.unit}  {note}"),
                    va="center", fontsize=8)
        ax.set_xlabel("share of the residual variance explained when added alone [%]")
        ax.set_title("Which effect is missing: candidates, best first "
                     "(dark blue: suggested, grey: not identifiable)", fontsize=10)
        ax.grid(axis="x", alpha=0.3)
        return self._save(fig, "candidates.svg")

    def orders(self, b: EquationDiagnosis, a: EquationDiagnosis | None) -> str:
        """The residual's amplitude at the integer rotation orders, before and (in its
        own panel, on its own scale) after; the peaks labelled with their order."""
        from matplotlib.ticker import FuncFormatter

        sp = b.spectrum
        assert sp is not None
        panels = [("before", b)] + ([("after", a)] if a is not None and
                                    a.spectrum is not None else [])
        fig = self.Figure(figsize=(11, 2.2 + 2.4 * len(panels)), layout="constrained")
        axes = fig.subplots(len(panels), 1, sharex=True, squeeze=False)[:, 0]
        top_order = 1.0
        for ax, (label, q), color in zip(axes, panels, (_BEFORE, _AFTER), strict=False):
            qs = q.spectrum
            assert qs is not None
            orders, amp, _, peaks = integer_orders(qs)
            top_order = max(top_order, float(orders[-1]) if len(orders) else 1.0)
            ax.bar(orders, amp, width=0.6, color=color, label=label)
            top = float(np.max(amp)) if len(amp) else 0.0
            for p in peaks:
                ax.annotate(f"{p:g}", (p, qs.at(p)[0]), textcoords="offset points",
                            xytext=(0, 3), ha="center", fontsize=9, color=color)
            text = "; ".join(f"order {p:g}: {qs.at(p)[0]:.3g} {qs.unit} "
                             f"({share_text(qs.share(p))} of the residual variance)"
                             for p in peaks[:3])
            if not text and top > 0:
                k = int(np.argmax(amp))
                text = (f"no order stands out (largest: order {orders[k]:g}, "
                        f"{top:.3g} {qs.unit})")
            ax.set_title(plain(f"{label}: {text or 'no order stands out'}"), fontsize=9,
                         loc="left")
            if top > 0:
                ax.set_ylim(0, 1.25 * top)
            ax.set_ylabel(plain(f"amplitude [{qs.unit}]"))
            # plain tick labels: no "1e-5" multiplier over the panel's title
            ax.yaxis.set_major_formatter(FuncFormatter(lambda v, _: f"{v:.3g}"))
            ax.grid(alpha=0.3)
        axes[-1].set_xlabel(f"rotation order (periods per {sp.per})")
        axes[-1].set_xlim(0, top_order + 1)
        fig.suptitle("Residual against rotation order (integer orders; each panel on its "
                     "own scale)", fontsize=10)
        return self._save(fig, "orders.svg")

    def convergence(self, q: EquationDiagnosis, after: bool) -> str:
        tr = q.traces
        n = len(tr.names)
        cols = 2 if n > 1 else 1
        rows = int(math.ceil(n / cols))
        fig = self.Figure(figsize=(11, 2.3 * rows + 0.8), layout="constrained")
        axes = np.atleast_1d(fig.subplots(rows, cols, sharex=True, squeeze=False).ravel())
        for j, ax in enumerate(axes):
            if j >= n:
                ax.set_visible(False)
                continue
            th = tr.theta[:, j] if len(tr.theta) else np.zeros(0)
            sd = tr.sigma[:, j] if len(tr.sigma) else np.zeros(0)
            fx = tr.theta_fixed[:, j] if len(tr.theta_fixed) else np.zeros(0)
            ax.fill_between(tr.conv_t, th - sd, th + sd, color=_AFTER, alpha=0.25, lw=0,
                            label="float ± σ")
            ax.plot(tr.conv_t, th, color=_AFTER, lw=1.0, label="float")
            ax.plot(tr.conv_t, fx, color="black", lw=0.9, ls="--", label="fixed point")
            if len(th):
                fin = th[-1]
                span = max(abs(fin) * 0.5, 4 * float(sd[-1]) if np.isfinite(sd[-1]) else 0.0,
                           1e-30)
                ax.set_ylim(fin - span, fin + span)
                ax.axhline(fin, color=_GREY, lw=0.6)
            ax.set_title(plain(f"{tr.names[j]} [{tr.units[j]}]"), fontsize=9)
            ax.grid(alpha=0.3)
            if j == 0:
                ax.legend(fontsize=7, loc="lower right")
        for ax in axes[-cols:]:
            ax.set_xlabel("time [s]")
        fig.suptitle("Parameter convergence (" + ("after" if after else "model as given")
                     + "; y axis: final value ± 50 %)", fontsize=11)
        return self._save(fig, "convergence.svg")

    def fixed(self, q: EquationDiagnosis) -> str:
        tr = q.traces
        fig = self.Figure(figsize=(11, 4.2), layout="constrained")
        ax = fig.subplots()
        floor = 1e-9
        for j, name in enumerate(tr.names):
            if not len(tr.theta):
                break
            th, fx, sd = tr.theta[:, j], tr.theta_fixed[:, j], tr.sigma[:, j]
            ref = np.maximum(np.abs(th), np.nan_to_num(sd, nan=0.0))
            ref = np.where(ref > 0, ref, 1.0)
            rel = np.abs(fx - th) / ref
            ax.plot(tr.conv_t, np.maximum(np.nan_to_num(rel, nan=floor), floor), lw=1.0,
                    label=plain(name))
        ax.axhline(1e-3, color="black", ls=":", lw=0.8, label="0.1 %")
        ax.set_yscale("log")
        ax.set_xlabel("time [s]")
        ax.set_ylabel("|fixed − float| / max(|float|, σ)")
        ax.set_title("Fixed point against float, every parameter", fontsize=10)
        ax.grid(alpha=0.3, which="both")
        ax.legend(fontsize=7, ncol=3)
        return self._save(fig, "fixed.svg")


def _symlog_speed(ax: Any, vmax: float) -> None:
    """Symmetric-log speed axis: linear within two decades below the top speed."""
    if not (vmax > 0 and math.isfinite(vmax)):
        return
    top = math.ceil(math.log10(vmax))
    lin = 10.0 ** (top - 2)
    ax.set_xscale("symlog", linthresh=lin, linscale=0.6)
    ticks = [0.0] + [s * 10.0 ** k for k in range(top - 2, top + 1) for s in (-1, 1)]
    ax.set_xticks(sorted(ticks), [f"{t:g}" for t in sorted(ticks)])
    ax.set_xlim(-1.05 * vmax, 1.05 * vmax)


#: why the estimator leaves samples out (estimation.selection.SamplePolicy): always, and
#: with sign-dependent friction in the model
UNUSED_WARMUP = "the filter's warm-up after the start and after each gap in the timestamps"
UNUSED_SLOW = "speeds below the minimum near reversals with the warm-up after them"
UNUSED_REASONS = (f"{UNUSED_WARMUP}, and, in a model with sign-dependent friction, "
                  f"{UNUSED_SLOW}")


def unused_spans(t: npt.NDArray[np.float64], used: npt.NDArray[np.bool_]
                  ) -> list[tuple[float, float]]:
    """(start, end) times of the runs of unused points, each from the last used point
    before it to the first used one after it."""
    if not len(t):
        return []
    edges = np.flatnonzero(np.diff(np.concatenate([[1], used.astype(np.int8), [1]])))
    out = []
    for a, b in zip(edges[0::2], edges[1::2], strict=True):
        out.append((float(t[max(a - 1, 0)]), float(t[min(b, len(t) - 1)])))
    return out


def integer_orders(sp: OrderSpectrum
                   ) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64],
                              npt.NDArray[np.float64], tuple[float, ...]]:
    """The spectrum at its integer orders: (orders, amplitude, explained, peaks), the
    peaks those of the whole spectrum that are integer orders and explain a share of
    their own beyond the stronger ones (the quarter orders beside a strong order are
    its leakage, not orders of their own)."""
    keep = np.isclose(sp.orders, np.round(sp.orders))
    peaks = tuple(p for p in sp.peaks if float(p).is_integer() and sp.share(p) >= PEAK_SHARE)
    return sp.orders[keep], sp.amplitude[keep], sp.explained[keep], peaks
