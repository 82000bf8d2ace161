"""The compiled codec of one DBC signal (:class:`SignalCodec`) and of a mapped message
(:class:`MessageCodec`): bit fields gathered with numpy, strict range checks, the E2E CRC
of whole blocks."""

from __future__ import annotations

from dataclasses import dataclass
from fractions import Fraction
from typing import Any

import numpy as np
import numpy.typing as npt

from canrls import _can
from canrls.can.e2e import CRC8_TABLE
from canrls.core.errors import DecodeError, SignalError

__all__ = ["CRC8_POWERS", "EncodeError", "MessageCodec", "PHYS_FLOAT", "PHYS_IDENTITY", "PHYS_INT",
           "RoleInfo", "SignalCodec", "crc_vector", "format_value"]

F64 = npt.NDArray[np.float64]
U8 = npt.NDArray[np.uint8]
U64 = npt.NDArray[np.uint64]

#: :meth:`SignalCodec.scaling` modes
PHYS_IDENTITY, PHYS_INT, PHYS_FLOAT = 0, 1, 2


class EncodeError(DecodeError):
    """A value cannot be encoded into a frame (outside the DBC range or the bit field, NaN).

    A :class:`~canrls.core.errors.DecodeError` with ``reason`` ``"range"`` or ``"nan"``, so
    that callers treat it like the matching rejection on the receiving side.
    """



