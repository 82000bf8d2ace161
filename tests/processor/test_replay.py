"""Offline replay and `canrls fit`: logs of the simulated drive through the whole pipeline."""

from __future__ import annotations

import dataclasses
import json
import re
from pathlib import Path

import numpy as np
import pytest

from canrls.can.frameblock import FrameBlock
from canrls.can.logs import read_frames, write_candump
from canrls.cli.main import main
from canrls.core.errors import ConfigError, EffectError
from canrls.core.samples import Signals
from canrls.estimation.pipeline import Pipeline
from canrls.processor import FrameProcessor
from canrls.processor.config import AppConfig, prepare
from canrls.processor.replay import fit_frames, fit_log, fit_logs
from canrls.sim.scenario import scenario, simulate

EFFECTS = "inertia,viscous,coulomb,offset"


@pytest.fixture(scope="module")
def sim_log(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, object]:
    res = simulate(scenario("standard", effects=EFFECTS, seed=4, duration=20.0))
    path = tmp_path_factory.mktemp("replay") / "drive.log"
    write_candump(path, [res.frames])
    return path, res


def _setup(effects: str = EFFECTS, kt: float | None = 0.1, log: Path | None = None) -> tuple:
    cfg = AppConfig()
    cfg.model = {"effects": effects.split(",")}
    if kt is not None:
        cfg.model["kt"] = kt
    return prepare(cfg)


def test_fit_log_recovers_the_true_parameters(sim_log: tuple[Path, object]) -> None:
    path, res = sim_log
    prot, model, settings = _setup(log=path)
    fit = fit_log(path, prot, model, settings)
    truth = res.truth.params  # type: ignore[attr-defined]
    for p in fit.parameters:
        assert p.value == pytest.approx(truth[p.name], rel=0.02), p
    assert fit.frames.total == len(res.frames)  # type: ignore[attr-defined]
    assert sum(fit.frames.rejected.values()) == 0
    # the residual is close to the noise floor of the simulated current sensor
    assert fit.residual_rms < 2.0 * res.noise_floor  # type: ignore[attr-defined]
    assert 90.0 < fit.fit_percent <= 100.0


def test_replay_is_bit_identical_whatever_the_block_sizes(sim_log: tuple[Path, object]) -> None:
    path, _ = sim_log
    prot, model, settings = _setup(log=path)
    whole = FrameBlock.concat(read_frames(path))
    a = fit_frames([whole], prot, model, settings)
    rng = np.random.default_rng(7)
    cuts = np.sort(rng.choice(len(whole), 40, replace=False))
    blocks = [whole.take(slice(int(s), int(e)))
              for s, e in zip(np.r_[0, cuts], np.r_[cuts, len(whole)], strict=True)]
    b = fit_frames(blocks, prot, model, settings)
    # one frame at a time, as the daemon may see them
    proc = FrameProcessor(prot, model, settings)
    for k in range(0, 3000):
        proc.process(whole.take(slice(k, k + 1)))
    proc.process(whole.take(slice(3000, len(whole))))
    proc.flush()
    c = proc.result("one by one")
    for pa, pb, pc in zip(a.parameters, b.parameters, c.parameters, strict=True):
        assert pa.value == pb.value == pc.value
        assert pa.fixed == pb.fixed == pc.fixed


def test_missing_effect_shows_in_the_residual(sim_log: tuple[Path, object]) -> None:
    path, _ = sim_log
    full = fit_log(path, *_setup(log=path))
    lacking = fit_log(path, *_setup("inertia,viscous,coulomb", log=path))
    assert lacking.residual_rms > 2 * full.residual_rms


def test_cli_fit_json(sim_log: tuple[Path, object], capsys: pytest.CaptureFixture[str]) -> None:
    path, res = sim_log
    assert main(["fit", str(path), "--kt", "0.1", "--effects", EFFECTS, "--json"]) == 0
    d = json.loads(capsys.readouterr().out)
    assert set(d["parameters"]) == set(res.truth.params)  # type: ignore[attr-defined]
    for name, p in d["parameters"].items():
        assert {"value", "sigma", "unit", "fixed"} <= set(p)
        assert p["value"] == pytest.approx(res.truth.params[name], rel=0.02)  # type: ignore[attr-defined]
    assert d["parameters"]["coulomb.Tc"]["unit"] == "N·m"
    assert d["residual_rms"] > 0 and 90 < d["fit_percent"] <= 100
    assert d["frames"]["total"] == len(res.frames)  # type: ignore[attr-defined]


