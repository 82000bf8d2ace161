"""The float RLS: recursive against batch, bit-identical paths, numerics and guards.

Every random draw is seeded. Reference solutions are computed in float64 with the
closed form of the weighted ridge least squares, never with the recursion itself.
"""

from __future__ import annotations

import io
import math
from collections.abc import Iterator

import numpy as np
import numpy.typing as npt
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from canrls import _kernels
from canrls.core.errors import CheckpointError, EstimatorError
from canrls.estimation.rls import RLS, RLSFlag, RLSStep, RLSTrace

F64 = npt.NDArray[np.float64]
DTYPES = [np.float64, np.float32]
UPDATES = ["symmetric", "literal"]


# --------------------------------------------------------------------- helpers
def batch(
    Phi: npt.ArrayLike, Y: npt.ArrayLike, lam: float | npt.ArrayLike, alpha: float
) -> tuple[F64, F64, float]:
    r"""Closed-form weighted ridge LS after all rows of ``Phi``, in float64.

    ``lam`` is a scalar or the factor of each step (:math:`\lambda_k`, e.g. 1 where
    the trace bound held the step). Returns ``theta``, ``R = P^-1`` and the
    minimised cost :math:`J_N(\theta_N)`.
    """
    Phi = np.asarray(Phi, np.float64)
    Y = np.asarray(Y, np.float64)
    N, n = Phi.shape
    lam_k = np.broadcast_to(np.asarray(lam, np.float64), (N,))
    # tail[k] = prod_{m >= k} lambda_m ; weight of row k = prod_{m > k} lambda_m
    tail = np.append(np.cumprod(lam_k[::-1])[::-1], 1.0)
    w = tail[1:]
    prior = tail[0] * alpha
    R = (Phi * w[:, None]).T @ Phi + prior * np.eye(n)
    b = (Phi * w[:, None]).T @ Y
    theta = np.linalg.solve(R, b)
    cost = float(w @ (Y - Phi @ theta) ** 2 + prior * theta @ theta)
    return theta, R, cost


def regression(N: int, n: int, seed: int, noise: float = 0.05) -> tuple[F64, F64, F64]:
    """Random regressors with column scales spread over a factor 16, plus noise."""
    rng = np.random.default_rng(seed)
    scales = 2.0 ** rng.integers(-2, 3, n)
    Phi = rng.normal(size=(N, n)) * scales
    theta = rng.uniform(-1.0, 1.0, n)
    return Phi, Phi @ theta + noise * rng.normal(size=N), theta


def drive(
    N: int, seed: int, dwell: int = 0, move: int = 1, dt: float = 1e-2, noise: float = 1e-3
) -> tuple[F64, F64, npt.NDArray[np.bool_]]:
    """Drive-like normalised regressors: the mechanical equation of a rotary axis.

    Columns (|phi_j| <= 1, power-of-two normalised, very different spreads, correlated):
    acceleration, speed, smoothed Coulomb sign, offset, unbalance sin/cos. The axis
    moves with a multisine speed (0.5, 2.3, 7.1 Hz) for ``move`` samples and stands
    still for ``dwell`` samples, alternately (standstill excites only the constant
    columns: the other directions wind up when lambda < 1).
    """
    rng = np.random.default_rng(seed)
    t = np.arange(N) * dt
    f = np.array([0.5, 2.3, 7.1])
    a = np.array([20.0, 8.0, 3.0])
    ph = rng.uniform(0.0, 2.0 * np.pi, 3)
    arg = 2.0 * np.pi * f * t[:, None] + ph
    moving = np.arange(N) % (dwell + move) >= dwell
    omega = (a * np.sin(arg)).sum(axis=1) * moving
    domega = (a * 2.0 * np.pi * f * np.cos(arg)).sum(axis=1) * moving
    pos = np.cumsum(omega) * dt
    Phi = np.column_stack(
        [domega / 1024, omega / 64, np.tanh(omega / 0.5), np.ones(N), np.sin(pos), np.cos(pos)]
    )
    theta = np.array([0.3, 0.2, 0.1, 0.05, 0.02, -0.01])
    return Phi, Phi @ theta + noise * rng.normal(size=N), moving


def rel_asym(P: npt.ArrayLike) -> float:
    """max |P - P'| / max |P|, in float64."""
    P = np.asarray(P, np.float64)
    return float(np.abs(P - P.T).max() / np.abs(P).max())


