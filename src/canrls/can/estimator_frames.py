"""Estimator, status and command frames (0x300..0x321 of the default DBC).

The daemon publishes its estimates and health, and accepts commands, through frames of
``canrls/data/canrls.dbc``: each encoded by an encoder compiled once per message from
cantools' model (the bytes and checks of cantools' strict ``Message.encode``) and
decoded through cantools, so ``cantools monitor`` shows what canrls sends. The IDs come
from the DBC (:func:`frame_ids`); parameter names follow :data:`COMPONENTS`. Every
frame and signal: docs/protocol.md.
"""

from __future__ import annotations

import math
import struct
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field, replace
from enum import IntEnum
from functools import cache
from pathlib import Path
from typing import Any

import can
import cantools

from canrls.can.codec import EncodeError
from canrls.can.mapping import SignalMapping
from canrls.can.protocol import DEFAULT_DBC, load_dbc
from canrls.core.checks import check_lambda
from canrls.core.effect_names import EffectId, EquationId, parse_effect_name
from canrls.core.errors import CommandError, ConfigError, EffectError

__all__ = ["CommandCode", "CommandResult", "COMPONENTS", "FLAG_NAMES", "REJECT_FIELDS",
           "REJECT_WRAP", "ParameterReport", "StatusReport", "Command", "CommandAck",
           "CommandFrameError", "parameter_name", "parse_effect", "encode_parameters",
           "encode_param_info", "encode_status", "encode_command", "encode_ack", "decode_command",
           "FrameDecoder", "FrameIds", "database", "frame_ids"]


class CommandCode(IntEnum):
    """Commands a tool can send in ``RlsCommand``."""

    RESET = 1
    FREEZE = 2
    RESUME = 3
    ADD_EFFECT = 4
    REMOVE_EFFECT = 5
    SET_LAMBDA = 6
    SAVE_MODEL = 7


class CommandResult(IntEnum):
    """Result codes of ``RlsCommandAck``."""

    OK = 0
    UNKNOWN_COMMAND = 1
    MALFORMED = 2
    DISABLED = 3
    UNKNOWN_EFFECT = 4
    BAD_VALUE = 5
    NOT_APPLICABLE = 6
    #: the changed model would have more parameters than ``[daemon] max_parameters``
    #: or than the parameter frames carry
    TOO_LARGE = 7
    #: more commands than ``[daemon] command_rate``/``command_burst`` allow: try later
    RATE_LIMITED = 8


#: Component symbols of each effect (component index -> parameter symbol).
COMPONENTS: dict[EffectId, tuple[str, ...]] = {
    EffectId.INERTIA: ("J",),
    EffectId.VISCOUS: ("B",),
    EffectId.COULOMB: ("Tc",),
    EffectId.STRIBECK: ("Ts",),
    EffectId.OFFSET: ("T0",),
    EffectId.UNBALANCE: ("sin", "cos"),
    EffectId.COGGING: ("sin", "cos"),
    EffectId.ELECTRICAL: ("R", "L", "Ke"),
    EffectId.USER: ("c",),
}

#: Health flags of ``RlsHealth``, in bit order (StatusReport field names).
FLAG_NAMES: tuple[str, ...] = ("windup", "low_excitation", "saturation", "frame_loss",
                               "frozen", "diverged", "bus_fault", "clock_fault", "implausible")
_FLAG_SIGNALS = ("Windup", "LowExcitation", "Saturation", "FrameLoss", "Frozen", "Diverged",
                 "BusFault", "ClockFault", "Implausible")

#: Counters of ``RlsRejects`` (:attr:`StatusReport.rejects` keys), in signal order: frames
#: rejected by the decoder (``crc``; ``malformed``: remote or wrong length; ``repeated``
#: and ``stale`` alive counters, ``stale`` with the decoder's ``sequence``; ``range``:
#: outside the DBC range or NaN), dropped by
#: pairing (``unpaired``: no partner, late, duplicated), put back in order
#: (``reordered``), and clock events (``clock_steps``: back, or forward beyond
#: :data:`canrls.processor.pairing.FORWARD_STEP`; ``gaps``); last ``time``, frames rejected for
#: their receive time (:mod:`canrls.processor.times`), which ``RlsHealth`` carries
#: (``TimeRejects``: RlsRejects is full). They wrap at :data:`REJECT_WRAP`.
REJECT_FIELDS: tuple[str, ...] = ("crc", "malformed", "repeated", "stale", "range", "unpaired",
                                  "reordered", "clock_steps", "gaps", "time")
_REJECT_SIGNALS = ("Crc", "Malformed", "Repeated", "Stale", "Range", "Unpaired", "Reordered",
                   "ClockSteps", "Gaps")
