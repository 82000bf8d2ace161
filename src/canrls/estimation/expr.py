"""User-defined terms: safe arithmetic expressions over the drive signals.

A user term ``c_u * f_u(signals)`` adds one regressor column ``f_u`` written as a small
expression in the configuration, for instance ``omega * abs(omega)`` (aerodynamic
drag) or ``sin(theta) * i`` (position-dependent torque constant).
:func:`compile_expression` parses the text with Python's :mod:`ast` module and accepts
only this whitelist; the text is never passed to ``eval``, ``exec`` or ``compile``:

========================  ================================================================
names                     ``omega``/``speed``/``v`` (speed), ``theta``/``position``/``x``
                          (unwrapped position), ``i``/``current``, ``u``/``voltage``, ``t``
constants                 ``pi``, ``e``, int and float literals
operators                 ``+ - * / **`` and unary ``+ -``
functions (elementwise)   ``sin cos tan asin acos atan atan2 sinh cosh tanh exp log log10
                          sqrt abs sign min max`` (``atan2(y, x)``, ``min``/``max`` of two or
                          more arguments, the others of one)
========================  ================================================================

Anything else (attributes, subscripts, comparisons, keywords, lambdas,
comprehensions, other names or functions) raises
:class:`~canrls.core.errors.ExpressionError` naming the term, the offending token and its
position. The compiled expression is evaluated elementwise with numpy, so evaluating
a block in chunks gives the same values bit for bit. Values outside a function's
domain (``log`` of a negative speed, division by zero) become ``nan``/``inf`` without a
warning; the pipeline then leaves those samples out (see
:class:`~canrls.estimation.model.RegressorBuilder`). Keep the expression finite over the
operating range.
"""

from __future__ import annotations

import ast
import math
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt

from canrls.core.errors import ExpressionError

__all__ = [
    "CompiledExpression",
    "compile_expression",
    "SIGNAL_NAMES",
    "CONSTANTS",
    "FUNCTIONS",
    "DEFAULT_NAMES",
]

F64 = npt.NDArray[np.float64]
Value = Any  # np.ndarray or np.float64 scalar during evaluation
Interval = tuple[float, float]

#: Names an expression may use, mapped to the signal role they read.
SIGNAL_NAMES: Mapping[str, str] = {
    "omega": "speed", "speed": "speed", "v": "speed",
    "theta": "position", "position": "position", "x": "position",
    "i": "current", "current": "current",
    "u": "voltage", "voltage": "voltage",
    "t": "t",
}
#: Every signal name (the default for ``allowed_names``).
DEFAULT_NAMES: frozenset[str] = frozenset(SIGNAL_NAMES)
#: Named constants.
CONSTANTS: Mapping[str, float] = {"pi": math.pi, "e": math.e}

_ROLE_ORDER = ("t", "current", "speed", "position", "voltage")
_MAX_TEXT = 2000
_MAX_DEPTH = 200
_INF = math.inf
_FULL: Interval = (-_INF, _INF)


# ---------------------------------------------------------------- interval helpers
def _iv(lo: Any, hi: Any) -> Interval:
    lo, hi = float(lo), float(hi)
    if math.isnan(lo):
        lo = -_INF
    if math.isnan(hi):
        hi = _INF
    return (lo, hi)


def _mono(fn: Callable[[Any], Any], lo: float, hi: float, dom: Interval = _FULL) -> Interval:
    """Image of [lo, hi] ∩ dom under a non-decreasing ``fn``."""
    lo, hi = max(lo, dom[0]), min(hi, dom[1])
    if lo > hi:
        return _FULL
    with np.errstate(all="ignore"):
        return _iv(fn(np.float64(lo)), fn(np.float64(hi)))


def _mul1(a: float, b: float) -> float:
    return 0.0 if a == 0.0 or b == 0.0 else a * b


def _imul(x: Interval, y: Interval) -> Interval:
    p = [_mul1(a, b) for a in x for b in y]
    return _iv(min(p), max(p))


