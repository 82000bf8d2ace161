"""canrls._kernels, the C kernels of the estimation: the same bits as before, and as the formulas.

* **Golden digests**: every kernel run on inputs from an integer generator (the same
  numbers on every machine), its outputs hashed. The digests were produced by the numba
  kernels these C kernels replace (canrls 19b846f: float_kernels, svf, selection, model,
  pipeline), so equal digests mean the C port gives those results bit for bit.
* **Reference formulas**: each loop written out in plain Python floats (IEEE double, the
  same operations in the same order) gives the same bits as the kernel.
* **The wrappers** refuse a wrong item type, shape or layout with a named error, never
  reading out of bounds.
"""

from __future__ import annotations

import hashlib
import math
from collections.abc import Callable, Iterator
from typing import Any

import numpy as np
import numpy.typing as npt
import pytest

from canrls import _kernels
from canrls.estimation.svf import SVF

F64 = npt.NDArray[np.float64]


# ----------------------------------------------------------------- the inputs
def uniform(seed: int, count: int) -> F64:
    """``count`` numbers in [-1, 1) from a 64-bit LCG: exact, the same everywhere."""
    x = seed
    out = np.empty(count)
    for k in range(count):
        x = (6364136223846793005 * x + 1442695040888963407) % 2**64
        out[k] = (x >> 11) * 2.0**-52 - 1.0
    return out