#: (field, RlsRejects signal) of every field but ``time``
_REJECTS_FRAME = tuple(zip(REJECT_FIELDS[:-1], _REJECT_SIGNALS, strict=True))
#: Where each counter wraps on the wire (its signal's width).
REJECT_WRAP: dict[str, int] = {**dict.fromkeys(REJECT_FIELDS, 256), "clock_steps": 16,
                               "gaps": 16, "time": 8}


def _no_rejects() -> dict[str, int]:
    return dict.fromkeys(REJECT_FIELDS, 0)


def parameter_name(effect: EffectId, component: int, order: int = 0,
                   user_names: Sequence[str] = ()) -> str:
    """Parameter name from its (effect, component, order): ``"cogging:24.sin"``, ``"viscous.B"``.

    User terms are named ``user:NAME.c`` with NAME = ``user_names[order - 1]`` when
    given, else ``user:ORDER.c``.
    """
    effect = EffectId(effect)
    syms = COMPONENTS.get(effect, ())
    sym = syms[component] if 0 <= component < len(syms) else f"c{component}"
    if effect is EffectId.COGGING:
        return f"cogging:{order}.{sym}"
    if effect is EffectId.USER:
        label = user_names[order - 1] if 0 < order <= len(user_names) else str(order)
        return f"user:{label}.{sym}"
    return f"{effect.effect_name}.{sym}"


def parse_effect(name: str) -> tuple[EffectId, int]:
    """``"cogging:24"`` -> (COGGING, 24); ``"viscous"`` -> (VISCOUS, 0); ``"user:3"`` -> (USER, 3).

    The grammar of :func:`canrls.core.effect_names.parse_effect_name`, with the user term given
    by its 1-based index (as the ``Order`` field carries it). Raises
    :class:`CommandFrameError` (result UNKNOWN_EFFECT / BAD_VALUE) for an unknown name or
    a missing / malformed order, or an order beyond the 16-bit ``Order`` field
    (:data:`~canrls.core.effect_names.MAX_ORDER`).
    """
    try:
        parsed = parse_effect_name(name, user="index")
    except EffectError as e:
        unknown = EffectId.from_name(str(name).partition(":")[0]) is EffectId.NONE
        raise CommandFrameError(str(e), CommandResult.UNKNOWN_EFFECT if unknown
                                else CommandResult.BAD_VALUE) from e
    return parsed.effect, parsed.order


class CommandFrameError(CommandError):
    """A command frame is rejected; ``result`` is the :class:`CommandResult` to acknowledge
    with and ``code`` the raw command byte (None when the frame has none)."""

    def __init__(self, message: str, result: CommandResult, code: int | None = None) -> None:
        super().__init__(message)
        self.result = result
        self.code = code


# ---------------------------------------------------------------------------
# Value objects
# ---------------------------------------------------------------------------


@dataclass(frozen=True)
class ParameterReport:
    """One estimated parameter, as published on the bus (float32 precision on the wire).

    ``fixed_value`` is the fixed-point estimate converted to SI, ``float_value`` the
    float reference, ``sigma`` its standard deviation; ``None`` when unknown.
    ``valid`` is False while the estimate is not meaningful (sent as Valid = 0).
    """

    index: int
    name: str = ""
    effect_id: EffectId = EffectId.NONE
    component: int = 0
    order: int = 0
    equation: EquationId = EquationId.MECHANICAL
    fixed_value: float | None = None
    sigma: float | None = None
    float_value: float | None = None
    unit: str = ""
    valid: bool = True

    def with_estimates(self, fixed_value: float | None, sigma: float | None,
                       float_value: float | None, valid: bool) -> ParameterReport:
        """This parameter with other estimates, as ``dataclasses.replace`` of these four fields.

        At about a third of the constructor's cost (the daemon reports after every block): the
        class has no ``__post_init__``, so filling the new instance's ``__dict__`` is all
        its ``__init__`` would do.
        """
        r = object.__new__(type(self))
        d = r.__dict__
        d.update(self.__dict__)
        d["fixed_value"] = fixed_value
        d["sigma"] = sigma
        d["float_value"] = float_value
        d["valid"] = valid
        return r


