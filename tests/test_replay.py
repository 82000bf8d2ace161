"""Offline replay and `canrls fit`: logs of the simulated drive through the whole pipeline."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from canrls.can.frameblock import FrameBlock
from canrls.can.logs import read_frames, write_candump
from canrls.cli.main import main
from canrls.config import AppConfig
from canrls.errors import ConfigError, EffectError
from canrls.processor import FrameProcessor
from canrls.replay import fit_frames, fit_log, prepare
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
    return prepare(cfg, log)


def test_fit_log_recovers_the_true_parameters(sim_log: tuple[Path, object]) -> None:
    path, res = sim_log
    prot, model, settings = _setup(log=path)
    fit = fit_log(path, prot, model, settings)
    truth = res.truth.params  # type: ignore[attr-defined]
    for p in fit.parameters:
        assert p.value == pytest.approx(truth[p.name], rel=0.02), p
    assert fit.frames == len(res.frames)  # type: ignore[attr-defined]
    assert sum(fit.rejected.values()) == 0
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
    # the command line overrides the file
    assert main(["fit", str(path), "--config", str(cfg), "--effects", "inertia,viscous",
                 "--json"]) == 0
    d = json.loads(capsys.readouterr().out)
    assert set(d["parameters"]) == {"inertia.J", "viscous.B"}


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


def test_calibration_from_the_first_seconds_matches_a_prescan(
        sim_log: tuple[Path, object]) -> None:
    """No ranges configured: the first seconds of samples calibrate them (they must be
    representative: the standard excitation reaches full speed after about 15 s)."""
    path, res = sim_log
    cfg = AppConfig()
    cfg.model = {"effects": EFFECTS.split(","), "kt": 0.1}
    prot = cfg.protocol()
    default_model = cfg.model_for(prot)
    proc = FrameProcessor(prot, default_model, cfg.settings(),
                          calibrate=lambda r: cfg.model_for(prot, r), calibrate_s=16.0)
    assert proc.calibrating
    blocks = list(read_frames(path, chunk_size=1000))
    proc.process(blocks[0])
    assert proc.calibrating and proc.pipeline.samples == 0  # held back
    for b in blocks[1:]:
        proc.process(b)
    proc.flush()
    assert not proc.calibrating
    assert proc.model.ranges["current"] != default_model.ranges["current"]
    fit = proc.result("calibrated")
    for p in fit.parameters:
        assert p.value == pytest.approx(res.truth.params[p.name], rel=0.02), p  # type: ignore[attr-defined]
        assert p.fixed == pytest.approx(p.value, rel=1e-3), p


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
    assert fit.rejected["crc"] == log.corrupted
    assert fit.rejected["repeated"] == log.duplicated
    assert sum(fit.lost.values()) > 0 and fit.pairing["unpaired"] > 0
    for p in fit.parameters:
        assert p.value == pytest.approx(res.truth.params[p.name], rel=0.01), p
        assert p.fixed == pytest.approx(p.value, rel=1e-3), p
