"""A CiA 402 drive from its EDS file instead of a DBC: the object dictionary and the
default TPDO mapping read with the ``canopen`` library (``pip install 'canrls[cia402]'``),
turned into the DBC text and the signal mapping canrls decodes with (:func:`read_eds`).

Roles come from the 402 objects (:data:`ROLE_OBJECTS`), the units from theirs: per
mille of the rated torque 0x6076 or current 0x6075, increments of the position encoder
(0x608F: increments per motor revolution). The EDS's default values of these give the
ratings; a rating the EDS lacks is asked for by its flag. Docs: docs/cia402.md.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

from canrls.core.errors import ConfigError
from canrls.core.units import Ratings

__all__ = ["ROLE_OBJECTS", "EdsDrive", "read_eds"]

#: CiA 402 object -> (role, DBC unit): torque actual value 0x6077 (‰ of 0x6076), current
#: actual value 0x6078 (‰ of 0x6075), velocity actual value 0x606C (increments/s),
#: position actual value 0x6064 (increments)
ROLE_OBJECTS: dict[int, tuple[str, str]] = {
    0x6077: ("torque", "‰"), 0x6078: ("current", "‰"),
    0x606C: ("speed", "inc/s"), 0x6064: ("position", "inc"),
}
#: TPDOs a CiA 301 device may have (communication 0x1800.., mapping 0x1A00..)
_TPDOS = 512


@dataclass(frozen=True)
class EdsDrive:
    """What an EDS tells canrls: the DBC text of its TPDOs (node 1's COB-IDs; an ID rule
    ``cia402:N`` moves them), the mapping ``ROLE=MESSAGE.SIGNAL`` of each 402 object
    found, and the ratings from the EDS's defaults."""

    dbc_text: str
    signals: tuple[str, ...]
    ratings: Ratings


def _name(text: str) -> str:
    """A DBC identifier from an object's name (``Torque actual value`` -> ``TorqueActualValue``)."""
    out = "".join(w[:1].upper() + w[1:] for w in re.findall(r"[A-Za-z0-9]+", text))
    return out if out[:1].isalpha() else f"Object{out}"


def _default(od: object, index: int, sub: int | None = None) -> float | None:
    """The default value of object ``index`` (``sub``) if the EDS has it."""
    try:
        obj = od[index] if sub is None else od[index][sub]  # type: ignore[index]
    except KeyError:
        return None
    v = getattr(obj, "default", None)
    return float(v) if isinstance(v, int | float) and v > 0 else None


def read_eds(path: str | Path) -> EdsDrive:
    """The DBC text, the mapping and the ratings of the EDS at ``path`` (its default TPDO
    mapping, node 1). Errors (:class:`ConfigError`) name the file and the object."""
    try:
        import canopen
        from canopen.objectdictionary import datatypes
    except ImportError as e:
        raise ConfigError(f"--eds {path}: reading an EDS needs the canopen library "
                          f"(pip install 'canrls[cia402]')") from e
    where = f"EDS {path}"
    try:
        od = canopen.import_od(str(path), node_id=1)
    except Exception as e:  # canopen's parser raises what configparser and int() raise
        raise ConfigError(f"cannot read {where}: {e}") from e
    lines = ['VERSION "canrls: the TPDOs of ' + Path(path).name.replace('"', "'") + '"',
             "", "NS_ :", "", "BS_:", "", "BU_: Drive Host", ""]
    signals: list[str] = []
    for k in range(_TPDOS):
        if 0x1A00 + k not in od or 0x1800 + k not in od:
            continue
        cob = _default(od, 0x1800 + k, 1)
        count = _default(od, 0x1A00 + k, 0)
        if cob is None or not count or int(cob) & 0x80000000:
            continue  # no COB-ID, nothing mapped, or the PDO is not valid
        start, sigs = 0, []
        for i in range(1, int(count) + 1):
            entry = int(_default(od, 0x1A00 + k, i) or 0)
            index, sub, bits = entry >> 16, (entry >> 8) & 0xFF, entry & 0xFF
            if index in ROLE_OBJECTS:
                try:
                    obj = od[index] if sub == 0 and not hasattr(od[index], "subindices") \
                        else od[index][sub]
                except KeyError:
                    raise ConfigError(f"{where}: TPDO{k + 1} maps 0x{index:04X}sub{sub}, "
                                      f"which the object dictionary lacks") from None
                role, unit = ROLE_OBJECTS[index]
                signed = obj.data_type in datatypes.SIGNED_TYPES
                lo, hi = ((-(1 << (bits - 1)), (1 << (bits - 1)) - 1) if signed
                          else (0, (1 << bits) - 1))
                name = _name(obj.name)
                sigs.append(f' SG_ {name} : {start}|{bits}@1{"-" if signed else "+"} (1,0) '
                            f'[{lo}|{hi}] "{unit}" Host')
                signals.append(f"{role}=TPDO{k + 1}.{name}")
            start += bits
        if sigs:
            lines += [f"BO_ {int(cob) & 0x7FF} TPDO{k + 1}: {(start + 7) // 8} Drive", *sigs, ""]
    if not signals:
        raise ConfigError(f"{where}: no TPDO maps the torque, current, velocity or position "
                          f"actual value (0x6077, 0x6078, 0x606C, 0x6064)")
    # 0x6075 [mA], 0x6076 [mN·m]; 0x608F: increments (sub 1) per motor revolutions (sub 2)
    current, torque = _default(od, 0x6075), _default(od, 0x6076)
    inc, revs = _default(od, 0x608F, 1), _default(od, 0x608F, 2)
    ratings = Ratings(rated_current=None if current is None else current / 1000.0,
                      rated_torque=None if torque is None else torque / 1000.0,
                      increments_per_rev=None if inc is None else inc / (revs or 1.0))
    return EdsDrive("\n".join(lines) + "\n", tuple(signals), ratings)
