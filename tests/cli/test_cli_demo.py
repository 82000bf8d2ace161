"""``canrls demo``: the story in one command, on the simulated drive."""

from __future__ import annotations

import io
import json

import pytest

from canrls.cli.demo import run_demo
from canrls.cli.main import main
from canrls.core.errors import ConfigError


def test_demo_finds_and_fixes_the_hidden_effect() -> None:
    out = io.StringIO()
    res = run_demo(duration=40.0, seed=2, hidden="unbalance", out=out)
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
