r"""The integer constants of the whole estimator on the target, for one model and DBC.

:func:`build` takes what the service runs after its calibration (the model with the
frozen exponents, the column energies, the columns still pending, the DBC mapping, the
estimator settings and the control period) and turns every number the per-sample path
needs into integers, once, here: the bit fields of the mapped signals, the raw ranges of
strict decoding, the state-variable filter's coefficients, the multipliers that fold a
signal's scale, offset and SI factor into the normalised Q format, the selection's
thresholds, the kernel's plan and prior. :class:`~canrls.firmware.spec.TargetEstimator`
(the specification) and the generated C (``canrls export-c``) run on these integers
and nothing else: neither holds a float.

What the target cannot do is refused here, with the reason: a user term (an expression
of the signals has no integer form here), a 16-bit float signal or counter, an integer
field wider than 32 bits,
a linear axis whose position wraps at other than a whole number of pitches.

The numbers (``docs/target.md`` has the same with the reasons):

* a signal ``x`` [SI] of raw field ``r``: ``x = k (r + o)`` with ``k`` = DBC scale x
  SI factor and ``o`` = offset / scale (raw units);
* a filter's state holds ``X = F[u] 2^FX`` (and ``sF[u] T 2^FX``, ``T`` the period),
  ``u`` its integer input: the raw field, or a Q30 value of tanh, the Stribeck shape,
  sin or cos; ``FX`` as large as keeps ``|X| < 2^60``;
* a column ``phi_j = rsh((X + O_j) m_j, sh_j)`` in the ``phi`` format, with ``m_j
  2^-sh_j = K_j 2^(f_phi - s_j - FX)`` (``K_j`` the SI value of one input unit, over
  ``T`` for a derivative; ``O_j = o 2^FX`` for a value column of a raw field); the output
  ``y`` likewise; a rescale adds to ``sh_j`` what it adds to ``s_j``.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from fractions import Fraction
from typing import Any

import numpy as np

from canrls.can.codec import SignalCodec
from canrls.can.protocol import Protocol
from canrls.core.errors import ConfigError
from canrls.core.samples import ROLES
from canrls.estimation.equation import Equation
from canrls.estimation.model import Model
from canrls.estimation.pipeline import EquationEstimator, Pipeline
from canrls.estimation.settings import EstimatorSettings
from canrls.estimation.svf import SVF, gain_bounds
from canrls.firmware.qmath import MASK64, clog2, float_fixed

__all__ = ["SRC_RAW", "SRC_TANH", "SRC_STRIBECK", "SRC_SIN", "SRC_COS", "SRC_CONST",
           "SOURCE_NAMES", "Field", "Message", "Filter", "OutFrame", "OUT_FRAMES", "out_frames",
           "Column", "Selection", "EquationSpec", "TargetModel", "build", "FX_MAX", "X_BITS",
           "BOUNDED", "TargetError"]

#: filter inputs (sources)
SRC_RAW, SRC_TANH, SRC_STRIBECK, SRC_SIN, SRC_COS, SRC_CONST = range(6)
SOURCE_NAMES = ("raw", "tanh", "stribeck", "sin", "cos", "const")
#: most fraction bits of a filter's state below its input's unit
FX_MAX = 40
#: the filter states stay below 2^X_BITS in magnitude (the C splits them at bit 31)
X_BITS = 60
#: the bound of a raw input of the filter bank: every raw value is an int32 (a DBC's
#: declared range only rejects frames, docs/target.md)
RAW_BOUND = 1 << 31
#: the constant column's state: 1.0 in Q30 with this many bits more (2^59)
CONST_FX = 29
#: the inputs bounded by 1 (Q30): their filters keep 32-bit states (``Filter.narrow``)
BOUNDED = (SRC_TANH, SRC_STRIBECK, SRC_SIN, SRC_COS)
#: a narrow state's headroom below 2^31 beyond the filter's gain (the rounding's drift)
NARROW_MARGIN = 1 << 24
#: Q24: the format of the arguments of tanh and of the Stribeck exponential
Z_FRAC = 24
#: the speed of the selection: raw 2^W_FRAC
W_FRAC = 16
#: roles in the order of the C's role index
ROLE_INDEX = {r: i for i, r in enumerate(ROLES)}


class TargetError(ConfigError):
    """The model or the DBC asks for something the target's integer path does not do."""


# ----------------------------------------------------------------- frames in

#: four Q30 coefficients (a 2 x 2 matrix by rows, or a hold's G0 and G1)
Quad = tuple[int, int, int, int]

