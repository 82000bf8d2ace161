r"""The integer arithmetic of the target's per-sample path: rounding shifts, the
function tables, the float32 bits of a scaled integer.

Every function here is the specification of a C function of the same name in
``src/canrls/c/firmware/canrls_target.c`` (prefix ``cr_``): the same operations on the same
integers. Python's ``>>`` is an arithmetic (flooring) shift, as the C requires of its
compiler (a compile-time check refuses one without it), and Python integers do not
overflow; the C holds every value in ``int64_t`` or splits a product where it would
not fit (each such place is named below with its bound).

* :func:`rsh` -- rounding right shift, round half up, :math:`\lfloor (x + 2^{s-1}) /
  2^s \rfloor`;
* :func:`mul_rsh` -- :math:`\mathrm{rsh}(x m, s)` of a 61-bit ``x`` and a 32-bit ``m``
  (a 93-bit product: the C splits ``x`` at bit 31), ``s >= 31``;
* :func:`clog2` -- :math:`\lceil\log_2 n\rceil`;
* :func:`table_eval` -- a piecewise cubic of :mod:`canrls.firmware.tables` at a Q32
  argument: tanh, the quarter wave of sine, :math:`2^{-x}`;
* :func:`tanh_q24`, :func:`exp_neg_q24`, :func:`sincos_q64` -- the functions the effect
  columns need, from those tables;
* :func:`float_fixed` -- an IEEE-754 binary32 or binary64 field's value times
  :math:`2^F`, rounded half away from zero, by integer operations only (None: NaN or
  infinity);
* :func:`f32_bits` -- the IEEE-754 binary32 nearest to :math:`v\,2^E`, round half to
  even, saturated at the DBC's :data:`F32_SAT`, by integer operations only.
"""

from __future__ import annotations

from fractions import Fraction

from canrls.firmware import tables

__all__ = ["ONE_Q30", "MASK32", "MASK64", "F32_SAT", "F32_NAN", "rsh", "mul_rsh", "clog2", "isqrt",
           "dyadic", "floor_scaled", "ceil_scaled", "sat", "scale_p64", "table_eval", "tanh_q24",
           "exp2_neg_q24", "exp_neg_q24", "sincos_q64", "f32_bits", "float_fixed", "LOG2E_Q30"]

#: 1.0 in Q30
ONE_Q30 = 1 << 30
MASK32 = (1 << 32) - 1
MASK64 = (1 << 64) - 1
#: log2(e) in Q30, rounded: 1.4426950408889634 * 2^30
LOG2E_Q30 = 1549082005
#: float32 of 3.4e38, the bound of the DBC's float signals (saturation of the frames)
F32_SAT = 0x7F7FC99E
_I62 = 1 << 62
#: a quiet NaN (a value not known)
F32_NAN = 0x7FC00000


def rsh(x: int, s: int) -> int:
    """``x`` brought ``s`` bits coarser, round half up: ``(x + 2^(s-1)) >> s``
    (``s <= 0``: ``x << -s``, exact)."""
    if s <= 0:
        return x << -s
    return (x + (1 << (s - 1))) >> s


def mul_rsh(x: int, m: int, s: int) -> int:
    """``rsh(x m, s)`` for ``|x| < 2^61``, ``|m| < 2^31``, ``s >= 0``, saturated at
    +-2^62 where it is larger.

    The C (``cr_mul_rsh``) splits ``x = h 2^31 + l`` (``0 <= l < 2^31``, ``|h| < 2^30``):
    for ``s >= 32``, ``x m + 2^(s-1) = (h m + 2^(s-32)) 2^31 + l m``, so the result is
    ``(h m + 2^(s-32) + (l m >> 31)) >> (s - 31)`` exactly (the low part cannot carry
    into a bit the final shift keeps); ``s = 31``: ``h m + ((l m + 2^30) >> 31)``;
    ``s >= 93``: 0. Every term fits ``int64`` and the result is below 2^61. ``s < 31``
    (a column whose filter state resolves it no finer than its word): ``h m 2^(31-s) +
    rsh(l m, s)``, and +-2^62 as soon as ``|h m| >= 2^(31+s)`` (the value is then far
    beyond any word: only its sign and size matter, to the rescale and the clamp).
    """
    if s >= 31:
        return rsh(x * m, s)
    h, lo = x >> 31, x & 0x7FFFFFFF
    a = h * m
    if abs(a) >= 1 << (31 + s):
        return _I62 if a >= 0 else -_I62
    return sat((a << (31 - s)) + rsh(lo * m, s), -_I62, _I62)


