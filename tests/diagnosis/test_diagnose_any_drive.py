"""The diagnosis on any drive (issue 28): excitation judged from the data, every
nonlinear parameter searched.

The simulated drive is encoded in a vendor's DBC that declares its speed over the raw
range of a 32-bit field (``tests/data/vendor32_drive.dbc``) and in the same DBC with
tidy limits; both must give the same answers. Hidden effects the simulator does not
model (a fan load, a dead time) are added to the measured current exactly as the
equation of motion carries them.
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt
import pytest

from canrls.can.encoder import FeedbackEncoder
from canrls.can.logs import write_log
from canrls.can.protocol import Protocol
from canrls.cli.main import main
from canrls.core.errors import ConfigError
from canrls.diagnosis.analysis import diagnose_log
from canrls.diagnosis.report import DiagnosisReport
from canrls.diagnosis.results import SearchResult
from canrls.estimation.model import Model
from canrls.sim.excitation import Sequence, chirp, phases
from canrls.sim.scenario import SimResult, scenario, simulate

F64 = npt.NDArray[np.float64]
DATA = Path(__file__).resolve().parents[1] / "data"
SIGNALS = ["current=MotorFeedback.PhaseCurrent", "speed=MotorFeedback.MotorSpeed",
           "position=MotorAngle.Angle"]
RAW32 = "[-21474836.48|21474836.47]"
KT = 0.1
TERMS = [{"name": "drag", "expr": "omega * abs(omega)", "unit": "rad²/s²"},
         {"name": "dead", "expr": "tanh(current / c)", "search": {"c": [0.005, 0.5]}}]
BASE = ["inertia", "viscous", "coulomb"]


def _dbc(tmp: Path, kind: str) -> Path:
    text = (DATA / "vendor32_drive.dbc").read_text()
    assert RAW32 in text
    if kind == "tidy":
        text = text.replace(RAW32, "[-3000|3000]")
    path = tmp / f"{kind}.dbc"
    path.write_text(text)
    return path


def _excitation() -> Sequence:
    """Reversals from 0.1 to 60 rad/s (the Stribeck bump's both sides; half the time
    above 12 rad/s) and a chirp."""
    return Sequence([phases([0.1, 0.3, 1.0, 3.0, 15.0, 30.0, 60.0], accel=40.0,
                            holds=[1.0, 1.0, 1.0, 1.0, 2.0, 2.0, 2.0]),
                     chirp(30.0, 0.2, 8.0, 6.0)], name="low and high speeds")


def _sim(effects: str, seed: int, **kw: float) -> SimResult:
    return simulate(scenario("standard", effects=effects, seed=seed, duration=30.0,
                             excitation=_excitation(), speed_noise=0.002, **kw))


def _log(tmp: Path, kind: str, res: SimResult,
         current: Callable[[SimResult], F64] | None = None) -> tuple[Path, Protocol]:
    """The run encoded in the vendor DBC (``raw32`` or ``tidy``), with the measured
    current as ``current`` makes it."""
    proto = Protocol.load(_dbc(tmp, kind), SIGNALS)
    m = res.measured
    i = np.asarray(m.current) if current is None else current(res)
    path = tmp / f"{kind}.log"
    write_log(path, [FeedbackEncoder(proto).encode(m.t, i, m.speed, m.position)])
    return path, proto


def _diagnose(path: Path, proto: Protocol, effects: list[str] = BASE,
              add: tuple[str, ...] = (), terms: list[dict[str, Any]] = TERMS,
              **options: float) -> DiagnosisReport:
    model = Model(effects, terms=terms, options_given=frozenset(options), **options)
    return diagnose_log(path, proto, model, max_order=4, add=add)


def _first(rep: DiagnosisReport) -> str:
    q = rep.before.equations[0]
    assert q.suggestion, q.verdict
    return q.suggestion.add[0]


@pytest.mark.parametrize("kind", ["raw32", "tidy"])
def test_a_fan_load_is_suggested_whatever_range_the_dbc_declares(
        tmp_path: Path, kind: str) -> None:
    res = _sim("inertia,viscous,coulomb", seed=3)
    c = 2e-6  # N·m/(rad/s)²: 1.8e-3 N·m at 30 rad/s, the Coulomb friction's tenth

    def with_drag(r: SimResult) -> F64:
        w = np.asarray(r.true.speed)
        return np.asarray(r.measured.current) + c * w * np.abs(w) / KT

    rep = _diagnose(*_log(tmp_path, kind, res, with_drag))
    q = rep.before.equations[0]
    assert _first(rep) == "user:drag", q.verdict
    cand = q.candidate("user:drag")
    assert cand.identifiable and "not excited" not in cand.reason
    assert cand.parameters["user:drag.c"][0] == pytest.approx(c / KT, rel=0.5)


@pytest.mark.parametrize("kind", ["raw32", "tidy"])
@pytest.mark.parametrize("ws", [0.2, 0.8, 3.0])
def test_stribeck_is_named_first_and_its_speed_found(tmp_path: Path, kind: str,
                                                     ws: float) -> None:
    res = _sim("inertia,viscous,coulomb,stribeck", seed=4, stribeck_speed=ws)
    path, proto = _log(tmp_path, kind, res)
    rep = _diagnose(path, proto, add=("stribeck",))
    assert _first(rep) == "stribeck"
    found = rep.before.equations[0].candidate("stribeck").search
    assert [r.key for r in found] == ["stribeck_speed"] and not found[0].kept
    # measured: 0.30, 0.80, 2.98 (the profile holds two speeds near 0.2 rad/s)
    assert abs(math.log(found[0].value / ws)) <= math.log(1.6)
    assert rep.after is not None
    assert rep.after.model.stribeck_speed == pytest.approx(found[0].value)
    # the batch least squares that knows the true speed
    known = _diagnose(path, proto, [*BASE, "stribeck"], stribeck_speed=ws)
    rms_found = rep.after.equations[0].residual_rms_ls
    rms_known = known.before.equations[0].residual_rms_ls
    assert rms_found <= 1.15 * rms_known, (rms_found, rms_known)


def test_a_stribeck_speed_set_in_the_configuration_is_kept(tmp_path: Path) -> None:
    res = _sim("inertia,viscous,coulomb,stribeck", seed=4, stribeck_speed=0.8)
    rep = _diagnose(*_log(tmp_path, "raw32", res), stribeck_speed=2.0)
    (r,) = rep.before.equations[0].candidate("stribeck").search
    assert r.kept and r.value == 2.0
    assert "Stribeck speed 2 rad/s (set in the configuration: kept)" in rep.format()


@pytest.mark.parametrize("kind", ["raw32", "tidy"])
def test_a_dead_time_term_has_its_width_searched(tmp_path: Path, kind: str) -> None:
    # the standard profile: its chirp and PRBS take the current through zero in motion
    # (on the reversals alone tanh(i / c) is the sign of the speed: Coulomb friction)
    res = simulate(scenario("standard", seed=5, duration=30.0))
    d, c0 = 0.002, 0.05  # N·m, A

    def with_dead_time(r: SimResult) -> F64:
        # Kt i - d tanh(i / c0) = the plant's torque Kt i_sim (a contraction: d/(Kt c0) < 1)
        i0 = np.asarray(r.measured.current)
        i = i0.copy()
        for _ in range(60):
            i = i0 + d / KT * np.tanh(i / c0)
        return i

    rep = _diagnose(*_log(tmp_path, kind, res, with_dead_time))
    assert _first(rep) == "user:dead"
    (r,) = rep.before.equations[0].candidate("user:dead").search
    assert r.key == "user:dead:c" and not r.kept
    # measured: 0.075 A (the complete model's own residual structure pulls it)
    assert c0 / 2.5 <= r.value <= 2.5 * c0
    assert f"user:dead c {r.value:.4g} (searched 0.005..0.5, 16 values" in rep.format()


@pytest.mark.slow
@pytest.mark.parametrize("profile", ["low and high speeds", "standard"])
@pytest.mark.parametrize("seed", range(10))
def test_no_false_suggestion_on_the_complete_model(tmp_path: Path, seed: int,
                                                   profile: str) -> None:
    # the standard profile leaves the filter's errors-in-variables bias in the residual:
    # a searched Stribeck speed or dead-time width took 5 to 9 % of it before the
    # searched candidates had to explain MIN_EXPLAINED_SEARCHED
    res = (_sim("inertia,viscous,coulomb", seed=100 + seed) if profile != "standard" else
           simulate(scenario("standard", seed=100 + seed, duration=30.0)))
    rep = _diagnose(*_log(tmp_path, "raw32" if seed % 2 else "tidy", res))
    q = rep.before.equations[0]
    assert not q.suggestion, q.verdict
    assert all(not c.suggested for c in q.candidates)


def test_a_bad_search_names_the_key(tmp_path: Path) -> None:
    path = tmp_path / "drive.toml"
    path.write_text('[model]\neffects = ["inertia", "user:dead"]\n[[model.terms]]\n'
                    'name = "dead"\nexpr = "tanh(current / c)"\nsearch = { c = [0.5, 0.005] }\n')
    from canrls.processor.config import load_model
    with pytest.raises(ConfigError, match=r"drive\.toml: model\.terms\[0\].*search\.c"):
        load_model(path)


def _cli(capsys: pytest.CaptureFixture[str], cmd: str, path: Path, *extra: str) -> str:
    flags = [a for s in SIGNALS for a in ("--signal", s)]
    assert main([cmd, str(path), "--dbc", str(path.with_suffix(".dbc")), *flags, "-q",
                 *extra]) == 0
    return capsys.readouterr().out


def test_fit_searches_the_stribeck_speed_it_is_not_given(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    res = simulate(scenario("standard", effects="inertia,viscous,coulomb,stribeck", seed=4,
                            duration=30.0, stribeck_speed=3.0))
    path, _ = _log(tmp_path, "raw32", res)
    eff = ["-e", "inertia,viscous,coulomb,stribeck"]
    d = json.loads(_cli(capsys, "fit", path, *eff, "--json"))
    (r,) = d["search"]
    assert r["key"] == "stribeck_speed" and not r["kept"]
    assert r["value"] == pytest.approx(3.0, rel=0.1)  # measured: 2.996
    ts = d["parameters"]["stribeck.Ts"]
    assert ts["value"] == pytest.approx(res.truth["stribeck.Ts"] / KT, rel=0.05)
    assert "stribeck_speed" not in d["calibration"]["defaults"]
    text = _cli(capsys, "fit", path, *eff)
    assert f"Stribeck speed {r['value']:.4g} rad/s (searched " in text
    assert f"set [model.stribeck] speed = {r['value']:.4g} for 'canrls run'" in text


def test_without_kt_the_units_say_per_ampere(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path, _ = _log(tmp_path, "raw32", _sim("inertia,viscous,coulomb", seed=6))
    line = ("units: no Kt and no torque signal, so the mechanical parameters are per "
            "ampere (A where N·m would be): multiply them by Kt [N·m/A] for N·m, or "
            "give --kt")
    text = _cli(capsys, "fit", path)
    assert text.count(line) == 1
    assert json.loads(_cli(capsys, "fit", path, "--json"))["axis"]["per_ampere"] == line
    assert line not in _cli(capsys, "fit", path, "--kt", "0.1")
    assert json.loads(_cli(capsys, "fit", path, "--kt", "0.1", "--json"))["axis"][
        "per_ampere"] is None
    diag = _cli(capsys, "diagnose", path, "--max-order", "2")
    assert diag.count(line) == 1
    assert json.loads(_cli(capsys, "diagnose", path, "--max-order", "2", "--json"))[
        "per_ampere"] == line


def test_the_daemon_without_kt_says_per_ampere(
        caplog: pytest.LogCaptureFixture, capsys: pytest.CaptureFixture[str]) -> None:
    for kt, times in (([], 1), (["--kt", "0.1"], 0)):
        caplog.clear()
        assert main(["run", "-i", "virtual", "-c", "issue28-units", "--duration", "0.2",
                     *kt]) == 0
        said = [r for r in caplog.records if "per ampere" in r.getMessage()]
        assert len(said) == times
    capsys.readouterr()


@pytest.mark.parametrize("band", [None, 0.02])
def test_a_missing_coulomb_friction_has_its_band_searched_or_kept(
        tmp_path: Path, band: float | None) -> None:
    path, proto = _log(tmp_path, "raw32", _sim("inertia,viscous,coulomb", seed=7))
    opts = {} if band is None else {"coulomb_band": band}
    # without the dead-time term: on these reversals tanh(i / c) is the sign of the
    # speed, and the diagnosis says it cannot tell the two apart
    rep = _diagnose(path, proto, ["inertia", "viscous"], terms=TERMS[:1], **opts)
    assert _first(rep) == "coulomb"
    (r,) = rep.before.equations[0].candidate("coulomb").search
    assert r.key == "coulomb_band" and r.kept == (band is not None)
    if band is None:
        assert r.lo < r.value < r.hi and r.delta_bic < 0
    else:
        assert r.value == band
        assert "Coulomb band 0.02 rad/s (set in the configuration: kept)" in rep.format()


def test_a_value_found_at_the_grid_s_end_reads_inside_the_range_searched() -> None:
    # the value and the range at the same precision: 9.859 was shown "searched 9.86..13.4"
    r = SearchResult("stribeck_speed", "Stribeck speed", "rad/s", 9.85942, False, 9.85942,
                     13.3449, 16, 10.27)
    assert "Stribeck speed 9.859 rad/s (searched 9.859..13.34 rad/s, 16 values" in r.text()