def bits(a: npt.ArrayLike) -> npt.NDArray[np.uint64]:
    """The bit patterns of a float array (exact comparison, -0 != +0)."""
    a = np.ascontiguousarray(a)
    return a.view(np.uint64 if a.dtype == np.float64 else np.uint32)


def same_bits(a: npt.ArrayLike, b: npt.ArrayLike) -> bool:
    a = np.asarray(a)
    b = np.asarray(b)
    return a.dtype == b.dtype and a.shape == b.shape and np.array_equal(bits(a), bits(b))


def same_state(r1: RLS, r2: RLS) -> bool:
    s1, s2 = r1.state(), r2.state()
    arrays = all(same_bits(s1[k], s2[k]) for k in ("theta", "P", "acc"))
    return arrays and all(s1[k] == s2[k] for k in s1 if k not in ("theta", "P", "acc"))


def awkward_data(N: int, n: int, seed: int) -> tuple[F64, F64]:
    """Data that visits every path: zero rows (windup), NaN/inf rows, regular rows."""
    Phi, Y, _ = regression(N, n, seed)
    rng = np.random.default_rng(seed + 100)
    Phi[rng.random(N) < 0.15] = 0.0
    bad = rng.choice(N, 5, replace=False)
    Phi[bad[0], 0] = np.nan
    Phi[bad[1], -1] = np.inf
    Y[bad[2]] = np.nan
    Y[bad[3]] = -np.inf
    Phi[bad[4]] = 1e200  # phi' P phi overflows (float32: inf after the cast)
    return Phi, Y


def chunks(N: int, seed: int) -> Iterator[slice]:
    """Random block boundaries, including empty and one-row blocks."""
    rng = np.random.default_rng(seed)
    i = 0
    while i < N:
        size = int(rng.choice([0, 1, 1, 2, 3, 7, 16, 41]))
        yield slice(i, min(N, i + size))
        i += size


# ------------------------------------------------ 1. recursion == closed form
@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("lam", [1.0, 0.97])
@pytest.mark.parametrize("n", [1, 3, 6])
def test_matches_batch_closed_form(n: int, lam: float, seed: int) -> None:
    alpha = 1e-3
    N = 300
    Phi, Y, _ = regression(N, n, seed)
    rls = RLS(n, lam=lam, alpha=alpha, trace_max=math.inf)
    trace = rls.run(Phi, Y)
    assert trace.theta is not None
    assert trace.count(RLSFlag.WINDUP) == 0
    # before the data determine theta (prior dominated), and after
    for k in sorted({0, n - 1, 2 * n, 50, N - 1}):
        theta_b, R, cost = batch(Phi[: k + 1], Y[: k + 1], lam, alpha)
        err = np.linalg.norm(trace.theta[k] - theta_b) / np.linalg.norm(theta_b)
        assert err < 1e-9, f"k={k}: relative error {err:.2e}"
        np.testing.assert_allclose(trace.trace_P[k], np.trace(np.linalg.inv(R)), rtol=1e-9)
    np.testing.assert_allclose(rls.P, np.linalg.inv(R), rtol=1e-8, atol=1e-14)
    # the noise accumulator V is the minimised cost J_N(theta_N), exactly
    assert rls.state()["acc"][0] == pytest.approx(cost, rel=1e-8)
    assert rls.count == N


@settings(max_examples=30, deadline=None, derandomize=True, database=None)
@given(
    n=st.integers(1, 5),
    lam=st.floats(0.8, 1.0),
    seed=st.integers(0, 2**16),
    p_zero=st.floats(0.0, 0.9),
)
def test_windup_steps_are_exact_lambda_one_steps(
    n: int, lam: float, seed: int, p_zero: float
) -> None:
    """With the trace bound, the recursion is the closed form with lambda_k = 1 at WINDUP."""
    N = 120
    Phi, Y, _ = regression(N, n, seed)
    Phi[np.random.default_rng(seed).random(N) < p_zero] = 0.0
    rls = RLS(n, lam=lam, alpha=0.01)
    trace = rls.run(Phi, Y)
    lam_k = np.where(trace.flags & RLSFlag.WINDUP, 1.0, lam)
    theta_b, R, cost = batch(Phi, Y, lam_k, 0.01)
    assert np.linalg.norm(rls.theta - theta_b) <= 1e-9 * np.linalg.norm(theta_b) + 1e-12
    np.testing.assert_allclose(rls.P, np.linalg.inv(R), rtol=1e-8, atol=1e-12)
    assert rls.state()["acc"][0] == pytest.approx(cost, rel=1e-8, abs=1e-12)
    assert np.all(trace.trace_P <= rls.trace_max * (1 + 1e-12))


