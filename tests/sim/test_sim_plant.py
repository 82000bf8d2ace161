"""The simulated drive's physics, excitation and scenarios."""

from __future__ import annotations

import hashlib
import math
import time
from collections.abc import Callable
from typing import Any

import numpy as np
import pytest

from canrls import _sim
from canrls.core.errors import ConfigError, EffectError
from canrls.sim import (
    PRESETS,
    Sensors,
    Simulator,
    Truth,
    excitation,
    load_torque,
    parse_effects,
    scenario,
    simulate,
)
from canrls.sim.excitation import chirp, prbs, reversals
from canrls.sim.plant import EFFECT_PARAMS, Plant

ALL = "inertia,viscous,coulomb,stribeck,offset,unbalance,cogging:24,electrical"
QUIET = Sensors(current_noise=0.0, speed_noise=0.0, current_step=0.0, speed_step=0.0,
                voltage_step=0.0, position_step=0.0)


def _trap(x: np.ndarray, dt: float) -> np.ndarray:
    return 0.5 * (x[:-1] + x[1:]) * dt


# --------------------------------------------------------------------------- physics


def test_constant_speed_current_balances_the_loads() -> None:
    # constant speed: Kt*i = B*w + Tc + T0 (no acceleration)
    r = simulate("poor", effects="inertia,viscous,coulomb,offset", duration=6.0, sensors=QUIET)
    tr, p = r.truth, r.truth.params
    w = 20.0
    steady = r.true.t > 3.0
    assert np.allclose(r.true.speed[steady], w, atol=1e-6)
    expected = (p["viscous.B"] * w + p["coulomb.Tc"] + p["offset.T0"]) / tr.kt
    assert r.true.current[steady] == pytest.approx(expected, rel=1e-5)


def test_constant_speed_with_noise_current_mean() -> None:
    r = simulate("poor", effects="inertia,viscous,coulomb,offset", duration=8.0, seed=4)
    p = r.truth.params
    steady = r.true.t > 3.0
    expected = (p["viscous.B"] * 20.0 + p["coulomb.Tc"] + p["offset.T0"]) / r.truth.kt
    assert r.measured.current[steady].mean() == pytest.approx(expected, abs=5e-4)


def test_equation_of_motion_recovered_by_least_squares() -> None:
    """The sampled run satisfies the architecture's equations (integral form over each period)."""
    r = simulate("standard", effects=ALL, duration=45.0, sensors=QUIET)
    tr, tru, dt = r.true, r.truth, r.scenario.dt
    th, w, i, u = tr.position, tr.speed, tr.current, tr.voltage
    assert u is not None
    sg = np.tanh(w / tru.coulomb_band)
    cols = {
        "inertia.J": np.diff(w),
        "viscous.B": _trap(w, dt),
        "coulomb.Tc": _trap(sg, dt),
        "stribeck.Ts": _trap(sg * np.exp(-(w / tru.stribeck_speed) ** 2), dt),
        "offset.T0": _trap(np.ones_like(w), dt),
        "unbalance.sin": _trap(np.sin(th), dt),
        "unbalance.cos": _trap(np.cos(th), dt),
        "cogging:24.sin": _trap(np.sin(24 * th), dt),
        "cogging:24.cos": _trap(np.cos(24 * th), dt),
    }
    x, *_ = np.linalg.lstsq(np.column_stack(list(cols.values())), tru.kt * _trap(i, dt),
                            rcond=None)
    for name, v in zip(cols, x, strict=True):
        assert v == pytest.approx(tru[name], rel=0.05), name
    # u_k is held over [t_k, t_k+1): u_k dt = R int i + L (i_k+1 - i_k) + Ke int w
    A = np.column_stack([_trap(i, dt), np.diff(i), _trap(w, dt)])
    x, *_ = np.linalg.lstsq(A, u[:-1] * dt, rcond=None)
    assert x == pytest.approx([tru["electrical.R"], tru["electrical.L"], tru["electrical.Ke"]],
                              rel=0.01)