@dataclass(frozen=True)
class Field:
    """A signal's bit field in its message (classic CAN, at most 8 bytes): the payload
    read as one 64-bit word, little endian (Intel) or big endian (Motorola: byte 0 the
    most significant), the field is ``length`` bits from bit ``shift`` of that word,
    two's complement when ``signed``; strict decoding accepts the raw values ``lo ..
    hi`` (the DBC's [minimum, maximum]). An unsigned 32-bit field is held less ``bias =
    2^31`` (``biased``), so that every raw value is an ``int32``: ``lo``, ``hi`` and
    what :meth:`extract` returns are then ``raw - 2^31``, and the signal's offset takes
    the ``2^31`` back. A float32 or float64 field (``is_float``) is held in fixed point,
    ``raw = round(v 2^frac)`` of its value ``v`` (:func:`~canrls.firmware.qmath.float_fixed`),
    and :meth:`extract` returns None for NaN and infinity."""

    msg: int
    big_endian: bool
    shift: int
    length: int
    signed: bool
    lo: int
    hi: int
    biased: bool = False
    is_float: bool = False
    frac: int = 0

    @property
    def bias(self) -> int:
        return 1 << 31 if self.biased else 0

    def extract(self, data: bytes) -> int | None:
        """The raw value of the field in ``data`` (sign-extended, less the bias; a float
        field's in fixed point, None for NaN and infinity)."""
        # the payload as a 64-bit word (bytes after the frame's end are 0)
        word = int.from_bytes(bytes(data).ljust(8, b"\0"), "big" if self.big_endian else "little")
        # raw = (word >> shift) mod 2^length
        acc = (word >> self.shift) & ((1 << self.length) - 1)
        if self.is_float:
            return float_fixed(acc, self.length, self.frac)
        if self.signed and acc >> (self.length - 1):
            acc -= 1 << self.length
        return acc - self.bias


@dataclass(frozen=True)
class Message:
    """A mapped feedback message: ``id`` (29 bits when ``extended``), its length, whether
    byte 0 is the E2E CRC-8 and the alive counter's field (None: none)."""

    name: str
    id: int
    extended: bool
    dlc: int
    crc: bool
    counter: Field | None


# ------------------------------------------------------------------ the filter
@dataclass(frozen=True)
class Filter:
    """One state-variable filter of the bank: its input and hold.

    ``kind`` (``SRC_*``) and ``role`` say what the input ``u`` is (the raw field of
    ``role``; a Q30 function of it; ``order`` the harmonic of sin and cos), ``hold`` 0
    straight-line, 1 zero-order; ``fx`` the fraction bits of the state below the input's
    unit."""

    kind: int
    role: str
    order: int
    hold: int
    fx: int

    @property
    def narrow(self) -> bool:
        """32-bit states: an input bounded by 1 (Q30) with no fraction bit more (``fx``
        0), each row's result saturated to int32 (the C: ``cr_narrow``)."""
        return self.kind in BOUNDED and self.fx == 0

    @property
    def label(self) -> str:
        arg = f"{self.role}" if self.kind in (SRC_RAW, SRC_TANH, SRC_STRIBECK) else \
            f"{self.order} position" if self.kind in (SRC_SIN, SRC_COS) else "1"
        return f"{SOURCE_NAMES[self.kind]}({arg}), {'zoh' if self.hold else 'foh'}"


@dataclass(frozen=True)
class Column:
    """A regressor column (or the output) from the filter bank: ``phi = rsh((X + offset)
    m, sh)`` where ``X`` is state 1 (value, ``F``) or 2 (``derivative``: ``sF T``) of
    filter ``filter``. ``adaptive``: its exponent follows the data (a rescale when a used
    row exceeds full scale); ``pending``: the calibration window showed nothing of it."""

    name: str
    filter: int
    derivative: bool
    offset: int
    m: int
    sh: int
    adaptive: bool
    pending: bool
    exponent: int


@dataclass(frozen=True)
class Selection:
    """Which samples update an equation's estimator (``canrls.estimation.selection``).

    ``warmup`` samples after a restart or a speed out of limits are not used; a speed
    ``W = raw 2^W_FRAC + w_offset`` with ``|W| < min_w`` or ``|W| > max_w`` (``max_w <
    0``: no upper limit) is out of limits, and so is a sign change since the last sample
    when ``cross``."""

    warmup: int
    min_w: int
    max_w: int
    cross: bool


