"""User-term expressions: whitelist, errors that point at the token, elementwise evaluation."""

from __future__ import annotations

import ast
import inspect

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import canrls.estimation.expr as expr_module
from canrls.core.errors import ConfigError, ExpressionError
from canrls.core.samples import Signals
from canrls.estimation.expr import DEFAULT_NAMES, FUNCTIONS, compile_expression

RNG = np.random.default_rng(0)
N = 64
DATA = {
    "t": np.arange(N) * 1e-3,
    "current": RNG.uniform(-5, 5, N),
    "speed": RNG.uniform(-50, 50, N),
    "position": RNG.uniform(-10, 10, N),
    "voltage": RNG.uniform(-24, 24, N),
}
w, th, i, u, t = (DATA[k] for k in ("speed", "position", "current", "voltage", "t"))


@pytest.mark.parametrize(("text", "expected", "signals"), [
    ("omega * abs(omega)", w * np.abs(w), ("speed",)),
    ("speed + v", w + w, ("speed",)),
    ("sin(theta) * i", np.sin(th) * i, ("current", "position")),
    ("x - position", th - th, ("position",)),
    ("u / (1 + current**2)", u / (1 + i**2), ("current", "voltage")),
    ("voltage", u, ("voltage",)),
    ("exp(-t) + log(1 + abs(omega)) - log10(2) + sqrt(abs(i))",
     np.exp(-t) + np.log(1 + np.abs(w)) - np.log10(2) + np.sqrt(np.abs(i)),
     ("t", "current", "speed")),
    ("atan2(i, omega) + atan(omega) + tanh(omega) + sinh(i) - cosh(i)",
     np.arctan2(i, w) + np.arctan(w) + np.tanh(w) + np.sinh(i) - np.cosh(i),
     ("current", "speed")),
    ("asin(sin(theta)) + acos(cos(theta)) + tan(theta / 4)",
     np.arcsin(np.sin(th)) + np.arccos(np.cos(th)) + np.tan(th / 4), ("position",)),
    ("sign(omega) * min(abs(omega), 10, i) + max(i, -1)",
     np.sign(w) * np.minimum(np.minimum(np.abs(w), 10), i) + np.maximum(i, -1),
     ("current", "speed")),
    ("-pi * e + +2 ** -1", np.full(N, -np.pi * np.e + 0.5), ()),
    ("3", np.full(N, 3.0), ()),
])
def test_whitelisted_expressions_evaluate_elementwise(text: str, expected: np.ndarray,
                                                       signals: tuple[str, ...]) -> None:
    c = compile_expression(text, name="T")
    assert c.signals == signals
    out = c(DATA)
    assert out.dtype == np.float64 and out.shape == (N,)
    np.testing.assert_allclose(out, expected, rtol=1e-15, atol=1e-15)


def test_evaluates_signals_blocks() -> None:
    s = Signals(DATA["t"], DATA["current"], DATA["speed"], DATA["position"])
    c = compile_expression("i * omega + theta", name="p")
    np.testing.assert_array_equal(c(s), i * w + th)
    with pytest.raises(ExpressionError, match="voltage"):
        compile_expression("u", name="needs_u")(s)


@pytest.mark.parametrize(("text", "token", "where"), [
    ("omega.real", "omega.real", "column 1"),
    ("abs(omega).real", "abs(omega).real", "column 1"),
    ("theta[0]", "theta[0]", "column 1"),
    ("foo(omega)", "foo", "column 1"),
    ("2 * np.sin(omega)", "np.sin", "column 5"),
    ("1 + eval('1')", "eval", "column 5"),
    ("__import__('os')", "__import__", "column 1"),
    ("sin(x=omega)", "x=omega", "column 5"),
    ("sin(*omega)", "*omega", "column 5"),
    ("lambda: 1", "lambda: 1", "column 1"),
    ("[a for a in omega]", "[a for a in omega]", "column 1"),
    ("omega if i else 0", "omega if i else 0", "column 1"),
    ("omega < 1", "omega < 1", "column 1"),
    ("omega and i", "omega and i", "column 1"),
    ("omega % 2", "%", "column 7"),
    ("(omega) // 2", "//", "column 9"),
    ("omega @ i", "@", "column 7"),
    ("~omega", "~", "column 1"),
    ("not omega", "not", "column 1"),
    ("'text'", "'text'", "column 1"),
    ("True", "True", "column 1"),
    ("1j", "1j", "column 1"),
    ("sin", "sin", "column 1"),
    ("alpha * omega", "alpha", "column 1"),
    ("omega + (y := 2)", "y := 2", "column 10"),
    ("sin(omega, i)", "sin", "column 1"),
    ("min(omega)", "min", "column 1"),
    ("(1, 2)", "(1, 2)", "column 1"),
])
def test_everything_else_is_rejected_naming_term_token_and_position(
        text: str, token: str, where: str) -> None:
    with pytest.raises(ExpressionError) as info:
        compile_expression(text, name="my_term")
    msg = str(info.value)
    assert "'my_term'" in msg
    assert repr(token) in msg
    assert where in msg
    assert isinstance(info.value, ConfigError) and isinstance(info.value, ValueError)