@dataclass(frozen=True)
class StatusReport:
    """Estimator health as published in RlsStatus, RlsHealth, RlsCounters and RlsRejects.

    ``active_effects`` is a bitmask: bit ``EffectId - 1`` set when the effect is in
    the model. The four counters wrap at 16 bits on the wire, ``update_count`` at 32.
    ``clock_fault``: the frames' timestamps stepped (back, or forward beyond a bound),
    or a frame was rejected for its receive time, during the last interval.
    ``rejects``: ``{reason: frames}`` for every reason of :data:`REJECT_FIELDS`
    (wrapping on the wire at :data:`REJECT_WRAP`; ``time`` in RlsHealth).
    """

    residual_rms: float = 0.0
    update_count: int = 0
    windup: bool = False
    low_excitation: bool = False
    saturation: bool = False
    frame_loss: bool = False
    frozen: bool = False
    diverged: bool = False
    bus_fault: bool = False
    clock_fault: bool = False
    #: an estimate physics rules out (:func:`canrls.estimation.physics.check_physics`)
    implausible: bool = False
    active_effects: int = 0
    divergence: float = 0.0
    frames_rejected: int = 0
    frames_lost: int = 0
    saturations: int = 0
    tx_dropped: int = 0
    rejects: Mapping[str, int] = field(default_factory=_no_rejects)

    @property
    def flags(self) -> tuple[str, ...]:
        """Names of the health flags that are set."""
        return tuple(f for f in FLAG_NAMES if getattr(self, f))

    def effects(self) -> frozenset[EffectId]:
        """The active effects (decoded bitmask)."""
        return frozenset(e for e in EffectId if e and self.active_effects >> (e - 1) & 1)

    @staticmethod
    def effect_mask(effects: Iterable[EffectId | int]) -> int:
        """Bitmask of ``effects`` (bit EffectId - 1)."""
        mask = 0
        for e in effects:
            e = EffectId(e)
            if e:
                mask |= 1 << (e - 1)
        return mask


@dataclass(frozen=True)
class Command:
    """A command to the daemon: ``code`` with its effect and order, or lambda."""

    code: CommandCode
    effect: EffectId = EffectId.NONE
    order: int = 0
    lam: float = 0.0

    def __str__(self) -> str:
        c = self.code.name.lower()
        if self.code in (CommandCode.ADD_EFFECT, CommandCode.REMOVE_EFFECT):
            e = self.effect.effect_name + (f":{self.order}" if self.order else "")
            return f"{c} {e}"
        if self.code is CommandCode.SET_LAMBDA:
            return f"{c} {self.lam:.9g}"
        return c


@dataclass(frozen=True)
class CommandAck:
    """The acknowledgement of a command (``command`` is the raw code, maybe unknown)."""

    command: int
    result: CommandResult
    counter: int = 0


# ---------------------------------------------------------------------------
# Encoding
# ---------------------------------------------------------------------------


@cache
def _database(path: str) -> Any:
    return load_dbc(path)[0]


def _db(dbc: str | Path | None = None) -> Any:
    return _database(str(DEFAULT_DBC if dbc is None else dbc))


def database(dbc: str | Path | None = None) -> Any:
    """canrls' DBC (default: the shipped one) as cantools reads it, strictly
    (:func:`~canrls.can.protocol.load_dbc`), read once per file: every user of its
    frames' layout shares it."""
    return _db(dbc)


#: DBC message names of the frames canrls publishes, in the order of :class:`FrameIds`.
_PUBLISHED = ("RlsEstimate", "RlsSigma", "RlsReference", "RlsParamInfo", "RlsStatus",
              "RlsHealth", "RlsCounters", "RlsRejects")


@dataclass(frozen=True)
class FrameIds:
    """Arbitration IDs of canrls' frames, read from the DBC (:func:`frame_ids`).

    One field per estimator, status and command frame; ``feedback`` holds the drive's
    frames of the default signal mapping (``DriveCurrent`` then ``DriveSpeed``), those of
    the DBC's messages that exist. Every ID is a standard (11-bit) one.
    """

    estimate: int
    sigma: int
    reference: int
    param_info: int
    status: int
    health: int
    counters: int
    rejects: int
    command: int
    ack: int
    feedback: tuple[int, ...]

    @property
    def own(self) -> dict[int, str]:
        """Every frame of canrls' own, ID -> DBC message name: the published frames, the
        command and its acknowledgement (standard IDs)."""
        ids = (self.estimate, self.sigma, self.reference, self.param_info, self.status,
               self.health, self.counters, self.rejects, self.command, self.ack)
        return dict(zip(ids, (*_PUBLISHED, "RlsCommand", "RlsCommandAck"), strict=True))

    @property
    def published(self) -> frozenset[int]:
        """The frames the daemon publishes every cycle (parameters and status, not the ack)."""
        return frozenset((self.estimate, self.sigma, self.reference, self.param_info,
                          self.status, self.health, self.counters, self.rejects))


@cache
def _frame_ids(path: str) -> FrameIds:
    db = _database(path)
    present = {m.name: m.frame_id for m in db.messages}
    wanted = (*_PUBLISHED, "RlsCommand", "RlsCommandAck")
    missing = [n for n in wanted if n not in present]
    if missing:
        raise ConfigError(f"DBC file {path}: no message {', '.join(missing)}: canrls' own "
                          f"frames (those of the shipped DBC, canrls/data/canrls.dbc) are "
                          f"needed to publish estimates or export their codecs")
    (estimate, sigma, reference, param_info, status, health, counters, rejects, command,
     ack) = (present[n] for n in wanted)
    names = dict.fromkeys(r.message for r in SignalMapping.default().roles.values())
    return FrameIds(estimate, sigma, reference, param_info, status, health, counters,
                    rejects, command, ack,
                    feedback=tuple(present[n] for n in names if n in present))


