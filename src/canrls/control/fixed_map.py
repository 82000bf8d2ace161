"""The anticogging map in the target's fixed point: the Python specification and its C.

Two forms, as the user picks (``canrls export-c --feedforward N --feedforward-form``):
the map of :meth:`~canrls.control.feedforward.Feedforward.position_map` as an
``int16_t`` table in Q``frac`` (the largest ``frac`` whose entries fit), read with a
32-bit angle (one revolution, or pitch, is 2**32) between its points (:func:`map_q`,
:func:`map_c`); or its harmonics, each amplitude int32 and phase uint32, the sine from a
Q15 table (:func:`harmonics_q`, :func:`harmonics_c`). Specification and C do the same
operations in the same order; tests/control/test_tune.py holds them to each other bit for bit.
docs/tune.md, *The C function*.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

from canrls.control.tune_limits import MAX_POINTS
from canrls.core.c_escape import c_comment, c_int
from canrls.core.checks import is_positive
from canrls.core.errors import ConfigError

if TYPE_CHECKING:
    import numpy as np
    import numpy.typing as npt

__all__ = ["CFunction", "FixedMap", "fixed_map", "map_q", "map_c", "FixedHarmonics",
           "fixed_harmonics", "sin_q15", "harmonics_q", "harmonics_c", "FixedFriction",
           "fixed_friction", "friction_q", "friction_c", "feedforward_c"]

#: Largest magnitude of a table entry: int16_t.
_WORD = 32767


def _largest_frac(total: float, limit: float) -> int:
    """The largest frac, at most 30 (and no less than -30), with total 2**frac <= limit."""
    frac = 30
    while frac > -30 and total * 2.0**frac > limit:
        frac -= 1
    return frac


def _q(x: float, frac: int) -> int:
    """x 2**frac, rounded half up."""
    # q = floor(x 2^frac + 1/2)
    return int(math.floor(x * 2.0**frac + 0.5))


def _lerp_q16(s0: int, s1: int, f: int) -> int:
    """Linear between two points, f their distance in Q16."""
    # s = s0 + ((s1 - s0) f + 2^15) >> 16   (arithmetic shift: floor)
    return s0 + (((s1 - s0) * f + 0x8000) >> 16)


@dataclass(frozen=True)
class CFunction:
    """One function of ``canrls_feedforward.c``: its declaration in the header (the
    comment that states its formats, its macros) and its definition (tables, helpers)."""

    declaration: str
    definition: str


@dataclass(frozen=True)
class FixedMap:
    """``table[j]`` = round(tau_j 2**frac), the torque at angle ``j 2**32 / N``."""

    table: tuple[int, ...]
    frac: int
    unit: str

    @property
    def flash(self) -> int:
        """Bytes of the table in flash."""
        return 2 * len(self.table)


def fixed_map(torque: Sequence[float] | npt.NDArray[np.float64], unit: str) -> FixedMap:
    """The table of a map: each torque times 2**frac, rounded half up, frac the largest
    (at most 30) with every entry within int16_t."""
    n = len(torque)
    if not 2 <= n <= MAX_POINTS:
        raise ConfigError(f"--feedforward {n}: the points of a map must be 2 to {MAX_POINTS}")
    big = max(abs(float(x)) for x in torque)
    if not math.isfinite(big):
        raise ConfigError("feedforward map: a torque is not a finite number")
    frac = _largest_frac(big, _WORD - 0.5)
    # m_j = floor(tau_j 2^frac + 1/2)
    table = tuple(_q(float(x), frac) for x in torque)
    return FixedMap(table, frac, unit)


def map_q(m: FixedMap, angle: int) -> int:
    """The specification: the torque in Q``frac`` (int32) at ``angle`` (uint32, 2**32 a
    revolution), linear between the table's points and periodic."""
    n = len(m.table)
    # x = angle N (64 bits); j = x >> 32; f = the next 16 bits (Q16)
    x = (angle & 0xFFFFFFFF) * n
    j = x >> 32
    f = (x >> 16) & 0xFFFF
    m0 = m.table[j]
    m1 = m.table[j + 1 if j + 1 < n else 0]
    # out = m0 + ((m1 - m0) f + 2^15) >> 16
    return _lerp_q16(m0, m1, f)