def test_sigma2_estimates_the_noise_variance() -> None:
    noise = 0.05
    Phi, Y, _ = regression(20_000, 4, seed=7, noise=noise)
    rls = RLS(4)
    assert math.isnan(rls.sigma2)
    rls.run(Phi, Y)
    assert rls.sigma2 == pytest.approx(noise**2, rel=0.05)
    # forgetting: W -> 1/(1 - lambda) effective samples
    rls = RLS(4, lam=0.995)
    rls.run(Phi, Y)
    assert rls.sigma2 == pytest.approx(noise**2, rel=0.15)


def test_std_matches_the_spread_of_the_estimates() -> None:
    """std() = sqrt(sigma2 diag P) predicts the scatter of theta over repeated experiments."""
    n, N, noise, trials = 3, 200, 0.1, 400
    rng = np.random.default_rng(11)
    Phi = rng.normal(size=(N, n)) * np.array([1.0, 0.5, 0.25])
    theta_true = np.array([1.0, -2.0, 0.5])
    estimates = np.empty((trials, n))
    stds = np.empty((trials, n))
    for i in range(trials):
        rls = RLS(n)
        rls.run(Phi, Phi @ theta_true + noise * rng.normal(size=N), record=False)
        estimates[i] = rls.theta
        stds[i] = rls.std()
    np.testing.assert_allclose(estimates.std(axis=0), stds.mean(axis=0), rtol=0.12)
    # unbiased: the mean of the estimates is within 4 standard errors of the truth
    assert np.all(np.abs(estimates.mean(axis=0) - theta_true) < 4 * stds.mean(axis=0) / trials**0.5)


# --------------------------------------------------- 2. bit-identical paths
@pytest.mark.parametrize("update", UPDATES)
@pytest.mark.parametrize("dtype", DTYPES)
def test_update_equals_run_bit_for_bit(dtype: type, update: str) -> None:
    n, N = 4, 400
    Phi, Y = awkward_data(N, n, seed=3)
    kw = dict(lam=0.9, alpha=0.01, trace_max=250.0, update=update, dtype=dtype)
    a, b = RLS(n, **kw), RLS(n, **kw)
    trace = a.run(Phi, Y)
    steps = [b.update(Phi[k], Y[k]) for k in range(N)]
    assert all(isinstance(s, RLSStep) for s in steps)
    assert trace.theta is not None
    eps = np.array([s.eps for s in steps]).astype(dtype)
    assert np.array_equal(eps, trace.eps, equal_nan=True)
    assert same_bits(np.array([s.theta for s in steps]), trace.theta)
    assert same_bits(np.array([s.trace_P for s in steps]).astype(dtype), trace.trace_P)
    assert [int(s.flags) for s in steps] == trace.flags.tolist()
    assert same_state(a, b)
    # every path was visited
    assert trace.count(RLSFlag.WINDUP) > 0
    assert trace.count(RLSFlag.NONFINITE) == 5
    assert trace.count(RLSFlag.NONE) > N // 2
    # K of the last applied step is the gain used: theta_k - theta_{k-1} = K eps
    k = max(i for i in range(N) if steps[i].flags == RLSFlag.NONE)
    np.testing.assert_allclose(
        steps[k].theta - steps[k - 1].theta, steps[k].K * steps[k].eps, rtol=1e-5, atol=1e-12
    )


