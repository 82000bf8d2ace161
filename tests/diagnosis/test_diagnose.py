"""Unit tests of canrls.diagnosis.analysis and canrls.diagnosis.report (the acceptance is in
test_diagnose_acceptance.py, the command line in test_cli_diagnose.py)."""

from __future__ import annotations

import copy
import dataclasses
import json
import math
import re
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from markupsafe import escape

from canrls.core.checks import json_safe
from canrls.core.errors import ConfigError, EffectError
from canrls.core.samples import Signals
from canrls.diagnosis.analysis import diagnose
from canrls.diagnosis.report import DiagnosisReport
from canrls.diagnosis.residual import bin_residual, chi2_sf, nice_magnitudes, whiteness
from canrls.estimation.effects import DEFAULT_STRIBECK_SPEED
from canrls.estimation.model import Model
from canrls.estimation.settings import EstimatorSettings
from canrls.processor import SampleProcessor, scan_ranges
from canrls.processor.config import DEFAULT_HELD
from canrls.sim.scenario import SimResult, scenario, simulate

BASE = ["inertia", "viscous", "coulomb"]
ORDER = 24  # a smaller cogging search keeps these tests quick


def _model(signals: Signals, effects: list[str], **kw: Any) -> Model:
    ranges = scan_ranges([signals], 1e-3, 25.0, 0.7071)
    return Model(effects, kt=0.1, held=DEFAULT_HELD, ranges=ranges, **kw)


@pytest.fixture(scope="module")
def offset_run() -> tuple[SimResult, Model, DiagnosisReport]:
    res = simulate(scenario("standard", effects="inertia,viscous,coulomb,offset", seed=3,
                            duration=20.0))
    model = _model(res.measured, BASE)
    rep = diagnose(res.measured, model, dt=1e-3, add=["offset"], max_order=ORDER,
                   source="offset-run")
    return res, model, rep


# ----------------------------------------------------------------------- the report
def test_offset_is_named_added_and_the_error_falls(offset_run: Any) -> None:
    res, _, rep = offset_run
    assert rep.candidates[0].effect == "offset"
    assert rep.suggestion == ("offset",)
    assert rep.added == ("offset",)
    assert rep.after is not None
    assert rep.after.residual_rms < 0.1 * rep.before.residual_rms
    assert rep.after.estimates["offset.T0"].value == pytest.approx(0.005, rel=0.02)
    c = rep.candidates[0]
    assert c.parameters["offset.T0"][0] == pytest.approx(0.005, rel=0.02)
    assert c.parameters["offset.T0"][1] == "N·m"
    assert c.rms_after == pytest.approx(rep.after.residual_rms, rel=0.2)
    assert c.description.startswith("Torque offset")
    assert "constant" in c.signature
    assert any("mean residual" in e for e in c.evidence)


def test_text_has_every_section(offset_run: Any) -> None:
    _, _, rep = offset_run
    text = rep.format()
    for part in ("offset-run: ", "Compare", "residual RMS", "fit ", "whiteness:",
                 "Where it fails", "moving forward", "Which effect is missing", "offset",
                 "Verdict:", "--add offset", "Before and after --add offset",
                 "offset.T0", "± σ", "After:"):
        assert part in text, part
    assert str(rep) == text


def test_json_is_plain_and_has_the_documented_keys(offset_run: Any) -> None:
    _, _, rep = offset_run
    d = rep.to_dict()
    json.dumps(json_safe(d), allow_nan=False, ensure_ascii=False)
    for key in ("source", "samples", "duration", "dt", "axis", "unit", "before", "after",
                "added", "candidates", "suggestion", "regions", "orders", "structure",
                "excitation", "identifiable", "identifiability", "verdict",
                "not_applicable", "max_order"):
        assert key in d, key
    for side in ("before", "after"):
        s = d[side]
        assert {"residual_rms", "fit_percent", "r2", "parameters", "whiteness", "effects",
                "candidates", "suggestion", "verdict", "equations"} <= set(s)
        for p in s["parameters"].values():
            assert {"value", "sigma", "unit", "fixed"} <= set(p)
    assert d["after"]["parameters"]["offset.T0"]["unit"] == "N·m"
    c = d["candidates"][0]
    assert c["effect"] == "offset"
    assert {"effect", "explained", "delta_bic", "rms_after", "identifiable", "suggested",
            "description", "evidence", "parameters"} <= set(c)
    assert d["suggestion"]["add"] == ["offset"]
    assert d["orders"]["per"] == "revolution"
    assert len(d["orders"]["orders"]) == len(d["orders"]["amplitude"])


