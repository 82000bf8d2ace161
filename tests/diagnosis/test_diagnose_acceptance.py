"""Acceptance of ``canrls diagnose`` on the simulated drive with a hidden effect.

For each case the drive has the effect, the model lacks it. Required:

* diagnose ranks it first (for a pair: one of the two first, and the suggestion is the
  pair);
* after adding it, the residual RMS is within 20 % of the noise floor, compared like
  with like (below);
* every true parameter comes back within 2 %;
* the fixed-point parameters stay within 0.1 % of the float ones (its own test);
* nothing more is suggested once it is added.

Plus a negative control (a complete model gets no suggestion), a linear axis (m, m/s,
N) and poor excitation, where the answer must be "not identifiable from this data".

Noise floor, like with like. ``SimResult.noise_floor`` is the RMS of the current noise
on the torque target, ``Kt*sqrt(sigma_i^2 + q^2/12)``, before any filter. The residual
is computed on the *filtered* equation, and more than the current noise reaches it: the
speed-sensor noise enters the regressors (the inertia column is ``sF`` of the measured
speed, the Coulomb column its sign), and the sampled-data regressors themselves are
exact only up to the straight line between samples (a friction step inside a sample
period). The floor a perfect identification reaches is therefore the residual of the
true model with the true parameters, built from the measured signals through the same
model, filter and normalisation, over the same samples as the fit (:func:`_floor`). On
the rotary drive it is about twice ``noise_floor * ||h||_2`` (the current noise through
the filter ``F``, impulse response ``h``); ``docs/diagnose.md`` gives the breakdown.

Scenario choices (documented in ``docs/diagnose.md``): 40 s of the ``standard``
excitation (one cycle is 41.5 s; a record ending in its ±5 rad/s PRBS); the cogging
cases use a cogging torque of 0.009/0.0045 N·m (about 1 % of the peak torque; the
default 0.003/0.0015 N·m is below the bias that speed-sensor noise puts on low
harmonics through the Coulomb column, ~7e-5 N·m on the cosine of order 6). The
pipeline's phase-step guard is off by default (``max_phase_step = inf``); the cases
marked ``guard`` switch it on (0.3 rad per sample) to show that cogging of low order
is still found with it.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
import pytest

from canrls.diagnosis.analysis import diagnose
from canrls.diagnosis.report import DiagnosisReport
from canrls.estimation.model import Model
from canrls.estimation.settings import EstimatorSettings
from canrls.processor import scan_ranges
from canrls.processor.config import DEFAULT_HELD
from canrls.sim.scenario import SimResult, scenario, simulate

DURATION = 40.0
BASE = ("inertia", "viscous", "coulomb")
COGGING = (0.009, 0.0045)


@dataclass(frozen=True)
class Case:
    hidden: tuple[str, ...]
    name: str = "standard"
    base: tuple[str, ...] = BASE
    guard: bool = False
    seed: int = 1
    duration: float = DURATION
    params: dict[str, float] = field(default_factory=dict)

    @property
    def id(self) -> str:
        tag = "" if self.name == "standard" else f"{self.name}-"
        return tag + ("+".join(self.hidden) or "complete") + ("-guard" if self.guard else "")

    def true_params(self) -> dict[str, float]:
        p = dict(self.params)
        for h in self.hidden:
            if h.startswith("cogging:"):
                p.setdefault(f"{h}.sin", COGGING[0])
                p.setdefault(f"{h}.cos", COGGING[1])
        return p


CASES = [
    Case(("coulomb",)),
    Case(("stribeck",)),
    Case(("offset",)),
    Case(("unbalance",)),
    Case(("viscous",)),
    Case(("cogging:6",)),
    Case(("cogging:12",)),
    Case(("cogging:6",), guard=True),
    Case(("cogging:24",)),
    Case(("cogging:36",)),
    Case(("coulomb", "offset")),
    Case(("offset", "unbalance")),
    Case(("viscous", "cogging:12")),
    Case(("stribeck", "cogging:24")),
    Case(("offset",), name="linear"),
    Case(("unbalance",), name="linear"),
]


@dataclass
class Outcome:
    case: Case
    res: SimResult
    model: Model
    report: DiagnosisReport

    @property
    def after(self) -> Any:
        assert self.report.after is not None
        return self.report.after


def _model(res: SimResult, effects: tuple[str, ...] | list[str]) -> Model:
    """The model a user would configure for this drive (ranges measured as ``canrls fit``)."""
    tr = res.truth
    kw: dict[str, Any] = {}
    if tr.axis == "linear":
        # the defaults (band 0.01, Stribeck speed 1.0) are sized for rad/s; the linear
        # axis moves at up to 0.5 m/s: configure the drive's own values, as a user would
        kw = {"coulomb_band": tr.coulomb_band, "stribeck_speed": tr.stribeck_speed}
    ranges = scan_ranges([res.measured], res.scenario.dt, 25.0, 0.7071)
    return Model(list(effects), kt=tr.kt, axis=tr.axis, pitch=tr.pitch, held=DEFAULT_HELD,
                 ranges=ranges, **kw)


def _settings(case: Case) -> EstimatorSettings:
    return EstimatorSettings(max_phase_step=0.3) if case.guard else EstimatorSettings()


def _run(case: Case) -> Outcome:
    true = tuple(dict.fromkeys(case.base + case.hidden))
    res = simulate(scenario(case.name, effects=",".join(true), params=case.true_params(),
                            seed=case.seed, duration=case.duration))
    model = _model(res, [e for e in true if e not in case.hidden])
    rep = diagnose(res.measured, model, _settings(case), dt=res.scenario.dt,
                   add=case.hidden, source=case.id)
    return Outcome(case, res, model, rep)


def _floor(out: Outcome) -> float:
    """RMS residual of the true model with the true parameters (see the module docstring)."""
    eq = out.after.model.equations[0]
    theta = eq.to_normalised([out.res.params[p.name] for p in eq.parameters])
    rb = eq.builder(out.res.scenario.dt).process(out.res.measured)
    r = eq.output_to_physical(rb.y - rb.phi @ theta)
    used = out.after.primary.traces.record_used
    assert used is not None
    return float(np.sqrt(np.mean(r[used] ** 2)))


_CACHE: dict[str, Outcome] = {}


def _get(case: Case) -> Outcome:
    """Simulate and diagnose a case once per test session (the tests share it)."""
    if case.id not in _CACHE:
        _CACHE[case.id] = _run(case)
    return _CACHE[case.id]


@pytest.fixture(scope="module", params=CASES, ids=[c.id for c in CASES])
def outcome(request: pytest.FixtureRequest) -> Outcome:
    return _get(request.param)


def test_hidden_effect_is_ranked_first(outcome: Outcome) -> None:
    rep, hidden = outcome.report, outcome.case.hidden
    assert rep.candidates[0].effect in hidden, rep.format()
    assert rep.candidates[0].suggested
    assert sorted(rep.suggestion) == sorted(hidden), rep.verdict
    for h in hidden:
        c = rep.before.primary.candidate(h)
        assert c.identifiable and c.suggested
        assert c.delta_bic < 0
    assert "missing" in rep.verdict


def test_error_falls_to_the_noise_floor(outcome: Outcome) -> None:
    before = outcome.report.before.residual_rms
    after = outcome.after.residual_rms
    floor = _floor(outcome)
    assert after < 0.5 * before
    assert 0.8 <= after / floor <= 1.2, (after, floor)
    # the prediction made before adding matches what the refit gives
    predicted = outcome.report.before.primary.suggestion.rms_after
    assert predicted == pytest.approx(after, rel=0.25)


def test_true_parameters_come_back_within_2_percent(outcome: Outcome) -> None:
    truth = outcome.res.params
    est = outcome.after.estimates
    assert {p.name for p in est.parameters} == set(truth)
    errors = {p.name: p.value / truth[p.name] - 1.0 for p in est.parameters}
    assert max(abs(e) for e in errors.values()) <= 0.02, errors


def test_fixed_point_within_0_1_percent_of_float(outcome: Outcome) -> None:
    est = outcome.after.estimates
    rel = {p.name: abs(p.fixed - p.value) / abs(p.value) for p in est.parameters}
    assert max(rel.values()) <= 1e-3, rel


def test_nothing_more_is_suggested_after_adding(outcome: Outcome) -> None:
    assert outcome.after.suggestion == (), outcome.after.primary.verdict
    assert "complete" in outcome.after.primary.verdict


LINEAR = [c for c in CASES if c.name == "linear"]


@pytest.mark.parametrize("case", LINEAR, ids=[c.id for c in LINEAR])
def test_linear_axis_units(case: Case) -> None:
    rep = _get(case).report
    d = rep.to_dict()
    assert d["axis"] == "linear" and d["unit"] == "N"
    assert d["before"]["parameters"]["viscous.B"]["unit"] == "N·s/m"
    assert rep.before.primary.bins["speed"].unit == "m/s"
    assert rep.before.primary.bins["position"].unit == "m"
    assert rep.before.primary.spectrum is not None
    assert rep.before.primary.spectrum.per == "pitch"


# ------------------------------------------------------------------ negative control
@pytest.mark.parametrize("effects", [BASE, BASE + ("offset", "unbalance", "cogging:12")],
                         ids=["base", "rich"])
def test_complete_model_gets_no_suggestion(effects: tuple[str, ...]) -> None:
    params = {"cogging:12.sin": COGGING[0], "cogging:12.cos": COGGING[1]} \
        if "cogging:12" in effects else {}
    res = simulate(scenario("standard", effects=",".join(effects), params=params, seed=2,
                            duration=DURATION))
    rep = diagnose(res.measured, _model(res, effects), dt=res.scenario.dt)
    assert rep.suggestion == ()
    assert not any(c.suggested for c in rep.candidates)
    assert all(c.explained < 0.05 for c in rep.candidates), \
        [(c.effect, c.explained) for c in rep.candidates]
    assert "complete" in rep.verdict
    assert rep.to_dict()["suggestion"]["add"] == []


# ---------------------------------------------------------------- poor excitation
@pytest.mark.parametrize("hidden", ["offset", "coulomb", "stribeck"])
def test_poor_excitation_is_not_identifiable(hidden: str) -> None:
    """Constant speed in one direction: the answer is 'not identifiable', not a wrong effect."""
    base = ("inertia", "viscous") if hidden == "coulomb" else BASE
    effects = ",".join(dict.fromkeys(base + (hidden,)))
    res = simulate(scenario("poor", effects=effects, seed=1, duration=30.0))
    rep = diagnose(res.measured, _model(res, base), dt=res.scenario.dt)
    assert rep.suggestion == (), rep.verdict
    assert not rep.identifiable
    assert "not identifiable from this data" in rep.verdict
    c = rep.before.primary.candidate(hidden)
    assert not c.identifiable and not c.suggested
    assert c.reason
    # and the reason names the excitation problem
    facts = " ".join(rep.before.primary.excitation.facts())
    assert "forward only" in facts and "nearly constant" in facts
