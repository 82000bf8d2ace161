r"""Fixed-point recursive least squares: the bit-exact specification of the embedded kernel.

:class:`FixedRLS` runs the recursion of :class:`canrls.estimation.rls.RLS` the way a
microcontroller runs it: integers end to end, every quantity in a signed Q format
chosen from the ranges of the problem, explicit rounding, saturation with a counter
on every store, one integer division per update. The kernel
(:func:`canrls.estimation.fixed_kernels.fixed_block`) is pure ``int64`` arithmetic with explicit
shifts, so the same inputs give the same integers on every platform, and per-sample
:meth:`FixedRLS.update` and block :meth:`FixedRLS.run` give the same bits.

.. math::

    \varepsilon &= y - \varphi^\top\theta \\
    h &= P\varphi, \qquad g = 1/(\lambda + \varphi^\top h) \\
    K &= g\,h \\
    \theta &\leftarrow \theta + K\varepsilon
        \qquad\text{(64 bits: the word and a fraction, below)} \\
    P &\leftarrow (P - K h^\top)/\lambda
    \qquad\text{upper triangle only;}\quad P_0 = I/\alpha

Inputs are the pipeline's normalised regressors: every column and the target are
scaled by exact powers of two so that :math:`|\varphi_j| \le 1`, :math:`|y| \le 1`
nominally; ``alpha`` is in the same units.

Q formats
---------
``QFormat(bits, frac)`` is a signed two's-complement word of ``bits`` bits whose
integer ``q`` stands for ``q * 2**-frac``; ``Q{m}.{frac}`` in the usual notation with
``m = bits - 1 - frac`` integer bits besides the sign. :meth:`FixedConfig.auto`
gives every quantity the smallest number of integer bits that holds its bound
(:meth:`QFormat.for_range`: :math:`2^m >` bound) and all the remaining bits to the
fraction. The bounds (``n`` parameters, :math:`\bar\varphi_j` = ``phi_max``,
:math:`\|\bar\varphi\|_2` their Euclidean norm, :math:`\bar P_h` half the range of
the ``P`` format, the largest :math:`\mathrm{tr}\tilde P` the block exponent allows)
are:

==========  =======================================================================
quantity    bound and reason
==========  =======================================================================
``phi``     ``max(phi_max)`` (one format for all columns, as one MAC loop needs)
``y``       ``y_max``
``P``       :math:`\bar P = 1/\alpha` for :math:`\lambda = 1` (:math:`P \preceq P_0`:
            information only accumulates); otherwise
            :math:`\max(n/\alpha, \mathrm{trace\_max})`: the trace bound caps
            :math:`\mathrm{tr}P`, and every :math:`|P_{ij}| \le \lambda_{max}(P)
            \le \mathrm{tr}P` for a positive semi-definite :math:`P`
``h``       :math:`\max(\bar P, \bar P_h)\,\|\bar\varphi\|_2` (Cauchy-Schwarz in the
            :math:`P` inner product: :math:`|h_i| \le \sqrt{P_{ii}}\sqrt{\varphi^\top
            P\varphi} \le \lambda_{max}(P)\|\varphi\|_2`)
``den``     :math:`1 + \max(\bar P, \bar P_h)\,\|\bar\varphi\|_2^2`
            (:math:`\lambda + \varphi^\top P\varphi`)
``g``       :math:`1/\lambda < 2` (:math:`\varphi^\top P\varphi \ge 0`), ``Q1``; its
            fraction is limited so that the dividend ``1 << (frac_g + frac_den)``
            fits the accumulator (with a narrow accumulator the fractions of ``g`` and
            ``den`` are balanced for equal relative precision)
``K``       :math:`\max\big(\min(\sqrt{\bar P}/(2\sqrt\lambda),\ \bar P\|\bar\varphi\|_2/\lambda),\
            \bar P_h\|\bar\varphi\|_2/\lambda\big)`: at ``e = 0``,
            :math:`|K_i| \le \sqrt{P_{ii}}\sqrt{s}/(\lambda+s) \le \sqrt{P_{ii}}/(2\sqrt\lambda)`
            (:math:`s = \varphi^\top P\varphi`); once scaled by :math:`2^e`, ``K``
            grows with :math:`P` again, :math:`|K_i| \le |h_i|/\lambda`
``theta``   ``theta_max``, default :math:`4\,y_{max}/\min_j\bar\varphi_j`: with
            normalised columns each term :math:`\theta_j\varphi_j` is of the size of
            the target, :math:`|\theta_j| \lesssim y_{max}/\bar\varphi_j`; two more
            bits leave room for terms that partly cancel and for the start-up
            transient. Pass the real range when known.
``eps``     :math:`4\,y_{max}`: the a-priori error starts at :math:`y`
            (:math:`\theta_0 = 0`) and shrinks to the noise; a larger error during a
            transient is clipped (counted), which only limits that one correction,
            like a robust (Huber) RLS
``lam``     :math:`\lambda \le 1`, :math:`1/\lambda < 2` and the forgetting scale
            :math:`c \le 1`: ``Q1.(bits-2)`` (requires :math:`\lambda > 1/2`; typical
            :math:`[0.98, 1]`)
==========  =======================================================================

``phi`` and ``y`` use ``input_bits``, everything else ``word_bits``. Any format can be
overridden: ``FixedConfig.auto(..., P=QFormat(32, 24))`` or
``dataclasses.replace(config, P=...)``; a saturation then shows in the counters.

Scaled P
--------
:math:`P` falls by many orders of magnitude from :math:`P_0 = I/\alpha` once data
arrive (and rises by :math:`1/\lambda` per step where they do not), far more than a
fixed Q format resolves. It is therefore held as :math:`P = c\,\tilde P\,2^{-(f_P +
e)}`: words :math:`\tilde P` in the ``P`` format, an integer block exponent
``e >= 0`` and a forgetting scale :math:`1/2 < c \le 1` (a ``lam`` word).
Forgetting multiplies ``c`` by :math:`1/\lambda` (one product per step, not one per
element); ``c > 1`` trades a factor 2 with ``e``, or at ``e = 0`` is folded into the
words. When :math:`\mathrm{tr}\tilde P` falls to a quarter of the word range the
words shift left and ``e`` rises. :math:`h = \tilde P\varphi` and ``K`` carry the
same ``e``, removed by shifts where they meet ``theta`` and ``den``. All of it is
integer arithmetic; it keeps about ``word_bits - 3`` significant bits on
:math:`\mathrm{tr}P` for any :math:`\alpha` and run length (without it, 32-bit
words lose the small eigenvalues of :math:`P` at :math:`\alpha = 10^{-3}`,
:math:`\lambda < 1`, and stall with :math:`\lambda = 1` once :math:`g h_i^2` falls
below half an LSB). The ``P`` format is the one at ``e = 0``.

Rounding and saturation
-----------------------
Every product of two words is exact (at most 32 x 32 bits: the multiplier's
double-width result). A value is brought to a coarser scale by a *rounding right
shift*: round half up, by adding ``1 << (s-1)`` before the arithmetic right shift, as
a DSP does with its rounding constant (bias +1/2 LSB only on exact ties). It is
then clamped to its word, and each clamp increments the counter of its site
(:data:`SITES`): ``phi_in``, ``y_in`` (inputs outside their word), ``eps``, ``h``,
``den``, ``div``, ``K``, ``theta``, ``P``. Nothing ever wraps. A single product
(``theta``, ``P`` updates) is rounded once to its destination and added with
saturation, e.g. :math:`\tilde P_{ij} \leftarrow \mathrm{sat}(\tilde P_{ij} -
\mathrm{rsh}(K_i \tilde h_j))`. The gain is *normalised*: once per step
:math:`\tilde h` and :math:`\varepsilon` are shifted left, exactly, to 31 bits (shifts
``k`` and ``ke``, bounded so that no later shift exceeds 62) and :math:`K` is the high
word of :math:`(\tilde h\,2^k)(g c\,2^{g_{up}})`, rounded half up: it cannot saturate
(its counter stays 0), its scale moves with ``k``, and the ``theta`` and ``P`` updates
shift by ``theta_s + e + k + ke`` and ``P_s + e + 2k``, at least 32 in the steady
state, so that the target takes the high word of each product (docs/fixed_point.md).
The ``K`` format of :class:`FixedConfig` no longer enters the arithmetic.

The estimate in 64 bits
-----------------------
:math:`\theta` is the word ``theta`` (the ``theta`` format, published and used in
:math:`\varepsilon`) and below it a fraction word ``theta_frac``, :math:`0 \le` ``theta_frac``
:math:`< 2^{32}`, in units of :math:`2^{-32}` LSB: the estimate is the 64-bit
``theta * 2**32 + theta_frac``. The update :math:`K\varepsilon` is added to it at
:math:`2^{-32}` LSB, floored (from the high word of its product when its shift is 32
or more, which the target's ``SMULL`` gives), and the sum saturated to the ``theta``
word. Why: with :math:`\lambda = 1` the gain falls like :math:`1/N`, and after a few
hundred thousand samples :math:`K\varepsilon` is a small fraction of an LSB (about 0.05
to 0.1 LSB on the simulated drive at 1 kHz after 10 min); rounded to the word each step,
almost every update became 0 and the estimate froze where it was while the float kept
converging: 0.15 % and 7 sigma from the float after one hour, against 0.004 % and 0.6
sigma with the fraction (``canrls fit``; docs/fixed_point.md). It costs one word per
parameter of state. The C kernel keeps the two words of a parameter as one 8-byte pair,
``canrls_rls_q31.theta_q[j]`` of type ``canrls_theta64`` (``frac``, ``word``: this
``theta_frac[j]`` and ``theta[j]``), read with ``canrls_theta_q31(S, j)`` and
``canrls_theta_frac_q31(S, j)``, so that the Cortex-M4 loads and stores it at once
(``LDRD``/``STRD``): at n = 6 built for that n, 984 instructions per update against
988 with a 32-bit estimate and 1004 with the fraction in an array of its own.

Accumulators (guard bits)
-------------------------
The multiply-accumulates (:math:`\varphi^\top\theta`, :math:`\tilde P\varphi`,
:math:`\varphi^\top\tilde h`) sum ``n`` products in ``acc_bits``. They never overflow,
by construction rather than by a check: the plan shifts the regressor operand right
(rounded, once per sample, shared by the three sums) by the smallest guard shift for
which ``n`` products at the *largest representable* magnitudes of their words, plus
the additive term and the final rounding constant, stay below ``2**(acc_bits-1)``
(``constants["phi_ps"]``). Because every operand is a saturated word this holds for
every input, including a corrupted state; with 32-bit words and inputs and 64-bit
accumulators it costs 4-5 of the 30 fraction bits of :math:`\varphi`, far below the
LSB of the results. A configuration whose accumulator cannot hold the products at all
(32-bit words with a 32-bit accumulator) is rejected. The ``acc`` counter is kept so
every site is listed, and stays 0; the pure-Python reference
:func:`canrls.estimation.fixed_kernels.reference_block` asserts every accumulator value against
``acc_bits``.

Division
--------
One per update, modelled as the target does it: ``g = (1 << (frac_g + frac_den)) / d``,
an ``acc_bits`` dividend over a word divisor, truncated toward zero (C semantics).
Everything else multiplies: :math:`\lambda` and :math:`1/\lambda` are Q constants
computed once, exactly, from the rational value of ``lam`` (Python fractions, no
floating point) when the estimator is built (:attr:`FixedRLS.constants`).

Trace bound and flags
---------------------
Like :class:`canrls.estimation.rls.RLS`: a step that would take :math:`\mathrm{tr}P` above
``trace_max`` is taken with :math:`\lambda = 1` (no forgetting; flag ``WINDUP``).
Decided before the division with the equivalent division-free test
:math:`(\mathrm{tr}P - \lambda\,\mathrm{trace\_max})(\lambda+\varphi^\top P\varphi) >
|P\varphi|^2`, so there is still one division. ``trace_max=None`` means
:math:`n/\alpha`, the prior's trace. ``LOW_EXCITATION`` is set by the kernel when
the sample's information :math:`K_i h_i` rounds to zero on the whole diagonal of
:math:`\tilde P` (the sample changed nothing the words can hold). ``SATURATION``
when any counter moved during the step, ``FROZEN`` after :meth:`FixedRLS.freeze`.

Update forms
------------
``update="symmetric"`` (default) is the embedded form: upper triangle only, so
:math:`P` is symmetric by construction at half the work. ``"literal"`` is the
textbook full-matrix :math:`P - K(\varphi^\top P)` with :math:`\varphi^\top P`
computed as written (as :mod:`canrls.estimation.rls` does); its rounding loses symmetry, but
its error propagates like the symmetric form's (to first order
:math:`\delta P \mapsto (I - K\varphi^\top)\,\delta P\,(I - \varphi K^\top)/\lambda`
for any :math:`\delta P`), so it stays close while costing twice the work.
``"naive"`` is the full-matrix update with :math:`\varphi^\top P` taken as
:math:`(P\varphi)^\top`, as embedded code often writes it: there the antisymmetric
part of the rounding error is not damped at all, :math:`A \mapsto A/\lambda`, so it
grows as :math:`\lambda^{-k}` and the estimator diverges within a few thousand
samples for any :math:`\lambda < 1` (``tests/test_fixed.py``). Both are kept only
for comparison.
"""

