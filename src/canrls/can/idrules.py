"""ID rules: where one axis's frames sit on a bus shared by several drives.

A rule maps each frame ID of the DBC to the ID of one axis (:class:`IdRule`):
CiA 402 (``COB-ID = function code + node``), ODrive CANSimple (``node << 5 | command``)
and "the DBC's IDs + an offset". :func:`parse_rule` reads the text form
(``"cia402:3"``, ``"cansimple:2"``, ``"offset:0x20"``) that ``[can] ids`` and ``[[axes]]``
take; :func:`parse_rules` the short form of ``--axes`` (docs/configuration.md).
"""

from __future__ import annotations

import re
from dataclasses import dataclass

from canrls.core.errors import ConfigError

__all__ = ["MAX_AXES", "MAX_EXTENDED_ID", "MAX_STANDARD_ID", "RULES", "IdRule", "parse_rule",
           "parse_rules"]

#: Highest 11-bit (standard) and 29-bit (extended) CAN identifier.
MAX_STANDARD_ID = 0x7FF
MAX_EXTENDED_ID = 0x1FFFFFFF
#: Most axes one configuration may declare: the nodes of one CiA 402 network (1..127).
MAX_AXES = 127
#: rule -> (first node, last node, what the node is); ``offset`` takes an offset instead
RULES: dict[str, tuple[int, int, str]] = {
    "cia402": (1, 127, "a CANopen node ID"),
    "cansimple": (0, 62, "an ODrive CANSimple node ID (63 is the broadcast)"),
    "offset": (-MAX_EXTENDED_ID, MAX_EXTENDED_ID, "an offset added to the DBC's IDs"),
}
_INT = r"[+-]?(?:0[xX][0-9A-Fa-f]+|\d+)"
_RULE_RE = re.compile(rf"^\s*(?P<rule>[a-z0-9]+)\s*:\s*(?P<n>{_INT})\s*$")
_LIST_RE = re.compile(rf"^\s*(?P<a>{_INT})\s*(?:-\s*(?P<b>{_INT}))?\s*$")


@dataclass(frozen=True)
class IdRule:
    """One axis's ID rule: ``kind`` (a key of :data:`RULES`) and its ``node`` (the offset
    for ``offset``). :meth:`frame_id` maps a DBC frame ID to the axis's."""

    kind: str
    node: int

    def __str__(self) -> str:
        n = f"{self.node:#x}" if self.kind == "offset" else str(self.node)
        return f"{self.kind}:{n}"

    def frame_id(self, frame_id: int, extended: bool, where: str) -> int:
        """The axis's ID of the DBC's ``frame_id``; a :class:`ConfigError` naming ``where``
        (the message) and the rule when the result is no ID of the frame's kind."""
        if self.kind == "offset":
            # ID' = ID + offset
            new = frame_id + self.node
        elif extended:
            raise ConfigError(f"{where}: ID rule {self}: 0x{frame_id:X} is an extended "
                              f"(29-bit) ID; {self.kind} numbers 11-bit IDs")
        elif self.kind == "cia402":
            # COB-ID = function code (ID & 0x780) + node
            new = (frame_id & 0x780) | self.node
        else:
            # CANSimple: ID = node << 5 | command (ID & 0x1F)
            new = (self.node << 5) | (frame_id & 0x1F)
        top = MAX_EXTENDED_ID if extended else MAX_STANDARD_ID
        if not 0 <= new <= top:
            kind = "extended" if extended else "standard"
            raise ConfigError(f"{where}: ID rule {self} puts 0x{frame_id:X} at "
                              f"{'-' if new < 0 else ''}0x{abs(new):X}, outside the "
                              f"{kind} IDs 0x0..0x{top:X}")
        return new


def _int(text: str, where: str) -> int:
    try:
        return int(text, 0)
    except ValueError:
        raise ConfigError(f"{where}: {text!r} is not an integer") from None


def _rule(kind: str, node: int, where: str) -> IdRule:
    if kind not in RULES:
        raise ConfigError(f"{where}: unknown ID rule {kind!r} (valid: {', '.join(RULES)})")
    lo, hi, what = RULES[kind]
    if not lo <= node <= hi:
        raise ConfigError(f"{where}: {kind} node {node} is outside {lo}..{hi} ({what})")
    return IdRule(kind, node)


def parse_rule(text: object, where: str) -> IdRule:
    """``"cia402:N"``, ``"cansimple:N"`` or ``"offset:N"`` (N decimal or ``0x`` hex) as an
    :class:`IdRule`; ``where`` names the key or flag in errors."""
    m = _RULE_RE.match(text) if isinstance(text, str) else None
    if m is None:
        raise ConfigError(f"{where} = {text!r}: expected RULE:N with RULE one of "
                          f"{', '.join(RULES)} (e.g. \"cia402:3\", \"offset:0x20\")")
    return _rule(m["rule"], _int(m["n"], where), f"{where} = {text}")


def parse_rules(text: str, where: str = "--axes") -> list[tuple[str, IdRule]]:
    """The axes of the short form ``RULE:LIST`` (``cia402:1-6``, ``cansimple:0,1,2``,
    ``offset:0,0x20,0x40``), each as (name, rule): ``nodeN`` for a node, ``axisI``
    (1, 2, ...) for an offset. At most :data:`MAX_AXES`, counted before any is built."""
    kind, sep, rest = text.partition(":")
    kind = kind.strip()
    if not sep or kind not in RULES:
        raise ConfigError(f"{where} {text}: expected RULE:LIST with RULE one of "
                          f"{', '.join(RULES)} and LIST like 1-6 or 1,3,5")
    numbers: list[int] = []
    for part in rest.split(","):
        m = _LIST_RE.match(part)
        if m is None:
            raise ConfigError(f"{where} {text}: {part.strip()!r} is not a number or a range "
                              f"A-B")
        a = _int(m["a"], f"{where} {text}")
        b = a if m["b"] is None else _int(m["b"], f"{where} {text}")
        if b < a:
            raise ConfigError(f"{where} {text}: range {a}-{b} runs backwards")
        if len(numbers) + b - a + 1 > MAX_AXES:
            raise ConfigError(f"{where} {text}: {len(numbers) + b - a + 1} axes or more; "
                              f"canrls serves at most {MAX_AXES} on one bus")
        numbers.extend(range(a, b + 1))
    if len(set(numbers)) != len(numbers):
        dup = next(n for n in numbers if numbers.count(n) > 1)
        raise ConfigError(f"{where} {text}: {dup} is given twice")
    axes = []
    for i, n in enumerate(numbers, 1):
        name = f"axis{i}" if kind == "offset" else f"node{n}"
        axes.append((name, _rule(kind, n, f"{where} {text}")))
    return axes
