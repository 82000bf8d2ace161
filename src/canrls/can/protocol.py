"""The feedback protocol: DBC, signal mapping and a strict, vectorised codec.

canrls reads motor current (or the torque the drive reports), speed, position and
voltage from CAN frames described by a DBC file. :class:`Protocol` ties three things
together:

* the DBC, loaded with cantools (the default one, ``canrls/data/canrls.dbc``, or
  the user's);
* a :class:`SignalMapping` that says which ``MESSAGE.SIGNAL`` carries each role
  (``current``, ``speed``, ``position``, ``voltage``, ``torque``), its scale to SI
  (with the :class:`~canrls.can.units.Ratings` that relative units need) and which
  signals of each message are the alive counter and the CRC;
* one compiled codec per mapped message, built once from cantools' ``Signal``
  objects (start bit, length, byte order, signedness, scale, offset, minimum,
  maximum, float), that decodes whole :class:`~canrls.can.frameblock.FrameBlock`
  arrays with numpy and encodes SI arrays back into frames.

Decoding is strict by default: a frame with the wrong length, a bad CRC, a
repeated, stale or out-of-sequence counter, a NaN/inf float, a value outside its DBC
range, an error frame or a remote frame is rejected, counted by reason
(:class:`RejectCounts`) and never passed on. The opt-outs are named:
``strict_range=False``, ``check_crc=False``, ``check_counter=False``.

>>> proto = Protocol.load()                       # default DBC and mapping
>>> enc = FeedbackEncoder(proto)
>>> block = enc.encode([0.0, 0.001], current=[1.5, 1.6], speed=[10.0, 10.1])
>>> dec = proto.decoder().decode(block)
>>> dec["DriveCurrent"].values["current"].tolist()
[1.5, 1.6]
"""

from __future__ import annotations

import functools
import hashlib
import math
import re
from collections.abc import Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from typing import Any

import cantools
import numpy as np
import numpy.typing as npt

from canrls import _can
from canrls.can.e2e import CRC8_TABLE
from canrls.can.frameblock import FrameBlock
from canrls.can.units import RATING_OPTIONS, Ratings, axis_of, si_factor
from canrls.errors import ConfigError, DecodeError, SignalError
from canrls.files import MAX_DBC_BYTES, read_bytes
from canrls.signals import ROLES

__all__ = [
    "DEFAULT_DBC",
    "MAX_MESSAGE_BYTES",
    "load_dbc",
    "REQUIRED_ROLES",
    "EFFORT_ROLES",
    "REJECT_REASONS",
    "RoleSpec",
    "SignalMapping",
    "SignalCodec",
    "MessageCodec",
    "Protocol",
    "RejectCounts",
    "MessageFrames",
    "DecodedFrames",
    "Decoder",
    "EncodeError",
    "FeedbackEncoder",
]

F64 = npt.NDArray[np.float64]
I64 = npt.NDArray[np.int64]
U8 = npt.NDArray[np.uint8]
U64 = npt.NDArray[np.uint64]

#: The DBC shipped with canrls (same content as ``dbc/canrls.dbc`` in the repository).
DEFAULT_DBC: Path = Path(str(resources.files("canrls") / "data" / "canrls.dbc"))

#: Longest message a DBC may declare [bytes]: a CAN FD frame's payload.
MAX_MESSAGE_BYTES = 64

#: Roles every mapping must fill; ``position`` and ``voltage`` are optional.
REQUIRED_ROLES: tuple[str, ...] = ("speed",)
#: A mapping fills at least one of these: the current, or the torque (force) the drive
#: reports; with both, the torque is the mechanical target and the current feeds the
#: electrical equation.
EFFORT_ROLES: tuple[str, ...] = ("current", "torque")

#: Rejection reasons, in the order the checks run (a frame counts under the first that fails).
REJECT_REASONS: tuple[str, ...] = (
    "error_frame",  # a CAN error frame (bus error, bus-off notification)
    "remote",       # a remote frame carrying a mapped message's ID
    "length",       # DLC differs from the DBC message length
    "crc",          # E2E CRC mismatch
    "repeated",     # same alive counter as the previous accepted frame of the message
    "stale",        # counter jumped backwards (by less than half its range)
    "sequence",     # counter jumped further ahead than the time since the last frame allows
    "nan",          # a float signal is NaN or infinite
    "range",        # a physical value lies outside the DBC [minimum, maximum]
    "time",         # the receive time is no time of the stream (canrls.can.times): judged
                    # first, by the front end, before decoding; listed last, so that the
                    # codes of the others stay
)
_R = {r: k + 1 for k, r in enumerate(REJECT_REASONS)}  # reason -> code (0 = accepted)
_NO_REJECTS = dict.fromkeys(REJECT_REASONS, 0)


#: :meth:`SignalCodec.scaling` modes
_PHYS_IDENTITY, _PHYS_INT, _PHYS_FLOAT = 0, 1, 2


class EncodeError(DecodeError):
    """A value cannot be encoded into a frame (outside the DBC range or the bit field, NaN).

    A :class:`~canrls.errors.DecodeError` with ``reason`` ``"range"`` or ``"nan"``, so
    that callers treat it like the matching rejection on the receiving side.
    """


# ---------------------------------------------------------------------------
# Mapping
# ---------------------------------------------------------------------------


@dataclass(frozen=True)
class RoleSpec:
    """Where one role lives: ``message.signal``, with an optional unit or explicit scale.

    ``unit`` overrides the DBC's unit string; ``scale`` (SI per DBC physical unit)
    overrides both. ``optional`` roles are dropped silently when the DBC lacks the
    message or signal (used by the default mapping for position and voltage).
    """

    message: str
    signal: str
    unit: str | None = None
    scale: float | None = None
    optional: bool = False

    def __str__(self) -> str:
        return f"{self.message}.{self.signal}"


_UNSET: Any = object()
_ROLE_KEYS = {"signal", "message", "unit", "scale", "counter", "crc", "optional"}
_MSG_KEYS = {"counter", "crc"}
_CLI_RE = re.compile(r"^\s*(?P<key>[A-Za-z_]+)\s*=\s*(?P<msg>[^.\s:]+)\.(?P<sig>[^.\s:]+)"
                     r"(?::(?P<unit>.+))?\s*$")


