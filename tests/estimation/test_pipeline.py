"""The pure pipeline on the standard simulated scenario: float vs fixed, chunking, gaps."""

from __future__ import annotations

import math

import numpy as np
import pytest

from canrls.core.errors import ConfigError
from canrls.core.samples import Signals
from canrls.estimation.estimates import divergence
from canrls.estimation.fixed.formats import QFormat
from canrls.estimation.pipeline import Pipeline
from canrls.estimation.settings import EstimatorSettings
from canrls.processor import scan_ranges
from canrls.processor.config import AppConfig
from canrls.sim.scenario import scenario, simulate

EFFECTS = "inertia,viscous,coulomb,offset,unbalance,cogging:6"


@pytest.fixture(scope="module")
def standard() -> object:
    return simulate(scenario("standard", effects=EFFECTS, seed=11, duration=30.0))


def _model(res: object, effects: str = EFFECTS, **model: object):
    cfg = AppConfig()
    cfg.model = {"effects": effects.split(","), "kt": 0.1, **model}
    prot = cfg.protocol()
    m0 = cfg.model_for(prot)
    ranges = scan_ranges([res.measured], 1e-3, m0.cutoff_hz, m0.zeta)  # type: ignore[attr-defined]
    return cfg.model_for(prot, ranges)


@pytest.mark.parametrize("lam", [1.0, 0.9995])
def test_fixed_point_within_0p1_percent_of_float_on_the_standard_scenario(
        standard: object, lam: float) -> None:
    pipe = Pipeline(_model(standard), 1e-3, EstimatorSettings(lam=lam))
    pipe.process(standard.measured)  # type: ignore[attr-defined]
    est = pipe.estimates()
    for p in est.parameters:
        assert p.fixed == pytest.approx(p.value, rel=1e-3), p
    assert not pipe.saturations.nonzero()
    assert est.equations[0].divergence < 1e-3


def test_true_parameters_come_back(standard: object) -> None:
    pipe = Pipeline(_model(standard), 1e-3)
    est = pipe.run([standard.measured])  # type: ignore[attr-defined]
    truth = standard.truth.params  # type: ignore[attr-defined]
    for p in est.parameters:
        assert p.value == pytest.approx(truth[p.name], rel=0.02), p
        # the true value lies within a few standard deviations (plus 0.5 % model error)
        assert abs(p.value - truth[p.name]) < 6 * p.sigma + 5e-3 * abs(truth[p.name]), p
    assert est.residual_rms < 1.5 * standard.noise_floor  # type: ignore[attr-defined]


def test_any_block_sizes_give_the_same_bits(standard: object) -> None:
    sig: Signals = standard.measured  # type: ignore[attr-defined]
    model = _model(standard)
    a = Pipeline(model, 1e-3)
    a.process(sig)
    b = Pipeline(model, 1e-3)
    rng = np.random.default_rng(3)
    k = 0
    while k < len(sig):
        step = int(rng.integers(1, 2000))
        b.process(sig.slice(k, k + step))
        k += step
    ea, eb = a.estimates(), b.estimates()
    for pa, pb in zip(ea.parameters, eb.parameters, strict=True):
        assert (pa.value, pa.fixed, pa.sigma) == (pb.value, pb.fixed, pb.sigma)
    assert ea.residual_rms == eb.residual_rms


@pytest.mark.parametrize("record", [False, True])
def test_the_fixed_point_thread_gives_the_same_bits(standard: object, record: bool,
                                                     monkeypatch: pytest.MonkeyPatch) -> None:
    """Large blocks run the fixed-point estimator in a thread beside the float one
    (OVERLAP_ROWS): every output and the state are those of the estimators one after the
    other."""
    from canrls.estimation import pipeline

    sig: Signals = standard.measured  # type: ignore[attr-defined]
    model = _model(standard)
    outs = []
    for rows in (1, 10**12):  # every block in a thread / none
        monkeypatch.setattr(pipeline, "OVERLAP_ROWS", rows)
        pipe = Pipeline(model, 1e-3)
        blocks = [pipe.process(sig.slice(k, k + 7000), record=record)
                  for k in range(0, len(sig), 7000)]
        outs.append(([(q.eps, q.eps_fixed, q.flags, q.online_rms, q.theta, q.theta_fixed)
                      for b in blocks for q in b.equations], pipe.state()))
    (a, sa), (b, sb) = outs
    for x, y in zip(a, b, strict=True):
        for u, v in zip(x, y, strict=True):
            assert (u is None and v is None) or np.array_equal(u, v, equal_nan=True)
    _same_state(sa, sb)