@dataclass(frozen=True)
class EquationSpec:
    """The integers of one equation: columns, output, selection, the kernel's plan and
    prior, and what a rescale needs."""

    name: str
    index: int
    columns: tuple[Column, ...]
    output: Column
    selection: Selection
    plan: dict[str, int]
    p0: tuple[int, ...]
    e0: int
    f_phi: int
    f_y: int
    f_theta: int
    f_eps: int
    theta_lo: int
    theta_hi: int
    P_lo: int
    P_hi: int
    phi_hi: int
    lam: float
    #: the FixedRLS the specification runs (plan and prior as above)
    config: Any
    ridge: tuple[Fraction, ...]
    #: the trace bound follows the prior (``trace_max`` not configured)
    trace_follows: bool
    #: per column: floor(lambda 2^(f_P - trace_ps) / alpha_j), the terms of the bound
    trace_terms: tuple[int, ...]
    trace_cap: int
    #: the weakest prior of the start (a column that grew takes it) and its trace term
    prior_floor: Fraction
    floor_term: int
    #: the prior of a pending column at its first value (alpha 2^-8) and its trace term
    first_ridge: Fraction
    first_term: int
    #: |theta_j| 2^(d_j - d_y) above this (theta words) moves the output's exponent
    theta_half: int
    #: the ResidualRms: r <- r + (eps^2 - r) >> rms_shift
    rms_shift: int
    #: a parameter's FixedValue is theta 2^(s_y - s_j - f_theta): these exponents
    exponents: tuple[int, ...]
    parameters: tuple[Any, ...]

    @property
    def n(self) -> int:
        return len(self.columns)


#: the estimator frames of canrls' DBC the target sends, and their signals
OUT_FRAMES: dict[str, tuple[str, ...]] = {
    "RlsEstimate": ("Index", "Counter", "Valid", "FixedValue"),
    "RlsParamInfo": ("Index", "Count", "EffectId", "Component", "Order", "Equation"),
    "RlsStatus": ("ResidualRms", "UpdateCount"),
    "RlsHealth": ("Windup", "LowExcitation", "Saturation", "FrameLoss", "Frozen", "Counter",
                  "ActiveEffects", "Divergence"),
}


@dataclass(frozen=True)
class OutFrame:
    """An estimator frame of canrls' DBC: its ID, length and each signal's ``(start bit,
    length)`` (little endian: bit ``b`` is bit ``b mod 8`` of byte ``b div 8``)."""

    name: str
    id: int
    dlc: int
    fields: dict[str, tuple[int, int]]

    def pack(self, values: Mapping[str, int]) -> bytes:
        """The payload with ``values`` (raw integers; float32 fields as their bits)."""
        word = 0
        for name, v in values.items():
            start, length = self.fields[name]
            # word |= (v mod 2^length) << start
            word |= (v & ((1 << length) - 1)) << start
        return word.to_bytes(self.dlc, "little")


def out_frames(dbc: Any = None) -> dict[str, OutFrame]:
    """The layout of the estimator frames in canrls' DBC (default: the shipped one; read
    once, :func:`canrls.can.estimator_frames.database`)."""
    from canrls.can.estimator_frames import database

    db = database(dbc)
    out = {}
    for name, sigs in OUT_FRAMES.items():
        msg = db.get_message_by_name(name)
        fields = {}
        for sname in sigs:
            sg = msg.get_signal_by_name(sname)
            if sg.byte_order != "little_endian" or sg.start + sg.length > 8 * msg.length:
                raise TargetError(f"{name}.{sname}: the target packs little-endian signals "
                                  f"of canrls' DBC only")
            fields[sname] = (int(sg.start), int(sg.length))
        if msg.is_extended_frame or msg.length != 8:
            raise TargetError(f"{name}: the target sends classic 8-byte frames")
        out[name] = OutFrame(name, int(msg.frame_id), int(msg.length), fields)
    return out


@dataclass(frozen=True)
class TargetModel:
    """Every integer of the per-sample path of one model on one DBC (:func:`build`)."""

    source: str
    dt: float
    tick_s: float
    dt_ticks: int
    gap_ticks: int
    tol_ticks: int
    messages: tuple[Message, ...]
    roles: dict[str, Field]
    #: per role: (m, b, shift) of the Q24 arguments (tanh: z = w / band, stribeck:
    #: r = w / ws): z = rsh(raw m + b, shift)
    tanh_arg: tuple[int, int, int] | None
    stribeck_arg: tuple[int, int, int] | None
    #: the phase of the periodic columns: raw PM + PO mod 2^64 (turns in Q64)
    phase: tuple[int, int] | None
    #: the speed of the selection: W = raw 2^W_FRAC + w_offset
    w_offset: int
    #: the filter's coefficients, Q30: A (2 x 2) and per hold (foh, zoh) G0, G1 (2 each)
    A: Quad
    G: tuple[Quad, Quad]
    filters: tuple[Filter, ...]
    equations: tuple[EquationSpec, ...]
    #: the parameter frames: samples per publication
    publish_every: int
    active_effects: int
    #: RlsParamInfo of every parameter (index order): (effect id, component, order, equation)
    param_info: tuple[tuple[int, int, int, int], ...]
    #: the estimator frames (None: left out, ``canrls export-c --frames none``)
    out: dict[str, OutFrame] | None
    model: Model = field(repr=False, compare=False)
    protocol: Protocol = field(repr=False, compare=False)

    @property
    def n_params(self) -> int:
        return sum(e.n for e in self.equations)

    @property
    def match_counters(self) -> bool:
        """Whether the frames of one period are paired by their alive counters: every
        message has one, all of one width."""
        widths = {None if m.counter is None else m.counter.length for m in self.messages}
        return None not in widths and len(widths) == 1