@dataclass(frozen=True)
class SignalMapping:
    """Role -> :class:`RoleSpec`, plus the alive-counter and CRC signal of each message.

    ``counters`` / ``crcs`` map a message name to a signal name, or to ``None`` for
    "this message has none". A message absent from them has a counter/CRC only
    when the DBC is the default one and has signals named ``Counter`` / ``CRC``
    (auto-detection never applies to user DBCs). ``ratings`` are what relative units
    (``‰`` of the rated torque or current, increments) refer to.
    """

    roles: Mapping[str, RoleSpec]
    counters: Mapping[str, str | None] = field(default_factory=dict)
    crcs: Mapping[str, str | None] = field(default_factory=dict)
    ratings: Ratings = field(default_factory=Ratings)

    @staticmethod
    def default() -> SignalMapping:
        """The default DBC's mapping: DriveCurrent.Current/Voltage, DriveSpeed.Speed/Position."""
        return SignalMapping(roles={
            "current": RoleSpec("DriveCurrent", "Current"),
            "speed": RoleSpec("DriveSpeed", "Speed"),
            "position": RoleSpec("DriveSpeed", "Position", optional=True),
            "voltage": RoleSpec("DriveCurrent", "Voltage", optional=True),
        })

    @staticmethod
    def from_config(config: Mapping[str, Any], *, source: str = "signal mapping") -> SignalMapping:
        """Build from a config table (e.g. the ``[signals]`` table of a TOML file).

        Each role is ``"MESSAGE.SIGNAL"`` or a table with ``signal = "MESSAGE.SIGNAL"``
        (or ``message`` + ``signal``) and optional ``unit``, ``scale``, ``counter``,
        ``crc``. ``counter``/``crc`` are a signal name of the role's message or
        ``false``. A ``messages`` table may give ``counter``/``crc`` per message;
        ``rated_torque``, ``rated_current`` and ``increments_per_rev`` give the
        :class:`~canrls.can.units.Ratings`::

            current = "Feedback.Iq"
            speed = { signal = "Feedback.Speed", unit = "rpm", counter = "Alive", crc = false }
            rated_current = 5.0
            [messages.Feedback]
            counter = "Alive"

        ``source`` names the file or table in error messages.
        """
        if not isinstance(config, Mapping):
            raise ConfigError(f"{source}: expected a table of roles, got {type(config).__name__}")
        roles: dict[str, RoleSpec] = {}
        counters: dict[str, str | None] = {}
        crcs: dict[str, str | None] = {}
        ratings: dict[str, float] = {}

        def e2e(kind: str, table: dict[str, str | None], message: str, value: Any,
                where: str) -> None:
            if value is False or value is None:
                name = None
            elif isinstance(value, str) and value:
                name = value.split(".", 1)[1] if value.startswith(message + ".") else value
            else:
                raise ConfigError(f"{source}: {where}.{kind} must be a signal name or false, "
                                  f"got {value!r}")
            if message in table and table[message] != name:
                raise ConfigError(f"{source}: {kind} of message {message} given twice "
                                  f"({table[message]!r} and {name!r})")
            table[message] = name

        for key, value in config.items():
            if key == "messages":
                if not isinstance(value, Mapping):
                    raise ConfigError(f"{source}: messages must be a table of message names")
                for msg, t in value.items():
                    if not isinstance(t, Mapping):
                        raise ConfigError(f"{source}: messages.{msg} must be a table")
                    for k in t:
                        if k not in _MSG_KEYS:
                            raise ConfigError(f"{source}: unknown key messages.{msg}.{k} "
                                              f"(expected counter, crc)")
                    if "counter" in t:
                        e2e("counter", counters, msg, t["counter"], f"messages.{msg}")
                    if "crc" in t:
                        e2e("crc", crcs, msg, t["crc"], f"messages.{msg}")
                continue
            if key in RATING_OPTIONS:
                ratings[key] = value
                continue
            if key not in ROLES:
                raise ConfigError(f"{source}: unknown key {key!r} (expected one of "
                                  f"{', '.join(ROLES)}, messages, "
                                  f"{', '.join(RATING_OPTIONS)})")
            if isinstance(value, str):
                msg, sig = _split_ref(value, f"{source}: {key}")
                roles[key] = RoleSpec(msg, sig)
                continue
            if not isinstance(value, Mapping):
                raise ConfigError(f"{source}: {key} must be \"MESSAGE.SIGNAL\" or a table, "
                                  f"got {value!r}")
            for k in value:
                if k not in _ROLE_KEYS:
                    raise ConfigError(f"{source}: unknown key {key}.{k} "
                                      f"(expected {', '.join(sorted(_ROLE_KEYS))})")
            ref = value.get("signal")
            if not isinstance(ref, str):
                raise ConfigError(f"{source}: {key}.signal is required (\"MESSAGE.SIGNAL\")")
            if "message" in value:
                msg, sig = str(value["message"]), ref
            else:
                msg, sig = _split_ref(ref, f"{source}: {key}.signal")
            unit = value.get("unit")
            if unit is not None and not isinstance(unit, str):
                raise ConfigError(f"{source}: {key}.unit must be a string, got {unit!r}")
            scale = value.get("scale")
            if scale is not None:
                if isinstance(scale, bool) or not isinstance(scale, (int, float)) \
                        or not math.isfinite(scale) or scale == 0:
                    raise ConfigError(f"{source}: {key}.scale must be a finite non-zero number, "
                                      f"got {scale!r}")
                scale = float(scale)
            roles[key] = RoleSpec(msg, sig, unit=unit, scale=scale,
                                  optional=bool(value.get("optional", False)))
            if "counter" in value:
                e2e("counter", counters, msg, value["counter"], key)
            if "crc" in value:
                e2e("crc", crcs, msg, value["crc"], key)
        for key, v in ratings.items():
            if (isinstance(v, bool) or not isinstance(v, int | float)
                    or not (math.isfinite(v) and v > 0)):
                raise ConfigError(f"{source}: {key} = {v!r}: must be a positive number "
                                  f"({RATING_OPTIONS[key][2]})")
        return SignalMapping(roles=roles, counters=counters, crcs=crcs,
                             ratings=Ratings(**ratings))

    @staticmethod
    def from_strings(items: Iterable[str], *, base: SignalMapping | None = None) -> SignalMapping:
        """Build from command-line strings ``ROLE=MESSAGE.SIGNAL[:UNIT_OR_SCALE]``.

        ``counter=MESSAGE.SIGNAL`` and ``crc=MESSAGE.SIGNAL`` name a message's alive
        counter and CRC; ``counter=MESSAGE.none`` says it has none. Roles given here
        replace those of ``base`` (default: an empty mapping).

        >>> m = SignalMapping.from_strings(["current=Fb.Iq:mA", "speed=Fb.Spd:rpm"])
        >>> m.roles["current"]
        RoleSpec(message='Fb', signal='Iq', unit='mA', scale=None, optional=False)
        """
        roles = dict(base.roles) if base else {}
        counters = dict(base.counters) if base else {}
        crcs = dict(base.crcs) if base else {}
        ratings = base.ratings if base else Ratings()
        for item in items:
            m = _CLI_RE.match(item)
            if not m:
                raise ConfigError(f"--signal {item}: expected ROLE=MESSAGE.SIGNAL[:UNIT] "
                                  f"with ROLE in {', '.join(ROLES)}, counter, crc")
            key, msg, sig, extra = m["key"], m["msg"], m["sig"], m["unit"]
            if key in ("counter", "crc"):
                if extra:
                    raise ConfigError(f"--signal {item}: {key} takes no unit")
                (counters if key == "counter" else crcs)[msg] = \
                    None if sig.lower() in ("none", "false") else sig
                continue
            if key not in ROLES:
                raise ConfigError(f"--signal {item}: unknown role {key!r} "
                                  f"(expected one of {', '.join(ROLES)}, counter, crc)")
            unit: str | None = None
            scale: float | None = None
            if extra:
                try:
                    scale = float(extra)
                except ValueError:
                    unit = extra.strip()
                else:
                    if not math.isfinite(scale) or scale == 0:
                        raise ConfigError(f"--signal {item}: scale must be finite "
                                          f"and non-zero")
            roles[key] = RoleSpec(msg, sig, unit=unit, scale=scale)
        return SignalMapping(roles=roles, counters=counters, crcs=crcs, ratings=ratings)

    def describe(self) -> str:
        """One line per role, e.g. ``current = DriveCurrent.Current``."""
        return "\n".join(f"{r} = {self.roles[r]}" for r in ROLES if r in self.roles)


def _split_ref(ref: str, where: str) -> tuple[str, str]:
    parts = ref.strip().split(".")
    if len(parts) != 2 or not all(parts):
        raise ConfigError(f"{where}: expected \"MESSAGE.SIGNAL\", got {ref!r}")
    return parts[0], parts[1]


