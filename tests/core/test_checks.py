"""canrls.core.checks: each rule once, and every place that takes such a value asks it.

A finite (positive) number: one definition (``is_real``, ``is_positive``), no module
writing it out by hand.

The forgetting factor: the configuration, the command line, the monitor's command, the
command frame the daemon decodes and both estimators take the one range
(:data:`~canrls.core.checks.LAMBDA_MIN`, 1]. Before, a monitor command ``lambda 0.3``
passed the monitor and the frame decoder, then the daemon refused it.
"""

from __future__ import annotations

import ast
import math
import re
import sys
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

from canrls.can.estimator_frames import CommandCode, decode_command, encode_command
from canrls.cli._common import overrides
from canrls.cli.main import build_parser
from canrls.core import checks
from canrls.core.errors import CanrlsError, ConfigError
from canrls.estimation.fixed.formats import check_lam as fixed_check_lam
from canrls.estimation.rls import RLS
from canrls.estimation.settings import EstimatorSettings
from canrls.live.monitor_listener import parse_command_text
from canrls.processor.config import AppConfig

#: every place a forgetting factor enters, each taking ``lam`` or raising a CanrlsError
LAMBDA_TAKERS: dict[str, Callable[[float], object]] = {
    "configuration": lambda lam: _config_settings(lam),
    "settings": lambda lam: EstimatorSettings(lam=lam),
    "command line": lambda lam: _cli_settings(lam),
    "monitor command": lambda lam: parse_command_text(f"lambda {lam!r}"),
    "command frame": lambda lam: decode_command(encode_command(CommandCode.SET_LAMBDA, lam=lam)),
    "float RLS": lambda lam: RLS(2, lam=lam),
    "float RLS set_lambda": lambda lam: RLS(2).set_lambda(lam),
    "fixed RLS": lambda lam: fixed_check_lam(lam),
}


def _config_settings(lam: float) -> object:
    cfg = AppConfig()
    cfg.estimator = {"lambda": lam}
    return cfg.settings()


def _cli_settings(lam: float) -> object:
    args = build_parser().parse_args(["fit", "x.log", "--lambda", repr(lam)])
    return AppConfig().apply(overrides(args)).settings()


def takes(place: str, lam: float) -> bool:
    try:
        LAMBDA_TAKERS[place](lam)
    except CanrlsError:
        return False
    return True


@pytest.mark.parametrize("place", sorted(LAMBDA_TAKERS))
def test_every_place_takes_the_one_range_of_lambda(place: str) -> None:
    # 0.75 is exact in float32, as the command frame carries it
    assert takes(place, 0.75) and takes(place, 1.0)
    for lam in (0.3, 0.5, 0.0, 1.5, math.nan, -1.0):
        assert not takes(place, lam), (place, lam)


@pytest.mark.parametrize("place", sorted(LAMBDA_TAKERS))
def test_every_place_asks_the_one_rule(place: str, monkeypatch: pytest.MonkeyPatch) -> None:
    """Move the rule and every place moves with it: none keeps a range of its own."""
    monkeypatch.setattr(checks, "LAMBDA_MIN", 0.25)
    assert takes(place, 0.375) and not takes(place, 0.125)


def test_a_refused_lambda_names_where_it_came_from() -> None:
    with pytest.raises(CanrlsError, match=r"'lambda 0.3': lambda = 0.3: must be in \(0.5, 1\]"):
        parse_command_text("lambda 0.3")
    with pytest.raises(CanrlsError, match=r"estimator.lambda = 2: must be in \(0.5, 1\]"):
        EstimatorSettings(lam=2)
    with pytest.raises(CanrlsError, match=r"FixedRLS lam \(forgetting factor\) = 0.3"):
        fixed_check_lam(0.3)
    assert checks.check_lambda(np.float32(0.75), "x") == 0.75
    with pytest.raises(CanrlsError, match="x = True"):
        checks.check_lambda(True, "x")
    with pytest.raises(CanrlsError, match="x = '0.9'"):
        checks.check_lambda("0.9", "x")


# -- a finite number: one definition ----------------------------------------------------
@pytest.mark.parametrize("value, real, positive", [
    (1, True, True), (0.5, True, True), (np.float32(2.0), True, True), (0, True, False),
    (-1.5, True, False), (math.inf, False, False), (math.nan, False, False),
    (True, False, False), ("1", False, False), (None, False, False),
])
def test_a_finite_number_is_one_definition(value: object, real: bool, positive: bool) -> None:
    assert checks.is_real(value) is real and checks.is_positive(value) is positive