class SignalCodec:
    """Vectorised codec of one DBC signal, built from a cantools ``Signal``.

    The signal's bits are gathered byte by byte: ``byte_index[j]`` is the payload byte
    holding bits ``8*j - shift .. 8*j - shift + 7`` of the raw value (least significant
    byte first), for both byte orders. Physical values are in the DBC unit.
    """

    __slots__ = ("name", "message", "length", "byte_order", "is_signed", "is_float", "scale",
                 "offset", "minimum", "maximum", "unit", "byte_index", "shift", "tol",
                 "raw_min", "raw_max", "enc_lo", "enc_hi")

    def __init__(self, signal: Any, message: str) -> None:
        conv = signal.conversion
        self.name: str = signal.name
        self.message = message
        self.length: int = int(signal.length)
        self.byte_order: str = signal.byte_order
        self.is_signed: bool = bool(signal.is_signed)
        self.is_float: bool = bool(conv.is_float)
        self.scale = conv.scale
        self.offset = conv.offset
        self.minimum: float | None = signal.minimum
        self.maximum: float | None = signal.maximum
        self.unit: str = signal.unit or ""
        L = self.length
        if self.is_float and L not in (16, 32, 64):
            raise SignalError(f"{message}.{self.name}: float signals must be 16, 32 or 64 bits, "
                              f"not {L}")
        if not 1 <= L <= 64:
            raise SignalError(f"{message}.{self.name}: length {L} outside 1..64 bits")
        if self.byte_order == "little_endian":
            first = signal.start // 8
            self.shift = signal.start % 8
            nb = (self.shift + L + 7) // 8
            self.byte_index: tuple[int, ...] = tuple(first + j for j in range(nb))
        else:
            msb = 8 * (signal.start // 8) + 7 - signal.start % 8  # sequential bit number
            last = msb + L - 1
            self.shift = 7 - last % 8
            nb = (self.shift + L + 7) // 8
            self.byte_index = tuple(last // 8 - j for j in range(nb))
        # tolerance of the range check, the same as cantools' encoder
        self.tol = abs(float(self.scale)) * 1e-6
        if self.is_signed:
            self.raw_min, self.raw_max = -(1 << (L - 1)), (1 << (L - 1)) - 1
        else:
            self.raw_min, self.raw_max = 0, (1 << L) - 1
        self.enc_lo, self.enc_hi = self._encodable_raw_range()

    def __repr__(self) -> str:
        return (f"SignalCodec({self.message}.{self.name}, {self.length} bit {self.byte_order}, "
                f"{'float' if self.is_float else 'signed' if self.is_signed else 'unsigned'}, "
                f"scale={self.scale}, offset={self.offset}, "
                f"[{self.minimum}, {self.maximum}] {self.unit!r})")

    @property
    def qualname(self) -> str:
        return f"{self.message}.{self.name}"

    # -- decoding ---------------------------------------------------------
    def extract(self, data: U8) -> U64:
        """Raw bit field of each row of ``data`` (N, W) as uint64 (not sign-extended)."""
        # the OR of byte byte_index[j] shifted by 8 j - shift (least significant byte
        # first), masked to the field's length
        acc = np.zeros(data.shape[0], np.uint64)
        for j, b in enumerate(self.byte_index):
            sh = 8 * j - self.shift
            col = data[:, b].astype(np.uint64)
            if sh < 0:
                acc |= col >> np.uint64(-sh)
            elif sh < 64:
                acc |= col << np.uint64(sh)
        if self.length < 64:
            acc &= np.uint64((1 << self.length) - 1)
        return acc

    def raw(self, data: U8) -> npt.NDArray[Any]:
        """Raw values: int64 (signed, or unsigned up to 63 bits), uint64 (64 bits) or float."""
        acc = self.extract(data)
        L = self.length
        if self.is_float:
            if L == 32:
                return acc.astype(np.uint32).view(np.float32)
            if L == 64:
                return acc.view(np.float64)
            return acc.astype(np.uint16).view(np.float16)
        if self.is_signed:
            sh = np.uint64(64 - L)
            return (acc << sh).view(np.int64) >> np.int64(64 - L)
        return acc if L == 64 else acc.view(np.int64)

    def physical(self, data: U8) -> F64:
        """Physical values in the DBC unit: ``raw * scale + offset`` (float64).

        Computed as cantools does: in float for a float scale or offset, exactly in
        integers (then rounded once to float64) for an integer scale and offset.
        """
        raw = self.raw(data)
        if self.is_float or not (isinstance(self.scale, int) and isinstance(self.offset, int)):
            # float signals may hold (signalling) NaN or overflow when scaled: rejected later
            with np.errstate(invalid="ignore", over="ignore"):
                r = raw.astype(np.float64)
                if self.scale == 1 and self.offset == 0:
                    return r
                return r * float(self.scale) + float(self.offset)
        if self.scale == 1 and self.offset == 0:
            return raw.astype(np.float64)
        if (1 << self.length) * abs(self.scale) + abs(self.offset) < (1 << 63):
            return (raw.astype(np.int64) * self.scale + self.offset).astype(np.float64)
        exact = [int(x) * self.scale + self.offset for x in raw.tolist()]  # beyond int64
        return np.array([float(x) for x in exact], np.float64)

    def scaling(self) -> tuple[int, int | float, int | float] | None:
        """How :meth:`physical` scales, for the fused decoding kernel: ``(mode, scale,
        offset)`` with mode :data:`PHYS_IDENTITY` (the raw value as float64),
        :data:`PHYS_INT` (``raw * scale + offset`` in int64, then float64; integer
        ``scale`` and ``offset``) or :data:`PHYS_FLOAT` (``float64(raw) * scale +
        offset``; float ``scale`` and ``offset``). ``None`` where the kernel cannot
        reproduce :meth:`physical` bit for bit: 16-bit floats, and integer scalings
        that overflow int64.
        """
        if self.is_float or not (isinstance(self.scale, int) and isinstance(self.offset, int)):
            if self.is_float and self.length == 16:
                return None
            if self.scale == 1 and self.offset == 0:
                return PHYS_IDENTITY, 1.0, 0.0
            return PHYS_FLOAT, float(self.scale), float(self.offset)
        if self.scale == 1 and self.offset == 0:
            return PHYS_IDENTITY, 1, 0
        if (1 << self.length) * abs(self.scale) + abs(self.offset) < (1 << 63):
            return PHYS_INT, int(self.scale), int(self.offset)
        return None

    def out_of_range(self, phys: F64) -> npt.NDArray[np.bool_]:
        """True where a physical value lies outside [minimum, maximum] (cantools' tolerance)."""
        bad = np.zeros(phys.shape, np.bool_)
        if self.minimum is not None:
            bad |= phys < self.minimum - self.tol
        if self.maximum is not None:
            bad |= phys > self.maximum + self.tol
        return bad

    # -- encoding ---------------------------------------------------------
    def _encodable_raw_range(self) -> tuple[int, int]:
        """Raw values whose decoded value lies in the DBC range and that fit the bit field."""
        lo, hi = self.raw_min, min(self.raw_max, (1 << 63) - 1)
        if self.is_float:
            return lo, hi
        s, o = float(self.scale), float(self.offset)

        def above_min(r: int) -> bool:
            return self.minimum is None or float(r) * s + o >= self.minimum - self.tol

        def below_max(r: int) -> bool:
            return self.maximum is None or float(r) * s + o <= self.maximum + self.tol

        # rising: false then true as r grows; falling: true then false (float rounding is monotone)
        rising, falling = (above_min, below_max) if s > 0 else (below_max, above_min)
        a, b = lo, hi + 1          # smallest r in [lo, hi] with rising(r), else hi + 1
        while a < b:
            mid = (a + b) // 2
            a, b = (a, mid) if rising(mid) else (mid + 1, b)
        new_lo = a
        a, b = lo - 1, hi          # largest r in [lo, hi] with falling(r), else lo - 1
        while a < b:
            mid = (a + b + 1) // 2
            a, b = (mid, b) if falling(mid) else (a, mid - 1)
        return new_lo, a

    def to_raw(self, values: F64, clip: bool = False,
               wrap: bool = False) -> tuple[npt.NDArray[Any], int]:
        """Physical values (DBC unit) -> raw values rounded to nearest (half to even, as cantools).

        ``wrap=True`` reduces integer raw values modulo the bit field (a full-turn angle).

        Returns the raw array (int64, or float for float signals) and the number of
        values clipped (only with ``clip=True``; otherwise out-of-range values raise
        :class:`EncodeError` naming the signal, the value and the limits).
        """
        v = np.asarray(values, np.float64)
        bad_nan = ~np.isfinite(v)
        if bad_nan.any():
            k = int(np.flatnonzero(bad_nan)[0])
            raise EncodeError(f"cannot encode {self.qualname} = {v[k]} {self.unit} (sample {k})",
                              reason="nan")
        if self.is_float:
            lo = -np.inf if self.minimum is None else self.minimum - self.tol
            hi = np.inf if self.maximum is None else self.maximum + self.tol
            if self.length == 32:
                f32 = float(np.finfo(np.float32).max)
                lo, hi = max(lo, -f32), min(hi, f32)
            bad = (v < lo) | (v > hi)
            n_clip = int(bad.sum())
            if n_clip:
                if not clip:
                    self._raise_range(v, bad)
                v = np.clip(v, lo, hi)
            r = v if self.scale == 1 and self.offset == 0 else \
                (v - float(self.offset)) / float(self.scale)
            return r, n_clip
        if self.scale == 1 and self.offset == 0:
            r = np.rint(v)
        else:
            r = np.rint((v - float(self.offset)) / float(self.scale))
        if wrap:
            # a full-turn position field: encode modulo one turn
            r = np.mod(r - self.raw_min, float(1 << self.length)) + self.raw_min
        lo, hi = float(self.enc_lo), float(self.enc_hi)
        bad = (r < lo) | (r > hi)
        n_clip = int(bad.sum())
        if n_clip:
            if not clip:
                self._raise_range(v, bad)
            r = np.clip(r, lo, hi)
        return r.astype(np.int64), n_clip

    def _raise_range(self, v: F64, bad: npt.NDArray[np.bool_]) -> None:
        k = int(np.flatnonzero(bad)[0])
        x = float(v[k])
        lo, hi = self.minimum, self.maximum
        if (lo is None or x >= lo - self.tol) and (hi is None or x <= hi + self.tol):
            what = (f"does not fit the {self.length}-bit field "
                    f"(raw {self.raw_min} .. {self.raw_max}, scale {self.scale}, "
                    f"offset {self.offset})")
        else:
            what = (f"outside [{format_value(lo) if lo is not None else '-inf'}, "
                    f"{format_value(hi) if hi is not None else 'inf'}] {self.unit}")
        raise EncodeError(f"cannot encode {self.qualname} = {format_value(x)} {self.unit}: {what} "
                          f"(sample {k})", reason="range")

    def insert(self, data: U8, raw: npt.NDArray[Any]) -> None:
        """OR the raw values into the rows of ``data`` (N, W), in place."""
        if self.is_float:
            f = np.asarray(raw, np.float64)
            if self.length == 32:
                u = f.astype(np.float32).view(np.uint32).astype(np.uint64)
            elif self.length == 64:
                u = f.view(np.uint64)
            else:
                u = f.astype(np.float16).view(np.uint16).astype(np.uint64)
        else:
            u = np.asarray(raw, np.int64).view(np.uint64)
            if self.length < 64:
                u = u & np.uint64((1 << self.length) - 1)
        for j, b in enumerate(self.byte_index):
            sh = 8 * j - self.shift
            part = (u << np.uint64(-sh)) if sh < 0 else (u >> np.uint64(sh))
            data[:, b] |= (part & np.uint64(0xFF)).astype(np.uint8)


def format_value(x: float) -> str:
    return f"{float(x):.6g}"


def _crc_powers() -> U8:
    """T, T^2, ..., T^8 of the CRC table T (:data:`canrls.can.e2e.CRC8_TABLE`), rows of a
    (8, 256) array: the C loops look bytes up in parallel (``src/canrls/c/host/can.c``)."""
    powers = np.empty((8, 256), np.uint8)
    powers[0] = CRC8_TABLE
    for k in range(1, 8):
        powers[k] = CRC8_TABLE[powers[k - 1]]
    x = np.arange(256)
    bits = [CRC8_TABLE[x & (1 << b)] for b in range(8)]
    if not (np.bitwise_xor.reduce(bits) == CRC8_TABLE).all():  # pragma: no cover
        raise AssertionError("the CRC table is not linear")
    return powers


#: :func:`_crc_powers`, computed once (the CRC kernels take it)
CRC8_POWERS = _crc_powers()


def crc_vector(frame_id: int, data: U8, length: int) -> U8:
    """E2E CRC (:func:`canrls.can.e2e.e2e_crc`) of every row: over the ID, then bytes
    1..length-1."""
    out = np.empty(data.shape[0], np.uint8)
    d = np.ascontiguousarray(data, np.uint8)
    _can.crc8(int(frame_id), d, d.shape[1], int(length), CRC8_POWERS, out)
    return out


@dataclass(frozen=True)
class RoleInfo:
    """A resolved role: its signal codec and the factor from the DBC unit to SI."""

    role: str
    codec: SignalCodec
    #: the factor from the DBC unit to SI (:func:`canrls.core.units.si_factor`)
    si_scale: float
    unit: str

    @property
    def message(self) -> str:
        return self.codec.message

    @property
    def si_per_raw_exact(self) -> Fraction:
        """The SI value of one raw unit, exactly: the DBC scale times the unit's factor
        to SI. The one place that multiplies them (the firmware's integers, the C
        export's comments, the encoder's full-turn test read it)."""
        return _exact(self.codec.scale) * Fraction(self.si_scale)

    @property
    def si_offset_exact(self) -> Fraction:
        """The DBC offset in SI, exactly (the offset times the unit's factor)."""
        return _exact(self.codec.offset) * Fraction(self.si_scale)

    @property
    def si_per_raw(self) -> float:
        """:attr:`si_per_raw_exact` as a float (the product of the two, rounded once)."""
        return float(self.si_per_raw_exact)

    @property
    def si_offset(self) -> float:
        """:attr:`si_offset_exact` as a float."""
        return float(self.si_offset_exact)

    @property
    def signal(self) -> str:
        return self.codec.name


@dataclass(frozen=True)
class MessageCodec:
    """A mapped DBC message: ID, length, cycle time, its roles and E2E signals."""

    name: str
    frame_id: int
    is_extended: bool
    length: int
    cycle_time: float | None          # [s], from GenMsgCycleTime (or the configured period)
    roles: tuple[RoleInfo, ...]
    counter: SignalCodec | None
    crc: SignalCodec | None
    message: Any                      # the cantools Message

    @property
    def counter_modulo(self) -> int | None:
        return None if self.counter is None else 1 << self.counter.length


def _exact(x: int | float) -> Fraction:
    """A DBC scale or offset (cantools: an int or a float) as an exact fraction."""
    return Fraction(x) if isinstance(x, int) else Fraction(float(x))
