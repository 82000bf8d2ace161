"""``canrls tune`` and the control layer, proved in closed loop on the simulated drive.

The maps and gains are made from logs of ordinary motion (the standard excitation), as a
user would; the simulated speed controller then takes them (``canrls sim --feedforward
--gains``, :func:`canrls.cli.sim.with_tuning`). docs/tune.md.
"""

from __future__ import annotations

import json
import math
import re
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from cli_tool import cli_error

from canrls.cli.main import main
from canrls.cli.sim import with_tuning
from canrls.control.feedforward import feedforward
from canrls.control.fixed_map import fixed_harmonics, fixed_map, harmonics_q, map_q
from canrls.processor.modelfile import SavedModel
from canrls.sim.excitation import constant, reversals
from canrls.sim.loop import speed_ripple, step_bandwidth
from canrls.sim.plant import Controller, Plant, Sensors, Truth
from canrls.sim.scenario import Simulator, scenario

COGGING = "inertia,viscous,coulomb,stribeck,cogging:6"
FRICTION = "inertia,viscous,coulomb,stribeck"
#: the simulator samples at t_k and holds the current over the period: half a period
SIM_DELAY = ("--delay", "0.5")


def tuned(tmp: Path, effects: str, *extra: str, seed: int = 1,
          params: tuple[str, ...] = ()) -> Path:
    """``canrls sim`` a 20 s log of ordinary motion, ``canrls tune`` it into ``tmp/out``."""
    log = tmp / "drive.log"
    p = [x for kv in params for x in ("-p", kv)]
    assert main(["sim", "--out", str(log), "--duration", "20", "--effects", effects,
                 "--seed", str(seed), *p]) == 0
    out = tmp / "out"
    assert main(["tune", str(log), "--kt", "0.1", "-e", effects, "--out", str(out),
                 *extra]) == 0
    return out


def closed_loop(effects: str, ex: Any, duration: float, ff: Path | None,
                gains: Path | None = None) -> Any:
    """The simulated drive under its speed controller (with the files, if given)."""
    sc = scenario("standard", effects=effects, excitation=ex, duration=duration, seed=3)
    sc = with_tuning(sc, None if ff is None else str(ff), None if gains is None else str(gains))
    return Simulator(sc).step(sc.periods)


def harmonic_ripple(ch: Any, skip: int = 3000) -> float:
    """The ripple an engineer sees on the rig, after the first 3 s."""
    return speed_ripple(ch.measured.position[skip:], ch.measured.speed[skip:])


def test_speed_ripple_at_5_rad_s_falls_by_80_percent(tmp_path: Path,
                                                      capsys: pytest.CaptureFixture[str]
                                                      ) -> None:
    out = tuned(tmp_path, COGGING, *SIM_DELAY)
    # tune's first line (canrls sim's own line, with the truth, comes before it)
    first = capsys.readouterr().out.splitlines()[1]
    assert first.startswith("canrls tune: compensate viscous, coulomb, stribeck, cogging:6")
    before = harmonic_ripple(closed_loop(COGGING, constant(5.0), 8.0, None))
    after = harmonic_ripple(closed_loop(COGGING, constant(5.0), 8.0,
                                        out / "feedforward.json"))
    assert after <= 0.2 * before, (before, after)


def test_speed_error_through_reversals_falls_by_half_with_friction(tmp_path: Path) -> None:
    out = tuned(tmp_path, FRICTION, *SIM_DELAY)
    ff = json.loads((out / "feedforward.json").read_text())
    assert "map" not in ff  # no position term: no map
    ex = reversals(2.0, accel=50.0, hold=1.0)

    def reversal_error(path: Path | None) -> float:
        ch = closed_loop(FRICTION, ex, 12.0, path)
        w_ref, _ = ex.reference(ch.true.t)
        near = np.abs(w_ref) < 1.0  # through the reversals
        near[:2000] = False
        return float(np.sqrt(np.mean((w_ref - ch.true.speed)[near] ** 2)))

    before, after = reversal_error(None), reversal_error(out / "feedforward.json")
    assert after <= 0.5 * before, (before, after)