# ------------------------------------------------------------------ building
def _mantissa(x: Fraction) -> tuple[int, int]:
    """``(m, sh)`` with ``m 2^-sh`` the nearest to ``x`` of 31 significant bits
    (``2^30 <= |m| < 2^31``)."""
    if x == 0:
        raise TargetError("a multiplier of the integer path is 0")
    a = abs(x)
    sh = 30 - (math.floor(math.log2(a.numerator)) - math.floor(math.log2(a.denominator)))
    # adjust for the floor of the two logarithms
    while a * 2 ** sh >= 2 ** 31:
        sh -= 1
    while a * 2 ** sh < 2 ** 30:
        sh += 1
    m = math.floor(a * 2 ** sh + Fraction(1, 2))
    if m >= 2 ** 31:
        m >>= 1
        sh -= 1
    return (m if x > 0 else -m), sh


#: a float field's fixed point holds its bound in at most this many bits (headroom for
#: the rounding and the filter); the bound of a float field whose DBC states no range
FLOAT_BITS = 30
FLOAT_BOUND = 1 << 15


def _float_range(codec: SignalCodec, strict: bool) -> tuple[int, int, int]:
    """``(frac, lo, hi)`` of a float field: ``frac`` the most fraction bits that hold the
    largest value its DBC range allows (:data:`FLOAT_BOUND` without one) in
    :data:`FLOAT_BITS` bits, ``lo .. hi`` that range in fixed point (strict) or all of
    ``int32``."""
    scale = Fraction(float(codec.scale))
    off = Fraction(float(codec.offset))
    ends = [(Fraction(float(x)) - off) / scale for x in (codec.minimum, codec.maximum)
            if x is not None]
    bound = max((abs(x) for x in ends), default=Fraction(FLOAT_BOUND)) or Fraction(1)
    # the largest frac with bound 2^frac <= 2^FLOAT_BITS
    frac = FLOAT_BITS - math.ceil(math.log2(bound))
    while bound * 2 ** frac > 2 ** FLOAT_BITS:
        frac -= 1
    while bound * 2 ** (frac + 1) <= 2 ** FLOAT_BITS:
        frac += 1
    frac = max(-60, min(60, frac))
    lo, hi = -(1 << 31) + 1, (1 << 31) - 1
    if strict:
        # the DBC's [minimum, maximum] in raw float units, in fixed point
        a = (Fraction(float(codec.minimum)) - off) / scale if codec.minimum is not None else None
        b = (Fraction(float(codec.maximum)) - off) / scale if codec.maximum is not None else None
        if scale < 0:
            a, b = b, a
        if a is not None:
            lo = max(lo, math.ceil(a * 2 ** frac))
        if b is not None:
            hi = min(hi, math.floor(b * 2 ** frac))
    return frac, lo, hi


def _shift(codec: SignalCodec, where: str) -> int:
    """The field's lowest bit in the payload's 64-bit word of its byte order."""
    if max(codec.byte_index) >= 8:
        raise TargetError(f"{where}: beyond the 8 bytes of a classic CAN frame")
    if codec.byte_order == "little_endian":
        # the field's first bit is bit 8 (first byte) + shift of the little-endian word
        return codec.byte_index[0] * 8 + codec.shift
    # its last bit in the sequential numbering (byte 0's bit 7 first), last = 8 (its
    # last byte) + 7 - shift, is bit 63 - last of the big-endian word
    return 63 - (8 * codec.byte_index[0] + 7 - codec.shift)


def _field(codec: SignalCodec, msg: int, where: str, strict: bool = True,
           counter: bool = False) -> Field:
    big = codec.byte_order != "little_endian"
    if codec.is_float:
        if codec.length == 16 or counter:
            raise TargetError(f"{where} is a {codec.length}-bit float"
                              f"{' alive counter' if counter else ''}: the target decodes "
                              f"float32 and float64 signals and integer counters")
        frac, lo, hi = _float_range(codec, strict)
        if lo > hi:
            raise TargetError(f"{where}: no value decodes inside its DBC range")
        return Field(msg, big, _shift(codec, where), codec.length, True, lo, hi,
                     is_float=True, frac=frac)
    if codec.length > 32:
        raise TargetError(f"{where} has {codec.length} bits: the target decodes integer "
                          f"fields of at most 32 bits")
    lo, hi = (codec.enc_lo, codec.enc_hi) if strict else (codec.raw_min, codec.raw_max)
    if lo > hi:
        raise TargetError(f"{where}: no raw value decodes inside its DBC range")
    biased = not codec.is_signed and codec.length == 32 and hi > (1 << 31) - 1
    if biased:
        lo, hi = lo - (1 << 31), hi - (1 << 31)
    if lo < -(1 << 31) or hi > (1 << 31) - 1:  # pragma: no cover - fields of <= 32 bits
        raise TargetError(f"{where}: raw values {lo} .. {hi} do not fit 32 bits")
    return Field(msg, big, _shift(codec, where), codec.length, codec.is_signed, int(lo),
                 int(hi), biased)


