"""Effect and equation identifiers, and the grammar of effect names.

The one place that says which effects exist, by name and by DBC id, which of them take
an argument after ``:``, and which id each equation carries. It sits in the bottom
layer (it imports only :mod:`canrls.core.errors`), so the protocol
(:mod:`canrls.can.estimator_frames`: commands and ``RlsParamInfo``) and the effect
library (:mod:`canrls.estimation.effects`) read the same table and the same grammar:

.. code-block:: text

    NAME        inertia | viscous | coulomb | stribeck | offset | unbalance | electrical
    cogging:K   K an integer >= 1, the harmonic order in position
    user:ARG    ARG the term's name (configuration) or its 1-based index (bus commands)

Names are case-insensitive and may carry spaces around the parts
(``" Cogging : 24 "`` is ``cogging:24``). The ids are the DBC value tables of
``EffectId`` and ``Equation`` (``VAL_ 771``); a test holds them against the DBC.

>>> parse_effect_name("cogging:24")
EffectName(effect=<EffectId.COGGING: 7>, order=24, term='')
>>> str(parse_effect_name("user:3", user="index"))
'user:3'
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from enum import IntEnum
from typing import Literal

from canrls.core.errors import EffectError

__all__ = ["EffectId", "EquationId", "EffectName", "MAX_ORDER", "VALID_EFFECTS",
           "parse_effect_name"]


class EffectId(IntEnum):
    """Effect identifiers, as in the DBC value table of ``EffectId``."""

    NONE = 0
    INERTIA = 1
    VISCOUS = 2
    COULOMB = 3
    STRIBECK = 4
    OFFSET = 5
    UNBALANCE = 6
    COGGING = 7
    ELECTRICAL = 8
    USER = 9

    @property
    def effect_name(self) -> str:
        """The effect's name on the command line (``"inertia"``, ``"cogging"``...)."""
        return self.name.lower()

    @property
    def takes_argument(self) -> bool:
        """True for ``cogging:K`` and ``user:ARG``, the effects named with an argument."""
        return self in (EffectId.COGGING, EffectId.USER)

    @classmethod
    def from_name(cls, name: str) -> EffectId:
        """The id of a base name (``"Viscous "`` -> VISCOUS); NONE when no effect has it."""
        key = name.strip().upper()
        return cls.NONE if key == "NONE" else cls.__members__.get(key, cls.NONE)


class EquationId(IntEnum):
    """The equation a parameter belongs to, as in the DBC value table of ``Equation``."""

    MECHANICAL = 0
    ELECTRICAL = 1

    @property
    def label(self) -> str:
        """``"mechanical"`` or ``"electrical"`` (the effect library's equation names)."""
        return self.name.lower()

    @classmethod
    def from_label(cls, label: str) -> EquationId:
        """``"electrical"`` -> ELECTRICAL; anything else is a :class:`EffectError`."""
        try:
            return cls[label.upper()]
        except (KeyError, AttributeError):
            raise EffectError(f"equation {label!r}: must be 'mechanical' or 'electrical'"
                              ) from None


#: The valid effect names, as error messages list them.
VALID_EFFECTS = ("inertia, viscous, coulomb, stribeck, offset, unbalance, cogging:K, "
                 "electrical, user:NAME")

_INTEGER = re.compile(r"[0-9]+")
#: Largest harmonic order K of ``cogging:K`` and index N of ``user:N``: what the 16-bit
#: ``Order`` field of canrls' parameter and command frames carries.
MAX_ORDER = 0xFFFF


@dataclass(frozen=True)
class EffectName:
    """A parsed effect name: the effect, its order and (configuration only) its term.

    ``order`` is the harmonic order K of ``cogging:K`` or the 1-based index of
    ``user:N`` on the bus (the DBC ``Order`` field), 0 otherwise; ``term`` the name of
    ``user:NAME`` in a configuration, "" otherwise.
    """

    effect: EffectId
    order: int = 0
    term: str = ""

    def __str__(self) -> str:
        arg = self.term or (str(self.order) if self.order else "")
        return f"{self.effect.effect_name}:{arg}" if arg else self.effect.effect_name


def parse_effect_name(spec: str, *, user: Literal["name", "index"] = "name") -> EffectName:
    """Split an effect name into its effect and argument, checking the grammar.

    :param spec: ``inertia``, ``cogging:24``, ``user:drag`` ...
    :param user: what follows ``user:``: a term ``"name"`` (configuration, command
        line) or an ``"index"`` >= 1 (commands on the bus, where a term is numbered).
    :raises EffectError: the base name is not an effect (the message lists the valid
        ones), ``cogging`` (or ``user``) lacks its argument or has a bad one, or
        another effect has an argument. :meth:`EffectId.from_name` of the part before
        ``:`` tells an unknown effect from a bad argument.
    """
    if not isinstance(spec, str):
        raise EffectError(f"effect {spec!r}: must be a string; valid effects: {VALID_EFFECTS}")
    base, sep, arg = spec.strip().partition(":")
    arg = arg.strip()
    effect = EffectId.from_name(base)
    if effect is EffectId.NONE:
        raise EffectError(f"unknown effect {spec!r}; valid effects: {VALID_EFFECTS}")
    if effect is EffectId.COGGING or (effect is EffectId.USER and user == "index"):
        if effect is EffectId.COGGING:
            what, letter, example = "harmonic order", "K", "cogging:24"
        else:
            what, letter, example = "term index", "N", "user:1"
        form = f"{effect.effect_name}:{letter}"
        if not sep or not arg:
            raise EffectError(f"effect {spec!r} needs a {what}: {form} with {letter} an "
                              f"integer >= 1 (e.g. {example})")
        # the digits are counted before int(): 5,000 of them exceed Python's limit
        if (not _INTEGER.fullmatch(arg) or len(arg.lstrip("0")) > len(str(MAX_ORDER))
                or not 1 <= int(arg) <= MAX_ORDER):
            shown = arg if len(arg) <= 20 else f"{arg[:20]}... ({len(arg)} characters)"
            raise EffectError(f"effect {effect.effect_name}:{letter}: {what} {letter} = "
                              f"{shown!r} must be an integer from 1 to {MAX_ORDER} ({form}; the "
                              f"16-bit Order field of canrls' frames)")
        return EffectName(effect, order=int(arg))
    if effect is EffectId.USER:
        if not sep or not arg:
            raise EffectError(f"effect {spec!r} needs a term name: user:NAME, with NAME "
                              f"defined in [[model.terms]]")
        return EffectName(effect, term=arg)
    if sep:
        raise EffectError(f"effect {spec!r}: {effect.effect_name!r} takes no argument "
                          f"after ':'; valid effects: {VALID_EFFECTS}")
    return EffectName(effect)