def test_energy_balance() -> None:
    # int Kt i w dt = dKE + int load(theta, w) w dt
    r = simulate("standard", effects="inertia,viscous,coulomb,offset,unbalance", duration=20.0,
                 sensors=QUIET, excitation="reversals")
    tr, tru, dt = r.true, r.truth, r.scenario.dt
    w = tr.speed
    p_motor = np.sum(_trap(tru.kt * tr.current * w, dt))
    d_ke = 0.5 * tru["inertia.J"] * (w[-1] ** 2 - w[0] ** 2)
    p_load = np.sum(_trap(load_torque(tru, tr.position, w) * w, dt))
    assert p_motor == pytest.approx(d_ke + p_load, rel=2e-3)


def test_integration_converges_with_substeps() -> None:
    sc = scenario("standard", effects=ALL, duration=12.0, sensors=QUIET)
    a = simulate(sc.replace(nsub=5))
    b = simulate(sc.replace(nsub=40))
    assert np.max(np.abs(a.true.speed - b.true.speed)) < 1e-4
    assert np.max(np.abs(a.true.current - b.true.current)) < 1e-4


def test_load_torque_matches_the_formula() -> None:
    tru = Truth({"inertia.J": 1e-4, "viscous.B": 2e-4, "coulomb.Tc": 0.03, "stribeck.Ts": 0.01,
                 "offset.T0": -0.002, "unbalance.sin": 0.01, "unbalance.cos": 0.02,
                 "cogging:6.sin": 0.004, "cogging:6.cos": -0.003}, kt=0.2,
                coulomb_band=0.05, stribeck_speed=2.0)
    th = np.array([0.0, 0.3, 2.0, -1.0])
    w = np.array([0.0, 0.01, 5.0, -3.0])
    sg = np.tanh(w / 0.05)
    want = (2e-4 * w + 0.03 * sg + 0.01 * sg * np.exp(-(w / 2.0) ** 2) - 0.002
            + 0.01 * np.sin(th) + 0.02 * np.cos(th) + 0.004 * np.sin(6 * th)
            - 0.003 * np.cos(6 * th))
    assert np.allclose(load_torque(tru, th, w), want, rtol=1e-14, atol=1e-16)
    assert np.allclose(tru.load_torque(th, w), want, rtol=1e-14, atol=1e-16)
    # a plain mapping takes the architecture defaults (band 0.01, ws 1.0)
    got = load_torque({"coulomb.Tc": 0.03, "offset.T0": 0.001}, th, w)
    assert np.allclose(got, 0.03 * np.tanh(w / 0.01) + 0.001)
    # linear axis: angle = 2*pi*x/pitch
    lin = Truth({"inertia.J": 2.0, "unbalance.sin": 1.0, "unbalance.cos": 0.0}, kt=20.0,
                axis="linear", pitch=0.1)
    assert load_torque(lin, [0.025], [0.0]) == pytest.approx([1.0])
    assert load_torque(lin, 0.025, 0.0, axis="rotary") == pytest.approx(math.sin(0.025))


def test_measured_signals_are_quantised_to_the_dbc() -> None:
    r = simulate("standard", effects="inertia,viscous,coulomb,electrical", duration=3.0, seed=2)
    m = r.measured
    for x, q in ((m.current, 1e-4), (m.speed, 1e-4), (m.voltage, 0.01),
                 (m.position, 2 * np.pi / 65536)):
        assert x is not None
        k = x / q
        assert np.allclose(k, np.round(k), atol=1e-6)
    assert m.position.min() >= 0.0 and m.position.max() < 2 * np.pi
    assert np.allclose(np.unwrap(m.position), r.true.position, atol=2e-4)


def test_voltage_only_with_the_electrical_effect() -> None:
    r = simulate("standard", duration=0.5)
    assert r.true.voltage is None and r.measured.voltage is None
    r = simulate("standard", effects="inertia,electrical", duration=0.5)
    assert r.true.voltage is not None and r.measured.voltage is not None


def test_noise_floor() -> None:
    r = simulate("standard", duration=10.0, seed=5)
    s = r.scenario.sensors
    assert r.noise_floor == pytest.approx(0.1 * math.sqrt(s.current_noise ** 2 + 1e-8 / 12))
    assert r.noise_floor_measured == pytest.approx(r.noise_floor, rel=0.03)
    quiet = simulate("standard", duration=1.0, current_noise=0.0)
    assert quiet.noise_floor == pytest.approx(0.1 * 1e-4 / math.sqrt(12))