def _messages(protocol: Protocol) -> tuple[tuple[Message, ...], dict[str, Field]]:
    msgs: list[Message] = []
    roles: dict[str, Field] = {}
    for i, m in enumerate(protocol.messages):
        if m.length > 8:
            raise TargetError(f"message {m.name} has {m.length} bytes: the target reads "
                              f"classic CAN frames (at most 8)")
        counter = None
        if m.counter is not None and protocol.check_counter:
            counter = _field(m.counter, i, f"counter {m.name}.{m.counter.name}", False, True)
        msgs.append(Message(m.name, m.frame_id, m.is_extended, m.length,
                            m.crc is not None and protocol.check_crc, counter))
        for r in m.roles:
            roles[r.role] = _field(r.codec, i, f"the {r.role} signal {m.name}.{r.signal}",
                                   protocol.strict_range)
    return tuple(msgs), roles


def _check_own_ids(protocol: Protocol) -> None:
    """Refuse a drive's frame on the ID of one of canrls' own frames, which the target
    sends (or receives, the command): it would take its own publications as feedback."""
    from canrls.can.estimator_frames import frame_ids

    own = frame_ids().own
    for m in protocol.messages:
        if not m.is_extended and m.frame_id in own:
            roles = ", ".join(r.role for r in m.roles) or "E2E signals"
            raise ConfigError(
                f"DBC {protocol.dbc_path}: message {m.name} (0x{m.frame_id:X}: {roles}) has "
                f"the ID of canrls' {own[m.frame_id]}: the target would take its own frames "
                f"as the drive's; give the drive's message another ID, or export with "
                f"--frames none (the firmware then sends the estimate itself)")


def _scale(protocol: Protocol, role: str, f: Field) -> tuple[Fraction, Fraction]:
    """``(k, o)``: SI value of one raw unit and the offset in raw units of ``role``
    held in field ``f`` (less its :attr:`Field.bias`; a float's raw unit ``2^-frac``)."""
    info = protocol.roles[role]
    k = info.si_per_raw_exact
    # the offset in raw units: (offset * f) / (scale * f); a float field's raw unit 2^-frac
    o = info.si_offset_exact / k
    return k / Fraction(2) ** f.frac, o * Fraction(2) ** f.frac + f.bias


def _source(eq: Equation, j: int, model: Model) -> tuple[int, str, int]:
    """(kind, role, order) of column ``j`` of ``eq``."""
    p = eq.parameters[j]
    base = p.effect.partition(":")[0]
    if base in ("inertia", "viscous"):
        return SRC_RAW, "speed", 0
    if base == "coulomb":
        return SRC_TANH, "speed", 0
    if base == "stribeck":
        return SRC_STRIBECK, "speed", 0
    if base == "offset":
        return SRC_CONST, "", 0
    if base in ("unbalance", "cogging"):
        return (SRC_SIN if p.symbol == "sin" else SRC_COS), "position", p.order
    if base == "electrical":
        return SRC_RAW, ("speed" if p.symbol == "Ke" else "current"), 0
    raise TargetError(f"{model.source}: effect {p.effect} ({p.name}) is not available on the "
                      f"target: a user term is an expression of the signals, which the "
                      f"integer path does not evaluate (no float); fit without it for the "
                      f"whole estimator, or export the kernel alone with --kernel-only")