def map_c(m: FixedMap) -> CFunction:
    """The table and ``canrls_ff_map_q``."""
    n = len(m.table)
    head = f"""/* canrls_ff_map_q(angle): the anticogging map (canrls export-c --feedforward {n}):
 * the torque the identified position terms need, in Q{m.frac}
 * ({c_comment(m.unit, "unit")} = value * 2^-{m.frac}), int32; angle: one revolution (linear
 * axis: one pitch) is 2^32, uint32, read ahead by the speed times the loop's delay
 * (feedforward.json "lead"). Linear between the {n} points, periodic; nothing saturates
 * (|result| <= 32767). Divide by Kt for a current reference; add the friction at the
 * speed reference (canrls_ff_friction_q, where the model has friction). */
#define CANRLS_FF_POINTS {n}u
#define CANRLS_FF_FRAC {m.frac}
int32_t canrls_ff_map_q(uint32_t angle);
"""
    rows = []
    for k in range(0, n, 12):
        rows.append("    " + ", ".join(c_int(v, 32, f"map[{k}]") for v in m.table[k:k + 12])
                    + ",")
    body = "\n".join(rows)
    src = f"""
/* tau_j * 2^{m.frac}, rounded half up, at angle j 2^32 / {n} */
static const int16_t canrls_ff_table[{n}] = {{
{body}
}};

int32_t canrls_ff_map_q(uint32_t angle)
{{
    /* x = angle N; j = x >> 32; f = the next 16 bits (Q16) */
    const uint64_t x = (uint64_t)angle * CANRLS_FF_POINTS;
    const uint32_t j = (uint32_t)(x >> 32);
    const int64_t f = (int64_t)((x >> 16) & 0xFFFFu);
    const int32_t m0 = canrls_ff_table[j];
    const int32_t m1 = canrls_ff_table[j + 1u < CANRLS_FF_POINTS ? j + 1u : 0u];
    /* out = m0 + ((m1 - m0) f + 2^15) >> 16 (arithmetic shift of a signed value) */
    return m0 + (int32_t)(((int64_t)(m1 - m0) * f + 0x8000) >> 16);
}}
"""
    return CFunction(head, src)


# ------------------------------------------------------------------------ harmonics
#: Points of the sine table of the harmonics' C (a power of two: the index is the top
#: bits of the phase).
SINE_BITS = 10
_SINE_POINTS = 1 << SINE_BITS
#: sin(2 pi j / 1024) in Q15, rounded half up.
SINE_Q15 = tuple(int(math.floor(32767.0 * math.sin(2.0 * math.pi * j / _SINE_POINTS) + 0.5))
                 for j in range(_SINE_POINTS))


@dataclass(frozen=True)
class FixedHarmonics:
    """``offset + sum_k amp_k sin(order_k angle + phase_k)`` in Q``frac``: amplitudes and
    offset int32, phases uint32 (2**32 a turn)."""

    orders: tuple[int, ...]
    amps: tuple[int, ...]
    phases: tuple[int, ...]
    offset: int
    frac: int
    unit: str


def fixed_harmonics(harmonics: Sequence[tuple[int, float, float]], unit: str
                    ) -> FixedHarmonics:
    """From ``(order, amplitude, phase [rad])`` (order 0: the offset, its amplitude the
    value): frac the largest (at most 30) with ``|offset| + sum |amp|`` within 2**30;
    the amplitudes times 32768/32767, the scale of the sine table."""
    orders = [k for k, _, _ in harmonics if k > 0]
    if not orders and not harmonics:
        raise ConfigError("--feedforward: no harmonic to export")
    if any(k >= 1 << 16 for k in orders):
        raise ConfigError(f"--feedforward: harmonic order {max(orders)} above 65535")
    total = sum(abs(a) for _, a, _ in harmonics) * 32768.0 / 32767.0
    frac = _largest_frac(total, 2.0**30)
    offset = sum(_q(a, frac) for k, a, _ in harmonics if k == 0)
    # the sine table holds 32767 sin: a_k 32768/32767 makes the product >> 15 a_k sin
    terms = [(k, _q(a * 32768.0 / 32767.0, frac),
              int(math.floor(p / (2 * math.pi) * 2.0**32 + 0.5)) % (1 << 32))
             for k, a, p in harmonics if k > 0]
    return FixedHarmonics(tuple(t[0] for t in terms), tuple(t[1] for t in terms),
                          tuple(t[2] for t in terms), offset, frac, unit)


