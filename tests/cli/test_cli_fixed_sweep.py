"""`canrls fixed-sweep`: error against word length, with a recommendation."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from canrls.can.logs import write_candump
from canrls.cli.main import main
from canrls.sim.scenario import scenario, simulate


def test_sweep_on_a_log_recommends_a_configuration(tmp_path: Path,
                                                   capsys: pytest.CaptureFixture[str]) -> None:
    res = simulate(scenario("standard", effects="inertia,viscous,coulomb,offset", seed=2,
                            duration=12.0))
    log = tmp_path / "drive.log"
    write_candump(log, [res.frames])
    assert main(["fixed-sweep", str(log), "--kt", "0.1", "--effects",
                 "inertia,viscous,coulomb,offset", "--word", "16,32", "--acc", "64",
                 "--input", "16,32", "--json"]) == 0
    d = json.loads(capsys.readouterr().out)
    mech = d["equations"]["mechanical"]
    rows = {r["label"]: r for r in mech["rows"]}
    assert set(rows) == {"W16/A64/I16", "W16/A64/I32", "W32/A64/I16", "W32/A64/I32"}
    # 32-bit state meets 0.1 %; 16-bit state does not; the smallest that meets it wins
    assert rows["W32/A64/I32"]["ok"] and rows["W32/A64/I32"]["max_rel_error"] < 1e-3
    assert not rows["W16/A64/I16"]["ok"]
    assert mech["recommended"] == "W32/A64/I16"
    assert mech["parameters"] == ["inertia.J", "viscous.B", "coulomb.Tc", "offset.T0"]
    # text mode prints the table and the chosen Q formats
    assert main(["fixed-sweep", str(log), "--kt", "0.1", "--effects",
                 "inertia,viscous,coulomb,offset", "--word", "32", "--acc", "64",
                 "--input", "32"]) == 0
    out = capsys.readouterr().out
    assert "recommended: W32/A64/I32" in out and "Q formats:" in out


def test_sweep_on_a_scenario(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["fixed-sweep", "--scenario", "standard", "--duration", "8", "--kt", "0.1",
                 "--word", "24,32", "--acc", "64", "--input", "32", "--json"]) == 0
    d = json.loads(capsys.readouterr().out)
    assert d["equations"]["mechanical"]["recommended"] in ("W24/A64/I32", "W32/A64/I32")


def test_several_logs_and_the_note_of_fit(tmp_path: Path,
                                          capsys: pytest.CaptureFixture[str]) -> None:
    """fixed-sweep reads several logs as one model, as fit does (the same rows: its 32-bit
    row gives fit's fixed point); fit says when its word lengths cannot follow the float,
    and names the sweep."""
    logs = []
    for seed in (2, 3):
        res = simulate(scenario("standard", effects="inertia,viscous,coulomb", seed=seed,
                                duration=6.0))
        logs.append(tmp_path / f"drive{seed}.log")
        write_candump(logs[-1], [res.frames])
    args = [*map(str, logs), "--kt", "0.1", "--effects", "inertia,viscous,coulomb"]
    assert main(["fixed-sweep", *args, "--word", "16,32", "--acc", "64", "--input", "32",
                 "--json", "--quiet"]) == 0
    d = json.loads(capsys.readouterr().out)
    assert d["source"] == f"{logs[0]}, {logs[1]}"
    mech = d["equations"]["mechanical"]
    rows = {r["label"]: r for r in mech["rows"]}
    assert not rows["W16/A64/I32"]["ok"] and mech["recommended"] == "W32/A64/I32"
    # the sweep runs the kernel on the float front end: fit's column of the same kernel
    assert main(["fit", *args, "--fixed", "kernel", "--json", "--quiet"]) == 0
    fit = json.loads(capsys.readouterr().out)
    assert mech["samples"] == fit["samples"]
    div = fit["equations"]["mechanical"]["divergence"]
    # the same measure: max |fixed - float| / max(|float|, 3 sigma) over the parameters
    assert rows["W32/A64/I32"]["max_rel_error"] == pytest.approx(div, rel=1e-6)
    assert div < 1e-3
    cfg = tmp_path / "narrow.toml"
    cfg.write_text("[fixed]\nword_bits = 24\ninput_bits = 8\n")
    assert main(["fit", *args, "-C", str(cfg), "--quiet"]) == 0
    out = capsys.readouterr().out
    assert "the fixed point (W24/A64/I8) is" in out and "'canrls fixed-sweep'" in out


def test_a_stribeck_speed_left_open_is_searched_as_fit_searches_it(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """A model with Stribeck friction and no speed configured: the sweep's row of fit's
    words is still fit's divergence (the model fit identifies, its speed searched)."""
    effects = "inertia,viscous,coulomb,stribeck"
    res = simulate(scenario("standard", effects=effects, seed=2, duration=20.0))
    log = tmp_path / "drive.log"
    write_candump(log, [res.frames])
    args = [str(log), "--kt", "0.1", "--effects", effects]
    assert main(["fit", *args, "--fixed", "kernel", "--json", "--quiet"]) == 0
    fit = json.loads(capsys.readouterr().out)
    assert [s["key"] for s in fit["search"]] == ["stribeck_speed"]
    assert main(["fixed-sweep", *args, "--word", "32", "--acc", "64", "--input", "32",
                 "--json", "--quiet"]) == 0
    mech = json.loads(capsys.readouterr().out)["equations"]["mechanical"]
    assert mech["rows"][0]["max_rel_error"] == pytest.approx(
        fit["equations"]["mechanical"]["divergence"], rel=1e-6)
