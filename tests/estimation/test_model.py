"""The model: configuration, validation, equations, and exact regressors on synthetic data."""

from __future__ import annotations

import logging
import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from canrls.core.errors import ConfigError, EffectError, ExpressionError, SignalError
from canrls.core.samples import Signals
from canrls.estimation.equation import PositionUnwrapper, RegressorBlock
from canrls.estimation.model import Model
from canrls.processor.config import load_model

DT = 1e-3
N = 20000
SKIP = 1000  # samples of filter transient left out of the fits
BAND, WS = 0.01, 1.0


# --------------------------------------------------------------------- synthetic data
def profile(scale: float = 1.0, n: int = N) -> dict[str, np.ndarray]:
    """A smooth speed profile crossing zero: speed, its derivatives and its integral."""
    t = np.arange(n) * DT
    w = np.full(n, 3.0 * scale)
    wd = np.zeros(n)
    wdd = np.zeros(n)
    th = 0.4 + 3.0 * scale * t
    for a, f, ph in ((20.0, 0.5, 0.0), (5.0, 1.7, 0.3), (2.0, 3.1, 1.1)):
        a *= scale
        om = 2 * np.pi * f
        w += a * np.sin(om * t + ph)
        wd += a * om * np.cos(om * t + ph)
        wdd -= a * om * om * np.sin(om * t + ph)
        th += a / om * (np.cos(ph) - np.cos(om * t + ph))
    return {"t": t, "w": w, "wd": wd, "wdd": wdd, "th": th}


ROTARY = {"inertia.J": 2e-3, "viscous.B": 1e-3, "coulomb.Tc": 0.05, "stribeck.Ts": 0.02,
          "offset.T0": 0.01, "unbalance.sin": 0.03, "unbalance.cos": -0.02,
          "cogging:24.sin": 0.004, "cogging:24.cos": 0.006}
ROTARY_EFFECTS = ["inertia", "viscous", "coulomb", "stribeck", "offset", "unbalance",
                  "cogging:24"]


def torque(p: dict[str, float], d: dict[str, np.ndarray], angle: np.ndarray,
           cog: int = 24, scale: float = 1.0) -> np.ndarray:
    """The mechanical convention of docs/architecture.md, written out independently."""
    w = d["w"]
    sg = np.tanh(w / BAND)
    return (p["inertia.J"] * d["wd"] + p["viscous.B"] * w + p["coulomb.Tc"] * sg
            + p["stribeck.Ts"] * sg * np.exp(-(w / (WS * scale)) ** 2) + p["offset.T0"]
            + p["unbalance.sin"] * np.sin(angle) + p["unbalance.cos"] * np.cos(angle)
            + p[f"cogging:{cog}.sin"] * np.sin(cog * angle)
            + p[f"cogging:{cog}.cos"] * np.cos(cog * angle))


def fit(model: Model, signals: Signals, eq: str = "mechanical") -> dict[str, float]:
    e = model.equation(eq)
    blk = e.builder(DT).process(signals)
    theta, *_ = np.linalg.lstsq(blk.phi[SKIP:], blk.y[SKIP:], rcond=None)
    return dict(zip([p.name for p in e.parameters], e.to_physical(theta), strict=True))


def assert_params(est: dict[str, float], true: dict[str, float], rtol: float = 1e-6) -> None:
    assert set(est) == set(true)
    for k, v in true.items():
        assert est[k] == pytest.approx(v, rel=rtol), (k, est[k], v)


def rotary_signals(kt: float = 0.1) -> Signals:
    d = profile()
    tau = torque(ROTARY, d, d["th"])
    pos = np.mod(d["th"], 2 * np.pi)  # single turn in [0, 2 pi)
    return Signals(d["t"], tau / kt, d["w"], pos)


RANGES = {"current": [-8.0, 8.0], "speed": [-40.0, 40.0]}


# -------------------------------------------------------------------- exact regression
@pytest.mark.parametrize("kt", [0.1, None])
def test_rotary_regression_is_exact(kt: float | None) -> None:
    model = Model(ROTARY_EFFECTS, kt=kt, ranges=RANGES, coulomb_band=BAND, stribeck_speed=WS)
    est = fit(model, rotary_signals(0.1))
    expected = ROTARY if kt is not None else {k: v / 0.1 for k, v in ROTARY.items()}
    assert_params(est, expected)