def frame_ids(dbc: str | Path | None = None) -> FrameIds:
    """The IDs of canrls' frames in ``dbc`` (default: the shipped DBC), read once.

    >>> hex(frame_ids().command)
    '0x320'
    """
    return _frame_ids(str(DEFAULT_DBC if dbc is None else dbc))


def _f32(x: float | None, lo: float, hi: float) -> float:
    """A float for a float32 signal: None -> NaN, NaN kept, saturated into [lo, hi]."""
    if x is None:
        return math.nan
    x = float(x)
    return lo if x < lo else hi if x > hi else x  # NaN fails both tests: kept


_FLOAT_PACKERS = {32: struct.Struct("<f").pack, 64: struct.Struct("<d").pack}


class _Layout:
    """The fast path of one set of little-endian signals: positions, masks, limits, packers.

    ``plain``: (name, shift, mask, lo, hi) of integers whose raw value is the value (lo,
    hi: the DBC range and the bit field together); ``scaled``: (..., to_raw, raw_lo,
    raw_hi) of scaled integers; ``floats``: (name, shift, lo, hi, pack, to_raw | None).
    """

    __slots__ = ("count", "plain", "scaled", "floats")

    def __init__(self, signals: Sequence[Any]) -> None:
        self.count = len(signals)
        plain: list[tuple[str, int, int, int, int]] = []
        scaled: list[tuple[str, int, int, float, float, Any, int, int]] = []
        floats: list[tuple[str, int, float, float, Any, Any]] = []
        for s in signals:
            conv = s.conversion
            lo, hi, raw_lo, raw_hi = _limits(s)
            identity = conv.scale == 1 and conv.offset == 0
            mask = (1 << s.length) - 1
            if s.is_float:
                floats.append((s.name, s.start, lo, hi, _FLOAT_PACKERS.get(s.length),
                               None if identity else conv.numeric_scaled_to_raw))
            elif identity:
                plain.append((s.name, s.start, mask,
                              raw_lo if s.minimum is None else max(raw_lo, math.ceil(lo)),
                              raw_hi if s.maximum is None else min(raw_hi, math.floor(hi))))
            else:
                scaled.append((s.name, s.start, mask, lo, hi, conv.numeric_scaled_to_raw,
                               raw_lo, raw_hi))
        self.plain = tuple(plain)
        self.scaled = tuple(scaled)
        self.floats = tuple(floats)

    def word(self, values: dict[str, Any]) -> int | None:
        """These signals of ``values`` as one little-endian integer; None when a value is
        not of the fast path. Raises KeyError for a missing signal, OverflowError when
        inf meets a conversion or a value is beyond float32."""
        word = 0
        for name, shift, mask, raw_lo, raw_hi in self.plain:
            v = values[name]
            if type(v) is not int or v < raw_lo or v > raw_hi:
                return None
            word |= (v & mask) << shift
        for name, shift, mask, lo, hi, to_raw, raw_lo, raw_hi in self.scaled:
            v = values[name]
            if type(v) is not int and type(v) is not float or not lo <= v <= hi:
                return None
            raw = to_raw(v)
            if raw < raw_lo or raw > raw_hi:
                return None
            word |= (raw & mask) << shift
        for name, shift, lo, hi, pack, to_raw in self.floats:
            v = values[name]
            if type(v) is not float or v < lo or v > hi:  # NaN passes, as in cantools
                return None
            word |= int.from_bytes(pack(v if to_raw is None else to_raw(v)), "little") << shift
        return word


def _limits(s: Any) -> tuple[float, float, int, int]:
    """(lo, hi) of a signal's value with cantools' tolerance, (raw_lo, raw_hi) of its field."""
    tol = abs(s.conversion.scale) * 1e-6  # cantools' tolerance on the limits
    lo = -math.inf if s.minimum is None else s.minimum - tol
    hi = math.inf if s.maximum is None else s.maximum + tol
    if s.is_signed:
        return lo, hi, -(1 << s.length - 1), (1 << s.length - 1) - 1
    return lo, hi, 0, (1 << s.length) - 1


