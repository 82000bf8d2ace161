"""Limits: input that used to cost exponential time, or to escape as a raw traceback,
is refused with one ``error:`` line naming the file and the field; an unexpected
exception in a command is one ``internal error:`` line and exit status 3."""

from __future__ import annotations

import re
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

import can
import numpy as np
import pytest
from cli_tool import cli_error

from canrls.can.frameblock import MAX_DATA_LENGTH, FrameBlock
from canrls.cli.main import INTERNAL_ERROR, main
from canrls.core.errors import ConfigError, DecodeError, ExpressionError
from canrls.estimation.expr import compile_expression
from canrls.estimation.svf import MAX_TIME_CONSTANT, SVF, ZETA_RANGE
from canrls.processor.config import MAX_DEPTH, load_config, read_toml

USER = ('[model]\neffects = ["inertia", "viscous", "coulomb", "user:d"]\n'
        '[[model.terms]]\nname = "d"\nexpr = "{expr}"\n{extra}\n')


@pytest.fixture(scope="module")
def log(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("limits") / "drive.log"
    assert main(["sim", "--out", str(path), "--duration", "2", "--seed", "1"]) == 0
    return path


def _fit_with(tmp_path: Path, log: Path, capsys: pytest.CaptureFixture[str],
              text: str) -> str:
    cfg = tmp_path / "drive.toml"
    cfg.write_text(text)
    line = cli_error(capsys, ["fit", "--config", str(cfg), str(log)])
    assert str(cfg) in line
    return line


# ------------------------------------------------------------------------ configuration
def test_theta_max_of_the_wrong_type_names_the_key(tmp_path: Path, log: Path,
                                                    capsys: pytest.CaptureFixture[str]) -> None:
    line = _fit_with(tmp_path, log, capsys, '[fixed]\ntheta_max = "big"\n')
    assert "fixed.theta_max = 'big'" in line


def test_huge_zeta_is_refused_by_its_range(tmp_path: Path, log: Path,
                                           capsys: pytest.CaptureFixture[str]) -> None:
    line = _fit_with(tmp_path, log, capsys, "[model.filter]\nzeta = 1e8\n")
    assert "model.filter.zeta" in line and "damping ratio" in line


@pytest.mark.parametrize("value", ["1e308", "1e-320", "nan"])
def test_alpha_out_of_range_names_the_flag(log: Path, value: str,
                                           capsys: pytest.CaptureFixture[str]) -> None:
    # 1e308 and 1e-320 used to end in "range of P: QFormat frac must be in -64..126",
    # nan in "<defaults>: estimator.alpha = nan": neither named --alpha
    line = cli_error(capsys, ["fit", "--alpha", value, str(log)])
    assert line.startswith(f"error: --alpha {value}: must be "), line


def test_alpha_out_of_range_names_the_key(tmp_path: Path, log: Path,
                                          capsys: pytest.CaptureFixture[str]) -> None:
    line = _fit_with(tmp_path, log, capsys, "[estimator]\nalpha = 1e300\n")
    assert "estimator.alpha = 1e+300: must be from 1e-09 to 1e+09" in line


@pytest.mark.parametrize("value", ["1e-9", "1e-6"])
def test_alpha_too_small_for_the_fixed_point_names_the_smallest(
        log: Path, value: str, capsys: pytest.CaptureFixture[str]) -> None:
    """--help called 1e-9 valid and every alpha below about 1e-5 was refused with a
    Q-format message: now the one limit (P0 needs a Q format) is named, the same for
    any alpha below it, and the value named is accepted."""
    effects = ["-e", "inertia,viscous,coulomb,offset"]
    line = cli_error(capsys, ["fit", "--alpha", value, *effects, str(log)])
    m = re.search(r"estimator\.alpha = [0-9.e+-]+: too small for the fixed-point words: "
                  r"the smallest is ([0-9.e+-]+) here", line)
    assert m, line
    assert main(["fit", "--alpha", m.group(1), *effects, "--quiet", str(log)]) == 0
    assert float(m.group(1)) == pytest.approx(7.7e-6, rel=0.3)  # 4 parameters, 32 bits


def test_a_cogging_order_of_5000_digits_is_one_short_error_line(
        log: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """-e cogging:<5000 digits> ended in "internal error: ValueError: Exceeds the limit
    (4300 digits)" (exit 3)."""
    line = cli_error(capsys, ["fit", "--kt", "0.1", "-e", "cogging:" + "9" * 5000, str(log)])
    assert "must be an integer from 1 to 65535" in line and len(line) < 600, line


def test_a_kt_whose_torque_overflows_is_one_error_line_naming_kt(
        log: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """--kt 1e308 printed numpy's overflow warnings, then "cannot quantize NaN to Q1.30":
    now the one line names model.kt and what overflowed (no warning: one line)."""
    line = cli_error(capsys, ["fit", "--kt", "1e308", "-e", "inertia,viscous", str(log)])
    assert line.startswith("error: model.kt = 1e+308: the output motor torque"), line
    assert "overflows a double" in line


def test_alpha_help_states_the_fixed_point_limit(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit):
        main(["fit", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    assert "1e-9 to 1e9, and at least what the fixed-point words hold" in text


def test_vanishing_cutoff_is_refused_before_allocating(
        tmp_path: Path, log: Path, capsys: pytest.CaptureFixture[str]) -> None:
    line = _fit_with(tmp_path, log, capsys, "[model.filter]\ncutoff_hz = 1e-300\n")
    assert "cutoff_hz = 1e-300" in line and str(MAX_TIME_CONSTANT) in line


def test_svf_limits_in_the_api() -> None:
    with pytest.raises(ConfigError, match="damping ratio"):
        SVF(25.0, 1e-3, ZETA_RANGE[1] * 10)
    with pytest.raises(ConfigError, match="damping ratio"):
        SVF(25.0, 1e-3, ZETA_RANGE[0] / 10)
    with pytest.raises(ConfigError, match="too low"):
        SVF(1e-300, 1e-3)
    SVF(25.0, 1e-3, ZETA_RANGE[1])  # the limits themselves are allowed


def test_term_range_given_as_a_table(tmp_path: Path, log: Path,
                                     capsys: pytest.CaptureFixture[str]) -> None:
    line = _fit_with(tmp_path, log, capsys,
                     USER.format(expr="omega * abs(omega)", extra="range = {}"))
    assert "model.terms[0] (d)" in line and "range = {}" in line


def test_term_range_of_strings_is_refused(tmp_path: Path, log: Path,
                                          capsys: pytest.CaptureFixture[str]) -> None:
    line = _fit_with(tmp_path, log, capsys,
                     USER.format(expr="omega * abs(omega)", extra='range = ["-1", "1"]'))
    assert "range = ('-1', '1')" in line


def test_deeply_nested_toml(tmp_path: Path, log: Path,
                            capsys: pytest.CaptureFixture[str]) -> None:
    # deeper than Python's recursion limit: tomllib itself used to overflow
    line = _fit_with(tmp_path, log, capsys, "a = " + "[" * 3000 + "]" * 3000 + "\n")
    assert f"nested deeper than {MAX_DEPTH}" in line


def test_nesting_just_past_the_limit_names_the_key(tmp_path: Path) -> None:
    p = tmp_path / "deep.toml"
    p.write_text("[model]\nx = " + "[" * MAX_DEPTH + "]" * MAX_DEPTH + "\n")
    with pytest.raises(ConfigError, match=r"deep.toml: model\.x(\[0\])+: nested deeper"):
        read_toml(p)
    p.write_text("[model]\nx = " + "[" * (MAX_DEPTH - 1) + "]" * (MAX_DEPTH - 1) + "\n")
    assert read_toml(p)["model"]["x"]  # at the limit: read


@pytest.mark.parametrize("table,key", [("estimator", "alpha"), ("model", "kt"),
                                       ("fixed", "word_bits"), ("can", "period")])
def test_310_digit_integer_names_the_key(tmp_path: Path, log: Path,
                                         capsys: pytest.CaptureFixture[str],
                                         table: str, key: str) -> None:
    line = _fit_with(tmp_path, log, capsys, f"[{table}]\n{key} = {'9' * 310}\n")
    assert f"{table}.{key}" in line and "64-bit" in line
    assert "9" * 30 not in line  # the message stays one short line


def test_64_bit_integers_are_read(tmp_path: Path) -> None:
    p = tmp_path / "ints.toml"
    p.write_text(f"[estimator]\nalpha = {2**63 - 1}\nlambda = {-2**63}\n")
    assert load_config(p).estimator["alpha"] == 2**63 - 1


# --------------------------------------------------------------------------- expressions
def _calls_of(fn: Callable[[], Any]) -> int:
    """Python function calls made by ``fn()`` (a count, not a time)."""
    n = 0

    def count(frame: Any, event: str, arg: Any) -> None:
        nonlocal n
        if event == "call":
            n += 1

    sys.setprofile(count)
    try:
        fn()
    finally:
        sys.setprofile(None)
    return n


@pytest.mark.parametrize("op", ["-", "+-", "-+"])
def test_bounds_of_nested_unary_minus_are_linear(op: str) -> None:
    ranges = {"speed": (-1.0, 2.0)}
    calls = []
    for depth in (8, 9, 10, 16):
        e = compile_expression(op * depth + "omega", name="d")
        calls.append(_calls_of(lambda e=e: e.bounds(ranges)))
        lo, hi = e.bounds(ranges)
        minus = (op * depth).count("-")
        assert (lo, hi) == ((-2.0, 1.0) if minus % 2 else (-1.0, 2.0))
    step = calls[1] - calls[0]
    assert calls[2] - calls[1] == step  # a constant per level, not a doubling
    assert calls[3] - calls[2] == 6 * step


def test_310_digit_literal_in_an_expression() -> None:
    with pytest.raises(ExpressionError, match="must be finite"):
        compile_expression("omega * " + "9" * 310, name="d")
    e = compile_expression("omega * " + "9" * 300, name="d")  # fits a float64
    assert e({"speed": np.ones(2)})[0] == float("9" * 300)


# ------------------------------------------------------------------------------ frames
def test_candump_line_with_256_data_bytes(tmp_path: Path, log: Path,
                                          capsys: pytest.CaptureFixture[str]) -> None:
    bad = tmp_path / "bad.log"
    lines = log.read_text().splitlines()
    bad.write_text("\n".join(lines[:20] + ["(1.000000) can0 123##0" + "00" * 256]
                             + lines[20:]) + "\n")
    line = cli_error(capsys, ["fit", str(bad)])
    assert f"{bad}:21" in line and "256 data bytes" in line


def test_frame_block_refuses_frames_longer_than_can_fd() -> None:
    ok = can.Message(arbitration_id=0x123, data=bytes(MAX_DATA_LENGTH), is_fd=True)
    assert FrameBlock.from_messages([ok]).dlc[0] == MAX_DATA_LENGTH
    long = can.Message(arbitration_id=0x123, data=bytes(MAX_DATA_LENGTH + 1), is_fd=True)
    with pytest.raises(DecodeError, match="0x123.*65 data bytes") as info:
        FrameBlock.from_messages([ok, long])
    assert info.value.reason == "length"


# ----------------------------------------------------------------------- internal errors
def _failing(monkeypatch: pytest.MonkeyPatch, exc: BaseException) -> None:
    import canrls.cli.fit as fit

    def boom(args: Any) -> int:
        raise exc

    monkeypatch.setattr(fit, "run", boom)


def test_unexpected_exception_is_one_internal_error_line(
        monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str],
        tmp_path: Path) -> None:
    _failing(monkeypatch, KeyError("theta\nsecond line"))
    rc = main(["fit", str(tmp_path / "x.log")])
    err = capsys.readouterr().err
    assert rc == INTERNAL_ERROR == 3
    lines = err.splitlines()
    assert len(lines) == 1 and lines[0].startswith("internal error: KeyError: ")
    assert "--debug" in lines[0] and "Traceback" not in err


def test_debug_shows_the_internal_error(monkeypatch: pytest.MonkeyPatch,
                                        tmp_path: Path) -> None:
    _failing(monkeypatch, RuntimeError("bug"))
    with pytest.raises(RuntimeError, match="bug"):
        main(["--debug", "fit", str(tmp_path / "x.log")])


def test_canrls_error_stays_exit_status_1(monkeypatch: pytest.MonkeyPatch,
                                          capsys: pytest.CaptureFixture[str],
                                          tmp_path: Path) -> None:
    _failing(monkeypatch, ConfigError("x.toml: model.kt = 0: must not be 0"))
    assert main(["fit", str(tmp_path / "x.log")]) == 1
    assert capsys.readouterr().err == "error: x.toml: model.kt = 0: must not be 0\n"


# ------------------------------------------------------------------------------ diagnose
def test_max_order_is_bounded(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """--max-order 100000000 built 2e8 candidate columns per block of rows (it ran for
    minutes and then out of memory); now argparse refuses it, naming the limit."""
    from canrls.diagnosis.candidates import MAX_ORDER_LIMIT

    with pytest.raises(SystemExit) as info:
        main(["diagnose", "--max-order", "100000000", str(tmp_path / "x.log")])
    assert info.value.code == 2
    assert f"must be in 1..{MAX_ORDER_LIMIT}" in capsys.readouterr().err


def test_max_order_is_bounded_in_the_api() -> None:
    from canrls.core.samples import Signals
    from canrls.diagnosis.analysis import diagnose
    from canrls.diagnosis.candidates import MAX_ORDER_LIMIT
    from canrls.estimation.model import Model

    n = 100
    sig = Signals(t=np.arange(n) * 1e-3, current=np.zeros(n), speed=np.zeros(n))
    with pytest.raises(ConfigError, match=f"1..{MAX_ORDER_LIMIT}"):
        diagnose(sig, Model(["inertia"]), max_order=MAX_ORDER_LIMIT + 1)


# ------------------------------------------------------------------------- the output
@pytest.mark.parametrize("argv", [["fit", "--json", "--kt", "0.1"], ["fit", "--kt", "0.1"]])
def test_a_reader_that_leaves_ends_the_command_quietly(log: Path, argv: list[str]) -> None:
    """`canrls fit --json | head -1` ended in "internal error: BrokenPipeError" (exit 3):
    now every subcommand exits quietly with 141, as a Unix tool that SIGPIPE ended."""
    from canrls.cli.main import PIPE_CLOSED

    with subprocess.Popen([sys.executable, "-m", "canrls", *argv, str(log)],
                          stdout=subprocess.PIPE, stderr=subprocess.PIPE) as p:
        assert p.stdout is not None and p.stderr is not None
        p.stdout.close()  # the reader leaves before the command writes its first byte
        err = p.stderr.read().decode()
        assert p.wait(timeout=120) == PIPE_CLOSED, err
    assert err == ""