from __future__ import annotations

import enum
import math
import operator
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass
from fractions import Fraction
from typing import Any

import importlib
from types import ModuleType

import numpy as np
import numpy.typing as npt

from canrls.errors import CheckpointError, EstimatorError, FixedPointError
from canrls.estimation import fixed_layout as kernels
from canrls.estimation.rls import check_lam as _rls_check_lam
from canrls.estimation.rls import check_real as _rls_real
from canrls.estimation.rls import check_ridge, ridge_value

__all__ = [
    "QFormat",
    "FixedConfig",
    "FixedFlag",
    "SaturationCounts",
    "FixedStep",
    "FixedTrace",
    "FixedRLS",
    "SweepRow",
    "SweepResult",
    "sweep",
    "SITES",
]

IntArray = npt.NDArray[np.int64]
FloatArray = npt.NDArray[np.float64]

#: Saturation sites, in counter order.
SITES: tuple[str, ...] = kernels.SITES

#: Format tag of :meth:`FixedRLS.state` dictionaries (``/3``: with ``P_frac``).
STATE_FORMAT = "canrls.fixed/3"
#: The tag before the 64-bit covariance: read with ``P_frac = 0`` (``P`` exactly its words).
STATE_FORMAT_2 = "canrls.fixed/2"
#: The tag before the 64-bit estimate: read with ``theta_frac = 0`` and ``P_frac = 0``.
STATE_FORMAT_1 = "canrls.fixed/1"
#: The range of a fraction of ``P`` (units of 2^-32 LSB): the word is ``P~`` rounded.
P_FRAC_RANGE = (-(1 << 31), (1 << 31) - 1)

_UPDATES = {
    "symmetric": kernels.MODE_SYMMETRIC,
    "literal": kernels.MODE_LITERAL,
    "naive": kernels.MODE_NAIVE,
}
#: Quantities that have a Q format in :class:`FixedConfig`, in table order.
_QUANTITIES = ("phi", "y", "theta", "P", "K", "eps", "h", "den", "g", "lam")
_MAX_WORD = 32  # products of two words must be exact in int64


# ---------------------------------------------------------------- Q formats
def _round_saturate(x: npt.NDArray[np.float64], scale: float, lo: float, hi: float,
                    out: IntArray) -> int:
    """``out = clip(floor(x * scale + 1/2), lo, hi)``; the number clamped, or -1 on a NaN.

    ``scale`` is the exact power of two ``2**frac``, so ``x * scale`` is ``ldexp(x, frac)``
    (one rounding of the exact product, as ldexp does). One pass in C
    (``canrls._fixed.round_saturate``: round half up, then saturate to the word, counted).
    """
    assert _CFIXED is not None, "canrls._fixed is not built (pip install builds it)"
    return int(_CFIXED.round_saturate(np.ascontiguousarray(x, np.float64), scale, lo, hi, out))


def _round_inputs(Phi: npt.NDArray[np.float64], Y: npt.NDArray[np.float64],
                  fmt: npt.NDArray[np.float64], Pq: IntArray, Yq: IntArray,
                  counts: IntArray) -> int:
    """:func:`_round_saturate` of ``Phi`` (flat) and ``Y`` (``fmt`` rows: ``[2**frac, lo,
    hi]`` of phi and y), the clamps added to the ``phi_in`` and ``y_in`` counters; 1 or 2
    when ``Phi`` or ``Y`` holds a NaN (then nothing is counted), else 0.
    """
    n_phi = _round_saturate(Phi, fmt[0, 0], fmt[0, 1], fmt[0, 2], Pq)
    if n_phi < 0:
        return 1
    n_y = _round_saturate(Y, fmt[1, 0], fmt[1, 1], fmt[1, 2], Yq)
    if n_y < 0:
        return 2
    counts[kernels.S_PHI] += n_phi
    counts[kernels.S_Y] += n_y
    return 0


def _c_kernel() -> ModuleType | None:
    """The compiled C kernel ``canrls._fixed`` (built by ``pip install``), or None."""
    try:
        return importlib.import_module("canrls._fixed")
    except ImportError:
        return None


_CFIXED = _c_kernel()


def _spec_kernels() -> ModuleType:
    """The compiled specification (:mod:`canrls.estimation.fixed_kernels`), imported on
    first use only: the literal and naive forms, a model larger than the C kernel's bound,
    or a machine without the extension."""
    return importlib.import_module("canrls.estimation.fixed_kernels")


def _nan_error(q: QFormat) -> FixedPointError:
    """The error of a NaN handed to :meth:`QFormat.quantize` (or the inputs of the RLS)."""
    return FixedPointError(f"cannot quantize NaN to {q}")


@dataclass(frozen=True, slots=True)
class QFormat:
    """A signed two's-complement fixed-point format: ``bits`` bits, ``frac`` fraction bits.

    The integer ``q`` represents ``q * 2**-frac``; its range is
    ``[-2**(bits-1), 2**(bits-1) - 1]``.

    Parameters
    ----------
    bits : int
        Word length, 2..64.
    frac : int
        Number of fraction bits (may exceed ``bits - 1`` for small quantities, or be
        negative for a coarse one).

    Examples
    --------
    >>> q = QFormat(16, 14)
    >>> str(q), q.lo, q.hi, q.max
    ('Q1.14', -32768, 32767, 1.99993896484375)
    """

    bits: int
    frac: int

    def __post_init__(self) -> None:
        for name in ("bits", "frac"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int | np.integer):
                raise FixedPointError(f"QFormat {name} must be an integer, got {v!r}")
            object.__setattr__(self, name, int(v))
        if not 2 <= self.bits <= 64:
            raise FixedPointError(f"QFormat bits must be in 2..64, got {self.bits}")
        if not -64 <= self.frac <= 126:
            raise FixedPointError(f"QFormat frac must be in -64..126, got {self.frac}")

    @classmethod
    def for_range(cls, max_abs: float, bits: int) -> QFormat:
        """The format of ``bits`` bits with the most fraction bits that holds ``±max_abs``.

        The integer bits ``m`` are the smallest with ``2**m > max_abs``, so
        ``max_abs`` itself is representable (``1.0`` gets ``Q1.(bits-2)``).
        """
        x = float(max_abs)
        if not (x > 0.0 and math.isfinite(x)):
            raise FixedPointError(f"range of a Q format must be finite and > 0, got {max_abs!r}")
        m = math.frexp(x)[1]  # x = f 2^m, 0.5 <= f < 1  ->  2^(m-1) <= x < 2^m
        return cls(bits, bits - 1 - m)

    @property
    def int_bits(self) -> int:
        """Integer bits besides the sign, ``bits - 1 - frac``."""
        return self.bits - 1 - self.frac

    @property
    def lo(self) -> int:
        """Smallest integer, ``-2**(bits-1)``."""
        return -(1 << (self.bits - 1))

    @property
    def hi(self) -> int:
        """Largest integer, ``2**(bits-1) - 1``."""
        return (1 << (self.bits - 1)) - 1

    @property
    def lsb(self) -> float:
        """Value of one LSB, ``2**-frac``."""
        return math.ldexp(1.0, -self.frac)

    @property
    def max(self) -> float:
        """Largest representable value, ``hi * 2**-frac``."""
        return math.ldexp(float(self.hi), -self.frac)

    def to_int(self, x: float | Fraction) -> int:
        """``x`` rounded half up to this format, exactly (no saturation)."""
        v = Fraction(x) * (Fraction(2) ** self.frac)
        return math.floor(v + Fraction(1, 2))

    def to_float(self, q: int | npt.ArrayLike) -> Any:
        """The real value of integer(s) ``q`` (float64)."""
        return np.ldexp(np.asarray(q, dtype=np.float64), -self.frac)

    def quantize(self, x: npt.ArrayLike) -> tuple[IntArray, int]:
        """Round float(s) to nearest (half up) and saturate to the word.

        Returns
        -------
        (q, saturated) : (ndarray of int64, int)
            The integers and how many values were clamped (``±inf`` clamp too).

        Raises
        ------
        FixedPointError
            A value is NaN.
        """
        a = np.asarray(x, dtype=np.float64)
        q = np.empty(a.shape, np.int64)
        # x 2^frac is exact (power of two); floor(v + 1/2) is exact for |v| < 2^52,
        # and larger values saturate anyway
        nsat = _round_saturate(a.ravel(), *self._rounding(), q.reshape(-1))
        if nsat < 0:
            raise _nan_error(self)
        return (q[()] if q.ndim == 0 else q), nsat

    def _rounding(self) -> tuple[float, float, float]:
        """``(2**frac, lo, hi)`` as floats: the constants of :meth:`quantize`."""
        return math.ldexp(1.0, self.frac), float(self.lo), float(self.hi)

    def __str__(self) -> str:
        return f"Q{self.int_bits}.{self.frac}"

    def to_dict(self) -> dict[str, int]:
        """``{"bits": ..., "frac": ...}``."""
        return {"bits": self.bits, "frac": self.frac}


# -------------------------------------------------------------- the config
def _as_qformat(name: str, v: object) -> QFormat:
    if isinstance(v, QFormat):
        return v
    if isinstance(v, Mapping):
        try:
            return QFormat(v["bits"], v["frac"])
        except KeyError as e:
            raise FixedPointError(f"Q format of {name!r} lacks key {e}") from e
    if isinstance(v, tuple | list) and len(v) == 2:
        return QFormat(v[0], v[1])
    raise FixedPointError(f"Q format of {name!r} must be a QFormat, got {v!r}")


