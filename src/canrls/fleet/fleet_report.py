"""The fleet's report: an HTML page (jinja2 template ``templates/fleet.html.j2``,
matplotlib figures as SVG) and the same as JSON.

The page ranks the drives with alerts by what needs a look first (the most severe
alert) and draws the parameter trends of the first ``figures`` of them with their sigma
bands, their alerts and, for an outlier, its siblings' level; the healthy drives are one
compact table; then the fleet's spread per parameter by drive type.
"""

from __future__ import annotations

import datetime
import math
import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from canrls.core.checks import is_epoch
from canrls.core.errors import ConfigError
from canrls.core.figtext import plain
from canrls.core.webpage import environment, num, relative_href, require_matplotlib, save_svg
from canrls.fleet.detect import RESIDUAL, DriveAssessment, FleetAssessment

__all__ = ["write_html", "report_dict", "MATPLOTLIB", "DEFAULT_FIGURES"]

#: drives with a figure of their trends (the first ones with alerts in the ranking)
DEFAULT_FIGURES = 20


#: the page and extra the fleet report names when matplotlib is missing
MATPLOTLIB = ("the fleet report", "fleet")


def report_dict(fleet: FleetAssessment, models: Sequence[tuple[str, str, int]] = ()
                ) -> dict[str, Any]:
    """The report as one JSON-able object (``canrls fleet report --json``)."""
    d = fleet.to_dict()
    d["models"] = [{"key": k, "description": desc, "recordings": n} for k, desc, n in models]
    return d


def _date(t: float) -> str:
    if not is_epoch(t):
        return num(t, ".6g")
    return datetime.datetime.fromtimestamp(t, tz=datetime.UTC).strftime("%Y-%m-%d %H:%M")


def _x(t: Any) -> Any:
    """Times as matplotlib dates when they are epoch times, else as they are."""
    import numpy as np

    t = np.asarray(t, dtype=float)
    if t.size and np.all((t > 1e8) & (t < 1e11)):
        return t / 86400.0  # matplotlib's date unit: days since 1970
    return t


def _siblings(fleet: FleetAssessment, d: DriveAssessment, name: str) -> list[float]:
    """The levels of ``name`` of ``d``'s siblings (same model and type, not ``d``)."""
    levels = fleet.spread.get(d.model_key, {}).get(name, {})
    return [v for drive, (t, v) in levels.items()
            if t == d.drive_type and drive != d.drive and math.isfinite(v)]


def _trend_figure(d: DriveAssessment, fleet: FleetAssessment, path: Path) -> str:
    """Each parameter of ``d`` per recording; returns the figure's alt text."""
    import numpy as np

    Figure, Canvas = require_matplotlib(*MATPLOTLIB)
    names = [n for n in d.series if n != RESIDUAL] + ([RESIDUAL] if RESIDUAL in d.series else [])
    fig = Figure(figsize=(11.0, 2.2 * len(names) + 0.6))
    Canvas(fig)
    alerts = {a.series: a for a in reversed(d.alerts)}
    tau = {n: b.tau for n, b in fleet.baselines.get(d.model_key, {}).items()}
    for i, n in enumerate(names):
        ax = fig.add_subplot(len(names), 1, i + 1)
        se = d.series[n]
        x = _x(se.t)
        tn = d.scatter.get(n, tau.get(f"{n}@{d.drive_type}", tau.get(n, 0.0)))
        v, s = se.value, se.sigma
        total = np.sqrt(s ** 2 + (tn * np.abs(v) if se.log else tn) ** 2)
        ax.errorbar(x, v, yerr=2 * total, fmt="none", ecolor="#9ecae1", elinewidth=6,
                    alpha=0.8)
        ax.errorbar(x, v, yerr=2 * s, fmt="o", color="#08519c", ms=3, elinewidth=1.5,
                    capsize=2)
        a = alerts.get(n)
        if a is not None and a.at is not None:
            k = a.at
            ax.axvline(x[k] if k < len(x) else x[-1], color="#cb181d", lw=1, ls="--")
            if a.kind in ("change", "residual", "new effect") and k >= 1:
                ax.axhspan(a.before * (1 - 2 * tn) if se.log else a.before - 2 * tn,
                           a.before * (1 + 2 * tn) if se.log else a.before + 2 * tn,
                           xmax=1.0, color="#fcbba1", alpha=0.4, lw=0)
            ax.set_title(plain(a.message[:110]), fontsize=8, color="#a50f15", loc="left")
        elif a is not None:
            ax.set_title(plain(a.message[:110]), fontsize=8, color="#a50f15", loc="left")
        sib = _siblings(fleet, d, n) if a is not None and a.kind == "outlier" else []
        if sib:
            # the siblings' level: their median, and the band their levels span
            ax.axhspan(min(sib), max(sib), color="#a1d99b", alpha=0.35, lw=0,
                       label=plain(f"{len(sib)} siblings ({d.drive_type}): their levels"))
            ax.axhline(float(np.median(sib)), color="#31a354", lw=1.2, ls="--",
                       label="siblings' median")
            ax.legend(fontsize=8, loc="best")
        ax.set_ylabel(plain(f"{n}\n[{se.unit}]" if se.unit else n), fontsize=9)
        ax.tick_params(labelsize=9)
        if np.all((se.t > 1e8) & (se.t < 1e11)):
            ax.xaxis_date()
    fig.tight_layout()
    save_svg(fig, Canvas, path, f"{path.parent}: {path.name}")
    said = "; ".join(a.message for a in d.alerts[:2])
    return (f"Trends of {d.drive}: {', '.join(names)} per recording with ±2σ bands"
            + (f"; {said}" if said else ""))


