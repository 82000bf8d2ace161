"""The compiled extension ``canrls._fixed`` (the C kernel in the service) against the spec.

:class:`FixedRLS` runs its blocks through the extension (``backend == "c"``); these tests
run the same blocks through the compiled specification (``backend = "spec"``,
``canrls._fixedspec``) and the pure-Python :func:`reference_block`, and require the same
integers: eps, trace, exponent, flags, theta after every row, the fractions of theta,
every word of P and its fraction, the forgetting scale, K and the counters. The cases are
the C kernel's test vectors (tests/firmware/test_ckernel.py). A digest of the compiled
specification's output holds its integers.
"""

from __future__ import annotations

import hashlib
import subprocess
import sys
from typing import Any

import numpy as np
import pytest

from canrls import _fixedspec
from canrls.estimation.fixed import kernels as fixed_kernels
from canrls.estimation.fixed.estimator import FixedRLS
from canrls.estimation.fixed.formats import FixedConfig

cfixed = pytest.importorskip(
    "canrls._fixed", reason="the C extension is not built (pip install builds it)"
)

import test_ckernel  # noqa: E402  (the vector cases)


def _run(est: FixedRLS, Phi: np.ndarray, Y: np.ndarray, frozen: np.ndarray) -> list[object]:
    """Run the rows in blocks split where ``frozen`` changes; everything observable."""
    out: list[object] = []
    k = 0
    while k < len(Y):
        j = k
        while j < len(Y) and frozen[j] == frozen[k]:
            j += 1
        est.freeze() if frozen[k] else est.resume()
        tr = est.run(Phi[k:j], Y[k:j], record=True)
        out += [tr.eps, tr.theta, tr.trace_P, tr.P_exp, tr.flags, tr.applied]
        k = j
    st = est.state()
    out += [st["theta"], st["theta_frac"], np.triu(st["P"]), np.triu(st["P_frac"]),
            st["P_exp"], st["P_scale"], st["counts"]]
    return out


def _same(a: list[object], b: list[object]) -> None:
    assert len(a) == len(b)
    for i, (x, y) in enumerate(zip(a, b, strict=True)):
        assert np.array_equal(np.asarray(x), np.asarray(y)), f"item {i} differs"


@pytest.mark.parametrize("case", test_ckernel._all_cases(), ids=lambda c: c.name)
def test_extension_equals_spec_on_the_vectors(case: test_ckernel.Case) -> None:
    c_est = FixedRLS.from_state(case.est.state())
    s_est = FixedRLS.from_state(case.est.state())
    s_est.backend = "spec"
    assert c_est.backend == "c" and s_est.backend == "spec"
    _same(_run(c_est, case.Phi, case.Y, case.frozen), _run(s_est, case.Phi, case.Y, case.frozen))


@pytest.mark.parametrize("case", test_ckernel._all_cases()[:4], ids=lambda c: c.name)
def test_update_equals_spec_step_by_step(case: test_ckernel.Case) -> None:
    c_est = FixedRLS.from_state(case.est.state())
    s_est = FixedRLS.from_state(case.est.state())
    s_est.backend = "spec"
    for k in range(len(case.Y)):
        for est in (c_est, s_est):
            est.freeze() if case.frozen[k] else est.resume()
        a = c_est.update(case.Phi[k], int(case.Y[k]))
        b = s_est.update(case.Phi[k], int(case.Y[k]))
        assert (a.eps, a.trace_P, a.P_exp, a.flags) == (b.eps, b.trace_P, b.P_exp, b.flags)
        assert np.array_equal(a.K, b.K) and np.array_equal(a.theta, b.theta)
    assert np.array_equal(c_est.P, s_est.P) and c_est.saturations == s_est.saturations


def test_inputs_beyond_int32_are_clamped_and_counted_as_the_spec_does() -> None:
    n = 3
    cfg = FixedConfig.auto(n, 1e-2, 0.99)
    rng = np.random.default_rng(7)
    Phi = rng.integers(-(1 << 40), 1 << 40, (50, n))
    Y = rng.integers(-(1 << 40), 1 << 40, 50)
    a, b = FixedRLS(cfg, n, 0.99, 1e-2), FixedRLS(cfg, n, 0.99, 1e-2)
    b.backend = "spec"
    _same(_run(a, Phi, Y, np.zeros(50, bool)), _run(b, Phi, Y, np.zeros(50, bool)))
    assert a.saturations["phi_in"] == 150 and a.saturations["y_in"] == 50