@dataclass(frozen=True)
class FixedConfig:
    r"""Word lengths and the Q format of every quantity of the fixed-point RLS.

    Build it with :meth:`auto` from the ranges of the problem; override any format
    with keywords of :meth:`auto` or with :func:`dataclasses.replace`.

    Attributes
    ----------
    word_bits : int
        State word (``theta``, ``P``, ``K``, ``eps``, ``h``, ``den``, ``g``, ``lam``),
        8..32.
    acc_bits : int
        Accumulator of multiply-accumulates and dividend of the division, 16..64.
    input_bits : int
        Input word of ``phi`` and ``y``, 2..32.
    phi, y, theta, P, K, eps, h, den, g, lam : QFormat
        Regressors, target, estimate, :math:`P`, gain, a-priori error,
        :math:`h = P\varphi`, :math:`d = \lambda + \varphi^\top P\varphi`, the
        reciprocal :math:`g = 1/d`, and :math:`\lambda`, :math:`1/\lambda`.

    Raises
    ------
    FixedPointError
        A word is wider than the limits above, or a format has a negative fraction
        or a fraction beyond 62 bits (the message names the quantity and format).
    """

    word_bits: int
    acc_bits: int
    input_bits: int
    phi: QFormat
    y: QFormat
    theta: QFormat
    P: QFormat
    K: QFormat
    eps: QFormat
    h: QFormat
    den: QFormat
    g: QFormat
    lam: QFormat

    def __post_init__(self) -> None:
        for name, lo, hi in (("word_bits", 8, 32), ("acc_bits", 16, 64), ("input_bits", 2, 32)):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int | np.integer) or not lo <= v <= hi:
                raise FixedPointError(
                    f"FixedConfig {name} must be an integer in {lo}..{hi}, got {v!r}"
                )
            object.__setattr__(self, name, int(v))
        for name in _QUANTITIES:
            q = _as_qformat(name, getattr(self, name))
            object.__setattr__(self, name, q)
            if q.bits > _MAX_WORD:
                raise FixedPointError(
                    f"FixedConfig {name} format {q} has {q.bits} bits; words are at most "
                    f"{_MAX_WORD} bits (products must be exact in 64 bits)"
                )
            if not 0 <= q.frac <= 62:
                raise FixedPointError(
                    f"FixedConfig {name} format {q} ({q.bits} bits) has {q.frac} fraction "
                    f"bits; the range of {name} needs more integer bits than the word has"
                )

    @classmethod
    def auto(
        cls,
        n: int,
        alpha: float | npt.ArrayLike,
        lam: float,
        phi_max: float | Sequence[float] | npt.ArrayLike = 1.0,
        y_max: float = 1.0,
        theta_max: float | None = None,
        word_bits: int = 32,
        acc_bits: int = 64,
        input_bits: int | None = None,
        trace_max: float | None = None,
        **overrides: QFormat,
    ) -> FixedConfig:
        r"""Choose every Q format from the ranges of the problem (module docstring table).

        Parameters
        ----------
        n : int
            Number of parameters.
        alpha : float or sequence of n floats
            Ridge weight, :math:`P_0 = I/\alpha` (normalised units, typical 1e-3..1e-1),
            or one per parameter, :math:`P_0 = \mathrm{diag}(1/\alpha_j)`: the bounds
            then use :math:`\max_j 1/\alpha_j` and :math:`\sum_j 1/\alpha_j`.
        lam : float
            Forgetting factor, :math:`1/2 < \lambda \le 1` (typical 0.98..1).
        phi_max : float or sequence of n floats, default 1.0
            Nominal :math:`\max|\varphi_j|`, one for all columns or one per column.
        y_max : float, default 1.0
            Nominal :math:`\max|y|`.
        theta_max : float or None
            Bound on :math:`|\theta_j|`; ``None``: :math:`4\,y_{max}/\min_j\bar\varphi_j`.
        word_bits, acc_bits : int, default 32, 64
            State word and accumulator.
        input_bits : int or None
            Input word of ``phi`` and ``y``; ``None``: ``word_bits``.
        trace_max : float or None
            The trace bound the estimator will use (``None``: :math:`\sum_j 1/\alpha_j`, the
            default of :class:`FixedRLS`); it bounds :math:`P` when :math:`\lambda < 1`.
        **overrides : QFormat
            Formats to use instead of the derived ones (``P=QFormat(32, 20)``, ...).

        Returns
        -------
        FixedConfig

        Raises
        ------
        FixedPointError
            A range does not fit its word (names the quantity and the format).
        """
        n_i = _check_n(n)
        ridge = _check_ridge(alpha, n_i)
        lam_f = _check_lam(lam)
        W = word_bits
        In = W if input_bits is None else input_bits
        pm = np.broadcast_to(np.asarray(phi_max, dtype=np.float64), (n_i,))
        if not (np.all(np.isfinite(pm)) and np.all(pm > 0)):
            raise FixedPointError(f"phi_max must be finite and > 0, got {phi_max!r}")
        ym = float(y_max)
        if not (math.isfinite(ym) and ym > 0):
            raise FixedPointError(f"y_max must be finite and > 0, got {y_max!r}")
        tm = 4.0 * ym / float(pm.min()) if theta_max is None else float(theta_max)
        finite = trace_max is not None and math.isfinite(trace_max)
        p0_sum = float(np.sum(1.0 / ridge))
        tr = float(trace_max) if finite else p0_sum  # type: ignore[arg-type]
        # bound on every |P_ij| (and on the largest eigenvalue of P)
        P_bar = float(np.max(1.0 / ridge)) if lam_f == 1.0 else max(p0_sum, tr)
        phi_norm = float(np.sqrt(np.sum(pm * pm)))

        def fmt(name: str, bound: float, bits: int) -> QFormat:
            try:
                return QFormat.for_range(bound, bits)
            except FixedPointError as e:
                raise FixedPointError(f"range of {name}: {e}") from e

        P_q = _as_qformat("P", overrides["P"]) if "P" in overrides else fmt("P", P_bar, W)
        # with the block exponent e > 0, tr P (words) <= half the range of P
        P_top = math.ldexp(1.0, P_q.int_bits - 1)
        # phi' P~ phi, with P~ = P / c (1/2 < c <= 1) bounded by P_bar or half its range
        den_max = 1.0 + max(P_bar, P_top) * phi_norm * phi_norm
        K_max = max(
            min(math.sqrt(P_bar) / (2.0 * math.sqrt(lam_f)), P_bar * phi_norm / lam_f),
            P_top * phi_norm / lam_f,
        )
        formats: dict[str, QFormat] = {
            "phi": fmt("phi", float(pm.max()), In),
            "y": fmt("y", ym, In),
            "theta": fmt("theta", tm, W),
            "P": P_q,
            "K": fmt("K", K_max, W),
            "eps": fmt("eps", 4.0 * ym, W),
            "h": fmt("h", max(P_bar, P_top) * phi_norm, W),
            "den": fmt("den", den_max, W),
            "lam": QFormat(W, W - 2),
        }
        # g = 1/d <= 1/lambda < 2: Q1.(W-2). The dividend 1 << (frac_g + frac_den) must fit
        # the accumulator; when it does not, the fractions are balanced so that d (at its
        # smallest, lambda) and g (at its smallest, 1/den_max) lose the same relative
        # precision: frac_den = frac_g - int_bits_den.
        if "den" in overrides:
            den_q = _as_qformat("den", overrides["den"])
        else:
            den_q = formats["den"]
            if den_q.frac + (W - 2) > acc_bits - 2:
                fg = min(W - 2, (acc_bits - 2 + den_q.int_bits) // 2)
                den_q = QFormat(W, min(den_q.frac, acc_bits - 2 - fg))
                formats["den"] = den_q
        formats["g"] = QFormat(W, min(W - 2, acc_bits - 2 - den_q.frac))
        unknown = set(overrides) - set(_QUANTITIES)
        if unknown:
            raise FixedPointError(
                f"FixedConfig.auto got unknown override(s) {sorted(unknown)}; "
                f"formats are {list(_QUANTITIES)}"
            )
        formats.update({k: _as_qformat(k, v) for k, v in overrides.items()})
        try:
            return cls(word_bits=W, acc_bits=acc_bits, input_bits=In, **formats)
        except FixedPointError as e:
            # P, K, h and den are sized from P0 = diag(1/alpha_j): name the knob
            raise FixedPointError(
                f"{e} (the ridge's P0 = diag(1/alpha_j) reaches {P_bar:.3g} here: a larger "
                f"estimator.alpha, or fixed.word_bits, gives it room)") from e

    def formats(self) -> dict[str, QFormat]:
        """The Q format of every quantity, in table order."""
        return {name: getattr(self, name) for name in _QUANTITIES}

    def quantize_inputs(
        self, Phi: npt.ArrayLike, Y: npt.ArrayLike
    ) -> tuple[IntArray, IntArray, SaturationCounts]:
        """Round normalised float inputs to the ``phi`` and ``y`` formats, saturating.

        Round to nearest (half up), then clamp to the input word; a value outside is
        counted, never wrapped. This runs at the edge (a host or the CAN decoder),
        not in the kernel.

        Returns
        -------
        (Phi_int, Y_int, saturations)
            ``int64`` arrays of the shapes of ``Phi`` and ``Y``, and the counts
            (``phi_in``, ``y_in``).
        """
        Pq, n_phi = self.phi.quantize(Phi)
        Yq, n_y = self.y.quantize(Y)
        counts = [0] * kernels.NSITES
        counts[kernels.S_PHI] = n_phi
        counts[kernels.S_Y] = n_y
        return Pq, Yq, SaturationCounts(counts)

    def to_dict(self) -> dict[str, Any]:
        """A JSON-able dict (``from_dict`` inverts it)."""
        d: dict[str, Any] = {
            "word_bits": self.word_bits,
            "acc_bits": self.acc_bits,
            "input_bits": self.input_bits,
        }
        d.update({name: q.to_dict() for name, q in self.formats().items()})
        return d

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> FixedConfig:
        """Rebuild a config from :meth:`to_dict`."""
        try:
            kw = {name: _as_qformat(name, d[name]) for name in _QUANTITIES}
            return cls(
                word_bits=d["word_bits"], acc_bits=d["acc_bits"], input_bits=d["input_bits"], **kw
            )
        except KeyError as e:
            raise FixedPointError(f"FixedConfig dict lacks key {e}") from e

    @property
    def label(self) -> str:
        """Short name of the word lengths, e.g. ``W32/A64/I16``."""
        return f"W{self.word_bits}/A{self.acc_bits}/I{self.input_bits}"

    def __str__(self) -> str:
        lines = [f"FixedConfig {self.label}"]
        for name, q in self.formats().items():
            lines.append(f"  {name:<6} {q!s:<8} {q.bits:>2} bit  lsb {q.lsb:.3g}  max {q.max:.6g}")
        return "\n".join(lines)


# --------------------------------------------------------------- validation
def _check_n(n: object) -> int:
    if isinstance(n, bool):
        raise EstimatorError(f"FixedRLS n must be a positive integer, got {n!r}")
    try:
        v = operator.index(n)  # type: ignore[arg-type]
    except TypeError as e:
        raise EstimatorError(f"FixedRLS n must be a positive integer, got {n!r}") from e
    if v < 1:
        raise EstimatorError(f"FixedRLS n must be a positive integer, got {n!r}")
    return v


def _real(name: str, value: object) -> float:
    return _rls_real(name, value, "FixedRLS")


def _check_lam(lam: object) -> float:
    return _rls_check_lam(lam, "FixedRLS", 0.5, " (1/lam is a Q1 word)")


def _check_ridge(alpha: object, n: int) -> npt.NDArray[np.float64]:
    return check_ridge(alpha, n, "FixedRLS")


# --------------------------------------------------------------------- plan
def _mac(
    acc_bits: int,
    phi: QFormat,
    b: QFormat,
    m: int,
    out: QFormat | None,
    term: QFormat | None = None,
    extra: int = 0,
) -> tuple[int, int, int]:
    """Shifts of one multiply-accumulate ``[term] + sum of m products (phi >> ps) * b -> out``.

    Returns ``(ps, ts, os)``: the guard shift of the ``phi`` operand (>= 0), the
    alignment of the term to the accumulator (> 0: left) and the output shift (> 0:
    rounding right shift). ``ps`` is the smallest for which the worst case (every
    operand at the largest magnitude its word holds) plus the rounding constant stays
    at or below ``2**(acc_bits - 1 - extra) - 1``.
    """
    lim = ((1 << (acc_bits - 1)) - 1) >> extra
    bmax = 1 << (b.bits - 1)
    for ps in range(0, 63):
        phimax = ((1 << (phi.bits - 1)) + ((1 << (ps - 1)) if ps else 0)) >> ps
        fa = phi.frac - ps + b.frac
        total = m * phimax * bmax
        ts = 0
        if term is not None:
            ts = fa - term.frac
            tmag = 1 << (term.bits - 1)
            total += tmag << ts if ts >= 0 else (tmag + (1 << (-ts - 1))) >> -ts
        os = 0 if out is None else fa - out.frac
        if os > 0:
            total += 1 << (os - 1)
        if total <= lim:
            return ps, ts, os
    raise FixedPointError(  # pragma: no cover - only absurd formats
        f"no guard shift of {phi} fits a {acc_bits}-bit accumulator"
    )


def _pre(acc_bits: int, a: QFormat, b: QFormat, m: int) -> int:
    """Pre-shift of each product of a rarely used multiply-accumulate (windup test)."""
    lim = (1 << (acc_bits - 1)) - 1
    pmax = (1 << (a.bits - 1)) * (1 << (b.bits - 1))
    for ps in range(0, 63):
        if m * ((pmax + ((1 << (ps - 1)) if ps else 0)) >> ps) <= lim:
            return ps
    raise FixedPointError("no pre-shift fits the accumulator")  # pragma: no cover


def _build_plan(
    cfg: FixedConfig, n: int, lam: float, trace_max: float
) -> tuple[IntArray, dict[str, int]]:
    """The kernel's integer constants (``fixed_kernels.I_*`` layout) and a named copy.

    Every constant is an exact function of the config, ``n``, the rational value of
    ``lam`` and ``trace_max``: Python integers and fractions, no floating point.
    """
    A = cfg.acc_bits
    p = np.zeros(kernels.NPARAM, dtype=np.int64)
    named: dict[str, int] = {}

    def put(i: int, name: str, v: int) -> None:
        if not -(1 << 63) <= v < (1 << 63):  # pragma: no cover - guarded by the checks
            raise FixedPointError(f"plan constant {name} = {v} does not fit 64 bits")
        p[i] = v
        named[name] = int(v)

    for q, lo_i, name in (
        (cfg.phi, kernels.I_PHI_LO, "phi"), (cfg.y, kernels.I_Y_LO, "y"), (cfg.eps, kernels.I_EPS_LO, "eps"),
        (cfg.h, kernels.I_H_LO, "h"), (cfg.den, kernels.I_DEN_LO, "den"), (cfg.g, kernels.I_G_LO, "g"),
        (cfg.K, kernels.I_K_LO, "K"), (cfg.theta, kernels.I_TH_LO, "theta"), (cfg.P, kernels.I_P_LO, "P"),
        (cfg.lam, kernels.I_L_LO, "lam"),
    ):  # fmt: skip
        put(lo_i, f"{name}_lo", q.lo)
        put(lo_i + 1, f"{name}_hi", q.hi)

    # the guard shift of phi: the largest the three multiply-accumulates need,
    #   eps = y - (phi >> ps)' theta ;  h~ = P~ (phi >> ps) ;  s~ = (phi >> ps)' h~ >> e
    # (s~ keeps one extra guard bit: the sum is then rounded by e bits)
    ps = max(
        _mac(A, cfg.phi, cfg.theta, n, cfg.eps, cfg.y)[0],
        _mac(A, cfg.phi, cfg.P, n, cfg.h)[0],
        _mac(A, cfg.phi, cfg.h, n, cfg.den, extra=1)[0],
    )
    if ps >= cfg.phi.bits - 1:
        raise FixedPointError(
            f"a {A}-bit accumulator cannot sum {n} products of phi {cfg.phi} "
            f"({cfg.phi.bits} bit) with {cfg.P.bits}-bit words: the guard shift {ps} "
            f"leaves no bit of phi"
        )
    put(kernels.I_PHI_PS, "phi_ps", ps)
    fa = cfg.phi.frac - ps + cfg.theta.frac
    put(kernels.I_EPS_TS, "eps_ts", fa - cfg.y.frac)
    put(kernels.I_EPS_OS, "eps_os", fa - cfg.eps.frac)
    put(kernels.I_H_OS, "h_os", cfg.phi.frac - ps + cfg.P.frac - cfg.h.frac)
    put(kernels.I_S_OS, "s_os", cfg.phi.frac - ps + cfg.h.frac - cfg.den.frac)
    # s = c s~ ; lambda and 1 in the den format
    put(kernels.I_SC_S, "sc_s", cfg.lam.frac)
    lam_d = cfg.den.to_int(Fraction(lam))
    one_d = cfg.den.to_int(1)
    if not 0 < lam_d <= one_d <= cfg.den.hi:
        raise FixedPointError(f"lam = {lam!r} and 1 must fit the den format {cfg.den}")
    put(kernels.I_LAM_D, "lam_den", lam_d)
    put(kernels.I_ONE_D, "one_den", one_d)
    # g = DIVIDEND // d ; gc = g c
    fdiv = cfg.g.frac + cfg.den.frac
    if fdiv > A - 2:
        raise FixedPointError(
            f"dividend 1 << (frac_g + frac_den) = 1 << {fdiv} of g {cfg.g} / den {cfg.den} "
            f"does not fit the {A}-bit accumulator"
        )
    put(kernels.I_DIVIDEND, "dividend", 1 << fdiv)
    put(kernels.I_GC_S, "gc_s", cfg.lam.frac)
    # single products rounded to their destination
    # K = rsh((h~ << k)(gc << g_up), 32): the high word of the product, with gc brought to
    # 32 bits; its fraction is then f_K' = f_h + k + f_g + g_up - 32 (exponent e)
    g_up = 32 - cfg.g.bits
    f_Kn = cfg.h.frac + cfg.g.frac + g_up - 32
    put(kernels.I_G_UP, "g_up", g_up)
    # g normalised: DIVIDEND 2^kg // d <= 2^(bits_g - 2) for d of bit length up to
    # kg_bl + kg, so that a large d (phi'P phi >= 1: the start, or data that suddenly
    # show a direction the prior held) still leaves g its bits; the dividend 2^(fdiv + kg)
    # must fit the accumulator
    put(kernels.I_KG_BL, "kg_bl", fdiv - cfg.g.bits + 3)
    put(kernels.I_KG_MAX, "kg_max", A - 2 - fdiv)
    put(kernels.I_TH_S, "theta_s", f_Kn + cfg.eps.frac - cfg.theta.frac)
    put(kernels.I_P_S, "P_s", f_Kn + cfg.h.frac - cfg.P.frac)
    # c <- c / lambda_k
    one_l = 1 << cfg.lam.frac
    inv_l = cfg.lam.to_int(1 / Fraction(lam))
    if not one_l <= inv_l <= cfg.lam.hi:
        raise FixedPointError(f"1/lam = {1 / lam!r} does not fit the lam format {cfg.lam}")
    put(kernels.I_INV_LAM, "inv_lam", inv_l)
    put(kernels.I_ONE_L, "one_lam", one_l)
    put(kernels.I_C_S, "c_s", cfg.lam.frac)
    # trace bound: the diagonal summed >> tr_ps must fit a word of min(P bits, A - 3) bits
    tw = min(cfg.P.bits, A - 3)
    tr_ps = 0
    while n * (((1 << (cfg.P.bits - 1)) + ((1 << (tr_ps - 1)) if tr_ps else 0)) >> tr_ps) >= (
        1 << (tw - 1)
    ):
        tr_ps += 1
    put(kernels.I_TR_PS, "trace_ps", tr_ps)
    put(kernels.I_TC_S, "tc_s", cfg.lam.frac)
    tr_cap = (1 << (tw - 1)) - 1  # tr P (times c <= 1) can never exceed this
    if math.isinf(trace_max):
        tmax = tr_cap
    else:
        lam_q = Fraction(cfg.lam.to_int(Fraction(lam)), one_l)
        tq = lam_q * Fraction(trace_max) * Fraction(2) ** (cfg.P.frac - tr_ps)
        tmax = min(math.floor(tq), tr_cap)
    put(kernels.I_TMAX, "trace_max_lam", tmax)
    put(kernels.I_TMAX_LIM, "trace_max_lim", 1 << (A - 3))
    # windup test: h = c h~, h'w pre-shifted, (tr P - lambda trace_max) d pre-shifted
    put(kernels.I_HC_S, "hc_s", cfg.lam.frac)
    vw_ps = _pre(A, cfg.h, cfg.h, n)
    lhs_ps = _pre(A, cfg.P, cfg.den, 1)
    put(kernels.I_VW_PS, "vw_ps", vw_ps)
    put(kernels.I_LHS_PS, "lhs_ps", lhs_ps)
    f_lhs = cfg.P.frac - tr_ps + cfg.den.frac - lhs_ps
    f_vw = 2 * cfg.h.frac - vw_ps
    put(kernels.I_CMP_DF, "cmp_scale_diff", f_lhs - f_vw)
    # block exponent of P: the window (tr_hi/2, tr_hi], and the largest exponent so
    # that every shift by (s + e) stays <= 62 and s~ >> e keeps its guard bit
    put(kernels.I_TR_HI, "trace_hi", 1 << (cfg.P.bits - 2))
    e_max = min(A - 3, 62 - named["theta_s"], 62 - named["P_s"])
    put(kernels.I_E_MAX, "e_max", e_max)
    for name, v in named.items():
        if name.endswith(("_ps", "_s")) and not 0 <= v <= 62:
            raise FixedPointError(
                f"shift {name} = {v} is outside 0..62: the Q formats of this configuration "
                f"are too far apart (or too close) for a {A}-bit accumulator"
            )
        if name.endswith(("_os", "_ts")) and abs(v) > 62:
            raise FixedPointError(f"shift {name} = {v} exceeds 62 bits")
    if e_max < 0:  # pragma: no cover - only absurd formats
        raise FixedPointError(f"no room for the block exponent of P {cfg.P}")
    return p, named


# --------------------------------------------------------- result objects
class FixedFlag(enum.IntFlag):
    """Per-step status bits; the values of :class:`canrls.estimation.rls.RLSFlag`."""

    NONE = 0
    #: The trace bound held this step: taken with lambda = 1.
    WINDUP = kernels.FLAG_WINDUP
    #: The sample's information rounded to zero on the diagonal of P.
    LOW_EXCITATION = kernels.FLAG_LOW_EXCITATION
    #: A value saturated during this step (see :attr:`FixedRLS.saturations`).
    SATURATION = kernels.FLAG_SATURATION
    #: The estimator is frozen: the error was computed, the state left untouched.
    FROZEN = kernels.FLAG_FROZEN


_FLAGS: tuple[FixedFlag, ...] = tuple(FixedFlag(i) for i in range(16))


class SaturationCounts(Mapping[str, int]):
    """Read-only counts of saturations per site (a ``Mapping[str, int]`` over :data:`SITES`).

    Examples
    --------
    >>> c = SaturationCounts.of({"theta": 2})
    >>> c["theta"], c["P"], c.total
    (2, 0, 2)
    """

    __slots__ = ("_v",)

    def __init__(self, values: Sequence[int] | npt.ArrayLike) -> None:
        v = tuple(np.asarray(values, dtype=np.int64).ravel().tolist())
        if len(v) != len(SITES):
            raise EstimatorError(f"SaturationCounts needs {len(SITES)} values, got {len(v)}")
        self._v = v

    @classmethod
    def of(cls, d: Mapping[str, int]) -> SaturationCounts:
        """Counts from a partial ``{site: count}`` mapping (missing sites are 0)."""
        bad = set(d) - set(SITES)
        if bad:
            raise EstimatorError(f"unknown saturation site(s) {sorted(bad)}; sites are {SITES}")
        return cls([int(d.get(s, 0)) for s in SITES])

    def __getitem__(self, key: str) -> int:
        try:
            return self._v[SITES.index(key)]
        except ValueError:
            raise KeyError(key) from None

    def __iter__(self) -> Iterator[str]:
        return iter(SITES)

    def __len__(self) -> int:
        return len(SITES)

    def __add__(self, other: SaturationCounts) -> SaturationCounts:
        return SaturationCounts([a + b for a, b in zip(self._v, other._v, strict=True)])

    def __sub__(self, other: SaturationCounts) -> SaturationCounts:
        return SaturationCounts([a - b for a, b in zip(self._v, other._v, strict=True)])

    def __eq__(self, other: object) -> bool:
        if isinstance(other, SaturationCounts):
            return self._v == other._v
        return Mapping.__eq__(self, other)

    def __hash__(self) -> int:
        return hash(self._v)

    @property
    def total(self) -> int:
        """Sum over all sites."""
        return sum(self._v)

    def nonzero(self) -> dict[str, int]:
        """The sites that saturated, ``{site: count}``."""
        return {s: v for s, v in zip(SITES, self._v, strict=True) if v}

    def __repr__(self) -> str:
        return f"SaturationCounts({self.nonzero()})"


@dataclass(frozen=True)
class FixedStep:
    """The result of one :meth:`FixedRLS.update` (integers in the config's formats).

    Attributes
    ----------
    eps : int
        A-priori error (``eps`` format).
    K : ndarray of int64, shape (n,)
        Gain applied this step, the high word of :math:`(\\tilde h\\,2^{k})(g c\\,2^{g_{up}})`:
        :math:`K\\,2^{f_h + f_g + g_{up} - 32 + e + k}` with ``e = P_exp`` before the
        renormalisation of this step and ``k`` the step's normalisation shift of
        :math:`\\tilde h` (zeros when frozen).
    theta : ndarray of int64, shape (n,)
        Estimate after the step (``theta`` format, a copy).
    trace_P : int
        :math:`\\mathrm{tr}\\,P\\,2^{f_{tr} + e}` after the step, with
        :math:`f_{tr}` = ``trace_frac``.
    P_exp : int
        Block exponent ``e`` of ``P`` after the step.
    trace_frac : int
        Fraction bits of ``trace_P`` at ``e = 0`` (``P.frac`` less the trace guard shift).
    flags : FixedFlag
        Status bits of the step.
    """

    eps: int
    K: IntArray
    theta: IntArray
    trace_P: int
    P_exp: int
    trace_frac: int
    flags: FixedFlag

    @property
    def trace_float(self) -> float:
        """:math:`\\mathrm{tr}\\,P` after the step as a float."""
        return math.ldexp(float(self.trace_P), -(self.trace_frac + self.P_exp))


@dataclass(frozen=True)
class FixedTrace:
    """The record of one :meth:`FixedRLS.run` over N samples (integers).

    Attributes
    ----------
    eps : ndarray of int64, shape (N,)
        A-priori errors (``eps`` format).
    theta : ndarray of int64, shape (N, n) or None
        Estimate after each sample (``theta`` format); ``None`` with ``record=False``.
    trace_P : ndarray of int64, shape (N,)
        :math:`\\mathrm{tr}\\,P\\,2^{f_{tr}+e}` after each sample (:meth:`trace_float`).
    P_exp : ndarray of int64, shape (N,)
        Block exponent ``e`` of ``P`` after each sample.
    trace_frac : int
        :math:`f_{tr}`: fraction bits of ``trace_P`` at ``e = 0``.
    flags : ndarray of uint8, shape (N,)
        :class:`FixedFlag` bits per sample.
    theta_final : ndarray of int64, shape (n,)
        Estimate at the end of the block.
    applied : int
        Samples that updated the state.
    saturations : SaturationCounts
        Saturations that happened during this block.
    config : FixedConfig
        The formats, to convert the integers (:meth:`theta_float`, :meth:`eps_float`).
    """

    eps: IntArray
    theta: IntArray | None
    trace_P: IntArray
    P_exp: IntArray
    trace_frac: int
    flags: npt.NDArray[np.uint8]
    theta_final: IntArray
    applied: int
    saturations: SaturationCounts
    config: FixedConfig

    def __len__(self) -> int:
        return int(self.eps.shape[0])

    def count(self, flag: FixedFlag) -> int:
        """Number of samples whose flags contain every bit of ``flag``."""
        f = int(flag)
        return int(np.count_nonzero((self.flags & f) == f))

    def theta_float(self) -> FloatArray:
        """``theta`` (or ``theta_final`` if not recorded) as floats."""
        t = self.theta if self.theta is not None else self.theta_final
        return np.asarray(self.config.theta.to_float(t))

    def eps_float(self) -> FloatArray:
        """``eps`` as floats."""
        return np.asarray(self.config.eps.to_float(self.eps))

    def trace_float(self) -> FloatArray:
        """:math:`\\mathrm{tr}\\,P` after each sample as floats."""
        return np.ldexp(self.trace_P.astype(np.float64), -(self.trace_frac + self.P_exp))


# ---------------------------------------------------------------- estimator
def _int_array(name: str, x: npt.ArrayLike, shape: tuple[int, ...]) -> IntArray:
    if (type(x) is np.ndarray and x.dtype == np.int64 and x.shape == shape
            and x.flags.c_contiguous):
        return x  # the common case (quantize_inputs output), as it is
    a = np.asarray(x)
    if a.dtype == object:
        try:
            a = a.astype(np.int64)
        except (OverflowError, TypeError, ValueError) as e:
            raise EstimatorError(f"FixedRLS {name} must hold 64-bit integers: {e}") from e
    if a.dtype.kind not in "iu" or a.dtype == np.bool_:
        raise EstimatorError(
            f"FixedRLS {name} must be integers (Q format), got dtype {a.dtype}; "
            f"convert floats with quantize_inputs()"
        )
    if a.shape != shape:
        raise EstimatorError(f"FixedRLS {name} must have shape {shape}, got {a.shape}")
    if a.dtype == np.uint64 and a.size and int(a.max()) > np.iinfo(np.int64).max:
        raise EstimatorError(f"FixedRLS {name} has values beyond 64-bit signed integers")
    if a.ndim == 0:
        return np.asarray(a, dtype=np.int64)
    return np.ascontiguousarray(a, dtype=np.int64)


class FixedRLS:
    r"""Fixed-point recursive least squares (integers in, integers out).

    Parameters
    ----------
    config : FixedConfig
        Word lengths and Q formats (:meth:`FixedConfig.auto`).
    n : int
        Number of parameters.
    lam : float
        Forgetting factor, :math:`1/2 < \lambda \le 1`, stored as Q integers
        :math:`\lambda` and :math:`1/\lambda` (rounded half up, exactly).
    alpha : float or sequence of n floats
        Ridge weight: :math:`P_0 = I/\alpha`, or one per parameter,
        :math:`P_0 = \mathrm{diag}(1/\alpha_j)`; each rounded to the ``P`` format.
    trace_max : float or None, default None
        Trace bound; ``None`` is :math:`\sum_j 1/\alpha_j` (the prior's trace), ``math.inf``
        disables it.
    update : {"symmetric", "literal", "naive"}, default "symmetric"
        ``"literal"``: full-matrix :math:`P - K\varphi^\top P`; ``"naive"``: full
        matrix with :math:`\varphi^\top P` taken as :math:`(P\varphi)^\top`. Both for
        comparison only (module docstring, *Update forms*).

    Raises
    ------
    EstimatorError
        An argument is out of range.
    FixedPointError
        ``config`` cannot represent :math:`P_0`, :math:`\lambda` or :math:`1/\lambda`,
        or its formats leave no valid shifts (names the quantity and format).

    Examples
    --------
    >>> import numpy as np
    >>> cfg = FixedConfig.auto(n=2, alpha=1e-2, lam=0.99)
    >>> rls = FixedRLS(cfg, n=2, lam=0.99, alpha=1e-2)
    >>> rng = np.random.default_rng(0)
    >>> Phi = rng.uniform(-1, 1, size=(2000, 2))
    >>> Phi_q, Y_q, sat = rls.quantize_inputs(Phi, Phi @ np.array([0.5, -0.25]))
    >>> trace = rls.run(Phi_q, Y_q)
    >>> np.round(rls.theta_float, 6)
    array([ 0.5 , -0.25])
    """

    def __init__(
        self,
        config: FixedConfig,
        n: int,
        lam: float,
        alpha: float | npt.ArrayLike,
        trace_max: float | None = None,
        update: str = "symmetric",
    ) -> None:
        if not isinstance(config, FixedConfig):
            raise EstimatorError(f"FixedRLS config must be a FixedConfig, got {config!r}")
        n_i = _check_n(n)
        lam_f = _check_lam(lam)
        ridge = _check_ridge(alpha, n_i)
        if update not in _UPDATES:
            raise EstimatorError(
                f"FixedRLS update must be one of {sorted(_UPDATES)}, got {update!r}"
            )
        if trace_max is None:
            tm = float(np.sum(1.0 / ridge))
        else:
            tm = _real("trace_max", trace_max)
            if not tm > 0.0:
                raise EstimatorError(f"FixedRLS trace_max must be > 0 (or None), got {trace_max!r}")
        # P0_jj = 1/alpha_j, exactly rounded to the P format
        p0 = np.array([config.P.to_int(1 / Fraction(float(a))) for a in ridge], np.int64)
        if not np.all((p0 > 0) & (p0 <= config.P.hi)):
            raise FixedPointError(
                f"P0 = 1/alpha = {float(np.max(1.0 / ridge)):.6g} does not fit the P format "
                f"{config.P} ({config.P.bits} bit, max {config.P.max:.6g})"
            )
        self._config = config
        self._n = n_i
        self._ridge = ridge
        #: whether the trace bound is the prior's trace (it follows a :meth:`rescale`)
        self._trace_default = trace_max is None
        self._trace_max = tm
        self._update = update
        self._mode = _UPDATES[update]
        self._p0 = p0
        self._lam = lam_f
        self._plan, self._named = _build_plan(config, n_i, lam_f, tm)
        self._cplan: IntArray = self._plan
        self._cplan_of: IntArray | None = None  # the plan self._cplan was built from
        self._force_spec = False
        self._trace_frac = config.P.frac - self._named["trace_ps"]
        self._in_fmt = np.array([config.phi._rounding(), config.y._rounding()])
        self._theta = np.zeros(n_i, np.int64)
        self._theta_frac = np.zeros(n_i, np.int64)  # below the LSB, 2^-32 LSB units
        self._P = np.zeros((n_i, n_i), np.int64)
        self._P_frac = np.zeros((n_i, n_i), np.int64)  # below the words, 2^-32 LSB units
        self._scale = np.zeros(2, np.int64)  # [e, c]
        self._work = np.zeros((6, n_i), np.int64)
        self._counts = np.zeros(len(SITES), np.int64)
        self._frozen = False
        self.count = 0
        self._reset_arrays()
        # one-row buffers of update()
        self._phi1 = np.zeros((1, n_i), np.int64)
        self._y1 = np.zeros(1, np.int64)
        self._eps1 = np.zeros(1, np.int64)
        self._tr1 = np.zeros(1, np.int64)
        self._exp1 = np.zeros(1, np.int64)
        self._flags1 = np.zeros(1, np.uint8)
        self._norec = np.zeros((0, n_i), np.int64)

    def _reset_arrays(self) -> None:
        # P0 = diag(1 / alpha_j) ; theta0 = 0
        self._P[...] = 0
        self._P_frac[...] = 0
        self._P[np.diag_indices(self._n)] = self._p0
        self._scale[0] = 0
        self._scale[1] = 1 << self._config.lam.frac
        self._theta[...] = 0
        self._theta_frac[...] = 0
        self._work[...] = 0

    # ----------------------------------------------------------- properties
    @property
    def config(self) -> FixedConfig:
        """Word lengths and Q formats."""
        return self._config

    @property
    def n(self) -> int:
        """Number of parameters."""
        return self._n

    @property
    def lam(self) -> float:
        """Forgetting factor (change it with :meth:`set_lambda`)."""
        return self._lam

    @property
    def alpha(self) -> float | npt.NDArray[np.float64]:
        """Ridge weight of the prior :math:`P_0 = I/\\alpha` (one float), or the weights
        :math:`\\alpha_j` of :math:`P_0 = \\mathrm{diag}(1/\\alpha_j)`."""
        return ridge_value(self._ridge)

    @property
    def trace_max(self) -> float:
        """Trace bound (``inf``: none)."""
        return self._trace_max

    @property
    def update_form(self) -> str:
        """``"symmetric"``, ``"literal"`` or ``"naive"``."""
        return self._update

    @property
    def frozen(self) -> bool:
        """Whether updates leave the state untouched."""
        return self._frozen

    @property
    def constants(self) -> dict[str, int]:
        """Every integer constant of the kernel by name (shifts, ranges, :math:`\\lambda`, ...).

        With :attr:`config` this is all an embedded implementation needs to
        reproduce the kernel bit for bit.
        """
        return dict(self._named)

    @property
    def theta(self) -> IntArray:
        """Estimate in the ``theta`` format, shape (n,) (read-only live view)."""
        v = self._theta.view()
        v.flags.writeable = False
        return v

    @property
    def theta_frac(self) -> IntArray:
        """The estimate's fraction below the LSB of :attr:`theta`, in units of
        :math:`2^{-32}` LSB (``0 <= theta_frac < 2**32``), shape (n,) (read-only live view).

        The estimate is the 64-bit ``theta * 2**32 + theta_frac``; the kernel publishes
        and predicts with the word :attr:`theta` and accumulates the updates below its
        LSB here (module docstring, *Rounding and saturation*).
        """
        v = self._theta_frac.view()
        v.flags.writeable = False
        return v

    @property
    def P_exp(self) -> int:
        """Block exponent ``e`` of :math:`P = c\\tilde P 2^{-(f_P + e)}`."""
        return int(self._scale[0])

    @property
    def P_scale(self) -> int:
        """Forgetting scale ``c`` of :math:`P = c\\tilde P 2^{-(f_P + e)}` (``lam`` format)."""
        return int(self._scale[1])

    @property
    def P(self) -> IntArray:
        """The words :math:`\\tilde P` of :math:`P = c\\tilde P 2^{-(f_P + e)}`, shape (n, n).

        A copy; the symmetric form's lower triangle, which the kernel never stores,
        is mirrored in. See :attr:`P_exp`, :attr:`P_scale`, :attr:`P_float`.
        """
        P = self._P.copy()
        if self._mode == kernels.MODE_SYMMETRIC:
            il = np.tril_indices(self._n, -1)
            P[il] = P.T[il]
        return P

    @property
    def P_frac(self) -> IntArray:
        """The fractions of the words :attr:`P` in units of :math:`2^{-32}` LSB, in
        :math:`[-2^{31}, 2^{31})`, shape (n, n) (a copy, mirrored like :attr:`P`).

        :math:`\\tilde P` is held in 64 bits, ``P * 2**32 + P_frac``; the word ``P`` is it
        rounded half up to the ``P`` format, which is what the kernel reads (``h = P~
        phi``, the trace); the update ``P~ - K h~'`` is subtracted from the 64 bits
        (docs/fixed_point.md, *The covariance in 64 bits*).
        """
        F = self._P_frac.copy()
        if self._mode == kernels.MODE_SYMMETRIC:
            il = np.tril_indices(self._n, -1)
            F[il] = F.T[il]
        return F

    @property
    def theta_float(self) -> FloatArray:
        """Estimate as float64 (normalised units)."""
        return np.asarray(self._config.theta.to_float(self._theta))

    @property
    def P_float(self) -> FloatArray:
        """:math:`P` as float64 (the words and their fractions), shape (n, n)."""
        c = self._config.lam.to_float(self.P_scale)
        words = self.P.astype(np.float64) + np.ldexp(self.P_frac.astype(np.float64), -32)
        return c * np.ldexp(words, -(self._config.P.frac + self.P_exp))

    @property
    def saturations(self) -> SaturationCounts:
        """Saturations per site since construction or :meth:`reset` (a snapshot)."""
        return SaturationCounts(self._counts)

    def std(self, sigma2: float) -> FloatArray:
        r"""Parameter standard deviations :math:`\sqrt{\sigma^2\,\mathrm{diag}\,P}` (float).

        Parameters
        ----------
        sigma2 : float
            Noise variance of :math:`y` in normalised units (e.g. the float
            estimator's :attr:`canrls.estimation.rls.RLS.sigma2`).

        Returns
        -------
        ndarray, shape (n,)
            ``nan`` where the diagonal of :math:`P` is negative (a broken literal P).
        """
        s2 = _real("sigma2", sigma2)
        if not s2 >= 0.0:
            raise EstimatorError(f"FixedRLS sigma2 must be >= 0, got {sigma2!r}")
        d = np.diag(self.P_float)
        with np.errstate(invalid="ignore"):
            return np.sqrt(s2 * d)

    # -------------------------------------------------------------- control
    def reset(self) -> None:
        """Return to :math:`P_0 = I/\\alpha`, :math:`\\theta_0 = 0`; zero the counters and count.

        The frozen state, ``lam`` and ``trace_max`` are kept.
        """
        self._reset_arrays()
        self._counts[...] = 0
        self.count = 0

    def freeze(self) -> None:
        """Stop adapting: updates compute :math:`\\varepsilon` only, flagged ``FROZEN``."""
        self._frozen = True

    def resume(self) -> None:
        """Adapt again after :meth:`freeze`."""
        self._frozen = False

    def set_lambda(self, lam: float) -> None:
        """Change the forgetting factor (new Q constants; validated like the constructor's)."""
        lam_f = _check_lam(lam)
        self._plan, self._named = _build_plan(self._config, self._n, lam_f, self._trace_max)
        self._lam = lam_f

    def rescale(self, d: npt.ArrayLike, dy: int = 0,
                prior: Mapping[int, float] | None = None) -> None:
        r"""New units for the columns and the target, by powers of two, and raised
        priors, as :meth:`canrls.estimation.rls.RLS.rescale` does them: computed exactly
        (rationals) on the real values the words stand for, then rounded half up back to
        the words: the 64-bit estimate, and the 64-bit :math:`\tilde P` (its words and
        fractions) with the largest block exponent ``e`` (at most ``e_max``) that keeps
        :math:`\mathrm{tr}\tilde P` within half the word's range, as the kernel keeps it.
        Where even ``e = 0`` cannot hold a value it saturates, counted (``theta``, ``P``)."""
        n = self._n
        dv = [int(x) for x in np.asarray(d, dtype=np.int64).reshape(-1)]
        if len(dv) != n:
            raise EstimatorError(f"FixedRLS rescale needs {n} exponents, got {len(dv)}")
        dy = int(dy)
        cfg = self._config
        two = Fraction(2)
        # the real values: P = c P~ 2^-(f_P + e), theta = (word 2^32 + frac) 2^-(32 + f_th)
        c = Fraction(int(self._scale[1])) / two ** cfg.lam.frac
        e = int(self._scale[0])
        Pw, Pf = self.P, self.P_frac  # the whole matrix (the triangle mirrored)
        unit = c / two ** (cfg.P.frac + e + 32)
        P = [[Fraction((int(Pw[j, k]) << 32) + int(Pf[j, k])) * unit * two ** (dv[j] + dv[k])
              for k in range(n)] for j in range(n)]
        th_unit = two ** -(32 + cfg.theta.frac)
        th = [Fraction((int(self._theta[j]) << 32) | int(self._theta_frac[j])) * th_unit
              * two ** (dv[j] - dy) for j in range(n)]
        ridge = [Fraction(float(a)) / two ** (2 * x) for a, x in zip(self._ridge, dv,
                                                                     strict=True)]
        for j, alpha in (prior or {}).items():
            delta = Fraction(float(alpha)) - ridge[j]
            if delta > 0:
                # g = P e_j / (1 + delta P_jj); theta -= delta theta_j g; P -= delta g P_j.
                den = 1 + delta * P[j][j]
                g = [P[i][j] / den for i in range(n)]
                tj, Pj = th[j], list(P[j])
                th = [th[i] - delta * tj * g[i] for i in range(n)]
                P = [[P[i][k] - delta * g[i] * Pj[k] for k in range(n)] for i in range(n)]
            ridge[j] = Fraction(float(alpha))
        # theta back to its 64 bits
        q = cfg.theta
        lo, hi = q.lo << 32, (q.hi << 32) | 0xFFFFFFFF
        for j in range(n):
            v = math.floor(th[j] / th_unit + Fraction(1, 2))
            if not lo <= v <= hi:
                self._counts[kernels.S_TH] += 1
                v = min(max(v, lo), hi)
            self._theta[j], self._theta_frac[j] = v >> 32, v & 0xFFFFFFFF
        # P back to its words, with the largest block exponent that keeps them in range
        sym = self._mode == kernels.MODE_SYMMETRIC
        cells = [(j, k) for j in range(n) for k in range(j if sym else 0, n)]
        half = Fraction(1 << (cfg.P.bits - 2))
        tr = sum(P[j][j] for j in range(n))
        top = max([abs(P[j][k]) for j, k in cells] + [Fraction(0)])

        def words_at(ex: int) -> Fraction:
            return c / two ** (cfg.P.frac + ex)

        e_new = 0
        for ex in range(int(self._named["e_max"]), 0, -1):
            if tr / words_at(ex) <= half and top / words_at(ex) <= cfg.P.hi:
                e_new = ex
                break
        u = words_at(e_new) / two ** 32
        for j, k in cells:
            self._put_P(j, k, math.floor(P[j][k] / u + Fraction(1, 2)))
        self._scale[0] = e_new
        self._ridge = np.array([float(a) for a in ridge], dtype=np.float64)
        self._prior_changed()

    def set_prior(self, j: int, alpha: float) -> None:
        r"""Give parameter ``j`` the ridge weight ``alpha`` as if from the start
        (:meth:`canrls.estimation.rls.RLS.set_prior`): :math:`\tilde P_{jj} \leftarrow
        \tilde P_{jj}\,\alpha_j/\alpha` in 64 bits, rounded half up at :math:`2^{-32}` LSB,
        saturated (counted)."""
        a = _real("alpha", alpha)
        if not (a > 0.0 and math.isfinite(a)):
            raise EstimatorError(f"FixedRLS alpha must be > 0, got {alpha!r}")
        ratio = Fraction(float(self._ridge[j])) / Fraction(a)
        V = (int(self._P[j, j]) << 32) + int(self._P_frac[j, j])
        self._put_P(j, j, math.floor(V * ratio + Fraction(1, 2)))
        self._ridge = self._ridge.copy()
        self._ridge[j] = a
        self._prior_changed()

    def _put_P(self, j: int, k: int, V: int) -> None:
        r"""Store :math:`V = \tilde P_{jk} 2^{32}` as the word ``rsh(V, 32)`` and its
        fraction, saturated to the word (counted), as the kernel stores it."""
        P = self._config.P
        lo, hi = (P.lo << 32) - (1 << 31), (P.hi << 32) + (1 << 31) - 1
        if not lo <= V <= hi:
            self._counts[kernels.S_P] += 1
            V = min(max(V, lo), hi)
        w = (V + (1 << 31)) >> 32
        self._P[j, k], self._P_frac[j, k] = w, V - (w << 32)

    def _prior_changed(self) -> None:
        """The prior's words for :meth:`reset` and, where it is the prior's, the trace bound."""
        P = self._config.P
        self._p0 = np.array([min(max(P.to_int(1 / Fraction(float(a))), 1), P.hi)
                             for a in self._ridge], np.int64)
        if self._trace_default:
            self._trace_max = float(np.sum(1.0 / self._ridge))
            self._plan, self._named = _build_plan(self._config, self._n, self._lam,
                                                  self._trace_max)

    # -------------------------------------------------------------- updates
    def quantize_inputs(
        self, Phi: npt.ArrayLike, Y: npt.ArrayLike, count: bool = True
    ) -> tuple[IntArray, IntArray, SaturationCounts]:
        """Round normalised float inputs to the input formats (:meth:`FixedConfig.quantize_inputs`).

        Parameters
        ----------
        Phi : array_like, shape (N, n) (or (n,))
        Y : array_like, shape (N,) (or scalar)
        count : bool, default True
            Add the input saturations to this estimator's ``phi_in``/``y_in``
            counters (the values handed to :meth:`run` are then in range, so the
            kernel does not count them again).

        Returns
        -------
        (Phi_int, Y_int, saturations)
        """
        Pq, Yq, sat = self._config.quantize_inputs(Phi, Y)
        if Pq.ndim not in (1, 2) or Pq.shape[-1] != self._n:
            raise EstimatorError(f"FixedRLS Phi must have shape (N, {self._n}), got {Pq.shape}")
        if count:
            self._counts[kernels.S_PHI] += sat["phi_in"]
            self._counts[kernels.S_Y] += sat["y_in"]
        return Pq, Yq, sat

    def quantize_block(self, Phi: FloatArray, Y: FloatArray) -> tuple[IntArray, IntArray]:
        """:meth:`quantize_inputs` (counted) without the checks, for a caller that built
        ``Phi`` (N, n) and ``Y`` (N,) itself, C-contiguous float64."""
        Pq = np.empty(Phi.shape, np.int64)
        Yq = np.empty(Y.shape, np.int64)
        nan = _round_inputs(Phi.reshape(-1), Y, self._in_fmt, Pq.reshape(-1), Yq, self._counts)
        if nan:
            raise _nan_error(self._config.phi if nan == 1 else self._config.y)
        return Pq, Yq

    def update(self, phi_int: npt.ArrayLike, y_int: int) -> FixedStep:
        r"""Process one sample: a block of one row of the same kernel as :meth:`run`.

        Parameters
        ----------
        phi_int : array_like of int, shape (n,)
            Regressor in the ``phi`` format (clamped to it if outside, counted).
        y_int : int
            Target in the ``y`` format.

        Returns
        -------
        FixedStep
        """
        if (
            type(phi_int) is np.ndarray
            and phi_int.dtype == np.int64
            and phi_int.shape == (self._n,)
        ):
            self._phi1[0] = phi_int  # the common case, without conversions
        else:
            self._phi1[0] = _int_array("phi_int", phi_int, (self._n,))
        if type(y_int) is int and -(1 << 63) <= y_int < (1 << 63):
            self._y1[0] = y_int
        else:
            self._y1[0] = _int_array("y_int", y_int, ())
        self.count += self._block(
            self._phi1, self._y1, False, self._eps1, self._norec, self._tr1, self._exp1,
            self._flags1,
        )  # fmt: skip
        return FixedStep(
            eps=int(self._eps1[0]),
            K=self._work[4].copy(),
            theta=self._theta.copy(),
            trace_P=int(self._tr1[0]),
            P_exp=int(self._exp1[0]),
            trace_frac=self._trace_frac,
            flags=_FLAGS[self._flags1[0]],
        )

    def run(self, Phi_int: npt.ArrayLike, Y_int: npt.ArrayLike, record: bool = True) -> FixedTrace:
        r"""Process a block of samples with the compiled kernel, carrying the state.

        Parameters
        ----------
        Phi_int : array_like of int, shape (N, n)
            Regressor rows in the ``phi`` format.
        Y_int : array_like of int, shape (N,)
            Targets in the ``y`` format.
        record : bool, default True
            Keep :math:`\theta` after every sample.

        Returns
        -------
        FixedTrace
        """
        Phi_a = np.asarray(Phi_int)
        if Phi_a.ndim != 2 or Phi_a.shape[1] != self._n:
            raise EstimatorError(
                f"FixedRLS Phi_int must have shape (N, {self._n}), got {Phi_a.shape}"
            )
        N = Phi_a.shape[0]
        Phi_c = _int_array("Phi_int", Phi_a, (N, self._n))
        Y_c = _int_array("Y_int", Y_int, (N,))
        before = self._counts.copy()
        eps, theta, trace_P, P_exp, flags, applied = self.run_block(Phi_c, Y_c, bool(record))
        return FixedTrace(
            eps=eps,
            theta=theta,
            trace_P=trace_P,
            P_exp=P_exp,
            trace_frac=self._trace_frac,
            flags=flags,
            theta_final=self._theta.copy(),
            applied=applied,
            saturations=SaturationCounts(self._counts - before),
            config=self._config,
        )

    def run_block(
        self, Phi_int: IntArray, Y_int: IntArray, record: bool
    ) -> tuple[IntArray, IntArray | None, IntArray, IntArray, npt.NDArray[np.uint8], int]:
        """:meth:`run` without the checks, for a caller that built the arrays itself.

        ``Phi_int`` (N, n) and ``Y_int`` (N,) are C-contiguous ``int64``. Returns
        ``(eps, theta or None, trace_P, P_exp, flags, applied)`` as in :class:`FixedTrace`.
        """
        N = Phi_int.shape[0]
        eps = np.empty(N, np.int64)
        trace_P = np.empty(N, np.int64)
        P_exp = np.empty(N, np.int64)
        flags = np.empty(N, np.uint8)
        theta_out = np.empty((N, self._n), np.int64) if record else self._norec
        applied = self._block(Phi_int, Y_int, record, eps, theta_out, trace_P, P_exp, flags)
        self.count += applied
        return eps, (theta_out if record else None), trace_P, P_exp, flags, applied

    @property
    def backend(self) -> str:
        """``"c"``: the blocks run in the C kernel (``canrls._fixed``, the symmetric form
        with ``n <= N_MAX``); ``"spec"``: in the compiled specification
        (:func:`canrls.estimation.fixed_kernels.fixed_block`). Both give the same integers.

        Set it to ``"spec"`` to run the specification (a test's reference), or to
        ``"auto"`` for the C kernel wherever it applies (the default).
        """
        if (not self._force_spec and _CFIXED is not None
                and self._mode == kernels.MODE_SYMMETRIC and self._n <= _CFIXED.N_MAX):
            return "c"
        return "spec"

    @backend.setter
    def backend(self, value: str) -> None:
        if value not in ("spec", "auto"):
            raise EstimatorError(f"FixedRLS backend must be 'spec' or 'auto', got {value!r}")
        self._force_spec = value == "spec"

    def _block(self, Phi: IntArray, Y: IntArray, record: bool, eps: IntArray,
               theta_out: IntArray, trace_P: IntArray, P_exp: IntArray,
               flags: npt.NDArray[np.uint8]) -> int:
        """Run the kernel (:attr:`backend`) over a block, in place; rows applied."""
        if self.backend == "c":
            assert _CFIXED is not None
            if self._cplan_of is not self._plan:
                # the plan in the order of the C struct's fields (canrls_plan_q31)
                self._cplan = np.array([self._named[f] for f in _CFIXED.PLAN_FIELDS], np.int64)
                self._cplan_of = self._plan
            return int(_CFIXED.run_block(
                Phi, Y, self._theta, self._theta_frac, self._P, self._P_frac, self._scale,
                self._work[4], self._counts, self._cplan, self._frozen, eps,
                theta_out if record else None, trace_P, P_exp, flags,
            ))  # fmt: skip
        return int(_spec_kernels().fixed_block(
            Phi, Y, self._theta, self._theta_frac, self._P, self._P_frac, self._scale,
            self._work, self._counts, self._plan, self._mode, self._frozen, record,
            eps, theta_out, trace_P, P_exp, flags,
        ))  # fmt: skip

    # ----------------------------------------------------------- checkpoint
    def state(self) -> dict[str, Any]:
        """The complete state as a plain dict (ints, strings, int64 arrays).

        Survives ``np.savez``/``np.load`` and JSON (after ``.tolist()``);
        :meth:`from_state` continues bit for bit.
        """
        return {
            "format": STATE_FORMAT,
            "config": self._config.to_dict(),
            "n": self._n,
            "lam": self._lam,
            "alpha": ridge_value(self._ridge),
            "trace_max": self._trace_max,
            "update": self._update,
            "frozen": self._frozen,
            "count": self.count,
            "theta": self._theta.copy(),
            "theta_frac": self._theta_frac.copy(),
            "P": self._P.copy(),
            "P_frac": self._P_frac.copy(),
            "P_exp": int(self._scale[0]),
            "P_scale": int(self._scale[1]),
            "counts": self._counts.copy(),
            "trace_default": self._trace_default,
        }

    @classmethod
    def from_state(cls, d: Mapping[str, Any] | Any) -> FixedRLS:
        """Rebuild an estimator from :meth:`state`.

        Raises
        ------
        CheckpointError
            A key is missing or malformed, or a value lies outside its word.
        """

        def get(key: str) -> Any:
            try:
                v = d[key]
            except KeyError as e:
                raise CheckpointError(f"FixedRLS checkpoint lacks key {key!r}") from e
            if isinstance(v, np.ndarray) and v.ndim == 0:
                return v.item()
            return v

        fmt = get("format")
        if fmt not in (STATE_FORMAT, STATE_FORMAT_2, STATE_FORMAT_1):
            raise CheckpointError(
                f"FixedRLS checkpoint format is {fmt!r}, expected {STATE_FORMAT!r} "
                f"(or {STATE_FORMAT_2!r}, read with P_frac = 0, or {STATE_FORMAT_1!r}, "
                f"read with theta_frac = 0 and P_frac = 0)"
            )
        try:
            cfg_d = get("config")
            if isinstance(cfg_d, str):
                import json

                cfg_d = json.loads(cfg_d)
            rls = cls(
                FixedConfig.from_dict(cfg_d),
                get("n"),
                lam=get("lam"),
                alpha=get("alpha"),
                trace_max=get("trace_max"),
                update=get("update"),
            )
        except (EstimatorError, TypeError, ValueError) as e:
            raise CheckpointError(f"FixedRLS checkpoint is invalid: {e}") from e
        n = rls.n
        cfg = rls.config
        frac = (0, (1 << 32) - 1)  # theta_frac: 2^-32 LSB, below one LSB
        for key, target, shape, q in (
            ("theta", rls._theta, (n,), cfg.theta),
            *((("theta_frac", rls._theta_frac, (n,), frac),) if fmt != STATE_FORMAT_1 else ()),
            ("P", rls._P, (n, n), cfg.P),
            *((("P_frac", rls._P_frac, (n, n), P_FRAC_RANGE),) if fmt == STATE_FORMAT else ()),
            ("counts", rls._counts, (len(SITES),), None),
        ):
            try:
                src = _int_array(key, get(key), shape)
            except EstimatorError as e:
                raise CheckpointError(f"FixedRLS checkpoint key {key!r}: {e}") from e
            lo, hi = (
                (0, np.iinfo(np.int64).max) if q is None
                else q if isinstance(q, tuple) else (q.lo, q.hi)
            )
            if src.size and (int(src.min()) < lo or int(src.max()) > hi):
                raise CheckpointError(
                    f"FixedRLS checkpoint key {key!r} has values outside [{lo}, {hi}]"
                )
            target[...] = src
        e = get("P_exp")
        if (
            isinstance(e, bool)
            or not isinstance(e, int | np.integer)
            or not (0 <= int(e) <= rls._named["e_max"])
        ):
            raise CheckpointError(
                f"FixedRLS checkpoint key 'P_exp' = {e!r} is not an integer in "
                f"0..{rls._named['e_max']}"
            )
        c = get("P_scale")
        if (
            isinstance(c, bool)
            or not isinstance(c, int | np.integer)
            or not (0 < int(c) <= rls._named["one_lam"])
        ):
            raise CheckpointError(
                f"FixedRLS checkpoint key 'P_scale' = {c!r} is not an integer in "
                f"1..{rls._named['one_lam']}"
            )
        rls._scale[0] = int(e)
        rls._scale[1] = int(c)
        rls._frozen = bool(get("frozen"))
        rls.count = int(get("count"))
        rls._trace_default = bool(d.get("trace_default", False)) if hasattr(d, "get") else False
        return rls

    def __repr__(self) -> str:
        return (
            f"FixedRLS({self._config.label}, n={self._n}, lam={self._lam!r}, "
            f"alpha={ridge_value(self._ridge)!r}, trace_max={self._trace_max!r}, update={self._update!r}, "
            f"count={self.count}, frozen={self._frozen})"
        )


# -------------------------------------------------------------------- sweep
@dataclass(frozen=True)
class SweepRow:
    """One configuration of a :func:`sweep`.

    Attributes
    ----------
    label : str
        ``W{word}/A{acc}/I{input}`` or the name given with the config.
    config : FixedConfig or None
        ``None`` when the word lengths cannot represent the problem (see ``error``).
    max_rel_error : float
        Largest relative parameter error against ``theta_ref`` (``inf`` if not run).
    rel_errors : tuple of float
        Relative error per parameter.
    theta : tuple of float
        Final fixed-point estimate (float, normalised units).
    saturations : SaturationCounts
        Saturations over the run (inputs included).
    ok : bool
        ``max_rel_error <= tol``.
    error : str or None
        Why the configuration could not be run.
    """

    label: str
    config: FixedConfig | None
    max_rel_error: float
    rel_errors: tuple[float, ...]
    theta: tuple[float, ...]
    saturations: SaturationCounts
    ok: bool
    error: str | None = None

    @property
    def cost(self) -> tuple[int, int, int]:
        """Sort key of "smallest": (state word, accumulator, input word)."""
        c = self.config
        return (c.word_bits, c.acc_bits, c.input_bits) if c is not None else (99, 99, 99)

    def to_dict(self) -> dict[str, Any]:
        """JSON-able dict (``inf``/``nan`` as ``None``)."""

        def num(x: float) -> float | None:
            return x if math.isfinite(x) else None

        return {
            "label": self.label,
            "word_bits": self.config.word_bits if self.config else None,
            "acc_bits": self.config.acc_bits if self.config else None,
            "input_bits": self.config.input_bits if self.config else None,
            "max_rel_error": num(self.max_rel_error),
            "rel_errors": [num(x) for x in self.rel_errors],
            "theta": [num(x) for x in self.theta],
            "saturations": dict(self.saturations),
            "ok": self.ok,
            "error": self.error,
            "config": self.config.to_dict() if self.config else None,
        }


@dataclass(frozen=True)
class SweepResult:
    """The outcome of :func:`sweep`: one row per configuration and a recommendation.

    ``str(result)`` is a text table; :meth:`to_dict` is JSON-able.

    Attributes
    ----------
    rows : tuple of SweepRow
        In the order run.
    tol : float
        Relative tolerance on every parameter.
    floor : float
        Parameters smaller than this are measured against it instead.
    theta_ref : tuple of float
        The float reference.
    recommended : SweepRow or None
        The smallest configuration (by :attr:`SweepRow.cost`) within ``tol``.
    """

    rows: tuple[SweepRow, ...]
    tol: float
    floor: float
    theta_ref: tuple[float, ...]
    recommended: SweepRow | None

    def to_dict(self) -> dict[str, Any]:
        """JSON-able dict."""
        return {
            "tol": self.tol,
            "floor": self.floor,
            "theta_ref": list(self.theta_ref),
            "recommended": self.recommended.label if self.recommended else None,
            "rows": [r.to_dict() for r in self.rows],
        }

    def __str__(self) -> str:
        head = (
            f"{'config':<16} {'word':>4} {'acc':>4} {'input':>5} {'max rel err':>12}  "
            f"{'ok':<3} saturations"
        )
        lines = [head, "-" * len(head)]
        for r in self.rows:
            c = r.config
            if c is None:
                blank = f"{'':>4} {'':>4} {'':>5}"
                lines.append(f"{r.label:<16} {blank} {'n/a':>12}  {'no':<3} {r.error}")
                continue
            sat = ", ".join(f"{k}={v}" for k, v in r.saturations.nonzero().items()) or "-"
            lines.append(
                f"{r.label:<16} {c.word_bits:>4} {c.acc_bits:>4} {c.input_bits:>5} "
                f"{r.max_rel_error:>12.3e}  {'yes' if r.ok else 'no':<3} {sat}"
            )
        if self.recommended is not None:
            lines.append(
                f"recommended: {self.recommended.label} (max relative error "
                f"{self.recommended.max_rel_error:.3e} <= {self.tol:.3g})"
            )
        else:
            lines.append(f"recommended: none meets the tolerance {self.tol:.3g}")
        return "\n".join(lines)


def sweep(
    Phi: npt.ArrayLike,
    Y: npt.ArrayLike,
    theta_ref: npt.ArrayLike,
    configs: Sequence[FixedConfig] | Mapping[str, FixedConfig] | None = None,
    *,
    lam: float = 1.0,
    alpha: float | npt.ArrayLike = 1e-2,
    trace_max: float | None = None,
    word_bits: Sequence[int] = (16, 24, 32),
    acc_bits: Sequence[int] = (32, 48, 64),
    input_bits: Sequence[int] = (16, 32),
    phi_max: float | Sequence[float] = 1.0,
    y_max: float = 1.0,
    theta_max: float | None = None,
    tol: float = 1e-3,
    floor: float | None = None,
    update: str = "symmetric",
) -> SweepResult:
    r"""Run the fixed-point RLS for several word lengths and compare with a float reference.

    Parameters
    ----------
    Phi : array_like, shape (N, n)
        Normalised regressors (float).
    Y : array_like, shape (N,)
        Normalised targets (float).
    theta_ref : array_like, shape (n,)
        Float reference estimate on the same data (e.g. ``canrls.estimation.rls.RLS`` with the
        same ``lam``, ``alpha``, ``trace_max``).
    configs : sequence or mapping of FixedConfig, optional
        Explicit configurations (a mapping gives them labels). Default: every
        combination of ``word_bits`` x ``acc_bits`` x ``input_bits`` through
        :meth:`FixedConfig.auto`.
    lam, alpha, trace_max : float
        Estimator settings (as for :class:`FixedRLS`).
    word_bits, acc_bits, input_bits : sequences of int
        The grid of word lengths (when ``configs`` is not given).
    phi_max, y_max, theta_max : float
        Ranges for :meth:`FixedConfig.auto`.
    tol : float, default 1e-3
        Tolerance on every parameter's relative error (0.1 %).
    floor : float or None
        A parameter smaller than this is measured against ``floor`` instead of its
        own size (so a zero parameter does not fail everything); ``None``: 1 % of
        the largest :math:`|\theta_{ref}|`.
    update : {"symmetric", "literal", "naive"}

    Returns
    -------
    SweepResult
        Per configuration: relative errors and saturations; the recommended (smallest
        by state word, then accumulator, then input word) configuration within ``tol``.
    """
    Phi_a = np.asarray(Phi, dtype=np.float64)
    Y_a = np.asarray(Y, dtype=np.float64)
    ref = np.asarray(theta_ref, dtype=np.float64)
    if Phi_a.ndim != 2:
        raise EstimatorError(f"sweep Phi must have shape (N, n), got {Phi_a.shape}")
    N, n = Phi_a.shape
    if Y_a.shape != (N,) or ref.shape != (n,):
        raise EstimatorError(
            f"sweep Y must have shape ({N},) and theta_ref ({n},), got {Y_a.shape}, {ref.shape}"
        )
    fl = 0.01 * float(np.max(np.abs(ref))) if floor is None else float(floor)
    if not fl > 0:
        fl = np.finfo(np.float64).tiny
    scale = np.maximum(np.abs(ref), fl)

    todo: list[tuple[str, FixedConfig | None, str | None]] = []
    if configs is None:
        for W in word_bits:
            for A in acc_bits:
                for In in input_bits:
                    label = f"W{W}/A{A}/I{In}"
                    try:
                        cfg = FixedConfig.auto(
                            n, alpha, lam, phi_max=phi_max, y_max=y_max, theta_max=theta_max,
                            word_bits=W, acc_bits=A, input_bits=In, trace_max=trace_max,
                        )  # fmt: skip
                        todo.append((label, cfg, None))
                    except FixedPointError as e:
                        todo.append((label, None, str(e)))
    elif isinstance(configs, Mapping):
        todo = [(str(k), v, None) for k, v in configs.items()]
    else:
        todo = [(c.label, c, None) for c in configs]

    rows: list[SweepRow] = []
    zero = SaturationCounts.of({})
    for label, cfg, err in todo:
        if cfg is not None:
            try:
                est = FixedRLS(cfg, n, lam, alpha, trace_max=trace_max, update=update)
            except FixedPointError as e:
                cfg, err = None, str(e)
        if cfg is None:
            rows.append(SweepRow(label, None, math.inf, (), (), zero, False, err))
            continue
        Pq, Yq, _ = est.quantize_inputs(Phi_a, Y_a)
        est.run(Pq, Yq, record=False)
        th = est.theta_float
        rel = np.abs(th - ref) / scale
        mx = float(rel.max())
        rows.append(
            SweepRow(label, cfg, mx, tuple(float(x) for x in rel), tuple(float(x) for x in th),
                     est.saturations, bool(mx <= tol))
        )  # fmt: skip
    ok = [r for r in rows if r.ok]
    rec = min(ok, key=lambda r: r.cost) if ok else None
    return SweepResult(tuple(rows), float(tol), fl, tuple(float(x) for x in ref), rec)
