"""The figures of the HTML report (``canrls diagnose --report DIR``), as PNG files.

:class:`Figures` draws each figure of a diagnosis (timeline, speed, position,
candidates, orders, convergence, fixed point; docs/diagnose.md, "The figures") into a
directory with matplotlib's object API (no pyplot, no global state). matplotlib is the
optional ``report`` extra: :func:`require_matplotlib` imports it when a report is
written, and its absence is a :class:`~canrls.core.errors.ConfigError` naming the package.
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
from canrls.core.files import atomic_writer
from canrls.diagnosis.results import EquationDiagnosis, Traces, decimation

__all__ = ["FIGURES", "Figures", "figures_in", "require_matplotlib"]

#: The figures a report holds (without an ``after`` some show ``before`` only).
FIGURES: tuple[str, ...] = ("timeline.png", "speed.png", "position.png", "candidates.png",
                            "orders.png", "convergence.png", "fixed.png")

_BEFORE = "#c0392b"
_AFTER = "#1f6fb4"
_GREY = "#9a9a9a"


def require_matplotlib() -> tuple[Any, Any]:
    """matplotlib's ``(Figure, FigureCanvasAgg)``.

    :raises ConfigError: matplotlib (the ``report`` extra) is not installed.
    """
    try:
        from matplotlib.backends.backend_agg import FigureCanvasAgg
        from matplotlib.figure import Figure
    except ImportError as e:
        raise ConfigError("the HTML report needs matplotlib, which is not installed: "
                          "pip install 'canrls[report]' (or pip install matplotlib)") from e
    return Figure, FigureCanvasAgg


def figures_in(directory: str | os.PathLike[str]) -> Figures:
    """:class:`Figures` drawing into ``directory`` (created), for a report's page.

    :raises ConfigError: matplotlib is missing, or the directory cannot be created.
    """
    Figure, Canvas = require_matplotlib()
    out = Path(directory)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise ConfigError(f"--report {out}: cannot create the directory: {e}") from e
    return Figures(Figure, Canvas, out)


def _decimate(n: int) -> slice:
    return slice(None, None, decimation(n))


def _timeline(tr: Traces) -> slice | npt.NDArray[np.bool_]:
    return _decimate(len(tr.t)) if tr.timeline is None else tr.timeline


class Figures:
    """Draws the figures into ``out`` with matplotlib's ``Figure`` and canvas classes
    (:func:`require_matplotlib`); each method returns the file name it wrote."""

    def __init__(self, Figure: Any, Canvas: Any, out: Path) -> None:
        self.Figure = Figure
        self.Canvas = Canvas
        self.out = out

    def _save(self, fig: Any, name: str) -> str:
        self.Canvas(fig)
        # a temporary beside it, renamed: never written through a link in the directory
        with atomic_writer(self.out / name, f"--report {self.out}: {name}") as f:
            fig.savefig(f, dpi=110, format="png")
        return name

    def timeline(self, b: EquationDiagnosis, a: EquationDiagnosis | None, *,
                 name: str = "timeline.png", label: str = "before") -> str:
        """Measured against model, residual below; ``label`` names ``b``'s model (a
        saved model's prediction for ``canrls validate``), ``name`` the file."""
        tr = b.traces
        fig = self.Figure(figsize=(11, 6.4), layout="constrained")
        ax1, ax2 = fig.subplots(2, 1, sharex=True, height_ratios=[3, 2])
        s = _timeline(tr)
        u = b.unit
        y = np.where(tr.used, tr.y, np.nan)
        ax1.plot(tr.t[s], y[s], color="black", lw=0.8, label="measured (filtered target)")
        ax1.plot(tr.t[s], np.where(tr.used, tr.yhat, np.nan)[s], color=_BEFORE, lw=0.7,
                 alpha=0.85, label=f"model {label}")
        if a is not None:
            ta = a.traces
            sa = _timeline(ta)
            ax1.plot(ta.t[sa], np.where(ta.used, ta.yhat, np.nan)[sa], color=_AFTER, lw=0.7,
                     alpha=0.85, label="model after")
        ax1.set_ylabel(plain(f"{b.target} [{u}]"))
        ax1.set_title(plain(f"{b.equation} equation: measured against model "
                            f"(fit {b.fit_percent:.1f} %"
                            + (f" {label}, {a.fit_percent:.1f} % after)" if a is not None
                               else ")")))
        ax1.legend(loc="upper right", fontsize=8)
        ax1.grid(alpha=0.3)
        ax2.plot(tr.t[s], np.where(tr.used, tr.residual, np.nan)[s], color=_BEFORE, lw=0.6,
                 label=plain(f"residual {label} (RMS {b.residual_rms:.3g} {u})"))
        if a is not None:
            ta = a.traces
            sa = _timeline(ta)
            ax2.plot(ta.t[sa], np.where(ta.used, ta.residual, np.nan)[sa], color=_AFTER,
                     lw=0.6, label=plain(f"residual after (RMS {a.residual_rms:.3g} {u})"))
        ax2.axhline(0.0, color="black", lw=0.5)
        ax2.set_xlabel("time [s]")
        ax2.set_ylabel(plain(f"residual [{u}]"))
        ax2.legend(loc="upper right", fontsize=8)
        ax2.grid(alpha=0.3)
        return self._save(fig, name)

    def binned(self, b: EquationDiagnosis, a: EquationDiagnosis | None,
               quantity: str, *, name: str | None = None, label: str = "before") -> str:
        """Residual against ``quantity`` ("speed" or "position"), in ``name``
        (default ``{quantity}.png``); ``label`` names ``b``'s panel."""
        panels = [(label, b, _BEFORE)] + ([("after", a, _AFTER)] if a is not None else [])
        fig = self.Figure(figsize=(11 if a is not None else 7, 4.4), layout="constrained")
        axes = fig.subplots(1, len(panels), sharey=True, sharex=True, squeeze=False)[0]
        from matplotlib.lines import Line2D

        handles = [Line2D([], [], marker="o", ls="", ms=4, color=_GREY, label="samples")]
        if quantity != "speed" or not b.traces.used.any():
            vmax = 1.0
        elif b.traces.scatter is not None:  # the points are decimated: the record's max
            vmax = float(b.excitation.speed_max)  # type: ignore[attr-defined]
        else:
            vmax = float(np.nanmax(np.abs(b.traces.speed[b.traces.used])))
        u = b.unit
        lim = 0.0
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
        if lim > 0:
            axes[0].set_ylim(-1.6 * lim, 1.6 * lim)
        what = "speed (both directions)" if quantity == "speed" else (
            "position in the revolution" if b.traces.angle is not None and
            (b.bins.get("position") is not None and b.bins["position"].unit == "rad")
            else "position along the travel")
        fig.suptitle(f"Residual against {what}")
        return self._save(fig, name or f"{quantity}.png")

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
        return self._save(fig, "candidates.png")

    def orders(self, b: EquationDiagnosis, a: EquationDiagnosis | None) -> str:
        sp = b.spectrum
        assert sp is not None
        fig = self.Figure(figsize=(11, 4.2), layout="constrained")
        ax = fig.subplots()
        ax.plot(sp.orders, sp.amplitude, color=_BEFORE, lw=0.9, label="before")
        if a is not None and a.spectrum is not None:
            ax.plot(a.spectrum.orders, a.spectrum.amplitude, color=_AFTER, lw=0.9,
                    label="after")
        for p in sp.peaks[:4]:
            amp, ex = sp.at(p)
            ax.annotate(plain(f"order {p:g}\n{amp:.2g} {b.unit}, {100 * ex:.0f} %"), (p, amp),
                        textcoords="offset points", xytext=(4, 6), fontsize=8,
                        color=_BEFORE)
        ax.set_xlabel(f"rotation order (periods per {sp.per})")
        ax.set_ylabel(plain(f"fitted amplitude [{sp.unit}]"))
        ax.set_xlim(0, float(sp.orders[-1]) + 0.5)
        top = float(np.nanmax(sp.amplitude)) if len(sp.amplitude) else 0.0
        if top > 0:
            ax.set_ylim(0, 1.3 * top)
        ax.set_title("Residual spectrum against rotation order (a position-periodic effect "
                     "shows as a peak at its order)", fontsize=10)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
        return self._save(fig, "orders.png")

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
        return self._save(fig, "convergence.png")

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
        return self._save(fig, "fixed.png")


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