def _idiv(x: Interval, y: Interval) -> Interval:
    if y[0] <= 0.0 <= y[1]:
        return _FULL
    return _imul(x, (1.0 / y[1], 1.0 / y[0]))


def _iabs(x: Interval) -> Interval:
    lo, hi = x
    if lo >= 0.0:
        return x
    if hi <= 0.0:
        return (-hi, -lo)
    return (0.0, max(-lo, hi))


def _ipow(x: Interval, y: Interval) -> Interval:
    lo, hi = x
    if y[0] == y[1] and float(y[0]).is_integer() and abs(y[0]) < 1e6:
        k = int(y[0])
        if k == 0:
            return (1.0, 1.0)
        if k < 0:
            return _idiv((1.0, 1.0), _ipow(x, (float(-k), float(-k))))
        with np.errstate(all="ignore"):
            if k % 2:
                return _iv(np.float64(lo) ** k, np.float64(hi) ** k)
            a = _iabs(x)
            return _iv(np.float64(a[0]) ** k, np.float64(a[1]) ** k)
    if lo > 0.0 and math.isfinite(y[0]) and math.isfinite(y[1]):
        with np.errstate(all="ignore"):
            p = [np.float64(a) ** b for a in (lo, hi) for b in y]
        return _iv(min(p), max(p))
    return _FULL


def _icosh(x: Interval) -> Interval:
    a = _iabs(x)
    with np.errstate(all="ignore"):
        return _iv(np.cosh(np.float64(a[0])), np.cosh(np.float64(a[1])))


def _isign(x: Interval) -> Interval:
    return (float(np.sign(x[0])), float(np.sign(x[1])))


@dataclass(frozen=True)
class _Fn:
    impl: Callable[..., Any]
    nmin: int
    nmax: int  # -1: unbounded
    bound: Callable[..., Interval]


_TRIG: Interval = (-1.0, 1.0)

#: Whitelisted functions: numpy implementation, arity and interval rule.
FUNCTIONS: Mapping[str, _Fn] = {
    "sin": _Fn(np.sin, 1, 1, lambda x: _TRIG),
    "cos": _Fn(np.cos, 1, 1, lambda x: _TRIG),
    "tan": _Fn(np.tan, 1, 1, lambda x: _FULL),
    "asin": _Fn(np.arcsin, 1, 1, lambda x: _mono(np.arcsin, x[0], x[1], dom=(-1.0, 1.0))),
    "acos": _Fn(np.arccos, 1, 1,
                lambda x: (0.0, math.pi) if x[0] < -1 or x[1] > 1 else
                _iv(math.acos(x[1]), math.acos(x[0]))),
    "atan": _Fn(np.arctan, 1, 1, lambda x: _mono(np.arctan, x[0], x[1])),
    "atan2": _Fn(np.arctan2, 2, 2, lambda y, x: (-math.pi, math.pi)),
    "sinh": _Fn(np.sinh, 1, 1, lambda x: _mono(np.sinh, x[0], x[1])),
    "cosh": _Fn(np.cosh, 1, 1, _icosh),
    "tanh": _Fn(np.tanh, 1, 1, lambda x: _mono(np.tanh, x[0], x[1])),
    "exp": _Fn(np.exp, 1, 1, lambda x: _mono(np.exp, x[0], x[1])),
    "log": _Fn(np.log, 1, 1, lambda x: _mono(np.log, x[0], x[1], dom=(0.0, _INF))),
    "log10": _Fn(np.log10, 1, 1, lambda x: _mono(np.log10, x[0], x[1], dom=(0.0, _INF))),
    "sqrt": _Fn(np.sqrt, 1, 1, lambda x: _mono(np.sqrt, x[0], x[1], dom=(0.0, _INF))),
    "abs": _Fn(np.abs, 1, 1, _iabs),
    "sign": _Fn(np.sign, 1, 1, _isign),
    "min": _Fn(np.minimum, 2, -1,
               lambda *xs: (min(x[0] for x in xs), min(x[1] for x in xs))),
    "max": _Fn(np.maximum, 2, -1,
               lambda *xs: (max(x[0] for x in xs), max(x[1] for x in xs))),
}

