"""What every HTML report of canrls shares: the page head, the figure files, the links.

The diagnosis, validation and fleet pages are jinja2 templates rendered through
:func:`environment`: autoescaped, strict about undefined names, with the filters
``num`` and ``fmt`` and the global ``head`` (a viewport, the one style sheet and a few
lines of inline script that sort a table by the column clicked: offline, no CDN).
Figures are written as SVG by :func:`save_svg` (sharp at any zoom; point clouds are
rasterised at twice the screen's resolution inside them), and files on disk are linked
by a path relative to the page (:func:`relative_href`).
"""

from __future__ import annotations

import math
import os
from pathlib import Path
from typing import TYPE_CHECKING, Any
from urllib.parse import quote

from canrls.core.errors import ConfigError
from canrls.core.files import atomic_writer

if TYPE_CHECKING:
    import jinja2

__all__ = ["HEAD", "RASTER_DPI", "environment", "num", "relative_href", "require_matplotlib",
           "save_svg"]

#: resolution of the rasterised point clouds inside an SVG figure (2x the 1x screen's)
RASTER_DPI = 200

_STYLE = (
    "body{font-family:sans-serif;max-width:1250px;margin:1.5em auto;padding:0 1em;"
    "color:#222;line-height:1.35}"
    "table{border-collapse:collapse;margin:1em 0}"
    "td,th{border:1px solid #ccc;padding:3px 8px;vertical-align:top;font-size:90%}"
    "th{background:#f0f0f0}th.sort{cursor:pointer;user-select:none}"
    "th.sort:after{content:' \\21C5';color:#999;font-size:80%}"
    ".wide{max-width:100%;overflow-x:auto}"
    "img{max-width:100%;height:auto;border:1px solid #ddd}"
    "figure{margin:1.2em 0}figcaption{color:#555;font-size:90%}"
    "code,a{overflow-wrap:anywhere}"
    ".verdict{background:#f6f8ff;padding:.8em;border-left:4px solid #1f6fb4}"
    ".bad{background:#fff4f2;border-left-color:#c0392b}"
    ".alert{color:#a40000}.quiet{color:#777}ul{margin:.2em 0}"
    "section{margin:2em 0;border-top:1px solid #ddd}")

# Click a header of a table of class "sortable": its rows sorted by that column,
# numerically where both cells start with a number (a second click reverses).
_SCRIPT = """
document.querySelectorAll('table.sortable').forEach(function (t) {
  var head = t.tHead ? t.tHead.rows[0] : t.rows[0];
  Array.prototype.forEach.call(head.cells, function (th, k) {
    th.classList.add('sort');
    th.title = 'sort by this column';
    th.addEventListener('click', function () {
      var body = t.tBodies[0], rows = Array.prototype.slice.call(body.rows);
      if (!t.tHead) { rows = rows.filter(function (r) { return r !== head; }); }
      var dir = th.dataset.dir === 'up' ? -1 : 1;
      th.dataset.dir = dir === 1 ? 'up' : 'down';
      function key(r) {
        var s = r.cells[k] ? r.cells[k].textContent.trim() : '';
        var x = parseFloat(s.replace(/[\\u2212]/g, '-').replace(/^[<>]\\s*/, ''));
        return isNaN(x) ? s.toLowerCase() : x;
      }
      rows.sort(function (a, b) {
        var x = key(a), y = key(b);
        if (typeof x !== typeof y) { x = String(x); y = String(y); }
        return (x < y ? -1 : x > y ? 1 : 0) * dir;
      });
      rows.forEach(function (r) { body.appendChild(r); });
    });
  });
});
"""

#: the head every page includes: viewport, style sheet; the script goes at the end
HEAD = ("<meta charset='utf-8'>"
        "<meta name='viewport' content='width=device-width, initial-scale=1'>"
        f"<style>{_STYLE}</style>")


def num(x: Any, spec: str = ".4g") -> str:
    """``x`` formatted with ``spec``; "—" when it is not a finite number."""
    try:
        v = float(x)
    except (TypeError, ValueError):
        return "—"
    return format(v, spec) if math.isfinite(v) else "—"


def environment(package: str, **filters: Any) -> jinja2.Environment:
    """The jinja2 environment of the templates under ``package``'s ``templates``:
    autoescaped, strict, with ``num``, ``fmt``, ``filters`` and the globals ``head``
    (in ``<head>``) and ``sort_script`` (before ``</body>``)."""
    import jinja2
    from markupsafe import Markup

    env = jinja2.Environment(
        loader=jinja2.PackageLoader(package, "templates"),
        autoescape=True, trim_blocks=True, lstrip_blocks=True,
        undefined=jinja2.StrictUndefined)
    env.filters["num"] = num
    env.filters["fmt"] = format
    env.filters.update(filters)
    env.globals["head"] = Markup(HEAD)
    env.globals["sort_script"] = Markup(f"<script>{_SCRIPT}</script>")
    return env


def require_matplotlib(report: str, extra: str) -> tuple[Any, Any]:
    """matplotlib's ``(Figure, FigureCanvasAgg)`` for the figures of ``report`` (a page's
    name in the error: "the HTML report").

    :raises ConfigError: matplotlib (the optional ``extra`` of canrls) is not installed.
    """
    try:
        from matplotlib.backends.backend_agg import FigureCanvasAgg
        from matplotlib.figure import Figure
    except ImportError as e:
        raise ConfigError(f"{report} needs matplotlib, which is not installed: "
                          f"pip install 'canrls[{extra}]' (or pip install matplotlib)") from e
    return Figure, FigureCanvasAgg


def save_svg(fig: Any, canvas: Any, path: Path, what: str) -> str:
    """Write matplotlib figure ``fig`` (with its canvas class ``canvas``) as SVG to
    ``path`` through a temporary renamed into place (never through a link); ``what``
    names the file in an error. Returns the file name."""
    canvas(fig)
    with atomic_writer(path, what) as f:
        fig.savefig(f, format="svg", dpi=RASTER_DPI, metadata={"Date": None})
    return path.name


def relative_href(path: str | os.PathLike[str], page_dir: str | os.PathLike[str]) -> str:
    """A link from a page in ``page_dir`` to the file ``path`` (relative paths taken
    from the working directory), relative and URL-quoted."""
    rel = os.path.relpath(os.path.abspath(path), os.path.abspath(page_dir))
    return quote(Path(rel).as_posix())