@pytest.mark.parametrize("update", UPDATES)
@pytest.mark.parametrize("dtype", DTYPES)
def test_any_chunking_is_bit_identical(dtype: type, update: str) -> None:
    n, N = 5, 600
    Phi, Y = awkward_data(N, n, seed=4)
    kw = dict(lam=0.95, alpha=0.01, trace_max=400.0, update=update, dtype=dtype)
    whole = RLS(n, **kw)
    ref = whole.run(Phi, Y)
    assert ref.theta is not None
    for seed in range(3):
        parts = RLS(n, **kw)
        traces = [parts.run(Phi[s], Y[s], record=bool(seed % 2 == 0)) for s in chunks(N, seed)]
        assert sum(len(t) for t in traces) == N
        assert np.array_equal(np.concatenate([t.eps for t in traces]), ref.eps, equal_nan=True)
        assert same_bits(np.concatenate([t.trace_P for t in traces]), ref.trace_P)
        assert np.array_equal(np.concatenate([t.flags for t in traces]), ref.flags)
        if seed % 2 == 0:
            thetas = [t.theta for t in traces]
            assert all(th is not None for th in thetas)
            assert same_bits(np.concatenate(thetas), ref.theta)  # type: ignore[arg-type]
        else:
            assert all(t.theta is None for t in traces)
        assert same_state(parts, whole)
        assert same_bits(traces[-1].theta_final, ref.theta_final)


@pytest.mark.parametrize("via_npz", [False, True])
@pytest.mark.parametrize("dtype", DTYPES)
def test_state_round_trip_continues_bit_for_bit(dtype: type, via_npz: bool) -> None:
    n, N = 4, 500
    Phi, Y = awkward_data(N, n, seed=5)
    kw = dict(lam=0.97, alpha=0.01, trace_max=300.0, dtype=dtype)
    unbroken = RLS(n, **kw)
    ref = unbroken.run(Phi, Y)
    first = RLS(n, **kw)
    first.run(Phi[:200], Y[:200])
    state = first.state()
    if via_npz:
        buf = io.BytesIO()
        np.savez(buf, **state)
        buf.seek(0)
        state = dict(np.load(buf))
    second = RLS.from_state(state)
    rest = second.run(Phi[200:], Y[200:])
    assert rest.theta is not None and ref.theta is not None
    assert same_bits(rest.theta, ref.theta[200:])
    assert np.array_equal(rest.eps, ref.eps[200:], equal_nan=True)
    assert same_state(second, unbroken)
    assert second.count == unbroken.count
    assert second.sigma2 == unbroken.sigma2


def test_from_state_rejects_bad_checkpoints() -> None:
    rls = RLS(3, dtype=np.float32)
    rls.run(np.eye(3), np.ones(3))
    good = rls.state()
    with pytest.raises(CheckpointError, match="'P'"):
        RLS.from_state({k: v for k, v in good.items() if k != "P"})
    with pytest.raises(CheckpointError, match="'theta'.*shape"):
        RLS.from_state({**good, "theta": np.zeros(4, np.float32)})
    with pytest.raises(CheckpointError, match="format"):
        RLS.from_state({**good, "format": "canrls.rls/0"})
    with pytest.raises(CheckpointError, match="lam"):
        RLS.from_state({**good, "lam": 2.0})
    with pytest.raises(CheckpointError, match="count"):
        RLS.from_state({**good, "count": -1})
    with pytest.raises(CheckpointError, match="not numeric"):
        RLS.from_state({**good, "acc": np.array(["a", "b"])})
    with pytest.raises(CheckpointError, match="not exact"):
        RLS.from_state({**good, "P": good["P"].astype(np.float64) + 1e-12})
    # float64 values that are exactly float32 are accepted
    assert same_state(RLS.from_state({**good, "P": good["P"].astype(np.float64)}), rls)