def test_literal_and_large_models_use_the_spec() -> None:
    cfg = FixedConfig.auto(3, 1e-2, 0.99)
    assert FixedRLS(cfg, 3, 0.99, 1e-2, update="literal").backend == "spec"
    n = cfixed.N_MAX + 1
    assert FixedRLS(FixedConfig.auto(n, 1e-2, 0.99), n, 0.99, 1e-2).backend == "spec"
    with pytest.raises(ValueError, match="backend"):
        FixedRLS(cfg, 3, 0.99, 1e-2).backend = "fast"


def test_fixed_runs_without_importing_the_spec() -> None:
    """The symmetric form runs on the target's kernel alone: the specification
    (fixed_kernels, canrls._fixedspec) loads only when needed."""
    code = (
        "import sys\n"
        "import numpy as np\n"
        "from canrls.estimation.fixed.estimator import FixedConfig, FixedRLS\n"
        "cfg = FixedConfig.auto(3, 1e-2, 0.99)\n"
        "est = FixedRLS(cfg, 3, 0.99, 1e-2)\n"
        "Pq, Yq = est.quantize_block(np.ones((4, 3)), np.ones(4))\n"
        "est.run(Pq, Yq)\n"
        "print('canrls.estimation.fixed.kernels' in sys.modules)\n"
    )
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                       check=True)
    assert r.stdout.strip() == "False"


def test_run_block_names_a_wrong_buffer() -> None:
    n, N = 3, 4
    z = np.zeros
    args = [z((N, n), np.int64), z(N, np.int64), z(n, np.int64), z(n, np.int64),
            z((n, n), np.int64), z((n, n), np.int64),
            z(2, np.int64), z(n, np.int64), z(cfixed.NSITES, np.int64),
            z(len(cfixed.PLAN_FIELDS), np.int64), False, z(N, np.int64), None,
            z(N, np.int64), z(N + 1, np.int64), z(N, np.uint8)]
    with pytest.raises(ValueError, match="exp: expected 4 items"):
        cfixed.run_block(*args)


def test_run_block_lets_other_threads_run() -> None:
    """The update loop holds no interpreter lock: the daemon's bus reader keeps taking
    frames while a block of the fixed-point estimator runs. With a switch interval
    longer than the block, a thread that needs the lock could not run during it."""
    import threading

    n, N = 8, 200_000
    cfg = FixedConfig.auto(n, 1e-2, 0.99)
    est = FixedRLS(cfg, n, 0.99, 1e-2)
    assert est.backend != "spec"
    rng = np.random.default_rng(11)
    Pq, Yq, _ = cfg.quantize_inputs(rng.uniform(-0.5, 0.5, (N, n)), rng.uniform(-0.5, 0.5, N))
    count = [0]
    stop = threading.Event()

    def spin() -> None:
        while not stop.is_set():
            count[0] += 1

    old = sys.getswitchinterval()
    t = threading.Thread(target=spin, daemon=True)
    try:
        t.start()
        while count[0] == 0:
            pass
        sys.setswitchinterval(1.0)  # from now on this thread keeps the lock unless released
        before = count[0]
        est.run(Pq, Yq, record=False)
        during = count[0] - before
    finally:
        sys.setswitchinterval(old)
        stop.set()
        t.join(10)
    assert during > 0


# ------------------------------------------------- the compiled specification's integers
#: (update, word, acc, input bits, n, lambda) of the digest runs: every form, n beyond the
#: C kernel's bound, narrow words and a narrow accumulator (16-bit words hold n <= 8)
SPEC_RUNS = [(u, *w, n, lam) for u in ("symmetric", "literal", "naive")
             for w in ((32, 64, 32), (24, 48, 16), (24, 32, 16), (16, 32, 16))
             for n, lam in ((3, 0.99), (8, 1.0), (14, 0.95)) if w[0] > 16 or n <= 8]