def closed_loop_bandwidth(gains: dict[str, Any], J: float, kt: float = 0.1) -> float:
    """The bandwidth [Hz] the gains give the drive of inertia ``J``, from speed steps."""
    truth = Truth({"inertia.J": J, "viscous.B": 1e-4, "coulomb.Tc": 0.02}, kt=kt,
                  coulomb_band=1e-3)
    ctl = Controller(kp_speed=gains["kp"] / kt, ki_speed=gains["ki"] / kt)
    return step_bandwidth(Plant(truth, 1e-3, ctl, Sensors(), seed=5), 20.0, 30.0)


@pytest.mark.parametrize("scale", [0.3, 1.0, 3.0])
def test_suggested_gains_reach_the_bandwidth_within_10_percent(tmp_path: Path,
                                                               scale: float) -> None:
    J = 2e-4 * scale
    out = tuned(tmp_path, "inertia,viscous,coulomb", "--bandwidth", "20", *SIM_DELAY,
                seed=2, params=(f"inertia.J={J}",))
    gains = json.loads((out / "gains.json").read_text())
    assert gains["inertia"] == pytest.approx(J, rel=0.01)
    bw = closed_loop_bandwidth(gains, J)
    assert abs(bw - 20.0) <= 2.0, bw


def test_terms_the_data_do_not_support_are_left_out(tmp_path: Path,
                                                    capsys: pytest.CaptureFixture[str]
                                                    ) -> None:
    out = tuned(tmp_path, COGGING)
    ff_all = json.loads((out / "feedforward.json").read_text())
    model = tmp_path / "m.json"
    assert main(["fit", str(tmp_path / "drive.log"), "--kt", "0.1", "-e", COGGING,
                 "--save-model", str(model)]) == 0
    d = json.loads(model.read_text())
    d["parameters"]["cogging:6.sin"]["identifiable"] = False
    d["parameters"]["stribeck.Ts"]["sigma"] = 0.5 * d["parameters"]["stribeck.Ts"]["value"]
    model.write_text(json.dumps(d))
    capsys.readouterr()
    assert main(["tune", "--model", str(model), "--out", str(tmp_path / "o2"),
                 "--current-tau", "0"]) == 0
    text = capsys.readouterr().out
    assert "left out  cogging:6" in text and "cogging:6.sin NOT IDENTIFIABLE" in text
    assert "left out  stribeck" in text and "50% of its size" in text
    ff = json.loads((tmp_path / "o2" / "feedforward.json").read_text())
    assert [t["effect"] for t in ff["terms"] if t["used"]] == ["viscous", "coulomb"]
    # the ripple left is the cogging the map leaves out: about all of it
    r, r_all = ff["ripple"], ff_all["ripple"]
    assert r["after"] == pytest.approx(r["before"], rel=1e-3)
    assert r_all["after"] < 0.01 * r_all["before"]


def test_ripple_and_harmonics_follow_the_parameters() -> None:
    from canrls.estimation.model import Model

    model = Model(["inertia", "unbalance", "cogging:6", "offset"], kt=0.1)
    params = {"inertia.J": {"value": 2e-4, "sigma": 1e-7},
              "unbalance.sin": {"value": 0.004, "sigma": 1e-5},
              "unbalance.cos": {"value": -0.003, "sigma": 1e-5},
              "cogging:6.sin": {"value": 0.003, "sigma": 2e-5},
              "cogging:6.cos": {"value": 0.0, "sigma": 2e-5},
              "offset.T0": {"value": 0.01, "sigma": 1e-4}}
    ff = feedforward(model, params)
    # RMS of A sin: A / sqrt 2; before sqrt((0.005^2 + 0.003^2) / 2)
    assert ff.ripple is not None
    assert ff.ripple.before == pytest.approx(math.sqrt((0.005**2 + 0.003**2) / 2), rel=1e-9)
    # after: sqrt(sum sigma_j^2 / 2) of the terms used
    assert ff.ripple.after == pytest.approx(math.sqrt((2e-10 + 8e-10) / 2), rel=1e-6)
    h = {x.order: x for x in ff.harmonics()}
    assert h[1].amplitude == pytest.approx(0.005) and h[6].sin == 0.003
    assert h[0].cos == 0.01
    pos, tau = ff.position_map(8)
    want = 0.004 * np.sin(pos) - 0.003 * np.cos(pos) + 0.003 * np.sin(6 * pos) + 0.01
    np.testing.assert_allclose(tau, want, atol=1e-15)