def test_multiline_positions_name_the_line() -> None:
    with pytest.raises(ExpressionError, match=r"'bad' at line 2, column 3"):
        compile_expression("(omega +\n  bad)", name="T")


@pytest.mark.parametrize(("text", "fragment"), [
    ("omega +", "end of the expression"),
    ("sin(omega", "was never closed"),
    ("3 omega", "'omega' at line 1, column 3"),
    ("", "empty"),
    ("   ", "empty"),
    ("1" + "+1" * 1500, "limit"),
    ("-" * 250 + "omega", "nest"),
    ("(" * 250 + "omega" + ")" * 250, "nested"),
])
def test_syntax_and_size_errors(text: str, fragment: str) -> None:
    with pytest.raises(ExpressionError, match="'T'") as info:
        compile_expression(text, name="T")
    assert fragment in str(info.value)


def test_allowed_names_restrict_the_signals() -> None:
    with pytest.raises(ExpressionError, match=r"name 'u' at column 7.*allowed: i, omega"):
        compile_expression("omega*u", name="T", allowed_names={"omega", "i"})
    assert compile_expression("omega*i", name="T", allowed_names={"omega", "i"}).signals == (
        "current", "speed")
    with pytest.raises(ExpressionError, match="not signal names"):
        compile_expression("omega", name="T", allowed_names={"omega", "os"})
    assert {"omega", "speed", "theta", "position", "i", "current", "u", "voltage", "t", "x",
            "v"} == DEFAULT_NAMES


def test_no_eval_exec_or_compile_in_the_module() -> None:
    tree = ast.parse(inspect.getsource(expr_module))
    called = {n.func.id for n in ast.walk(tree)
              if isinstance(n, ast.Call) and isinstance(n.func, ast.Name)}
    assert not called & {"eval", "exec", "compile", "__import__"}


def test_out_of_domain_values_become_nan_without_warnings() -> None:
    c = compile_expression("log(omega) + 1 / (omega - omega)", name="T")
    out = c({"speed": np.array([-1.0, 2.0])})
    assert np.isnan(out[0]) and np.isinf(out[1])


@settings(max_examples=30, deadline=None)
@given(st.sampled_from([
    "omega * abs(omega)", "sin(3 * theta) * i + exp(-abs(omega))", "max(i, omega, 0.5)",
    "u / (1 + i**2) - t", "tanh(omega / 0.01) * exp(-(omega / 2)**2)", "2.5",
]), st.lists(st.integers(0, N), max_size=5))
def test_chunked_evaluation_is_bit_identical(text: str, cuts: list[int]) -> None:
    c = compile_expression(text, name="T")
    whole = c(DATA)
    edges = [0, *sorted(cuts), N]
    parts = [c({k: v[a:b] for k, v in DATA.items()})
             for a, b in zip(edges[:-1], edges[1:], strict=True)]
    assert np.array_equal(np.concatenate(parts), whole)


RANGES = {"speed": (-3.0, 5.0), "current": (-2.0, 1.5), "voltage": (10.0, 20.0)}


@pytest.mark.parametrize("text", [
    "omega * abs(omega)", "sin(theta) * i", "omega**2 - i**3", "u / (1 + i**2)",
    "exp(omega) / u", "sqrt(u) + log(u) + log10(u)", "cosh(i) - sinh(omega) + atan(omega)",
    "min(omega, i) * max(i, 0.5)", "sign(omega) * 2", "tanh(omega / 0.1)", "-omega + 3",
    "asin(i / 2) + acos(i / 2)", "u ** 0.5 + 2 ** i", "i ** -2 + 1 / u",
])
def test_bounds_contain_every_value_in_the_ranges(text: str) -> None:
    c = compile_expression(text, name="T")
    lo, hi = c.bounds(RANGES)
    rng = np.random.default_rng(5)
    data = {k: rng.uniform(*r, 5000) for k, r in RANGES.items()}
    data["position"] = rng.uniform(-100, 100, 5000)
    data = {k: np.concatenate([v, np.array(RANGES.get(k, (0.0, 0.0)))]) for k, v in data.items()}
    out = c(data)
    finite = np.isfinite(out)
    assert np.all(out[finite] >= lo - 1e-12 * abs(lo))
    assert np.all(out[finite] <= hi + 1e-12 * abs(hi))


def test_bounds_are_infinite_when_unknown() -> None:
    assert compile_expression("theta", name="T").bounds(RANGES) == (-np.inf, np.inf)
    assert compile_expression("1 / i", name="T").bounds(RANGES) == (-np.inf, np.inf)
    assert compile_expression("sin(theta)", name="T").bounds(RANGES) == (-1.0, 1.0)
    assert compile_expression("t * 0 + 1", name="T").bounds({}) == (1.0, 1.0)


def test_function_table_is_the_documented_whitelist() -> None:
    assert set(FUNCTIONS) == set(
        "sin cos tan asin acos atan atan2 sinh cosh tanh exp log log10 sqrt abs sign min max"
        .split())