@pytest.mark.parametrize("update", UPDATES)
@pytest.mark.parametrize("dtype", DTYPES)
def test_kernel_is_the_documented_recursion_in_the_state_dtype(dtype: type, update: str) -> None:
    """A scalar reference in numpy scalars of ``dtype`` reproduces the kernel bit for bit.

    numpy float32 scalar arithmetic rounds every operation to float32, so this also
    shows that the float32 kernel computes in float32 (not in float64, rounded).
    """
    t = np.dtype(dtype).type
    n, N = 3, 60
    Phi, Y, _ = regression(N, n, seed=9)
    Phi[:4] = 0.0  # windup steps (tr P0 = trace_max)
    Phi[30:40] = 0.0
    lam, alpha, trace_max = 0.9, 0.01, 300.0
    rls = RLS(n, lam=lam, alpha=alpha, trace_max=trace_max, update=update, dtype=dtype)
    trace = rls.run(Phi, Y)
    assert trace.count(RLSFlag.WINDUP) > 0

    lam_, one, zero = t(lam), t(1), t(0)
    il0 = one / lam_
    theta = [zero] * n
    P = [[t(1.0 / alpha) if i == j else zero for j in range(n)] for i in range(n)]
    V = W = zero
    for k in range(N):
        phi = [t(x) for x in Phi[k]]
        yhat = zero
        for j in range(n):
            yhat = yhat + phi[j] * theta[j]
        eps = t(Y[k]) - yhat
        w = [zero] * n  # P' phi, summed over rows
        for j in range(n):
            for i in range(n):
                w[i] = w[i] + P[j][i] * phi[j]
        if update == "symmetric":
            v = w
        else:  # P phi, row dot products
            v = [zero] * n
            for i in range(n):
                for j in range(n):
                    v[i] = v[i] + P[i][j] * phi[j]
        s = zero
        for i in range(n):
            s = s + phi[i] * v[i]
        trP = zero
        for i in range(n):
            trP = trP + P[i][i]
        g = one / (lam_ + s)
        vw = zero
        for i in range(n):
            vw = vw + v[i] * w[i]
        lam_k, il = lam_, il0
        if (trP - g * vw) * il0 > t(trace_max):
            lam_k, il, g = one, one, one / (one + s)
        K = [g * v[i] for i in range(n)]
        theta = [theta[i] + K[i] * eps for i in range(n)]
        if update == "symmetric":
            P = [[(P[i][j] - g * (v[i] * v[j])) * il for j in range(n)] for i in range(n)]
        else:
            P = [[(P[i][j] - K[i] * w[j]) * il for j in range(n)] for i in range(n)]
        V = lam_k * V + eps * (eps * (lam_k * g))
        W = lam_k * W + one
        assert eps == trace.eps[k], f"row {k}"
    assert same_bits(np.array(theta, dtype), rls.theta)
    assert same_bits(np.array(P, dtype), rls.P)
    assert same_bits(np.array([V, W], dtype), rls.state()["acc"])


def test_flag_values_are_stable() -> None:
    assert [(name, int(f)) for name, f in RLSFlag.__members__.items()] == [
        ("NONE", 0),
        ("WINDUP", 1),
        ("LOW_EXCITATION", 2),
        ("SATURATION", 4),
        ("FROZEN", 8),
        ("NONFINITE", 16),
    ]
    assert _kernels.FLAG_WINDUP == RLSFlag.WINDUP
    assert _kernels.FLAG_FROZEN == RLSFlag.FROZEN
    assert _kernels.FLAG_NONFINITE == RLSFlag.NONFINITE


# ------------------------------------------- 3. literal update vs symmetric
@pytest.mark.parametrize("lam", [0.98, 0.99, 0.995])
def test_float32_literal_loses_symmetry_symmetric_tracks_float64(lam: float) -> None:
    """float32, drive-like data with standstills (windup ~ e^7 between moves).

    The literal update's P becomes measurably asymmetric (relative asymmetry
    ~1e-3, vs float32 resolution 6e-8: it grows with the windup factor); ours
    stays exactly symmetric and positive definite, and its estimate stays within
    1e-4 of the float64 closed form at the end of every move.
    """
    dwell = round(7.0 / (1.0 - lam))
    N = 10 * 2 * dwell
    Phi, Y, moving = drive(N, seed=0, dwell=dwell, move=dwell)
    ends = np.flatnonzero(moving[:-1] & ~moving[1:])  # last sample of each move
    metrics = {}
    for update in UPDATES:
        rls = RLS(6, lam=lam, trace_max=math.inf, update=update, dtype=np.float32)
        asym, min_eig, err = 0.0, math.inf, 0.0
        start = 0
        for stop in [*range(50, N, 50), N]:
            tr = rls.run(Phi[start:stop], Y[start:stop])
            P = rls.P.astype(np.float64)
            asym = max(asym, rel_asym(P))
            min_eig = min(min_eig, float(np.linalg.eigvalsh(0.5 * (P + P.T))[0]))
            for k in ends[(ends >= start) & (ends < stop)]:
                assert tr.theta is not None
                theta_b, _, _ = batch(Phi[: k + 1], Y[: k + 1], lam, 1e-3)
                err = max(err, float(np.abs(tr.theta[k - start] - theta_b).max()))
            start = stop
        metrics[update] = (asym, min_eig, err)
    lit, sym = metrics["literal"], metrics["symmetric"]
    assert sym[0] == 0.0, "symmetric update must stay exactly symmetric"
    assert sym[1] > 0.0, f"symmetric P lost positive definiteness: {sym[1]:.2e}"
    assert sym[2] < 1e-4, f"symmetric float32 vs float64 batch: {sym[2]:.2e}"
    assert lit[0] > 3e-5, f"literal asymmetry only {lit[0]:.2e}"
    assert lit[0] > 1000 * np.finfo(np.float32).eps