@pytest.mark.parametrize("kt", [250.0, None])
def test_linear_regression_is_exact(kt: float | None) -> None:
    pitch = 0.012
    scale = 0.01  # m/s instead of rad/s
    d = profile(scale)
    p = {"inertia.J": 3.5, "viscous.B": 20.0, "coulomb.Tc": 4.0, "stribeck.Ts": 1.5,
         "offset.T0": -2.0, "unbalance.sin": 0.8, "unbalance.cos": 0.5,
         "cogging:3.sin": 0.3, "cogging:3.cos": -0.2}
    angle = 2 * np.pi * d["th"] / pitch
    force = torque(p, d, angle, cog=3, scale=scale)
    kf = 250.0
    s = Signals(d["t"], force / kf, d["w"], d["th"])
    effects = ["inertia", "viscous", "coulomb", "stribeck", "offset", "unbalance", "cogging:3"]
    model = Model(effects, axis="linear", pitch=pitch, kt=kt, coulomb_band=BAND,
                  stribeck_speed=WS * scale, ranges={"current": [-4, 4], "speed": [-0.4, 0.4]})
    expected = p if kt is not None else {k: v / kf for k, v in p.items()}
    assert_params(fit(model, s), expected)
    units = [q.unit for q in model.equations[0].parameters]
    assert units[:3] == (["kg", "N·s/m", "N"] if kt else ["A·s²/m", "A·s/m", "A"])


def test_electrical_and_mechanical_equations_with_voltage() -> None:
    d = profile()
    kt, J, B, T0 = 0.08, 2e-3, 1e-3, 0.02
    R, L, Ke = 0.4, 1.2e-3, 0.07
    i = (J * d["wd"] + B * d["w"] + T0) / kt
    di = (J * d["wdd"] + B * d["wd"]) / kt
    c_rv = 0.05
    u = R * i + L * di + Ke * d["w"] + c_rv * i * np.abs(i)
    s = Signals(d["t"], i, d["w"], None, u)
    terms = [{"name": "rv", "expr": "i * abs(i)", "unit": "A²", "equation": "electrical"}]
    # u here is the instantaneous value of a smooth voltage, not held: held = []
    model = Model(["inertia", "viscous", "offset", "electrical", "user:rv"], kt=kt,
                  terms=terms, ranges={"current": [-8, 8], "speed": [-40, 40],
                                       "voltage": [-10, 10]},
                  available_signals=["voltage"], held=[])
    assert [e.name for e in model.equations] == ["mechanical", "electrical"]
    elec = model.equation("electrical")
    assert elec.output.unit == "V" and elec.index == 1
    assert [p.unit for p in elec.parameters] == ["Ohm", "H", "V·s/rad", "V/A²"]
    assert_params(fit(model, s), {"inertia.J": J, "viscous.B": B, "offset.T0": T0})
    assert_params(fit(model, s, "electrical"),
                  {"electrical.R": R, "electrical.L": L, "electrical.Ke": Ke, "user:rv.c": c_rv})


def test_user_term_is_identified() -> None:
    d = profile()
    tau = 2e-3 * d["wd"] + 1e-4 * d["w"] * np.abs(d["w"]) + 0.01 * np.sin(3 * d["th"]) * d["w"]
    s = Signals(d["t"], tau, d["w"], np.mod(d["th"] + np.pi, 2 * np.pi) - np.pi)
    terms = {"drag": {"expr": "omega * abs(omega)", "unit": "rad²/s²"},
             "wobble": {"expr": "sin(3 * theta) * omega", "unit": "rad/s"}}
    model = Model(["inertia", "user:drag", "user:wobble"], kt=1.0, terms=terms, ranges=RANGES)
    eq = model.equations[0]
    assert [p.unit for p in eq.parameters] == ["kg·m²", "N·m/(rad²/s²)", "N·m/(rad/s)"]
    assert_params(fit(model, s), {"inertia.J": 2e-3, "user:drag.c": 1e-4,
                                  "user:wobble.c": 0.01})


def test_electrical_only_model_and_filter_options() -> None:
    d = profile()
    i = 3 * np.sin(2 * np.pi * 2 * d["t"])
    di = 12 * np.pi * np.cos(2 * np.pi * 2 * d["t"])
    u = 0.3 * i + 2e-3 * di + 0.05 * d["w"]
    model = Model(["electrical"], cutoff_hz=40.0, zeta=1.0, ranges=RANGES, held=())
    assert [e.name for e in model.equations] == ["electrical"]
    assert_params(fit(model, Signals(d["t"], i, d["w"], None, u), "electrical"),
                  {"electrical.R": 0.3, "electrical.L": 2e-3, "electrical.Ke": 0.05})


# ------------------------------------------------- held signals (zero-order hold)
def _fit_arrays(model: Model, s: Signals, eq: str = "mechanical") -> np.ndarray:
    e = model.equation(eq)
    blk = e.builder(DT).process(s)
    theta, *_ = np.linalg.lstsq(blk.phi[SKIP:], blk.y[SKIP:], rcond=None)
    return e.to_physical(theta)


