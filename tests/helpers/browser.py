"""A report page opened in a real browser: Debian's chromium, headless.

:func:`open_page` installs ``chromium`` with ``apt-get`` when it is missing and the
tests run as root (as CI does on a fresh machine; :func:`debian.need_tool`), otherwise
the test skips with the reason. It loads a copy of the page with two scripts added (one
first in ``<head>`` that records errors, one at the end that, once everything has
loaded, clicks every sortable table's headers and writes what it measured into the
DOM), dumps the DOM with ``--dump-dom`` and reads the measurements back, together with
the console messages chromium logs on stderr. Nothing leaves the machine: the page is a
local file and chromium runs with its network features off.
"""

from __future__ import annotations

import json
import re
import shutil
import subprocess
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from debian import need_tool

__all__ = ["PageCheck", "open_page"]

_RECORD = """<script>
window.__errors = [];
window.addEventListener('error', function (e) {
  var t = e.target;
  window.__errors.push(e.message || ('cannot load ' + (t && (t.src || t.href))));
}, true);
var __error = console.error;
console.error = function () {
  window.__errors.push(Array.prototype.join.call(arguments, ' '));
  __error.apply(console, arguments);
};
</script>"""

_MEASURE = """<script>
window.addEventListener('load', function () {
  document.querySelectorAll('table.sortable th').forEach(function (th) { th.click(); });
  var W = document.documentElement.clientWidth, over = [];
  document.querySelectorAll('body *').forEach(function (el) {
    var r = el.getBoundingClientRect();
    if (r.width > 0 && r.right > W + 1) {
      over.push(el.tagName.toLowerCase() + '.' + el.className + ' right ' + Math.round(r.right));
    }
  });
  document.querySelectorAll('.wide').forEach(function (el) {
    if (el.scrollWidth > el.clientWidth + 1) {
      over.push('scrolling table box ' + el.scrollWidth + ' > ' + el.clientWidth);
    }
  });
  var images = Array.prototype.map.call(document.images, function (i) {
    return {src: i.getAttribute('src'), alt: i.alt, loaded: i.complete && i.naturalWidth > 0,
            width: i.getBoundingClientRect().width};
  });
  // the text a reader sees in each element of class 'note' (none when hidden)
  var notes = Array.prototype.map.call(document.querySelectorAll('.note'),
                                       function (el) { return el.innerText; });
  var pre = document.createElement('pre');
  pre.id = 'canrls-check';
  pre.textContent = JSON.stringify({
    errors: window.__errors, images: images, overflow: over.slice(0, 20), width: W,
    notes: notes,
    scroll_width: document.documentElement.scrollWidth,
    viewport: !!document.querySelector('meta[name=viewport]')});
  document.body.appendChild(pre);
});
</script>"""


@dataclass(frozen=True)
class PageCheck:
    """What the browser measured on a page at one window width."""

    width: int
    errors: tuple[str, ...]
    images: tuple[dict[str, Any], ...]
    overflow: tuple[str, ...]
    scroll_width: int
    viewport: bool
    #: the text shown in each element of class ``note``, in the page's order
    notes: tuple[str, ...] = ()


def open_page(page: Path, width: int, height: int = 1200) -> PageCheck:
    """Load ``page`` (an ``index.html`` beside its figures) at ``width`` CSS pixels."""
    chromium = need_tool("chromium", ["chromium"])
    html = page.read_text(encoding="utf-8")
    head = html.index("<head>") + len("<head>")
    body = html.rindex("</body>")
    probe = page.with_name(f".check-{page.name}")
    probe.write_text(html[:head] + _RECORD + html[head:body] + _MEASURE + html[body:],
                     encoding="utf-8")
    profile = tempfile.mkdtemp(prefix="canrls-chromium-")
    try:
        res = subprocess.run(
            [chromium, "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic",
             "--no-first-run", "--disable-background-networking",
             "--disable-component-update", "--disable-sync", "--hide-scrollbars",
             "--enable-logging=stderr", "--v=0", f"--user-data-dir={profile}",
             f"--window-size={width},{height}", "--virtual-time-budget=5000",
             "--dump-dom", probe.resolve().as_uri()],
            capture_output=True, text=True, timeout=120)
    finally:
        shutil.rmtree(profile, ignore_errors=True)
        probe.unlink()
    m = re.search(r"<pre id=\"canrls-check\">(.*?)</pre>", res.stdout, re.S)
    assert m is not None, f"chromium: no measurement (exit {res.returncode}): {res.stderr[-2000:]}"
    d = json.loads(m.group(1).replace("&lt;", "<").replace("&gt;", ">").replace("&amp;", "&"))
    # what chromium logs of the page's console (uncaught errors, failed loads)
    console = [line for line in res.stderr.splitlines()
               if "CONSOLE" in line and ("Uncaught" in line or "rror" in line)]
    return PageCheck(width=width, errors=tuple(d["errors"]) + tuple(console),
                     images=tuple(d["images"]), overflow=tuple(d["overflow"]),
                     scroll_width=int(d["scroll_width"]), viewport=bool(d["viewport"]),
                     notes=tuple(d["notes"]))