class _Codec:
    """Strict encoder of one DBC message, compiled once from its cantools ``Message``.

    :meth:`encode` gives the bytes of ``Message.encode(values, scaling=True,
    strict=True)``. Messages of little-endian (Intel) signals, plain or multiplexed by
    one multiplexer at the top level (the estimator frames' ``Index``), take a fast
    path: a :class:`_Layout` of all signals, or for a multiplexed message one per
    multiplexer value of the signals it selects and those always present (shared by the
    values that select the same signals), the frame built as one integer. Whatever that
    path does not cover (big-endian signals, nested multiplexing, an unknown multiplexer
    value, a value of another type, out of range or only allowed by a value table) takes
    the careful path: the limits checked again with an :class:`EncodeError` naming the
    message, the signal, the value and the limits, then cantools itself.
    """

    __slots__ = ("message", "name", "frame_id", "is_extended", "length", "_layout", "_mux",
                 "_by_mux", "_checks")

    def __init__(self, message: Any) -> None:
        self.message = message
        self.name: str = message.name
        self.frame_id: int = message.frame_id
        self.is_extended: bool = message.is_extended_frame
        self.length: int = message.length
        signals = message.signals
        self._checks = tuple((s, *_limits(s)) for s in signals)
        #: the layout of a message without multiplexing (None: multiplexed, or no fast path)
        self._layout: _Layout | None = None
        #: the multiplexer's name and its value -> the layout of the signals it selects
        self._mux: str | None = None
        self._by_mux: dict[int, _Layout] = {}
        if message.is_container or not all(
                s.byte_order == "little_endian" and (not s.is_float or s.length in _FLOAT_PACKERS)
                for s in signals):
            return
        root = [s for s in signals if s.multiplexer_signal is None]
        muxes = [s for s in root if s.is_multiplexer]
        if not muxes:
            self._layout = _Layout(signals)
            return
        mux = muxes[0]
        children = [s for s in signals if s.multiplexer_signal is not None]
        conv = mux.conversion
        if (len(muxes) > 1 or any(s.is_multiplexer or s.multiplexer_signal != mux.name
                                  for s in children)
                or mux.is_float or conv.scale != 1 or conv.offset != 0):
            return  # nested or several multiplexers: cantools alone
        ids: set[int] = set(conv.choices or ())  # cantools accepts these even without signals
        for s in children:
            ids.update(s.multiplexer_ids or ())
        shared: dict[tuple[str, ...], _Layout] = {}
        for k in sorted(ids):
            sel = [s for s in signals if s.multiplexer_signal is None or k in s.multiplexer_ids]
            key = tuple(s.name for s in sel)
            if key not in shared:
                shared[key] = _Layout(sel)
            self._by_mux[k] = shared[key]
        self._mux = mux.name

    @property
    def fast(self) -> bool:
        """Whether the message has a fast path (values of the right types then take it)."""
        return self._layout is not None or self._mux is not None

    def frame(self, values: dict[str, Any], timestamp: float) -> can.Message:
        """The ``can.Message`` of ``values`` (data as :meth:`encode`)."""
        data = self._pack(values)
        # positional (timestamp, arbitration_id, is_extended_id, is_remote_frame,
        # is_error_frame, channel, dlc, data): keywords make it half as slow again
        return can.Message(timestamp, self.frame_id, self.is_extended, False, False, None,
                           self.length, self._careful(values) if data is None else data)

    def encode(self, values: dict[str, Any]) -> bytes:
        """The data of the frame: ``values`` maps every signal of the message to its value.

        Raises :class:`EncodeError` (reason ``"range"``, or ``"nan"`` for a non-finite
        value of an integer signal) naming the message, the signal, the value and the
        limits, or wrapping cantools' error (missing or unknown signal, bad choice,
        multiplexer value without signals).
        """
        data = self._pack(values)
        return self._careful(values) if data is None else data

    def _pack(self, values: dict[str, Any]) -> bytes | None:
        """The fast path; None when it does not apply."""
        layout = self._layout
        if layout is None:
            if self._mux is None:
                return None
            k = values.get(self._mux)
            # the layout checks k again (type, range) among its plain integers
            layout = self._by_mux.get(k) if type(k) is int else None
            if layout is None:
                return None
        if len(values) != layout.count:
            return None
        try:
            word = layout.word(values)
        except KeyError:  # a signal missing (and another one too many)
            return None
        except OverflowError:  # inf met a conversion, or beyond float32: cantools decides
            return None
        return None if word is None else word.to_bytes(self.length, "little")

    def _careful(self, values: dict[str, Any]) -> bytes:
        """Strict encoding the slow way: the checks of :meth:`_check`, then cantools."""
        for s, lo, hi, raw_lo, raw_hi in self._checks:
            v = values.get(s.name)
            if isinstance(v, (int, float)):
                self._check(s, v, lo, hi, raw_lo, raw_hi)
        try:
            return self.message.encode(values, scaling=True, strict=True)
        except (cantools.database.EncodeError, KeyError, ValueError) as e:
            raise EncodeError(f"cannot encode {self.name}: {e}", reason="range") from e

    def _check(self, s: Any, v: float, lo: float, hi: float, raw_lo: int, raw_hi: int
               ) -> None:
        """cantools' strict checks on one value, and that its raw value fits the field."""
        what = f"cannot encode {self.name}.{s.name} = {v!r}"
        if not s.is_float and isinstance(v, float) and not math.isfinite(v):
            raise EncodeError(f"{what}: an integer signal needs a finite value", reason="nan")
        conv = s.conversion
        raw = conv.numeric_scaled_to_raw(v)
        if not (conv.choices and raw in conv.choices) and (v < lo or v > hi):
            raise EncodeError(f"{what}: outside [{'-inf' if s.minimum is None else s.minimum}, "
                              f"{'inf' if s.maximum is None else s.maximum}]", reason="range")
        if not s.is_float and not raw_lo <= raw <= raw_hi:
            raise EncodeError(f"{what}: raw value {raw} does not fit the {s.length}-bit field "
                              f"({raw_lo} .. {raw_hi})", reason="range")