def _coefficients(model: Model, dt: float) -> tuple[Quad, tuple[Quad, Quad]]:
    """The filter's Q30 coefficients with the derivative state scaled by ``dt``: ``A`` and
    ``(G0, G1)`` of each hold. ``G0 + G1 = (I - A) e1`` exactly, so a constant input stays
    exactly constant."""
    svf = SVF(model.cutoff_hz, dt, model.zeta)
    Ad = svf.Ad
    # z = D x, D = diag(1, dt): A' = D A D^-1, G' = D G
    a = [Ad[0, 0], Ad[0, 1] / dt, Ad[1, 0] * dt, Ad[1, 1]]
    q = [int(round(v * (1 << 30))) for v in a]
    A: Quad = (q[0], q[1], q[2], q[3])
    for v in A:
        if not -(1 << 31) < v < (1 << 31):
            raise TargetError(f"the filter's coefficients do not fit Q30 at cutoff "
                              f"{model.cutoff_hz} Hz and period {dt} s: the cutoff must be "
                              f"well below the sample rate")
    # Gu = (I - A) e1
    gu = ((1 << 30) - A[0], -A[2])
    G: list[Quad] = []
    for hold in ("foh", "zoh"):
        _, g1 = svf.coefficients(hold)
        g1q = (int(round(g1[0] * (1 << 30))), int(round(g1[1] * dt * (1 << 30))))
        g0q = (gu[0] - g1q[0], gu[1] - g1q[1])
        for v in (*g0q, *g1q):
            if not abs(v) <= (1 << 30):
                raise TargetError(f"the filter's input coefficients exceed 1 at cutoff "
                                  f"{model.cutoff_hz} Hz and period {dt} s")
        G.append((g0q[0], g0q[1], g1q[0], g1q[1]))
        # each row's coefficients sum below 2^31 in magnitude: the C sums the row's four
        # products of 31-bit words (the low parts of the split states) in 62 bits
        for row in ((A[0], A[1], g0q[0], g1q[0]), (A[2], A[3], g0q[1], g1q[1])):
            if sum(abs(v) for v in row) >= 1 << 31:
                raise TargetError(f"the filter's coefficients at cutoff {model.cutoff_hz} Hz "
                                  f"and period {dt} s are too large for the integer path: "
                                  f"the cutoff must be well below the sample rate")
    return A, (G[0], G[1])


def _fx(bound: int, gamma: float) -> int:
    """Fraction bits of a state whose input is at most ``bound``: ``|X| < 2^X_BITS`` with
    the filter's gain ``gamma`` and a factor 2 for the rounding."""
    fx = X_BITS - 1 - clog2(max(1, math.ceil(bound * gamma * 2)))
    if fx < 0:
        raise TargetError(f"an input of {bound} leaves the filter no fraction bit")
    return min(fx, FX_MAX)


def _narrow_fits(gamma: float) -> bool:
    """Whether a Q30 state of an input bounded by 1 (2^30) stays within int32 with the
    filter's gain ``gamma`` and ``NARROW_MARGIN`` for the rounding."""
    return math.ceil((1 << 30) * gamma) + NARROW_MARGIN < 1 << 31


class _Columns:
    """The filters and columns of one build: a filter is made once and shared by every
    column that reads it."""

    def __init__(self, protocol: Protocol, roles: Mapping[str, Field],
                 scales: Mapping[str, tuple[Fraction, Fraction]], gamma: float,
                 dt: float) -> None:
        self.protocol, self.roles, self.scales = protocol, roles, scales
        self.gamma, self.dt = gamma, dt
        self.filters: list[Filter] = []

    def filter_of(self, kind: int, role: str, order: int, hold: int) -> int:
        """The index of the filter of ``kind`` on ``role`` (made if new)."""
        if kind == SRC_CONST:
            # the constant 1 in Q30 with CONST_FX fraction bits more: no filter
            key = Filter(kind, "", 0, 0, CONST_FX)
        else:
            if role not in self.roles:
                raise TargetError(f"the model needs the {role} signal, which the mapping of "
                                  f"{self.protocol.dbc_path.name} does not give")
            # a raw input's bound is that of every raw word (2^31), never its DBC range:
            # a DBC's declared limits must not change the fraction bits, and so the answer
            bound = RAW_BOUND if kind == SRC_RAW else 1 << 30
            # an input bounded by 1 in Q30 whose filter's gain leaves it within int32 is
            # filtered in 32 bits (fx 0), else in 64
            fx = 0 if kind in BOUNDED and _narrow_fits(self.gamma) else _fx(bound, self.gamma)
            key = Filter(kind, role, order, hold, fx)
        for i, f_ in enumerate(self.filters):
            if f_ == key:
                return i
        self.filters.append(key)
        return len(self.filters) - 1

    def column(self, name: str, kind: int, role: str, order: int, hold: int, deriv: bool,
               gain: Fraction, frac: int, s: int, adaptive: bool, pend: bool) -> Column:
        """A column (or the output) read from its filter's state into ``frac`` bits at ``2**-s``."""
        fi = self.filter_of(kind, role, order, hold)
        flt = self.filters[fi]
        if kind == SRC_RAW:
            k, o = self.scales[role]
            K = gain * k
            offset = 0 if deriv else math.floor(o * 2 ** flt.fx + Fraction(1, 2))
        else:
            K, offset = gain * Fraction(1, 1 << 30), 0
        if deriv:
            K /= Fraction(self.dt)
        m, sh = _mantissa(K * Fraction(2) ** (frac - s - flt.fx))
        if sh < 0:
            raise TargetError(f"{name}: the filter's state cannot resolve this column finely "
                              f"enough (multiplier shift {sh} < 0)")
        return Column(name, fi, deriv, offset, m, sh, adaptive, pend, s)