# ---------------------------------------------------------------------------
# Signal and message codecs
# ---------------------------------------------------------------------------


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
        offset)`` with mode :data:`_PHYS_IDENTITY` (the raw value as float64),
        :data:`_PHYS_INT` (``raw * scale + offset`` in int64, then float64; integer
        ``scale`` and ``offset``) or :data:`_PHYS_FLOAT` (``float64(raw) * scale +
        offset``; float ``scale`` and ``offset``). ``None`` where the kernel cannot
        reproduce :meth:`physical` bit for bit: 16-bit floats, and integer scalings
        that overflow int64.
        """
        if self.is_float or not (isinstance(self.scale, int) and isinstance(self.offset, int)):
            if self.is_float and self.length == 16:
                return None
            if self.scale == 1 and self.offset == 0:
                return _PHYS_IDENTITY, 1.0, 0.0
            return _PHYS_FLOAT, float(self.scale), float(self.offset)
        if self.scale == 1 and self.offset == 0:
            return _PHYS_IDENTITY, 1, 0
        if (1 << self.length) * abs(self.scale) + abs(self.offset) < (1 << 63):
            return _PHYS_INT, int(self.scale), int(self.offset)
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
            what = (f"outside [{_fmt(lo) if lo is not None else '-inf'}, "
                    f"{_fmt(hi) if hi is not None else 'inf'}] {self.unit}")
        raise EncodeError(f"cannot encode {self.qualname} = {_fmt(x)} {self.unit}: {what} "
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


def _fmt(x: float) -> str:
    return f"{float(x):.6g}"


def _crc_powers() -> U8:
    """T, T^2, ..., T^8 of the CRC table T (:data:`canrls.can.e2e.CRC8_TABLE`), rows of a
    (8, 256) array: the C loops look bytes up in parallel (``src/canrls/c/can.c``)."""
    powers = np.empty((8, 256), np.uint8)
    powers[0] = CRC8_TABLE
    for k in range(1, 8):
        powers[k] = CRC8_TABLE[powers[k - 1]]
    x = np.arange(256)
    bits = [CRC8_TABLE[x & (1 << b)] for b in range(8)]
    if not (np.bitwise_xor.reduce(bits) == CRC8_TABLE).all():  # pragma: no cover
        raise AssertionError("the CRC table is not linear")
    return powers


#: :func:`_crc_powers`, computed once
_CRC8_POWERS = _crc_powers()


def _crc_vector(frame_id: int, data: U8, length: int) -> U8:
    """E2E CRC (:func:`canrls.can.e2e.e2e_crc`) of every row: over the ID, then bytes
    1..length-1."""
    out = np.empty(data.shape[0], np.uint8)
    d = np.ascontiguousarray(data, np.uint8)
    _can.crc8(int(frame_id), d, d.shape[1], int(length), _CRC8_POWERS, out)
    return out


@dataclass(frozen=True)
class RoleInfo:
    """A resolved role: its signal codec and the factor from the DBC unit to SI."""

    role: str
    codec: SignalCodec
    si_scale: float
    unit: str

    @property
    def message(self) -> str:
        return self.codec.message

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


# ---------------------------------------------------------------------------
# Protocol
# ---------------------------------------------------------------------------


def load_dbc(path: str | Path, what: str | None = None) -> tuple[Any, bytes]:
    """The cantools database of the DBC at ``path`` (strict) and the file's bytes.

    The one DBC reader of canrls: a regular file of at most
    :data:`~canrls.files.MAX_DBC_BYTES`, whose every message fits a CAN frame
    (:data:`MAX_MESSAGE_BYTES`) and every signal its message, checked on cantools'
    tokens before cantools builds anything (its strict check is quadratic in a start
    bit, its codec linear in a length); then every signal's scale, offset and limits
    must be finite numbers, the scale not zero, and the physical range of its raw
    integers finite. Errors (:class:`ConfigError`) name the file, message and signal.
    """
    p = Path(path)
    where = what or f"DBC file {p}"
    raw = read_bytes(p, where, limit=MAX_DBC_BYTES)
    try:
        text = raw.decode("cp1252")  # cantools' encoding of DBC files
    except UnicodeDecodeError as e:
        line = raw.count(b"\n", 0, e.start) + 1
        raise ConfigError(f"cannot parse {where}: byte 0x{raw[e.start]:02x} at line "
                          f"{line} is not cp1252 text") from e
    from cantools.database.can.formats.dbc.dbc_loader import DbcParser

    try:
        tokens = DbcParser().parse(text)
    except Exception as e:  # textparser's errors say where
        raise ConfigError(f"cannot parse {where}: {e}") from e
    _check_layout(tokens, where)
    try:
        db = cantools.database.load_string(text, database_format="dbc", strict=True)
    except Exception as e:  # cantools raises several parse error types
        raise ConfigError(f"cannot parse {where}: {e}") from e
    for m in db.messages:
        for sig in m.signals:
            _check_numbers(sig, f"{where}: message {m.name}: signal {sig.name}")
    return db, raw


def _check_layout(tokens: Any, where: str) -> None:
    """Every message at most :data:`MAX_MESSAGE_BYTES` long, every signal's start bit
    and length within its message (what cantools will then check exactly)."""
    for msg in tokens.get("BO_", []) if isinstance(tokens, Mapping) else []:
        try:
            name, length = str(msg[2]), int(msg[4], 0)
        except (IndexError, TypeError, ValueError):
            continue  # cantools says what is wrong
        if not 0 <= length <= MAX_MESSAGE_BYTES:
            raise ConfigError(f"{where}: message {name}: {length} bytes long, a CAN frame "
                              f"carries at most {MAX_MESSAGE_BYTES}")
        bits = 8 * length
        for sig in msg[6] if len(msg) > 6 and isinstance(msg[6], list) else []:
            try:
                sname = str(sig[1][0])
                start, n = int(sig[3]), int(sig[5])
            except (IndexError, TypeError, ValueError):
                continue
            if not (0 <= start < max(bits, 1) and 1 <= n <= bits):
                raise ConfigError(f"{where}: message {name}: signal {sname}: start bit "
                                  f"{start} and length {n} do not fit the message's "
                                  f"{length} bytes")


def _check_numbers(sig: Any, where: str) -> None:
    """Scale, offset and limits finite, the scale not zero, and the physical range of the
    raw integers finite (a scale of 1e308 on 16 bits is not)."""
    conv = sig.conversion
    for name, v in (("scale", conv.scale), ("offset", conv.offset),
                    ("minimum", sig.minimum), ("maximum", sig.maximum)):
        if v is None and name in ("minimum", "maximum"):
            continue
        try:
            ok = math.isfinite(float(v))
        except (TypeError, ValueError, OverflowError):
            ok = False
        if not ok:
            raise ConfigError(f"{where}: {name} {v!r} is not a finite number")
    if float(conv.scale) == 0.0:
        raise ConfigError(f"{where}: scale 0: every raw value would decode to the offset")
    if not sig.is_float:
        lo = -(1 << (sig.length - 1)) if sig.is_signed else 0
        hi = (1 << (sig.length - 1)) - 1 if sig.is_signed else (1 << sig.length) - 1
        try:
            ends = (lo * float(conv.scale) + float(conv.offset),
                    hi * float(conv.scale) + float(conv.offset))
        except OverflowError:
            ends = (math.inf, math.inf)
        if not all(math.isfinite(x) for x in ends):
            raise ConfigError(f"{where}: scale {float(conv.scale):g} and offset "
                              f"{float(conv.offset):g} put the raw values {lo}..{hi} beyond "
                              f"the range of a double")


@functools.cache
def _default_hash() -> str:
    return hashlib.sha256(DEFAULT_DBC.read_bytes()).hexdigest()


class Protocol:
    """A loaded DBC with its signal mapping and the compiled codec of each mapped message.

    Build it with :meth:`load`. Attributes: ``db`` (the cantools database),
    ``dbc_path``, ``is_default_dbc``, ``mapping``, ``roles`` (role ->
    :class:`RoleInfo`), ``messages`` (the mapped :class:`MessageCodec`, the current's
    message first (else the torque's), then the speed's, position's and voltage's),
    ``strict_range``, ``check_crc``, ``check_counter``, ``period_source`` (who states
    :attr:`period`: the configuration's name for it, ``"the DBC's GenMsgCycleTime"``,
    or None).
    """

    period_source: str | None = None

    def __init__(self, db: Any, dbc_path: Path, is_default_dbc: bool, mapping: SignalMapping,
                 roles: dict[str, RoleInfo], messages: tuple[MessageCodec, ...], *,
                 strict_range: bool, check_crc: bool, check_counter: bool) -> None:
        self.db = db
        self.dbc_path = dbc_path
        self.is_default_dbc = is_default_dbc
        self.mapping = mapping
        self.roles = roles
        self.messages = messages
        self.strict_range = strict_range
        self.check_crc = check_crc
        self.check_counter = check_counter

    def __repr__(self) -> str:
        roles = ", ".join(f"{r}={i.message}.{i.signal}" for r, i in self.roles.items())
        return f"Protocol({self.dbc_path.name}: {roles})"

    @staticmethod
    def load(dbc: str | Path | None = None,
             mapping: SignalMapping | Mapping[str, Any] | Sequence[str] | None = None, *,
             strict_range: bool = True, check_crc: bool = True, check_counter: bool = True,
             period: float | None = None, period_source: str = "the configured period",
             axis: str | None = None) -> Protocol:
        """Load a DBC (default: the one shipped with canrls) and resolve a signal mapping.

        Parameters
        ----------
        dbc : path of the DBC file, or ``None`` for the default DBC.
        mapping : a :class:`SignalMapping`, a config table (see
            :meth:`SignalMapping.from_config`), a sequence of ``ROLE=MESSAGE.SIGNAL``
            strings, or ``None`` for the default mapping.
        strict_range, check_crc, check_counter : named opt-outs of the strict checks.
        period : control period [s] of the feedback messages, overriding their
            ``GenMsgCycleTime``; ``period_source`` names it in messages (``"--period"``).
        axis : ``"linear"`` when an increment (``inc``, ``inc/s``) is a fraction of a
            metre (default: of a revolution).

        Raises
        ------
        ConfigError
            The DBC cannot be read or parsed, or the mapping is malformed.
        SignalError
            The DBC lacks a mapped message or signal, or a unit cannot be converted.
        """
        path = DEFAULT_DBC if dbc is None else Path(dbc)
        db, raw = load_dbc(path)
        is_default = hashlib.sha256(raw).hexdigest() == _default_hash()
        if mapping is None:
            mp = SignalMapping.default()
        elif isinstance(mapping, SignalMapping):
            mp = mapping
        elif isinstance(mapping, Mapping):
            mp = SignalMapping.from_config(mapping)
        elif isinstance(mapping, Sequence) and not isinstance(mapping, (str, bytes)):
            mp = SignalMapping.from_strings(mapping)
        else:
            raise ConfigError(f"signal mapping must be a SignalMapping, a table or a list of "
                              f"ROLE=MESSAGE.SIGNAL strings, got {type(mapping).__name__}")
        if period is not None and not (math.isfinite(period) and period > 0):
            raise ConfigError(f"period must be a positive number of seconds, got {period!r}")
        roles, messages = _resolve(db, path, is_default, mp, period, axis)
        proto = Protocol(db, path, is_default, mp, roles, messages, strict_range=strict_range,
                         check_crc=check_crc, check_counter=check_counter)
        if period is not None:
            proto.period_source = period_source
        elif proto.period is not None:
            proto.period_source = f"the GenMsgCycleTime of DBC {path.name}"
        return proto

    def has(self, role: str) -> bool:
        """True when ``role`` is mapped."""
        return role in self.roles

    def signal_range(self, role: str) -> tuple[float, float] | None:
        """The range ``(lo, hi)`` in SI units that a decoded ``role`` value cannot leave:
        the DBC's [minimum, maximum] under strict decoding, else (and where the DBC gives
        none) what the signal's raw integers can represent; None for a float signal
        without both limits."""
        info = self.roles[role]
        c = info.codec
        if c.is_float:
            if not (self.strict_range and c.minimum is not None and c.maximum is not None):
                return None
            a, b = float(c.minimum), float(c.maximum)
        else:
            a, b = c.raw_min * c.scale + c.offset, c.raw_max * c.scale + c.offset
        lo, hi = min(a, b), max(a, b)
        if self.strict_range:
            lo = lo if c.minimum is None else max(lo, float(c.minimum))
            hi = hi if c.maximum is None else min(hi, float(c.maximum))
        a, b = lo * info.si_scale, hi * info.si_scale
        return (min(a, b), max(a, b))

    def message(self, name: str) -> MessageCodec:
        """The mapped message ``name``."""
        for m in self.messages:
            if m.name == name:
                return m
        raise KeyError(name)

    def message_of(self, role: str) -> MessageCodec:
        """The mapped message carrying ``role``."""
        return self.message(self.roles[role].message)

    @property
    def period(self) -> float | None:
        """Control period [s]: the smallest cycle time of the mapped messages (None: unknown)."""
        ts = [m.cycle_time for m in self.messages if m.cycle_time]
        return min(ts) if ts else None

    @property
    def axis(self) -> str | None:
        """``"rotary"`` or ``"linear"`` from the DBC units of the speed and position
        signals (:func:`~canrls.can.units.axis_of`); None when the units do not say."""
        for role in ("speed", "position"):
            if role in self.roles and (ax := axis_of(self.roles[role].unit)) is not None:
                return ax
        return None

    def decoder(self) -> Decoder:
        """A new stateful strict decoder (counters carried across blocks)."""
        return Decoder(self)

    def encoder(self, **kwargs: Any) -> FeedbackEncoder:
        """A new :class:`FeedbackEncoder` (keyword arguments passed on)."""
        return FeedbackEncoder(self, **kwargs)


def _resolve(db: Any, path: Path, is_default: bool, mp: SignalMapping,
             period: float | None, axis: str | None = None
             ) -> tuple[dict[str, RoleInfo], tuple[MessageCodec, ...]]:
    where = f"DBC {path}"
    names = {m.name for m in db.messages}
    roles: dict[str, RoleInfo] = {}
    for role in ROLES:
        spec = mp.roles.get(role)
        if spec is None:
            continue
        if spec.message not in names:
            if spec.optional:
                continue
            raise SignalError(f"{where} has no message {spec.message!r} (mapped to {role} = "
                              f"{spec}); its messages are {', '.join(sorted(names))}")
        msg = db.get_message_by_name(spec.message)
        sigs = {s.name: s for s in msg.signals}
        if spec.signal not in sigs:
            if spec.optional:
                continue
            raise SignalError(f"{where}: message {spec.message} has no signal {spec.signal!r} "
                              f"(mapped to {role}); its signals are {', '.join(sigs)}")
        sig = sigs[spec.signal]
        if sig.multiplexer_ids or sig.is_multiplexer:
            raise SignalError(f"{where}: {spec} is multiplexed; canrls maps plain signals only")
        if msg.is_container:
            raise SignalError(f"{where}: message {spec.message} is a container message")
        codec = SignalCodec(sig, msg.name)
        unit = spec.unit if spec.unit is not None else (sig.unit or "")
        factor = si_factor(role, unit, message=msg.name, signal=sig.name, scale=spec.scale,
                           ratings=mp.ratings, axis=axis)
        roles[role] = RoleInfo(role, codec, factor, unit)
    if not any(r in roles for r in EFFORT_ROLES):
        raise SignalError(f"signal mapping for {where} lacks the required role current "
                          f"(give current=MESSAGE.SIGNAL, or torque=MESSAGE.SIGNAL for a "
                          f"drive that reports its torque)")
    for role in REQUIRED_ROLES:
        if role not in roles:
            raise SignalError(f"signal mapping for {where} lacks the required role {role} "
                              f"(give {role}=MESSAGE.SIGNAL)")
    if "position" in roles:
        ax_s, ax_p = axis_of(roles["speed"].unit), axis_of(roles["position"].unit)
        if ax_s and ax_p and ax_s != ax_p:
            raise SignalError(f"{where}: speed {roles['speed'].message}.{roles['speed'].signal} "
                              f"is {ax_s} ({roles['speed'].unit}) but position "
                              f"{roles['position'].message}.{roles['position'].signal} is "
                              f"{ax_p} ({roles['position'].unit})")

    # the messages in the order of their roles: the current's (else the torque's) first
    order = ("current", "torque", "speed", "position", "voltage")
    mapped = list(dict.fromkeys(roles[r].message for r in order if r in roles))
    for table, kind in ((mp.counters, "counter"), (mp.crcs, "CRC")):
        for mname in table:
            if mname not in mapped:
                raise ConfigError(f"{kind} configured for message {mname!r}, which no role "
                                  f"maps (mapped: {', '.join(mapped)})")
    messages = []
    for mname in mapped:
        msg = db.get_message_by_name(mname)
        sigs = {s.name: s for s in msg.signals}
        role_signals = {r.signal for r in roles.values() if r.message == mname}

        auto = is_default
        counter = _e2e_signal(where, mname, sigs, role_signals, mp.counters, "Counter" if auto
                              else None, "counter")
        crc = _e2e_signal(where, mname, sigs, role_signals, mp.crcs, "CRC" if auto else None,
                          "CRC")
        if counter is not None and crc is not None and counter.byte_index == (0,):
            raise SignalError(f"{where}: counter {mname}.{counter.name} overlaps the CRC byte")
        cycle = period if period is not None else (
            msg.cycle_time / 1000.0 if msg.cycle_time else None)
        messages.append(MessageCodec(
            name=mname, frame_id=int(msg.frame_id), is_extended=bool(msg.is_extended_frame),
            length=int(msg.length), cycle_time=cycle,
            roles=tuple(r for r in roles.values() if r.message == mname),
            counter=counter, crc=crc, message=msg))
    return roles, tuple(messages)


def _e2e_signal(where: str, mname: str, sigs: Mapping[str, Any], role_signals: set[str],
                table: Mapping[str, str | None], auto: str | None, kind: str
                ) -> SignalCodec | None:
    """The counter or CRC codec of message ``mname``: as configured, else auto-detected by name."""
    if mname in table:
        sname = table[mname]
    else:
        sname = auto if auto in sigs else None
    if sname is None:
        return None
    if sname not in sigs:
        raise SignalError(f"{where}: message {mname} has no {kind} signal {sname!r}; "
                          f"its signals are {', '.join(sigs)}")
    if sname in role_signals:
        raise SignalError(f"{where}: {mname}.{sname} is mapped to a role and cannot "
                          f"also be the {kind}")
    c = SignalCodec(sigs[sname], mname)
    if c.is_float or c.is_signed or c.scale != 1 or c.offset != 0:
        raise SignalError(f"{where}: {kind} {mname}.{sname} must be an unsigned integer "
                          f"with scale 1 and offset 0")
    if kind == "CRC" and (c.length != 8 or c.byte_index != (0,) or c.shift != 0):
        raise SignalError(f"{where}: CRC {mname}.{sname} must be the 8 bits of byte 0 "
                          f"(E2E profile 1 layout, see canrls.can.e2e)")
    return c


# ---------------------------------------------------------------------------
# Decoding
# ---------------------------------------------------------------------------


class RejectCounts(Mapping[str, int]):
    """Rejected frames: a mapping reason -> count (every reason of :data:`REJECT_REASONS`).

    ``per_message[name][reason]`` splits the counts by message (error frames, which
    belong to no message, are filed under ``"*"``); ``examples[reason]`` keeps the
    earliest (in stream order) human-readable example of each reason, e.g.
    ``"DriveSpeed.Speed = 830.5 rad/s outside [-800, 800] (t=1.234000 s)"``.
    """

    def __init__(self) -> None:
        self._counts: dict[str, int] = _NO_REJECTS.copy()
        self.per_message: dict[str, dict[str, int]] = {}
        self.examples: dict[str, str] = {}
        self._example_key: dict[str, int] = {}

    def __getitem__(self, reason: str) -> int:
        return self._counts[reason]

    def __iter__(self) -> Iterator[str]:
        return iter(self._counts)

    def __len__(self) -> int:
        return len(self._counts)

    @property
    def total(self) -> int:
        return sum(self._counts.values())

    def add(self, reason: str, message: str, n: int = 1, example: str | None = None,
            key: int = 0) -> None:
        """Count ``n`` rejections; ``example`` is kept if it is the earliest (smallest ``key``)."""
        if n <= 0:
            return
        self._counts[reason] += n
        per = self.per_message.setdefault(message, dict.fromkeys(REJECT_REASONS, 0))
        per[reason] += n
        if example is not None and self.wants_example(reason, key):
            self.examples[reason] = example
            self._example_key[reason] = key

    def wants_example(self, reason: str, key: int) -> bool:
        """True when an example of ``reason`` at position ``key`` would replace the kept one."""
        return reason not in self._example_key or key < self._example_key[reason]

    def merge(self, other: RejectCounts) -> None:
        """Add ``other``'s counts (and its examples where they come earlier) into this one."""
        for msg, per in other.per_message.items():
            for reason, n in per.items():
                self.add(reason, msg, n)
        for reason, ex in other.examples.items():
            key = other._example_key[reason]
            if self.wants_example(reason, key):
                self.examples[reason] = ex
                self._example_key[reason] = key

    def summary(self) -> str:
        """One line per reason with a non-zero count, with its example."""
        lines = []
        for r in REJECT_REASONS:
            if self._counts[r]:
                ex = self.examples.get(r)
                lines.append(f"{r}: {self._counts[r]}" + (f"  e.g. {ex}" if ex else ""))
        return "\n".join(lines)

    def __repr__(self) -> str:
        nz = {r: n for r, n in self._counts.items() if n}
        return f"RejectCounts({nz})"