def test_speed_tracking() -> None:
    r = simulate("standard", effects=ALL, duration=42.0, seed=1)
    err = r.true.speed - r.speed_ref
    assert np.sqrt(np.mean(err ** 2)) < 0.02 * np.sqrt(np.mean(r.speed_ref ** 2))
    assert np.max(np.abs(r.current_ref)) < r.scenario.controller.i_max  # never saturated
    # the reference reached: both directions, slow and fast
    assert r.true.speed.max() > 99 and r.true.speed.min() < -99


def test_linear_axis_scenario() -> None:
    r = simulate("linear", effects="inertia,viscous,coulomb,unbalance,electrical", duration=42.0)
    tru = r.truth
    assert tru.axis == "linear" and tru.pitch == 0.1 and tru.kt == 20.0
    assert tru.unit("inertia.J") == "kg" and tru.unit("viscous.B") == "N·s/m"
    assert 0.4 < np.abs(r.true.speed).max() < 0.6
    err = r.true.speed - r.speed_ref
    assert np.sqrt(np.mean(err ** 2)) < 0.05 * np.sqrt(np.mean(r.speed_ref ** 2))
    assert r.noise_floor == pytest.approx(20.0 * math.sqrt(0.005 ** 2 + 1e-8 / 12))
    assert scenario("standard", axis="linear").truth.axis == "linear"


# --------------------------------------------------------------------------- reproducibility


def test_same_seed_same_output_and_different_seed_differs() -> None:
    a = simulate("standard", effects=ALL, duration=2.0, seed=11)
    b = simulate("standard", effects=ALL, duration=2.0, seed=11)
    c = simulate("standard", effects=ALL, duration=2.0, seed=12)
    for name in ("current", "speed", "position", "voltage"):
        assert np.array_equal(getattr(a.measured, name), getattr(b.measured, name))
        assert np.array_equal(getattr(a.true, name), getattr(b.true, name))
    assert np.array_equal(a.frames.data, b.frames.data)
    assert not np.array_equal(a.measured.current, c.measured.current)


def test_output_does_not_depend_on_chunking() -> None:
    sc = scenario("standard", effects=ALL, duration=3.0, seed=3, faults="drop=0.0")
    whole = simulate(sc)
    sim = Simulator(sc)
    parts = [sim.step(n) for n in (1, 999, 1234, 5000)]
    assert sum(len(p) for p in parts) == 3000
    for name in ("current", "speed", "position", "voltage"):
        got = np.concatenate([getattr(p.measured, name) for p in parts])
        assert np.array_equal(got, getattr(whole.measured, name))
    assert np.array_equal(np.concatenate([p.true.t for p in parts]), whole.true.t)


# --------------------------------------------------------------------------- truth, scenario


#: (effects, axis, sensors, band, offset of the speed reference) of the digest runs: every
#: term of the loop, the electrical equation and the ideal current source, the stiff
#: zone at standstill, a linear axis, sensors without quantisation
PLANT_RUNS = [
    ("inertia,viscous", "rotary", Sensors(), 1e-3, 0.0),
    ("inertia,viscous,coulomb,offset", "rotary", Sensors(), 1e-3, 5.0),
    ("inertia,viscous,coulomb,stribeck,offset,unbalance,cogging:6,cogging:24", "linear",
     Sensors(), 0.05, 0.0),
    ("inertia,viscous,coulomb,electrical", "rotary",
     Sensors(current_step=0.0, speed_step=0.0, position_step=0.0, position_noise=0.01),
     1e-3, 0.0),
    ("inertia,stribeck,unbalance,electrical,cogging:3", "linear", Sensors(), 1e-3, 5.0),
]


