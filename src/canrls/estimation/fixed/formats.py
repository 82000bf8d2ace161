"""Q formats, the configuration and the saturation counters of the fixed-point RLS.

:class:`QFormat` is one signed word, :class:`FixedConfig` the word lengths and the
format of every quantity of :class:`canrls.estimation.fixed.estimator.FixedRLS`,
:class:`SaturationCounts` its counters; the rounding of float inputs runs in the C
extension ``canrls._fixed``. The bound behind each automatic format
(:meth:`FixedConfig.auto`) is in docs/fixed_point.md, *The Q formats*.
"""

from __future__ import annotations

import enum
import importlib
import math
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass
from fractions import Fraction
from types import ModuleType
from typing import Any

import numpy as np
import numpy.typing as npt

from canrls.core.checks import is_positive
from canrls.core.errors import EstimatorError, FixedPointError
from canrls.estimation.fixed import layout as kernels
from canrls.estimation.rls import check_lam as _rls_check_lam
from canrls.estimation.rls import check_n as _rls_check_n
from canrls.estimation.rls import check_real as _rls_real
from canrls.estimation.rls import check_ridge as _rls_check_ridge

IntArray = npt.NDArray[np.int64]
FloatArray = npt.NDArray[np.float64]

#: Saturation sites, in counter order.
SITES: tuple[str, ...] = kernels.SITES

#: Quantities that have a Q format in :class:`FixedConfig`, in table order.
QUANTITIES = ("phi", "y", "theta", "P", "K", "eps", "h", "den", "g", "lam")
_MAX_WORD = 32  # products of two words must be exact in int64

#: The word lengths [bits] a :class:`FixedConfig` takes: (least, most) of each.
WORD_LIMITS = {"word_bits": (8, _MAX_WORD), "acc_bits": (16, 64), "input_bits": (2, _MAX_WORD)}


def word_problem(name: str, v: object) -> str | None:
    """Why ``v`` cannot be the word length ``name`` (a key of :data:`WORD_LIMITS`), or
    None: the one check of a word length, for the configuration and the kernel alike."""
    lo, hi = WORD_LIMITS[name]
    if isinstance(v, bool) or not isinstance(v, int | np.integer) or not lo <= v <= hi:
        return f"must be an integer in {lo}..{hi}"
    return None


# ---------------------------------------------------------------- Q formats
def _round_saturate(x: npt.NDArray[np.float64], scale: float, lo: float, hi: float,
                    out: IntArray) -> int:
    """``out = clip(floor(x * scale + 1/2), lo, hi)``; the number clamped, or -1 on a NaN.

    ``scale`` is the exact power of two ``2**frac``, so ``x * scale`` is ``ldexp(x, frac)``
    (one rounding of the exact product, as ldexp does). One pass in C
    (``canrls._fixed.round_saturate``: round half up, then saturate to the word, counted).
    """
    assert C_FIXED is not None, "canrls._fixed is not built (pip install builds it)"
    return int(C_FIXED.round_saturate(np.ascontiguousarray(x, np.float64), scale, lo, hi, out))


def round_inputs(Phi: npt.NDArray[np.float64], Y: npt.NDArray[np.float64],
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


C_FIXED = _c_kernel()


def nan_error(q: QFormat) -> FixedPointError:
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
        nsat = _round_saturate(a.ravel(), *self.rounding(), q.reshape(-1))
        if nsat < 0:
            raise nan_error(self)
        return (q[()] if q.ndim == 0 else q), nsat

    def rounding(self) -> tuple[float, float, float]:
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
        for name in WORD_LIMITS:
            v = getattr(self, name)
            if (why := word_problem(name, v)) is not None:
                raise FixedPointError(f"FixedConfig {name} {why}, got {v!r}")
            object.__setattr__(self, name, int(v))
        for name in QUANTITIES:
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
        r"""Choose every Q format from the ranges of the problem (docs/fixed_point.md,
        *The Q formats*).

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
        n_i = check_n(n)
        ridge = check_ridge(alpha, n_i)
        lam_f = check_lam(lam)
        W = word_bits
        In = W if input_bits is None else input_bits
        pm = np.broadcast_to(np.asarray(phi_max, dtype=np.float64), (n_i,))
        if not (np.all(np.isfinite(pm)) and np.all(pm > 0)):
            raise FixedPointError(f"phi_max must be finite and > 0, got {phi_max!r}")
        ym = float(y_max)
        if not is_positive(ym):
            raise FixedPointError(f"y_max must be finite and > 0, got {y_max!r}")
        tm = 4.0 * ym / float(pm.min()) if theta_max is None else float(theta_max)
        p0_sum = float(np.sum(1.0 / ridge))
        tr = (float(trace_max) if trace_max is not None and math.isfinite(trace_max)
              else p0_sum)
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
        unknown = set(overrides) - set(QUANTITIES)
        if unknown:
            raise FixedPointError(
                f"FixedConfig.auto got unknown override(s) {sorted(unknown)}; "
                f"formats are {list(QUANTITIES)}"
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
        return {name: getattr(self, name) for name in QUANTITIES}

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
            kw = {name: _as_qformat(name, d[name]) for name in QUANTITIES}
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
def check_n(n: object) -> int:
    """The number of parameters, a positive integer."""
    return _rls_check_n(n, "FixedRLS")


def check_real(name: str, value: object) -> float:
    """``value`` as a float, or an :class:`EstimatorError` naming ``name``."""
    return _rls_real(name, value, "FixedRLS")


def check_lam(lam: object) -> float:
    """The forgetting factor (:func:`canrls.core.checks.check_lambda`: ``1/lam`` is a Q1
    word)."""
    return _rls_check_lam(lam, "FixedRLS")


def check_ridge(alpha: object, n: int) -> npt.NDArray[np.float64]:
    """The ridge ``alpha``: a positive scalar or one per parameter, as ``n`` values."""
    return _rls_check_ridge(alpha, n, "FixedRLS")



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