_BINOPS: Mapping[type[ast.operator], tuple[Callable[[Value, Value], Value],
                                           Callable[[Interval, Interval], Interval]]] = {
    ast.Add: (np.add, lambda x, y: _iv(x[0] + y[0], x[1] + y[1])),
    ast.Sub: (np.subtract, lambda x, y: _iv(x[0] - y[1], x[1] - y[0])),
    ast.Mult: (np.multiply, _imul),
    ast.Div: (np.divide, _idiv),
    ast.Pow: (np.power, _ipow),
}
_OP_SYMBOL: Mapping[type[ast.AST], str] = {
    ast.Mod: "%", ast.FloorDiv: "//", ast.MatMult: "@", ast.LShift: "<<", ast.RShift: ">>",
    ast.BitOr: "|", ast.BitXor: "^", ast.BitAnd: "&", ast.Not: "not", ast.Invert: "~",
}


# ---------------------------------------------------------------- compiled nodes
# Each node compiles to (evaluate(env) -> value, bound(ranges) -> interval).
_Eval = Callable[[Mapping[str, Value]], Value]
_Bound = Callable[[Mapping[str, Interval]], Interval]


@dataclass(frozen=True)
class CompiledExpression:
    """A whitelisted expression compiled to a tree of numpy calls.

    Call it with a mapping of signal roles to arrays (``"t"``, ``"current"``,
    ``"speed"``, ``"position"``, ``"voltage"``) or with an object holding them as
    attributes (:class:`canrls.core.samples.Signals`); it returns a float64 array of the
    block length. :attr:`signals` lists the roles it reads.
    """

    name: str
    text: str
    #: Signal roles the expression reads, in the order t, current, speed, position, voltage.
    signals: tuple[str, ...]
    _eval: _Eval = field(repr=False, compare=False)
    _bound: _Bound = field(repr=False, compare=False)
    #: The free parameters (:func:`compile_expression`) the expression reads.
    parameters: tuple[str, ...] = ()

    def __call__(self, data: Mapping[str, npt.ArrayLike] | Any) -> F64:
        env: dict[str, Value] = {}
        n: int | None = None
        for role in self.signals:
            v = data.get(role) if isinstance(data, Mapping) else getattr(data, role, None)
            if v is None:
                raise ExpressionError(
                    f"term {self.name!r}: needs signal {role!r}, which is not available")
            arr = np.ascontiguousarray(v, dtype=np.float64)
            env[role] = arr
            n = len(arr)
        if n is None:  # a constant expression: size it from any available signal
            for role in _ROLE_ORDER:
                v = data.get(role) if isinstance(data, Mapping) else getattr(data, role, None)
                if v is not None:
                    n = len(np.asarray(v))
                    break
            else:
                raise ExpressionError(
                    f"term {self.name!r}: constant expression needs a block to size it")
        with np.errstate(all="ignore"):
            out = self._eval(env)
        return np.broadcast_to(np.asarray(out, dtype=np.float64), (n,)).copy()

    evaluate = __call__

    def bounds(self, ranges: Mapping[str, tuple[float, float]] | None = None) -> Interval:
        """A conservative ``(lo, hi)`` for the value given ranges of the signal roles.

        Roles without a range are unbounded; the result may be infinite (the model then
        needs an explicit ``range`` for the term).
        """
        rs: dict[str, Interval] = {}
        for role, r in (ranges or {}).items():
            lo, hi = float(r[0]), float(r[1])
            rs[role] = (min(lo, hi), max(lo, hi))
        return self._bound(rs)