def test_before_is_what_the_pipeline_fits(offset_run: Any) -> None:
    """diagnose runs the same front end and pipeline: the same parameters, bit for bit."""
    res, model, rep = offset_run
    proc = SampleProcessor(model, 1e-3, EstimatorSettings())
    proc.run(res.measured)
    est = proc.pipeline.estimates()
    assert [p.value for p in rep.before.estimates.parameters] == \
        [p.value for p in est.parameters]
    assert [p.fixed for p in rep.before.estimates.parameters] == \
        [p.fixed for p in est.parameters]
    assert rep.before.residual_rms == est.residual_rms
    assert rep.to_dict()["before"]["parameters"] == est.to_dict()["parameters"]


def test_blocks_give_the_same_diagnosis(offset_run: Any) -> None:
    res, model, rep = offset_run
    s = res.measured
    k = len(s) // 3
    blocks = [s.slice(0, k), s.slice(k, 2 * k), s.slice(2 * k, len(s))]
    rep2 = diagnose(blocks, model, dt=1e-3, max_order=ORDER)
    assert [p.value for p in rep2.before.estimates.parameters] == \
        [p.value for p in rep.before.estimates.parameters]
    assert [(c.effect, c.explained) for c in rep2.candidates] == \
        [(c.effect, c.explained) for c in rep.candidates]
    assert rep2.after is None and rep2.to_dict()["after"] is None


def test_regions_say_where_in_words(offset_run: Any) -> None:
    _, _, rep = offset_run
    q = rep.before.primary
    assert q.regions
    # a constant offset shows everywhere: the top region covers (almost) all samples,
    # and the speed region says it is the same moving forward and backward
    assert q.regions[0].share > 0.9
    top = next(r for r in q.regions if r.quantity == "speed")
    assert "moving forward" in top.text and "moving backward" in top.text
    assert top.mean_forward == pytest.approx(0.005, rel=0.1)
    assert top.mean_backward == pytest.approx(0.005, rel=0.1)
    assert top.share > 0.9
    for name in ("speed", "position", "current", "acceleration", "time"):
        b = q.bins[name]
        assert len(b.edges) == len(b.count) + 1
        assert int(b.count.sum()) == q.fit.samples


def test_convergence_traces(offset_run: Any) -> None:
    _, _, rep = offset_run
    tr = rep.after.primary.traces  # type: ignore[union-attr]
    assert tr.names == ("inertia.J", "viscous.B", "coulomb.Tc", "offset.T0")
    assert tr.theta.shape == tr.sigma.shape == tr.theta_fixed.shape == (len(tr.conv_t), 4)
    # the re-run RLS ends where the pipeline did
    final = [p.value for p in rep.after.estimates.parameters]  # type: ignore[union-attr]
    np.testing.assert_allclose(tr.theta[-1], final, rtol=1e-12)
    sig = [p.sigma for p in rep.after.estimates.parameters]  # type: ignore[union-attr]
    np.testing.assert_allclose(tr.sigma[-1], sig, rtol=1e-9)


# ------------------------------------------------------------------ the cogging order
def test_cogging_order_is_found_and_bare_cogging_takes_it() -> None:
    res = simulate(scenario("standard", effects="inertia,viscous,coulomb,cogging:9", seed=5,
                            duration=20.0,
                            params={"cogging:9.sin": 0.009, "cogging:9.cos": -0.0045}))
    rep = diagnose(res.measured, _model(res.measured, BASE), dt=1e-3, add=["cogging"],
                   max_order=ORDER)
    assert rep.candidates[0].effect == "cogging:9"
    assert rep.added == ("cogging:9",)
    assert rep.after is not None and "cogging:9" in rep.after.effects
    sp = rep.before.primary.spectrum
    assert sp is not None and sp.peaks[0] == 9.0
    amp, share = sp.at(9)
    assert amp == pytest.approx(math.hypot(0.009, 0.0045), rel=0.1)
    assert rep.after.estimates["cogging:9.sin"].value == pytest.approx(0.009, rel=0.03)