@pytest.mark.parametrize("lam", [1.0, 0.999])
def test_float64_long_run_literal_asymmetric_symmetric_exact(lam: float) -> None:
    """10^6 samples in float64: ours is exactly symmetric at every checkpoint.

    The literal P is asymmetric at rounding level throughout; in float64 the two
    estimates agree (the asymmetric error is damped like the symmetric one).
    """
    N = 1_000_000
    Phi, Y, _ = drive(N, seed=1, dwell=300, move=700)
    lit = RLS(6, lam=lam, update="literal")
    sym = RLS(6, lam=lam)
    asym_lit, asym_sym = [], []
    for start in range(0, N, 100_000):
        s = slice(start, start + 100_000)
        lit.run(Phi[s], Y[s], record=False)
        sym.run(Phi[s], Y[s], record=False)
        asym_lit.append(rel_asym(lit.P))
        asym_sym.append(float(np.abs(sym.P - sym.P.T).max()))
    assert max(asym_sym) == 0.0
    assert min(asym_lit) > 0.0 and max(asym_lit) > 1e-18
    np.testing.assert_allclose(lit.theta, sym.theta, rtol=1e-9, atol=1e-12)


# ----------------------------------------------------------- 4. trace bound
@pytest.mark.parametrize("dtype", DTYPES)
def test_trace_bound_holds_without_excitation(dtype: type) -> None:
    n, N, lam = 4, 2000, 0.98
    Phi = np.zeros((N, n))
    Y = np.zeros(N)
    bounded = RLS(n, lam=lam, dtype=dtype)
    tr = bounded.run(Phi, Y)
    assert bounded.trace_max == pytest.approx(n / bounded.alpha)
    assert np.all(tr.trace_P <= bounded.trace_max)
    assert tr.count(RLSFlag.WINDUP) == N
    assert same_bits(bounded.P, RLS(n, dtype=dtype).P)  # held at the prior
    # without the bound: P = P0 / lambda^N, exponential windup
    free = RLS(n, lam=lam, trace_max=math.inf, dtype=dtype)
    tr = free.run(Phi, Y)
    assert tr.count(RLSFlag.WINDUP) == 0
    if dtype is np.float64:
        assert tr.trace_P[-1] == pytest.approx(n / 1e-3 * lam**-N, rel=1e-9)
    assert tr.trace_P[-1] > 1e12 * bounded.trace_max


@pytest.mark.parametrize("dtype", DTYPES)
def test_trace_bound_with_one_dimensional_excitation(dtype: type) -> None:
    n, N, lam = 4, 5000, 0.98
    rng = np.random.default_rng(2)
    d = np.array([0.6, 0.0, -0.8, 0.0])  # the only excited direction
    u = np.sin(0.05 * np.arange(N)) + 0.1 * rng.normal(size=N)
    Phi = u[:, None] * d
    Y = 1.5 * u  # theta' d = 1.5
    bounded = RLS(n, lam=lam, dtype=dtype)
    tr = bounded.run(Phi, Y)
    assert np.all(tr.trace_P <= bounded.trace_max * (1 + 1e-6))
    assert N // 2 < tr.count(RLSFlag.WINDUP) < N
    P = bounded.P.astype(np.float64)
    assert np.all(np.isfinite(P)) and np.linalg.eigvalsh(P)[0] > 0
    assert float(bounded.theta @ d) == pytest.approx(1.5, rel=1e-3)
    free = RLS(n, lam=lam, trace_max=math.inf, dtype=dtype)
    tr_free = free.run(Phi, Y)
    # without the bound the unexcited directions wind up as lambda^-N until
    # P is so large that the update cancels catastrophically (P no longer definite)
    blown = np.abs(tr_free.trace_P) > 1e12 * bounded.trace_max
    assert blown.any() or not np.all(np.isfinite(tr_free.trace_P))


