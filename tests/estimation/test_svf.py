"""The state-variable filter: exact discretisation, chunk invariance, linearity."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from canrls.core.errors import ConfigError
from canrls.estimation.svf import SVF, gain_bounds

DT = 1e-3


def _expm_series(a: np.ndarray) -> np.ndarray:
    """Reference matrix exponential: scaling and squaring of a long Taylor series."""
    s = 10
    b = a / 2.0**s
    out = np.eye(len(a))
    term = np.eye(len(a))
    for k in range(1, 40):
        term = term @ b / k
        out = out + term
    for _ in range(s):
        out = out @ out
    return out


def _chunks(x: np.ndarray, cuts: list[int]) -> list[np.ndarray]:
    bounds = [0, *sorted(c % (len(x) + 1) for c in cuts), len(x)]
    return [x[a:b] for a, b in zip(bounds[:-1], bounds[1:], strict=True)]


@pytest.mark.parametrize(("kwargs", "word"), [
    ({"cutoff_hz": 0.0}, "cutoff_hz"),
    ({"cutoff_hz": -5.0}, "cutoff_hz"),
    ({"cutoff_hz": float("nan")}, "cutoff_hz"),
    ({"cutoff_hz": 500.0}, "Nyquist"),
    ({"cutoff_hz": 600.0}, "Nyquist"),
    ({"dt": 0.0}, "dt"),
    ({"zeta": 0.0}, "zeta"),
    ({"hold": "linear"}, "hold"),
])
def test_invalid_settings_raise_config_error(kwargs: dict, word: str) -> None:
    args = {"cutoff_hz": 25.0, "dt": DT, "zeta": 0.7071} | kwargs
    with pytest.raises(ConfigError, match=word):
        SVF(**args)


@pytest.mark.parametrize("zeta", [0.3, 0.7071, 1.0, 2.0])
def test_transition_matrix_is_the_matrix_exponential(zeta: float) -> None:
    f = SVF(25.0, DT, zeta)
    wc = f.wc
    A = np.array([[0.0, 1.0], [-wc * wc, -2.0 * zeta * wc]])
    np.testing.assert_allclose(f.Ad, _expm_series(A * DT), rtol=1e-12, atol=1e-12)
    # the input matrices of both holds: the augmented exponential gives the ZOH column
    M = np.zeros((3, 3))
    M[:2, :2] = A
    M[:2, 2] = [0.0, wc * wc]
    E = _expm_series(M * DT)
    z = SVF(25.0, DT, zeta, hold="zoh")
    np.testing.assert_allclose(z.G0, E[:2, 2], rtol=1e-10, atol=1e-14)
    np.testing.assert_allclose(f.G0 + f.G1, E[:2, 2], rtol=1e-10, atol=1e-14)


def test_constant_input_starts_at_rest() -> None:
    f = SVF(25.0, DT)
    y, dy = f.process(np.full(500, 3.25))
    assert np.all(y == 3.25)
    assert np.all(np.abs(dy) < 1e-12)


@pytest.mark.parametrize("zeta", [0.7071, 1.0, 1.5])
def test_filtered_derivative_of_a_ramp_is_its_slope(zeta: float) -> None:
    t = np.arange(3000) * DT
    slope = -2.5
    f = SVF(25.0, DT, zeta)
    y, dy = f.process(1.0 + slope * t)
    after = t > 10 * f.settling_time
    assert after.sum() > 1000
    np.testing.assert_allclose(dy[after], slope, rtol=1e-10)
    # F of a ramp lags it by 2 zeta / wc
    np.testing.assert_allclose(y[after], 1.0 + slope * (t[after] - 2 * zeta / f.wc), rtol=1e-10)


def test_zero_order_hold_has_the_documented_ramp_gain_error() -> None:
    t = np.arange(3000) * DT
    f = SVF(25.0, DT, hold="zoh")
    _, dy = f.process(t)
    err = dy[-1] - 1.0
    assert err == pytest.approx(-((f.wc * DT) ** 2) / 12, rel=0.1)


def test_sinusoid_gain_matches_the_continuous_filter() -> None:
    fr = 10.0
    t = np.arange(20000) * DT
    f = SVF(25.0, DT)
    y, dy = f.process(np.sin(2 * np.pi * fr * t))
    s = 2j * np.pi * fr
    F = f.wc**2 / (s * s + 2 * f.zeta * f.wc * s + f.wc**2)
    tail = slice(10000, None)
    assert np.max(np.abs(y[tail])) == pytest.approx(abs(F), rel=1e-3)
    assert np.max(np.abs(dy[tail])) == pytest.approx(abs(s * F), rel=1e-3)


def test_filtered_derivative_matches_filter_of_the_derivative() -> None:
    t = np.arange(10000) * DT
    w = np.sin(2 * np.pi * 1.3 * t) + 0.5 * np.cos(2 * np.pi * 0.4 * t)
    wd = 2 * np.pi * 1.3 * np.cos(2 * np.pi * 1.3 * t) - np.pi * 0.4 * np.sin(2 * np.pi * 0.4 * t)
    _, sfw = SVF(25.0, DT).process(w)
    fwd, _ = SVF(25.0, DT).process(wd)
    tail = slice(1000, None)
    assert np.max(np.abs(sfw[tail] - fwd[tail])) < 1e-6 * np.max(np.abs(wd))


@settings(max_examples=40, deadline=None)
@given(st.lists(st.integers(0, 400), max_size=8), st.integers(1, 4),
       st.sampled_from(["foh", "zoh", "mixed"]))
def test_any_chunking_is_bit_identical(cuts: list[int], m: int, hold: str) -> None:
    rng = np.random.default_rng(len(cuts) * 7 + m)
    if hold == "mixed":
        hold = tuple("zoh" if j % 2 else "foh" for j in range(m))  # type: ignore[assignment]
    u = rng.normal(size=(400, m)) * 10.0 ** rng.integers(-3, 4, size=m)
    one = SVF(25.0, DT, hold=hold).process(u)
    f = SVF(25.0, DT, hold=hold)
    parts = [f.process(c) for c in _chunks(u, cuts)]
    assert np.array_equal(np.concatenate([p[0] for p in parts]), one[0])
    assert np.array_equal(np.concatenate([p[1] for p in parts]), one[1])


def test_per_sample_processing_is_bit_identical() -> None:
    rng = np.random.default_rng(1)
    u = rng.normal(size=(300, 3))
    y, dy = SVF(40.0, DT).process(u)
    f = SVF(40.0, DT)
    rows = [f.process(u[k:k + 1]) for k in range(len(u))]
    assert np.array_equal(np.vstack([r[0] for r in rows]), y)
    assert np.array_equal(np.vstack([r[1] for r in rows]), dy)


@settings(max_examples=40, deadline=None)
@given(st.floats(-1e3, 1e3), st.floats(-1e3, 1e3), st.integers(0, 2**32 - 1))
def test_filter_commutes_with_linear_combinations(a: float, b: float, seed: int) -> None:
    rng = np.random.default_rng(seed)
    u = np.cumsum(rng.normal(size=600))
    v = np.sin(np.arange(600) * 0.05) * rng.uniform(0.1, 100)
    fu, su = SVF(25.0, DT).process(u)
    fv, sv = SVF(25.0, DT).process(v)
    fw, sw = SVF(25.0, DT).process(a * u + b * v)
    scale_f = abs(a) * np.max(np.abs(fu)) + abs(b) * np.max(np.abs(fv)) + 1e-300
    scale_s = abs(a) * np.max(np.abs(su)) + abs(b) * np.max(np.abs(sv)) + 1e-300
    assert np.max(np.abs(fw - (a * fu + b * fv))) <= 1e-12 * scale_f
    assert np.max(np.abs(sw - (a * su + b * sv))) <= 1e-12 * scale_s


@pytest.mark.parametrize("zeta", [0.5, 0.7071, 1.0, 2.0])
def test_gain_bounds_are_the_l1_norms_of_the_impulse_responses(zeta: float) -> None:
    f_gain, sf_gain = gain_bounds(25.0, zeta)
    dt = 1e-5  # fine sampling: the discrete L1 norms approach the continuous ones
    f = SVF(25.0, dt, zeta)
    u = np.zeros(200000)
    u[1] = 1.0 / dt  # unit-area pulse (hat of width 2 dt with the first-order hold)
    y, dy = f.process(u)
    assert np.sum(np.abs(y)) * dt == pytest.approx(f_gain, rel=2e-3)
    assert np.sum(np.abs(dy)) * dt == pytest.approx(sf_gain, rel=2e-3)


def test_gain_bounds_hold_for_bang_bang_inputs() -> None:
    f_gain, sf_gain = gain_bounds(25.0, 0.7071)
    rng = np.random.default_rng(3)
    lo, hi = -2.0, 6.0
    f = SVF(25.0, DT)
    u = np.where(rng.random((20000, 4)) < 0.5, lo, hi)
    # worst case: switch at the resonance
    u[:, 0] = np.where(np.sin(2 * np.pi * 25.0 * np.arange(20000) * DT) > 0, hi, lo)
    y, dy = f.process(u)
    assert np.max(np.abs(y)) <= abs((lo + hi) / 2) + f_gain * (hi - lo) / 2
    assert np.max(np.abs(dy)) <= sf_gain * (hi - lo) / 2
    assert np.max(np.abs(dy)) > 0.5 * sf_gain * (hi - lo) / 2  # and it is not loose


def test_per_column_holds_match_single_hold_filters() -> None:
    rng = np.random.default_rng(4)
    u = rng.normal(size=(500, 3))
    mixed = SVF(25.0, DT, hold=("zoh", "foh", "zoh"))
    f, sf = mixed.process(u)
    for j, h in enumerate(("zoh", "foh", "zoh")):
        fj, sfj = SVF(25.0, DT, hold=h).process(u[:, j])
        assert np.array_equal(f[:, j], fj) and np.array_equal(sf[:, j], sfj)
    assert mixed.G0.shape == (3, 2) and np.all(mixed.G1[[0, 2]] == 0.0)
    with pytest.raises(ValueError, match="3 holds"):
        SVF(25.0, DT, hold=("zoh", "foh", "zoh")).process(u[:, :2])
    with pytest.raises(ConfigError, match="'pwl'"):
        SVF(25.0, DT, hold=("zoh", "pwl"))


def test_zero_order_hold_is_exact_for_staircases() -> None:
    """A held input: the filter output equals the continuous filter's at the samples."""
    f = SVF(25.0, DT, hold="zoh")
    u = np.array([0.0, 1.0, 1.0, -2.0, 0.5] + [0.5] * 45)
    y, dy = f.process(u)
    # reference: fine-step integration of the continuous filter with u held
    x = np.array([0.0, 0.0])
    A = np.array([[0.0, 1.0], [-f.wc**2, -2 * f.zeta * f.wc]])
    ref = [x.copy()]
    for k in range(len(u) - 1):
        step = _expm_series(A * DT / 1000)
        g = np.linalg.solve(A, (step - np.eye(2)) @ np.array([0.0, f.wc**2]))
        for _ in range(1000):
            x = step @ x + g * u[k]
        ref.append(x.copy())
    ref_arr = np.array(ref)
    np.testing.assert_allclose(y, ref_arr[:, 0], atol=1e-11)
    np.testing.assert_allclose(dy, ref_arr[:, 1], atol=1e-8)


def test_one_dimensional_input_state_and_reset() -> None:
    f = SVF(25.0, DT)
    assert f.state is None
    y1, _ = f.process(np.arange(10.0))
    assert y1.shape == (10,)
    x1, x2 = f.state  # type: ignore[misc]
    assert x1.shape == (1,) and x1[0] == y1[-1]
    with pytest.raises(ValueError, match="columns"):
        f.process(np.zeros((3, 2)))
    f.reset()
    y2, _ = f.process(np.arange(10.0))
    assert np.array_equal(y1, y2)
    assert "cutoff_hz=25.0" in repr(f)
    assert f.process(np.zeros((0, 1)))[0].shape == (0, 1)


def test_settling_time_covers_the_transient() -> None:
    f = SVF(25.0, DT)
    t = np.arange(2000) * DT
    _, dy = f.process(t)
    k = int(math.ceil(f.settling_time / DT))
    assert abs(dy[k] - 1.0) < 0.05