# -------------------------------------------------- structure no candidate explains
@pytest.fixture(scope="module")
def plain() -> SimResult:
    return simulate(scenario("standard", effects="inertia,viscous,coulomb", seed=4,
                             duration=20.0))


def _with_torque(res: SimResult, torque: np.ndarray) -> Signals:
    m = res.measured
    return Signals(m.t, m.current + torque / res.truth.kt, m.speed, m.position)


def test_time_drift_is_described_not_blamed_on_an_effect(plain: SimResult) -> None:
    m = plain.measured
    s = _with_torque(plain, 0.01 * np.sin(2 * np.pi * m.t / 20.0))
    rep = diagnose(s, _model(s, BASE), dt=1e-3, max_order=ORDER)
    assert rep.suggestion == ()
    kinds = [x.kind for x in rep.before.primary.structure]
    assert "time" in kinds
    assert "no effect of the library explains the structure left" in rep.verdict
    assert "drifting in time" in rep.verdict


def test_fractional_order_is_described_not_blamed_on_cogging(plain: SimResult) -> None:
    s = _with_torque(plain, 0.005 * np.sin(2.5 * np.asarray(plain.true.position)))
    rep = diagnose(s, _model(s, BASE), dt=1e-3, max_order=ORDER)
    assert rep.suggestion == ()
    periodic = [x for x in rep.before.primary.structure if x.kind == "periodic"]
    assert periodic and "order 2.5" in periodic[0].text
    assert "periodic at order 2.5" in rep.verdict


def test_complete_model_suggests_nothing(plain: SimResult) -> None:
    rep = diagnose(plain.measured, _model(plain.measured, BASE), dt=1e-3, max_order=ORDER)
    assert rep.suggestion == ()
    assert "complete" in rep.verdict
    assert rep.before.primary.structure == ()


def test_the_low_speed_share_is_below_the_stribeck_speed_the_search_found() -> None:
    """A model without Stribeck friction and without a configured speed: the excitation's
    low_speed is the share below twice the Stribeck speed the search found (it was the
    library's default, 1 rad/s), the same share a model configured with that speed
    gets; an equation without a Stribeck speed found says none."""
    res = simulate(scenario("standard", effects="inertia,viscous,coulomb,stribeck,electrical",
                            seed=3, duration=10.0))
    s = res.measured
    model = _model(s, [*BASE, "electrical"], options_given=())
    rep = diagnose(s, model, dt=1e-3, max_order=8)
    mech, elec = rep.before.equations
    ws = next(r.value for r in mech.candidate("stribeck").search if r.key == "stribeck_speed")
    assert ws != DEFAULT_STRIBECK_SPEED
    exc = rep.to_dict()["before"]["equations"]["mechanical"]["excitation"]
    assert exc["stribeck_speed"] == ws == mech.excitation.stribeck_speed
    given = _model(s, [*BASE, "electrical"], stribeck_speed=ws, options_given=("stribeck_speed",))
    again = diagnose(s, given, dt=1e-3, max_order=8).before.primary.excitation
    assert again.stribeck_speed == ws and exc["low_speed"] == again.low_speed
    default = _model(s, [*BASE, "electrical"], stribeck_speed=DEFAULT_STRIBECK_SPEED,
                     options_given=("stribeck_speed",))
    assert exc["low_speed"] != diagnose(s, default, dt=1e-3, max_order=8
                                        ).before.primary.excitation.low_speed
    assert elec.excitation.stribeck_speed is None and elec.excitation.low_speed is None