def test_held_current_is_filtered_with_a_zero_order_hold() -> None:
    """An ideal current source: i[k] acts over [t_k, t_k + dt) (the simulated drive)."""
    t = np.arange(N) * DT
    J, B, T0, kt = 2e-3, 1e-3, 0.01, 0.1
    i = (2 * np.sin(2 * np.pi * 0.7 * t) + 0.8 * np.sin(2 * np.pi * 3.3 * t + 1)
         + 0.3 * np.sign(np.sin(2 * np.pi * 0.2 * t)))
    # exact solution of J w' = Kt i[k] - B w - T0 over each period
    decay = math.exp(-B / J * DT)
    w = np.zeros(N)
    for k in range(N - 1):
        w_inf = (kt * i[k] - T0) / B
        w[k + 1] = w_inf + (w[k] - w_inf) * decay
    s = Signals(t, i, w)
    true = np.array([J, B, T0])
    kw: dict[str, Any] = {"kt": kt, "ranges": {"current": [-4, 4], "speed": [-200, 200]}}
    held = Model(["inertia", "viscous", "offset"], held=["current"], **kw)
    assert held.equations[0].holds == ("zoh", "foh", "foh", "foh")
    np.testing.assert_allclose(_fit_arrays(held, s), true, rtol=1e-5)
    sampled = Model(["inertia", "viscous", "offset"], **kw)
    assert abs(_fit_arrays(sampled, s)[1] / B - 1) > 1e-3  # half a sample off: biased


def test_held_voltage_is_filtered_with_a_zero_order_hold() -> None:
    """An inverter: u[k] acts over [t_k, t_k + dt); the current is a sampled state."""
    t = np.arange(N) * DT
    R, L, Ke = 0.4, 1.2e-3, 0.07
    comps = ((20.0, 0.5, 0.0), (5.0, 1.7, 0.3))
    w = sum(a * np.sin(2 * np.pi * f * t + ph) for a, f, ph in comps)
    u = 3 * np.sin(2 * np.pi * 2 * t) + 1.5 * np.sin(2 * np.pi * 9 * t + 0.5) + Ke * w

    def i_emf(tt: float) -> float:
        """Particular solution of L i' + R i = -Ke w(t)."""
        return sum(-Ke * a * (np.exp(1j * (2 * np.pi * f * tt + ph))
                              / (R + 2j * np.pi * f * L)).imag for a, f, ph in comps)

    decay = math.exp(-R / L * DT)
    i = np.zeros(N)
    for k in range(N - 1):
        c = i[k] - i_emf(t[k]) - u[k] / R
        i[k + 1] = i_emf(t[k + 1]) + u[k] / R + c * decay
    s = Signals(t, i, w, None, u)
    kw: dict[str, Any] = {"ranges": {"current": [-30, 30], "speed": [-40, 40],
                                     "voltage": [-10, 10]}}
    est = _fit_arrays(Model(["electrical"], **kw), s, "electrical") / np.array([R, L, Ke]) - 1
    # the current ripple the held voltage causes between samples limits L to about 1 %
    assert abs(est[0]) < 1e-3 and abs(est[1]) < 2e-2 and abs(est[2]) < 1e-5
    wrong = _fit_arrays(Model(["electrical"], held=[], **kw), s, "electrical")
    assert abs(wrong[1] / L - 1) > 0.1


# ------------------------------------------------------------------ chunk invariance
def _run(builder: Any, s: Signals, cuts: list[int]) -> RegressorBlock:
    edges = [0, *sorted(c % (len(s) + 1) for c in cuts), len(s)]
    parts = [builder.process(s.slice(a, b)) for a, b in zip(edges[:-1], edges[1:], strict=True)]
    return RegressorBlock(np.vstack([p.phi for p in parts]), np.concatenate([p.y for p in parts]),
                          np.concatenate([p.t for p in parts]))


CHUNK_MODEL = Model(ROTARY_EFFECTS + ["user:k"], kt=0.1, ranges=RANGES,
                    terms={"k": {"expr": "theta * 1e-3 + i * omega", "range": [-1e3, 1e3]}})
CHUNK_SIGNALS = rotary_signals().slice(0, 3000)


@settings(max_examples=25, deadline=None)
@given(st.lists(st.integers(0, 3000), max_size=10))
def test_any_chunking_gives_bit_identical_regressors(cuts: list[int]) -> None:
    eq = CHUNK_MODEL.equations[0]
    one = eq.builder(DT).process(CHUNK_SIGNALS)
    many = _run(eq.builder(DT), CHUNK_SIGNALS, cuts)
    assert np.array_equal(one.phi, many.phi)
    assert np.array_equal(one.y, many.y)
    assert one.phi.dtype == np.float64 and one.phi.shape == (3000, eq.n)


def test_sample_by_sample_is_bit_identical_and_reset_restarts() -> None:
    eq = CHUNK_MODEL.equations[0]
    s = CHUNK_SIGNALS.slice(0, 400)
    one = eq.builder(DT).process(s)
    b = eq.builder(DT)
    rows = _run(b, s, list(range(400)))
    assert np.array_equal(one.phi, rows.phi) and np.array_equal(one.y, rows.y)
    b.reset()
    again = b.process(s)
    assert np.array_equal(one.phi, again.phi)
    assert len(b.process(s.slice(0, 0))) == 0