#: what the modules wrote by hand before asking core.checks: "not a bool, an int or a
#: float, finite (and above zero)"
HAND_WRITTEN = [re.compile(r"math\.isfinite\((\w[\w.]*)\)\s+and\s+\1 > 0"),
                re.compile(r"isinstance\((\w[\w.]*), bool\)\s+or\s+not\s+isinstance\(\1, "
                           r"int \| float\)\s+or\s+not\s+math\.isfinite\(\1\)")]


#: "a finite float, else None" for JSON, as five modules wrote it before asking
#: core.checks.finite_or_none / json_safe
HAND_WRITTEN_JSON = [re.compile(r"if math\.isfinite\((\w[\w.]*)\) else None"),
                     re.compile(r"None if \w[\w.]* is None or not math\.isfinite"),
                     re.compile(r"isinstance\((\w+), float\) and not math\.isfinite\(\1\):"
                                r"\s+return None")]


def hand_written(patterns: list[re.Pattern[str]]) -> list[str]:
    src = Path(checks.__file__).resolve().parents[1]
    return [f"{p.relative_to(src)}:{s.count(chr(10), 0, m.start()) + 1}"
            for p in sorted(src.rglob("*.py")) if p.name != "checks.py"
            for s in [p.read_text()] for rx in patterns for m in rx.finditer(s)]


def test_no_module_writes_finite_or_none_by_hand() -> None:
    bad = hand_written(HAND_WRITTEN_JSON)
    assert not bad, "ask canrls.core.checks.finite_or_none / json_safe:\n" + "\n".join(bad)


#: a user's number checked against a range by hand (finite, then lo < x < hi), as a dozen
#: places did before asking core.checks.in_range
HAND_WRITTEN_RANGE = [
    re.compile(r"math\.isfinite\((\w[\w.]*)\)\s+and\s+[-\w.]+\s*<=?\s*\1\s*<"),
    re.compile(r"isinstance\((\w[\w.]*), \(?int(, | \| )float\)?\)\s+(and|or not)\s+"
               r"\(?[-\w.]+\s*<=?\s*\1\s*<"),
    re.compile(r"isinstance\((\w[\w.]*), int \| float\)\s+and\s+\1 > 0 and"),
    re.compile(r"not\s+\(?0\s*<\s*[\w.]+\s*<\s*(float\(\"inf\"\)|math\.inf)"),
    re.compile(r"not \w[\w.]* <= [\w.]+ <= \w+_RANGE\[1\]"),
    re.compile(r"1e8 < \w+ < 1e11|_EPOCH\[0\] < "),  # the epoch window, three times before
]


def test_no_module_writes_a_range_check_by_hand() -> None:
    bad = hand_written(HAND_WRITTEN_RANGE)
    assert not bad, "ask canrls.core.checks.in_range / is_positive:\n" + "\n".join(bad)


@pytest.mark.parametrize("value, lo, hi, lo_open, hi_open, inside", [
    (0.5, 0, 1, True, True, True), (0, 0, 1, True, False, False),
    (0, 0, 1, False, False, True), (1, 0, 1, True, True, False), (1, 0, 1, True, False, True),
    (math.nan, 0, 1, False, False, False),
    (1e300, 0, math.inf, True, True, True), (math.inf, 0, math.inf, False, False, False),
    (True, 0, 2, False, False, False), ("0.5", 0, 1, False, False, False),
])
def test_in_range(value: object, lo: float, hi: float, lo_open: bool, hi_open: bool,
                  inside: bool) -> None:
    assert checks.in_range(value, lo, hi, lo_open=lo_open, hi_open=hi_open) is inside


def test_estimator_settings_refuse_a_bad_alpha_by_the_one_rule() -> None:
    for alpha in (True, math.nan, math.inf, -1.0, 0.0, "0.1"):
        with pytest.raises(CanrlsError, match="estimator.alpha"):
            EstimatorSettings(alpha=alpha)  # type: ignore[arg-type]
    for key, bad in (("warmup_s", True), ("calibration_s", math.inf)):
        with pytest.raises(CanrlsError, match=f"estimator.{key}"):
            EstimatorSettings(**{key: bad})


