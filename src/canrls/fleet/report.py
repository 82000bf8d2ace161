"""The fleet's report: an HTML page (jinja2 template ``templates/fleet.html.j2``,
matplotlib figures) and the same as JSON.

The page ranks the drives by what needs a look first (the most severe alert), draws
the parameter trends of the first ``figures`` drives of that ranking with their sigma
bands and alerts (the others are listed), and the fleet's spread per parameter by
drive type.
"""

from __future__ import annotations

import datetime
import math
import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from canrls.core.errors import ConfigError
from canrls.core.figtext import plain
from canrls.fleet.detect import RESIDUAL, DriveAssessment, FleetAssessment

__all__ = ["write_html", "report_dict", "require_matplotlib", "DEFAULT_FIGURES"]

#: drives with a figure of their trends (the first ones of the ranking)
DEFAULT_FIGURES = 20


def require_matplotlib() -> tuple[Any, Any]:
    try:
        from matplotlib.backends.backend_agg import FigureCanvasAgg
        from matplotlib.figure import Figure
    except ImportError as e:
        raise ConfigError("the fleet report needs matplotlib, which is not installed: "
                          "pip install 'canrls[fleet]' (or pip install matplotlib)") from e
    return Figure, FigureCanvasAgg


def report_dict(fleet: FleetAssessment, models: Sequence[tuple[str, str, int]] = ()
                ) -> dict[str, Any]:
    """The report as one JSON-able object (``canrls fleet report --json``)."""
    d = fleet.to_dict()
    d["models"] = [{"key": k, "description": desc, "recordings": n} for k, desc, n in models]
    return d


def _num(x: Any, spec: str = ".4g") -> str:
    try:
        v = float(x)
    except (TypeError, ValueError):
        return "—"
    return format(v, spec) if math.isfinite(v) else "—"


def _date(t: float) -> str:
    if not (isinstance(t, int | float) and 1e8 < t < 1e11):
        return _num(t, ".6g")
    return datetime.datetime.fromtimestamp(t, tz=datetime.UTC).strftime("%Y-%m-%d %H:%M")


def _x(t: Any) -> Any:
    """Times as matplotlib dates when they are epoch times, else as they are."""
    import numpy as np

    t = np.asarray(t, dtype=float)
    if t.size and np.all((t > 1e8) & (t < 1e11)):
        return t / 86400.0  # matplotlib's date unit: days since 1970
    return t


def _trend_figure(d: DriveAssessment, fleet: FleetAssessment, path: Path) -> None:
    import numpy as np

    Figure, Canvas = require_matplotlib()
    names = [n for n in d.series if n != RESIDUAL] + ([RESIDUAL] if RESIDUAL in d.series else [])
    fig = Figure(figsize=(9.0, 1.9 * len(names) + 0.6))
    Canvas(fig)
    alerts = {a.series: a for a in reversed(d.alerts)}
    tau = {n: b.tau for n, b in fleet.baselines.get(d.model_key, {}).items()}
    for i, n in enumerate(names):
        ax = fig.add_subplot(len(names), 1, i + 1)
        se = d.series[n]
        x = _x(se.t)
        tn = tau.get(f"{n}@{d.drive_type}", tau.get(n, 0.0))
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
        ax.set_ylabel(plain(f"{n}\n[{se.unit}]" if se.unit else n), fontsize=8)
        ax.tick_params(labelsize=7)
        if np.all((se.t > 1e8) & (se.t < 1e11)):
            ax.xaxis_date()
    fig.tight_layout()
    fig.savefig(path, dpi=80)


def _spread_figure(fleet: FleetAssessment, key: str, name: str, path: Path) -> None:
    import numpy as np

    Figure, Canvas = require_matplotlib()
    levels = fleet.spread[key][name]
    types = sorted({t for t, _ in levels.values()})
    out = {a.drive for a in fleet.alerts if a.kind == "outlier" and a.series == name}
    fig = Figure(figsize=(6.0, 0.5 + 0.45 * max(1, len(types))))
    Canvas(fig)
    ax = fig.add_subplot(1, 1, 1)
    rng = np.random.default_rng(0)  # the jitter of the strip only
    for i, ty in enumerate(types):
        pts = [(d, v) for d, (t, v) in levels.items() if t == ty]
        ys = i + rng.uniform(-0.15, 0.15, len(pts))
        for (d, v), y in zip(pts, ys, strict=True):
            bad = d in out
            ax.plot(v, y, "o", ms=5 if bad else 3, color="#cb181d" if bad else "#3182bd")
            if bad:
                ax.annotate(plain(d), (v, y), fontsize=7, xytext=(3, 3),
                            textcoords="offset points")
    ax.set_yticks(range(len(types)), [plain(t or "(no type)") for t in types], fontsize=8)
    ax.set_xlabel(plain(name), fontsize=8)
    if all(v > 0 for _, v in levels.values()):
        ax.set_xscale("log")
    ax.tick_params(labelsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=80)


def write_html(fleet: FleetAssessment, directory: str | os.PathLike[str], *,
               models: Sequence[tuple[str, str, int]] = (), recordings: int = 0,
               errors: int = 0, figures: int = DEFAULT_FIGURES,
               title: str = "canrls fleet report") -> Path:
    """Write ``directory/index.html`` with its PNG figures; returns the page's path.

    :raises ConfigError: matplotlib or jinja2 missing, or the directory not writable.
    """
    import jinja2

    require_matplotlib()
    out = Path(directory)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise ConfigError(f"{out}: cannot create the report directory ({e.strerror})") from e
    drives: list[tuple[DriveAssessment, str | None]] = []
    drawn = 0
    for k, d in enumerate(fleet.drives):
        fig = None
        if drawn < figures and d.series:
            fig = f"drive-{k + 1:04d}.png"
            _trend_figure(d, fleet, out / fig)
            drawn += 1
        drives.append((d, fig))
    spread = []
    for key, per in fleet.spread.items():
        for name in per:
            if not per[name]:
                continue
            fig = f"spread-{len(spread) + 1:02d}.png"
            _spread_figure(fleet, key, name, out / fig)
            spread.append((name if len(fleet.spread) == 1 else f"{name} ({key[:8]})", fig))
    env = jinja2.Environment(loader=jinja2.PackageLoader("canrls.fleet", "templates"),
                             autoescape=True, trim_blocks=True, lstrip_blocks=True,
                             undefined=jinja2.StrictUndefined)
    env.filters["num"] = _num
    env.filters["date"] = _date
    page = env.get_template("fleet.html.j2").render(
        f=fleet, drives=drives, spread=spread, title=title, models=list(models),
        recordings=recordings, errors=errors,
        generated=datetime.datetime.now(datetime.UTC).strftime("%Y-%m-%d %H:%M UTC"))
    path = out / "index.html"
    try:
        path.write_text(page, encoding="utf-8")
    except OSError as e:
        raise ConfigError(f"{path}: cannot write the report ({e.strerror})") from e
    return path
