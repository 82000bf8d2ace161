"""Peak RSS of ``canrls diagnose`` (and ``canrls fit`` for reference) on simulated logs of
10 and 40 minutes at 1 kHz: how the memory grows with the log.

Each command runs in its own Python process, which reports its own peak resident set
(``getrusage(RUSAGE_SELF).ru_maxrss``), so the figures include the interpreter, numpy,
numba and the compiled kernels. Prints one line per log and command, and the growth per
minute of log. A measurement, not a test: run it once, by hand::

    PYTHONPATH=src python tools/bench_diagnose_memory.py            # 10 and 40 min
    PYTHONPATH=src python tools/bench_diagnose_memory.py --minutes 2 8
    PYTHONPATH=src python tools/bench_diagnose_memory.py --keep DIR  # keep the logs

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
import resource, sys
from canrls.cli.main import main
rc = main(sys.argv[1:])
print("maxrss_kib", resource.getrusage(resource.RUSAGE_SELF).ru_maxrss, file=sys.stderr)
sys.exit(rc)
"""

EFFECTS = "inertia,viscous,coulomb,offset,cogging:6"


def _run(args: list[str]) -> int:
    """Peak RSS [KiB] of ``canrls ARGS`` in a fresh process."""
    out = subprocess.run([sys.executable, "-c", RUN, *args], capture_output=True, text=True,
                         env=dict(os.environ))
    if out.returncode != 0:
        raise SystemExit(f"canrls {' '.join(args)} failed:\n{out.stderr}")
    line = [ln for ln in out.stderr.splitlines() if ln.startswith("maxrss_kib")][-1]
    return int(line.split()[1])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--minutes", type=float, nargs="+", default=[10.0, 40.0])
    ap.add_argument("--keep", metavar="DIR", help="write (and reuse) the logs in DIR")
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
        fit = _run(["fit", *model, str(log)])
        diag = _run(["diagnose", *model, "--max-order", "16", str(log)])
        rows.append((m, fit, diag))
        print(f"{m:6g} min log ({log.stat().st_size / 1e6:7.1f} MB): peak RSS fit "
              f"{fit / 1024:7.0f} MB, diagnose {diag / 1024:7.0f} MB", flush=True)
    if len(rows) >= 2:
        (m0, f0, d0), (m1, f1, d1) = rows[0], rows[-1]
        per = 60.0 / (m1 - m0) / 1024
        print(f"growth per hour of 1 kHz log: fit {(f1 - f0) * per:.0f} MB, "
              f"diagnose {(d1 - d0) * per:.0f} MB")
    if tmp is not None:
        tmp.cleanup()


if __name__ == "__main__":
    main()