@pytest.mark.parametrize("key,bad", [("gap_periods", math.nan), ("gap_periods", math.inf),
                                     ("gap_periods", 1.0), ("rms_time_s", math.nan),
                                     ("rms_time_s", math.inf), ("rms_time_s", 0.0),
                                     ("max_phase_step", math.nan),
                                     ("max_phase_step", 0.0)])
def test_estimator_settings_refuse_what_is_no_number_of_their_range(key: str,
                                                                   bad: float) -> None:
    """NaN passed ``x <= lo`` checks before: each setting is a finite number of its range
    (``max_phase_step`` may be infinite: no limit, the default)."""
    with pytest.raises(CanrlsError, match=f"estimator.{key}"):
        EstimatorSettings(**{key: bad})
    assert EstimatorSettings(max_phase_step=math.inf).max_phase_step == math.inf


def test_json_safe_values() -> None:
    assert checks.finite_or_none(None) is None and checks.finite_or_none(math.nan) is None
    assert checks.finite_or_none(-math.inf) is None and checks.finite_or_none(2) == 2.0
    assert checks.json_safe({1: (math.inf, [np.float64(0.5), math.nan]), "s": "x"}) == {
        "1": [None, [0.5, None]], "s": "x"}


def test_no_module_writes_the_number_check_by_hand() -> None:
    src = Path(checks.__file__).resolve().parents[1]
    bad = [f"{p.relative_to(src)}:{s.count(chr(10), 0, m.start()) + 1}"
           for p in sorted(src.rglob("*.py")) if p.name != "checks.py"
           for s in [p.read_text()] for rx in HAND_WRITTEN for m in rx.finditer(s)]
    assert not bad, "ask canrls.core.checks.is_real / is_positive:\n" + "\n".join(bad)


# -- matplotlib, an optional extra: one import and one message ------------------------------
def definitions(name: str) -> list[str]:
    """The modules of src/canrls that define a function ``name``."""
    src = Path(checks.__file__).resolve().parents[1]
    return sorted(str(p.relative_to(src)) for p in src.rglob("*.py")
                  for node in ast.walk(ast.parse(p.read_text()))
                  if isinstance(node, ast.FunctionDef) and node.name == name)


def test_one_require_matplotlib_names_each_page_and_its_extra(
        monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    from canrls.core import webpage
    from canrls.diagnosis import figures
    from canrls.fleet import fleet_report

    assert definitions("require_matplotlib") == ["core/webpage.py"]
    for mod in [m for m in sys.modules if m == "matplotlib" or m.startswith("matplotlib.")]:
        monkeypatch.delitem(sys.modules, mod)
    monkeypatch.setitem(sys.modules, "matplotlib", None)
    with pytest.raises(CanrlsError, match=r"^the HTML report needs matplotlib, which is not "
                                          r"installed: pip install 'canrls\[report\]'"):
        figures.figures_in(tmp_path)
    with pytest.raises(CanrlsError, match=r"^the fleet report needs matplotlib, .*"
                                          r"'canrls\[fleet\]'"):
        webpage.require_matplotlib(*fleet_report.MATPLOTLIB)


@pytest.mark.parametrize("value", [1e308, 1e10 * 1.001, pytest.param(10 ** 400, id="10**400"),
                                   0, -1e-3, math.nan, "1"])
def test_a_period_is_a_positive_number_no_larger_than_a_receive_time(value: object) -> None:
    """``--dt 1e308`` (or ``calibration.period`` of a model file) passed as a period: the
    export's timestamp ticks then overflowed, an internal error (exit 3); ``--period
    1e308`` failed later naming the pairing's clock-step bound instead of the flag."""
    with pytest.raises(ConfigError, match=r"--dt: the control period must be a positive "
                                          r"number of seconds, at most 1e\+10"):
        checks.positive_period(value, "--dt")
    assert checks.positive_period(1e-3, "--dt") == 1e-3
    assert checks.positive_period(checks.MAX_TIMESTAMP, "--dt") == checks.MAX_TIMESTAMP


def test_an_integer_beyond_a_double_is_no_real_number() -> None:
    """``float(10**400)`` raises OverflowError: the one definition of a number says no."""
    assert checks.real_value(10 ** 400) is None and not checks.is_real(-(10 ** 400))