def test_cli_fit_text_and_config_file(sim_log: tuple[Path, object], tmp_path: Path,
                                      capsys: pytest.CaptureFixture[str]) -> None:
    path, _ = sim_log
    cfg = tmp_path / "canrls.toml"
    cfg.write_text('[model]\nkt = 0.1\neffects = ["inertia", "viscous", "coulomb", "offset"]\n'
                   '[estimator]\nlambda = 1.0\n')
    assert main(["fit", str(path), "--config", str(cfg)]) == 0
    out = capsys.readouterr().out
    for name in ("inertia.J", "viscous.B", "coulomb.Tc", "offset.T0", "residual RMS", "fit"):
        assert name in out
    # the answer first: the parameters and the fit, then what the replay read
    lines = out.splitlines()
    assert lines[0].startswith("parameter "), lines[:2]
    fit_line = next(i for i, x in enumerate(lines) if x.startswith("mechanical: residual RMS"))
    read = next(i for i, x in enumerate(lines) if x.startswith(f"{path}: "))
    assert fit_line < read, out
    # the command line overrides the file
    assert main(["fit", str(path), "--config", str(cfg), "--effects", "inertia,viscous",
                 "--json"]) == 0
    d = json.loads(capsys.readouterr().out)
    assert set(d["parameters"]) == {"inertia.J", "viscous.B"}


def test_the_saturations_are_named_not_a_dict(sim_log: tuple[Path, object]) -> None:
    path, _ = sim_log
    prot, model, settings = _setup(log=path)
    est = fit_log(path, prot, model, settings).estimates
    eq = dataclasses.replace(est.equations[0], saturations={"phi": 3, "P": 1})
    line = next(x for x in dataclasses.replace(est, equations=(eq,)).format().splitlines()
                if x.startswith("mechanical: residual RMS"))
    assert "saturations phi 3, P 1" in line and "{" not in line, line


def test_without_kt_parameters_are_per_ampere(sim_log: tuple[Path, object]) -> None:
    path, res = sim_log
    fit = fit_log(path, *_setup(kt=None, log=path))
    tc = fit.estimates["coulomb.Tc"]
    assert tc.unit == "A"
    assert tc.value == pytest.approx(res.truth.params["coulomb.Tc"] / 0.1, rel=0.02)  # type: ignore[attr-defined]


def test_bad_inputs_are_clear_errors(tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                     sim_log: tuple[Path, object]) -> None:
    path, _ = sim_log
    assert main(["fit", str(path), "--effects", "inertia,friction"]) == 1
    assert "friction" in capsys.readouterr().err
    bad = tmp_path / "bad.toml"
    bad.write_text("[estimator]\nlamda = 0.99\n")
    assert main(["fit", str(path), "--config", str(bad)]) == 1
    err = capsys.readouterr().err
    assert "bad.toml" in err and "estimator.lamda" in err
    with pytest.raises(ConfigError, match="missing.toml"):
        AppConfig.load(bad.parent / "missing.toml")
    assert main(["fit", str(tmp_path / "none.log")]) == 1
    assert "none.log" in capsys.readouterr().err
    with pytest.raises(EffectError):
        _setup("inertia,electrical,nonsense")