def _same_state(a: object, b: object) -> None:
    """Two states (nested dicts, lists, arrays, numbers) equal item for item, bit for bit."""
    if isinstance(a, dict):
        assert isinstance(b, dict) and a.keys() == b.keys()
        for k in a:
            _same_state(a[k], b[k])
    elif isinstance(a, (list, tuple)):
        assert isinstance(b, (list, tuple)) and len(a) == len(b)
        for x, y in zip(a, b, strict=True):
            _same_state(x, y)
    elif isinstance(a, np.ndarray):
        assert a.dtype == np.asarray(b).dtype and a.tobytes() == np.asarray(b).tobytes()
    else:
        assert a == b or (a != a and b != b), (a, b)  # nan: itself


def test_an_error_of_the_fixed_point_thread_reaches_the_caller(
        standard: object, monkeypatch: pytest.MonkeyPatch) -> None:
    from canrls.estimation import pipeline

    monkeypatch.setattr(pipeline, "OVERLAP_ROWS", 1)
    pipe = Pipeline(_model(standard), 1e-3)

    def broken(*args: object) -> None:
        raise RuntimeError("the fixed-point kernel failed")

    monkeypatch.setattr(pipe.estimators[0], "_fixed_block", broken)
    with pytest.raises(RuntimeError, match="fixed-point kernel failed"):
        pipe.process(standard.measured)  # type: ignore[attr-defined]


def test_a_gap_restarts_the_filter_and_skips_its_warm_up(standard: object) -> None:
    sig: Signals = standard.measured  # type: ignore[attr-defined]
    # without friction effects only the warm-ups are skipped
    pipe = Pipeline(_model(standard, "inertia,viscous,offset"), 1e-3)
    warm = pipe.estimators[0].warmup
    first = pipe.process(sig.slice(0, 5000)).equations[0]
    assert not first.used[:warm].any() and first.used[warm:].all()
    # 0.5 s of silence: the next samples warm the filter up again
    blk = pipe.process(sig.slice(5500, 9000)).equations[0]
    assert not blk.used[:warm].any() and blk.used[warm:].all()
    # with friction, standstill is skipped too, and the estimate survives the gap
    full = Pipeline(_model(standard), 1e-3)
    full.process(sig.slice(0, 5000))
    blk = full.process(sig.slice(5500, len(sig))).equations[0]
    assert not blk.used[:warm].any()
    slow = np.abs(sig.speed[5500:]) < full.estimators[0].min_speed
    assert not blk.used[slow].any()
    truth = standard.truth.params  # type: ignore[attr-defined]
    assert full.estimates()["coulomb.Tc"].value == pytest.approx(truth["coulomb.Tc"], rel=0.02)


def test_a_missing_effect_raises_the_residual_and_adding_it_lowers_it(standard: object) -> None:
    sig = standard.measured  # type: ignore[attr-defined]
    lacking = Pipeline(_model(standard, "inertia,viscous,coulomb,offset,unbalance"), 1e-3)
    full = Pipeline(lacking.model.with_effects(add=["cogging:6"]), 1e-3)
    r_lacking = lacking.run([sig]).residual_rms
    r_full = full.run([sig]).residual_rms
    assert r_full < 0.5 * r_lacking
    assert r_full < 1.5 * standard.noise_floor  # type: ignore[attr-defined]


def test_reset_freeze_resume_and_lambda(standard: object) -> None:
    sig = standard.measured  # type: ignore[attr-defined]
    pipe = Pipeline(_model(standard), 1e-3, EstimatorSettings(lam=0.9995))
    pipe.process(sig.slice(0, 10000))
    before = pipe.estimates()["inertia.J"].value
    pipe.freeze()
    assert pipe.frozen
    pipe.process(sig.slice(10000, 15000))
    assert pipe.estimates()["inertia.J"].value == before
    pipe.resume()
    pipe.set_lambda(0.999)
    pipe.process(sig.slice(15000, 20000))
    assert pipe.estimates()["inertia.J"].value != before
    pipe.reset()
    assert pipe.estimates()["inertia.J"].value == 0.0
    with pytest.raises(ValueError, match="lambda"):
        pipe.set_lambda(1.5)


def test_state_round_trip_continues_identically(standard: object) -> None:
    sig = standard.measured  # type: ignore[attr-defined]
    model = _model(standard)
    a = Pipeline(model, 1e-3)
    a.process(sig.slice(0, 12000))
    b = Pipeline(model, 1e-3)
    b.restore(a.state())
    # both continue after a restart of the filter (a restored daemon warms up again)
    a2 = Pipeline(model, 1e-3)
    a2.restore(a.state())
    for p in (b, a2):
        p.process(sig.slice(12000, 20000))
    for pa, pb in zip(a2.estimates().parameters, b.estimates().parameters, strict=True):
        assert (pa.value, pa.fixed) == (pb.value, pb.fixed)


