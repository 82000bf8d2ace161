"""``canrls diagnose``: options, JSON, text, report, errors."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

import pytest

from canrls.cli.main import build_parser, main

MODEL = ["--kt", "0.1", "--effects", "inertia,viscous,coulomb"]
QUICK = ["--max-order", "16"]


@pytest.fixture(scope="module")
def log(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("diag") / "drive.log"
    rc = main(["sim", "--out", str(path), "--duration", "20", "--seed", "1",
               "--effects", "inertia,viscous,coulomb,offset"])
    assert rc == 0
    return path


def _json(capsys: pytest.CaptureFixture[str], argv: list[str]) -> dict[str, Any]:
    assert main(argv) == 0
    out: dict[str, Any] = json.loads(capsys.readouterr().out)
    return out


def _options(name: str) -> set[str]:
    parser = build_parser()
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    p = sub.choices[name]
    return {s for a in p._actions for s in a.option_strings}


def test_takes_every_option_of_fit() -> None:
    fit, diag = _options("fit"), _options("diagnose")
    # but fit's --fixed, which takes fit's fixed-point column from the target's integer
    # path (the exported C's): the diagnosis is the float model's and keeps the kernel's
    assert fit - {"--fixed"} <= diag, fit - diag
    assert "--fixed" in fit and "--fixed" not in diag
    assert {"--add", "--report", "--max-order"} <= diag


def test_json_before_after_and_candidates(log: Path, capsys: pytest.CaptureFixture[str]) -> None:
    d = _json(capsys, ["diagnose", str(log), *MODEL, *QUICK, "--add", "offset", "--json"])
    before, after = d["before"], d["after"]
    assert d["added"] == ["offset"]
    assert before["residual_rms"] > 10 * after["residual_rms"]
    assert after["fit_percent"] > before["fit_percent"]
    assert set(after["parameters"]) == {"inertia.J", "viscous.B", "coulomb.Tc", "offset.T0"}
    t0 = after["parameters"]["offset.T0"]
    assert t0["unit"] == "N·m" and t0["value"] == pytest.approx(0.005, rel=0.02)
    assert {"value", "sigma", "unit", "fixed"} <= set(t0)
    cands = d["candidates"]
    assert cands[0]["effect"] == "offset" and cands[0]["suggested"]
    for c in cands:
        assert {"effect", "explained", "delta_bic", "rms_after"} <= set(c)
        assert 0.0 <= c["explained"] <= 1.0
    assert [c["explained"] for c in cands if c["identifiable"] and not c["suggested"]] == \
        sorted((c["explained"] for c in cands if c["identifiable"] and not c["suggested"]),
               reverse=True)
    assert d["suggestion"]["add"] == ["offset"]
    assert d["frames"]["total"] == 40000
    assert d["source"] == str(log)


def test_before_has_the_parameters_of_fit(log: Path, capsys: pytest.CaptureFixture[str]) -> None:
    # diagnose's fixed column is the kernel's (docs/diagnose.md): fit --fixed kernel's
    fit = _json(capsys, ["fit", str(log), *MODEL, "--json", "--fixed", "kernel"])
    d = _json(capsys, ["diagnose", str(log), *MODEL, *QUICK, "--json"])
    assert d["before"]["parameters"] == fit["parameters"]
    # ... and every float value and sigma is plain fit's (whose fixed column is the target's)
    plain = _json(capsys, ["fit", str(log), *MODEL, "--json"])
    assert {n: (p["value"], p["sigma"]) for n, p in plain["parameters"].items()} == {
        n: (p["value"], p["sigma"]) for n, p in d["before"]["parameters"].items()}
    assert d["before"]["residual_rms"] == fit["residual_rms"]
    assert d["before"]["fit_percent"] == fit["fit_percent"]
    assert d["after"] is None and d["added"] == []


def test_before_is_fit_with_the_stribeck_speed_fit_searches(
        log: Path, capsys: pytest.CaptureFixture[str]) -> None:
    # a model with Stribeck friction and no speed configured: canrls fit searches the
    # speed on the record, and the diagnosis's "before" is still fit's, bit for bit
    model = ["--kt", "0.1", "--effects", "inertia,viscous,coulomb,stribeck"]
    fit = _json(capsys, ["fit", str(log), *model, "--json", "--fixed", "kernel"])
    assert [s["key"] for s in fit["search"]] == ["stribeck_speed"]
    d = _json(capsys, ["diagnose", str(log), *model, *QUICK, "--json"])
    assert d["before"]["parameters"] == fit["parameters"]
    assert d["before"]["residual_rms"] == fit["residual_rms"]


def test_text_and_report(log: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    pytest.importorskip("matplotlib")
    out_dir = tmp_path / "report"
    assert main(["diagnose", str(log), *MODEL, *QUICK, "--add", "offset",
                 "--report", str(out_dir)]) == 0
    text = capsys.readouterr().out
    # the answer first: how far the residual fell with the effect added, and what is left
    first = text.splitlines()[0]
    assert first.startswith("After --add offset: residual RMS "), text[:400]
    assert "mechanical: the model is complete for this data" in first, first
    assert "Which effect is missing" in text
    assert "Verdict: mechanical: missing offset" in text
    assert "Before and after --add offset" in text
    assert f"report: {out_dir / 'index.html'}" in text
    assert (out_dir / "index.html").is_file()
    for svg in ("timeline.svg", "speed.svg", "position.svg", "candidates.svg", "orders.svg",
                "convergence.svg", "fixed.svg"):
        assert (out_dir / svg).stat().st_size > 1000, svg


def test_the_first_line_is_the_verdict(log: Path, capsys: pytest.CaptureFixture[str]) -> None:
    # what the command read (the control period, the values used) comes under the answer
    assert main(["diagnose", str(log), *MODEL, *QUICK]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[0].startswith("Verdict: mechanical: missing offset; "), lines[:3]
    assert lines[0].endswith(")."), lines[0]
    assert any(x.startswith("control period ") for x in lines[1:4]), lines[:4]


def test_report_without_matplotlib_is_a_clear_error(log: Path, tmp_path: Path,
                                                     capsys: pytest.CaptureFixture[str],
                                                     monkeypatch: pytest.MonkeyPatch) -> None:
    for mod in [m for m in sys.modules if m == "matplotlib" or m.startswith("matplotlib.")]:
        monkeypatch.delitem(sys.modules, mod)
    monkeypatch.setitem(sys.modules, "matplotlib", None)
    assert main(["diagnose", str(log), *MODEL, "--report", str(tmp_path / "r")]) == 1
    err = capsys.readouterr().err
    assert err.startswith("error: ") and "matplotlib" in err
    assert not (tmp_path / "r").exists()


@pytest.mark.parametrize("argv, message", [
    (["--add", "friction"], "unknown effect 'friction'"),
    (["--add", "coulomb"], "already in the model"),
])
def test_bad_add_is_one_error_line(log: Path, capsys: pytest.CaptureFixture[str],
                                   argv: list[str], message: str) -> None:
    assert main(["diagnose", str(log), *MODEL, *argv]) == 1
    err = capsys.readouterr().err
    assert err.startswith("error: ") and message in err
    assert err.count("\n") == 1


def test_max_order_must_be_positive(log: Path, capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit):
        main(["diagnose", str(log), "--max-order", "0"])
    assert "--max-order" in capsys.readouterr().err


def test_a_unit_matplotlib_would_read_as_mathtext_is_drawn_as_text(
        log: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """Issue 30, 4: a user term's unit `$a^$` ended `diagnose --report` with exit 3
    (matplotlib's mathtext parser); it is plain text now (canrls.figtext.plain)."""
    pytest.importorskip("matplotlib")
    cfg = tmp_path / "drive.toml"
    cfg.write_text('[model]\neffects = ["inertia", "viscous", "coulomb", "user:drag"]\n'
                   'kt = 0.1\n[[model.terms]]\nname = "drag"\nexpr = "speed * abs(speed)"\n'
                   'unit = "$a^$"\n')
    out_dir = tmp_path / "report"
    assert main(["diagnose", str(log), "--config", str(cfg), *QUICK,
                 "--report", str(out_dir)]) == 0, capsys.readouterr().err
    assert (out_dir / "convergence.svg").stat().st_size > 1000