@cache
def _codec(dbc: str | Path | None, name: str) -> _Codec:
    """The compiled encoder of message ``name`` of ``dbc`` (default: the shipped DBC)."""
    return _Codec(_db(dbc).get_message_by_name(name))


def _message(name: str, values: dict[str, Any], timestamp: float, dbc: str | Path | None
             ) -> can.Message:
    return _codec(dbc, name).frame(values, timestamp)


def _index(report: ParameterReport) -> int:
    if not 0 <= report.index <= 255:
        raise EncodeError(f"parameter {report.name or report.index}: index {report.index} "
                          f"outside 0..255", reason="range")
    return report.index


_F32_MAX = 3.4e38


def encode_parameters(reports: Iterable[ParameterReport], counter: int, *,
                      timestamp: float = 0.0, dbc: str | Path | None = None
                      ) -> list[can.Message]:
    """RlsEstimate, RlsSigma and RlsReference of every parameter (3 frames per index).

    All frames carry ``counter`` mod 16. An estimate that is ``None``/NaN or not
    ``valid`` is sent as 0 with Valid = 0; values are saturated to the float32 range
    of the DBC; an unknown sigma or float value is sent as NaN.
    """
    c = counter % 16
    estimate, sigma, reference = (_codec(dbc, "RlsEstimate"), _codec(dbc, "RlsSigma"),
                                  _codec(dbc, "RlsReference"))
    out: list[can.Message] = []
    for r in reports:
        i = _index(r)
        fixed = r.fixed_value
        valid = bool(r.valid) and fixed is not None and not math.isnan(fixed)
        out += (
            estimate.frame({"Index": i, "Counter": c, "Valid": int(valid),
                            "FixedValue": _f32(fixed, -_F32_MAX, _F32_MAX) if valid else 0.0},
                           timestamp),
            sigma.frame({"Index": i, "Counter": c, "Sigma": _f32(r.sigma, 0.0, _F32_MAX)},
                        timestamp),
            reference.frame({"Index": i, "Counter": c,
                             "FloatValue": _f32(r.float_value, -_F32_MAX, _F32_MAX)},
                            timestamp))
    return out


def encode_param_info(reports: Sequence[ParameterReport], *, timestamp: float = 0.0,
                      dbc: str | Path | None = None) -> list[can.Message]:
    """RlsParamInfo of every parameter (Count = ``len(reports)``)."""
    n = len(reports)
    if n > 255:
        raise EncodeError(f"{n} parameters: RlsParamInfo.Count holds at most 255",
                          reason="range")
    return [_message("RlsParamInfo", {
        "Index": _index(r), "Count": n, "EffectId": int(r.effect_id),
        "Component": r.component, "Order": r.order, "Equation": int(r.equation)},
        timestamp, dbc) for r in reports]


def encode_status(status: StatusReport, counter: int, *, timestamp: float = 0.0,
                  dbc: str | Path | None = None) -> list[can.Message]:
    """RlsStatus, RlsHealth, RlsCounters and RlsRejects (counters wrap at 16 bits,
    UpdateCount at 32, the reject counters at :data:`REJECT_WRAP`)."""
    s = status
    health: dict[str, Any] = {sig: int(bool(getattr(s, f)))
                              for f, sig in zip(FLAG_NAMES, _FLAG_SIGNALS, strict=True)}
    health.update(Counter=counter % 16, ActiveEffects=s.active_effects & 0xFFFF,
                  Divergence=_f32(s.divergence, 0.0, _F32_MAX),
                  TimeRejects=int(s.rejects.get("time", 0)) % REJECT_WRAP["time"])
    return [
        _message("RlsStatus", {"ResidualRms": _f32(s.residual_rms, 0.0, _F32_MAX),
                               "UpdateCount": s.update_count % (1 << 32)}, timestamp, dbc),
        _message("RlsHealth", health, timestamp, dbc),
        _message("RlsCounters", {"FramesRejected": s.frames_rejected % 65536,
                                 "FramesLost": s.frames_lost % 65536,
                                 "Saturations": s.saturations % 65536,
                                 "TxDropped": s.tx_dropped % 65536}, timestamp, dbc),
        _message("RlsRejects", {sig: int(s.rejects.get(f, 0)) % REJECT_WRAP[f]
                                for f, sig in _REJECTS_FRAME},
                 timestamp, dbc),
    ]