def sin_q15(phase: int) -> int:
    """sin(2 pi phase / 2**32) in Q15: the table, linear between its points."""
    # j = phase >> 22 (the top 10 bits); f = the next 16 bits (Q16)
    j = (phase >> (32 - SINE_BITS)) & (_SINE_POINTS - 1)
    f = (phase >> (16 - SINE_BITS)) & 0xFFFF
    s0 = SINE_Q15[j]
    s1 = SINE_Q15[(j + 1) & (_SINE_POINTS - 1)]
    # s = s0 + ((s1 - s0) f + 2^15) >> 16
    return _lerp_q16(s0, s1, f)


def harmonics_q(h: FixedHarmonics, angle: int) -> int:
    """The specification: the torque in Q``frac`` (int32) at ``angle`` (uint32)."""
    acc = 0
    for k, a, p in zip(h.orders, h.amps, h.phases, strict=True):
        # phi_k = k angle + phase_k (mod 2^32); acc += a_k sin(phi_k) (Q(frac + 15))
        acc += a * sin_q15((k * angle + p) & 0xFFFFFFFF)
    # out = offset + (acc + 2^14) >> 15
    return h.offset + ((acc + 0x4000) >> 15)


def harmonics_c(h: FixedHarmonics) -> CFunction:
    """The sine table and ``canrls_ff_harmonics_q``, one line per harmonic (no loop)."""
    n = len(h.orders)
    head = f"""/* canrls_ff_harmonics_q(angle): the position terms as {n} harmonics (canrls
 * export-c --feedforward-form harmonics): offset + sum_k a_k sin(k angle + phase_k), in
 * Q{h.frac} ({c_comment(h.unit, "unit")} = value * 2^-{h.frac}), int32; angle: one
 * revolution (linear axis: one pitch) is 2^32, uint32, read ahead by the speed times
 * the loop's delay (feedforward.json "lead"). sin from a table of {_SINE_POINTS} points in
 * Q15, linear between them; nothing saturates (|offset| + sum |a_k| <= 2^30). */
#define CANRLS_FF_HARMONICS {n}u
#define CANRLS_FF_FRAC {h.frac}
int32_t canrls_ff_harmonics_q(uint32_t angle);
"""
    rows = "\n".join("    " + ", ".join(str(v) for v in SINE_Q15[k:k + 12]) + ","
                     for k in range(0, _SINE_POINTS, 12))
    terms = "\n".join(
        f"    acc += (int64_t){c_int(a, 32, f'amplitude of order {k}')} * sin_q15("
        f"(uint32_t)({k}u * angle + {p}u));  /* order {k} */"
        for k, a, p in zip(h.orders, h.amps, h.phases, strict=True))
    src = f"""
/* sin(2 pi j / {_SINE_POINTS}) in Q15, rounded half up */
static const int16_t canrls_ff_sine[{_SINE_POINTS}] = {{
{rows}
}};

/* sin(2 pi phase / 2^32) in Q15: j the top {SINE_BITS} bits, f the next 16 (Q16) */
static inline int32_t sin_q15(uint32_t phase)
{{
    const uint32_t j = phase >> {32 - SINE_BITS};
    const int64_t f = (int64_t)((phase >> {16 - SINE_BITS}) & 0xFFFFu);
    const int32_t s0 = canrls_ff_sine[j];
    const int32_t s1 = canrls_ff_sine[(j + 1u) & {_SINE_POINTS - 1}u];
    /* s = s0 + ((s1 - s0) f + 2^15) >> 16 (arithmetic shift of a signed value) */
    return s0 + (int32_t)(((int64_t)(s1 - s0) * f + 0x8000) >> 16);
}}

int32_t canrls_ff_harmonics_q(uint32_t angle)
{{
    int64_t acc = 0;  /* Q{h.frac + 15} */
{terms}
    /* out = offset + (acc + 2^14) >> 15 */
    return {c_int(h.offset, 32, "offset")} + (int32_t)((acc + 0x4000) >> 15);
}}
"""
    return CFunction(head, src)