def test_a_non_finite_value_never_enters_the_filter() -> None:
    """log(omega) is -inf at rest and nan backwards: each such value is replaced by the
    last finite value of its column (0 before any, carried between blocks) and its row
    marked; the output stays finite, and any chunking gives the same bits."""
    model = Model(["inertia", "user:lg"], kt=0.1, ranges=RANGES,
                  terms={"lg": {"expr": "log(omega)", "range": [-10.0, 10.0]}})
    eq = model.equations[0]
    s = CHUNK_SIGNALS.slice(0, 2000)
    speed = np.asarray(s.speed, dtype=np.float64).copy()
    speed[[5, 6, 700]] = 0.0
    s = Signals(s.t, s.current, speed, s.position, s.voltage)
    one = eq.builder(DT).process(s)
    bad = ~(speed > 0)
    assert bad.any() and (~bad).any()
    assert one.nonfinite is not None and np.array_equal(one.nonfinite, bad)
    assert np.isfinite(one.phi).all() and np.isfinite(one.y).all()
    for cuts in ([1, 6, 7, 699, 701], list(range(0, 2000, 37))):
        many = _run(eq.builder(DT), s, cuts)
        assert np.array_equal(one.phi, many.phi) and np.array_equal(one.y, many.y)
    # what the filter saw: the last finite log(omega) before each bad row
    col = np.log(np.where(speed > 0, speed, np.nan))
    last = np.maximum.accumulate(np.where(np.isfinite(col), np.arange(len(col)), -1))
    seen = np.where(last >= 0, col[np.maximum(last, 0)], 0.0)
    ref = Model(["inertia", "user:x"], kt=0.1, ranges=RANGES,
                terms={"x": {"expr": "omega", "range": [-10.0, 10.0]}}).equations[0]
    want = ref.builder(DT).process(Signals(s.t, s.current, seen, s.position, s.voltage))
    assert np.array_equal(one.phi[:, 1], want.phi[:, 1]) and np.array_equal(one.y, want.y)
    assert eq.builder(DT).process(CHUNK_SIGNALS.slice(0, 50)).nonfinite is None


def test_position_conventions_single_turn_and_multi_turn_agree() -> None:
    d = profile(n=6000)
    model = Model(["unbalance", "cogging:5", "user:p"], ranges=RANGES,
                  terms={"p": {"expr": "theta", "range": [-300, 300]}})
    eq = model.equations[0]
    blocks = []
    for pos in (d["th"], np.mod(d["th"], 2 * np.pi), np.mod(d["th"] + np.pi, 2 * np.pi) - np.pi):
        s = Signals(d["t"], d["w"] * 0, d["w"], pos)
        blocks.append(_run(eq.builder(DT), s, [777, 2001, 2002, 4500]))
    for b in blocks[1:]:
        np.testing.assert_allclose(b.phi[:, :4], blocks[0].phi[:, :4], atol=1e-9)
    # the user term sees the unwrapped position (up to the 2 pi offset of the start)
    offsets = [b.phi[:, 4] - blocks[0].phi[:, 4] for b in blocks[1:]]
    for off in offsets:
        assert np.ptp(off) < 1e-9


def test_unwrapper_counts_turns_across_blocks() -> None:
    th = np.linspace(0, 40 * np.pi, 5001)
    u = PositionUnwrapper(2 * np.pi)
    wrapped = np.mod(th, 2 * np.pi)
    out = np.concatenate([u.process(wrapped[a:a + 333]) for a in range(0, 5001, 333)])
    np.testing.assert_allclose(out, th, atol=1e-9)
    assert u.turns == 20 or u.turns == 19
    lin = PositionUnwrapper(None)
    x = np.array([0.1, 0.9, 0.05])
    assert np.array_equal(lin.process(x), x)
    w = PositionUnwrapper(0.5)
    np.testing.assert_allclose(w.process(np.array([0.4, 0.45, 0.02, 0.1])),
                               [0.4, 0.45, 0.52, 0.6])


def test_linear_wrap_period_is_applied() -> None:
    d = profile(scale=0.01, n=3000)
    x = d["th"] - 0.4
    model = Model(["user:x"], axis="linear", wrap=0.05, ranges={"speed": [-1, 1]},
                  terms={"x": {"expr": "x", "range": [-1, 1]}})
    s = Signals(d["t"], x * 0, d["w"], np.mod(x, 0.05))
    blk = model.equations[0].builder(DT).process(s)
    ref = Model(["user:x"], axis="linear", ranges={"speed": [-1, 1]},
                terms={"x": {"expr": "x", "range": [-1, 1]}})
    blk2 = ref.equations[0].builder(DT).process(Signals(d["t"], x * 0, d["w"], x))
    np.testing.assert_allclose(blk.phi, blk2.phi, atol=1e-12)