# ------------------------------------------------------------ 5. excitation
def test_excitation_well_excited_is_not_low() -> None:
    Phi, Y, _ = regression(3000, 4, seed=12)
    rls = RLS(4, lam=0.99)
    rls.run(Phi, Y)
    ex = rls.excitation()
    assert not ex.low and ex.positive_definite
    assert 1.0 <= ex.cond < 1e3
    assert ex.min_eig > 10 * rls.alpha
    assert ex.flags == RLSFlag.NONE
    R = np.linalg.inv(rls.P)
    assert ex.min_eig == pytest.approx(np.linalg.eigvalsh(R)[0], rel=1e-9)
    assert ex.cond == pytest.approx(np.linalg.cond(R), rel=1e-6)


@pytest.mark.parametrize("lam", [1.0, 0.99])
def test_excitation_rank_deficient_is_low(lam: float) -> None:
    rng = np.random.default_rng(13)
    a, b = rng.normal(size=(2, 3000))
    Phi = np.column_stack([a, 2.0 * a, b])  # rank 2 of 3
    rls = RLS(3, lam=lam)
    rls.run(Phi, a + b)
    ex = rls.excitation()
    assert ex.low and ex.flags == RLSFlag.LOW_EXCITATION
    assert ex.min_eig < 10 * rls.alpha
    # the prior alone (no data) is low excitation too
    assert RLS(3).excitation().low


def test_excitation_thresholds_are_validated() -> None:
    with pytest.raises(EstimatorError, match="cond_max"):
        RLS(2).excitation(cond_max=0.5)
    with pytest.raises(EstimatorError, match="info_min"):
        RLS(2).excitation(info_min=-1.0)


# ------------------------------------- 6. frozen, reset, lambda, bad input
def test_frozen_leaves_state_untouched_and_resume_continues() -> None:
    n = 3
    Phi, Y, _ = regression(300, n, seed=14)
    rls = RLS(n, lam=0.98)
    ref = RLS(n, lam=0.98)
    rls.run(Phi[:100], Y[:100])
    ref.run(Phi[:100], Y[:100])
    rls.freeze()
    assert rls.frozen
    before = rls.state()
    tr = rls.run(Phi[100:200], Y[100:200])
    step = rls.update(Phi[5], Y[5])
    assert np.all(tr.flags == RLSFlag.FROZEN) and step.flags == RLSFlag.FROZEN
    assert tr.applied == 0 and not np.any(step.K)
    np.testing.assert_allclose(tr.eps, Y[100:200] - Phi[100:200] @ before["theta"], atol=1e-12)
    after = rls.state()
    assert all(same_bits(before[k], after[k]) for k in ("theta", "P", "acc"))
    assert after["count"] == before["count"] == 100
    rls.resume()
    rls.run(Phi[200:], Y[200:])
    ref.run(Phi[200:], Y[200:])
    assert same_state(rls, ref)


def test_reset_returns_to_the_prior() -> None:
    Phi, Y, _ = regression(200, 3, seed=15)
    rls = RLS(3, lam=0.99, alpha=0.1)
    rls.run(Phi, Y)
    rls.reset()
    fresh = RLS(3, lam=0.99, alpha=0.1)
    assert same_state(rls, fresh) and rls.count == 0 and math.isnan(rls.sigma2)
    np.testing.assert_array_equal(rls.P, np.eye(3) / 0.1)
    rls.run(Phi, Y)
    fresh.run(Phi, Y)
    assert same_state(rls, fresh)


def test_set_lambda_takes_effect_and_is_validated() -> None:
    Phi, Y, _ = regression(200, 3, seed=16)
    rls = RLS(3, lam=1.0, trace_max=math.inf)
    rls.run(Phi[:100], Y[:100])
    rls.set_lambda(0.9)
    assert rls.lam == 0.9
    rls.run(Phi[100:], Y[100:])
    lam_k = np.r_[np.ones(100), np.full(100, 0.9)]
    theta_b, _, _ = batch(Phi, Y, lam_k, 1e-3)
    np.testing.assert_allclose(rls.theta, theta_b, rtol=1e-9)
    for bad in (0.0, -0.5, 1.01, math.nan, "0.9x", True):
        with pytest.raises(EstimatorError, match="lam"):
            rls.set_lambda(bad)  # type: ignore[arg-type]
    assert rls.lam == 0.9