# ------------------------------------------------------------------------ friction
#: Points of the tanh and exp tables (plus their end point).
FRICTION_BITS = 10
_FP = 1 << FRICTION_BITS
#: tanh(x) on [0, 8] and exp(-x) on [0, 16] in Q15 (rounded half up), 1,025 points each.
TANH_Q15 = tuple(int(math.floor(32767.0 * math.tanh(8.0 * j / _FP) + 0.5))
                 for j in range(_FP + 1))
EXP_Q15 = tuple(int(math.floor(32767.0 * math.exp(-16.0 * j / _FP) + 0.5))
                for j in range(_FP + 1))
#: 8 and 16 in Q16: where the tables end.
_TANH_END = 8 << 16
_EXP_END = 16 << 16


@dataclass(frozen=True)
class FixedFriction:
    """``B w + (Tc + Ts exp(-(w/ws)^2)) tanh(w/e)`` with ``w`` in Q16 (rad/s; m/s):
    ``B`` (Q``frac``+16 per Q16), ``Tc``, ``Ts`` in Q``frac``, and the reciprocals of
    ``e`` and ``ws`` as ``inv * 2**-shift``."""

    B: int
    Tc: int
    Ts: int
    inv_e: int
    shift_e: int
    inv_ws: int
    shift_ws: int
    frac: int
    unit: str


def _reciprocal(x: float, what: str) -> tuple[int, int]:
    """(m, s) with m 2**-s = 1/x, m < 2**31, s the largest up to 62."""
    if not is_positive(x):
        raise ConfigError(f"feedforward: {what} = {x!r}: must be a positive number")
    s = 62
    while s > 0 and math.floor(2.0**s / x + 0.5) >= 2**31:
        s -= 1
    return int(math.floor(2.0**s / x + 0.5)), s


def fixed_friction(B: float, Tc: float, Ts: float, band: float, ws: float,
                   unit: str) -> FixedFriction:
    """From the friction of ``feedforward.json`` ``speed``: frac the largest (at most 30)
    with ``|Tc| + |Ts| + |B| 32768`` (the speed's range) within 2**30."""
    total = abs(Tc) + abs(Ts) + abs(B) * 32768.0
    frac = _largest_frac(total, 2.0**30)
    inv_e, s_e = _reciprocal(band, "coulomb_band")
    inv_ws, s_ws = _reciprocal(ws, "stribeck_speed")
    # tanh and exp from Q15 tables of 32767 x: Tc, Ts times 32768/32767
    return FixedFriction(_q(B, frac), _q(Tc * 32768.0 / 32767.0, frac),
                         _q(Ts * 32768.0 / 32767.0, frac),
                         inv_e, s_e, inv_ws, s_ws, frac, unit)


def _table_q15(table: tuple[int, ...], u: int, end: int) -> int:
    """``table`` (1,025 points over [0, end) in Q16) at ``u`` >= 0, linear between."""
    if u >= end:
        return table[_FP]
    step = end >> FRICTION_BITS  # 2^9 (tanh) or 2^10 (exp)
    sh = step.bit_length() - 1
    j = u >> sh
    f = (u & (step - 1)) << (16 - sh)  # Q16
    return _lerp_q16(table[j], table[j + 1], f)


def friction_q(fr: FixedFriction, w: int) -> int:
    """The specification: the friction torque in Q``frac`` (int32) at ``w`` (int32, Q16)."""
    a = -w if w < 0 else w
    # u = |w| / e, v = |w| / ws (Q16)
    u = (a * fr.inv_e) >> fr.shift_e
    v = min((a * fr.inv_ws) >> fr.shift_ws, _EXP_END)
    # r2 = v^2 (Q16)
    r2 = (v * v) >> 16
    t = _table_q15(TANH_Q15, u, _TANH_END)
    ex = _table_q15(EXP_Q15, r2, _EXP_END)
    # c = Tc + Ts exp(-r2); f = c tanh(u)  (Q frac)
    c = fr.Tc + ((fr.Ts * ex + 0x4000) >> 15)
    f = (c * t + 0x4000) >> 15
    # out = B w + sign(w) f
    return ((fr.B * w + 0x8000) >> 16) + (-f if w < 0 else f)