# -------------------------------------------------------------------------- scaling
def test_scaling_keeps_regressors_within_one_and_maps_back_exactly() -> None:
    model = Model(ROTARY_EFFECTS, kt=0.1, ranges=RANGES)
    eq = model.equations[0]
    blk = eq.builder(DT).process(rotary_signals())
    assert np.max(np.abs(blk.phi)) <= 1.0 and np.max(np.abs(blk.y)) <= 1.0
    sc = eq.scaling
    for b, s in zip(sc.column_bounds, sc.columns, strict=True):
        assert b <= 2.0**s < 2 * b or (b <= 1 and s == 0)
    theta = np.random.default_rng(0).normal(size=eq.n)
    phys = eq.to_physical(theta)
    assert np.array_equal(phys, theta * 2.0 ** (sc.output - np.array(sc.columns)))
    assert np.array_equal(eq.to_normalised(phys), theta)
    assert np.array_equal(eq.sigma_to_physical(np.abs(theta)), np.abs(phys))
    assert eq.to_physical(np.tile(theta, (3, 1))).shape == (3, eq.n)
    assert eq.output_to_physical(0.5) == 0.5 * 2.0**sc.output
    # the inertia column (sF of speed) is bounded by the documented SF gain
    from canrls.estimation.svf import gain_bounds
    assert sc.column_bounds[0] == pytest.approx(gain_bounds(25.0)[1] * 40.0)


def test_worst_case_inputs_stay_within_one() -> None:
    model = Model(["inertia", "viscous", "coulomb", "offset", "cogging:2"], kt=0.1,
                  ranges=RANGES)
    eq = model.equations[0]
    rng = np.random.default_rng(2)
    n = 20000
    t = np.arange(n) * DT
    sw = np.where(np.sin(2 * np.pi * 25 * t) > 0, 40.0, -40.0)  # bang-bang at the cutoff
    s = Signals(t, np.where(rng.random(n) < 0.5, -8.0, 8.0), sw, rng.uniform(0, 6.28, n))
    blk = eq.builder(DT).process(s)
    assert np.max(np.abs(blk.phi)) <= 1.0 and np.max(np.abs(blk.y)) <= 1.0


def test_derivative_range_tightens_the_inertia_scaling() -> None:
    wide = Model(["inertia"], ranges=RANGES).equations[0].scaling.columns[0]
    tight = Model(["inertia"], ranges={**RANGES, "acceleration": [-100, 100]}
                  ).equations[0].scaling.columns[0]
    assert tight == 7 and wide == 13


# --------------------------------------------------------------- configuration files
GOOD = """
[model]
axis = "rotary"
kt = 0.12
effects = ["inertia", "viscous", "coulomb", "cogging:24", "user:drag"]

[model.filter]
cutoff_hz = 30.0
zeta = 0.8

[model.coulomb]
band = 0.02

[model.stribeck]
speed = 2.0

[[model.terms]]
name = "drag"
expr = "omega * abs(omega)"
unit = "rad²/s²"

[model.ranges]
current = [-20.0, 20.0]
speed = [-300.0, 300.0]
voltage = [-48.0, 48.0]

[bus]
interface = "virtual"
"""


def _write(tmp_path: Path, text: str, name: str = "drive.toml") -> Path:
    p = tmp_path / name
    p.write_text(text, encoding="utf-8")
    return p


def test_from_toml_builds_the_documented_schema(tmp_path: Path) -> None:
    m = load_model(_write(tmp_path, GOOD))
    assert m.effect_names == ("inertia", "viscous", "coulomb", "cogging:24", "user:drag")
    assert (m.kt, m.cutoff_hz, m.zeta, m.coulomb_band, m.stribeck_speed) == (
        0.12, 30.0, 0.8, 0.02, 2.0)
    assert m.held == {"voltage"} and m.held_list == ["voltage"]
    assert m.ranges["speed"] == (-300.0, 300.0)
    assert m.source.endswith("drive.toml")
    eq = m.equations[0]
    assert eq.output.unit == "N·m" and eq.output.gain == 0.12
    assert [p.name for p in eq.parameters] == ["inertia.J", "viscous.B", "coulomb.Tc",
                                               "cogging:24.sin", "cogging:24.cos", "user:drag.c"]
    assert [p.effect_id for p in eq.parameters] == [1, 2, 3, 7, 7, 9]
    assert m.active_effects == 0b101000111
    assert Model.from_dict(m.to_dict()) == m
    assert "inertia" in repr(m) and "mechanical" in repr(eq)