@pytest.mark.parametrize("argv, says", [
    (["--points", "0"], "--points 0: the points of a map"),
    (["--points", "1"], "--points 1: the points of a map"),
    (["--points", "65537"], "--points 65537: the points of a map"),
    (["--bandwidth", "0"], "--bandwidth 0"),
    (["--bandwidth", "-5"], "--bandwidth -5"),
    (["--bandwidth", "500"], "Nyquist frequency 500 Hz"),
    (["--bandwidth", "400"], "reaches at most"),
])
def test_bad_requests_are_one_error_and_nothing_written(
        tmp_path: Path, capsys: pytest.CaptureFixture[str], argv: list[str], says: str
) -> None:
    model = saved_model(tmp_path)
    out = tmp_path / "out"
    line = cli_error(capsys, ["tune", "--model", str(model), "--out", str(out), *argv])
    assert says in line
    assert not out.exists() or not any(out.iterdir())


def saved_model(tmp: Path, edit: Any = None) -> Path:
    truth = {"inertia.J": {"value": 2e-4, "sigma": 1e-7, "identifiable": True},
             "cogging:6.sin": {"value": 0.003, "sigma": 1e-5},
             "cogging:6.cos": {"value": 0.001, "sigma": 1e-5}}
    d = {"format": "canrls-model", "version": 1, "effects": ["inertia", "cogging:6"],
         "model": {"axis": "rotary", "kt": 0.1, "effects": ["inertia", "cogging:6"]},
         "parameters": truth, "calibration": {"period": 0.001}}
    if edit is not None:
        edit(d)
    p = tmp / "model.json"
    p.write_text(json.dumps(d))
    return p


@pytest.mark.parametrize("edit, says", [
    (lambda d: d.update(version=2), "model file version 2"),
    (lambda d: d["parameters"]["cogging:6.sin"].update(value=math.nan),
     "parameters.cogging:6.sin.value = nan: must be a finite number"),
    (lambda d: d["parameters"]["cogging:6.cos"].update(sigma=math.inf),
     "parameters.cogging:6.cos.sigma = inf"),
    (lambda d: d.update(calibration=None), "--period: the model file {model} holds no "
                                           "control period (calibration.period)"),
])
def test_bad_model_files_are_one_error_and_nothing_written(
        tmp_path: Path, capsys: pytest.CaptureFixture[str], edit: Any, says: str) -> None:
    model = saved_model(tmp_path, edit)
    out = tmp_path / "out"
    line = cli_error(capsys, ["tune", "--model", str(model), "--out", str(out),
                              "--bandwidth", "20"])
    assert says.format(model=model) in line, line
    assert not out.exists() or not any(out.iterdir())


def test_tuning_on_the_logs_is_tuning_the_model_fit_saves(tmp_path: Path,
                                                         capsys: pytest.CaptureFixture[str]
                                                         ) -> None:
    """``canrls tune LOG [fit options]`` identifies the model as ``canrls fit`` does (the
    Stribeck speed searched on the record): the same answer as ``canrls fit --save-model``
    then ``canrls tune --model`` (docs/tune.md's first block)."""
    log = tmp_path / "drive.log"
    assert main(["sim", "--out", str(log), "--duration", "10", "--effects", COGGING,
                 "--seed", "1"]) == 0
    model = tmp_path / "drive.json"
    assert main(["fit", str(log), "--kt", "0.1", "-e", COGGING, "--save-model",
                 str(model)]) == 0
    capsys.readouterr()
    assert main(["tune", "--model", str(model), "--bandwidth", "20"]) == 0
    from_file = capsys.readouterr().out
    assert main(["tune", str(log), "--kt", "0.1", "-e", COGGING, "--bandwidth", "20"]) == 0
    assert capsys.readouterr().out == from_file