class _Compiler:
    def __init__(self, text: str, name: str, allowed: frozenset[str],
                 parameters: Mapping[str, float]) -> None:
        self.text = text
        self.name = name
        self.allowed = allowed
        self.parameters = parameters
        self.used: set[str] = set()
        self.roles: set[str] = set()
        self.lines = text.splitlines() or [""]

    def where(self, lineno: int, col: int) -> str:
        # ast columns are 0-based UTF-8 byte offsets; report 1-based characters
        line = self.lines[lineno - 1] if 0 < lineno <= len(self.lines) else ""
        col_chars = len(line.encode("utf-8")[:col].decode("utf-8", errors="ignore")) + 1
        if len(self.lines) > 1:
            return f"line {lineno}, column {col_chars}"
        return f"column {col_chars}"

    def at(self, node: ast.AST | None) -> str | None:
        """:meth:`where` ``node`` is, or None for a node without a place (an operator)."""
        lineno, col = getattr(node, "lineno", None), getattr(node, "col_offset", None)
        return None if lineno is None or col is None else self.where(lineno, col)

    def fail(self, what: str, token: str, node: ast.AST | None, hint: str = "") -> ExpressionError:
        pos = ""
        at = self.at(node)
        if at is not None:
            pos = f" at {at}"
        msg = f"term {self.name!r}: {what} {token!r}{pos} is not allowed"
        if hint:
            msg += f" ({hint})"
        return ExpressionError(msg + f" in {self.text!r}")

    def token(self, node: ast.AST) -> str:
        seg = ast.get_source_segment(self.text, node)
        return seg if seg is not None else type(node).__name__

    def compile(self, node: ast.AST, depth: int = 0) -> tuple[_Eval, _Bound, float | None]:
        """Return (eval, bound, constant value or None)."""
        if depth > _MAX_DEPTH:
            where = self.at(node) or "?"
            raise ExpressionError(f"term {self.name!r}: expression nested deeper than "
                                  f"{_MAX_DEPTH} levels at {where}")
        if isinstance(node, ast.Constant):
            v = node.value
            if isinstance(v, bool) or not isinstance(v, int | float):
                raise self.fail("literal", self.token(node), node, "only numbers")
            # an int beyond float64 (a 310-digit literal) is as infinite as 1e999
            c = float(v) if not isinstance(v, int) or v.bit_length() <= 1024 else math.inf
            if not math.isfinite(c):
                raise self.fail("literal", self.token(node), node, "must be finite")
            cv = np.float64(c)
            return (lambda env: cv), (lambda rs: (c, c)), c
        if isinstance(node, ast.Name):
            return self.compile_name(node)
        if isinstance(node, ast.UnaryOp):
            if isinstance(node.op, ast.USub):
                f, b, cu = self.compile(node.operand, depth + 1)

                def neg_bound(rs: Mapping[str, Interval]) -> Interval:
                    # -[lo, hi] = [-hi, -lo]; the operand's bound is evaluated once, so
                    # bounding is linear in the expression's size (calling it twice
                    # doubled the time with every nested minus)
                    lo, hi = b(rs)
                    return -hi, -lo

                return (lambda env: np.negative(f(env))), neg_bound, None if cu is None else -cu
            if isinstance(node.op, ast.UAdd):
                return self.compile(node.operand, depth + 1)
            raise self.fail("operator", _OP_SYMBOL.get(type(node.op), type(node.op).__name__),
                            node)
        if isinstance(node, ast.BinOp):
            op = _BINOPS.get(type(node.op))
            if op is None:
                raise self.fail("operator", _OP_SYMBOL.get(type(node.op), type(node.op).__name__),
                                self._op_node(node), "use + - * / **")
            fl, bl, _ = self.compile(node.left, depth + 1)
            fr, br, cr = self.compile(node.right, depth + 1)
            impl, ib = op
            return ((lambda env: impl(fl(env), fr(env))),
                    (lambda rs: ib(bl(rs), br(rs))), None)
        if isinstance(node, ast.Call):
            return self.compile_call(node, depth)
        raise self.fail(_describe(node), self.token(node), node,
                        "only numbers, signal names, + - * / **, and whitelisted functions")

    def _op_node(self, node: ast.BinOp) -> ast.AST:
        """A stand-in node carrying the position of the operator symbol itself."""
        src = self.lines
        try:
            ln, col = node.left.end_lineno, node.left.end_col_offset
            assert ln is not None and col is not None
            line = src[ln - 1].encode("utf-8")
            while col < len(line) and line[col:col + 1] in (b" ", b"\t", b")"):
                col += 1
            stub = ast.Pass()
            stub.lineno, stub.col_offset = ln, col
            return stub
        except (AssertionError, IndexError):
            return node

    def compile_name(self, node: ast.Name) -> tuple[_Eval, _Bound, float | None]:
        nm = node.id
        if nm in CONSTANTS or nm in self.parameters:
            c = CONSTANTS[nm] if nm in CONSTANTS else self.parameters[nm]
            if nm not in CONSTANTS:
                self.used.add(nm)
            cv = np.float64(c)
            return (lambda env: cv), (lambda rs: (c, c)), c
        if nm in SIGNAL_NAMES:
            if nm not in self.allowed:
                raise self.fail("name", nm, node,
                                f"signal not available here; allowed: {_names(self.allowed)}")
            role = SIGNAL_NAMES[nm]
            self.roles.add(role)
            return (lambda env: env[role]), (lambda rs: rs.get(role, _FULL)), None
        if nm in FUNCTIONS:
            raise self.fail("function name", nm, node, "call it, e.g. sin(theta)")
        raise self.fail("name", nm, node, f"allowed names: {_names(self.allowed)}, pi, e")

    def compile_call(self, node: ast.Call, depth: int) -> tuple[_Eval, _Bound, float | None]:
        if not isinstance(node.func, ast.Name):
            raise self.fail("call of", self.token(node.func), node.func,
                            f"functions: {', '.join(FUNCTIONS)}")
        fname = node.func.id
        fn = FUNCTIONS.get(fname)
        if fn is None:
            raise self.fail("function", fname, node.func, f"functions: {', '.join(FUNCTIONS)}")
        if node.keywords:
            kw = node.keywords[0]
            raise self.fail("keyword argument", self.token(kw), kw)
        for a in node.args:
            if isinstance(a, ast.Starred):
                raise self.fail("starred argument", self.token(a), a)
        n = len(node.args)
        if n < fn.nmin or (fn.nmax >= 0 and n > fn.nmax):
            want = (str(fn.nmin) if fn.nmin == fn.nmax else
                    f"{fn.nmin} or more" if fn.nmax < 0 else f"{fn.nmin} to {fn.nmax}")
            raise self.fail(f"call with {n} argument(s) to", fname, node.func,
                            f"{fname} takes {want}")
        parts = [self.compile(a, depth + 1) for a in node.args]
        evs = [p[0] for p in parts]
        bds = [p[1] for p in parts]
        impl, rule = fn.impl, fn.bound
        if fn.nmax < 0:  # min / max of several arguments: fold pairwise
            def ev(env: Mapping[str, Value]) -> Value:
                acc = evs[0](env)
                for e_ in evs[1:]:
                    acc = impl(acc, e_(env))
                return acc
        elif n == 1:
            e0 = evs[0]

            def ev(env: Mapping[str, Value]) -> Value:
                return impl(e0(env))
        else:
            def ev(env: Mapping[str, Value]) -> Value:
                return impl(*(e_(env) for e_ in evs))

        def bd(rs: Mapping[str, Interval]) -> Interval:
            return rule(*(b(rs) for b in bds))

        return ev, bd, None