def clog2(n: int) -> int:
    """Smallest ``k`` with ``n <= 2^k`` (``n >= 1``)."""
    return (n - 1).bit_length()


def isqrt(n: int) -> int:
    """``floor(sqrt(n))`` (``n >= 0``); the C takes it bit by bit, 32 iterations."""
    r = 0
    bit = 1 << 62
    while bit > n:
        bit >>= 2
    while bit:
        if n >= r + bit:
            n -= r + bit
            r = (r >> 1) + bit
        else:
            r >>= 1
        bit >>= 2
    return r


def dyadic(x: Fraction) -> tuple[int, int]:
    """``(m, e)`` with ``x = m 2^e`` exactly (a ridge weight: a double, so dyadic)."""
    e = 0
    while x.denominator != 1:
        x *= 2
        e -= 1
    m = x.numerator
    while m and m % 2 == 0 and m >> 53:
        m //= 2
        e += 1
    return m, e


def floor_scaled(m: int, e: int) -> int:
    """``floor(m 2^e)`` of ``m >= 0``, saturated at 2^62 (the C's ``cr_floor_scaled``)."""
    if e >= 0:
        return _I62 if e >= 62 or m >= (_I62 >> e) else m << e
    return m >> -e if -e < 64 else 0


def ceil_scaled(m: int, e: int) -> int:
    """``ceil(m 2^e)`` of ``m >= 0``, saturated at 2^62."""
    if e >= 0:
        return floor_scaled(m, e)
    return (m + (1 << -e) - 1) >> -e if -e < 64 else (1 if m else 0)


def sat(x: int, lo: int, hi: int) -> int:
    """``x`` clamped to ``[lo, hi]``."""
    return lo if x < lo else hi if x > hi else x


def scale_p64(word: int, frac: int, s: int, lo: int, hi: int) -> tuple[int, int, bool]:
    """An element of the kernel's 64-bit ``P~``, ``V = word 2^32 + frac``, times ``2^s``
    (``s >= 0``, exact) or ``rsh(V, -s)`` (``s < 0``), back into the word ``V`` rounded
    half up (``rsh(V, 32)``) and the fraction below it; saturated where the word leaves
    ``[lo, hi]`` (the word ``lo`` or ``hi`` with the fraction ``-2^31`` or ``2^31 - 1``).
    Returns the word, the fraction and whether it saturated."""
    v = (word << 32) + frac
    v = rsh(v, -s) if s < 0 else v << s
    vlo, vhi = (lo << 32) - (1 << 31), (hi << 32) + (1 << 31) - 1
    clamped = not vlo <= v <= vhi
    v = sat(v, vlo, vhi)
    w = (v + (1 << 31)) >> 32
    return w, v - (w << 32), clamped


def table_eval(table: tuple[tuple[int, int, int, int], ...], u: int) -> int:
    r"""The piecewise cubic ``table`` at ``u / 2^32`` (``0 <= u < 2^32``), Q30.

    With ``S = 2^k`` segments: the segment ``i = u >> (32 - k)``, the position in it
    ``t = ((u << k) mod 2^32) >> 1`` (Q31, ``0 <= t < 2^31``), and Horner's rule with
    one rounding per step:

    .. math:: p = c_3;\quad p = c_i + \mathrm{rsh}(p\,t, 31),\ i = 2, 1, 0
    """
    k = len(table).bit_length() - 1
    c0, c1, c2, c3 = table[u >> (32 - k)]
    # t = position in the segment, Q31
    t = ((u << k) & MASK32) >> 1
    # p = c3 ; p = c_i + rsh(p t, 31)
    p = c3
    p = c2 + rsh(p * t, 31)
    p = c1 + rsh(p * t, 31)
    p = c0 + rsh(p * t, 31)
    return p