@pytest.mark.parametrize("dtype", DTYPES)
def test_nonfinite_input_is_rejected_and_state_untouched(dtype: type) -> None:
    n = 3
    Phi, Y, _ = regression(100, n, seed=17)
    rls = RLS(n, lam=0.99, dtype=dtype)
    ref = RLS(n, lam=0.99, dtype=dtype)
    rls.run(Phi[:50], Y[:50])
    ref.run(Phi[:50], Y[:50])
    before = rls.state()
    bad_rows = [
        ([np.nan, 0.0, 1.0], 1.0),
        ([0.0, np.inf, 1.0], 1.0),
        ([1.0, 2.0, -np.inf], 0.0),
        ([1.0, 2.0, 3.0], np.nan),
        ([1.0, 2.0, 3.0], np.inf),
        ([1e30 if dtype is np.float32 else 1e200, 1.0, 1.0], 1.0),  # phi' P phi overflows
    ]
    for phi, y in bad_rows:
        step = rls.update(phi, y)
        assert step.flags == RLSFlag.NONFINITE, (phi, y)
        assert not np.any(step.K)
    tr = rls.run(np.array([r[0] for r in bad_rows]), np.array([r[1] for r in bad_rows]))
    assert np.all(tr.flags == RLSFlag.NONFINITE) and tr.applied == 0
    assert same_state(rls, RLS.from_state(before)) and rls.count == 50
    rls.run(Phi[50:], Y[50:])
    ref.run(Phi[50:], Y[50:])
    assert same_state(rls, ref)


@pytest.mark.parametrize(
    ("kwargs", "name"),
    [
        (dict(n=0), "n"),
        (dict(n=2.5), "n"),
        (dict(n=True), "n"),
        (dict(n="3"), "n"),
        (dict(lam=0.0), "lam"),
        (dict(lam=1.5), "lam"),
        (dict(lam=math.nan), "lam"),
        (dict(lam=None), "lam"),
        (dict(alpha=0.0), "alpha"),
        (dict(alpha=-1e-3), "alpha"),
        (dict(alpha=math.inf), "alpha"),
        (dict(trace_max=0.0), "trace_max"),
        (dict(trace_max=math.nan), "trace_max"),
        (dict(update="joseph"), "update"),
        (dict(dtype=np.int32), "dtype"),
        (dict(dtype=np.float16), "dtype"),
        (dict(dtype="bogus"), "dtype"),
    ],
)
def test_constructor_errors_name_the_parameter(kwargs: dict[str, object], name: str) -> None:
    args = {"n": 3, **kwargs}
    with pytest.raises(EstimatorError, match=rf"\b{name}\b") as info:
        RLS(**args)  # type: ignore[arg-type]
    assert repr(kwargs[next(iter(kwargs))]) in str(info.value)


def test_shape_errors_name_the_argument() -> None:
    rls = RLS(3)
    with pytest.raises(EstimatorError, match=r"phi .*\(3,\)"):
        rls.update(np.zeros(4), 0.0)
    with pytest.raises(EstimatorError, match="y must be a scalar"):
        rls.update(np.zeros(3), np.zeros(2))  # type: ignore[arg-type]
    with pytest.raises(EstimatorError, match=r"Phi .*\(N, 3\)"):
        rls.run(np.zeros((5, 2)), np.zeros(5))
    with pytest.raises(EstimatorError, match=r"Phi .*\(N, 3\)"):
        rls.run(np.zeros(3), np.zeros(1))
    with pytest.raises(EstimatorError, match=r"Y .*\(5,\)"):
        rls.run(np.zeros((5, 3)), np.zeros(4))
    with pytest.raises(EstimatorError, match="real numbers"):
        rls.update(["a", "b", "c"], 0.0)
    assert rls.count == 0


def test_results_are_inspectable() -> None:
    rls = RLS(2, lam=0.99)
    tr = rls.run(np.eye(2), np.array([1.0, 2.0]))
    assert isinstance(tr, RLSTrace) and len(tr) == 2 and tr.applied == 2
    assert tr.flags.dtype == np.uint8 and tr.eps.dtype == np.float64
    with pytest.raises(ValueError):
        rls.theta[0] = 5.0  # read-only view of the live state
    view = rls.P
    rls.update([1.0, 1.0], 3.0)
    assert same_bits(view, rls.P)  # the view follows the state
    assert "RLS(n=2" in repr(rls) and "count=3" in repr(rls)
    assert rls.std().shape == (2,)