@dataclass(frozen=True, init=False)
class MessageFrames:
    """The accepted frames of one mapped message in a block.

    ``index`` is each frame's position in the whole stream (0-based, across blocks),
    ``counter`` the raw alive counter (0 .. ``counter_modulo``-1) or, when the message
    has none, a running sequence number of its accepted frames (``counter_modulo`` is
    then ``None``); ``values`` maps each role of the message to SI values.
    """

    name: str
    t: F64
    index: I64
    counter: I64
    values: dict[str, F64]
    counter_modulo: int | None

    def __init__(self, name: str, t: F64, index: I64, counter: I64, values: dict[str, F64],
                 counter_modulo: int | None) -> None:
        # the fields go straight into the instance dict: a frozen dataclass's own
        # __init__ sets each through object.__setattr__, microseconds per live block
        d = self.__dict__
        d["name"], d["t"], d["index"], d["counter"] = name, t, index, counter
        d["values"], d["counter_modulo"] = values, counter_modulo

    def __len__(self) -> int:
        return len(self.t)


@dataclass(frozen=True, init=False)
class DecodedFrames:
    """Result of decoding one block: the accepted frames of each mapped message and the counts.

    ``rejected`` and ``lost`` (message -> frames missing according to the counter) and
    ``foreign`` (frames of other IDs, ignored) count this block only; the
    :class:`Decoder` keeps running totals.
    """

    messages: dict[str, MessageFrames]
    rejected: RejectCounts
    lost: dict[str, int]
    foreign: int

    def __init__(self, messages: dict[str, MessageFrames], rejected: RejectCounts,
                 lost: dict[str, int], foreign: int) -> None:
        d = self.__dict__  # as MessageFrames.__init__
        d["messages"], d["rejected"], d["lost"], d["foreign"] = messages, rejected, lost, foreign

    def __getitem__(self, name: str) -> MessageFrames:
        return self.messages[name]

    def __iter__(self) -> Iterator[MessageFrames]:
        return iter(self.messages.values())

    @property
    def accepted(self) -> int:
        return sum(len(m) for m in self.messages.values())


