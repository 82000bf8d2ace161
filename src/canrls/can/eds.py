"""A CiA 402 drive from its EDS file instead of a DBC: the object dictionary and the
TPDO mapping read with the ``canopen`` library (``pip install 'canrls[cia402]'``),
turned into the DBC text and the signal mapping canrls decodes with (:func:`read_eds`).

Roles come from the 402 objects (:data:`ROLE_OBJECTS`), the units from theirs: per
mille of the rated torque 0x6076 or current 0x6075, position units per motor revolution
from the factor group (0x608F encoder resolution, 0x6091 gear, 0x6092 feed). On the bus
(``canrls run``) a :class:`NodeReader` uploads the TPDO mapping and these objects from
the node over SDO (never a download); a value the node does not give comes from the
EDS's defaults, one neither gives from its flag. Docs: docs/cia402.md.
"""

from __future__ import annotations

import logging
import re
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from canrls.core.errors import ConfigError
from canrls.core.units import Ratings

__all__ = ["ROLE_OBJECTS", "SDO_TIMEOUT", "EdsDrive", "NodeReader", "read_eds"]

#: CiA 402 object -> (role, DBC unit): torque actual value 0x6077 (‰ of 0x6076), current
#: actual value 0x6078 (‰ of 0x6075), velocity actual value 0x606C (position units/s),
#: position actual value 0x6064 (position units)
ROLE_OBJECTS: dict[int, tuple[str, str]] = {
    0x6077: ("torque", "‰"), 0x6078: ("current", "‰"),
    0x606C: ("speed", "inc/s"), 0x6064: ("position", "inc"),
}
#: TPDOs a CiA 301 device may have (communication 0x1800.., mapping 0x1A00..)
_TPDOS = 512
#: what each rating is counted in, for the lines that say where it came from
_UNITS = {"rated_current": " A", "rated_torque": " N·m (linear: N)",
          "increments_per_rev": " position units per motor revolution"}
#: seconds an SDO upload waits for the node's answer (canopen's default, 0.3 s)
SDO_TIMEOUT = 0.3


class _Abort(Exception):
    """The node aborted an upload (its abort code said)."""


class _Silent(Exception):
    """The node did not answer an upload."""


#: a value of the object dictionary: ``get(index, sub)`` (sub None: a variable), None
#: when absent; a node's raises :class:`_Abort` or :class:`_Silent`
_Getter = Callable[[int, "int | None"], "int | None"]


@dataclass(frozen=True)
class EdsDrive:
    """What an EDS (and the node, on the bus) tells canrls: the DBC text of its TPDOs,
    the mapping ``ROLE=MESSAGE.SIGNAL`` of each 402 object found, the ratings, and where
    each came from (``sources``, one phrase each). ``node``: the TPDOs are that node's
    own IDs (read from it; no ID rule moves them); None: node 1's, an ID rule
    ``cia402:N`` moves them. ``from_node``: the ratings the node gave (over any flag)."""

    dbc_text: str
    signals: tuple[str, ...]
    ratings: Ratings
    sources: tuple[str, ...] = ()
    node: int | None = None
    from_node: frozenset[str] = field(default_factory=frozenset)


def _name(text: str) -> str:
    """A DBC identifier from an object's name (``Torque actual value`` -> ``TorqueActualValue``)."""
    out = "".join(w[:1].upper() + w[1:] for w in re.findall(r"[A-Za-z0-9]+", text))
    return out if out[:1].isalpha() else f"Object{out}"


def _entry(od: Any, index: int, sub: int | None) -> Any:
    """The variable ``index`` (sub-index ``sub`` of a record or array) of ``od``;
    KeyError if absent."""
    obj = od[index]
    return obj[sub or 0] if hasattr(obj, "subindices") else obj


def _eds_getter(od: Any) -> _Getter:
    """The EDS's default values."""
    def get(index: int, sub: int | None) -> int | None:
        try:
            v = getattr(_entry(od, index, sub), "default", None)
        except KeyError:
            return None
        return int(v) if isinstance(v, int | float) else None
    return get