def test_a_model_without_position_asks_for_no_map(tmp_path: Path,
                                                  capsys: pytest.CaptureFixture[str]) -> None:
    model = saved_model(tmp_path, lambda d: (
        d.update(effects=["inertia", "viscous", "offset"]),
        d["model"].update(effects=["inertia", "viscous", "offset"]),
        d.update(parameters={"inertia.J": {"value": 2e-4, "sigma": 1e-7},
                             "viscous.B": {"value": 1e-4, "sigma": 1e-7},
                             "offset.T0": {"value": 0.004, "sigma": 1e-5}})))
    out = tmp_path / "out"
    assert main(["tune", "--model", str(model), "--out", str(out), "--bandwidth", "20"]) == 0
    text = capsys.readouterr().out
    assert "no anticogging map: the model has no term of the position" in text
    assert sorted(p.name for p in out.iterdir()) == ["feedforward.json", "gains.json"]
    # the offset, with no map to hold it, goes with the speed terms, and the simulator
    # takes it
    ff = json.loads((out / "feedforward.json").read_text())
    assert ff["speed"]["parameters"] == {"viscous.B": 1e-4, "offset.T0": 0.004}
    sc = with_tuning(scenario("standard"), str(out / "feedforward.json"), None)
    assert sc.controller.compensation.T0 == 0.004 and sc.controller.compensation.map == ()
    # again without --bandwidth: no gains this time (no current loop's time constant); the
    # gains.json of the run before is kept, and said not to be of this run
    gains = (out / "gains.json").read_bytes()
    assert main(["tune", "--model", str(model), "--out", str(out)]) == 0
    text = capsys.readouterr().out
    assert f"kept {out / 'gains.json'}: an earlier tune's, not of this one" in text, text
    assert f"wrote {out / 'gains.json'}" not in text
    assert (out / "gains.json").read_bytes() == gains