def regression(seed: int, N: int, n: int) -> tuple[F64, F64]:
    """Rows with spread column scales, some standstills (windup) and targets."""
    u = uniform(seed, N * n + N + n).reshape(-1)
    Phi = u[:N * n].reshape(N, n) * np.ldexp(1.0, (np.arange(n) % 7) - 3)
    Phi[N // 5:N // 5 + N // 4] *= 1e-7  # a standstill: the trace bound holds steps
    theta = u[N * n:N * n + n] * 4.0
    Y = Phi @ theta + 0.01 * u[N * n + n:]
    return np.ascontiguousarray(Phi), Y


def digest(arrays: list[Any]) -> str:
    h = hashlib.sha256()
    for a in arrays:
        a = np.asarray(a)
        h.update(str(a.dtype).encode() + str(a.shape).encode() + a.tobytes())
    return h.hexdigest()[:16]


# --------------------------------------------------------- runs of every kernel
def run_rls(K: Any, name: str, dtype: type, lam: float) -> list[Any]:
    """A stream of 400 rows in blocks of 1, 37, 0 and the rest, with a non-finite row
    and a frozen block; every output and the final state."""
    n = 6
    Phi, Y = regression(7, 400, n)
    Phi, Y = Phi.astype(dtype), Y.astype(dtype)
    Y[50] = np.nan
    t = np.dtype(dtype).type
    theta = np.zeros(n, dtype)
    P = np.diag(np.ldexp(1.0, np.arange(n) + 2)).astype(dtype)
    work = np.zeros((3, n), dtype)
    acc = np.zeros(2, dtype)
    trace_max = t(K.trace_of(P) * 2.0**-4)  # the bound holds the standstill's steps
    out: list[Any] = []
    for a, b, frozen in ((0, 1, False), (1, 38, False), (38, 38, False), (38, 60, True),
                         (60, 400, False)):
        m = b - a
        eps, tr = np.empty(m, dtype), np.empty(m, dtype)
        flags, th = np.empty(m, np.uint8), np.empty((m, n), dtype)
        applied = getattr(K, name)(np.ascontiguousarray(Phi[a:b]), np.ascontiguousarray(Y[a:b]),
                                   theta, P, work, acc, t(lam), trace_max, frozen, True,
                                   eps, th, tr, flags)
        out += [eps, th, tr, flags, np.int64(applied)]
    return [*out, theta, P, work[1], acc]


def run_svf(K: Any, hold: tuple[str, ...]) -> list[Any]:
    f = SVF(cutoff_hz=25.0, dt=1e-3, hold=hold)
    m = len(hold)
    u = uniform(11, 300 * m).reshape(300, m) * 10.0
    G0 = np.array([f.coefficients(h)[0] for h in hold])
    G1 = np.array([f.coefficients(h)[1] for h in hold])
    x1, x2, up, primed = np.zeros(m), np.zeros(m), np.zeros(m), np.zeros(1, np.int64)
    out: list[Any] = []
    for a, b in ((0, 1), (1, 120), (120, 300)):
        ff, sf = np.empty((b - a, m)), np.empty((b - a, m))
        K.svf(np.ascontiguousarray(u[a:b]), f.Ad, G0, G1, x1, x2, up, primed, ff, sf)
        out += [ff, sf]
    deriv = np.array([j % 2 == 1 for j in range(m)])
    scale = np.ldexp(1.0, np.arange(m) - 2)
    y, phi = np.empty(300), np.empty((300, m - 1))
    K.svf_scaled(u, f.Ad, G0, G1, x1, x2, up, primed, deriv, scale, y, phi)
    return [*out, y, phi, x1, x2, up, primed]


def sample_times(seed: int, N: int) -> F64:
    """1 ms steps with lost frames (2, 3 periods), a long gap and a step back."""
    u = uniform(seed, N)
    step = np.where(u < 0.6, 1e-3, np.where(u < 0.8, 2e-3, np.where(u < 0.9, 3e-3, 1e-3)))
    step[N // 3] = 0.5
    step[N // 2] = -0.01
    return 2.0 + np.cumsum(step)


def run_selection(K: Any) -> list[Any]:
    N = 500
    t = sample_times(3, N)
    omega = uniform(4, N) * 100.0
    out: list[Any] = []
    state = np.array([np.nan, 0.0, 0.0])
    for a, b in ((0, 200), (200, 500)):
        restart, use = np.zeros(b - a, np.bool_), np.empty(b - a, np.bool_)
        r = K.select(np.ascontiguousarray(t[a:b]), np.ascontiguousarray(omega[a:b]), 0.01, 7,
                     5.0, 80.0, state, restart, use)
        out += [np.array(r, np.int64), restart, use, state.copy()]
    fills = [K.nothing_to_fill(t, False, 0.0, 1e-3, 0.05),
             K.nothing_to_fill(t[:40], True, t[0] - 1e-3, 1e-3, 0.05),
             K.nothing_to_fill(2.0 + 1e-3 * np.arange(100), True, 1.999, 1e-3, 0.05),
             K.nothing_to_fill(2.0 + 1e-3 * np.arange(100), True, 1.990, 1e-3, 0.05)]
    return [*out, np.array(fills, np.bool_)]


def run_unwrap(K: Any) -> list[Any]:
    out: list[Any] = []
    for period in (2 * math.pi, 0.01):
        p = np.mod(np.cumsum(uniform(5, 400) * period * 0.3), period)
        p[100] = np.nan
        turns = 0
        last = math.nan
        for a, b in ((0, 1), (1, 250), (250, 400)):
            o = np.empty(b - a)
            turns = int(K.unwrap(np.ascontiguousarray(p[a:b]), period, turns, last, o))
            last = float(p[b - 1])
            out += [o, np.int64(turns)]
    return out


def bookkeeping_inputs() -> tuple[F64, F64, npt.NDArray[np.bool_], F64, npt.NDArray[np.int64]]:
    """phi (300, 5), y, use, and the float and fixed-point errors of the used rows."""
    N, n = 300, 5
    use = uniform(10, N) < 0.4
    u = int(use.sum())
    return (uniform(8, N * n).reshape(N, n), uniform(9, N), use, uniform(12, u),
            (uniform(13, u) * 2.0**31).astype(np.int64))


def run_bookkeeping(K: Any) -> list[Any]:
    phi, y, use, eps_u, epsq_u = bookkeeping_inputs()
    (N, n), u = phi.shape, len(eps_u)
    flags_u = ((uniform(14, u) + 1.0) * 16).astype(np.uint8)
    flagsq_u = ((uniform(15, u) + 1.0) * 2).astype(np.uint8)
    out: list[Any] = []
    for s_y in (0, 5, -9, 1023, -1074, 1100, -1100, 2000):
        M, v, s, r = np.ones((n, n)), np.ones(n), np.array([1.0, 2.0, 3.0]), np.array([0.5])
        y_out, eps, eps_fixed = np.empty(N), np.empty(N), np.empty(N)
        flags, rms = np.empty(N, np.uint8), np.empty(N)
        w = K.bookkeeping(phi, y, use, eps_u, epsq_u, 2.0**-24, flags_u, flagsq_u, M, v, s,
                          0.01, r, s_y, y_out, eps, eps_fixed, flags, rms)
        out += [np.int64(w), M, v, s, r, y_out, eps, eps_fixed, flags, rms]
    M, v, s = np.zeros((n, n)), np.zeros(n), np.zeros(3)
    K.accumulate(phi, y, use, M, v, s)
    return [*out, M, v, s]


def run_sincos(K: Any) -> list[Any]:
    """The diagnosis's harmonic columns: angles over many turns (a large argument reduces
    the way libm does), the orders of the spectrum in steps of 1/4 and whole ones."""
    a = np.cumsum(uniform(16, 500)) * 40.0
    a[7] = 0.0
    a[8] = -1e5
    orders = np.concatenate([np.arange(1, 17) * 0.25, [1.0, 6.0, 24.0, 97.0]])
    out = np.empty((len(a), 2 * len(orders)))
    K.sincos(a, orders, out)
    return [out]


def runs(K: Any) -> Iterator[tuple[str, Callable[[], list[Any]]]]:
    for name in ("rls_block_symmetric", "rls_block_literal"):
        for dtype in (np.float64, np.float32):
            for lam in (1.0, 0.98):
                yield (f"{name}-{np.dtype(dtype).name}-{lam}",
                       lambda name=name, dtype=dtype, lam=lam: run_rls(K, name, dtype, lam))
    yield "svf-foh", lambda: run_svf(K, ("foh", "foh", "zoh"))
    yield "svf-mixed", lambda: run_svf(K, ("zoh", "foh", "foh", "zoh", "foh"))
    yield "selection", lambda: run_selection(K)
    yield "unwrap", lambda: run_unwrap(K)
    yield "bookkeeping", lambda: run_bookkeeping(K)
    yield "sincos", lambda: run_sincos(K)


#: Digests of the numba kernels of canrls 19b846f on these runs (sincos: the diagnosis's
#: numba kernel of f79833d, ``canrls.diagnosis.residual._sincos``).
GOLDEN = {
    "rls_block_symmetric-float64-1.0": "4670ca557c93036b",
    "rls_block_symmetric-float64-0.98": "a498196c1608557f",
    "rls_block_symmetric-float32-1.0": "292d33a663784935",
    "rls_block_symmetric-float32-0.98": "91b642a5b4c72823",
    "rls_block_literal-float64-1.0": "424afdbd86a1f408",
    "rls_block_literal-float64-0.98": "39bc812960a36a0f",
    "rls_block_literal-float32-1.0": "43ea2192b48e3b4b",
    "rls_block_literal-float32-0.98": "127041bb31abfca2",
    "svf-foh": "815385e1adc60c40",
    "svf-mixed": "560bdb3630ce2974",
    # the selection since a reversal between two samples counts as a low speed (the
    # numba kernel's digest was 6c84fa46cd5807c7); test_selection_is_the_documented_rule
    # holds the rule itself
    "selection": "448c81fa1ed33444",
    "unwrap": "07f3f565c3102d12",
    "bookkeeping": "40d0e57a3af08396",
    "sincos": "43dbfaba3af727b8",
}


@pytest.mark.parametrize("case", [name for name, _ in runs(_kernels)])
def test_c_kernels_give_the_numba_kernels_bits(case: str) -> None:
    fn = dict(runs(_kernels))[case]
    assert digest(fn()) == GOLDEN[case]


def test_the_runs_exercise_what_they_are_for() -> None:
    """The RLS runs hit the trace bound, a non-finite row and a frozen block."""
    out = run_rls(_kernels, "rls_block_symmetric", np.float64, 0.98)
    flags = np.concatenate([out[i] for i in range(3, 25, 5)])
    for bit in (_kernels.FLAG_WINDUP, _kernels.FLAG_NONFINITE, _kernels.FLAG_FROZEN):
        assert np.any(flags & bit), bit
    sel = run_selection(_kernels)
    assert sel[0][0] == 2 and sel[4][0] == 1  # start, long gap; step back
    assert sel[-1].tolist() == [False, False, True, False]


# --------------------------------------------------------- reference formulas
def test_svf_is_the_documented_recurrence() -> None:
    """x[k] = Ad x[k-1] + G0 u[k-1] + G1 u[k], summed left to right; at rest on the first."""
    hold = ("foh", "zoh")
    out = run_svf(_kernels, hold)
    f = SVF(cutoff_hz=25.0, dt=1e-3, hold=hold)
    u = uniform(11, 600).reshape(300, 2) * 10.0
    Ad = f.Ad.tolist()
    F, SF = [], []
    for j, h in enumerate(hold):
        G0, G1 = (c.tolist() for c in f.coefficients(h))
        x1, x2, up = u[0, j], 0.0, u[0, j]
        col, dcol = [x1], [x2]
        for k in range(1, 300):
            uk = u[k, j]
            n1 = Ad[0][0] * x1 + Ad[0][1] * x2 + G0[0] * up + G1[0] * uk
            n2 = Ad[1][0] * x1 + Ad[1][1] * x2 + G0[1] * up + G1[1] * uk
            x1, x2, up = n1, n2, uk
            col.append(x1)
            dcol.append(x2)
        F.append(col)
        SF.append(dcol)
    ref_f, ref_sf = np.array(F).T, np.array(SF).T
    assert np.concatenate(out[0:6:2]).tobytes() == ref_f.tobytes()
    assert np.concatenate(out[1:6:2]).tobytes() == ref_sf.tobytes()


def test_selection_is_the_documented_rule() -> None:
    t = sample_times(3, 500)
    omega = uniform(4, 500) * 100.0
    gap, warm, lo, hi = 0.01, 7, 5.0, 80.0
    last, left, w_last = math.nan, 0.0, 0.0
    restart, use = [], []
    crossings = 0
    for tk, wk in zip(t.tolist(), omega.tolist(), strict=True):
        r = not (tk - last <= gap) or tk < last  # nan: the first sample restarts
        if r:
            left = warm
            w_last = 0.0
        last = tk
        # a sign change since the last sample: the speed passed zero in between
        crossed = w_last * wk < 0
        crossings += crossed and lo <= abs(wk) <= hi
        if abs(wk) > hi or abs(wk) < lo or crossed:
            left = warm + 1
        w_last = wk
        restart.append(r)
        use.append(left <= 0)
        left = left - 1 if left > 0 else left
    out = run_selection(_kernels)
    assert crossings > 10  # the rule for a reversal between samples is exercised
    assert np.concatenate([out[1], out[5]]).tolist() == restart
    assert np.concatenate([out[2], out[6]]).tolist() == use
    assert out[0].tolist() == [sum(restart[:200]), sum(use[:200])]


def test_unwrap_is_the_documented_rule() -> None:
    period = 0.01
    p = np.mod(np.cumsum(uniform(5, 400) * period * 0.3), period)
    p[100] = np.nan
    turns, prev, ref = 0, float(p[0]), []
    for pk in p.tolist():
        d = pk - prev
        if math.isfinite(d):
            turns -= int(np.rint(d / period))
        ref.append(pk + float(turns) * period)
        prev = pk
    out = run_unwrap(_kernels)
    assert np.concatenate(out[6:12:2]).tobytes() == np.array(ref).tobytes()
    assert int(out[11]) == turns


def test_bookkeeping_is_the_documented_sums() -> None:
    phi, y, use, eps_u, epsq_u = bookkeeping_inputs()
    N, n = phi.shape
    M, v, s = [[0.0] * n for _ in range(n)], [0.0] * n, [0.0, 0.0, 0.0]
    r, i, e_out, ef_out, rms = 0.5, 0, [], [], []
    for k in range(N):
        e = ef = 0.0
        if use[k]:
            e, ef = float(eps_u[i]), float(epsq_u[i]) * 2.0**-24
            r += 0.01 * (e * e - r)
            i += 1
            for a in range(n):
                v[a] += phi[k, a] * y[k]
                for b in range(a, n):
                    M[a][b] += phi[k, a] * phi[k, b]
            s = [s[0] + 1.0, s[1] + y[k], s[2] + y[k] * y[k]]
        e_out.append(e * 32.0)
        ef_out.append(ef * 32.0)
        rms.append(math.sqrt(r) * 32.0)
    out = run_bookkeeping(_kernels)[10:20]  # s_y = 5
    assert out[6].tolist() == e_out and out[7].tolist() == ef_out and out[9].tolist() == rms
    assert out[5].tolist() == (y * 32.0).tolist()
    Mc, vc, sc = np.zeros((n, n)), np.zeros(n), np.zeros(3)
    _kernels.accumulate(phi, y, use, Mc, vc, sc)
    assert Mc.tolist() == M and vc.tolist() == v and sc.tolist() == s


# ----------------------------------------------------------------- the wrappers
def rls_args(n: int = 3, N: int = 4, dtype: type = np.float64) -> list[Any]:
    return [np.zeros((N, n), dtype), np.zeros(N, dtype), np.zeros(n, dtype),
            np.eye(n, dtype=dtype), np.zeros((3, n), dtype), np.zeros(2, dtype), 0.99, 1e9,
            False, True, np.zeros(N, dtype), np.zeros((N, n), dtype), np.zeros(N, dtype),
            np.zeros(N, np.uint8)]


def test_the_wrappers_refuse_wrong_arrays_with_named_errors() -> None:
    good = rls_args()
    assert _kernels.rls_block_symmetric(*good) == 4
    bad: list[tuple[int, Any, type[Exception], str]] = [
        (3, np.eye(4), ValueError, r"P must have shape \(3, 3\)"),
        (1, np.zeros(5), ValueError, r"Y must have shape \(4,\)"),
        (0, np.zeros((4, 3), np.float32), TypeError, "Phi must be a float64 array"),
        (0, np.zeros((3, 4)).T, TypeError, "Phi must be a C-contiguous"),
        (2, np.zeros(3, np.int64), TypeError, "theta must be a float64 array"),
        (13, np.zeros(4, np.bool_), TypeError, "flags_out must be a uint8 array"),
        (11, np.zeros((0, 3)), ValueError, r"theta_out must have shape \(4, 3\)"),
        (0, np.zeros(12), ValueError, "Phi must have 2 dimension"),
        (4, [[0.0] * 3] * 3, TypeError, "work must be a C-contiguous writable float64"),
    ]
    for i, value, err, msg in bad:
        args = list(good)
        args[i] = value
        with pytest.raises(err, match=msg):
            _kernels.rls_block_symmetric(*args)
    ro = np.eye(3)
    ro.flags.writeable = False
    with pytest.raises(TypeError, match="P must be a C-contiguous writable"):
        _kernels.rls_block_literal(*good[:3], ro, *good[4:])
    with pytest.raises(TypeError, match=r"takes 14 arguments \(3 given\)"):
        _kernels.rls_block_symmetric(*good[:3])
    with pytest.raises(TypeError):
        _kernels.rls_block_symmetric(*good[:6], "x", *good[7:])
    # without record, theta_out may have no rows
    assert _kernels.rls_block_symmetric(*good[:9], False, good[10], np.zeros((0, 3)),
                                        *good[12:]) == 4
    # float32 state: every array float32
    assert _kernels.rls_block_symmetric(*rls_args(dtype=np.float32)) == 4
    with pytest.raises(TypeError, match="Phi must be a float32 array"):
        _kernels.rls_block_symmetric(np.zeros((4, 3)), *rls_args(dtype=np.float32)[1:])
    t = np.zeros(3)
    with pytest.raises(ValueError, match="state must have shape"):
        _kernels.select(t, t, 0.1, 1, 0.0, 1.0, np.zeros(2), np.zeros(3, np.bool_),
                        np.zeros(3, np.bool_))
    with pytest.raises(TypeError, match="use must be a bool array"):
        _kernels.select(t, t, 0.1, 1, 0.0, 1.0, np.zeros(3), np.zeros(3, np.bool_),
                        np.zeros(3, np.uint8))
    with pytest.raises(ValueError, match="at least one sample"):
        _kernels.unwrap(np.zeros(0), 1.0, 0, math.nan, np.zeros(0))
    with pytest.raises(ValueError, match="at least one sample"):
        _kernels.nothing_to_fill(np.zeros(0), False, 0.0, 1e-3, 0.1)
    with pytest.raises(ValueError, match=r"G0 must have shape \(2, 2\)"):
        _kernels.svf(np.zeros((5, 2)), np.eye(2), np.zeros((3, 2)), np.zeros((2, 2)),
                     *(np.zeros(2) for _ in range(3)), np.zeros(1, np.int64),
                     np.zeros((5, 2)), np.zeros((5, 2)))
    use = np.ones(4, np.bool_)
    with pytest.raises(ValueError, match="eps_u must have as many rows as use has used rows"):
        _kernels.bookkeeping(np.zeros((4, 2)), np.zeros(4), use, np.zeros(3),
                             np.zeros(4, np.int64), 1.0, np.zeros(4, np.uint8),
                             np.zeros(4, np.uint8), np.zeros((2, 2)), np.zeros(2),
                             np.zeros(3), 0.1, np.zeros(1), 0, *(np.zeros(4) for _ in range(3)),
                             np.zeros(4, np.uint8), np.zeros(4))
