"""Property tests: whatever the configuration file or the user expression, the loader
and the parser end in a result or a :class:`~canrls.core.errors.CanrlsError`, never another
exception.

Time is bounded by construction, not by a timer: the strategies draw bounded sizes
(nesting, leaves, text length), and the code under test is linear in them (the limits
of :mod:`canrls.processor.config` and :mod:`canrls.estimation.expr`).
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np
from cli_tool import inline_toml
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st

from canrls.core.errors import CanrlsError
from canrls.estimation.expr import CONSTANTS, FUNCTIONS, SIGNAL_NAMES, compile_expression
from canrls.processor.config import load_config

SETTINGS = settings(max_examples=150, deadline=None, derandomize=True,
                    suppress_health_check=[HealthCheck.function_scoped_fixture,
                                           HealthCheck.too_slow])

# ------------------------------------------------------------------- configuration files
#: the keys canrls reads, and some it does not, so that most drawn files reach the checks
KEYS = {
    "model": ["effects", "kt", "axis", "pitch", "wrap", "filter", "terms", "ranges",
              "scaling", "extra"],
    "estimator": ["lambda", "alpha", "trace_max", "warmup_s", "gap_periods",
                  "calibration_s", "rms_time_s", "max_phase_step", "min_speed", "bogus"],
    "fixed": ["word_bits", "acc_bits", "input_bits", "theta_max", "formats"],
    "can": ["period", "strict_range", "check_crc", "check_counter", "dbc", "bitrate"],
    "signals": ["current", "speed", "position", "voltage"],
    "nonsense": ["a"],
}
INNER = ["cutoff_hz", "zeta", "held", "name", "expr", "range", "unit", "equation",
         "current", "speed", "P", "signal", "x"]

scalars = st.one_of(
    st.booleans(),
    st.integers(min_value=-(10 ** 320), max_value=10 ** 320),
    st.integers(min_value=-40, max_value=40),
    st.floats(allow_nan=True, allow_infinity=True),
    st.sampled_from([0.0, 1e-300, 1e300, 0.7071, 25.0, 1e8, -1.0]),
    st.text(max_size=12),
    st.sampled_from(["inertia", "viscous", "coulomb", "user:d", "cogging:6", "rotary",
                     "linear", "omega * abs(omega)", "-" * 30 + "omega", "rpm",
                     "DriveSpeed.Speed", "current"]),
)
values = st.recursive(
    scalars,
    lambda inner: st.one_of(
        st.lists(inner, max_size=4),
        st.dictionaries(st.sampled_from(INNER), inner, max_size=4)),
    max_leaves=12)
documents = st.dictionaries(
    st.sampled_from(list(KEYS)),
    st.sampled_from(list(KEYS)).flatmap(
        lambda t: st.dictionaries(st.sampled_from(KEYS[t] + INNER), values, max_size=5)),
    max_size=4)


def _write(doc: dict[str, dict[str, Any]]) -> str:
    out = []
    for table, body in doc.items():
        out.append(f"[{table}]")
        out.extend(f"{json.dumps(k)} = {inline_toml(v)}" for k, v in body.items())
    return "\n".join(out) + "\n"


def _load_everything(path: Path) -> None:
    cfg = load_config(path)
    protocol = cfg.protocol()
    cfg.model_for(protocol)
    cfg.settings()


@SETTINGS
@given(doc=documents)
@example(doc={"fixed": {"theta_max": "big"}})
@example(doc={"model": {"filter": {"zeta": 1e8}}})
@example(doc={"estimator": {"alpha": 10 ** 309}})
@example(doc={"model": {"terms": [{"name": "d", "expr": "omega", "range": {}}]}})
def test_config_loader_on_random_documents(tmp_path: Path, doc: dict[str, Any]) -> None:
    p = tmp_path / "random.toml"
    p.write_text(_write(doc))
    try:
        _load_everything(p)
    except CanrlsError as e:
        assert "\n" not in str(e)


@SETTINGS
@given(text=st.one_of(
    st.text(max_size=200),
    st.text(alphabet="[]{}=,.\"' \nabc0123456789-+e", max_size=400),
    st.integers(min_value=1, max_value=5000).map(lambda n: "a = " + "[" * n + "]" * n)))
def test_config_loader_on_random_text(tmp_path: Path, text: str) -> None:
    p = tmp_path / "random.toml"
    p.write_text(text)
    try:
        _load_everything(p)
    except CanrlsError:
        pass


# ---------------------------------------------------------------------------- expressions
names = st.sampled_from(sorted(SIGNAL_NAMES) + sorted(CONSTANTS) + ["foo", "__import__"])
numbers = st.one_of(st.integers(min_value=0, max_value=10 ** 400).map(str),
                    st.floats(min_value=0, allow_nan=False).map(repr),
                    st.sampled_from(["1e999", "0", "0.5", "1_000", "0x1f", "1j"]))


def _combine(parts: st.SearchStrategy[str]) -> st.SearchStrategy[str]:
    return st.one_of(
        st.tuples(st.sampled_from(["-", "+", "~", "not "]), parts).map("".join),
        st.tuples(parts, st.sampled_from(["+", "-", "*", "/", "**", "%", "//", "<", "&"]),
                  parts).map(lambda p: f"({p[0]} {p[1]} {p[2]})"),
        st.tuples(st.sampled_from(sorted(FUNCTIONS) + ["eval", "open"]),
                  st.lists(parts, max_size=4)).map(lambda p: f"{p[0]}({', '.join(p[1])})"),
        st.tuples(st.integers(min_value=1, max_value=300), parts).map(
            lambda p: "-" * p[0] + p[1]),
        parts.map(lambda p: f"{p}.real"),
        parts.map(lambda p: f"[{p}]"),
    )


expressions = st.recursive(st.one_of(names, numbers), _combine, max_leaves=20)
RANGES = {"speed": (-50.0, 50.0), "current": (-5.0, 5.0), "position": (-10.0, 10.0),
          "voltage": (-24.0, 24.0), "t": (0.0, 1.0)}
DATA = {k: np.linspace(lo, hi, 16) for k, (lo, hi) in RANGES.items()}


def _check_expression(text: str) -> None:
    try:
        e = compile_expression(text, name="d")
    except CanrlsError as err:
        assert "\n" not in str(err).replace(repr(text), "")
        return
    assert e(DATA).shape == (16,)
    lo, hi = e.bounds(RANGES)
    assert lo <= hi or math.isnan(lo) or math.isnan(hi)


@SETTINGS
@given(text=expressions)
@example(text="omega * " + "9" * 310)
@example(text="-" * 60 + "omega")
def test_expression_parser_on_random_expressions(text: str) -> None:
    _check_expression(text)


@SETTINGS
@given(text=st.text(max_size=100))
def test_expression_parser_on_random_text(text: str) -> None:
    _check_expression(text)