def friction_c(fr: FixedFriction) -> CFunction:
    """The tables and ``canrls_ff_friction_q``."""
    def rows(t: tuple[int, ...]) -> str:
        return "\n".join("    " + ", ".join(str(v) for v in t[k:k + 12]) + ","
                         for k in range(0, len(t), 12))

    head = f"""/* canrls_ff_friction_q(w): B w + (Tc + Ts exp(-(w/ws)^2)) tanh(w/e) at the speed
 * reference w in Q16 (rad/s; linear axis: m/s), int32, in Q{fr.frac}
 * ({c_comment(fr.unit, "unit")} = value * 2^-{fr.frac}); tanh and exp from Q15 tables of
 * {_FP + 1} points, linear between them. Nothing saturates. */
#define CANRLS_FF_FRICTION_FRAC {fr.frac}
int32_t canrls_ff_friction_q(int32_t w);
"""
    tanh_sh = (_TANH_END >> FRICTION_BITS).bit_length() - 1  # 9: 2^19 / 1024
    exp_sh = (_EXP_END >> FRICTION_BITS).bit_length() - 1  # 10
    src = f"""
/* tanh(8 j / {_FP}) and exp(-16 j / {_FP}) in Q15, rounded half up */
static const int16_t canrls_ff_tanh[{_FP + 1}] = {{
{rows(TANH_Q15)}
}};
static const int16_t canrls_ff_exp[{_FP + 1}] = {{
{rows(EXP_Q15)}
}};

/* a table of {_FP + 1} points over [0, end) at u >= 0 (Q16), linear between them */
static int32_t table_q15(const int16_t *t, int64_t u, int64_t end, int sh)
{{
    if (u >= end)
        return t[{_FP}];
    const int64_t j = u >> sh;
    const int64_t f = (u & ((1 << sh) - 1)) << (16 - sh);
    return t[j] + (int32_t)(((int64_t)(t[j + 1] - t[j]) * f + 0x8000) >> 16);
}}

int32_t canrls_ff_friction_q(int32_t w)
{{
    const int64_t b = {c_int(fr.B, 32, "B")}, tc = {c_int(fr.Tc, 32, "Tc")};
    const int64_t ts = {c_int(fr.Ts, 32, "Ts")};
    const int64_t a = w < 0 ? -(int64_t)w : (int64_t)w;
    /* u = |w| / e, v = |w| / ws (Q16) */
    const int64_t u = (a * {c_int(fr.inv_e, 64, "1/e")}) >> {fr.shift_e};
    int64_t v = (a * {c_int(fr.inv_ws, 64, "1/ws")}) >> {fr.shift_ws};
    if (v > {_EXP_END})
        v = {_EXP_END};
    /* r2 = v^2 (Q16) */
    const int64_t r2 = (v * v) >> 16;
    const int64_t t = table_q15(canrls_ff_tanh, u, {_TANH_END}, {tanh_sh});
    const int64_t ex = table_q15(canrls_ff_exp, r2, {_EXP_END}, {exp_sh});
    /* c = Tc + Ts exp(-r2); f = c tanh(u) (Q{fr.frac}) */
    const int64_t c = tc + ((ts * ex + 0x4000) >> 15);
    const int64_t f = (c * t + 0x4000) >> 15;
    /* out = B w + sign(w) f */
    return (int32_t)((b * w + 0x8000) >> 16) + (int32_t)(w < 0 ? -f : f);
}}
"""
    return CFunction(head, src)


# ------------------------------------------------------------------------ the files
def feedforward_c(parts: Sequence[CFunction], source: str) -> tuple[str, str]:
    """``canrls_feedforward.h`` and ``.c`` of ``parts`` (the map or its harmonics, the
    friction): one include guard around every declaration, then the definitions."""
    decls = "\n".join(p.declaration for p in parts)
    head = f"""/* canrls_feedforward.h -- the feedforward of {c_comment(source, "source")}
 * (canrls export-c --feedforward; canrls.control.fixed_map is its specification).
 */
#ifndef CANRLS_FEEDFORWARD_H
#define CANRLS_FEEDFORWARD_H

#include <stdint.h>

{decls}
#endif
"""
    src = ("/* canrls_feedforward.c -- see canrls_feedforward.h (generated by canrls "
           "export-c). */\n#include \"canrls_feedforward.h\"\n"
           + "".join(p.definition for p in parts))
    return head, src
