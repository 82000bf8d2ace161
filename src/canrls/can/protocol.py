"""The feedback protocol: a DBC (:func:`load_dbc`, the one reader), the signal mapping and
the compiled codec of each mapped message. The strict decoder
(:class:`~canrls.can.decoder.Decoder`) and the encoder
(:class:`~canrls.can.encoder.FeedbackEncoder`) each take a protocol:

>>> from canrls.can.decoder import Decoder
>>> from canrls.can.encoder import FeedbackEncoder
>>> proto = Protocol.load()                       # default DBC and mapping
>>> enc = FeedbackEncoder(proto)
>>> block = enc.encode([0.0, 0.001], current=[1.5, 1.6], speed=[10.0, 10.1])
>>> dec = Decoder(proto).decode(block)
>>> dec["DriveCurrent"].values["current"].tolist()
[1.5, 1.6]
"""

from __future__ import annotations

import dataclasses
import functools
import hashlib
import logging
import math
from collections.abc import Mapping, Sequence
from importlib import resources
from pathlib import Path
from typing import Any

import cantools

from canrls.can.codec import (
    MessageCodec,
    RoleInfo,
    SignalCodec,
)
from canrls.can.idrules import IdRule
from canrls.can.mapping import EFFORT_ROLES, REQUIRED_ROLES, SignalMapping
from canrls.core.checks import positive_period
from canrls.core.errors import ConfigError, SignalError
from canrls.core.files import MAX_DBC_BYTES, read_bytes
from canrls.core.samples import ROLES
from canrls.core.units import axis_of, si_factor

__all__ = ["DEFAULT_DBC", "MAX_MESSAGE_BYTES", "load_dbc", "parse_dbc", "Protocol"]


#: The DBC shipped with canrls (same content as ``dbc/canrls.dbc`` in the repository).
DEFAULT_DBC: Path = Path(str(resources.files("canrls") / "data" / "canrls.dbc"))

#: Longest message a DBC may declare [bytes]: a CAN FD frame's payload.
MAX_MESSAGE_BYTES = 64
#: DBCs kept parsed, by the SHA-256 of their bytes (:func:`parse_dbc`)
_PARSED_KEPT = 8
_parsed: dict[bytes, Any] = {}


def load_dbc(path: str | Path, what: str | None = None) -> tuple[Any, bytes]:
    """The cantools database of the DBC at ``path`` (strict) and the file's bytes.

    The one DBC reader of canrls: a regular file of at most
    :data:`~canrls.core.files.MAX_DBC_BYTES`, whose every message fits a CAN frame
    (:data:`MAX_MESSAGE_BYTES`) and every signal its message, checked on cantools'
    tokens before cantools builds anything (its strict check is quadratic in a start
    bit, its codec linear in a length); then every signal's scale, offset and limits
    must be finite numbers, the scale not zero, and the physical range of its raw
    integers finite. Errors (:class:`ConfigError`) name the file, message and signal.
    """
    p = Path(path)
    where = what or f"DBC file {p}"
    raw = read_bytes(p, where, limit=MAX_DBC_BYTES)
    return parse_dbc(raw, where), raw


def parse_dbc(raw: bytes, where: str) -> Any:
    """The cantools database of a DBC's bytes, checked as :func:`load_dbc` says (errors
    name ``where``). The same bytes are parsed once: the database is kept (the last
    :data:`_PARSED_KEPT` DBCs) and shared, never changed by canrls; a DBC that fails is
    checked again each time, so every caller gets its own error."""
    key = hashlib.sha256(raw).digest()
    db = _parsed.get(key)
    if db is None:
        db = _parse_dbc(raw, where)
        while len(_parsed) >= _PARSED_KEPT:
            del _parsed[next(iter(_parsed))]
        _parsed[key] = db
    return db


def _parse_dbc(raw: bytes, where: str) -> Any:
    text = _dbc_text(raw, where)
    from cantools.database.can.formats.dbc.dbc_loader import DbcParser

    try:
        tokens = DbcParser().parse(text)
    except Exception as e:  # textparser's errors say where
        raise ConfigError(f"cannot parse {where}: {e}") from e
    _check_layout(tokens, where)
    # cantools logs "Overwriting message ..." for two messages of one name or ID, a line
    # with a time stamp on stderr beside canrls' one error line: a mapped message that
    # shares its name or ID is refused where the mapping is resolved (_resolve)
    log = logging.getLogger("cantools.database.can.database")
    log.addFilter(_no_overwriting)
    try:
        db = cantools.database.load_string(text, database_format="dbc", strict=True)
    except Exception as e:  # cantools raises several parse error types
        raise ConfigError(f"cannot parse {where}: {e}") from e
    finally:
        log.removeFilter(_no_overwriting)
    if not isinstance(db, cantools.database.can.Database):  # what format "dbc" gives
        raise ConfigError(f"cannot parse {where}: not a CAN database")
    for m in db.messages:
        for sig in m.signals:
            _check_numbers(sig, f"{where}: message {m.name}: signal {sig.name}")
    return db


def _no_overwriting(record: logging.LogRecord) -> bool:
    """A log filter: False for cantools' warning of a message name or ID given twice."""
    return not str(record.msg).startswith("Overwriting message")


