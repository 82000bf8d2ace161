"""Peak RSS of ``canrls diagnose`` (and ``canrls fit`` for reference) on simulated logs of
10 and 40 minutes at 1 kHz, and the peak of the memory Python traces: how the memory
grows with the log.

Each command runs in its own Python process, which reports its own peak resident set
(``getrusage(RUSAGE_SELF).ru_maxrss``), so the figures include the interpreter, numpy
and the C extensions. ``--traced`` runs ``diagnose`` once more per log under
:mod:`tracemalloc` (numpy's arrays included; the peak above the memory in use when the
command starts, which leaves out the imports; slower, and the tracing's own memory
would inflate the resident set, hence a run of its own). Prints one line per log and
command, and the growth per hour of 1 kHz log. A measurement, not a test: run it once,
by hand::

    PYTHONPATH=src python tools/bench_diagnose_memory.py            # 10 and 40 min
    PYTHONPATH=src python tools/bench_diagnose_memory.py --minutes 2 8
    PYTHONPATH=src python tools/bench_diagnose_memory.py --keep DIR  # keep the logs
    PYTHONPATH=src python tools/bench_diagnose_memory.py --traced    # and traced peaks

The logs are written to a temporary directory (or ``--keep DIR``, where existing logs of
the same length are reused).
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
from pathlib import Path

RUN = """
import resource, sys, time, tracemalloc
from canrls.cli import main as cli
import canrls.diagnosis.analysis, canrls.processor.replay  # imported before the tracing starts
traced = sys.argv[1] == "traced"
if traced:
    tracemalloc.start()
start = tracemalloc.get_traced_memory()[0]
t0 = time.perf_counter()
rc = cli.main(sys.argv[2:])
wall = time.perf_counter() - t0
if traced:
    print("traced_bytes", tracemalloc.get_traced_memory()[1] - start, file=sys.stderr)
print("maxrss_kib", resource.getrusage(resource.RUSAGE_SELF).ru_maxrss, file=sys.stderr)
print("wall_s", wall, file=sys.stderr)
sys.exit(rc)
"""

EFFECTS = "inertia,viscous,coulomb,offset,cogging:6"


def _run(args: list[str], traced: bool = False) -> dict[str, float]:
    """``maxrss_kib`` (peak RSS [KiB]), ``wall_s`` and with ``traced`` ``traced_bytes``
    (the traced peak) of ``canrls ARGS`` in a fresh process."""
    out = subprocess.run([sys.executable, "-c", RUN, "traced" if traced else "plain", *args],
                         capture_output=True, text=True, env=dict(os.environ))
    if out.returncode != 0:
        raise SystemExit(f"canrls {' '.join(args)} failed:\n{out.stderr}")
    got = {}
    for ln in out.stderr.splitlines():
        k, _, v = ln.partition(" ")
        if k in ("maxrss_kib", "wall_s", "traced_bytes"):
            got[k] = float(v)
    return got


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--minutes", type=float, nargs="+", default=[10.0, 40.0])
    ap.add_argument("--keep", metavar="DIR", help="write (and reuse) the logs in DIR")
    ap.add_argument("--traced", action="store_true",
                    help="also the traced peak of diagnose (tracemalloc, a run of its own)")
    a = ap.parse_args()
    tmp = None if a.keep else tempfile.TemporaryDirectory(prefix="bench-diag-")
    d = Path(a.keep or tmp.name)  # type: ignore[union-attr]
    d.mkdir(parents=True, exist_ok=True)
    model = ["--kt", "0.1", "--effects", "inertia,viscous", "--quiet"]
    rows = []
    for m in a.minutes:
        log = d / f"drive_{m:g}min.log"
        if not log.exists():
            subprocess.run([sys.executable, "-m", "canrls", "sim", "--out", str(log),
                            "--duration", str(60 * m), "--seed", "1", "--effects", EFFECTS],
                           check=True, capture_output=True)
        fit = _run(["fit", *model, str(log)])["maxrss_kib"]
        dr = _run(["diagnose", *model, "--max-order", "16", str(log)])
        diag = dr["maxrss_kib"]
        tr = (_run(["diagnose", *model, "--max-order", "16", str(log)], traced=True)
              ["traced_bytes"] if a.traced else None)
        rows.append((m, fit, diag, tr))
        print(f"{m:6g} min log ({log.stat().st_size / 1e6:7.1f} MB): peak RSS fit "
              f"{fit / 1024:7.0f} MB, diagnose {diag / 1024:7.0f} MB ({dr['wall_s']:.1f} s)"
              + (f", traced peak {tr / 1e6:.1f} MB" if tr is not None else ""), flush=True)
    if len(rows) >= 2:
        (m0, f0, d0, t0), (m1, f1, d1, t1) = rows[0], rows[-1]
        per = 60.0 / (m1 - m0) / 1024
        print(f"growth per hour of 1 kHz log: fit {(f1 - f0) * per:.0f} MB, "
              f"diagnose {(d1 - d0) * per:.0f} MB"
              + (f", traced {(t1 - t0) * per * 1024 / 1e6:.1f} MB "
                 f"({(t1 - t0) / ((m1 - m0) * 60_000):.2f} bytes per sample)"
                 if t0 is not None and t1 is not None else ""))
    if tmp is not None:
        tmp.cleanup()


if __name__ == "__main__":
    main()