_STATUS_OK, _STATUS_REPEATED, _STATUS_STALE, _STATUS_SEQUENCE = 0, 1, 2, 3

#: columns of the counter state of one message (:func:`_counter_kernel`), then the
#: running sequence number of a message without counter (``Decoder._counters``)
_ST_COUNTER_COLS, _ST_COLS = 5, 6


def _counter_kernel(c: I64, t: F64, mod: int, window: int, period: float,
                    state: I64, state_t: F64, skip: npt.NDArray[np.bool_] | None = None,
                    ) -> tuple[npt.NDArray[np.int8], I64]:
    """Classify alive counters one frame at a time (``counter_step`` in
    ``src/canrls/c/can.c``), carrying state across blocks: state = [last counter (-1:
    none yet), run, counter of the last frame of the run, skipped, trusted]; state_t =
    [time of the last accepted frame]. Returns the status and the frames lost before
    each frame. Frames marked in ``skip`` (rejected before the counter check: length,
    CRC) are received but not classified (status 0, lost 0): they count as skipped.

    Per frame, counter ``c`` received at ``t``: d = (c - last) mod M; with dt the time
    since the last accepted frame and T the period (0: none),

    * d == 0 is ``repeated``, unless dt >= (M - 0.5) T (the counter went round);
    * d >= M - window is ``stale`` (a jump backwards), unless dt >= (d - 0.5) T;
    * 2 <= d < M - window is ``sequence`` (a wrong counter, not a loss: the AUTOSAR E2E
      receiver's wrong sequence) when the time says fewer periods passed, dt < (d -
      0.5) T, and the last accepted frame's time agreed with its counter (``trusted``:
      |dt - gap T| < T / 2 when it was accepted; a frame swapped with its neighbour
      arrives a period late and says nothing of the next one's time);
    * otherwise the frame is accepted: gap = d, plus k M when the time implies k =
      floor((dt / T - d) / M + 0.5) > 0 whole wraps and agrees with them, |dt / T - d -
      k M| < 1/2 (only for dt up to 1 s, :data:`canrls.can.pairing.FORWARD_STEP`: a
      longer jump is a clock step or a silence as long, and the time says nothing of the
      frames lost in it; a shorter one off the wraps by more is a clock step too), and
      ``lost = max(0, gap - 1 - skipped)``: the frames of the message rejected since the
      last accepted one (``skipped``: stale, sequence, repeated half a period or more
      after the frame it repeats (with a period; a copy arriving with it takes no place
      in the sequence), and those marked in ``skip``) were received, not lost.

    A rejected frame leaves the state as it was, so the next good frame continues the
    sequence of the last accepted one: one wrong counter costs one frame. ``run``
    counts consecutive frames rejected for their counter that count up by one: a
    ``sequence`` frame that continues the one before it is accepted (the jump was a
    loss after all: timestamps bunched by the receiver), three ``stale`` ones
    resynchronise (loss unknown). Without a period, a forward jump is always a loss.
    """
    n = len(c)
    status = np.empty(n, np.uint8)
    lost = np.empty(n, np.int64)
    st = np.ascontiguousarray(state, np.int64)
    st_t = np.ascontiguousarray(state_t, np.float64)
    _can.counters(np.ascontiguousarray(c, np.int64), np.ascontiguousarray(t, np.float64),
                  int(mod), int(window), float(period), st, st_t, status, lost,
                  None if skip is None else np.ascontiguousarray(skip, np.bool_))
    if st is not state:
        state[:] = st
    if st_t is not state_t:
        state_t[:] = st_t
    return status.view(np.int8), lost


def _select_rows(arbitration_id: npt.NDArray[np.uint32], is_extended: npt.NDArray[np.bool_],
                 is_error: npt.NDArray[np.bool_], frame_id: int, extended: bool,
                 mine: npt.NDArray[np.bool_]) -> npt.NDArray[np.intp]:
    """Rows with this ID and format that are not error frames (marked in ``mine``)."""
    rows = (arbitration_id == frame_id) & (is_extended == extended) & ~is_error
    mine |= rows
    return np.flatnonzero(rows)


def _gather_check(data: U8, rows: npt.NDArray[np.intp], length: int,
                  is_remote: npt.NDArray[np.bool_], dlc: U8, check_crc: bool, frame_id: int,
                  powers: U8, out: U8, flags: U8) -> int:
    """Copy ``data[rows, :length]`` into ``out``; flag the first check each row fails:
    1 remote, 2 length (DLC), 4 CRC (only when ``check_crc``). Returns the flagged rows.
    """
    c = np.ascontiguousarray  # a no-op for the arrays of a FrameBlock
    d = c(data, np.uint8)
    return int(_can.gather_check(d, d.shape[1], c(rows, np.int64), length,
                                 c(is_remote, np.bool_), c(dlc, np.uint8), check_crc,
                                 frame_id, powers, out, flags))