_ROW_FIELDS = ("t", "y", "eps", "eps_fixed", "used", "online_rms", "flags", "theta",
               "theta_fixed", "phi")


@pytest.mark.parametrize("record", [False, True])
@pytest.mark.parametrize("case", ["plain", "rescaling"])
def test_blocks_of_0_to_5_samples_give_the_rows_of_one_block(
        standard: object, record: bool, case: str) -> None:
    """The short cuts of small blocks (empty blocks, every row or no row used, nothing to
    fill, no restart inside) give the rows and the state of one large block bit for bit."""
    sig: Signals = standard.measured.slice(0, 8000)  # type: ignore[attr-defined]
    rng = np.random.default_rng(17)
    keep = np.ones(len(sig), bool)
    for c in rng.integers(100, len(sig) - 10, 40):  # lost samples: filled
        keep[c:c + int(rng.integers(1, 3))] = False
    keep[3000:3020] = False  # a long gap: the filter restarts
    idx = np.flatnonzero(keep)
    t = sig.t[idx].copy()
    t[5000] = t[4990]  # time going back: the filter restarts
    current = sig.current[idx] * (40.0 if case == "rescaling" else 1.0)
    s = Signals(t, current, sig.speed[idx], sig.position[idx])
    settings = EstimatorSettings(lam=0.998 if case == "rescaling" else 1.0)
    whole = Pipeline(_model(standard), 1e-3, settings)
    ref = whole.process(s, record=record).equations[0]
    parts = Pipeline(_model(standard), 1e-3, settings)
    blocks = []
    k = 0
    while k < len(s):
        n = int(rng.integers(0, 6))
        blocks.append(parts.process(s.slice(k, k + n), record=record).equations[0])
        k += n
    for name in _ROW_FIELDS:
        want = getattr(ref, name)
        if want is None:
            assert all(getattr(b, name) is None for b in blocks), name
            continue
        got = np.concatenate([getattr(b, name) for b in blocks])
        assert got.dtype == want.dtype and got.tobytes() == want.tobytes(), name
    a, b = whole.estimators[0], parts.estimators[0]
    sa, sb = a.state(), b.state()
    for key in ("M", "v", "s", "rms"):
        assert sa[key].tobytes() == sb[key].tobytes(), key
    assert sa["windup_steps"] == sb["windup_steps"]
    for est in ("rls", "fixed"):
        for key, va in sa[est].items():
            assert np.array_equal(va, sb[est][key]), (est, key)
    if case == "rescaling":
        # the current 40 times what the start showed: the normalisation follows, at the
        # same rows in both
        assert a.rescale_count > 0 and a.rescales == b.rescales
        assert sa["windup_steps"] > 0
    assert whole.saturations == parts.saturations


def test_divergence_matches_its_formula_with_nan_and_zero() -> None:
    rng = np.random.default_rng(11)
    for _ in range(200):
        n = int(rng.integers(0, 6))
        th = rng.normal(size=n) * rng.choice([0.0, 1.0, 1e3], size=n)
        fx = th + rng.normal(size=n) * 1e-3
        sd = np.abs(rng.normal(size=n))
        sd[rng.random(n) < 0.3] = np.nan  # not known yet: counts as 0
        # max_j |fx - th| / max(|th|, 3 sd), a zero reference counting as 1
        ref = np.maximum(np.abs(th), 3.0 * np.nan_to_num(sd, nan=0.0))
        ref = np.where(ref > 0, ref, 1.0)
        want = float(np.max(np.abs(fx - th) / ref)) if n else 0.0
        assert divergence(th.tolist(), fx.tolist(), sd.tolist()) == want
    assert math.isnan(divergence([1.0, np.nan], [1.0, 2.0], [0.1, 0.1]))
    assert divergence([0.0], [0.5], [np.nan]) == 0.5


def test_restored_state_keeps_its_own_fixed_point_formats(standard: object) -> None:
    """A state saved with other Q formats continues in them: eps_fixed and theta_fixed
    are both read in the formats of the restored fixed-point estimator."""
    sig = standard.measured  # type: ignore[attr-defined]
    model = _model(standard)
    coarse = EstimatorSettings(fixed_overrides={"eps": QFormat(32, 8)})
    a = Pipeline(model, 1e-3, coarse)
    a.process(sig.slice(0, 12000))
    b = Pipeline(model, 1e-3)  # the default formats
    b.restore(a.state())
    a.restore(a.state())  # the same restart of the filter
    oa, ob = (p.process(sig.slice(12000, 14000)) for p in (a, b))
    ea, eb = oa.equations[0], ob.equations[0]
    assert b.estimators[0].fixed_config == a.estimators[0].fixed_config
    assert np.array_equal(ea.eps_fixed, eb.eps_fixed)
    # on the coarse grid of the restored format (lsb 2**-8 in normalised units)
    lsb = math.ldexp(2.0**-8, model.equations[0].scaling.output)
    assert np.allclose(eb.eps_fixed[eb.used] / lsb, np.round(eb.eps_fixed[eb.used] / lsb))