# ------------------------------------------------------------- other equations, signals
def test_without_position_periodic_effects_are_not_applicable(plain: SimResult) -> None:
    m = plain.measured
    s = Signals(m.t, m.current, m.speed)
    rep = diagnose(s, _model(s, ["inertia", "viscous"]), dt=1e-3)
    q = rep.before.primary
    assert q.spectrum is None
    assert "position" not in q.bins
    na = dict(q.not_applicable)
    assert "position" in na["cogging:K"] and "position" in na["unbalance"]
    assert rep.candidates[0].effect == "coulomb"
    with pytest.raises(EffectError, match="cogging"):
        diagnose(s, _model(s, BASE), dt=1e-3, add=["cogging"])


def test_electrical_equation_and_user_terms() -> None:
    res = simulate(scenario("standard", effects="inertia,viscous,coulomb,electrical", seed=6,
                            duration=10.0))
    s = res.measured
    terms = [{"name": "drag", "expr": "omega * abs(omega)", "unit": "rad²/s²",
              "range": [-1e4, 1e4]}]
    model = Model(BASE + ["electrical"], kt=0.1, held=["voltage"], terms=terms,
                  ranges=scan_ranges([s], 1e-3, 25.0, 0.7071))
    rep = diagnose(s, model, dt=1e-3, max_order=8)
    assert [q.equation for q in rep.before.equations] == ["mechanical", "electrical"]
    assert "user:drag" in [c.effect for c in rep.before.equations[0].candidates]
    assert not rep.before.equations[0].candidate("user:drag").suggested
    assert rep.before.equations[1].unit == "V"
    assert "electrical equation" in rep.format()
    d = rep.to_dict()
    assert set(d["before"]["equations"]) == {"mechanical", "electrical"}


# ------------------------------------------------------------------------ errors
def test_errors(plain: SimResult) -> None:
    s = plain.measured
    model = _model(s, BASE)
    with pytest.raises(EffectError, match="unknown effect"):
        diagnose(s, model, dt=1e-3, add=["friction"])
    with pytest.raises(EffectError, match="already in the model"):
        diagnose(s, model, dt=1e-3, add=["coulomb"])
    with pytest.raises(ConfigError, match="max_order"):
        diagnose(s, model, dt=1e-3, max_order=0)
    with pytest.raises(ConfigError, match="dt"):
        diagnose(s, model, dt=-1.0)
    with pytest.raises(ConfigError, match="samples"):
        diagnose(s.slice(0, 1), model, dt=1e-3)


# ------------------------------------------------------------------ building blocks
def test_chi2_tail() -> None:
    # chi-square(20) quantiles: 37.566 (p = 0.01), 19.337 (p = 0.5), 45.315 (p = 0.001)
    assert chi2_sf(37.566, 20) == pytest.approx(0.01, abs=0.001)
    assert chi2_sf(19.337, 20) == pytest.approx(0.5, abs=0.01)
    assert chi2_sf(45.315, 20) == pytest.approx(0.001, abs=0.0003)
    assert chi2_sf(0.0, 20) == 1.0


def test_whiteness_of_white_and_coloured_residuals() -> None:
    rng = np.random.default_rng(11)
    n = 5000
    used = np.ones(n, np.bool_)
    white = rng.normal(size=n)
    u = {"input": rng.normal(size=n)}
    w = whiteness(white, used, u, np.array([1.0]), 20)
    assert w is not None and w.decimation == 1
    assert w.white and w.independent
    assert w.bound == pytest.approx(2.5758 / math.sqrt(n), rel=1e-4)
    coloured = np.convolve(white, np.ones(5) / 5, mode="same")
    w2 = whiteness(coloured, used, {"input": white}, np.array([1.0]), 20)
    assert w2 is not None and not w2.white and w2.outside >= 3
    assert not w2.independent  # the residual is made of the input
    # through a low pass, the decimation takes the filter's own colour out
    h = np.exp(-np.arange(60) / 6.0)
    filt = np.convolve(white, h)[:n]
    w3 = whiteness(filt, used, u, h, 20)
    assert w3 is not None and w3.decimation > 10 and w3.white


