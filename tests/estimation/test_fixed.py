"""The fixed-point RLS: Q arithmetic, bit-exactness, accuracy against float, guards.

Every random draw is seeded. The float reference is :class:`canrls.estimation.rls.RLS` when it
is importable, otherwise the same recursion written out below in numpy float64.
Bounds are stated in the docstrings, relative and in LSBs of the ``theta`` format.
"""

from __future__ import annotations

import dataclasses
import json
import math
from collections.abc import Iterator
from fractions import Fraction

import numpy as np
import numpy.typing as npt
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from canrls.core.errors import CheckpointError, EstimatorError, FixedPointError
from canrls.estimation.fixed import kernels as K
from canrls.estimation.fixed.estimator import FixedRLS
from canrls.estimation.fixed.formats import SITES, FixedConfig, FixedFlag, QFormat, SaturationCounts
from canrls.estimation.fixed.sweep import SweepResult, sweep
from canrls.estimation.fixed.trace import FixedStep, FixedTrace

F64 = npt.NDArray[np.float64]
UPDATES = ["symmetric", "literal", "naive"]


# --------------------------------------------------------------------- helpers
def float_rls(Phi: F64, Y: F64, lam: float, alpha: float, trace_max: float) -> F64:
    """Final estimate of the float64 reference RLS (canrls.estimation.rls, or the
    recursion here)."""
    try:
        from canrls.estimation.rls import RLS
    except ImportError:  # pragma: no cover - only before canrls.estimation.rls exists
        n = Phi.shape[1]
        theta = np.zeros(n)
        P = np.eye(n) / alpha
        for phi, y in zip(Phi, Y, strict=True):
            eps = y - phi @ theta
            v = P @ phi
            g = 1.0 / (lam + phi @ v)
            lam_k = lam
            if (np.trace(P) - g * (v @ v)) / lam > trace_max:
                lam_k, g = 1.0, 1.0 / (1.0 + phi @ v)
            theta = theta + g * v * eps
            P = (P - g * np.outer(v, v)) / lam_k
        return theta
    rls = RLS(Phi.shape[1], lam=lam, alpha=alpha, trace_max=trace_max)
    rls.run(Phi, Y, record=False)
    return np.array(rls.theta)


def drive_data(
    N: int, n: int, seed: int = 0, noise: float = 2e-3, dt: float = 1e-3
) -> tuple[F64, F64, F64]:
    """A drive-like normalised regression (the mechanical equation of a rotary axis).

    Columns, each scaled by a power of two to ``|phi_j| <= 1``: acceleration
    ``dw/dt / 2^9``, speed ``w / 2^7``, Coulomb ``tanh(w / 0.5)``, offset ``1``,
    unbalance ``sin th, cos th``, cogging ``sin 6th, cos 6th`` (the first ``n``),
    from a multisine speed profile; the target is ``Phi theta`` plus white noise.
    Parameters are all of meaningful size (0.025 .. 0.3).
    """
    rng = np.random.default_rng(seed)
    t = np.arange(N) * dt
    f = np.array([0.23, 0.71, 1.9, 3.7])
    a = np.array([40.0, 18.0, 7.0, 3.0])
    ph = rng.uniform(0.0, 2.0 * np.pi, 4)
    arg = 2.0 * np.pi * f * t[:, None] + ph
    w = (a * np.sin(arg)).sum(axis=1) + 5.0
    dw = (a * 2.0 * np.pi * f * np.cos(arg)).sum(axis=1)
    th = np.cumsum(w) * dt
    cols = [dw / 2**9, w / 2**7, np.tanh(w / 0.5), np.ones(N),
            np.sin(th), np.cos(th), np.sin(6 * th), np.cos(6 * th)]  # fmt: skip
    Phi = np.column_stack(cols[:n])
    theta = np.array([0.30, 0.12, 0.08, 0.05, 0.06, -0.04, 0.03, 0.025])[:n]
    return Phi, Phi @ theta + noise * rng.standard_normal(N), theta


def moving_data(N: int, seed: int, dwell: int = 0, move: int = 1) -> tuple[F64, F64]:
    """Drive-like data, dt = 10 ms, that alternates ``move`` samples moving and
    ``dwell`` standing still (only the constant columns are excited then)."""
    rng = np.random.default_rng(seed)
    t = np.arange(N) * 1e-2
    f = np.array([0.5, 2.3, 7.1])
    a = np.array([20.0, 8.0, 3.0])
    arg = 2.0 * np.pi * f * t[:, None] + rng.uniform(0.0, 2.0 * np.pi, 3)
    moving = np.arange(N) % (dwell + move) >= dwell
    w = (a * np.sin(arg)).sum(axis=1) * moving
    dw = (a * 2.0 * np.pi * f * np.cos(arg)).sum(axis=1) * moving
    pos = np.cumsum(w) * 1e-2
    Phi = np.column_stack(
        [dw / 1024, w / 64, np.tanh(w / 0.5), np.ones(N), np.sin(pos), np.cos(pos)]
    )
    theta = np.array([0.3, 0.2, 0.1, 0.05, 0.02, -0.01])
    return Phi, Phi @ theta + 1e-3 * rng.normal(size=N)


