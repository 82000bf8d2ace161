"""``canrls demo``: the story in one command, on the simulated drive."""

from __future__ import annotations

import io
import json

import pytest

from canrls.cli.demo import run_demo
from canrls.cli.main import main
from canrls.core.errors import ConfigError


def test_demo_finds_and_fixes_the_hidden_effect(caplog: pytest.LogCaptureFixture) -> None:
    out = io.StringIO()
    with caplog.at_level("WARNING"):
        res = run_demo(duration=40.0, seed=2, hidden="unbalance", out=out)
    # its fixed column is the target's integer path, as canrls run publishes by default
    assert "no target path" not in caplog.text and "thread failed" not in caplog.text
    text = out.getvalue()
    for piece in ("1. Estimating with the incomplete model", "2. Diagnosis",
                  "3. Sending RlsCommand add_effect", "RlsCommandAck: ok",
                  "4. Estimating with the completed model", "the residual RMS falls from",
                  "unbalance.sin", "truth"):
        assert piece in text, piece
    assert res.ack == "ok" and res.diagnosed == res.added == "unbalance"
    assert res.improvement > 0.4, text
    assert res.parameters["unbalance.sin"]["truth"] == 0.008
    assert res.parameters["unbalance.sin"]["float"] == pytest.approx(0.008, rel=0.25)
    assert res.parameters["unbalance.sin"]["fixed"] == pytest.approx(0.008, rel=0.25)


def test_demo_cli_json(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["demo", "--duration", "40", "--seed", "3", "--hidden", "cogging:6",
                 "--json"]) == 0
    cap = capsys.readouterr()
    res = json.loads(cap.out)
    assert res["hidden"] == "cogging:6" and res["ack"] == "ok"
    assert res["rms_after"] < res["rms_before"]
    assert "the residual RMS falls" in cap.err  # the story goes to stderr with --json


@pytest.mark.parametrize("hidden", ["inertia", "unbalance,offset", "nonsense"])
def test_demo_rejects_bad_hidden_effects(hidden: str) -> None:
    with pytest.raises(ConfigError):
        run_demo(duration=20.0, hidden=hidden, out=io.StringIO())


def test_demo_of_four_axes_fixes_the_one_axis_that_hides_an_effect(
        capsys: pytest.CaptureFixture[str]) -> None:
    """``canrls demo --axes 4``: seed 4 hides cogging:6 in axis3 only; the diagnosis names
    it there and nowhere else, the command reaches axis3 alone, its error falls."""
    assert main(["demo", "--axes", "4", "--duration", "12", "--seed", "4", "--hidden",
                 "cogging:6", "--json"]) == 0
    cap = capsys.readouterr()
    res = json.loads(cap.out)
    story = cap.err.splitlines()
    assert story[0] == res["answer"]  # the first line says the answer
    assert story[0].startswith("canrls demo: axis3 lacks cogging:6; added to it alone, its "
                               "residual RMS fell ")
    assert res["fixed_axis"] == "axis3" and res["added"] == "cogging:6"
    axes = res["axes"]
    assert [a["hidden"] for a in axes.values()] == ["", "", "cogging:6", ""]
    assert [a["diagnosed"] for a in axes.values()] == [None, None, "cogging:6", None]
    assert axes["axis3"]["effects"] == ["inertia", "viscous", "coulomb", "cogging:6"]
    assert all(axes[n]["effects"] == ["inertia", "viscous", "coulomb"]
               for n in ("axis1", "axis2", "axis4"))
    assert axes["axis3"]["change"] < -0.5, cap.err
    assert "3. RlsCommand add_effect cogging:6 to axis3 only (ID 0x3a0):" in story
    # the command is taken at once, not after the other axes were let go
    assert ("  axis3 now estimates inertia, viscous, coulomb, cogging:6; the others "
            "inertia, viscous, coulomb") in story
    # the machine is the simulated one on its own bus, as canrls run -i canrls-sim sees it
    assert story[1].startswith("4 simulated drives on one bus (canrls-sim), seed 4")


@pytest.mark.parametrize("axes", ["0", "33"])
def test_demo_refuses_a_machine_it_cannot_simulate(
        axes: str, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["demo", "--axes", axes]) == 1
    assert capsys.readouterr().err == (f"error: --axes {axes}: the machine demo has 2 to 32 "
                                       "axes\n")


def test_demo_of_a_machine_refuses_an_excitation_it_would_not_use(
        capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["demo", "--axes", "4", "--excitation", "slow"]) == 1
    assert capsys.readouterr().err == ("error: --excitation slow: the drives of --axes 4 run "
                                       "the simulated machine's own profile\n")