def plant_digest(run: Callable[..., Any]) -> str:
    """SHA-256 of the loop's outputs and final states over :data:`PLANT_RUNS` (seeded
    parameters and noise, 3,000 periods each in blocks of 1, 999 and 2,000)."""
    h = hashlib.sha256()
    for k, (effects, axis, sensors, band, offset) in enumerate(PLANT_RUNS):
        rng = np.random.default_rng(k)
        params = {f"{e}.{s}": float(rng.uniform(0.01, 0.5)) * (1e-3 if s == "J" else 1.0)
                  for e in parse_effects(effects) for s in EFFECT_PARAMS[e.split(":")[0]]}
        params.update({p: v for p, v in (("electrical.R", 0.5), ("electrical.L", 1e-3),
                                         ("electrical.Ke", 0.1)) if p in params})
        truth = Truth(params, axis=axis, pitch=0.05 if axis == "linear" else 1.0,
                      coulomb_band=band)
        plant = Plant(truth, sensors=sensors, seed=k)
        t = np.arange(3000) * 1e-3
        w = 30.0 * np.sin(2 * np.pi * 0.7 * t) + offset
        a = 30.0 * 2 * np.pi * 0.7 * np.cos(2 * np.pi * 0.7 * t)
        for s in (slice(0, 1), slice(1, 1000), slice(1000, 3000)):
            n = s.stop - s.start
            noise = rng.standard_normal((n, 3)) * np.array([0.005, 0.02, 0.001])
            out = np.empty((n, 9))
            run(plant.dt, plant.nsub, plant.h_stiff, plant._state, plant._p, plant._ck,
                plant._cs, plant._cc, plant._gains, plant._quant, *plant._ff,
                np.ascontiguousarray(w[s]), np.ascontiguousarray(a[s]), noise, out)
            h.update(out.tobytes())
        h.update(plant._state.tobytes())
    return h.hexdigest()[:16]


def test_the_c_loop_gives_the_numba_loops_bits() -> None:
    """The simulated drive's loop in C (``canrls._sim``) gives, bit for bit, what the numba
    kernel it replaces gave (f79833d: ``canrls.sim.plant._run``); the simulated logs that
    tests keep as goldens are unchanged."""
    assert plant_digest(_sim.plant_run) == "82cb553671107f57"


def test_the_loop_refuses_wrong_arrays() -> None:
    plant = Plant(Truth({"inertia.J": 1e-4}))
    args = [plant.dt, plant.nsub, plant.h_stiff, plant._state, plant._p, plant._ck, plant._cs,
            plant._cc, plant._gains, plant._quant, *plant._ff, np.zeros(4), np.zeros(4),
            np.zeros((4, 3)), np.empty((4, 9))]
    _sim.plant_run(*args)
    for k, bad, err, msg in ((15, np.empty((3, 9)), ValueError, "out must have shape"),
                             (14, np.zeros((4, 2)), ValueError, "noise must have shape"),
                             (4, np.zeros(14), ValueError, "p must have shape"),
                             (10, np.zeros(7), ValueError, "ffv must have shape"),
                             (12, np.zeros(4, np.float32), TypeError, "w_ref must be a float64"),
                             (1, 0, ValueError, "nsub")):
        with pytest.raises(err, match=msg):
            _sim.plant_run(*args[:k], bad, *args[k + 1:])


def test_truth_and_effect_validation() -> None:
    assert parse_effects("cogging:24, inertia,viscous") == ("inertia", "viscous", "cogging:24")
    with pytest.raises(EffectError, match="cogging:K"):
        scenario("standard", effects="inertia,cogging")
    with pytest.raises(EffectError, match="friction"):
        scenario("standard", effects="inertia,friction")
    with pytest.raises(EffectError, match="inertia"):
        scenario("standard", effects="viscous,coulomb")
    with pytest.raises(EffectError, match="stribeck.Ts"):
        scenario("standard", effects="inertia,coulomb", params={"stribeck.Ts": 0.1})
    with pytest.raises(ConfigError, match="unknown scenario"):
        scenario("turbo")
    with pytest.raises(ConfigError, match="axis"):
        scenario("standard", axis="spiral")
    sc = scenario("standard", effects="inertia,coulomb,cogging:6", params={"coulomb.Tc": 0.05,
                                                                           "cogging:6.cos": 0.0})
    assert dict(sc.truth.params) == {"inertia.J": 2e-4, "coulomb.Tc": 0.05,
                                     "cogging:6.sin": 0.003, "cogging:6.cos": 0.0}
    assert sc.truth.divided_by_kt()["coulomb.Tc"] == pytest.approx(0.5)
    assert "coulomb.Tc=0.05" in sc.truth.summary()