def _spread_figure(fleet: FleetAssessment, key: str, name: str, path: Path) -> str:
    """Each drive's level of ``name`` by type, outliers marked; returns the alt text."""
    import numpy as np
    from matplotlib.ticker import FuncFormatter, LogLocator, NullFormatter

    Figure, Canvas = require_matplotlib(*MATPLOTLIB)
    levels = fleet.spread[key][name]
    types = sorted({t for t, _ in levels.values()})
    out = {a.drive for a in fleet.alerts if a.kind == "outlier" and a.series == name}
    fig = Figure(figsize=(11.0, 1.3 + 0.8 * max(1, len(types))), layout="constrained")
    ax = fig.add_subplot(1, 1, 1)
    rng = np.random.default_rng(0)  # the jitter of the strip only
    for i, ty in enumerate(types):
        pts = [(d, v) for d, (t, v) in levels.items() if t == ty]
        ys = i + rng.uniform(-0.2, 0.2, len(pts))
        bad = np.array([d in out for d, _ in pts], dtype=bool)
        vs = np.array([v for _, v in pts], dtype=float)
        # one marker set per type (a plant's thousand drives draw fast), outliers on top
        ax.plot(vs[~bad], ys[~bad], "o", ms=5, color="#3182bd", alpha=0.7, ls="none")
        ax.plot(vs[bad], ys[bad], "o", ms=7, color="#cb181d", ls="none")
        for k, j in enumerate(np.flatnonzero(bad)):  # labels staggered above and below
            ax.annotate(plain(pts[j][0]), (vs[j], ys[j]), fontsize=9,
                        xytext=(5, 6 if k % 2 else -12), textcoords="offset points",
                        color="#a50f15")
    ax.set_yticks(range(len(types)), [plain(t or "(no type)") for t in types], fontsize=10)
    ax.set_ylim(-0.6, len(types) - 0.4)
    unit = next((d.series[name].unit for d in fleet.drives if name in d.series), "")
    ax.set_xlabel(plain(f"{name} [{unit}]" if unit else name), fontsize=10)
    if all(v > 0 for _, v in levels.values()):
        ax.set_xscale("log")
        # 1, 2 and 5 of each decade labelled in plain numbers, the minor ticks unlabelled
        # (their labels overlapped); a range within one decade still gets labels
        ax.xaxis.set_major_locator(LogLocator(subs=(1.0, 2.0, 5.0), numticks=12))
        ax.xaxis.set_major_formatter(FuncFormatter(lambda v, _: f"{v:.3g}"))
        ax.xaxis.set_minor_formatter(NullFormatter())
    ax.tick_params(labelsize=10)
    ax.grid(alpha=0.3, axis="x")
    save_svg(fig, Canvas, path, f"{path.parent}: {path.name}")
    return (f"Each drive's level of {name} by type ({', '.join(t or '(no type)' for t in types)})"
            + (f"; outliers: {', '.join(sorted(out))}" if out else "; no outlier"))


def write_html(fleet: FleetAssessment, directory: str | os.PathLike[str], *,
               models: Sequence[tuple[str, str, int]] = (), recordings: int = 0,
               errors: int = 0, figures: int = DEFAULT_FIGURES,
               title: str = "canrls fleet report") -> Path:
    """Write ``directory/index.html`` with its SVG figures; returns the page's path.

    :raises ConfigError: matplotlib or jinja2 missing, or the directory not writable.
    """
    require_matplotlib(*MATPLOTLIB)
    out = Path(directory)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise ConfigError(f"{out}: cannot create the report directory ({e.strerror})") from e
    drives: list[tuple[DriveAssessment, str | None, str]] = []
    healthy: list[DriveAssessment] = []
    for k, d in enumerate(fleet.drives):
        if not d.alerts:
            healthy.append(d)
            continue
        fig, alt = None, ""
        if sum(1 for _, f, _ in drives if f) < figures and d.series:
            fig = f"drive-{k + 1:04d}.svg"
            alt = _trend_figure(d, fleet, out / fig)
        drives.append((d, fig, alt))
    spread: list[tuple[str, str, str]] = []
    for key, per in fleet.spread.items():
        for name in per:
            if not per[name]:
                continue
            fig = f"spread-{len(spread) + 1:02d}.svg"
            alt = _spread_figure(fleet, key, name, out / fig)
            spread.append((name if len(fleet.spread) == 1 else f"{name} ({key[:8]})", fig, alt))
    env = environment("canrls.fleet", date=_date,
                      href=lambda p: relative_href(p, out))
    page = env.get_template("fleet.html.j2").render(
        f=fleet, drives=drives, healthy=healthy, spread=spread, title=title,
        noted=[d for d in fleet.drives if d.notes],
        models=list(models), recordings=recordings, errors=errors,
        generated=datetime.datetime.now(datetime.UTC).strftime("%Y-%m-%d %H:%M UTC"))
    path = out / "index.html"
    try:
        path.write_text(page, encoding="utf-8")
    except OSError as e:
        raise ConfigError(f"{path}: cannot write the report ({e.strerror})") from e
    return path