def test_programmatic_model_defaults() -> None:
    m = Model(["offset"])
    assert m.kt is None and m.axis == "rotary"
    eq = m.equations[0]
    assert eq.output.unit == "A" and eq.parameters[0].unit == "A"
    lin = Model(["viscous"], axis="linear")
    assert lin.ranges["speed"] == (-1.0, 1.0)
    assert lin.parameters[0].description == "viscous friction coefficient"
    with pytest.raises(KeyError, match="electrical"):
        m.equation("electrical")


BAD_CASES = [
    ('effects = ["inertia", "friction"]', EffectError,
     ["model.effects[1]", "'friction'", "cogging:K"]),
    ('effects = ["cogging"]', EffectError, ["model.effects[0]", "'cogging'", "cogging:K"]),
    ('effects = ["inertia", "inertia"]', EffectError, ["model.effects[1]", "duplicate"]),
    ('effects = ["user:wind"]', EffectError, ["model.effects[0]", "'wind'"]),
    ('effects = "inertia"', ConfigError, ["model.effects", "'inertia'", "list"]),
    ('effects = []', ConfigError, ["model.effects", "no effects"]),
    ('effects = ["inertia"]\nspeed_limit = 3', ConfigError, ["model.speed_limit", "3"]),
    ('effects = ["inertia"]\naxis = "planar"', ConfigError, ["model.axis", "'planar'"]),
    ('effects = ["inertia"]\nkt = 0', ConfigError, ["model.kt", "0"]),
    ('effects = ["inertia"]\nkt = "big"', ConfigError, ["model.kt", "'big'"]),
    ('effects = ["inertia"]\nwrap = 0.5', ConfigError, ["model.wrap", "0.5", "linear"]),
    ('effects = ["inertia"]\n[model.filter]\ncutoff_hz = -5.0', ConfigError,
     ["model.filter.cutoff_hz", "-5.0"]),
    ('effects = ["inertia"]\n[model.filter]\ncutoff_hz = 0', ConfigError,
     ["model.filter.cutoff_hz", "= 0"]),
    ('effects = ["inertia"]\n[model.filter]\norder = 2', ConfigError,
     ["model.filter.order", "2"]),
    ('effects = ["inertia"]\n[model.filter]\nheld = ["pressure"]', ConfigError,
     ["model.filter.held", "'pressure'"]),
    ('effects = ["inertia"]\n[model.filter]\nheld = "voltage"', ConfigError,
     ["model.filter.held", "'voltage'", "list"]),
    ('effects = ["coulomb"]\n[model.coulomb]\nband = 0.0', ConfigError,
     ["model.coulomb.band", "0.0"]),
    ('effects = ["coulomb"]\n[model.coulomb]\nband = -0.1', ConfigError,
     ["model.coulomb.band", "-0.1"]),
    ('effects = ["stribeck"]\n[model.stribeck]\nspeed = 0', ConfigError,
     ["model.stribeck.speed", "0"]),
    ('effects = ["inertia"]\n[model.ranges]\ncurrent = [5, -5]', ConfigError,
     ["model.ranges.current", "[5, -5]"]),
    ('effects = ["inertia"]\n[model.ranges]\npressure = [0, 1]', ConfigError,
     ["model.ranges.pressure"]),
    ('effects = ["inertia"]\noutput = "force"', ConfigError, ["model.output", "'force'"]),
    ('effects = ["inertia"]\noutput = "torque"\nkt = 0.1', ConfigError,
     ["model.kt", "the torque the drive reports", "Kt is not used"]),
    ('effects = ["inertia"]\n[model.ranges]\nspeed = 100', ConfigError,
     ["model.ranges.speed", "100"]),
    ('effects = ["user:w"]\n[[model.terms]]\nname = "w"\nexpr = "import os"', ExpressionError,
     ["model.terms[0]", "'w'", "syntax"]),
    ('effects = ["user:w"]\n[[model.terms]]\nname = "w"\nexpr = "omega.real"', ExpressionError,
     ["model.terms[0]", "'omega.real'", "column 1"]),
    ('effects = ["inertia"]\n[[model.terms]]\nname = "w"\nexpr = "1"\ncolor = 1', ConfigError,
     ["model.terms[0].color"]),
    ('effects = ["inertia"]\n[[model.terms]]\nname = "w"', ConfigError,
     ["model.terms[0].expr"]),
    ('effects = ["inertia"]\n[[model.terms]]\nexpr = "1"', ConfigError, ["model.terms[0]"]),
    ('effects = ["user:w"]\n[[model.terms]]\nname = "w"\nexpr = "theta"', ConfigError,
     ["user:w.c", "range"]),
    ('effects = ["inertia", "user:e"]\n[[model.terms]]\nname = "e"\nexpr = "i"\n'
     'equation = "electrical"', EffectError, ["model.effects[1]", "'user:e'", "electrical"]),
    ('axis = "rotary"', ConfigError, ["model.effects", "required"]),
]