# --------------------------------------------------------------------------- excitation


@pytest.mark.parametrize("name", sorted(PRESETS))
def test_presets_are_finite_and_accel_is_the_derivative(name: str) -> None:
    ex = excitation(name)
    t = np.arange(0.0, 90.0, 1e-4)
    w, a = ex.reference(t)
    assert np.all(np.isfinite(w)) and np.all(np.isfinite(a))
    assert w[0] == pytest.approx(0.0, abs=1e-9)  # starts at rest
    # a is dw/dt wherever w is smooth (away from the breakpoints of ramps)
    num = np.diff(w) / 1e-4
    mid = 0.5 * (a[:-1] + a[1:])
    smooth = np.abs(np.diff(a)) < 1.0
    assert np.allclose(num[smooth], mid[smooth], rtol=1e-3, atol=0.05)


def test_standard_profile_excites_everything() -> None:
    ex = excitation("standard")
    assert ex.period is not None and 35 < ex.period < 50
    t = np.arange(0.0, ex.period, 1e-3)
    w, a = ex.reference(t)
    assert w.max() >= 100 and w.min() <= -100  # fast, both directions
    slow = (np.abs(w) > 0.2) & (np.abs(w) < 1.0)
    assert slow.mean() > 0.1  # slow phases
    assert np.abs(a).max() > 1000  # accelerations for inertia
    assert np.sum(np.abs(w)) * 1e-3 / (2 * np.pi) > 50  # many revolutions
    crossings = np.count_nonzero(np.diff(np.sign(w[np.abs(w) > 1e-9])))
    assert crossings > 100
    # periodic and continuous where it repeats
    w2, _ = ex.reference(t + ex.period)
    assert np.allclose(w, w2, atol=1e-9)


def test_poor_profile_one_direction_constant() -> None:
    w, a = excitation("poor").reference(np.arange(1.0, 100.0, 0.01))
    assert np.all(w == 20.0) and np.all(a == 0.0)


def test_excitation_composition_and_scaling() -> None:
    s = excitation("reversals+prbs", scale=0.5)
    w, _ = s.reference(np.array([0.5]))
    w1, _ = excitation("reversals").reference(np.array([0.5]))
    w2, _ = excitation("prbs").reference(np.array([0.5]))
    assert w[0] == pytest.approx(0.5 * (w1[0] + w2[0]))
    c = chirp(1.0, 0.3, 7.0, 3.0)
    assert (c.f0 + c.f1) / 2 * c.sweep_time == pytest.approx(round((c.f0 + c.f1) / 2 * 3.0))
    assert np.array_equal(prbs(1.0, seed=1).speeds, prbs(1.0, seed=1).speeds)
    assert not np.array_equal(prbs(1.0, seed=1).speeds, prbs(1.0, seed=2).speeds)
    assert reversals(10.0, 100.0, 1.0).period == pytest.approx(2.4)
    with pytest.raises(ConfigError, match="unknown profile"):
        excitation("wiggle")


# --------------------------------------------------------------------------- speed


@pytest.mark.slow
def test_one_hour_simulates_fast() -> None:
    """Benchmark: one hour at 1 kHz (3.6 M periods). Timing is printed, never asserted."""
    sc = scenario("standard", duration=3600.0, seed=1)  # inertia,viscous,coulomb
    sim = Simulator(sc)
    sim.step(10)  # the first call (imports, first touch of the arrays)
    t0 = time.perf_counter()
    peak = 0.0
    for c in sim.chunks(262144):
        peak = max(peak, float(np.abs(c.true.speed).max()))
    el = time.perf_counter() - t0
    print(f"\n1 h of the standard drive ({','.join(sc.truth.effects)}): {el:.1f} s, "
          f"{(sc.periods - 10) / el / 1e6:.2f} M periods/s")
    assert sim.remaining == 0 and 99 < peak < 102