def spec_digest(block: Any) -> str:
    """SHA-256 of everything ``block`` (:func:`fixed_kernels.fixed_block`'s signature)
    gives over :data:`SPEC_RUNS`: 1,500 rows each with saturating inputs and frozen
    stretches, from the prior and from a disturbed state (random words of P, random
    fractions of theta and of P)."""
    rng = np.random.default_rng(17)
    h = hashlib.sha256()
    for update, W, A, In, n, lam in SPEC_RUNS:
        cfg = FixedConfig.auto(n, 1e-2, lam, word_bits=W, acc_bits=A, input_bits=In,
                               trace_max=0.3 * n / 1e-2)
        for disturbed in (False, True):
            est = FixedRLS(cfg, n, lam, 1e-2, trace_max=0.3 * n / 1e-2, update=update)
            if disturbed:
                st = est.state()
                lim = 2 ** (W - 1)
                st["P"] = np.clip(st["P"] + rng.integers(-1000, 1000, st["P"].shape),
                                  -lim, lim - 1)
                st["theta_frac"] = rng.integers(0, 2**32, n)
                st["P_frac"] = rng.integers(-2**31, 2**31, st["P"].shape)
                est = FixedRLS.from_state(st)
            N = 1500
            Phi = rng.uniform(-1, 1, (N, n)) * (rng.random((N, 1)) < 0.9)
            Pq, Yq, _ = cfg.quantize_inputs(Phi, Phi @ rng.uniform(-1, 1, n)
                                            + rng.normal(0, 0.1, N))
            Pq = Pq.copy()
            big = rng.random(N) < 0.01
            Pq[big] = rng.integers(-(1 << 40), 1 << 40, (int(big.sum()), n))
            frozen = rng.random(N) < 0.05
            k = 0
            while k < N:
                j = k + 1
                while j < N and frozen[j] == frozen[k]:
                    j += 1
                m = j - k
                out = [np.empty(m, np.int64), np.empty((m, n), np.int64),
                       np.empty(m, np.int64), np.empty(m, np.int64), np.empty(m, np.uint8)]
                applied = block(np.ascontiguousarray(Pq[k:j]), np.ascontiguousarray(Yq[k:j]),
                                est._theta, est._theta_frac, est._P, est._P_frac, est._scale,
                                est._work, est._counts, est._plan, est._mode,
                                bool(frozen[k]), True, *out)
                h.update(repr(int(applied)).encode())
                for a in out:
                    h.update(a.tobytes())
                k = j
            for a in (est._theta, est._theta_frac, est._P, est._P_frac, est._scale, est._work,
                      est._counts):
                h.update(a.tobytes())
    return h.hexdigest()[:16]


def test_the_compiled_spec_keeps_its_integers() -> None:
    """The specification compiled in C (``canrls._fixedspec``: every update form, any n)
    gives the integers recorded when P became 64 bits (the fraction below each word, the
    product's high word rounded, g normalised), bit for bit. (Before that change the
    digest was d78b252228a97305, the numba specification's of f79833d.) A change of the
    recursion changes this digest on purpose: its commit says so."""
    assert spec_digest(fixed_kernels.fixed_block) == "3706d5658e267aad"


def test_the_compiled_spec_refuses_wrong_arrays() -> None:
    n, N = 3, 4
    z = np.zeros
    est = FixedRLS(FixedConfig.auto(n, 1e-2, 0.99), n, 0.99, 1e-2)
    args = [z((N, n), np.int64), z(N, np.int64), z(n, np.int64), z(n, np.int64),
            z((n, n), np.int64), z((n, n), np.int64), z(2, np.int64), z((6, n), np.int64),
            z(fixed_kernels.NSITES, np.int64), est._plan, 0, False, True, z(N, np.int64),
            z((N, n), np.int64), z(N, np.int64), z(N, np.int64), z(N, np.uint8)]
    assert fixed_kernels.fixed_block(*args) == N
    for k, bad, err, msg in ((14, z((N - 1, n), np.int64), ValueError, "theta_out must have"),
                             (5, z((n, n + 1), np.int64), ValueError, "P_frac must have"),
                             (7, z((5, n), np.int64), ValueError, "work must have shape"),
                             (9, z(3, np.int64), ValueError, "prm must have shape"),
                             (0, z((N, n)), TypeError, "Phi must be a int64"),
                             (10, 3, ValueError, "unknown mode 3")):
        with pytest.raises(err, match=msg):
            fixed_kernels.fixed_block(*args[:k], bad, *args[k + 1:])
    assert (fixed_kernels.NSITES, fixed_kernels.NPARAM) == (_fixedspec.NSITES,
                                                            _fixedspec.NPARAM)