def test_calibration_is_frozen_recorded_and_the_held_samples_are_used(
        sim_log: tuple[Path, object]) -> None:
    """The first calibration_s seconds are held back, then calibrate the normalisation and
    the prior, and are estimated on: nothing is lost, and the result is recorded."""
    path, res = sim_log
    cfg = AppConfig()
    cfg.model = {"effects": EFFECTS.split(","), "kt": 0.1}
    cfg.estimator = {"calibration_s": 3.0}
    prot = cfg.protocol()
    proc = FrameProcessor(prot, cfg.model_for(prot), cfg.settings())
    blocks = list(read_frames(path, chunk_size=1000))
    proc.process(blocks[0])
    assert proc.calibrating and proc.pipeline.samples == 0  # held back
    for b in blocks[1:]:
        proc.process(b)
    proc.flush()
    cal = proc.calibration
    assert cal is not None and cal.samples == 3000
    assert cal.t_end - cal.t_start == pytest.approx(2.999, abs=1e-6)
    assert cal.sources["current"] == cal.sources["speed"] == "dbc"
    assert proc.model.exponents["mechanical"] == cal.scaling["mechanical"]
    fit = proc.result("calibrated")
    assert fit.estimates.samples > 19000  # the held samples were estimated on too
    d = fit.to_dict()["calibration"]
    assert d["window"]["samples"] == 3000 and d["ranges"]["speed"]["source"] == "dbc"
    assert "calibration: first 3000 samples" in fit.format()
    for p in fit.parameters:
        assert p.value == pytest.approx(res.truth.params[p.name], rel=0.02), p  # type: ignore[attr-defined]
        assert p.fixed == pytest.approx(p.value, rel=1e-3), p


def _recorded_fit(path: Path, model_cfg: dict) -> tuple:
    """(estimates, normalised regressors and targets of the used rows, equation)."""
    cfg = AppConfig()
    cfg.model = {"effects": EFFECTS.split(","), "kt": 0.1, **model_cfg}
    prot = cfg.protocol()
    proc = FrameProcessor(prot, cfg.model_for(prot), cfg.settings())
    blocks = [proc.process(b, record=True) for b in read_frames(path)]
    blocks.append(proc.flush(record=True))
    eq = proc.pipeline.estimators[0].equation
    used = [b.equations[0] for b in blocks if len(b.equations[0].t)]
    phi = np.concatenate([e.phi[e.used] for e in used])
    y = np.concatenate([np.ldexp(e.y[e.used], -eq.scaling.output) for e in used])
    return proc.pipeline.estimates(), (phi, y), eq


def _samples(path: Path) -> Signals:
    proc = FrameProcessor(AppConfig().protocol(), AppConfig().model_for())
    return Signals.concat([s for b in read_frames(path) if len(s := proc.samples(b))])


def test_ridge_does_not_bias_and_scaling_changes_rounding_only(
        sim_log: tuple[Path, object]) -> None:
    """With lambda = 1 the ridge moves no parameter by more than a tenth of its sigma
    (against an independent batch least squares of the same regressors), and the same
    log fitted under very different normalisations gives the same float parameters."""
    path, _ = sim_log
    est, (phi, y), eq = _recorded_fit(path, {})
    # batch least squares of the same rows, no prior: theta = argmin |y - Phi theta|
    theta_ls = eq.to_physical(np.linalg.lstsq(phi, y, rcond=None)[0])
    for p, ls in zip(est.parameters, theta_ls, strict=True):
        assert abs(p.value - ls) < 0.1 * p.sigma, (p, ls)
    # very different exponents (the columns 2**5 up or down, 2**10 apart, the target
    # 2**3): the float parameters agree to the rounding of the worse-scaled problem,
    # far inside 0.1 sigma (the fixed-point ones saturate: the exponents leave no room)
    s = eq.scaling
    far = {"mechanical": {"output": s.output + 3,
                          **{p.name: c + (5 if j % 2 else -5) for j, (p, c) in
                             enumerate(zip(eq.parameters, s.columns, strict=True))}}}
    other, _, eq2 = _recorded_fit(path, {"scaling": far})
    assert eq2.scaling.columns != eq.scaling.columns
    for a, b in zip(est.parameters, other.parameters, strict=True):
        assert abs(a.value - b.value) < 0.01 * a.sigma, (a, b)
    # the uniform prior P0 = I/alpha of before, in the same two normalisations, does
    # depend on them: the check above can fail
    sig = _samples(path)
    moved = []
    for e in (eq, eq2):
        pipe = Pipeline(e.model, 1e-3)
        pipe.process(sig)
        moved.append(pipe.estimates())
    assert max(abs(a.value - b.value) / a.sigma for a, b in
               zip(moved[0].parameters, moved[1].parameters, strict=True)) > 0.1