class NodeReader:
    """Uploads objects from CiA 402 nodes over SDO (``canopen``'s client; never a
    download) on a bus ``open_bus()`` opens at the first upload and :meth:`close`
    closes; each node's values are read once (:meth:`getter`)."""

    def __init__(self, open_bus: Callable[[], Any], timeout: float = SDO_TIMEOUT) -> None:
        self._open = open_bus
        self.timeout = timeout
        self._cache: dict[tuple[int, int | None], int | None | _Abort] = {}
        self._silent: set[int] = set()
        self._net: Any = None
        #: node -> what :func:`read_eds` said of its values' sources
        self.said: dict[int, tuple[str, ...]] = {}

    def getter(self, node: int, od: Any) -> _Getter:
        """``get(index, sub)`` of node ``node`` (decoded by ``od``'s types), cached;
        :class:`_Silent` once the node has not answered."""
        def get(index: int, sub: int | None) -> int | None:
            if index not in od:  # the EDS describes what the node has: not asked
                return None
            if node in self._silent:
                raise _Silent(f"no SDO answer in {self.timeout:g} s")
            key = (node, (index << 8) | (sub or 0))
            if key not in self._cache:
                self._cache[key] = self._upload(node, od, index, sub)
            v = self._cache[key]
            if isinstance(v, _Abort):
                raise v
            return v
        return get

    def _upload(self, node: int, od: Any, index: int, sub: int | None) -> int | None | _Abort:
        import canopen

        if self._net is None:
            self._net = canopen.Network(self._open())
            self._net.connect()
        remote = self._net.nodes.get(node)
        if remote is None:
            remote = self._net.add_node(canopen.RemoteNode(node, od))
            remote.sdo.RESPONSE_TIMEOUT = self.timeout
            remote.sdo.MAX_RETRIES = 1  # one request, no repetition
        quiet = logging.getLogger("canopen")
        level = quiet.level
        quiet.setLevel(logging.CRITICAL)  # its timeout lines: said once, in sources
        try:
            data = remote.sdo.upload(index, sub or 0)
        except canopen.SdoAbortedError as e:
            return _Abort(f"SDO abort 0x{e.code:08X} on 0x{index:04X}sub{sub or 0}")
        except canopen.SdoCommunicationError:
            self._silent.add(node)
            raise _Silent(f"no SDO answer in {self.timeout:g} s") from None
        finally:
            quiet.setLevel(level)
        try:
            v = _entry(od, index, sub).decode_raw(data)
        except (KeyError, ValueError, TypeError, AttributeError) as e:
            return _Abort(f"0x{index:04X}sub{sub or 0}: {len(data)} bytes the EDS's "
                          f"type does not decode ({e})")
        return int(v) if isinstance(v, int | float) else None

    def close(self) -> None:
        """Close the bus the uploads used (opened again by the next)."""
        net, self._net = self._net, None
        if net is not None:
            net.disconnect()


def _tpdos(od: Any, get: _Getter) -> list[tuple[int, int, list[tuple[int, int, int]]]]:
    """(k, COB-ID, [(index, sub, bits)]) of each valid TPDO ``k`` (0-based) of ``od``,
    the values from ``get``."""
    out = []
    for k in range(_TPDOS):
        if 0x1A00 + k not in od or 0x1800 + k not in od:
            continue
        cob = get(0x1800 + k, 1)
        count = get(0x1A00 + k, 0)
        if not cob or not count or cob & 0x80000000:
            continue  # no COB-ID, nothing mapped, or the PDO is not valid
        entries = []
        for i in range(1, count + 1):
            e = get(0x1A00 + k, i) or 0
            entries.append((e >> 16, (e >> 8) & 0xFF, e & 0xFF))
        # COB-ID bit 29: an extended (29-bit) CAN ID
        out.append((k, cob & (0x1FFFFFFF if cob & 0x20000000 else 0x7FF), entries))
    return out


def _ratio(get: _Getter, index: int) -> float | None:
    """``sub1 / sub2`` of a CiA 402 ratio object (0x608F, 0x6091, 0x6092; sub2 0 or
    absent: 1), None without a positive sub1."""
    num = get(index, 1)
    if not num or num <= 0:
        return None
    den = get(index, 2)
    return num / (den if den and den > 0 else 1)


def _units_per_rev(get: _Getter) -> tuple[float | None, str]:
    """Position units of 0x6064 per motor revolution and the objects it came from: with
    the feed constant 0x6092 (feed per driving-shaft revolution), feed / gear (0x6091:
    motor per shaft revolutions); else the encoder's increments per motor revolution
    (0x608F), the position units being increments."""
    feed = _ratio(get, 0x6092)
    if feed is not None:
        gear = _ratio(get, 0x6091)
        # units/motor rev = (feed / shaft rev) / (motor revs / shaft rev)
        return feed / (gear or 1.0), "0x6092 / 0x6091" if gear else "0x6092"
    return _ratio(get, 0x608F), "0x608F"