def test_bins_and_share() -> None:
    rng = np.random.default_rng(12)
    x = rng.uniform(-1, 1, 4000)
    edges = np.linspace(-1, 1, 11)
    step = np.where(x > 0, 1.0, -1.0)
    b = bin_residual(x, step, edges, "speed", "speed", "rad/s")
    assert b.share == pytest.approx(1.0)
    np.testing.assert_allclose(b.mean, [-1] * 5 + [1] * 5)
    noise = bin_residual(x, rng.normal(size=4000), edges, "speed", "speed", "rad/s")
    assert noise.share < 0.01
    mags = nice_magnitudes(100.0)
    assert mags[0] == 0.0 and mags[-1] >= 100.0
    assert list(mags[1:4]) == [0.5, 1.0, 2.0]


# ------------------------------------------------------------------------ figures
def test_html_report(offset_run: Any, tmp_path: Any) -> None:
    pytest.importorskip("matplotlib")
    from canrls.diagnosis.figures import FIGURES

    _, _, rep = offset_run
    page = rep.write_html(tmp_path / "rep")
    assert page.name == "index.html"
    text = page.read_text(encoding="utf-8")
    for name in FIGURES:
        if name in ("position.svg", "orders.svg") and not (tmp_path / "rep" / name).exists():
            continue  # the offset run has a position: both are drawn
        f = tmp_path / "rep" / name
        assert f.read_bytes().startswith(b"<?xml") and b"<svg" in f.read_bytes()[:2000], name
        assert f"src='{name}'" in text
        assert f"alt='{name}'" not in text  # the alt says what it shows
    assert "Verdict" in text and "offset.T0" in text
    assert "name='viewport'" in text and "table.sortable" in text
    # the figure that proves an offset: the residual against speed, right under the verdict
    first = re.search(r"<img src='([^']+)' alt='([^']+)'", text)
    assert first is not None and first.group(1) == "speed.svg"
    assert "Residual against speed" in first.group(2)
    assert text.index("Verdict") < first.start() < text.index("<h2>Compare")


@pytest.fixture(scope="module")
def cogging_report(plain: SimResult) -> DiagnosisReport:
    """A hidden cogging of order 6, diagnosed and added."""
    s = _with_torque(plain, 0.003 * np.sin(6 * np.asarray(plain.true.position)))
    return diagnose(s, _model(s, BASE), dt=1e-3, add=["cogging:6"], max_order=ORDER,
                    source="cogging-run")


def test_report_proves_a_position_effect_with_position(cogging_report: DiagnosisReport,
                                                       tmp_path: Path) -> None:
    pytest.importorskip("matplotlib")
    from canrls.diagnosis.report import samples_text, split_regions

    rep = cogging_report
    b = rep.before.primary
    lead, rest = split_regions(b)
    assert lead and {r.quantity for r in lead} == {"position"}
    assert all(r.quantity != "position" for r in rest)
    used = b.fit.samples
    assert 0 < used < rep.samples
    said = samples_text(rep)
    assert said.startswith(f"{used:,} of {rep.samples:,} samples used")
    assert f"the other {rep.samples - used:,} were left out" in said
    assert "(100 %)" not in said  # 97.5 % is not rounded up
    assert "speeds below the minimum near reversals (below 0.0" in said  # Coulomb's band
    nearly = copy.copy(rep)
    nearly.samples = used + 3  # 99.98 % used: said as 99.9 %, never 100 %
    assert samples_text(nearly).startswith(f"{used:,} of {used + 3:,} samples used (99.9 %)")
    text = rep.write_html(tmp_path / "rep").read_text(encoding="utf-8")
    # the residual against position, then the order spectrum, under the verdict
    assert re.findall(r"<img src='([^']+)'", text)[:2] == ["position.svg", "orders.svg"]
    assert text.index("orders.svg") < text.index("<h2>Compare")
    assert text.index(lead[0].text) < text.index("Also in other quantities")
    assert str(escape(said)) in text
    # the text too: the position ranges first
    where = rep.format().split("Where it fails\n")[1]
    assert where.startswith(f"  - {lead[0].text}") and "  also in other quantities:" in where