def test_faulty_frames_are_rejected_and_lost_samples_do_not_bias(tmp_path: Path) -> None:
    """Dropped, duplicated, reordered, corrupted frames and a silence: the strict decoder
    rejects and counts them, pairing never makes a sample from stale data, and short
    gaps keep the filter's time base (inertia would come out ~5 % low otherwise)."""
    res = simulate(scenario("standard", effects="inertia,viscous,coulomb", seed=3,
                            duration=20.0,
                            faults="drop=0.01,dup=0.005,reorder=0.01,corrupt=0.001,"
                                   "silence=0.5s@10s"))
    path = tmp_path / "faulty.log"
    write_candump(path, [res.frames])
    fit = fit_log(path, *_setup("inertia,viscous,coulomb", log=path))
    log = res.fault_log
    assert fit.frames.rejected["crc"] == log.corrupted
    assert fit.frames.rejected["repeated"] == log.duplicated
    assert sum(fit.frames.lost.values()) > 0 and fit.frames.pairing["unpaired"] > 0
    for p in fit.parameters:
        assert p.value == pytest.approx(res.truth.params[p.name], rel=0.01), p
        assert p.fixed == pytest.approx(p.value, rel=1e-3), p


def _edited(src: Path, dst: Path, edit: object) -> Path:
    """``src``'s lines, each through ``edit`` (a line or None to drop it), into ``dst``."""
    lines = [edit(line) for line in src.read_text().splitlines()]  # type: ignore[operator]
    dst.write_text("".join(line + "\n" for line in lines if line is not None))
    return dst


def _times8(line: str) -> str:
    close = line.index(")")
    return f"({float(line[1:close]) * 8:.6f}{line[close:]}"


def _every_other_speed(line: str) -> str | None:
    # the speed frames come 0.1 ms after the current's: drop those of odd milliseconds
    t = float(line[1:line.index(")")])
    return None if " 102#" in line and round(t * 1e4) % 20 == 11 else line


@pytest.mark.parametrize("edit, message", [
    (lambda line: line.replace(" 101#", " 00000101#").replace(" 102#", " 00000102#"),
     "none of the mapped messages occurs"),
    (_every_other_speed, "the mapped messages come at different periods"),
    (_times8, "the GenMsgCycleTime of DBC canrls.dbc gives a control period of 1 ms"),
])
def test_what_a_logs_frames_say_is_an_error_naming_the_log(
        sim_log: tuple[Path, object], tmp_path: Path, edit: object, message: str) -> None:
    """A log whose frames cannot be paired (no mapped ID, messages at two periods, times
    that disagree with the DBC's cycle time) said so without naming the log: with
    several logs the user could not tell which. The period is measured on the first."""
    path, _ = sim_log
    bad = _edited(path, tmp_path / "bad.log", edit)
    prot, model, settings = _setup()
    with pytest.raises(ConfigError, match="^" + re.escape(str(bad)) + ": " + message):
        fit_logs([bad, path], prot, model, settings)


def test_a_later_log_without_a_mapped_message_is_an_error_naming_it(
        sim_log: tuple[Path, object], tmp_path: Path) -> None:
    """The first log's frames measure the period and its error names the IDs seen; a later
    log with frames but none of a mapped message was passed over in silence (it added no
    sample), as if it had been fitted."""
    path, _ = sim_log
    other = _edited(path, tmp_path / "other.log",
                    lambda line: line.replace(" 101#", " 00000101#").replace(" 102#",
                                                                             " 00000102#"))
    prot, model, settings = _setup()
    with pytest.raises(ConfigError, match="^" + re.escape(str(other)) + ": none of the "
                       "mapped messages occurs in its [0-9]+ frames .*it would add no sample"):
        fit_logs([path, other], prot, model, settings)
