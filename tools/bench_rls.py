"""Throughput of the float RLS, against padasip's FilterRLS as the reference point.

Prints figures; it is not a test. For n = 4 and n = 8, on the same seeded data:

* ``RLS.update`` called once per sample from Python (updates/s),
* ``RLS.run`` over the whole block, float64 (and float32), without and with
  recording theta (updates/s),
* ``padasip.filters.FilterRLS(n, mu=lambda, w="zeros").run(d, x)`` on the first
  ``--padasip-rows`` rows (it is a Python loop), and the ratio ``run / padasip``,
  plus the largest difference between its weights and our theta on those rows
  (the same recursion, so it should be at rounding level).

Every figure is the best of ``--repeat`` timed runs after a warm-up run (the first
touch of the output arrays is not timed). The
machine may be shared: the best of several runs is the least disturbed one, and
``--clock cpu`` times with the thread's CPU time instead of the wall clock.

Usage::

    python tools/bench_rls.py [--rows 2000000] [--padasip-rows 20000] [--repeat 3]
                              [--lam 0.999] [--clock wall|cpu]
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Callable, Sequence

import numpy as np
import numpy.typing as npt

from canrls.estimation.rls import RLS

F64 = npt.NDArray[np.float64]


def make_data(rows: int, n: int, seed: int = 0) -> tuple[F64, F64]:
    """Seeded regressors (spread column scales) and noisy targets."""
    rng = np.random.default_rng(seed)
    Phi = rng.normal(size=(rows, n)) * 2.0 ** rng.integers(-2, 3, n)
    Y = Phi @ rng.uniform(-1.0, 1.0, n) + 0.01 * rng.normal(size=rows)
    return Phi, Y


#: The clock of every measurement: wall time (default) or this thread's CPU time,
#: which leaves out the time the thread waited for a core on a shared machine.
CLOCK: Callable[[], float] = time.perf_counter


def best_rate(fn: Callable[[], object], count: int, repeat: int) -> float:
    """Best ``count / seconds`` over ``repeat`` timed calls of ``fn`` (after one warm-up)."""
    fn()
    best = 0.0
    for _ in range(repeat):
        t0 = CLOCK()
        fn()
        best = max(best, count / (CLOCK() - t0))
    return best


def bench_update(n: int, Phi: F64, Y: F64, lam: float, repeat: int) -> float:
    """Per-sample ``RLS.update`` calls per second."""
    rls = RLS(n, lam=lam)
    rows = Phi.shape[0]

    def loop() -> None:
        update = rls.update
        for k in range(rows):
            update(Phi[k], Y[k])

    return best_rate(loop, rows, repeat)


def bench_run(
    n: int,
    Phi: F64,
    Y: F64,
    lam: float,
    repeat: int,
    dtype: type = np.float64,
    record: bool = False,
) -> float:
    """``RLS.run`` updates per second over the whole block."""
    rls = RLS(n, lam=lam, dtype=dtype)
    rows = Phi.shape[0]
    # inputs already in the state dtype: the conversion is not what we time
    Phi_d = np.ascontiguousarray(Phi, dtype=dtype)
    Y_d = np.ascontiguousarray(Y, dtype=dtype)
    return best_rate(lambda: rls.run(Phi_d, Y_d, record=record), rows, repeat)


def bench_padasip(n: int, Phi: F64, Y: F64, lam: float, repeat: int) -> tuple[float, float] | None:
    """padasip FilterRLS updates per second, and max |w - theta| against ours.

    ``None`` if padasip is not installed (``pip install canrls[bench]``).
    """
    try:
        import padasip
    except ImportError:
        return None
    rows = Phi.shape[0]
    filt: list[object] = []

    def once() -> None:
        f = padasip.filters.FilterRLS(n, mu=lam, w="zeros")  # eps=0.001: P0 = I/1e-3
        f.run(Y, Phi)
        filt[:] = [f]

    rate = best_rate(once, rows, repeat)
    ours = RLS(n, lam=lam, alpha=1e-3, trace_max=np.inf)
    ours.run(Phi, Y, record=False)
    diff = float(np.abs(np.asarray(filt[0].w) - ours.theta).max())  # type: ignore[attr-defined]
    return rate, diff


def bench_float(n: int, rows: int, padasip_rows: int, lam: float, repeat: int) -> None:
    """Print the float-RLS section for one n."""
    Phi, Y = make_data(rows, n, seed=n)
    upd_rows = min(rows, 200_000)
    per_sample = bench_update(n, Phi[:upd_rows], Y[:upd_rows], lam, repeat)
    run64 = bench_run(n, Phi, Y, lam, repeat)
    run64_rec = bench_run(n, Phi, Y, lam, repeat, record=True)
    run32 = bench_run(n, Phi, Y, lam, repeat, dtype=np.float32)
    clock = "wall" if CLOCK is time.perf_counter else "cpu"
    print(f"n = {n}  ({rows} rows, lambda = {lam}, {clock} clock)")
    print(f"  RLS.update, per sample         {per_sample / 1e3:10.1f} k updates/s  ({upd_rows})")
    print(f"  RLS.run float64                {run64 / 1e6:10.2f} M updates/s")
    print(f"  RLS.run float64, record=True   {run64_rec / 1e6:10.2f} M updates/s")
    print(f"  RLS.run float32                {run32 / 1e6:10.2f} M updates/s")
    pa = bench_padasip(n, Phi[:padasip_rows], Y[:padasip_rows], lam, max(1, repeat // 2))
    if pa is None:
        print("  padasip FilterRLS              not installed (pip install canrls[bench])")
        return
    rate, diff = pa
    print(
        f"  padasip FilterRLS.run          {rate / 1e3:10.1f} k updates/s  "
        f"(first {padasip_rows} rows; max |w - theta| = {diff:.1e})"
    )
    print(f"  ratio run float64 / padasip    {run64 / rate:10.0f} x")
    print(f"  ratio update / padasip         {per_sample / rate:10.1f} x")


def bench_fixed(n: int, rows: int, lam: float, repeat: int) -> None:
    """Print the fixed-point section for one n: the same data, quantised at the boundary."""
    from canrls.estimation.fixed.estimator import FixedRLS
    from canrls.estimation.fixed.formats import FixedConfig

    Phi, Y = make_data(rows, n, seed=n)
    scale = float(np.abs(Phi).max())
    Phi, Y = Phi / scale, Y / max(float(np.abs(Y).max()), 1e-300)
    alpha = 1e-1
    cfg = FixedConfig.auto(n, alpha, lam)
    rls = FixedRLS(cfg, n, lam, alpha)
    Pq, Yq, _ = rls.quantize_inputs(Phi, Y)
    rls.run(Pq[:10], Yq[:10], record=False)  # compile or load the cache outside the timing

    def run_block() -> None:
        rls.run(Pq, Yq, record=False)

    batch = best_rate(run_block, rows, repeat)
    m = min(rows, 100_000)
    items = [(Pq[k], int(Yq[k])) for k in range(m)]

    def per_sample() -> None:
        for phi, y in items:
            rls.update(phi, y)

    single = best_rate(per_sample, m, max(1, repeat // 2))
    # the per-sample path and the block path give the same integers
    a = FixedRLS(cfg, n, lam, alpha)
    b = FixedRLS(cfg, n, lam, alpha)
    a.run(Pq[:5000], Yq[:5000], record=False)
    for k in range(5000):
        b.update(Pq[k], int(Yq[k]))
    same = bool(np.array_equal(a.theta, b.theta) and np.array_equal(a.P, b.P))
    print(f"  FixedRLS.update, per sample    {single / 1e3:10.1f} k updates/s  ({m})")
    print(f"  FixedRLS.run {cfg.label:<17} {batch / 1e6:10.2f} M updates/s"
          f"  (per-sample == block: {same})")


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--rows", type=int, default=2_000_000, help="rows per block (2000000)")
    parser.add_argument(
        "--padasip-rows", type=int, default=20_000, help="rows given to padasip (20000)"
    )
    parser.add_argument("--repeat", type=int, default=3, help="timed runs, best kept (3)")
    parser.add_argument("--lam", type=float, default=0.999, help="forgetting factor (0.999)")
    parser.add_argument(
        "--clock",
        choices=("wall", "cpu"),
        default="wall",
        help="wall time, or the thread's CPU time (for a shared machine)",
    )
    args = parser.parse_args(argv)
    global CLOCK
    CLOCK = time.perf_counter if args.clock == "wall" else time.thread_time
    if args.rows < 1 or args.padasip_rows < 1 or args.repeat < 1:
        parser.error("--rows, --padasip-rows and --repeat must be >= 1")
    for n in (4, 8):
        bench_float(n, args.rows, min(args.padasip_rows, args.rows), args.lam, args.repeat)
        bench_fixed(n, args.rows, args.lam, args.repeat)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