def _import(path: str | Path, node: int) -> Any:
    try:
        import canopen
    except ImportError as e:
        raise ConfigError(f"--eds {path}: reading an EDS needs the canopen library "
                          f"(pip install 'canrls[cia402]')") from e
    try:
        return canopen.import_od(str(path), node_id=node)
    except Exception as e:  # canopen's parser raises what configparser and int() raise
        raise ConfigError(f"cannot read EDS {path}: {e}") from e


def read_eds(path: str | Path, *, node: int | None = None,
             reader: NodeReader | None = None) -> EdsDrive:
    """The DBC text, the mapping and the ratings of the EDS at ``path``: its default
    TPDO mapping at node 1; with a ``reader`` and a ``node``, each value read from
    that node over SDO first (a silent node or an aborted upload: the EDS's, said in
    ``sources``). Errors (:class:`ConfigError`) name the file and the object."""
    from canopen.objectdictionary import datatypes

    where = f"EDS {path}"
    od = _import(path, node if reader is not None and node is not None else 1)
    eds = _eds_getter(od)
    sources: list[str] = []
    tpdos = None
    who = f"node {node}"
    node_get = reader.getter(node, od) if reader is not None and node is not None else None
    if node_get is not None:
        try:
            tpdos = _tpdos(od, node_get)
            differs = tpdos != _tpdos(od, eds)
            sources.append(f"{who}: TPDO mapping read over SDO"
                           + (f" (not the default of {where}: the node's used)"
                              if differs else ""))
        except _Silent as e:
            node_get = None
            sources.append(f"{who}: {e} (not on the bus?): mapping and ratings from {where} "
                           f"and flags")
        except _Abort as e:
            sources.append(f"{who}: {e}: TPDO mapping from {where}")
    if tpdos is None:
        tpdos = _tpdos(od, eds)
    lines = ['VERSION "canrls: the TPDOs of ' + Path(path).name.replace('"', "'") + '"',
             "", "NS_ :", "", "BS_:", "", "BU_: Drive Host", ""]
    signals: list[str] = []
    for k, cob, entries in tpdos:
        start, sigs = 0, []
        for index, sub, bits in entries:
            if index in ROLE_OBJECTS:
                try:
                    obj = _entry(od, index, sub)
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
            fid = cob | 0x80000000 if cob > 0x7FF else cob  # a DBC's extended-ID flag
            lines += [f"BO_ {fid} TPDO{k + 1}: {(start + 7) // 8} Drive", *sigs, ""]
    if not signals:
        raise ConfigError(f"{where}: no TPDO maps the torque, current, velocity or position "
                          f"actual value (0x6077, 0x6078, 0x606C, 0x6064)")
    ratings, from_node = _ratings(eds, node_get, who, where, sources)
    if reader is not None and node is not None:
        reader.said[node] = tuple(sources)
    return EdsDrive("\n".join(lines) + "\n", tuple(signals), ratings, tuple(sources),
                    node if node_get is not None else None, frozenset(from_node))


def _ratings(eds: _Getter, node_get: _Getter | None, who: str, where: str,
             sources: list[str]) -> tuple[Ratings, set[str]]:
    """The ratings from the node (each it gives), else the EDS's defaults; the keys the
    node gave. 0x6075 [mA], 0x6076 [mN·m] -> A, N·m."""
    values: dict[str, float] = {}
    from_node: set[str] = set()
    fetch: dict[str, Callable[[_Getter], tuple[float | None, str]]] = {
        "rated_current": lambda g: (_milli(g(0x6075, None)), "0x6075"),
        "rated_torque": lambda g: (_milli(g(0x6076, None)), "0x6076"),
        "increments_per_rev": _units_per_rev,
    }
    for key, f in fetch.items():
        v, objs = None, ""
        if node_get is not None:
            try:
                v, objs = f(node_get)
                src = f"{who} over SDO"
            except _Abort as e:
                sources.append(f"{who}: {e}")
            except _Silent:
                pass
        if v is not None:
            from_node.add(key)
        else:
            v, objs = f(eds)
            src = f"{where} default"
        if v is not None:
            values[key] = v
            sources.append(f"{key.replace('_', ' ')} {v:g}{_UNITS[key]} from {src} ({objs})")
    return Ratings(**values), from_node


def _milli(v: int | None) -> float | None:
    """mA or mN·m to A or N·m; None for an absent or non-positive value."""
    return v / 1000.0 if v is not None and v > 0 else None