def tanh_q24(z: int) -> int:
    """``tanh(z 2^-24)`` in Q30 (``z`` an int32, Q24): odd; ``1`` from ``|z| >= 8``
    (``tanh(8) = 1 - 2.3e-7``), the table :data:`~canrls.firmware.tables.TANH` below."""
    a = -z if z < 0 else z
    # |z| >= 8: 1.0 ; else the table at |z| / 8 (Q24 -> Q32 of z/8: << 5)
    v = ONE_Q30 if a >= (8 << 24) else table_eval(tables.TANH, a << 5)
    return -v if z < 0 else v


def exp2_neg_q24(x: int) -> int:
    """``2^(-x 2^-24)`` in Q30 for ``x >= 0`` (Q24): the integer part a shift, the
    fraction from :data:`~canrls.firmware.tables.EXP2`; 0 from ``x >= 31``."""
    n = x >> 24
    if n >= 31:
        return 0
    # 2^-f from the table (f Q24 -> Q32: << 8), then >> n, rounded
    return rsh(table_eval(tables.EXP2, (x & ((1 << 24) - 1)) << 8), n)


def exp_neg_q24(x: int) -> int:
    """``exp(-x 2^-24)`` in Q30 for ``x >= 0`` (Q24): ``2^(-x log2 e)``."""
    # y = x log2(e), Q24
    return exp2_neg_q24(rsh(x * LOG2E_Q30, 30))


def sincos_q64(phase: int) -> tuple[int, int]:
    r"""``(sin, cos)`` of ``2 pi phase / 2^64`` (``0 <= phase < 2^64``, turns in Q64),
    Q30, from the quarter wave :data:`~canrls.firmware.tables.SIN`.

    The quadrant ``q`` is the top two bits, ``x`` the next 32 (Q32 of the quadrant):
    ``sin = S(x), S(~x), -S(x), -S(~x)`` for ``q = 0, 1, 2, 3`` with ``S(x) =
    sin(pi x / 2)`` and ``~x = 2^32 - 1 - x`` (``1 - x`` less 2^-32); the cosine is the
    sine a quarter turn on.
    """

    def quarter(q: int, x: int) -> int:
        v = table_eval(tables.SIN, x if q & 1 == 0 else MASK32 ^ x)
        return v if q < 2 else -v

    q = phase >> 62
    x = (phase >> 30) & MASK32
    return quarter(q, x), quarter((q + 1) & 3, x)


def f32_bits(v: int, e: int) -> int:
    """The binary32 bits of ``v 2^e`` rounded to nearest, ties to even (subnormals
    included; 0 for 0), saturated to +-:data:`F32_SAT` (the DBC's +-3.4e38)."""
    if v == 0:
        return 0
    sign = 0x80000000 if v < 0 else 0
    a = -v if v < 0 else v
    # quantum of the result: 2^q with q = exponent - 23, at least 2^-149
    q = max(a.bit_length() - 1 + e - 23, -149)
    s = q - e
    if s > 0:
        # round half to even at bit s
        m = a >> s
        rem = a - (m << s)
        half = 1 << (s - 1)
        if rem > half or (rem == half and m & 1):
            m += 1
    else:
        m = a << -s
    if m >> 24:  # the rounding carried into a new bit
        m >>= 1
        q += 1
    if m >> 23:
        biased = q + 150
        bits = (biased << 23) | (m & 0x7FFFFF) if biased < 255 else F32_SAT + 1
    else:  # subnormal
        bits = m
    if bits > F32_SAT:
        bits = F32_SAT
    return sign | bits


def float_fixed(bits: int, width: int, frac: int) -> int | None:
    """The value of the IEEE-754 field ``bits`` (``width`` 32 or 64) times ``2^frac``,
    rounded half away from zero; None for NaN and infinity (C ``cr_float``)."""
    mb = 23 if width == 32 else 52          # stored mantissa bits
    emax = (1 << (width - 1 - mb)) - 1       # 255, 2047: NaN and infinity
    e = (bits >> mb) & emax
    if e == emax:
        return None
    # v 2^frac = M 2^s: M the mantissa with its hidden bit, s = max(e, 1) - bias - mb + frac
    M = (bits & ((1 << mb) - 1)) | ((1 << mb) if e else 0)
    s = max(e, 1) - (emax >> 1) - mb + frac
    # |raw| = M 2^s, or rsh(M, -s) (round half up of the magnitude)
    mag = M << s if s >= 0 else (M + (1 << (-s - 1))) >> -s
    return -mag if bits >> (width - 1) & 1 else mag