def _dbc_text(raw: bytes, where: str) -> str:
    """The text of a DBC file's bytes: UTF-8 when they are UTF-8 (a byte-order mark
    dropped), else Windows-1252, cantools' encoding and most DBC editors'. A cp1252 '‰'
    (0x89) or 'µ' (0xb5) is never valid UTF-8; a UTF-8 '‰' read as cp1252 would be 'â€°'.
    """
    try:
        return raw.decode("utf-8-sig")
    except UnicodeDecodeError:
        pass
    try:
        return raw.decode("cp1252")
    except UnicodeDecodeError as e:
        line = raw.count(b"\n", 0, e.start) + 1
        raise ConfigError(f"cannot parse {where}: byte 0x{raw[e.start]:02x} at line "
                          f"{line} is neither UTF-8 nor cp1252 text") from e


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
    #: the ID rule that moved the messages (:meth:`with_ids`); None: the DBC's own IDs
    rule: IdRule | None = None
    #: SHA-256 of the DBC file as it was read ("" when not read from a file)
    dbc_digest: str = ""

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
             axis: str | None = None, dbc_bytes: bytes | None = None) -> Protocol:
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
        dbc_bytes : the DBC's text, made from the file ``dbc`` (an EDS:
            :mod:`canrls.can.eds`) rather than read from it.

        Raises
        ------
        ConfigError
            The DBC cannot be read or parsed, or the mapping is malformed.
        SignalError
            The DBC lacks a mapped message or signal, or a unit cannot be converted.
        """
        path = DEFAULT_DBC if dbc is None else Path(dbc)
        if dbc_bytes is None:
            db, raw = load_dbc(path)
        else:
            db, raw = parse_dbc(dbc_bytes, f"the DBC made from {path}"), dbc_bytes
        digest = hashlib.sha256(raw).hexdigest()
        is_default = digest == _default_hash()
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
        if period is not None:
            period = positive_period(period, period_source or "period")
        roles, messages = _resolve(db, path, is_default, mp, period, axis)
        proto = Protocol(db, path, is_default, mp, roles, messages, strict_range=strict_range,
                         check_crc=check_crc, check_counter=check_counter)
        proto.dbc_digest = digest
        if period is not None:
            proto.period_source = period_source
        elif proto.period is not None:
            proto.period_source = f"the GenMsgCycleTime of DBC {path.name}"
            positive_period(proto.period, proto.period_source)
        return proto

    def with_ids(self, rule: IdRule) -> Protocol:
        """This protocol with its mapped messages moved to the IDs of ``rule`` (one axis of
        several on a bus, :mod:`canrls.can.idrules`); the DBC stays as it is."""
        where = f"DBC {self.dbc_path}"
        messages = tuple(dataclasses.replace(
            m, frame_id=rule.frame_id(m.frame_id, m.is_extended, f"{where}: message {m.name}"))
            for m in self.messages)
        seen: dict[tuple[int, bool], str] = {}
        for m in messages:
            other = seen.setdefault((m.frame_id, m.is_extended), m.name)
            if other != m.name:
                raise ConfigError(f"{where}: ID rule {rule} puts messages {other} and "
                                  f"{m.name} both on ID 0x{m.frame_id:X}")
        proto = Protocol(self.db, self.dbc_path, self.is_default_dbc, self.mapping, self.roles,
                         messages, strict_range=self.strict_range, check_crc=self.check_crc,
                         check_counter=self.check_counter)
        proto.period_source = self.period_source
        proto.dbc_digest = self.dbc_digest
        proto.rule = rule
        return proto
    def changes(self, other: Protocol) -> list[str]:
        """The configuration keys in which ``other`` decodes differently from this
        protocol (``can.dbc``: another file, or the file changed; ``signals``: the
        mapping; the strict checks; the period): empty when the two decode alike."""
        out = []
        if (self.dbc_path.resolve() != other.dbc_path.resolve()
                or self.dbc_digest != other.dbc_digest):
            out.append("can.dbc")
        if self.mapping != other.mapping:
            out.append("signals")
        if self.rule != other.rule:
            out.append("can.ids")
        out += [f"can.{k}" for k in ("strict_range", "check_crc", "check_counter")
                if getattr(self, k) != getattr(other, k)]
        if self.period != other.period:
            out.append("can.period")
        return out

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
        signals (:func:`~canrls.core.units.axis_of`); None when the units do not say."""
        for role in ("speed", "position"):
            if role in self.roles and (ax := axis_of(self.roles[role].unit)) is not None:
                return ax
        return None


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
        # two messages of one name or ID: cantools keeps one, the DBC does not say which
        named = [m for m in db.messages if m.name == msg.name]
        if len(named) > 1:
            raise SignalError(
                f"{where}: {len(named)} messages are named {msg.name} ("
                + ", ".join(f"0x{m.frame_id:X}" for m in named) + f"; mapped to {role}): "
                f"which one is meant is not said; a DBC gives each message its own name")
        same_id = [m.name for m in db.messages if m is not msg and (
            m.frame_id, m.is_extended_frame) == (msg.frame_id, msg.is_extended_frame)]
        if same_id:
            raise SignalError(
                f"{where}: messages {msg.name} (mapped to {role}) and {', '.join(same_id)} "
                f"share the ID 0x{msg.frame_id:X}: a frame of one cannot be told from the "
                f"other's; a DBC gives each message its own ID")
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
        if sig.minimum is not None and sig.maximum is not None and sig.minimum > sig.maximum:
            raise SignalError(f"{where}: {spec.message}.{spec.signal} (mapped to {role}): "
                              f"minimum {sig.minimum:g} > maximum {sig.maximum:g}: every value "
                              f"would be out of range (swap them in the DBC)")
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