@pytest.mark.parametrize(("body", "exc", "fragments"), BAD_CASES)
def test_configuration_errors_name_file_key_and_value(tmp_path: Path, body: str,
                                                      exc: type[Exception],
                                                      fragments: list[str]) -> None:
    path = _write(tmp_path, "[model]\n" + body + "\n", name="bad_drive.toml")
    with pytest.raises(exc) as info:
        load_model(path)
    msg = str(info.value)
    assert "bad_drive.toml" in msg
    for f in fragments:
        assert f in msg, (f, msg)


def test_missing_signals_are_reported_at_build_time(tmp_path: Path) -> None:
    path = _write(tmp_path, '[model]\neffects = ["inertia", "cogging:12", "electrical"]\n',
                  name="nopos.toml")
    with pytest.raises(EffectError) as info:
        load_model(path, available_signals=["voltage"])
    msg = str(info.value)
    assert all(f in msg for f in ("nopos.toml", "model.effects[1]", "cogging:12", "position"))
    with pytest.raises(EffectError, match=r"model.effects\[2\].*voltage"):
        load_model(path, available_signals=["position"])
    with pytest.raises(EffectError, match=r"user:th.*position"):
        Model(["user:th"], available_signals=[], terms={"th": {"expr": "sin(theta)"}})
    with pytest.raises(ConfigError, match="'pressure'"):
        Model(["inertia"], available_signals=["pressure"])
    # a drive that reports its torque: the current only when it says so
    with pytest.raises(ConfigError, match="model.output = 'current': the drive sends no "
                                          "current signal"):
        Model(["inertia"], available_signals=["torque"])
    with pytest.raises(EffectError, match=r"electrical.*needs signal\(s\) \['current'\]"):
        Model(["inertia", "electrical"], output="torque", available_signals=["torque",
                                                                            "voltage"])
    with pytest.raises(ConfigError, match="model.output = 'torque': the drive sends no "
                                          "torque signal"):
        Model(["inertia"], output="torque", available_signals=["position"])
    m = Model(["inertia", "coulomb"], output="torque", available_signals=["torque"])
    eq = m.equations[0]
    assert (eq.output.signal, eq.output.unit, eq.output.gain) == ("torque", "N·m", 1.0)
    assert [p.unit for p in m.parameters] == ["kg·m²", "N·m"] and m.torque_known
    assert Model.from_dict(m.to_dict()) == m and m.to_dict()["output"] == "torque"
    assert load_model(path, available_signals=["position", "voltage"]).equations


def test_toml_and_table_errors(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="broken.toml.*invalid TOML"):
        load_model(_write(tmp_path, "[model\n", name="broken.toml"))
    with pytest.raises(ConfigError, match="nomodel.toml.*no \\[model\\]"):
        load_model(_write(tmp_path, "[bus]\n", name="nomodel.toml"))
    with pytest.raises(ConfigError, match="missing.toml.*cannot read"):
        load_model(tmp_path / "missing.toml")
    with pytest.raises(ConfigError, match=r"cfg: model.filter = 3"):
        Model.from_dict({"effects": ["inertia"], "filter": 3}, source="cfg")


def test_nyquist_is_checked_when_the_builder_knows_dt() -> None:
    eq = Model(["inertia"], cutoff_hz=300.0, source="fast.toml").equations[0]
    eq.builder(1e-3)
    with pytest.raises(ConfigError, match=r"fast.toml: model.filter.cutoff_hz = 300.0.*Nyquist"):
        eq.builder(2e-3)


def test_blocks_without_a_required_signal_raise_signal_error() -> None:
    eq = Model(["unbalance"], source="cfg").equations[0]
    with pytest.raises(SignalError, match=r"cfg: .*'position'.*unbalance"):
        eq.builder(DT).process(Signals(np.zeros(3), np.zeros(3), np.zeros(3)))


# ---------------------------------------------------------------------- with_effects
def test_with_effects_returns_a_new_validated_model() -> None:
    base = Model(["inertia", "viscous"], kt=0.1, terms={"d": {"expr": "omega**3"}},
                 ranges=RANGES, available_signals=["position"])
    grown = base.with_effects(add=["coulomb", "cogging:6", "user:d"], remove=["viscous"])
    assert base.effect_names == ("inertia", "viscous")
    assert grown.effect_names == ("inertia", "coulomb", "cogging:6", "user:d")
    assert (grown.kt, grown.ranges, grown.source) == (base.kt, base.ranges, base.source)
    assert grown.with_effects(remove=["Cogging:6"]).effect_names == ("inertia", "coulomb",
                                                                       "user:d")
    with pytest.raises(EffectError, match="'stribeck'.*not in the model"):
        base.with_effects(remove=["stribeck"])
    with pytest.raises(EffectError, match="'inertia'.*already"):
        base.with_effects(add=["inertia"])
    with pytest.raises(EffectError, match="'friction'"):
        base.with_effects(add=["friction"])
    with pytest.raises(EffectError, match="voltage"):
        base.with_effects(add=["electrical"])
    both = base.with_effects(add=["offset"], remove=["inertia", "viscous"])
    assert both.effect_names == ("offset",)
    assert both.equations[0].n == 1