def _describe(node: ast.AST) -> str:
    names = {
        ast.Attribute: "attribute", ast.Subscript: "subscript", ast.Compare: "comparison",
        ast.BoolOp: "boolean operator", ast.IfExp: "conditional expression",
        ast.Lambda: "lambda", ast.ListComp: "comprehension", ast.SetComp: "comprehension",
        ast.DictComp: "comprehension", ast.GeneratorExp: "comprehension",
        ast.List: "list", ast.Tuple: "tuple", ast.Dict: "dict", ast.Set: "set",
        ast.JoinedStr: "string", ast.NamedExpr: "assignment", ast.Await: "await",
        ast.Yield: "yield", ast.YieldFrom: "yield", ast.Starred: "starred expression",
        ast.Slice: "slice",
    }
    return names.get(type(node), "construct")


def _names(allowed: Iterable[str]) -> str:
    return ", ".join(sorted(allowed))


def compile_expression(text: str, *, name: str,
                       allowed_names: Iterable[str] | None = None,
                       parameters: Mapping[str, float] | None = None) -> CompiledExpression:
    """Parse and compile a user-term expression.

    :param text: the expression, e.g. ``"omega * abs(omega)"``.
    :param name: the term's name, used in error messages.
    :param allowed_names: signal names the expression may use (a subset of
        :data:`SIGNAL_NAMES`, e.g. without ``u``/``voltage`` when the drive does not send
        voltage); default all of them.
    :param parameters: free parameters of the term (``{"c": 0.05}``), read as constants
        of these values; each name an identifier that is no signal, constant or function.
    :raises ExpressionError: the text does not parse or uses anything outside the
        whitelist; the message names the term, the token and its position.
    """
    allowed = DEFAULT_NAMES if allowed_names is None else frozenset(allowed_names)
    unknown = allowed - DEFAULT_NAMES
    if unknown:
        raise ExpressionError(
            f"term {name!r}: allowed_names {sorted(unknown)} are not signal names "
            f"(known: {_names(DEFAULT_NAMES)})")
    params = dict(parameters or {})
    for p, v in params.items():
        if (not isinstance(p, str) or not p.isidentifier() or p in SIGNAL_NAMES
                or p in CONSTANTS or p in FUNCTIONS):
            raise ExpressionError(f"term {name!r}: parameter name {p!r} must be an "
                                  f"identifier that is no signal, constant or function")
        if not math.isfinite(v):
            raise ExpressionError(f"term {name!r}: parameter {p} = {v!r} must be finite")
    if not isinstance(text, str):
        raise ExpressionError(f"term {name!r}: expression must be a string, got {text!r}")
    if not text.strip():
        raise ExpressionError(f"term {name!r}: expression is empty")
    if len(text) > _MAX_TEXT:
        raise ExpressionError(
            f"term {name!r}: expression is {len(text)} characters, the limit is {_MAX_TEXT}")
    text = text.strip()  # positions in messages count from the first non-blank character
    try:
        tree = ast.parse(text, mode="eval")
    except SyntaxError as e:
        line = e.text.rstrip("\n") if e.text else ""
        if e.offset and 0 < e.offset <= len(line):
            token = line[e.offset - 1:e.offset + 9].strip()
            where = f"{token!r} at line {e.lineno or 1}, column {e.offset}"
        else:
            where = "the end of the expression"
        raise ExpressionError(
            f"term {name!r}: syntax error at {where} in {text!r}: {e.msg}") from e
    except (RecursionError, MemoryError, ValueError) as e:
        raise ExpressionError(f"term {name!r}: expression cannot be parsed: {e}") from e
    comp = _Compiler(text, name, allowed, params)
    try:
        ev, bd, _ = comp.compile(tree.body)
    except RecursionError as e:
        raise ExpressionError(f"term {name!r}: expression is nested too deeply") from e
    roles = tuple(r for r in _ROLE_ORDER if r in comp.roles)
    return CompiledExpression(name=name, text=text, signals=roles, _eval=ev, _bound=bd,
                              parameters=tuple(sorted(comp.used)))