def _ticks(dt: float, tick_s: float) -> int:
    """The control period in timestamp ticks."""
    if not (dt > 0 and math.isfinite(dt)):
        raise TargetError(f"the control period {dt!r} s must be > 0")
    dt_ticks = round(dt / tick_s)
    if dt_ticks < 2 or abs(dt_ticks * tick_s - dt) > 1e-3 * dt:
        raise TargetError(f"the control period {dt} s is not a whole number of timestamp "
                          f"ticks of {tick_s} s")
    return dt_ticks


def _selection(est: EquationEstimator, scales: Mapping[str, tuple[Fraction, Fraction]]
               ) -> Selection:
    """The sample selection (:class:`canrls.estimation.selection.SamplePolicy`) in the
    raw speed's units."""
    pol = est.policy
    k_w, o_w = scales["speed"]
    unit = abs(k_w) / Fraction(2) ** 16  # SI speed of one unit of W
    min_w = math.ceil(Fraction(pol.min_speed) / unit) if pol.min_speed > 0 else 0
    max_w = math.floor(Fraction(pol.max_speed) / unit) if math.isfinite(pol.max_speed) else -1
    return Selection(int(pol.warmup), int(min_w), int(max_w), pol.min_speed > 0)


def _equation(est: EquationEstimator, model: Model, settings: EstimatorSettings, dt: float,
              columns: _Columns, pending: Mapping[str, Sequence[str]] | None,
              param_info: list[tuple[int, int, int, int]]) -> EquationSpec:
    """One equation's integers: its columns and output, selection, plan and prior
    (``param_info`` gets a row per parameter)."""
    eq = est.equation
    frls = est.frls
    cfg = frls.config
    holds = eq.holds
    sc = eq.scaling
    pend = set((pending or {}).get(eq.name, ()))
    own = eq.intrinsic
    cols = []
    for j, p in enumerate(eq.parameters):
        kind, role, order = _source(eq, j, model)
        cols.append(columns.column(p.name, kind, role, order, int(holds[j + 1] == "zoh"),
                                   eq.derivative_mask[j], Fraction(1), cfg.phi.frac,
                                   sc.columns[j], not own[j], p.name in pend))
        param_info.append((int(p.effect_id), int(p.component), int(p.order),
                           int(eq.index)))
    trole = eq.output.signal
    if trole not in ("current", "torque", "voltage"):
        raise TargetError(f"the {eq.name} output {trole} is not a signal")
    output = columns.column("output", SRC_RAW, trole, 0, int(holds[0] == "zoh"), False,
                            Fraction(eq.output.gain), cfg.y.frac, sc.output, True,
                            "output" in pend)
    sel = _selection(est, columns.scales)
    # the kernel: its plan with the trace bound of the target's rule
    named = frls.constants
    lam_q = Fraction(cfg.lam.to_int(Fraction(frls.lam)), 1 << cfg.lam.frac)
    ktr = lam_q * Fraction(2) ** (cfg.P.frac - named["trace_ps"])
    tw = min(cfg.P.bits, cfg.acc_bits - 3)
    cap = (1 << (tw - 1)) - 1
    ridge = tuple(Fraction(float(a)) for a in est.ridge)
    terms = tuple(math.floor(ktr / r) for r in ridge)
    follows = settings.trace_max is None
    plan = dict(named)
    if follows:
        plan["trace_max_lam"] = min(sum(terms), cap)
    floor = min(ridge)
    first = Fraction(float(settings.alpha)) * Fraction(1, 256)
    st = frls.state()
    p0 = tuple(int(v) for v in np.diag(np.asarray(st["P"])))
    # theta_max / 2 in theta words
    half = math.floor(Fraction(settings.theta_max) / 2 * 2 ** cfg.theta.frac)
    beta = min(1.0, dt / settings.rms_time_s)
    rms_shift = max(0, round(-math.log2(beta)))
    return EquationSpec(
        name=eq.name, index=int(eq.index), columns=tuple(cols), output=output,
        selection=sel, plan=plan, p0=p0, e0=int(st["P_exp"]), f_phi=cfg.phi.frac,
        f_y=cfg.y.frac, f_theta=cfg.theta.frac, f_eps=cfg.eps.frac,
        theta_lo=cfg.theta.lo, theta_hi=cfg.theta.hi, P_lo=cfg.P.lo, P_hi=cfg.P.hi,
        phi_hi=cfg.phi.hi, lam=frls.lam, config=cfg, ridge=ridge, trace_follows=follows,
        trace_terms=terms, trace_cap=cap, prior_floor=floor,
        floor_term=math.floor(ktr / floor), first_ridge=first,
        first_term=math.floor(ktr / first), theta_half=half, rms_shift=rms_shift,
        exponents=tuple(sc.columns) + (sc.output,), parameters=eq.parameters)


