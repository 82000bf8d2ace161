"""Which DBC signal carries each role (current, speed, position, voltage, torque), its
unit or scale to SI, and each message's alive counter and CRC: :class:`SignalMapping`."""

from __future__ import annotations

import math
import re
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from typing import Any

from canrls.core.checks import is_positive
from canrls.core.errors import ConfigError
from canrls.core.samples import ROLES
from canrls.core.units import RATING_OPTIONS, Ratings

__all__ = ["REQUIRED_ROLES", "EFFORT_ROLES", "RoleSpec", "SignalMapping"]


#: Roles every mapping must fill; ``position`` and ``voltage`` are optional.
REQUIRED_ROLES: tuple[str, ...] = ("speed",)
#: A mapping fills at least one of these: the current, or the torque (force) the drive
#: reports; with both, the torque is the mechanical target and the current feeds the
#: electrical equation.
EFFORT_ROLES: tuple[str, ...] = ("current", "torque")



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
        :class:`~canrls.core.units.Ratings`::

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
            if not is_positive(v):
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
