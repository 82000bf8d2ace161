"""The axes of a machine: several drives on one bus, each its own name, ID rule, signals and
model (the ``[[axes]]`` tables and ``--axes`` of docs/configuration.md).

:func:`parse_axes` checks the tables once, at the edge; :func:`check_shared` refuses two
axes that would decode the same feedback signal. :meth:`AppConfig.axis_configs
<canrls.processor.config.AppConfig.axis_configs>` builds each axis's configuration.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

from canrls.can.estimator_frames import frame_ids
from canrls.can.idrules import MAX_AXES, MAX_STANDARD_ID, IdRule, parse_rule, parse_rules
from canrls.can.protocol import Protocol
from canrls.core.errors import ConfigError

__all__ = ["AXIS_KINDS", "AXIS_KEYS", "OWN_STEP", "AxisSpec", "check_name", "check_own",
           "check_shared", "own_offset", "parse_axes", "short_form"]

#: values of ``--axis`` that name the kind of axis, not an axis: no axis may be called so
AXIS_KINDS = ("rotary", "linear")
#: keys of one ``[[axes]]`` table
AXIS_KEYS = ("name", "ids", "own", "signals", "model")
#: IDs between two axes' own frames by default: axis k (0-based) publishes on the shipped
#: DBC's IDs + k * 0x40 (``[daemon] own_ids = "offset:..."``)
OWN_STEP = 0x40


@dataclass(frozen=True)
class AxisSpec:
    """One ``[[axes]]`` table, checked: the axis's ``name``, its ID ``rule`` (None: the
    DBC's own IDs) and the ``signals`` and ``model`` keys it sets over the file's."""

    name: str
    rule: IdRule | None = None
    #: the offset of its own frames (``own``; default: index * :data:`OWN_STEP`)
    own: int = 0
    signals: Mapping[str, Any] = field(default_factory=dict)
    model: Mapping[str, Any] = field(default_factory=dict)


def check_name(name: object, where: str) -> str:
    """An axis name: an ASCII identifier (it names C symbols, JSON keys and checkpoint
    files) other than :data:`AXIS_KINDS`."""
    if not (isinstance(name, str) and name.isascii() and name.isidentifier()):
        raise ConfigError(f"{where} = {name!r}: an axis name must be an identifier (letters, "
                          f"digits, _; not starting with a digit)")
    if name in AXIS_KINDS:
        raise ConfigError(f"{where} = {name!r}: {' and '.join(AXIS_KINDS)} name the kind of "
                          f"axis (--axis rotary|linear), not an axis")
    return name


def parse_axes(tables: object, source: str) -> tuple[AxisSpec, ...]:
    """The ``[[axes]]`` tables of ``source`` as :class:`AxisSpec`, each checked (unknown
    keys, names, rules), counted first: more than :data:`MAX_AXES` is refused unread."""
    if not isinstance(tables, Sequence) or isinstance(tables, str):
        raise ConfigError(f"{source}: axes must be an array of tables ([[axes]])")
    if len(tables) > MAX_AXES:
        raise ConfigError(f"{source}: {len(tables)} [[axes]] tables; canrls serves at most "
                          f"{MAX_AXES} axes on one bus")
    specs: list[AxisSpec] = []
    seen: dict[str, int] = {}
    for i, t in enumerate(tables):
        where = f"{source}: axes[{i}]"
        if not isinstance(t, Mapping):
            raise ConfigError(f"{where} must be a table, got {t!r}")
        for k in t:
            if k not in AXIS_KEYS:
                raise ConfigError(f"{where}: unknown key {k} = {t[k]!r} "
                                  f"(valid: {', '.join(AXIS_KEYS)})")
        if "name" not in t:
            raise ConfigError(f"{where}: name is required (an identifier, e.g. \"joint1\")")
        name = check_name(t["name"], f"{where}.name")
        if name in seen:
            raise ConfigError(f"{where}.name = {name!r}: also the name of axes[{seen[name]}]")
        seen[name] = i
        rule = parse_rule(t["ids"], f"{where}.ids") if "ids" in t else None
        own = own_offset(t["own"], f"{where}.own") if "own" in t else i * OWN_STEP
        tabs = {}
        for k in ("signals", "model"):
            v = t.get(k, {})
            if not isinstance(v, Mapping):
                raise ConfigError(f"{where}.{k} must be a table, got {v!r}")
            tabs[k] = dict(v)
        specs.append(AxisSpec(name, rule, own, tabs["signals"], tabs["model"]))
    return tuple(specs)


def short_form(text: str) -> list[dict[str, Any]]:
    """``--axes RULE:LIST`` as ``[[axes]]`` tables (``cia402:1-6``: ``node1`` .. ``node6``)."""
    return [{"name": name, "ids": str(rule)} for name, rule in parse_rules(text)]


def own_offset(text: object, where: str) -> int:
    """The offset of an ``"offset:N"`` rule of canrls' own frames (``own``,
    ``[daemon] own_ids``): the only rule they take, all of them moved alike."""
    rule = parse_rule(text, where)
    if rule.kind != "offset":
        raise ConfigError(f"{where} = {text!r}: canrls' own frames move by an offset only "
                          f"(\"offset:N\")")
    return rule.node


#: what :func:`check_own` tells an axis of ``[[axes]]`` to do
AXIS_OWN_HINT = 'give the axis another own = "offset:N"'


def check_own(protocols: Mapping[str, Protocol], offsets: Mapping[str, int],
              hint: str = AXIS_OWN_HINT) -> None:
    """Refuse an axis's own frame (parameters, status, command, ack: the shipped DBC's
    IDs + its offset) beyond the standard IDs or on the ID of another own frame or of
    any axis's feedback frame (one ``ConfigError`` naming both frames and ending in
    ``hint``); the keys of ``protocols`` and ``offsets`` name the axes (``"axis a"``,
    ``"the drive"``)."""
    owner: dict[int, str] = {}
    for name, proto in protocols.items():
        for m in proto.messages:
            if not m.is_extended:
                owner.setdefault(m.frame_id, f"{name}'s feedback {m.name}")
    for name, off in offsets.items():
        for fid, msg in frame_ids().own.items():
            new = fid + off
            what = f"{name}'s {msg}"
            if not 0 <= new <= MAX_STANDARD_ID:
                raise ConfigError(f"{what} would be on ID {new:#x}, outside the standard IDs "
                                  f"0x0..0x7FF: {hint}")
            other = owner.setdefault(new, what)
            if other != what:
                raise ConfigError(f"{what} and {other} would both be on ID 0x{new:X}: {hint}")


def check_shared(protocols: Mapping[str, Protocol]) -> None:
    """Refuse two axes that decode the same feedback signal of the same frame (one
    ``ConfigError`` naming both axes, the signal and the ID)."""
    owner: dict[tuple[int, bool, str], str] = {}
    for name, proto in protocols.items():
        for m in proto.messages:
            for r in m.roles:
                key = (m.frame_id, m.is_extended, r.signal)
                other = owner.setdefault(key, name)
                if other != name:
                    raise ConfigError(
                        f"axes {other} and {name} both map feedback signal "
                        f"{m.name}.{r.signal} on ID 0x{m.frame_id:X}: give each axis its own "
                        f"ID rule (ids = \"cia402:N\", ...) or its own signals")