def test_effect_objects_are_accepted() -> None:
    from canrls.estimation.effects import parse_effect
    m = Model([parse_effect("inertia"), "viscous"])
    assert m.effect_names == ("inertia", "viscous")
    with pytest.raises(EffectError, match="linear"):
        Model([parse_effect("inertia", {"axis": "linear"})])
    with pytest.raises(EffectError, match=r"model.effects\[0\].*options differ"):
        Model([parse_effect("coulomb", {"band": 0.5})])
    assert Model([parse_effect("coulomb", {"band": 0.5})], coulomb_band=0.5).effects[0].band == 0.5
    with pytest.raises(EffectError, match="42"):
        Model([42])  # type: ignore[list-item]


def test_parameter_specs_carry_the_param_info_fields() -> None:
    m = Model(["electrical", "unbalance", "cogging:24"], kt=0.1)
    mech, elec = m.equations
    assert [(p.effect_id, p.component, p.order, p.equation_index) for p in mech.parameters] == [
        (6, 0, 1, 0), (6, 1, 1, 0), (7, 0, 24, 0), (7, 1, 24, 0)]
    assert [(p.effect_id, p.component, p.order, p.equation_index) for p in elec.parameters] == [
        (8, 0, 0, 1), (8, 1, 0, 1), (8, 2, 0, 1)]
    assert mech.n == 4 and elec.n == 3
    assert m.parameters == mech.parameters + elec.parameters
    assert mech.derivative_mask == (False,) * 4 and elec.derivative_mask == (False, True, False)
    assert math.isclose(mech.scaling.output_bound, 0.1 * 10.0 * 1.0903370996826590)


def test_unwrapper_gives_what_the_numpy_formulation_gives() -> None:
    """Seeded random blocks of 0..7 samples with wraps, large jumps and non-finite
    positions: the same positions, turn counts and carried sample as the numpy
    formulation of the unwrapping (before its compiled kernel)."""
    rng = np.random.default_rng(9)
    for period in (2 * np.pi, 0.5, 0.2):
        u = PositionUnwrapper(period)
        turns, last = 0, None
        for _ in range(2000):
            p = rng.uniform(-2.0, 2.0, int(rng.integers(0, 8))) * period
            if len(p) and rng.random() < 0.2:
                p[rng.integers(0, len(p))] = rng.choice([np.nan, np.inf, -np.inf, 1e6])
            got = u.process(p)
            if len(p) == 0:
                assert len(got) == 0
                continue
            prev = np.concatenate([[p[0] if last is None else last], p[:-1]])
            with np.errstate(invalid="ignore"):
                d = p - prev
            ok = np.isfinite(d)
            jumps = np.zeros(len(p), dtype=np.int64)
            jumps[ok] = -np.rint(d[ok] / period).astype(np.int64)
            tn = turns + np.cumsum(jumps)
            turns = int(tn[-1])
            last = float(p[-1]) if math.isfinite(p[-1]) else last
            assert got.tobytes() == (p + tn.astype(np.float64) * period).tobytes()
            assert (u.turns, u._last) == (turns, last)


def test_the_old_name_of_the_output_is_read_with_a_warning(
        caplog: pytest.LogCaptureFixture) -> None:
    """``model.target`` (and ``"target"`` among the exponents of ``model.scaling``) is the
    old name of ``model.output``: read for one release, with one warning line each."""
    d = {"effects": ["inertia", "coulomb"], "target": "torque",
         "scaling": {"mechanical": {"target": 3, "inertia.J": 2}}}
    with caplog.at_level(logging.WARNING, logger="canrls.estimation.model"):
        m = Model.from_dict(d, source="old.json", available_signals=["torque"])
        Model.from_dict(d, source="old.json", available_signals=["torque"])
    assert m.output == "torque" and m.equations[0].scaling.output == 3
    assert m.to_dict()["output"] == "torque" and "target" not in m.to_dict()
    assert m.to_dict()["scaling"] == {"mechanical": {"output": 3, "inertia.J": 2}}
    lines = [r.getMessage() for r in caplog.records]
    assert lines == ["old.json: model.target is now called output; the old name goes in the "
                     "next release",
                     "old.json: model.scaling.mechanical.target is now called output; the "
                     "old name goes in the next release"]
    with pytest.warns(DeprecationWarning, match="Model.target is now Model.output"):
        assert m.target == "torque"
    with pytest.raises(ConfigError, match="model.target = 'torque': is the old name of "
                                          "model.output: give one of them"):
        Model.from_dict({**d, "output": "torque"}, source="both.json")
