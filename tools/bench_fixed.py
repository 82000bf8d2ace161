"""Benchmark of the fixed-point RLS kernel, and a word-length sweep demonstration.

Prints, for n = 4 and n = 8 (32-bit state, 64-bit accumulators, 32-bit inputs,
lambda = 0.999) and each backend of ``FixedRLS`` (``c``: the C kernel through the
extension ``canrls._fixed``, the default; ``spec``: the compiled specification,
``canrls._fixedspec``): updates
per second of the per-sample path (``FixedRLS.update``, one Python call per sample) and
of the batch path (``FixedRLS.run`` over a block, ``record=False``), each the best of
several repeats. The target is >= 3 M
updates/s in batch at n = 8. Then runs :func:`canrls.estimation.fixed.sweep.sweep` on a drive-like
regression and prints its table.

Usage::

    python tools/bench_fixed.py [--samples N] [--repeats R] [--no-sweep]

The machine is shared: the best of the repeats is the figure that measures the
kernel rather than the neighbours.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from canrls.estimation.fixed.estimator import FixedRLS
from canrls.estimation.fixed.formats import FixedConfig
from canrls.estimation.fixed.sweep import sweep

TARGET_BATCH_N8 = 3e6


def bench(n: int, samples: int, repeats: int, backend: str = "auto") -> tuple[float, float]:
    """(per-sample updates/s, batch updates/s) for ``n`` parameters on ``backend``."""
    lam, alpha = 0.999, 1e-2
    rng = np.random.default_rng(n)
    Phi = rng.uniform(-1.0, 1.0, size=(samples, n))
    Y = Phi @ rng.uniform(-0.2, 0.2, n) + 0.01 * rng.normal(size=samples)
    cfg = FixedConfig.auto(n, alpha, lam)
    rls = FixedRLS(cfg, n, lam, alpha)
    rls.backend = backend
    Pq, Yq, _ = rls.quantize_inputs(Phi, Y)
    rls.run(Pq[:10], Yq[:10])  # compile (or load the cache) outside the timing
    rls.update(Pq[0], int(Yq[0]))
    best = np.inf
    for _ in range(repeats):
        t0 = time.perf_counter()
        rls.run(Pq, Yq, record=False)
        best = min(best, time.perf_counter() - t0)
    batch = samples / best
    m = min(samples, 20_000)
    rows = [(Pq[k], int(Yq[k])) for k in range(m)]
    best1 = np.inf
    for _ in range(max(1, repeats // 2)):
        t0 = time.perf_counter()
        for phi, y in rows:
            rls.update(phi, y)
        best1 = min(best1, time.perf_counter() - t0)
    return m / best1, batch


def drive_data(N: int, n: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Normalised drive-like regression (as in tests/estimation/test_fixed.py)."""
    rng = np.random.default_rng(seed)
    t = np.arange(N) * 1e-3
    f = np.array([0.23, 0.71, 1.9, 3.7])
    a = np.array([40.0, 18.0, 7.0, 3.0])
    arg = 2.0 * np.pi * f * t[:, None] + rng.uniform(0.0, 2.0 * np.pi, 4)
    w = (a * np.sin(arg)).sum(axis=1) + 5.0
    dw = (a * 2.0 * np.pi * f * np.cos(arg)).sum(axis=1)
    th = np.cumsum(w) * 1e-3
    cols = [dw / 2**9, w / 2**7, np.tanh(w / 0.5), np.ones(N),
            np.sin(th), np.cos(th), np.sin(6 * th), np.cos(6 * th)]  # fmt: skip
    Phi = np.column_stack(cols[:n])
    theta = np.array([0.30, 0.12, 0.08, 0.05, 0.06, -0.04, 0.03, 0.025])[:n]
    return Phi, Phi @ theta + 2e-3 * rng.standard_normal(N)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--samples", type=int, default=200_000, help="batch size (default 200000)")
    ap.add_argument("--repeats", type=int, default=9, help="repeats, best kept (default 9)")
    ap.add_argument("--no-sweep", action="store_true", help="skip the sweep demonstration")
    args = ap.parse_args()

    print("fixed-point RLS, W32/A64/I32, lambda = 0.999, update='symmetric'")
    print(f"{'n':>3} {'backend':>8} {'per-sample update/s':>20} {'batch run() update/s':>21}")
    ok = True
    for n in (4, 8):
        for backend in ("auto", "spec"):
            single, batch = bench(n, args.samples, args.repeats, backend)
            name = FixedRLS(FixedConfig.auto(n, 1e-2, 0.999), n, 0.999, 1e-2).backend \
                if backend == "auto" else "spec"
            print(f"{n:>3} {name:>8} {single:>20,.0f} {batch:>21,.0f}")
            if n == 8 and backend == "auto":
                ok = batch >= TARGET_BATCH_N8
    print(f"target batch n = 8: >= {TARGET_BATCH_N8:,.0f} update/s: {'met' if ok else 'NOT met'}")

    if not args.no_sweep:
        from canrls.estimation.rls import RLS

        n, lam, alpha = 8, 0.999, 1e-1
        Phi, Y = drive_data(50_000, n)
        ref = RLS(n, lam=lam, alpha=alpha)
        ref.run(Phi, Y, record=False)
        t0 = time.perf_counter()
        res = sweep(Phi, Y, ref.theta, lam=lam, alpha=alpha)
        dt = time.perf_counter() - t0
        print()
        print(f"sweep: drive-like regression, n = {n}, lambda = {lam}, alpha = {alpha}, "
              f"N = {len(Y)}, tolerance {res.tol:.1%} ({len(res.rows)} configurations "
              f"in {dt:.1f} s)")  # fmt: skip
        print(res)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