def _counter_params(m: MessageCodec) -> tuple[int, int, float]:
    """Counter modulo M, stale window (half the range, less one) and period [s] (0: none)
    that :func:`_counter_kernel` takes for message ``m`` (which has a counter)."""
    modulo = int(m.counter_modulo or 0)
    return modulo, max(1, modulo // 2 - 1), float(m.cycle_time or 0.0)


# columns of _FastPlan.msg, one row per message
(_M_ID, _M_EXT, _M_LEN, _M_CRC, _M_CHECK, _M_MOD, _M_WINDOW, _M_COUNTER, _M_SIG0, _M_SIG1,
 _M_TROW, _M_COLS) = range(12)
# columns of _FastPlan.sig, one row per signal (the roles, then the counters): where the
# field is (bit _S_POS of the 64-bit little-endian word of payload bytes 0..7, or of the
# big-endian one when _S_BE), how it scales (SignalCodec.scaling) and the row of its SI
# values in the float output
(_S_SIGNED, _S_FLOAT, _S_MODE, _S_LEN, _S_BE, _S_POS, _S_SCALE, _S_OFFSET, _S_ROW,
 _S_COLS) = range(10)
# columns of _FastPlan.sig_f: float scale and offset, range limits in the DBC unit, SI factor
_F_SCALE, _F_OFFSET, _F_LO, _F_HI, _F_SI, _F_COLS = range(6)


class _NoFastPath(Exception):
    """A mapped signal that :func:`_fast_kernel` cannot decode (see :meth:`_FastPlan.build`)."""


class _FastPlan:
    """The constants of :func:`_fast_kernel` for one protocol and its options.

    ``msg`` / ``sig`` / ``sig_f`` are the packed message and signal tables (columns
    ``_M_*``, ``_S_*``, ``_F_*``); ``period`` the counters' periods [s]. The kernel
    writes, per message k, the times to row ``layout[k][1]`` of its float output and
    the SI values of the roles ``layout[k][2]`` to the rows after it, the stream indices
    and the counters to rows 2k and 2k + 1 of its integer output; ``counts`` receives
    the frames accepted (K) and lost (K) of each message, then the foreign frames.
    Build with :meth:`build`.

    The kernel takes each field from the 64-bit words of payload bytes 0..7 (one shift
    and mask, much faster in the frame loop than :meth:`SignalCodec.extract`'s byte loop): a
    field beyond byte 7 (CAN FD) leaves the protocol to the careful path.
    """

    __slots__ = ("options", "msg", "period", "sig", "sig_f", "n_float", "layout", "counts",
                 "out_f", "out_i")

    def __init__(self, p: Protocol) -> None:
        self.options = (p.strict_range, p.check_crc, p.check_counter)
        K = len(p.messages)
        roles = [r for m in p.messages for r in m.roles]
        counters = [m.counter for m in p.messages if m.counter is not None]
        self.msg = np.full((K, _M_COLS), -1, np.int64)
        self.period = np.zeros(K, np.float64)
        self.sig = np.zeros((len(roles) + len(counters), _S_COLS), np.int64)
        self.sig_f = np.zeros((len(roles), _F_COLS), np.float64)
        layout = []
        s, q, row = 0, len(roles), 0
        for k, m in enumerate(p.messages):
            mk = self.msg[k]
            mk[_M_ID], mk[_M_EXT], mk[_M_LEN] = m.frame_id, m.is_extended, m.length
            mk[_M_CRC], mk[_M_CHECK] = m.crc is not None and p.check_crc, p.check_counter
            if m.counter is not None:
                mk[_M_MOD], mk[_M_WINDOW], self.period[k] = _counter_params(m)
                mk[_M_COUNTER] = q
                self._locate(q, m.counter)
                q += 1
            mk[_M_SIG0], mk[_M_SIG1], mk[_M_TROW] = s, s + len(m.roles), row
            for r in m.roles:
                row += 1
                self._locate(s, r.codec)
                self._scaling(s, r, p.strict_range)
                self.sig[s, _S_ROW] = row
                s += 1
            row += 1
            layout.append((m.name, int(mk[_M_TROW]), tuple(r.role for r in m.roles),
                           m.counter_modulo))
        self.n_float = row
        self.layout: tuple[tuple[str, int, tuple[str, ...], int | None], ...] = tuple(layout)
        self.counts = np.zeros(2 * K + 1, np.int64)
        self.out_f = np.empty((self.n_float, 0), np.float64)
        self.out_i = np.empty((2 * K, 0), np.int64)

    def outputs(self, n: int) -> tuple[F64, I64]:
        """The kernel's float and integer outputs for ``n`` frames: kept between blocks and
        grown as needed (fresh large arrays on every block cost page faults)."""
        if self.out_f.shape[1] < n:
            cols = max(n, self.out_f.shape[1] * 3 // 2)
            self.out_f = np.empty((self.n_float, cols), np.float64)
            self.out_i = np.empty((self.out_i.shape[0], cols), np.int64)
        return self.out_f, self.out_i

    def _locate(self, s: int, c: SignalCodec) -> None:
        """Row ``s`` of ``sig``: where the field of ``c`` lies in the payload words."""
        if max(c.byte_index) > 7:
            raise _NoFastPath(c.qualname)
        row = self.sig[s]
        row[_S_SIGNED], row[_S_FLOAT], row[_S_LEN] = c.is_signed, c.is_float, c.length
        # raw bit b is bit (b + shift) % 8 of byte byte_index[(b + shift) // 8] (SignalCodec):
        # ascending bytes (little endian) or descending (big endian) from byte_index[0]
        row[_S_BE] = c.byte_order != "little_endian"
        row[_S_POS] = 8 * (7 - c.byte_index[0] if row[_S_BE] else c.byte_index[0]) + c.shift

    def _scaling(self, s: int, r: RoleInfo, strict_range: bool) -> None:
        """Rows ``s`` of ``sig`` and ``sig_f``: how role ``r`` scales, its range check."""
        c = r.codec
        scaling = c.scaling()
        if scaling is None:
            raise _NoFastPath(c.qualname)
        mode, scale, offset = scaling
        self.sig[s, _S_MODE] = mode
        if mode == _PHYS_INT:
            self.sig[s, _S_SCALE], self.sig[s, _S_OFFSET] = scale, offset
        else:
            self.sig_f[s, _F_SCALE], self.sig_f[s, _F_OFFSET] = scale, offset
        # the bounds SignalCodec.out_of_range compares with
        on_min = strict_range and c.minimum is not None
        on_max = strict_range and c.maximum is not None
        self.sig_f[s, _F_LO] = c.minimum - c.tol if on_min else -np.inf
        self.sig_f[s, _F_HI] = c.maximum + c.tol if on_max else np.inf
        self.sig_f[s, _F_SI] = r.si_scale

    @staticmethod
    def build(p: Protocol) -> _FastPlan | None:
        """The plan, or None when a mapped signal is beyond the kernel (a field beyond
        payload byte 7, a scaling :meth:`SignalCodec.scaling` declines)."""
        try:
            return _FastPlan(p)
        except _NoFastPath:
            return None


def _fast_kernel(t: F64, arbitration_id: npt.NDArray[np.uint32],
                 is_extended: npt.NDArray[np.bool_], is_remote: npt.NDArray[np.bool_],
                 is_error: npt.NDArray[np.bool_], dlc: U8, data: U8, msg: I64, period: F64,
                 sig: I64, sig_f: F64, powers: U8, state: I64, state_t: F64, base: int,
                 out_f: F64, out_i: I64, counts: I64) -> int:
    """Decode the frames of a block in one pass, up to the first that is not well-formed.

    Frames in stream order; a frame belongs to the message (row of ``msg``) with its ID
    and format. Per frame of a message: not remote, DLC = the message length, CRC
    (:func:`_crc_vector`), alive counter in sequence (:func:`_counter_kernel`), each role's
    physical value ``raw * scale + offset`` (as :meth:`SignalCodec.physical` computes it,
    see :meth:`SignalCodec.scaling`) finite and within [lo, hi]; then the time, stream
    index ``base + i``, counter (or running sequence number) and SI values ``physical *
    si_scale`` go to the outputs (see :class:`_FastPlan`). ``state`` = per message the
    counter state of :func:`_counter_kernel`, then the sequence number (``_ST_COLS``
    columns), ``state_t`` = [time of the last accepted frame].

    Stops at the first error frame or frame of a mapped message that fails a check, and
    returns the number of frames decoded: outputs, counts and state are those of the
    frames before it, and the caller decodes the rest the careful way.
    """
    c = np.ascontiguousarray  # a no-op for the arrays of a FrameBlock
    d = c(data, np.uint8)
    return int(_can.decode_fast(c(t, np.float64), c(arbitration_id, np.uint32),
                                c(is_extended, np.bool_), c(is_remote, np.bool_),
                                c(is_error, np.bool_), c(dlc, np.uint8), d, d.shape[1], msg,
                                period, sig, sig_f, powers, state, state_t, int(base), out_f,
                                out_i, counts))


class Decoder:
    """Stateful strict decoder of the mapped feedback messages (see :meth:`Protocol.decoder`).

    Running totals: ``rejected`` (:class:`RejectCounts`), ``lost`` (message -> frames
    missing by counter), ``accepted`` (message -> frames passed on), ``foreign``
    (frames of other IDs) and ``frames`` (all frames seen). Decoding is chunk-invariant:
    the alive-counter state is carried from block to block.
    """

    def __init__(self, protocol: Protocol) -> None:
        self.protocol = protocol
        self.rejected = RejectCounts()
        self.lost: dict[str, int] = {m.name: 0 for m in protocol.messages}
        self.accepted: dict[str, int] = {m.name: 0 for m in protocol.messages}
        self.foreign = 0
        self.frames = 0
        # per message: [last counter, run, last counter of the run, skipped, trusted] (see
        # _counter_kernel), then the running sequence number of a message without counter;
        # time of the last accepted frame. The careful path works on views of the rows.
        K = len(protocol.messages)
        self._counters = np.tile(np.array([-1, 0, -1, 0, 1, 0], np.int64), (K, 1))
        self._counters_t = np.zeros(K, np.float64)
        self._state = {m.name: (self._counters[k, :_ST_COUNTER_COLS],
                                self._counters_t[k:k + 1])
                       for k, m in enumerate(protocol.messages)}
        self._seq = {m.name: self._counters[k, _ST_COUNTER_COLS:]
                     for k, m in enumerate(protocol.messages)}
        self._plan = _FastPlan.build(protocol)

    def decode(self, block: FrameBlock) -> DecodedFrames:
        """Decode one block; rejected frames are counted and dropped, never passed on.

        The frames up to the first that is not well-formed (all of them, commonly) are
        decoded in one compiled pass (:func:`_fast_kernel`); the rest the careful way,
        check by check, which also names each rejection. Decoding being chunk-invariant,
        the result is that of the careful way on the whole block.
        """
        p = self.protocol
        n = len(block)
        base = self.frames
        self.frames += n
        plan = self._plan
        if plan is not None and plan.options != (p.strict_range, p.check_crc, p.check_counter):
            plan = self._plan = _FastPlan.build(p)
        if plan is None:
            return self._decode_careful(block, base)
        fast, done = self._decode_fast(plan, block, base)
        if done == n:
            return fast
        rest = self._decode_careful(block.take(slice(done, None)) if done else block,
                                    base + done)
        return _joined(fast, rest) if done else rest

    def _decode_careful(self, block: FrameBlock, base: int) -> DecodedFrames:
        """Decode a block check by check (the frames numbered from ``base`` in the stream)."""
        p = self.protocol
        n = len(block)
        rej = RejectCounts()
        err = block.is_error
        n_err = int(err.sum())
        if n_err:
            k = int(np.flatnonzero(err)[0])
            rej.add("error_frame", "*", n_err, f"error frame at t={block.t[k]:.6f} s", base + k)
        mine = np.zeros(n, np.bool_)
        out: dict[str, MessageFrames] = {}
        lost_block: dict[str, int] = {}
        for m in p.messages:
            # rows of this message: its ID and format, not an error frame (mine |= them)
            rows = _select_rows(block.arbitration_id, block.is_extended, err, int(m.frame_id),
                                bool(m.is_extended), mine)
            frames, lost = self._decode_message(m, block, rows, base, rej)
            out[m.name] = frames
            lost_block[m.name] = lost
            self.lost[m.name] += lost
            self.accepted[m.name] += len(frames)
        foreign = int(n - n_err - mine.sum())
        self.foreign += foreign
        self.rejected.merge(rej)
        return DecodedFrames(out, rej, lost_block, foreign)

    def _decode_fast(self, plan: _FastPlan, block: FrameBlock,
                     base: int) -> tuple[DecodedFrames, int]:
        """:func:`_fast_kernel` on the block: the decoded frames (counted in the running
        totals) and how many of the block's frames they cover."""
        out_f, out_i = plan.outputs(len(block))
        done = _fast_kernel(block.t, block.arbitration_id, block.is_extended, block.is_remote,
                            block.is_error, block.dlc, block.data, plan.msg, plan.period,
                            plan.sig, plan.sig_f, _CRC8_POWERS, self._counters, self._counters_t,
                            base, out_f, out_i, plan.counts)
        counts = plan.counts.tolist()
        K = len(plan.layout)
        out: dict[str, MessageFrames] = {}
        lost: dict[str, int] = {}
        for k, (name, t_row, roles, modulo) in enumerate(plan.layout):
            c = counts[k]
            f = out_f[t_row:t_row + 1 + len(roles), :c].copy()  # times, then the roles
            i = out_i[2 * k:2 * k + 2, :c].copy()  # stream indices, counters
            out[name] = MessageFrames(name, f[0], i[0], i[1],
                                      {role: f[1 + j] for j, role in enumerate(roles)}, modulo)
            lost[name] = counts[K + k]
            self.lost[name] += counts[K + k]
            self.accepted[name] += c
        foreign = counts[2 * K]
        self.foreign += foreign
        return DecodedFrames(out, RejectCounts(), lost, foreign), done

    def _decode_message(self, m: MessageCodec, block: FrameBlock, rows: npt.NDArray[np.intp],
                        base: int, rej: RejectCounts) -> tuple[MessageFrames, int]:
        p = self.protocol
        t = block.t[rows]
        reason = np.zeros(len(rows), np.int8)

        def reject(mask: npt.NDArray[np.bool_], name: str, example: Any) -> None:
            mask = mask & (reason == 0)
            if mask.any():
                k = int(np.flatnonzero(mask)[0])
                reason[mask] = _R[name]
                key = base + int(rows[k])
                want = self.rejected.wants_example(name, key) and rej.wants_example(name, key)
                rej.add(name, m.name, int(mask.sum()), example(k) if want else None, key)

        n_rows = len(rows)
        crc_on = m.crc is not None and p.check_crc
        if block.data.shape[1] >= m.length:
            # one compiled pass: payload bytes of every row, and the first of remote /
            # length / CRC that fails (flags 1, 2, 4; 0: passed)
            gathered = np.empty((n_rows, m.length), np.uint8)
            flags = np.empty(n_rows, np.uint8)
            n_bad = _gather_check(block.data, rows, m.length, block.is_remote, block.dlc,
                                  crc_on, int(m.frame_id), _CRC8_POWERS, gathered, flags)
        else:  # a block narrower than the message: the checks below, one by one
            gathered, flags, n_bad = None, None, n_rows
        # payload bytes of the rows still accepted; the rows only ever shrink, so the
        # same count means the same rows and the gathered bytes can be reused
        cache: list[Any] = [None, None]
        if n_bad == 0 and gathered is not None:
            cache = [np.arange(n_rows), gathered]

        def accepted() -> tuple[npt.NDArray[np.intp], U8]:
            ok = np.flatnonzero(reason == 0)
            if cache[0] is None or len(cache[0]) != len(ok):
                cache[0] = ok
                if not len(ok):
                    cache[1] = np.zeros((0, m.length), np.uint8)
                elif gathered is not None:
                    cache[1] = gathered[ok]
                else:
                    cache[1] = block.data[rows[ok], :m.length]
            return cache[0], cache[1]

        if n_bad:
            reject(block.is_remote[rows], "remote",
                   lambda k: f"{m.name}: remote frame (t={t[k]:.6f} s)")
            dlc = block.dlc[rows]
            reject(dlc != m.length, "length",
                   lambda k: f"{m.name}: {dlc[k]} bytes, expected {m.length} (t={t[k]:.6f} s)")
            ok, data = accepted()
            if crc_on and len(ok):
                if flags is not None:
                    bad = flags == 4
                else:
                    bad = np.zeros(len(rows), np.bool_)
                    bad[ok] = _crc_vector(m.frame_id, data, m.length) != data[:, 0]

                def crc_example(k: int) -> str:
                    good = int(_crc_vector(m.frame_id, block.data[rows[k:k + 1], :m.length],
                                           m.length)[0])
                    return (f"{m.name}: CRC 0x{block.data[rows[k], 0]:02X}, computed "
                            f"0x{good:02X} (t={t[k]:.6f} s)")

                reject(bad, "crc", crc_example)
        lost_total = 0
        counter_all = np.zeros(len(rows), np.int64)
        modulo = m.counter_modulo
        if m.counter is not None:
            ok, data = accepted()
            if len(ok):
                counter_all[ok] = m.counter.raw(data)
            # frames rejected for their length or CRC were received: not lost
            skip = (reason == _R["length"]) | (reason == _R["crc"])
            if p.check_counter and (len(ok) or skip.any()):
                state, state_t = self._state[m.name]
                before = int(state[0])
                # the accepted rows and those, in stream order (the accepted ones alone
                # when none was rejected so)
                sel = np.flatnonzero((reason == 0) | skip)
                status, lost = _counter_kernel(counter_all[sel], t[sel], *_counter_params(m),
                                               state, state_t, skip[sel])
                status = status[~skip[sel]]
                lost_total = int(lost.sum())

                def previous(k: int) -> int:
                    j = np.flatnonzero((ok < k) & (status == _STATUS_OK))
                    return int(counter_all[ok[j[-1]]]) if len(j) else before

                for code, name in ((_STATUS_REPEATED, "repeated"), (_STATUS_STALE, "stale"),
                                   (_STATUS_SEQUENCE, "sequence")):
                    if not status.any():
                        break
                    bad = np.zeros(len(rows), np.bool_)
                    bad[ok] = status == code
                    reject(bad, name, lambda k, name=name: (
                        f"{m.name}: counter {counter_all[k]} {name} after counter "
                        f"{previous(k)} (t={t[k]:.6f} s)"))
        # values of the mapped roles
        ok, data = accepted()
        phys: dict[str, F64] = {}
        for r in m.roles:
            phys[r.role] = r.codec.physical(data)
        for r in m.roles:
            v = phys[r.role]
            if r.codec.is_float:
                nan = ~np.isfinite(v)
                if not nan.any():
                    continue
                bad = np.zeros(len(rows), np.bool_)
                bad[ok] = nan
                reject(bad, "nan", lambda k, r=r: (
                    f"{r.codec.qualname} = {_phys_at(r.codec, block, rows, k, m.length)} "
                    f"{r.codec.unit} (t={t[k]:.6f} s)"))
        if p.strict_range:
            for r in m.roles:
                oor = r.codec.out_of_range(phys[r.role])
                if not oor.any():
                    continue
                bad = np.zeros(len(rows), np.bool_)
                bad[ok] = oor
                c = r.codec
                reject(bad, "range", lambda k, c=c: (
                    f"{c.qualname} = {_fmt(_phys_at(c, block, rows, k, m.length))} {c.unit} "
                    f"outside [{_fmt(c.minimum) if c.minimum is not None else '-inf'}, "
                    f"{_fmt(c.maximum) if c.maximum is not None else 'inf'}] (t={t[k]:.6f} s)"))
        keep_local = reason[ok] == 0
        if len(ok) == n_rows and keep_local.all():  # every row accepted
            keep = ok
            values = {r.role: phys[r.role] * r.si_scale for r in m.roles}
            t_keep = t
            counter = counter_all if modulo is not None else None
        else:
            keep = ok[keep_local]
            values = {r.role: phys[r.role][keep_local] * r.si_scale for r in m.roles}
            t_keep = t[keep]
            counter = counter_all[keep] if modulo is not None else None
        if counter is None:
            seq = self._seq[m.name]
            s0 = int(seq[0])
            counter = np.arange(s0, s0 + len(keep), dtype=np.int64)
            seq[0] = s0 + len(keep)
        index = (rows if len(keep) == n_rows else rows[keep]).astype(np.int64, copy=False) + base
        frames = MessageFrames(m.name, t_keep, index, counter, values, modulo)
        return frames, lost_total


def _joined(a: DecodedFrames, b: DecodedFrames) -> DecodedFrames:
    """Two consecutive parts of a block decoded as one; ``a`` has no rejections."""
    cat = np.concatenate
    out = {}
    for name, x in a.messages.items():
        y = b.messages[name]
        out[name] = MessageFrames(name, cat([x.t, y.t]), cat([x.index, y.index]),
                                  cat([x.counter, y.counter]),
                                  {r: cat([v, y.values[r]]) for r, v in x.values.items()},
                                  x.counter_modulo)
    return DecodedFrames(out, b.rejected, {k: v + b.lost[k] for k, v in a.lost.items()},
                         a.foreign + b.foreign)


def _phys_at(c: SignalCodec, block: FrameBlock, rows: npt.NDArray[np.intp], k: int,
             length: int) -> float:
    return float(c.physical(block.data[rows[k:k + 1], :length])[0])


# ---------------------------------------------------------------------------
# Encoding
# ---------------------------------------------------------------------------


class FeedbackEncoder:
    """Encode SI arrays into the mapped feedback frames (the inverse of :class:`Decoder`).

    One frame per mapped message and period, interleaved in the protocol's message
    order (the current's message first); every message of a period carries the same
    alive counter (mod its range), and the E2E CRC is computed as
    :func:`canrls.can.e2e.e2e_crc` does. Raw values are rounded to nearest (half to even,
    as cantools) and checked against the DBC range: out of range raises
    :class:`EncodeError` naming the signal and the value, unless ``clip=True``, which
    clips and counts in ``clipped`` (signal -> count).

    A position signal whose bit field spans exactly one turn (e.g. 16 bits of
    2*pi/65536 rad) is encoded modulo one turn, so unwrapped angles can be passed.

    Parameters
    ----------
    protocol : the :class:`Protocol` (its feedback messages and mapping).
    clip : clip out-of-range values instead of raising (for the simulator).
    counter : alive counter of the first period.
    stagger : time [s] between the frames of one period (message k at ``t + k*stagger``).
    """

    def __init__(self, protocol: Protocol, *, clip: bool = False, counter: int = 0,
                 stagger: float = 0.0) -> None:
        self.protocol = protocol
        self.clip = clip
        self.counter = int(counter)
        self.stagger = float(stagger)
        self.clipped: dict[str, int] = {}
        #: roles encoded modulo one turn (a full-turn position field)
        self.wrapping: frozenset[str] = frozenset(
            r.role for r in protocol.roles.values()
            if r.role == "position" and not r.codec.is_float and axis_of(r.unit) == "rotary"
            and abs((1 << r.codec.length) * abs(float(r.codec.scale)) * r.si_scale - 2 * math.pi)
            <= 1e-9 * 2 * math.pi)
        self._width = max(8, max(m.length for m in protocol.messages))

    def encode(self, t: npt.ArrayLike, current: npt.ArrayLike | None, speed: npt.ArrayLike,
               position: npt.ArrayLike | None = None,
               voltage: npt.ArrayLike | None = None,
               torque: npt.ArrayLike | None = None) -> FrameBlock:
        """Frames of ``len(t)`` periods (``len(t) * len(protocol.messages)`` frames).

        Values are SI (A, rad/s, rad, V, N·m). A mapped role given as ``None`` is sent
        as raw 0; a role given but not mapped is ignored.
        """
        p = self.protocol
        tt = np.asarray(t, np.float64).ravel()
        n = len(tt)
        si = {"current": current, "speed": speed, "position": position, "voltage": voltage,
              "torque": torque}
        m_count = len(p.messages)
        block = FrameBlock.allocate(n * m_count, self._width)
        seq = self.counter + np.arange(n, dtype=np.int64)
        for k, m in enumerate(p.messages):
            data = np.zeros((n, self._width), np.uint8)
            for r in m.roles:
                v = si[r.role]
                if v is None:
                    continue
                arr = np.asarray(v, np.float64).ravel()
                if len(arr) != n:
                    raise ValueError(f"{r.role} has {len(arr)} samples, t has {n}")
                dbc_units = arr / r.si_scale if r.si_scale != 1.0 else arr
                raw, n_clip = r.codec.to_raw(dbc_units, clip=self.clip,
                                             wrap=r.role in self.wrapping)
                if n_clip:
                    self.clipped[r.codec.qualname] = self.clipped.get(r.codec.qualname, 0) + n_clip
                r.codec.insert(data, raw)
            if m.counter is not None:
                m.counter.insert(data, seq % (1 << m.counter.length))
            if m.crc is not None:
                data[:, 0] = _crc_vector(m.frame_id, data, m.length)
            sl = slice(k, None, m_count)
            block.t[sl] = tt + k * self.stagger
            block.arbitration_id[sl] = m.frame_id
            block.is_extended[sl] = m.is_extended
            block.dlc[sl] = m.length
            block.data[sl] = data
        self.counter += n
        return block