def test_the_diagnosis_says_what_compensation_would_leave(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    log = tmp_path / "drive.log"
    assert main(["sim", "--out", str(log), "--duration", "20", "--effects", COGGING,
                 "--seed", "1"]) == 0
    capsys.readouterr()
    assert main(["diagnose", str(log), "--kt", "0.1", "-e", FRICTION, "--add", "cogging:6",
                 "--json"]) == 0
    comp = json.loads(capsys.readouterr().out)["compensation"]
    assert comp["effects"] == ["cogging:6"]
    # the truth's ripple: sqrt((0.003^2 + 0.0015^2) / 2)
    assert comp["before"] == pytest.approx(math.sqrt((0.003**2 + 0.0015**2) / 2), rel=0.02)
    assert comp["after"] < 0.01 * comp["before"]
    assert main(["diagnose", str(log), "--kt", "0.1", "-e", FRICTION, "--add",
                 "cogging:6"]) == 0
    line = capsys.readouterr().out.splitlines()[-1]
    assert line.startswith("with this compensation (cogging:6; canrls tune), the torque "
                           "ripple would fall: 0.00237 ± ")
    # found, not added: its ripple, no claim on what compensation leaves (no sigma yet)
    assert main(["diagnose", str(log), "--kt", "0.1", "-e", FRICTION]) == 0
    line = capsys.readouterr().out.splitlines()[-1]
    assert line == ("cogging:6 (found): a torque ripple of 0.00237 N·m RMS; add it (--add "
                    "cogging:6) to learn what compensation (canrls tune) would leave")


DRIVER = """#include <stdio.h>
#include <inttypes.h>
#include "canrls_feedforward.h"
int main(void)
{
    unsigned long a;
    while (scanf("%lu", &a) == 1)
        printf("%" PRId32 "\\n", canrls_ff_map_q((uint32_t)a));
    return 0;
}
"""


def c_outputs(out: Path, driver: str, inputs: list[int]) -> list[int]:
    """Compile the exported ``canrls_feedforward.c`` with a driver (the firmware's
    warnings) and run it on ``inputs``, one a line: its outputs."""
    import shutil
    import subprocess

    cc = shutil.which("gcc")
    if cc is None:
        pytest.skip("no C compiler")
    (out / "driver.c").write_text(driver)
    exe = out / "ff"
    subprocess.run([cc, "-std=c99", "-O2", "-Wall", "-Wextra", "-Werror", "-pedantic",
                    "-I", str(out), str(out / "driver.c"), str(out / "canrls_feedforward.c"),
                    "-o", str(exe)], check=True, capture_output=True, text=True)
    got = subprocess.run([str(exe)], input="\n".join(map(str, inputs)) + "\n",
                         capture_output=True, text=True, check=True).stdout.split()
    return [int(g) for g in got]


def some_angles(seed: int) -> list[int]:
    """0, 1, 2**31, 2**32 - 1 and 3,000 seeded random angles (uint32)."""
    rng = np.random.default_rng(seed)
    return [0, 1, 0xFFFFFFFF, 0x80000000, *rng.integers(0, 1 << 32, 3000).tolist()]


@pytest.mark.parametrize("points", [2, 7, 1024, 65536])
def test_the_c_map_is_the_specification_bit_for_bit(tmp_path: Path, points: int) -> None:
    model = saved_model(tmp_path, lambda d: d["parameters"].update({
        "cogging:6.sin": {"value": -0.02, "sigma": 1e-5}}))
    out = tmp_path / "c"
    assert main(["export-c", "--model", str(model), "--out", str(out), "--kernel-only",
                 "--feedforward", str(points)]) == 0
    angles = some_angles(points)
    got = c_outputs(out, DRIVER, angles)
    sm = SavedModel.load(model)
    ff = feedforward(sm.build_model(), sm.parameters)
    pos, tau = ff.position_map(points)
    fm = fixed_map(tau, ff.unit)
    want = [map_q(fm, a) for a in angles]
    assert got == want
    # and the fixed point follows the float map within its rounding (half an LSB of the
    # table and of the interpolation) plus the chord's sag between points
    th = np.array(angles, dtype=np.float64) * (2 * np.pi / 2**32)
    exact = ff.torque(th, np.zeros(len(th)))
    sag = 0.02 * 36 * (2 * np.pi / points) ** 2 / 8
    assert np.max(np.abs(np.array(want) * 2.0**-fm.frac - exact)) <= 2.0**-fm.frac + sag


def test_the_daemon_saves_its_running_model_for_tune(tmp_path: Path,
                                                     capsys: pytest.CaptureFixture[str]
                                                     ) -> None:
    from daemon_tool import ACK_ID, daemon_fed

    from canrls.can.estimator_frames import CommandCode, CommandResult, encode_command
    from canrls.can.frameblock import FrameBlock
    from canrls.live.daemon import DaemonSettings
    from canrls.processor.config import AppConfig

    sc = scenario("standard", effects=COGGING, duration=20.0, seed=1)
    frames = FrameBlock.concat(list(Simulator(sc).frames()))
    cfg = AppConfig()
    cfg.model = {"effects": COGGING.split(","), "kt": 0.1}
    protocol = cfg.protocol()
    path = tmp_path / "live.json"
    dset = DaemonSettings(publish_interval=0.05, info_interval=0.2, commands=True,
                          saved_model=path)
    with daemon_fed(protocol, cfg.model_for(protocol), cfg.settings(),
                    frames.to_messages(), "test-tune-save", daemon=dset,
                    configuration=cfg) as (d, reader):
        d.process([encode_command(CommandCode.SAVE_MODEL)])
        acks = [m for m in reader_messages(reader) if m.arbitration_id == ACK_ID]
    assert acks and CommandResult(acks[-1].data[1]) is CommandResult.OK
    capsys.readouterr()
    assert main(["tune", "--model", str(path), "--bandwidth", "20"]) == 0
    first = capsys.readouterr().out.splitlines()[0]
    assert "compensate viscous, coulomb, stribeck, cogging:6" in first
    saved = json.loads(path.read_text())
    assert saved["calibration"]["period"] == pytest.approx(1e-3)
    assert saved["parameters"]["inertia.J"]["value"] == pytest.approx(2e-4, rel=0.02)


def reader_messages(reader: Any) -> list[Any]:
    """Every message the daemon sent that the reader holds now (after a moment)."""
    import time

    from daemon_tool import collect

    time.sleep(0.2)
    return collect(reader)


def test_save_model_without_a_file_is_not_applicable() -> None:
    from canrls.can.estimator_frames import CommandCode, CommandResult, encode_command
    from canrls.live.commands import CommandHandler
    from canrls.processor import FrameProcessor
    from canrls.processor.config import AppConfig

    cfg = AppConfig()
    cfg.model = {"effects": ["inertia"], "kt": 0.1}
    protocol = cfg.protocol()
    proc = FrameProcessor(protocol, cfg.model_for(protocol), cfg.settings())
    sent: list[Any] = []
    h = CommandHandler(proc, True, lambda m: sent.extend(m) or len(m),
                       lambda m, w: None, lambda: None)
    assert h.handle(encode_command(CommandCode.SAVE_MODEL)) is CommandResult.NOT_APPLICABLE


def test_the_diagnosis_report_page_says_it_too(tmp_path: Path) -> None:
    pytest.importorskip("matplotlib")
    log = tmp_path / "drive.log"
    assert main(["sim", "--out", str(log), "--duration", "10", "--effects", COGGING,
                 "--seed", "1"]) == 0
    assert main(["diagnose", str(log), "--kt", "0.1", "-e", FRICTION, "--add", "cogging:6",
                 "--report", str(tmp_path / "rep")]) == 0
    page = (tmp_path / "rep" / "index.html").read_text()
    assert "<b>Compensation.</b> with this compensation (cogging:6; canrls tune)" in page


HARMONICS_DRIVER = DRIVER.replace("canrls_ff_map_q", "canrls_ff_harmonics_q")


def test_the_c_harmonics_are_the_specification_bit_for_bit(tmp_path: Path) -> None:
    def edit(d: dict[str, Any]) -> None:
        effects = ["inertia", "offset", "unbalance", "cogging:6", "cogging:48"]
        d["effects"] = d["model"]["effects"] = effects
        d["parameters"].update({
            "offset.T0": {"value": -0.011, "sigma": 1e-5},
            "unbalance.sin": {"value": 0.004, "sigma": 1e-5},
            "unbalance.cos": {"value": -0.003, "sigma": 1e-5},
            "cogging:48.sin": {"value": -0.0007, "sigma": 1e-5},
            "cogging:48.cos": {"value": 0.0009, "sigma": 1e-5}})

    model = saved_model(tmp_path, edit)
    out = tmp_path / "c"
    assert main(["export-c", "--model", str(model), "--out", str(out), "--kernel-only",
                 "--feedforward", "1024", "--feedforward-form", "harmonics"]) == 0
    angles = some_angles(48)
    got = c_outputs(out, HARMONICS_DRIVER, angles)
    sm = SavedModel.load(model)
    ff = feedforward(sm.build_model(), sm.parameters)
    fh = fixed_harmonics([(h.order, h.cos if h.order == 0 else h.amplitude, h.phase)
                          for h in ff.harmonics()], ff.unit)
    assert fh.orders == (1, 6, 48)
    want = [harmonics_q(fh, a) for a in angles]
    assert got == want
    # the specification follows the float torque within the sine table's error
    # (1/32767 rounding and the chord's sag (2 pi / 1024)^2 / 8 per amplitude)
    th = np.array(angles, dtype=np.float64) * (2 * np.pi / 2**32)
    exact = ff.torque(th, np.zeros(len(th)))
    amps = 0.005 + math.hypot(0.003, 0.001) + math.hypot(0.0007, 0.0009)
    bound = amps * (1 / 32767 + (2 * np.pi / 1024) ** 2 / 8) + 2 * 2.0**-fh.frac
    err = np.max(np.abs(np.array(want) * 2.0**-fh.frac - exact))
    assert err <= bound, (err, bound)


@pytest.mark.parametrize("which, edit, says", [
    ("feedforward", lambda d: d.update(version=2), "version 2"),
    ("feedforward", lambda d: d.update(format="x"), "not a canrls-feedforward file"),
    ("feedforward", lambda d: d["map"]["torque"].__setitem__(3, math.nan),
     "map.torque[3] = nan"),
    ("feedforward", lambda d: d["map"].update(torque=[0.1]), "map.torque has 1"),
    ("feedforward", lambda d: d.update(lead=-1.0), "lead = -1.0"),
    ("feedforward", lambda d: d["speed"]["parameters"].update({"coulomb.Tc": "big"}),
     "speed.parameters.coulomb.Tc = 'big'"),
    ("gains", lambda d: d.update(kp=0.0), "kp = 0.0"),
    ("gains", lambda d: d.update(unit="furlong"), "unit = 'furlong'"),
])
def test_sim_refuses_bad_tuning_files(tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                      which: str, edit: Any, says: str) -> None:
    model = saved_model(tmp_path)
    out = tmp_path / "out"
    assert main(["tune", "--model", str(model), "--out", str(out), "--bandwidth", "20",
                 "--points", "16"]) == 0
    f = out / ("feedforward.json" if which == "feedforward" else "gains.json")
    d = json.loads(f.read_text())
    edit(d)
    f.write_text(json.dumps(d))
    log = tmp_path / "x.log"
    line = cli_error(capsys, ["sim", "--out", str(log), "--duration", "1",
                              f"--{which}", str(f)])
    assert says in line and str(f) in line
    assert not log.exists()


FRICTION_DRIVER = """#include <stdio.h>
#include <inttypes.h>
#include "canrls_feedforward.h"
int main(void)
{
    long w;
    while (scanf("%ld", &w) == 1)
        printf("%" PRId32 "\\n", canrls_ff_friction_q((int32_t)w));
    return 0;
}
"""


def test_the_c_friction_is_the_specification_bit_for_bit(tmp_path: Path) -> None:
    from canrls.control.fixed_map import fixed_friction, friction_q

    model = saved_model(tmp_path, lambda d: (
        d.update(effects=d["effects"] + ["viscous", "coulomb", "stribeck"]),
        d["model"].update(effects=d["effects"], coulomb={"band": 0.04},
                          stribeck={"speed": 1.0}),
        d["parameters"].update({"viscous.B": {"value": 1e-4, "sigma": 1e-7},
                                "coulomb.Tc": {"value": 0.02, "sigma": 1e-5},
                                "stribeck.Ts": {"value": 0.01, "sigma": 1e-4}})))
    out = tmp_path / "c"
    assert main(["export-c", "--model", str(model), "--out", str(out), "--kernel-only",
                 "--feedforward", "64"]) == 0
    rng = np.random.default_rng(7)
    # Q16 speeds: the extremes, the band, the Stribeck speed and beyond, both signs
    ws = [0, 1, -1, 2**31 - 1, -2**31, *rng.integers(-2**31, 2**31, 1000).tolist(),
          *(rng.normal(0, 0.2, 1000) * 2**16).astype(int).tolist(),
          *(rng.normal(0, 5.0, 1000) * 2**16).astype(int).tolist()]
    got = c_outputs(out, FRICTION_DRIVER, ws)
    fr = fixed_friction(1e-4, 0.02, 0.01, 0.04, 1.0, "N·m")
    want = [friction_q(fr, w) for w in ws]
    assert got == want
    # the specification follows the float friction within the tables' rounding and sag,
    # and B's half LSB times the speed
    w = np.array(ws, dtype=np.float64) / 2**16
    sg = np.tanh(w / 0.04)
    exact = 1e-4 * w + (0.02 + 0.01 * np.exp(-w**2)) * sg
    err = np.abs(np.array(want) * 2.0**-fr.frac - exact)
    assert np.all(err <= 0.03 * 2e-4 + 4 * 2.0**-fr.frac + np.abs(w) * 2.0**-(fr.frac + 1))


def test_a_loop_scans_its_frequency_grid_once(monkeypatch: pytest.MonkeyPatch) -> None:
    """The tuning's bisection asks a loop's bandwidth and margin dozens of times; the
    4,000 frequencies they scan are built once per loop, and the gains are those of a
    grid built every time."""
    from canrls.control import gains as g

    loop = g.Loop(J=2e-4, J_sigma=1e-5, dt=1e-3, Td=1.5e-3, Ti=0.0)
    fresh = g.for_bandwidth(g.Loop(J=2e-4, J_sigma=1e-5, dt=1e-3, Td=1.5e-3, Ti=0.0), 20.0)
    made = []
    real = np.geomspace
    monkeypatch.setattr(np, "geomspace", lambda *a, **k: made.append(a) or real(*a, **k))
    got = g.for_bandwidth(loop, 20.0)
    g.symmetric_optimum(loop)
    assert len(made) == 1, f"the grid was built {len(made)} times"
    assert (got.kp, got.ki, got.bandwidth_hz) == (fresh.kp, fresh.ki, fresh.bandwidth_hz)


@pytest.mark.parametrize("form", ["table", "harmonics"])
def test_export_c_feedforward_reads_the_model_once_and_declares_in_one_guard(
        tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch,
        form: str) -> None:
    """export-c --feedforward read the saved model twice (once for the map, once for the
    export) and put the friction's declaration into the map's header by replacing its
    #endif. One read; the header is generated whole: one include guard around the
    declarations of every function the .c defines, each declared once."""
    model = saved_model(tmp_path, lambda d: (
        d.update(effects=d["effects"] + ["viscous", "coulomb"]),
        d["model"].update(effects=d["effects"]),
        d["parameters"].update({"viscous.B": {"value": 1e-4, "sigma": 1e-7},
                                "coulomb.Tc": {"value": 0.02, "sigma": 1e-5}})))
    reads: list[Path] = []
    real = SavedModel.load

    def counted(path: Any) -> SavedModel:
        reads.append(Path(path))
        return real(path)

    monkeypatch.setattr(SavedModel, "load", staticmethod(counted))
    out = tmp_path / "c"
    assert main(["export-c", "--model", str(model), "--out", str(out), "--kernel-only",
                 "--feedforward", "64", "--feedforward-form", form]) == 0
    assert reads == [model]
    assert "; the friction at the speed reference in Q" in capsys.readouterr().out
    head = (out / "canrls_feedforward.h").read_text()
    c_src = (out / "canrls_feedforward.c").read_text()
    body = head[head.index("#define CANRLS_FEEDFORWARD_H\n"):]
    assert head.count("#ifndef CANRLS_FEEDFORWARD_H") == 1 and body.endswith("\n#endif\n")
    defined = re.findall(r"^int32_t (canrls_ff_\w+)\(", c_src, re.M)
    mapped = "canrls_ff_map_q" if form == "table" else "canrls_ff_harmonics_q"
    assert defined == [mapped, "canrls_ff_friction_q"]
    assert re.findall(r"^int32_t (canrls_ff_\w+)\(.*\);$", body, re.M) == defined
    assert c_src.count("#include") == 1
    driver = DRIVER if form == "table" else HARMONICS_DRIVER
    assert len(c_outputs(out, driver, [0, 1 << 31])) == 2  # it builds with -Werror