def random_block(rng: np.random.Generator, cfg: FixedConfig, N: int, n: int) -> tuple:
    """Integer inputs that visit every path: out-of-range raw integers, quiet spells
    (windup), bursts that saturate theta and eps."""
    Phi = rng.uniform(-1.2, 1.2, size=(N, n))
    Phi[N // 4 : N // 2, 1:] *= 1e-3  # poorly excited: P grows, the trace bound holds
    Y = Phi @ rng.uniform(-1.0, 1.0, n) + 0.05 * rng.normal(size=N)
    Y[rng.random(N) < 0.02] *= 40.0  # outliers: eps and theta saturate
    Pq, Yq, _ = cfg.quantize_inputs(Phi, Y)
    hit = rng.random((N, n)) < 0.01
    Pq[hit] = rng.choice([-1, 1], size=int(hit.sum())) * (cfg.phi.hi * 5)  # raw overflow
    Yq[rng.random(N) < 0.01] = cfg.y.lo * 7
    return Pq, Yq


def chunks(N: int, seed: int) -> Iterator[slice]:
    """Random block boundaries, including empty and one-row blocks."""
    rng = np.random.default_rng(seed)
    i = 0
    while i < N:
        size = int(rng.choice([0, 1, 1, 2, 3, 7, 16, 41, 200]))
        yield slice(i, min(N, i + size))
        i += size


def rel_asym(P: npt.ArrayLike, F: npt.ArrayLike | None = None) -> float:
    """max |P - P'| / max |P| of the words P, or of the 64-bit P * 2^32 + F (exactly)."""
    if F is None:
        P = np.asarray(P, np.float64)
        return float(np.abs(P - P.T).max() / np.abs(P).max())
    V = [[(int(w) << 32) + int(f) for w, f in zip(rw, rf, strict=True)]
         for rw, rf in zip(np.asarray(P).tolist(), np.asarray(F).tolist(), strict=True)]
    n = len(V)
    d = max(abs(V[i][j] - V[j][i]) for i in range(n) for j in range(n))
    return float(Fraction(d, max(abs(v) for r in V for v in r)))


def snapshot(rls: FixedRLS) -> dict:
    s = rls.state()
    return {k: (v.tolist() if isinstance(v, np.ndarray) else v) for k, v in s.items()}


# ------------------------------------------------- 1. Q-format arithmetic
def ref_rsh(x: int, s: int) -> int:
    """Round half up of x / 2^s, from the rational value."""
    return math.floor(Fraction(x, 2**s) + Fraction(1, 2))


WORD = st.integers(-(2**31), 2**31 - 1)


@settings(max_examples=400, deadline=None)
@given(x=st.integers(-(2**61), 2**61), s=st.integers(0, 60))
def test_round_shift_is_round_half_up(x: int, s: int) -> None:
    assert K.round_shift(x, s) == ref_rsh(x, s)


@settings(max_examples=400, deadline=None)
@given(a=WORD, b=WORD, s=st.integers(-40, 62), bits=st.integers(8, 32))
def test_saturating_multiply(a: int, b: int, s: int, bits: int) -> None:
    """a*b brought to scale 2^s (right: rounded half up; left: exact), clamped, flagged."""
    lo, hi = -(2 ** (bits - 1)), 2 ** (bits - 1) - 1
    exact = ref_rsh(a * b, s) if s >= 0 else a * b * 2 ** (-s)
    want = min(max(exact, lo), hi)
    assert K.sat_mul(a, b, s, lo, hi) == (want, int(want != exact))


@settings(max_examples=400, deadline=None)
@given(a=st.integers(-(2**61), 2**61), b=st.integers(-(2**61), 2**61), bits=st.integers(8, 32))
def test_saturating_add(a: int, b: int, bits: int) -> None:
    lo, hi = -(2 ** (bits - 1)), 2 ** (bits - 1) - 1
    want = min(max(a + b, lo), hi)
    assert K.sat_add(a, b, lo, hi) == (want, int(want != a + b))


@settings(max_examples=400, deadline=None)
@given(x=st.integers(-(2**40), 2**40), s=st.integers(-80, 40), bits=st.integers(8, 32))
def test_store_never_wraps(x: int, s: int, bits: int) -> None:
    """Stores to a finer format (s < 0) saturate before shifting: no wrap for any shift."""
    lo, hi = -(2 ** (bits - 1)), 2 ** (bits - 1) - 1
    exact = ref_rsh(x, s) if s >= 0 else x * 2 ** (-s)
    want = min(max(exact, lo), hi)
    assert K.store(x, s, lo, hi) == (want, int(want != exact))


@settings(max_examples=400, deadline=None)
@given(a=st.integers(-(2**62), 2**62), b=WORD.filter(lambda v: v != 0))
def test_division_truncates_toward_zero(a: int, b: int) -> None:
    assert K.div_trunc(a, b) == int(Fraction(a, b))  # int() truncates toward zero


@settings(max_examples=300, deadline=None)
@given(
    x=st.floats(-1e3, 1e3, allow_nan=False) | st.sampled_from([math.inf, -math.inf, 0.5]),
    bits=st.integers(4, 32),
    frac=st.integers(0, 40),
)
def test_quantize_round_to_nearest_and_saturate(x: float, bits: int, frac: int) -> None:
    q = QFormat(bits, frac)
    got, nsat = q.quantize([x])
    if math.isinf(x):
        want = q.hi if x > 0 else q.lo
    else:
        want = min(max(q.to_int(x), q.lo), q.hi)  # exact rational round half up
    assert int(got[0]) == want
    assert nsat == int(math.isinf(x) or want != q.to_int(x))


@settings(max_examples=200, deadline=None)
@given(m=st.floats(1e-6, 1e6), bits=st.integers(8, 32))
def test_for_range_holds_the_bound_with_least_integer_bits(m: float, bits: int) -> None:
    q = QFormat.for_range(m, bits)
    assert q.max >= m * (1 - 2.0 ** (1 - bits)) or q.hi * q.lsb >= m  # representable
    assert 2.0 ** (q.int_bits - 1) <= m < 2.0**q.int_bits


def test_qformat_basics_and_errors() -> None:
    q = QFormat(16, 14)
    assert (str(q), q.lo, q.hi, q.int_bits) == ("Q1.14", -32768, 32767, 1)
    assert q.to_float(16384) == 1.0 and q.lsb == 2.0**-14
    assert QFormat.for_range(1.0, 32) == QFormat(32, 30)  # 1.0 itself fits
    with pytest.raises(FixedPointError, match="NaN"):
        q.quantize([math.nan])
    with pytest.raises(FixedPointError, match="bits"):
        QFormat(65, 0)
    with pytest.raises(FixedPointError):
        QFormat.for_range(0.0, 16)
    with pytest.raises(dataclasses.FrozenInstanceError):
        q.bits = 8  # type: ignore[misc]


# ------------------------------------------------------------ 2. the config
def test_auto_formats_follow_the_documented_bounds() -> None:
    """n = 8, alpha = 1e-2, lambda = 0.999, defaults: the table of the module docstring."""
    cfg = FixedConfig.auto(8, 1e-2, 0.999)
    f = {k: str(v) for k, v in cfg.formats().items()}
    # P_bar = max(n/alpha, trace_max) = 800 -> 10 integer bits
    assert f == {"phi": "Q1.30", "y": "Q1.30", "theta": "Q3.28", "P": "Q10.21",
                 "K": "Q11.20", "eps": "Q3.28", "h": "Q12.19", "den": "Q13.18",
                 "g": "Q1.30", "lam": "Q1.30"}  # fmt: skip
    assert (cfg.word_bits, cfg.acc_bits, cfg.input_bits) == (32, 64, 32)
    # lambda = 1: P <= P0 = I/alpha, three bits fewer
    assert str(FixedConfig.auto(8, 1e-2, 1.0).P) == "Q7.24"
    # 16-bit inputs, 24-bit state
    c16 = FixedConfig.auto(4, 1e-1, 0.99, word_bits=24, acc_bits=48, input_bits=16)
    assert (c16.phi.bits, c16.theta.bits, str(c16.phi)) == (16, 24, "Q1.14")
    # per-column ranges: one phi format from the largest, theta from the smallest
    cp = FixedConfig.auto(3, 1e-2, 0.99, phi_max=[1.0, 0.5, 0.25])
    assert (str(cp.phi), str(cp.theta)) == ("Q1.30", "Q5.26")  # 4 y_max / 0.25 = 16
    # a narrow accumulator balances the fractions of den and g (dividend fits)
    c32 = FixedConfig.auto(8, 1e-2, 0.999, acc_bits=32)
    assert c32.g.frac + c32.den.frac <= 30 and c32.g.frac > 16


def test_formats_are_overridable() -> None:
    cfg = FixedConfig.auto(4, 1e-2, 0.99, P=QFormat(32, 24), theta=(32, 20))
    assert cfg.P == QFormat(32, 24) and cfg.theta == QFormat(32, 20)
    cfg2 = dataclasses.replace(cfg, K=QFormat(32, 22))
    assert cfg2.K == QFormat(32, 22) and cfg2.P == cfg.P
    assert FixedConfig.from_dict(json.loads(json.dumps(cfg2.to_dict()))) == cfg2
    with pytest.raises(FixedPointError, match="unknown override"):
        FixedConfig.auto(4, 1e-2, 0.99, Q=QFormat(32, 1))
    with pytest.raises(FixedPointError, match="theta"):
        dataclasses.replace(cfg, theta=QFormat(64, 30))  # products must fit 64 bits
    with pytest.raises(FixedPointError, match="P format"):
        # 16-bit P cannot hold 1/alpha = 1e5
        FixedRLS(FixedConfig.auto(4, 1e-2, 0.99, word_bits=16), 4, 0.99, 1e-5)
    with pytest.raises(FixedPointError, match="range of P"):
        FixedConfig.auto(4, 1e-9, 0.99, word_bits=16)
    with pytest.raises(FixedPointError, match="32-bit accumulator cannot sum"):
        # 32 x 32-bit products do not fit a 32-bit accumulator at all
        FixedRLS(FixedConfig.auto(4, 1e-2, 0.99, acc_bits=32), 4, 0.99, 1e-2)


def test_constants_are_exact_integers_from_the_rational_lambda() -> None:
    rls = FixedRLS(FixedConfig.auto(3, 1e-2, 0.99), 3, 0.99, 1e-2)
    c = rls.constants
    f = rls.config.lam.frac
    assert c["inv_lam"] == math.floor(Fraction(2**f) / Fraction(0.99) + Fraction(1, 2))
    assert c["lam_den"] == math.floor(Fraction(0.99) * 2**rls.config.den.frac + Fraction(1, 2))
    assert c["dividend"] == 1 << (rls.config.g.frac + rls.config.den.frac)
    assert all(isinstance(v, int) for v in c.values())


def test_flag_values_match_the_float_estimator() -> None:
    rls_mod = pytest.importorskip("canrls.estimation.rls")
    for name in ("WINDUP", "LOW_EXCITATION", "SATURATION", "FROZEN"):
        assert int(getattr(FixedFlag, name)) == int(getattr(rls_mod.RLSFlag, name))


# ------------------------------------------- 3. bit-exact against Python ints
CONFIGS = [
    # (word, acc, input, lam, n, alpha, trace_max * alpha)
    (32, 64, 32, 0.99, 4, 1e-2, 0.3),
    (32, 64, 16, 1.0, 3, 1e-3, 3.0),
    (24, 48, 16, 0.98, 5, 1e-1, 0.5),
    (16, 32, 16, 0.995, 3, 1e-1, 0.3),
    (24, 32, 16, 0.99, 3, 1e-2, 0.3),  # narrow accumulator: large guard shifts
]


@pytest.mark.parametrize("update", UPDATES)
@pytest.mark.parametrize("W, A, In, lam, n, alpha, tm", CONFIGS)
def test_kernel_is_bit_exact_against_python_integers(
    update: str, W: int, A: int, In: int, lam: float, n: int, alpha: float, tm: float
) -> None:
    """The compiled kernels (the target's for the symmetric form, the compiled
    specification for the others) == the pure-Python reference, integer for integer, on
    inputs that saturate (raw integers beyond the word, outliers), wind up and excite
    poorly.

    The reference also asserts every accumulator value against ``acc_bits``: the
    guard-bit argument holds on these inputs.
    """
    seed = sum(map(ord, update)) * 1000 + W * 100 + A + In + n
    rng = np.random.default_rng(seed)
    cfg = FixedConfig.auto(n, alpha, lam, word_bits=W, acc_bits=A, input_bits=In,
                           trace_max=tm * n / alpha)  # fmt: skip
    rls = FixedRLS(cfg, n, lam, alpha, trace_max=tm * n / alpha, update=update)
    Pq, Yq = random_block(rng, cfg, 500, n)
    theta = [0] * n
    theta_frac = [0] * n
    P = rls.P.tolist() if update == "symmetric" else rls._P.tolist()
    P_frac = [[0] * n for _ in range(n)]
    scale = [rls.P_exp, rls.P_scale]
    counts = [0] * len(SITES)
    eps, tr, ex, fl = K.reference_block(
        Pq.tolist(), Yq.tolist(), theta, P, scale, counts, rls._plan.tolist(), A,
        {"symmetric": K.MODE_SYMMETRIC, "literal": K.MODE_LITERAL, "naive": K.MODE_NAIVE}[update],
        theta_frac, P_frac,
    )  # fmt: skip
    trace = rls.run(Pq, Yq)
    assert trace.eps.tolist() == eps
    assert trace.trace_P.tolist() == tr
    assert trace.P_exp.tolist() == ex
    assert trace.flags.tolist() == fl
    assert rls.theta.tolist() == theta
    assert rls.theta_frac.tolist() == theta_frac
    for mine, ref in ((rls._P, P), (rls._P_frac, P_frac)):
        Pk = mine if update != "symmetric" else np.triu(mine)
        Pr = np.array(ref) if update != "symmetric" else np.triu(np.array(ref))
        assert Pk.tolist() == Pr.tolist()
    assert np.any(rls._P_frac != 0)  # the fractions carry P
    assert [rls.P_exp, rls.P_scale] == scale
    assert list(rls.saturations.values()) == counts
    assert rls.saturations["acc"] == 0
    assert trace.count(FixedFlag.SATURATION) > 0  # the saturating paths were visited
    if lam < 1.0 and update == "symmetric":
        assert trace.count(FixedFlag.WINDUP) > 0  # and the trace bound


# ------------------------------------------- 4. same bits whatever the blocks
@pytest.mark.parametrize("update", ["symmetric", "literal"])
def test_per_sample_block_and_chunked_runs_are_identical(update: str) -> None:
    n, N, lam, alpha = 5, 3000, 0.99, 1e-2
    cfg = FixedConfig.auto(n, alpha, lam)
    Pq, Yq = random_block(np.random.default_rng(7), cfg, N, n)
    block = FixedRLS(cfg, n, lam, alpha, update=update)
    tb = block.run(Pq, Yq)
    chunked = FixedRLS(cfg, n, lam, alpha, update=update)
    parts = [chunked.run(Pq[s], Yq[s]) for s in chunks(N, 3)]
    single = FixedRLS(cfg, n, lam, alpha, update=update)
    steps = [single.update(Pq[k], int(Yq[k])) for k in range(N)]
    for name in ("eps", "trace_P", "P_exp", "flags", "theta"):
        joined = np.concatenate([getattr(p, name) for p in parts])
        assert np.array_equal(joined, getattr(tb, name)), name
    assert [s.eps for s in steps] == tb.eps.tolist()
    assert [s.trace_P for s in steps] == tb.trace_P.tolist()
    assert [int(s.flags) for s in steps] == tb.flags.tolist()
    assert np.array_equal(np.array([s.theta for s in steps]), tb.theta)
    for other in (chunked, single):
        assert snapshot(other) == snapshot(block)
    assert sum((p.saturations for p in parts), SaturationCounts.of({})) == tb.saturations
    assert tb.saturations == block.saturations  # counted in the kernel only
    # record=False changes nothing but the record
    quiet = FixedRLS(cfg, n, lam, alpha, update=update)
    tq = quiet.run(Pq, Yq, record=False)
    assert tq.theta is None and np.array_equal(tq.theta_final, tb.theta_final)
    assert snapshot(quiet) == snapshot(block)


# ---------------------------------------------- 5. accuracy against float
@pytest.mark.parametrize("lam", [0.999, 1.0])
@pytest.mark.parametrize("n, alpha", [(4, 1e-3), (8, 1e-2), (8, 1e-3)])
def test_fixed_tracks_float_on_a_drive_regression(n: int, lam: float, alpha: float) -> None:
    """N = 50 000 samples, 32-bit state, 64-bit accumulators, 32-bit inputs.

    Bound: every parameter within 0.1 % of the float64 RLS (the requirement) and
    within 500 LSB of the theta format (Q3.28, 3.7e-9: 1.9e-6 absolute); measured
    about 2e-6 relative, 30-100 LSB. No saturation anywhere.
    """
    Phi, Y, _ = drive_data(50_000, n)
    ref = float_rls(Phi, Y, lam, alpha, n / alpha)
    cfg = FixedConfig.auto(n, alpha, lam)
    rls = FixedRLS(cfg, n, lam, alpha)
    Pq, Yq, sat = rls.quantize_inputs(Phi, Y)
    tr = rls.run(Pq, Yq, record=False)
    err = np.abs(rls.theta_float - ref)
    assert np.all(err <= 1e-3 * np.abs(ref)), err / np.abs(ref)
    assert err.max() <= 500 * cfg.theta.lsb, err.max() / cfg.theta.lsb
    assert rls.saturations.total == 0 and sat.total == 0
    assert tr.P_exp[-1] > 0  # P has shrunk far below its Q format: the block exponent
    # P itself, in the metric of the float P (eigenvalues of L^-1 P_fixed L^-T, P = L L'):
    # within 0.5 % (measured <= 0.12 %, at lambda = 1 and alpha = 1e-3)
    assert info_error(rls.P_float, _float_P(Phi, lam, alpha, n / alpha)) < 5e-3


def test_lambda_1_long_run_keeps_the_updates_below_the_lsb() -> None:
    """lambda = 1, N = 400 000 (n = 8, drive-like regressors, small parameters, noise 2e-4,
    theta in Q6.25 as the pipeline's ranges give it): the gain falls like 1/N, and the
    update K eps of theta falls to a small fraction of theta's LSB (~0.05 LSB here). Rounded
    to the word each step, most updates became 0: the estimate froze and drifted from
    the float (measured 0.23 % and 4.4 sigma before the 64-bit estimate). With the fraction
    word ``theta_frac`` the updates accumulate: measured 0.0014 % and 0.02 sigma.
    Bound: 0.1 % (the requirement) and 0.5 sigma of the float estimate."""
    from canrls.estimation.rls import RLS

    n, N, alpha = 8, 400_000, 1e-2
    Phi, _, _ = drive_data(N, n, seed=1)
    theta = np.array([0.30, 0.12, 0.08, 0.05, 0.002, -0.001, 0.0008, 0.0005])
    Y = Phi @ theta + 2e-4 * np.random.default_rng(2).standard_normal(N)
    cfg = FixedConfig.auto(n, alpha, 1.0, theta_max=32.0)
    est = FixedRLS(cfg, n, 1.0, alpha)
    Pq, Yq, sat = est.quantize_inputs(Phi, Y)
    est.run(Pq, Yq, record=False)
    ref = RLS(n, 1.0, alpha)  # the float RLS on the same quantised inputs
    ref.run(cfg.phi.to_float(Pq), cfg.y.to_float(Yq), record=False)
    err = est.theta_float - ref.theta
    assert est.saturations.total == 0 and sat.total == 0
    assert np.all(np.abs(err) <= 1e-3 * np.abs(ref.theta)), 100 * err / np.abs(ref.theta)
    assert np.all(np.abs(err) <= 0.5 * ref.std()), err / ref.std()
    assert np.any(est.theta_frac != 0)  # the fraction word carries the estimate


def info_error(P_fixed: F64, P_ref: F64) -> float:
    """Largest relative error of P_fixed in the metric of P_ref: max |eig(L^-1 P L^-T) - 1|."""
    Li = np.linalg.inv(np.linalg.cholesky(P_ref))
    ev = np.linalg.eigvalsh(Li @ (0.5 * (P_fixed + P_fixed.T)) @ Li.T)
    return float(np.abs(ev - 1.0).max())


def _float_P(Phi: F64, lam: float, alpha: float, trace_max: float) -> F64:
    from canrls.estimation.rls import RLS

    rls = RLS(Phi.shape[1], lam=lam, alpha=alpha, trace_max=trace_max)
    rls.run(Phi, np.zeros(len(Phi)), record=False)
    return np.array(rls.P)


def test_sixteen_bit_inputs_track_float() -> None:
    """16-bit inputs (Q1.14), 32-bit state, lambda = 0.999, n = 8, N = 50 000.

    Looser bound for the input quantisation (2^-15 rounding on every phi and y, an
    errors-in-variables noise): 0.1 % relative, 1e-5 absolute; measured about 2e-5
    relative (vs 2e-6 with 32-bit inputs).
    """
    n, lam, alpha = 8, 0.999, 1e-2
    Phi, Y, _ = drive_data(50_000, n, seed=1)
    ref = float_rls(Phi, Y, lam, alpha, n / alpha)
    cfg = FixedConfig.auto(n, alpha, lam, input_bits=16)
    assert (cfg.phi.bits, cfg.y.bits, cfg.theta.bits) == (16, 16, 32)
    rls = FixedRLS(cfg, n, lam, alpha)
    Pq, Yq, _ = rls.quantize_inputs(Phi, Y)
    rls.run(Pq, Yq, record=False)
    err = np.abs(rls.theta_float - ref)
    assert np.all(err <= 1e-3 * np.abs(ref)) and err.max() < 1e-5, err
    assert rls.saturations.total == 0


# -------------------------------------- 6. literal and naive vs symmetric
@pytest.mark.parametrize("lam", [0.99, 0.995])
def test_naive_update_diverges_with_forgetting_where_symmetric_holds(lam: float) -> None:
    """lambda < 1, 20 000 samples of drive data with 0.7 s standstills, n = 6.

    ``naive`` (full matrix, phi'P taken as (P phi)'): its asymmetric rounding error
    grows as lambda^-k; within a few thousand samples P is indefinite, every stage
    saturates and theta is garbage. ``symmetric`` stays exactly symmetric, positive
    definite and within 1e-6 of the float64 RLS. ``literal`` (phi'P as written)
    loses symmetry but, its error being damped like the symmetric one's, stays
    within 1e-6 as well (module docstring, *Update forms*).
    """
    n, N, alpha = 6, 20_000, 1e-2
    Phi, Y = moving_data(N, 0, dwell=70, move=700)
    ref = float_rls(Phi, Y, lam, alpha, n / alpha)
    out = {}
    for update in UPDATES:
        cfg = FixedConfig.auto(n, alpha, lam)
        rls = FixedRLS(cfg, n, lam, alpha, update=update)
        Pq, Yq, _ = rls.quantize_inputs(Phi, Y)
        asym, min_eig, first_sat = 0.0, math.inf, None
        for s in range(0, N, 500):
            tr = rls.run(Pq[s : s + 500], Yq[s : s + 500], record=False)
            if first_sat is None and tr.count(FixedFlag.SATURATION):
                first_sat = s + int(np.flatnonzero(tr.flags & FixedFlag.SATURATION)[0])
            raw = rls._P.astype(np.float64)
            if update != "symmetric":
                asym = max(asym, rel_asym(raw, rls._P_frac))
            Pf = rls.P_float
            min_eig = min(min_eig, float(np.linalg.eigvalsh(0.5 * (Pf + Pf.T))[0]))
        out[update] = (float(np.abs(rls.theta_float - ref).max()), asym, min_eig, first_sat, rls)
    err_s, _, eig_s, sat_s, sym = out["symmetric"]
    assert sat_s is None and sym.saturations.total == 0
    assert eig_s > 0.0 and err_s < 1e-6
    assert np.array_equal(sym.P, sym.P.T)
    err_n, _, eig_n, sat_n, naive = out["naive"]
    assert sat_n is not None and sat_n < 5000, "naive form should break within 5000 samples"
    assert naive.saturations["P"] > 1000 and naive.saturations["theta"] > 100
    assert eig_n < 0.0
    assert err_n > 0.1 and err_n > 1e4 * err_s
    err_l, asym_l, eig_l, sat_l, _ = out["literal"]
    assert asym_l > 0.0, "the literal form must lose exact symmetry"
    assert sat_l is None and eig_l > 0.0 and err_l < 1e-6


def test_without_forgetting_naive_asymmetry_random_walks() -> None:
    """lambda = 1, 300 000 samples: the naive form's asymmetry grows (a random walk,
    1e-5 -> 1e-3 relative) while the symmetric P stays exactly symmetric; without
    forgetting the asymmetric error is not amplified, so all three estimates agree
    with the float one within 1e-5."""
    n, N, lam, alpha = 6, 300_000, 1.0, 1e-2
    Phi, Y = moving_data(N, 1, dwell=300, move=700)
    ref = float_rls(Phi, Y, lam, alpha, n / alpha)
    asym = {}
    for update in UPDATES:
        cfg = FixedConfig.auto(n, alpha, lam)
        rls = FixedRLS(cfg, n, lam, alpha, update=update)
        Pq, Yq, _ = rls.quantize_inputs(Phi, Y)
        a = []
        for s in (slice(0, 5000), slice(5000, N)):
            rls.run(Pq[s], Yq[s], record=False)
            a.append(rel_asym(rls._P, rls._P_frac) if update != "symmetric"
                     else rel_asym(rls.P, rls.P_frac))
        asym[update] = a
        assert np.abs(rls.theta_float - ref).max() < 1e-5, update
    assert asym["symmetric"] == [0.0, 0.0]
    assert asym["naive"][1] > 10 * asym["naive"][0] > 0.0
    assert asym["literal"][1] > 0.0


# ------------------------------------------------------- 7. saturation
def test_out_of_range_inputs_saturate_with_a_count_never_wrap() -> None:
    n = 3
    cfg = FixedConfig.auto(n, 1e-2, 0.99, input_bits=16)
    rls = FixedRLS(cfg, n, 0.99, 1e-2)
    Phi = np.array([[0.5, 2.5, -0.1], [-3.0, 0.2, 1.99], [1.0, 1.0, 1.0]])
    Y = np.array([0.1, 5.0, -2.5])
    Pq, Yq, sat = rls.quantize_inputs(Phi, Y)
    assert sat.nonzero() == {"phi_in": 2, "y_in": 2}
    assert Pq[0, 1] == cfg.phi.hi and Pq[1, 0] == cfg.phi.lo and Yq[1] == cfg.y.hi
    assert rls.saturations.nonzero() == {"phi_in": 2, "y_in": 2}  # added by default
    # raw integers beyond the input word are clamped (and counted) by the kernel
    step = rls.update([cfg.phi.hi * 100, 0, cfg.phi.lo - 1], cfg.y.lo * 3)
    assert step.flags & FixedFlag.SATURATION
    assert rls.saturations["phi_in"] == 4 and rls.saturations["y_in"] == 3
    # the count=False edge does not touch the counters
    rls.quantize_inputs(Phi, Y, count=False)
    assert rls.saturations["phi_in"] == 4


def test_theta_beyond_its_format_saturates_and_recovers() -> None:
    """True parameter 3.0, theta format limited to |theta| < 1 (Q0.31): theta sits at
    the largest word (counted, never wraps to negative), the others stay right."""
    n, lam, alpha = 2, 0.99, 1e-1
    rng = np.random.default_rng(4)
    Phi = rng.uniform(-0.3, 0.3, size=(4000, n))
    Y = Phi @ np.array([3.0, 0.25])
    cfg = FixedConfig.auto(n, alpha, lam, theta_max=0.9)
    assert str(cfg.theta) == "Q0.31"
    rls = FixedRLS(cfg, n, lam, alpha)
    Pq, Yq, _ = rls.quantize_inputs(Phi, Y)
    tr = rls.run(Pq, Yq)
    assert rls.saturations["theta"] > 1000
    assert tr.theta is not None
    assert tr.theta[:, 0].min() >= cfg.theta.lo and tr.theta[:, 0].max() == cfg.theta.hi
    assert rls.theta[0] == cfg.theta.hi
    assert np.all(tr.theta[1000:, 0] > 0)  # pinned at +max, no wrap-around
    assert rls.saturations["acc"] == 0
    # with theta_max covering the truth, no saturation and the right answer
    ok = FixedRLS(FixedConfig.auto(n, alpha, lam, theta_max=4.0), n, lam, alpha)
    ok.run(*ok.quantize_inputs(Phi, Y)[:2])
    np.testing.assert_allclose(ok.theta_float, [3.0, 0.25], atol=1e-6)
    assert ok.saturations.total == 0


# ------------------------------------------- 8. flags, freeze, reset, windup
def test_trace_bound_holds_without_excitation() -> None:
    """Zero regressors, lambda = 0.98: without the bound P would grow as 0.98^-N.
    Every step is held (WINDUP) and P stays the prior, exactly."""
    n, N, lam, alpha = 4, 2000, 0.98, 1e-2
    rls = FixedRLS(FixedConfig.auto(n, alpha, lam), n, lam, alpha)
    P0 = rls.P.copy()
    tr = rls.run(np.zeros((N, n), np.int64), np.zeros(N, np.int64))
    assert tr.count(FixedFlag.WINDUP) == N
    assert np.array_equal(rls.P, P0) and rls.P_exp == 0
    assert np.all(tr.trace_float() <= n / alpha * (1 + 1e-6))
    assert rls.trace_max == n / alpha


def test_freeze_resume_reset_and_set_lambda() -> None:
    n, lam, alpha = 3, 0.99, 1e-2
    cfg = FixedConfig.auto(n, alpha, lam)
    rls = FixedRLS(cfg, n, lam, alpha)
    Phi, Y, _ = drive_data(2000, n)
    Pq, Yq, _ = rls.quantize_inputs(Phi, Y)
    rls.run(Pq[:1000], Yq[:1000])
    before = snapshot(rls)
    rls.freeze()
    step = rls.update(Pq[1000], int(Yq[1000]))
    assert isinstance(step, FixedStep) and step.flags == FixedFlag.FROZEN
    assert step.eps != 0 and not step.K.any()
    tr = rls.run(Pq[1000:1100], Yq[1000:1100])
    assert isinstance(tr, FixedTrace) and tr.applied == 0 and tr.count(FixedFlag.FROZEN) == 100
    after = snapshot(rls)
    assert {k: v for k, v in after.items() if k != "frozen"} == {
        k: v for k, v in before.items() if k != "frozen"
    }
    rls.resume()
    assert rls.update(Pq[1100], int(Yq[1100])).flags & FixedFlag.FROZEN == 0
    rls.reset()
    fresh = FixedRLS(cfg, n, lam, alpha)
    assert snapshot(rls) == snapshot(fresh)
    rls.set_lambda(1.0)
    assert rls.lam == 1.0 and rls.constants["inv_lam"] == rls.constants["one_lam"]
    with pytest.raises(EstimatorError, match="lam"):
        rls.set_lambda(0.4)


def test_std_and_float_views() -> None:
    n, lam, alpha = 4, 1.0, 1e-2
    Phi, Y, _ = drive_data(20_000, n)
    rls = FixedRLS(FixedConfig.auto(n, alpha, lam), n, lam, alpha)
    rls.run(*rls.quantize_inputs(Phi, Y)[:2])
    P = _float_P(Phi, lam, alpha, n / alpha)
    np.testing.assert_allclose(rls.std(4e-6), np.sqrt(4e-6 * np.diag(P)), rtol=1e-4)
    assert info_error(rls.P_float, P) < 1e-3  # measured 1.5e-4
    assert np.array_equal(rls.P_float, rls.P_float.T)
    with pytest.raises(EstimatorError):
        rls.std(-1.0)


# -------------------------------------------------------- 9. checkpoints
def test_state_round_trip_continues_bit_for_bit() -> None:
    n, N, lam, alpha = 5, 6000, 0.995, 1e-2
    cfg = FixedConfig.auto(n, alpha, lam, word_bits=24, acc_bits=48, input_bits=16)
    Pq, Yq = random_block(np.random.default_rng(11), cfg, N, n)
    whole = FixedRLS(cfg, n, lam, alpha)
    whole.run(Pq, Yq)
    first = FixedRLS(cfg, n, lam, alpha)
    first.run(Pq[: N // 2], Yq[: N // 2])
    state = first.state()
    # through JSON (arrays as lists) and through numpy arrays alike
    as_json = json.loads(json.dumps(snapshot(first)))
    for src in (state, as_json):
        second = FixedRLS.from_state(src)
        second.run(Pq[N // 2 :], Yq[N // 2 :])
        assert snapshot(second) == snapshot(whole)
        assert second.saturations == whole.saturations


def test_corrupted_checkpoints_are_rejected() -> None:
    rls = FixedRLS(FixedConfig.auto(3, 1e-2, 0.99), 3, 0.99, 1e-2)
    good = rls.state()
    for key, value, match in (
        ("format", "other/1", "format"),
        ("theta", np.zeros(4, np.int64), "shape"),
        ("theta", np.full(3, 2**40), "outside"),
        ("theta_frac", np.full(3, 2**32), "theta_frac.*outside"),
        ("theta_frac", np.full(3, -1), "theta_frac.*outside"),
        ("P_frac", np.full((3, 3), 2**31), "P_frac.*outside"),
        ("P_frac", np.full((3, 3), -2**31 - 1), "P_frac.*outside"),
        ("P", np.zeros((3, 3)), "integers"),
        ("P_exp", -1, "P_exp"),
        ("P_scale", 0, "P_scale"),
        ("lam", 2.0, "invalid"),
    ):
        bad = dict(good)
        bad[key] = value
        with pytest.raises(CheckpointError, match=match):
            FixedRLS.from_state(bad)
    bad = dict(good)
    del bad["P"]
    with pytest.raises(CheckpointError, match="lacks"):
        FixedRLS.from_state(bad)


@pytest.mark.parametrize("fmt, missing", [("canrls.fixed/1", ("theta_frac", "P_frac")),
                                          ("canrls.fixed/2", ("P_frac",))])
def test_older_checkpoints_continue_with_zero_fractions(fmt: str, missing: tuple) -> None:
    """A state written before the 64-bit estimate (format canrls.fixed/1: no theta_frac,
    no P_frac) or before the 64-bit P (/2: no P_frac) still loads: the estimate and P
    exactly at their words, the fractions 0, and it continues as the same state with
    zero fractions does; a state of format /3 without a fraction is refused, naming
    the key."""
    n, lam, alpha = 4, 1.0, 1e-2
    cfg = FixedConfig.auto(n, alpha, lam)
    Pq, Yq = random_block(np.random.default_rng(5), cfg, 3000, n)
    rls = FixedRLS(cfg, n, lam, alpha)
    rls.run(Pq[:2000], Yq[:2000])
    assert np.any(rls.theta_frac != 0) and np.any(rls.P_frac != 0)
    old = rls.state()
    zero = rls.state()
    for key in missing:
        del old[key]
        zero[key] = np.zeros_like(zero[key])
    old["format"] = fmt
    back = FixedRLS.from_state(old)
    assert back.theta.tolist() == rls.theta.tolist() and back.P.tolist() == rls.P.tolist()
    for key in missing:
        assert not np.any(getattr(back, key))
    same = FixedRLS.from_state(zero)
    back.run(Pq[2000:], Yq[2000:])
    same.run(Pq[2000:], Yq[2000:])
    assert snapshot(back) == snapshot(same)
    for key in missing:
        bad = rls.state()
        del bad[key]
        with pytest.raises(CheckpointError, match=key):
            FixedRLS.from_state(bad)


# ----------------------------------------------------- 10. argument checks
def test_arguments_are_validated() -> None:
    cfg = FixedConfig.auto(3, 1e-2, 0.99)
    rls = FixedRLS(cfg, 3, 0.99, 1e-2)
    with pytest.raises(EstimatorError, match="integers"):
        rls.run(np.zeros((4, 3)), np.zeros(4, np.int64))  # floats: quantize first
    with pytest.raises(EstimatorError, match="shape"):
        rls.run(np.zeros((4, 2), np.int64), np.zeros(4, np.int64))
    with pytest.raises(EstimatorError, match="shape"):
        rls.update(np.zeros(4, np.int64), 0)
    with pytest.raises(EstimatorError, match="64-bit"):
        rls.update([2**70, 0, 0], 0)
    with pytest.raises(EstimatorError, match="update"):
        FixedRLS(cfg, 3, 0.99, 1e-2, update="joseph")
    with pytest.raises(EstimatorError, match="alpha"):
        FixedRLS(cfg, 3, 0.99, 0.0)
    with pytest.raises(EstimatorError, match="n must"):
        FixedRLS(cfg, 0, 0.99, 1e-2)
    with pytest.raises(EstimatorError, match="config"):
        FixedRLS({}, 3, 0.99, 1e-2)  # type: ignore[arg-type]
    assert "W32/A64/I32" in repr(rls) and "W32/A64/I32" in str(cfg)


# ---------------------------------------------------------------- 11. sweep
def test_sweep_reports_and_recommends_the_smallest_configuration() -> None:
    """Drive data, n = 6, lambda = 0.999, alpha = 0.1, 20 000 samples: 16-bit state is
    far off, 24-bit state meets 0.1 %, and the smallest such is recommended."""
    n, lam, alpha = 6, 0.999, 1e-1
    Phi, Y, _ = drive_data(20_000, n, seed=2)
    ref = float_rls(Phi, Y, lam, alpha, n / alpha)
    res = sweep(Phi, Y, ref, lam=lam, alpha=alpha, word_bits=(16, 24, 32),
                acc_bits=(32, 48, 64), input_bits=(16,))  # fmt: skip
    assert isinstance(res, SweepResult) and len(res.rows) == 9
    by = {r.label: r for r in res.rows}
    assert not by["W16/A32/I16"].ok
    assert by["W32/A32/I16"].config is None and "cannot sum" in str(by["W32/A32/I16"].error)
    assert by["W32/A64/I16"].ok and by["W32/A64/I16"].max_rel_error < 1e-4
    assert res.recommended is not None and res.recommended.config is not None
    assert res.recommended.config.word_bits == 24
    assert res.recommended.cost == min(r.cost for r in res.rows if r.ok)
    text = str(res)
    assert "W16/A32/I16" in text and f"recommended: {res.recommended.label}" in text
    d = json.loads(json.dumps(res.to_dict()))
    assert d["recommended"] == res.recommended.label and len(d["rows"]) == 9
    # explicit configurations by name
    cfgs = {"mine": FixedConfig.auto(n, alpha, lam)}
    res2 = sweep(Phi, Y, ref, cfgs, lam=lam, alpha=alpha)
    assert [r.label for r in res2.rows] == ["mine"] and res2.rows[0].ok


def test_sweep_with_sigma_measures_as_fit_does() -> None:
    """With the reference's sigma, each parameter's error is relative to
    max(|theta_ref|, 3 sigma), the measure of canrls fit (pipeline.divergence)."""
    from canrls.estimation.estimates import divergence

    n, lam, alpha = 4, 0.999, 1e-1
    Phi, Y, _ = drive_data(5_000, n, seed=4)
    ref = float_rls(Phi, Y, lam, alpha, n / alpha)
    cfg = FixedConfig.auto(n, alpha, lam, word_bits=24)
    sigma = np.array([0.0, np.nan, 10.0 * abs(ref[2]), 0.0])
    res = sweep(Phi, Y, ref, {"w24": cfg}, lam=lam, alpha=alpha, sigma=sigma)
    row = res.rows[0]
    assert row.max_rel_error == pytest.approx(
        divergence(ref.tolist(), list(row.theta), sigma.tolist()), rel=1e-12)
    # the third parameter is measured against 3 sigma = 30 |theta_3|, the others not
    rel = np.abs(np.array(row.theta) - ref) / np.abs(ref)
    assert row.rel_errors[2] == pytest.approx(rel[2] / 30.0, rel=1e-12)
    assert row.rel_errors[0] == pytest.approx(rel[0], rel=1e-12)
    assert res.sigma_ref[2] == sigma[2] and res.to_dict()["sigma_ref"][3] == 0.0
    with pytest.raises(EstimatorError, match="sigma must have shape"):
        sweep(Phi, Y, ref, {"w24": cfg}, lam=lam, alpha=alpha, sigma=[1.0])


def _quantize_numpy(q: QFormat, x: npt.ArrayLike) -> tuple[npt.NDArray[np.int64], int]:
    """The numpy formulation of :meth:`QFormat.quantize` (before its compiled kernel)."""
    a = np.asarray(x, dtype=np.float64)
    with np.errstate(over="ignore"):
        v = np.floor(np.ldexp(a, q.frac) + 0.5)
    lo, hi = float(q.lo), float(q.hi)
    return np.clip(v, lo, hi).astype(np.int64), int(np.count_nonzero((v < lo) | (v > hi)))


def test_quantize_gives_what_the_numpy_formulation_gives() -> None:
    """Seeded random arrays of every shape (0-d, empty, 2-D, strided) and magnitude, with
    ties, infinities and subnormals: the same integers, types and saturation counts."""
    rng = np.random.default_rng(5)
    shapes: list[tuple[int, ...]] = [(), (0,), (1,), (5,), (3, 4), (4, 1)]
    for i in range(3000):
        q = QFormat(int(rng.integers(2, 54)), int(rng.integers(-64, 127)))
        x = rng.normal(size=shapes[i % len(shapes)]) * 2.0 ** int(rng.integers(-80, 80))
        if x.size:
            lsb = 2.0 ** -q.frac
            x.flat[0] = rng.choice([math.inf, -math.inf, 0.5 * lsb, -0.5 * lsb, 2.5 * lsb,
                                    5e-324, -0.0, float(x.flat[0])])
        if x.ndim == 2 and i % 2:
            x = x.T  # not contiguous
        got, nsat = q.quantize(x)
        want, wsat = _quantize_numpy(q, x)
        assert type(got) is type(want) and np.shape(got) == np.shape(want)
        assert np.asarray(got).tobytes() == np.asarray(want).tobytes() and nsat == wsat
    with pytest.raises(FixedPointError, match="NaN"):
        QFormat(16, 14).quantize([[0.25, 0.5], [math.nan, 0.0]])