def encode_command(command: Command | CommandCode | int, effect: EffectId | int = 0,
                   order: int = 0, lam: float = 0.0, *, timestamp: float = 0.0,
                   dbc: str | Path | None = None) -> can.Message:
    """An RlsCommand frame: ``encode_command(Command(...))`` or ``encode_command(code, ...)``.

    >>> encode_command(CommandCode.SET_LAMBDA, lam=0.999).data.hex()
    '0600000077be7f3f'
    """
    if isinstance(command, Command):
        code, effect, order, lam = int(command.code), command.effect, command.order, command.lam
    else:
        code = int(command)
    return _message("RlsCommand", {"Command": code, "EffectId": int(effect), "Order": int(order),
                                   "Lambda": float(lam)}, timestamp, dbc)


def encode_ack(command: int, result: CommandResult | int, counter: int, *,
               timestamp: float = 0.0, dbc: str | Path | None = None) -> can.Message:
    """An RlsCommandAck frame for the raw command code ``command``."""
    return _message("RlsCommandAck", {"Command": int(command) & 0xFF, "Result": int(result),
                                      "Counter": counter % 16}, timestamp, dbc)


# ---------------------------------------------------------------------------
# Decoding
# ---------------------------------------------------------------------------


def decode_command(msg: can.Message, *, dbc: str | Path | None = None) -> Command:
    """Validate and decode an RlsCommand frame.

    Raises :class:`CommandFrameError` (a :class:`~canrls.core.errors.CommandError`) with
    ``.result``: MALFORMED for another ID, a remote/error frame or a DLC other than 8;
    UNKNOWN_COMMAND for an unknown command code; UNKNOWN_EFFECT for an effect id
    outside 1..9 (add/remove); BAD_VALUE for a missing or spurious order (cogging and
    user need one, others take none) or a lambda outside
    (:data:`~canrls.core.checks.LAMBDA_MIN`, 1].
    """
    m = _db(dbc).get_message_by_name("RlsCommand")
    if msg.arbitration_id != m.frame_id or msg.is_extended_id != m.is_extended_frame:
        raise CommandFrameError(f"frame 0x{msg.arbitration_id:X} is not RlsCommand "
                                f"(0x{m.frame_id:X})", CommandResult.MALFORMED)
    if msg.is_error_frame or msg.is_remote_frame:
        raise CommandFrameError("RlsCommand: remote or error frame", CommandResult.MALFORMED)
    data = bytes(msg.data)
    code = data[0] if data else None
    if len(data) != m.length:
        raise CommandFrameError(f"RlsCommand: DLC {len(data)}, expected {m.length}",
                                CommandResult.MALFORMED, code)
    v = m.decode(data, decode_choices=False, scaling=True)
    try:
        cc = CommandCode(int(v["Command"]))
    except ValueError:
        raise CommandFrameError(f"RlsCommand: unknown command code {v['Command']}",
                                CommandResult.UNKNOWN_COMMAND, code) from None
    if cc in (CommandCode.ADD_EFFECT, CommandCode.REMOVE_EFFECT):
        eid, order = int(v["EffectId"]), int(v["Order"])
        if _enum(EffectId, eid, EffectId.NONE) is EffectId.NONE:
            raise CommandFrameError(f"RlsCommand {cc.name.lower()}: unknown effect id {eid}",
                                    CommandResult.UNKNOWN_EFFECT, code)
        effect = EffectId(eid)
        needs = effect in (EffectId.COGGING, EffectId.USER)
        if needs and order == 0:
            raise CommandFrameError(f"RlsCommand {cc.name.lower()} {effect.effect_name}: "
                                    f"order 0, {effect.effect_name} needs an order >= 1",
                                    CommandResult.BAD_VALUE, code)
        if not needs and order != 0:
            raise CommandFrameError(f"RlsCommand {cc.name.lower()} {effect.effect_name}: "
                                    f"order {order}, {effect.effect_name} takes none",
                                    CommandResult.BAD_VALUE, code)
        return Command(cc, effect, order)
    if cc is CommandCode.SET_LAMBDA:
        try:
            lam = check_lambda(float(v["Lambda"]), "RlsCommand set_lambda: lambda")
        except ConfigError as e:
            raise CommandFrameError(str(e), CommandResult.BAD_VALUE, code) from None
        return Command(cc, lam=lam)
    return Command(cc)


