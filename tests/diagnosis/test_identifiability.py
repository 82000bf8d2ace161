"""Honest identifiability (issue 13, item 1): no suggestion the data cannot support.

Simulated cases with known truth, each a way the data can fail to show an effect:
the speed never reverses (Coulomb friction and an offset are one column), the travel
is shorter than a harmonic's period (it fits any slow trend), no position signal
(position effects cannot be tested at all).
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from typing import Any

import pytest

from canrls.diagnosis.analysis import diagnose
from canrls.diagnosis.candidates import MIN_PERIODS, SIGN_PAIR_TEXT
from canrls.processor.config import AppConfig
from canrls.sim.excitation import chirp
from canrls.sim.scenario import scenario, simulate

QUICK = 8


def _model(effects: str) -> Any:
    cfg = AppConfig()
    cfg.model = {"effects": effects.split(","), "kt": 0.1}
    return cfg.model_for(), cfg.settings()


def _run(truth: str, effects: str, exc: Any, duration: float = 12.0, seed: int = 5,
         drop_position: bool = False) -> Any:
    res = simulate(scenario("standard", effects=truth, excitation=exc, duration=duration,
                            seed=seed))
    sig = res.measured
    if drop_position:
        sig = dataclasses.replace(sig, position=None)
    model, settings = _model(effects)
    return diagnose(sig, model, settings, dt=0.001, max_order=QUICK)


def _cands(rep: Any) -> dict[str, Any]:
    return {c.effect: c for c in rep.before.primary.candidates}


@pytest.fixture(scope="module")
def one_direction() -> Any:
    # 20 .. 40 rad/s, accelerating (a chirp around 30 rad/s): never reverses
    return chirp(10.0, 0.2, 5.0, 10.0, offset=30.0)


def test_one_direction_coulomb_and_offset_cannot_be_separated(one_direction: Any) -> None:
    rep = _run("inertia,viscous,coulomb", "inertia,viscous", one_direction)
    c = _cands(rep)
    for name in ("coulomb", "offset"):
        assert not c[name].identifiable and not c[name].suggested, c[name]
        assert SIGN_PAIR_TEXT in c[name].reason
        assert c[name].explained > 0.5  # it would explain much: said, not hidden
    assert not rep.before.primary.suggestion.add
    verdict = rep.before.primary.verdict
    assert "record a run in both directions" in verdict
    assert "--add coulomb" not in verdict and "--add offset" not in verdict
    assert "complete" not in verdict
    d = rep.to_dict()
    assert d["suggestion"]["add"] == []


def test_one_direction_offset_against_the_models_coulomb(one_direction: Any) -> None:
    rep = _run("inertia,viscous,coulomb,offset", "inertia,viscous,coulomb", one_direction)
    c = _cands(rep)["offset"]
    assert not c.identifiable and not c.suggested
    assert SIGN_PAIR_TEXT in c.reason
    assert "record a run in both directions" in rep.before.primary.verdict


def test_both_directions_find_coulomb_and_offset() -> None:
    rep = _run("inertia,viscous,coulomb,offset", "inertia,viscous", "standard", duration=20.0)
    sug = rep.before.primary.suggestion.add
    assert "coulomb" in sug and "offset" in sug
    c = _cands(rep)
    assert c["coulomb"].identifiable and c["offset"].identifiable


def test_short_travel_harmonics_are_not_identifiable() -> None:
    # +-2 rad/s at 0.5 .. 3 Hz around standstill: the position covers a fraction of a turn
    exc = chirp(2.0, 0.5, 3.0, 10.0)
    rep = _run("inertia,viscous,coulomb,unbalance", "inertia,viscous,coulomb", exc)
    prim = rep.before.primary
    cov = prim.excitation.coverage
    assert cov is not None and cov < 0.5
    c = _cands(rep)
    assert not c["unbalance"].identifiable and not c["unbalance"].suggested
    assert "record more travel" in c["unbalance"].reason
    assert "longer than the travel covered" in c["unbalance"].reason
    for name, cand in c.items():
        if name.startswith("cogging:") and int(name[8:]) * cov < MIN_PERIODS:
            assert not cand.identifiable and "record more travel" in cand.reason
    # the harmonic that fits the slow trend best is not suggested, nor any other whose
    # period the travel does not hold twice
    assert c["unbalance"].explained > 0.9
    for a in prim.suggestion.add:
        if a.startswith("cogging:"):
            assert int(a[8:]) * cov >= MIN_PERIODS
        assert not a.startswith("unbalance")
    assert "record more travel" in prim.verdict


def test_no_position_complete_names_what_was_not_tested() -> None:
    rep = _run("inertia,viscous,coulomb", "inertia,viscous,coulomb", "standard",
               duration=20.0, drop_position=True)
    prim = rep.before.primary
    assert not prim.suggestion.add
    v = prim.verdict
    assert "no effect of the library that these data could test" in v
    assert "Untested:" in v and "unbalance" in v and "cogging" in v and "position" in v


def test_complete_with_position_says_so_plainly() -> None:
    rep = _run("inertia,viscous,coulomb", "inertia,viscous,coulomb", "standard",
               duration=20.0)
    v = rep.before.primary.verdict
    assert "complete" in v and "Untested" not in v


# ------------------------------------------------------------------ the same, on the CLI
def _cli_json(capsys: pytest.CaptureFixture[str], argv: list[str]) -> dict[str, Any]:
    from canrls.cli.main import main

    capsys.readouterr()
    assert main(argv) == 0
    return dict(json.loads(capsys.readouterr().out))


def _sim(tmp: Path, capsys: pytest.CaptureFixture[str], name: str, *args: str) -> Path:
    from canrls.cli.main import main

    log = tmp / f"{name}.log"
    assert main(["sim", "--out", str(log), "--seed", "5", *args]) == 0
    capsys.readouterr()
    return log


def _diagnose(capsys: pytest.CaptureFixture[str], log: Path, effects: str,
              *extra: str) -> tuple[dict[str, Any], dict[str, Any]]:
    d = _cli_json(capsys, ["diagnose", str(log), "--kt", "0.1", "--effects", effects,
                           "--max-order", str(QUICK), "--quiet", "--json", *extra])
    return d, {c["effect"]: c for c in d["candidates"]}


def test_cli_one_direction_at_constant_speed(tmp_path: Path,
                                             capsys: pytest.CaptureFixture[str]) -> None:
    # 'poor': 20 rad/s forward, nothing else: Coulomb friction and an offset are one
    # column, and at constant speed both are also viscous friction
    log = _sim(tmp_path, capsys, "poor", "--duration", "12", "--excitation", "poor",
               "--effects", "inertia,viscous,coulomb")
    d, c = _diagnose(capsys, log, "inertia,viscous")
    for name in ("coulomb", "offset"):
        assert not c[name]["identifiable"] and not c[name]["suggested"], c[name]
        # the reason, and the experiment that would separate it
        assert "forward only" in c[name]["reason"]
        assert "record a run in both directions" in c[name]["reason"]
    assert d["suggestion"]["add"] == []
    v = d["verdict"]
    assert "record a run in both directions" in v and "complete" not in v
    assert "--add" not in v


def test_cli_short_travel_suggests_no_harmonic_longer_than_the_travel(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    # 'prbs': +-5 rad/s switched every 40 ms: the position wanders over half a turn
    log = _sim(tmp_path, capsys, "prbs", "--duration", "10", "--excitation", "prbs",
               "--effects", "inertia,viscous,coulomb,unbalance")
    d, c = _diagnose(capsys, log, "inertia,viscous,coulomb")
    cov = d["excitation"]["coverage"]
    assert cov is not None and cov < 0.5
    assert c["unbalance"]["explained"] > 0.9  # it would fit the slow trend perfectly ...
    for name, cand in c.items():
        k = 1 if name == "unbalance" else int(name[8:]) if name.startswith("cogging:") else 0
        if k and k * cov < MIN_PERIODS:
            # ... and is neither suggested nor ranked above any identifiable candidate
            assert not cand["identifiable"] and not cand["suggested"], cand
            assert "record more travel" in cand["reason"]
    ranks = [x["identifiable"] for x in d["candidates"]]
    assert ranks == sorted(ranks, reverse=True)  # identifiable ones first
    assert not any(a == "unbalance" or a.startswith("cogging:") for a in d["suggestion"]["add"])
    assert "record more travel" in d["verdict"] and "complete" not in d["verdict"]


def test_cli_no_position_logged_names_position_effects_untested(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    # a drive whose DBC carries no position signal at all
    from importlib.resources import files

    dbc = tmp_path / "nopos.dbc"
    text = (files("canrls") / "data" / "canrls.dbc").read_text(encoding="utf-8")
    dbc.write_text("".join(line for line in text.splitlines(keepends=True)
                           if "SG_ Position" not in line), encoding="utf-8")
    log = _sim(tmp_path, capsys, "std", "--duration", "20")
    d, c = _diagnose(capsys, log, "inertia,viscous,coulomb", "--dbc", str(dbc))
    assert "unbalance" not in c and not any(n.startswith("cogging") for n in c)
    untested = {x["effect"]: x["reason"] for x in d["not_applicable"]}
    assert "position" in untested["unbalance"] and "position" in untested["cogging:K"]
    v = d["verdict"]
    assert "complete for this data" in v
    assert "no effect of the library that these data could test" in v
    assert "Untested: unbalance, cogging:K (needs the position" in v


def test_whiteness_passes_yet_a_candidate_explains_most_so_not_complete() -> None:
    # PRBS around standstill: the speed's sign flips faster than the whiteness test's
    # decimation, so a missing Coulomb friction leaves a residual that passes the test
    # while the Coulomb candidate would explain nearly all of it. The verdict follows
    # the candidates, not the whiteness test.
    rep = _run("inertia,viscous,coulomb", "inertia,viscous", "prbs", duration=12.0)
    prim = rep.before.primary
    assert prim.whiteness is not None and prim.whiteness.white
    best = max(prim.candidates, key=lambda x: x.explained)
    assert best.explained >= 0.75
    v = prim.verdict
    assert "complete" not in v
    assert best.effect in v and "would explain" in v
    # and the text does not let "white" stand alone
    text = rep.format()
    white = next(i for i, ln in enumerate(text.splitlines()) if "whiteness: white" in ln)
    assert f"white, yet not complete: {best.effect} would explain" in \
        text.splitlines()[white + 1]


def test_complete_names_the_candidates_these_data_could_not_excite() -> None:
    # 8 s of the standard profile never dwell near standstill: Stribeck friction is not
    # excited. The right model is complete for what could be tested, and says which
    # effect could not be.
    rep = _run("inertia,viscous,coulomb", "inertia,viscous,coulomb", "standard",
               duration=8.0)
    prim = rep.before.primary
    strib = next(c for c in prim.candidates if c.effect == "stribeck")
    assert not strib.identifiable and strib.explained < 0.05
    v = prim.verdict
    assert "complete for this data" in v and "could test" in v
    assert "Untested: stribeck (not excited" in v
    assert "not identifiable from this data" not in v