def test_order_figure_shows_integer_orders(cogging_report: DiagnosisReport) -> None:
    from canrls.diagnosis.figures import integer_orders

    sp = cogging_report.before.primary.spectrum
    assert sp is not None and any(not float(p).is_integer() for p in sp.orders)
    orders, amp, expl, peaks = integer_orders(sp)
    assert all(float(p).is_integer() for p in orders) and len(orders) == ORDER
    assert peaks and peaks[0] == 6 and all(float(p).is_integer() for p in peaks)
    # fitted together, the peaks' shares add up to at most 1; a quarter order beside
    # order 6 (its leakage) explains next to nothing beyond it
    assert len(sp.shares) == len(sp.peaks) and sum(sp.shares) <= 1.0
    assert sp.share(6) == pytest.approx(sp.at(6)[1], abs=1e-9)
    assert all(sp.share(p) <= sp.at(p)[1] + 1e-9 for p in sp.peaks)
    # the figure's after panel: the order-6 amplitude gone once cogging:6 is added
    after = cogging_report.after
    assert after is not None and after.primary.spectrum is not None
    assert after.primary.spectrum.at(6)[0] < 0.1 * sp.at(6)[0]


def test_leakage_of_an_order_gets_no_share_of_its_own() -> None:
    """The quarter orders beside a strong order 6 (its leakage on the standard run)
    each explain 5-19 % alone, and nothing beyond order 6 fitted with it."""
    res = simulate(scenario("standard", effects="inertia,viscous,coulomb,offset,cogging:6",
                            seed=1, duration=40.0))
    s = res.measured
    sp = diagnose(s, _model(s, BASE + ["offset"]), dt=1e-3, max_order=ORDER
                  ).before.primary.spectrum
    assert sp is not None and sp.peaks[0] == 6
    leaks = [p for p in sp.peaks if not float(p).is_integer()]
    assert leaks
    for p in leaks:
        assert sp.share(p) < 0.01 and sp.at(p)[1] > 0.04, p
    assert sum(sp.shares) <= 1.0 < sum(sp.at(p)[1] for p in sp.peaks)


def test_figures_say_clipped_axes_and_unused_spans(cogging_report: DiagnosisReport,
                                                   tmp_path: Path) -> None:
    pytest.importorskip("matplotlib")
    from canrls.diagnosis.figures import figures_in, unused_spans

    t = np.arange(10.0)
    used = np.array([0, 0, 1, 1, 0, 0, 1, 1, 1, 0], bool)
    assert unused_spans(t, used) == [(0.0, 2.0), (3.0, 6.0), (8.0, 9.0)]
    figs = figures_in(tmp_path)
    b = cogging_report.before.primary
    figs.timeline(b, None)
    assert "spans the estimator does not use" in figs.notes["timeline.svg"]
    # 1 % of the samples far out: the axis, sized by the bin means, cuts them off
    r = b.traces.residual.copy()
    r[::100] += 0.1
    spiky = dataclasses.replace(b, traces=dataclasses.replace(b.traces, residual=r))
    figs.binned(spiky, None, "speed")
    note = figs.notes["speed.svg"]
    assert note.startswith("Y axis clipped at ±") and "of the samples lie beyond it" in note


def test_r2_is_never_rounded_up_to_one() -> None:
    from canrls.diagnosis.results import r2_text

    assert r2_text(0.99996) == "> 0.9999"
    assert r2_text(0.99994) == "0.9999"
    assert r2_text(1.0) == "1.0000"
    assert r2_text(0.5) == "0.5000"
    assert r2_text(0.999999, 5) == "> 0.99999"
    assert r2_text(float("nan")) == "n/a"


def test_html_report_without_matplotlib(offset_run: Any, tmp_path: Any,
                                        monkeypatch: pytest.MonkeyPatch) -> None:
    for mod in [m for m in sys.modules if m == "matplotlib" or m.startswith("matplotlib.")]:
        monkeypatch.delitem(sys.modules, mod)
    monkeypatch.setitem(sys.modules, "matplotlib", None)
    _, _, rep = offset_run
    with pytest.raises(ConfigError, match="matplotlib"):
        rep.write_html(tmp_path / "rep")