def _argument(roles: Mapping[str, Field], role_scale: tuple[Fraction, Fraction],
              div: float) -> tuple[int, int, int]:
    """``(m, b, sh)`` of the argument ``z = (r + o) k / div`` in Q24 = rsh(r m + b, sh)."""
    # z = (r + o) k / div in Q24 = rsh(r m + b, sh)
    k, o = role_scale
    m, sh = _mantissa(k / Fraction(div) * 2 ** Z_FRAC)
    b = math.floor(o * m + Fraction(1, 2))
    f = roles["speed"]
    if max(abs(f.lo), abs(f.hi)) * abs(m) + abs(b) >= 1 << 62:
        raise TargetError(f"the speed's offset ({float(o):g} raw) is too large for the "
                          f"integer path")
    return m, b, sh


def _phase(model: Model, position: tuple[Fraction, Fraction]) -> tuple[int, int]:
    """The raw position's multiplier and offset to turns in Q64 (modulo 2^64)."""
    k, o = position
    if model.axis == "rotary":
        turns = k / Fraction(2 * math.pi)
    else:
        if model.wrap is not None and Fraction(model.wrap) / Fraction(model.pitch) \
                != round(Fraction(model.wrap) / Fraction(model.pitch)):
            raise TargetError(f"{model.source}: a linear position that wraps at "
                              f"{model.wrap} m, not a whole number of pitches "
                              f"({model.pitch} m), is not available on the target")
        turns = k / Fraction(model.pitch)
    pm = math.floor(turns * 2 ** 64 + Fraction(1, 2))
    po = math.floor(o * turns * 2 ** 64 + Fraction(1, 2))
    return pm & MASK64, po & MASK64


def build(model: Model, protocol: Protocol, settings: EstimatorSettings, dt: float, *,
          energy: Mapping[str, Sequence[float]] | None = None,
          pending: Mapping[str, Sequence[str]] | None = None,
          tick_s: float = 1e-6, publish_s: float = 0.1, frames: bool = True,
          source: str = "the model") -> TargetModel:
    """The integers of ``model`` on ``protocol`` at the period ``dt`` [s], as the service
    runs it after the calibration that gave ``energy`` and ``pending`` (``canrls fit
    --save-model`` keeps both; without, the prior of an estimator that has not
    calibrated). ``tick_s``: the unit of the frames' timestamps on the target (1 us);
    ``publish_s``: the period of the parameter frames; ``frames``: the estimator frames
    of canrls' DBC (False: the target computes the estimate, the caller sends it).

    :raises TargetError: something the target does not do (the message says what).
    """
    if frames:
        _check_own_ids(protocol)
    dt_ticks = _ticks(dt, tick_s)
    messages, roles = _messages(protocol)
    pipe = Pipeline(model, dt, settings, energy, pending)
    A, G = _coefficients(model, dt)
    f_gain, sf_gain = gain_bounds(model.cutoff_hz, model.zeta)
    gamma = max(f_gain, sf_gain * dt, 1.0)
    scales = {r: _scale(protocol, r, f) for r, f in roles.items()}
    columns = _Columns(protocol, roles, scales, gamma, dt)

    param_info: list[tuple[int, int, int, int]] = []
    eqs = [_equation(est, model, settings, dt, columns, pending, param_info)
           for est in pipe.estimators]

    filters = columns.filters
    uses = {f.kind for f in filters}
    tanh_arg = stribeck_arg = phase = None
    if uses & {SRC_TANH, SRC_STRIBECK}:
        tanh_arg = _argument(roles, scales["speed"], model.coulomb_band)
    if SRC_STRIBECK in uses:
        stribeck_arg = _argument(roles, scales["speed"], model.stribeck_speed)
    if uses & {SRC_SIN, SRC_COS}:
        phase = _phase(model, scales["position"])
    k_w, o_w = scales["speed"]
    w_offset = math.floor(o_w * 2 ** W_FRAC + Fraction(1, 2))
    publish_every = max(1, round(publish_s / dt))
    return TargetModel(
        source=source, dt=float(dt), tick_s=float(tick_s), dt_ticks=int(dt_ticks),
        gap_ticks=int(dt_ticks + dt_ticks // 2), tol_ticks=int(dt_ticks // 2),
        messages=messages, roles=roles, tanh_arg=tanh_arg, stribeck_arg=stribeck_arg,
        phase=phase, w_offset=w_offset, A=A, G=G, filters=tuple(filters),
        equations=tuple(eqs), publish_every=publish_every,
        active_effects=int(model.active_effects), param_info=tuple(param_info),
        out=out_frames() if frames else None, model=model, protocol=protocol)


def describe(tm: TargetModel) -> dict[str, Any]:
    """A plain description (for the README of an export and the tests)."""
    return {"messages": [m.name for m in tm.messages],
            "filters": [f.label for f in tm.filters],
            "equations": {e.name: [c.name for c in e.columns] for e in tm.equations}}