def test_a_term_outside_its_domain_skips_those_samples_and_the_filter_recovers(
        standard: object) -> None:
    """sqrt(speed) is NaN whenever the drive turns backwards: those samples (and the
    filter's warm-up after each stretch) are left out; the NaN never reaches the
    filter's state, so the estimator goes on updating and the true parameters come back
    (only forward motion is used, so Coulomb friction and the load offset are seen
    as their sum)."""
    sig: Signals = standard.measured  # type: ignore[attr-defined]
    model = _model(standard, EFFECTS + ",user:root",
                   terms={"root": {"expr": "sqrt(omega)", "range": [0.0, 10.0]}})
    pipe = Pipeline(model, 1e-3)
    out = pipe.process(sig)
    est = pipe.estimators[0]
    eb = out.equations[0]
    backwards = sig.speed < 0
    assert 0.2 < backwards.mean() < 0.8
    assert est.nonfinite_rows == int(np.count_nonzero(backwards))
    assert not eb.used[backwards].any()
    # after each backward stretch, the next warm-up rows are left out too
    ends = np.flatnonzero(backwards[:-1] & ~backwards[1:]) + 1
    assert not eb.used[ends[ends + est.warmup < len(sig)]].any()
    assert np.isfinite(eb.eps[eb.used]).all() and est.rls.count >= eb.used.sum() * 0.99
    truth = standard.truth.params  # type: ignore[attr-defined]
    fit = pipe.estimates()
    got = {p.name: p.value for p in fit.parameters}
    assert all(np.isfinite([p.value, p.fixed, p.sigma]).all() for p in fit.parameters)
    for name, value in got.items():
        if name in truth and name.split(".")[0] not in ("coulomb", "offset"):
            assert value == pytest.approx(truth[name], rel=0.05), name
    both = [n for n in got if n.split(".")[0] in ("coulomb", "offset")]
    assert sum(got[n] for n in both) == pytest.approx(sum(truth[n] for n in both), rel=0.05)
    assert fit.equations[0].nonfinite_rows == est.nonfinite_rows
    assert f"{est.nonfinite_rows} samples with a non-finite term left out" in fit.format()
    assert fit.equations[0].to_dict()["nonfinite_rows"] == est.nonfinite_rows
    # blocks of any size give the same bits (the last finite value is carried)
    b = Pipeline(model, 1e-3)
    for k in range(0, len(sig), 777):
        b.process(sig.slice(k, k + 777))
    assert b.estimates().parameters == fit.parameters


@pytest.mark.parametrize("key, value, message", [
    ("word_bits", -32, r"fixed\.word_bits = -32: must be an integer in 8\.\.32"),
    ("word_bits", 2 ** 63 - 1, r"fixed\.word_bits = 9223372036854775807: must be an integer"),
    ("acc_bits", 100_000, r"fixed\.acc_bits = 100000: must be an integer in 16\.\.64"),
    ("input_bits", 1, r"fixed\.input_bits = 1: must be an integer in 2\.\.32"),
    ("calibration_s", 1e308, r"estimator\.calibration_s = 1e\+308: must be > 0 seconds, "
                             r"at most 1e\+10"),
    ("theta_max", 1e300, r"fixed\.theta_max = 1e\+300: no Q format of 32-bit words holds "
                         r"it"),
])
def test_settings_refuse_words_and_windows_no_estimator_can_run_naming_the_key(
        key: str, value: object, message: str) -> None:
    """``[fixed] word_bits = -32`` was refused only when the Q formats were built, as
    "range of P: QFormat bits must be in 2..64", naming neither the key nor the file
    (``theta_max = 1e300`` alike, as "range of theta");
    ``[estimator] calibration_s = 1e308`` made the window's sample count infinite, an
    internal error (exit 3) of ``canrls fit``. Through the configuration, the file is
    named too."""
    with pytest.raises(ConfigError, match=message):
        EstimatorSettings(**{key: value})
    section = "fixed" if key.endswith("_bits") or key == "theta_max" else "estimator"
    cfg = AppConfig(source="drive.toml")
    setattr(cfg, section, {key: value})
    with pytest.raises(ConfigError, match="drive.toml: " + message):
        cfg.settings()