@dataclass
class FrameDecoder:
    """Turn received estimator frames back into objects (for the monitor).

    Feed every received ``can.Message`` to :meth:`feed`; frames of the same parameter
    index accumulate into one :class:`ParameterReport` (``parameters``), the three
    status frames into one :class:`StatusReport` (``status``). Acknowledgements go to
    ``acks`` (the latest last) and commands seen on the bus to ``commands``. Frames
    of other IDs are counted in ``ignored``; frames of a known ID that cantools
    cannot decode (wrong length) in ``malformed``.

    ``user_names`` name user terms by their order (1-based); ``units`` maps parameter
    names to units for the reports.
    """

    user_names: Sequence[str] = ()
    units: Mapping[str, str] = field(default_factory=dict)
    dbc: str | Path | None = None
    parameters: dict[int, ParameterReport] = field(default_factory=dict)
    status: StatusReport | None = None
    count: int | None = None
    acks: list[CommandAck] = field(default_factory=list)
    commands: list[Command] = field(default_factory=list)
    ignored: int = 0
    malformed: int = 0

    def __post_init__(self) -> None:
        db = _db(self.dbc)
        names = {*_PUBLISHED, "RlsCommand", "RlsCommandAck"}
        self._by_id = {m.frame_id: m for m in db.messages if m.name in names}

    def feed(self, msg: can.Message
             ) -> ParameterReport | StatusReport | CommandAck | Command | None:
        """Take one frame; return the object it updated (None if ignored or malformed)."""
        m = self._by_id.get(msg.arbitration_id)
        if m is None or msg.is_extended_id != m.is_extended_frame or msg.is_error_frame \
                or msg.is_remote_frame:
            self.ignored += 1
            return None
        if m.name == "RlsCommand":
            try:
                cmd = decode_command(msg, dbc=self.dbc)
            except CommandError:
                self.malformed += 1
                return None
            self.commands.append(cmd)
            return cmd
        try:
            v = m.decode(bytes(msg.data), decode_choices=False, scaling=True)
        except cantools.database.DecodeError:
            self.malformed += 1
            return None
        name = m.name
        if name in ("RlsEstimate", "RlsSigma", "RlsReference", "RlsParamInfo"):
            i = int(v["Index"])
            r = self.parameters.get(i) or ParameterReport(i)
            if name == "RlsEstimate":
                valid = bool(v["Valid"])
                r = replace(r, fixed_value=float(v["FixedValue"]) if valid else None, valid=valid)
            elif name == "RlsSigma":
                r = replace(r, sigma=_nan_none(v["Sigma"]))
            elif name == "RlsReference":
                r = replace(r, float_value=_nan_none(v["FloatValue"]))
            else:
                self.count = int(v["Count"])
                eid = _enum(EffectId, v["EffectId"], EffectId.NONE)
                comp, order = int(v["Component"]), int(v["Order"])
                pname = parameter_name(eid, comp, order, self.user_names) if eid else ""
                r = replace(r, effect_id=eid, component=comp, order=order,
                            equation=EquationId(int(v["Equation"])), name=pname,
                            unit=self.units.get(pname, r.unit))
            self.parameters[i] = r
            return r
        if name == "RlsCommandAck":
            res = int(v["Result"])
            ack = CommandAck(int(v["Command"]), _enum(CommandResult, res, CommandResult.MALFORMED),
                             int(v["Counter"]))
            self.acks.append(ack)
            return ack
        s = self.status or StatusReport()
        if name == "RlsStatus":
            s = replace(s, residual_rms=float(v["ResidualRms"]), update_count=int(v["UpdateCount"]))
        elif name == "RlsHealth":
            flags = {f: bool(v[sig]) for f, sig in zip(FLAG_NAMES, _FLAG_SIGNALS, strict=True)}
            s = replace(s, active_effects=int(v["ActiveEffects"]),
                        divergence=float(v["Divergence"]),
                        rejects={**s.rejects, "time": int(v.get("TimeRejects", 0))}, **flags)
        elif name == "RlsRejects":
            s = replace(s, rejects={**{f: int(v[sig]) for f, sig in _REJECTS_FRAME},
                                    "time": int(s.rejects.get("time", 0))})
        else:  # RlsCounters
            s = replace(s, frames_rejected=int(v["FramesRejected"]),
                        frames_lost=int(v["FramesLost"]), saturations=int(v["Saturations"]),
                        tx_dropped=int(v["TxDropped"]))
        self.status = s
        return s

    def feed_all(self, messages: Iterable[can.Message]) -> None:
        """Feed many frames."""
        for m in messages:
            self.feed(m)

    def table(self) -> list[ParameterReport]:
        """The parameters sorted by index."""
        return [self.parameters[i] for i in sorted(self.parameters)]


def _enum(kind: Any, value: Any, default: Any) -> Any:
    try:
        return kind(int(value))
    except ValueError:
        return default


def _nan_none(x: Any) -> float | None:
    f = float(x)
    return None if math.isnan(f) else f
