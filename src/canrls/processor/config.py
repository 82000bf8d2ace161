"""The canrls configuration file (TOML) and how command-line options override it.

One reader (:func:`read_toml`), the command line's options applied once
(:class:`Overrides`) and one builder of (protocol, model, settings) for every command
(:func:`prepare`). The file's sections and keys: docs/configuration.md.
"""

from __future__ import annotations

import dataclasses
import re
import tomllib
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, NamedTuple

from canrls.can.eds import EdsDrive, NodeReader, read_eds
from canrls.can.idrules import parse_rule
from canrls.can.mapping import SignalMapping
from canrls.can.protocol import Protocol
from canrls.core.checks import is_positive, is_real
from canrls.core.errors import ConfigError, FixedPointError
from canrls.core.files import MAX_CONFIG_BYTES, check_path, read_bytes
from canrls.core.samples import ROLES
from canrls.core.units import RATING_OPTIONS, Ratings
from canrls.estimation.fixed.formats import QUANTITIES, QFormat
from canrls.estimation.model import OLD_OUTPUT_KEY, Model
from canrls.estimation.settings import EstimatorSettings
from canrls.processor.axes import (
    AxisSpec,
    check_own,
    check_shared,
    group_tables,
    own_offset,
    parse_axes,
    short_form,
)

__all__ = ["AppConfig", "DEFAULT_EFFECTS", "MAX_DEPTH", "MAX_INT_BITS", "Overrides", "Prepared",
           "load_config", "load_model", "prepare", "read_toml"]

#: Deepest nesting of tables and arrays a configuration file may have (ours need 3).
MAX_DEPTH = 16
#: TOML integers are 64-bit signed (the TOML spec: a value that cannot be represented
#: losslessly is an error); a longer one is refused with its key, never turned into inf.
MAX_INT_BITS = 63

#: Effects of the model when neither the configuration nor ``--effects`` name any.
DEFAULT_EFFECTS: tuple[str, ...] = ("inertia", "viscous", "coulomb")

#: ``[model.filter] held`` when the configuration does not set it: a cascaded drive holds
#: its current reference over the control period and its fast current loop tracks it, and
#: the inverter holds its voltage (the built-in simulated drive does the same).
DEFAULT_HELD: tuple[str, ...] = ("current", "voltage")

_SECTIONS = ("model", "estimator", "fixed", "can", "signals", "daemon", "monitor", "history",
             "axes", "fleet")
_ESTIMATOR_KEYS = {"lambda": "lam", "alpha": "alpha", "trace_max": "trace_max",
                   "warmup_s": "warmup_s", "gap_periods": "gap_periods",
                   "rms_time_s": "rms_time_s", "max_phase_step": "max_phase_step",
                   "min_speed": "min_speed", "calibration_s": "calibration_s"}
_FIXED_KEYS = ("word_bits", "acc_bits", "input_bits", "theta_max", "formats")
#: options of the command line that set a configuration key: (attribute, flag, table, key)
_FLAGS = (("kt", "--kt", "model", "kt"), ("axis", "--axis", "model", "axis"),
          ("lam", "--lambda", "estimator", "lambda"), ("alpha", "--alpha", "estimator", "alpha"),
          ("period", "--period", "can", "period"),
          *((key, flag, "signals", key) for key, (flag, _, _) in RATING_OPTIONS.items()))
_CAN_KEYS = ("dbc", "period", "strict_range", "check_crc", "check_counter", "interface",
             "channel", "bitrate", "fd", "data_bitrate", "ids", "eds")
#: ``[monitor]``: defaults of ``canrls monitor``'s options of the same names
_MONITOR_KEYS = {"interval": "a positive number of seconds",
                 "timeout": "a positive number of seconds", "plain": "true or false"}


@dataclass(frozen=True)
class Overrides:
    """What the command line sets over the configuration file, built once from the
    arguments by the command line (nothing below it sees them); hashable and picklable,
    so a fleet's workers take it as it is."""

    dbc: str | None = None
    #: ``--eds FILE``: a CiA 402 drive's EDS instead of a DBC
    eds: str | None = None
    signals: tuple[str, ...] = ()
    effects: str | None = None
    kt: float | None = None
    axis: str | None = None
    lam: float | None = None
    alpha: float | None = None
    period: float | None = None
    #: what relative units refer to (``--rated-torque``, ``--rated-current``,
    #: ``--increments-per-rev``)
    rated_torque: float | None = None
    rated_current: float | None = None
    increments_per_rev: float | None = None
    #: python-can's bus arguments (``-i -c -b --fd --data-bitrate --timing``,
    #: ``--bus-kwargs``), over ``[can]``
    bus: tuple[tuple[str, Any], ...] = ()
    #: ``--axes RULE:LIST``: the axes of the machine, over ``[[axes]]``
    axes: str | None = None
    #: ``--axis NAME``: the one axis a command works on
    axis_name: str | None = None
    #: ``--axis NAME --signal ... --axis NAME ...``: the axes declared on the command line,
    #: each (name, ((option, value), ...)) with option ``signal`` (a tuple), ``dbc``,
    #: ``eds`` or ``ids``; over ``[[axes]]``
    groups: tuple[tuple[str, tuple[tuple[str, Any], ...]], ...] = ()


class Prepared(NamedTuple):
    """What every command builds from a configuration (:func:`prepare`)."""

    protocol: Protocol
    model: Model
    settings: EstimatorSettings


def prepare(cfg: AppConfig) -> Prepared:
    """Protocol, model and settings from a configuration: the one builder of them. The
    ranges it does not give are measured by the front end on the calibration window
    (:mod:`canrls.processor`), live and offline alike: no first pass over a log. Of a
    machine's configuration, the axis :meth:`AppConfig.one_axis` picks."""
    cfg = cfg.one_axis()
    protocol = cfg.protocol()
    return Prepared(protocol, cfg.model_for(protocol), cfg.settings())


def read_toml(path: str | Path, table: str | None = None, *, key: str | None = None
              ) -> dict[str, Any]:
    """The document of TOML file ``path``, or its ``[table]`` when ``table`` is given.

    The one TOML reader of canrls. Every error is a :class:`ConfigError` whose message
    begins with the configuration ``key`` that named the file, if any, and the file:
    ``"daemon.model_file = m.toml: invalid TOML: Expected ']' ... (at line 1, column 7)"``,
    ``"drive.toml: cannot read: No such file or directory"``, ``"x.toml: no [model] table"``.
    """
    where = f"{key} = {path}" if key else str(path)
    p = check_path(path, where)
    # a regular file of bounded size: a FIFO or a device is refused, never opened
    text = read_bytes(p, where, limit=MAX_CONFIG_BYTES)
    try:
        doc = tomllib.loads(text.decode("utf-8"))
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as e:
        raise ConfigError(f"{where}: invalid TOML: {e}") from e
    except RecursionError as e:  # tomllib recurses once per nested array or inline table
        raise ConfigError(f"{where}: invalid TOML: nested deeper than {MAX_DEPTH} "
                          f"levels") from e
    except ValueError as e:  # e.g. an integer of more than sys.get_int_max_str_digits()
        raise ConfigError(f"{where}: invalid TOML: {e}") from e
    _check_limits(doc, where)
    if table is None:
        return doc
    if not isinstance(doc.get(table), dict):
        raise ConfigError(f"{where}: no [{table}] table")
    return dict(doc[table])


def _check_limits(doc: dict[str, Any], where: str) -> None:
    """Refuse nesting deeper than :data:`MAX_DEPTH` and integers beyond 64 bits, naming
    the key (walked with a stack: no recursion, linear in the document's size)."""
    stack: list[tuple[str, Any, int]] = [(k, v, 1) for k, v in doc.items()]
    while stack:
        key, v, depth = stack.pop()
        if depth > MAX_DEPTH:
            raise ConfigError(f"{where}: {key}: nested deeper than {MAX_DEPTH} levels")
        if isinstance(v, dict):
            stack.extend((f"{key}.{k}", x, depth + 1) for k, x in v.items())
        elif isinstance(v, list):
            stack.extend((f"{key}[{i}]", x, depth + 1) for i, x in enumerate(v))
        elif (isinstance(v, int) and not isinstance(v, bool)
              and not -(1 << MAX_INT_BITS) <= v < (1 << MAX_INT_BITS)):
            raise ConfigError(f"{where}: {key}: integer of {len(str(abs(v)))} digits is "
                              f"outside the 64-bit range of TOML")


def load_model(path: str | Path, *, available_signals: Iterable[str] | None = None) -> Model:
    """The model of the ``[model]`` table of TOML file ``path`` (errors name the file)."""
    return Model.from_dict(read_toml(path, "model"), source=str(path),
                           available_signals=available_signals)


@dataclass
class AppConfig:
    """The raw tables of a configuration file, with where they came from."""

    source: str = "<defaults>"
    base_dir: Path = field(default_factory=Path.cwd)
    model: dict[str, Any] = field(default_factory=dict)
    estimator: dict[str, Any] = field(default_factory=dict)
    fixed: dict[str, Any] = field(default_factory=dict)
    can: dict[str, Any] = field(default_factory=dict)
    signals: dict[str, Any] = field(default_factory=dict)
    daemon: dict[str, Any] = field(default_factory=dict)
    monitor: dict[str, Any] = field(default_factory=dict)
    #: ``[history]``: where ``canrls run`` appends its parameters (canrls.fleet.live_appender)
    history: dict[str, Any] = field(default_factory=dict)
    #: ``[fleet]``: what ``canrls fleet report`` alerts on (canrls.fleet.detect)
    fleet: dict[str, Any] = field(default_factory=dict)
    signal_overrides: list[str] = field(default_factory=list)
    #: configuration keys set from the command line, with the flag and value typed
    #: (``{"model.effects": "--effects inertia,foo"}``): errors name those, not the key
    flags: dict[str, str] = field(default_factory=dict)
    #: the bus arguments of the command line (over the bus keys of ``[can]``)
    bus: dict[str, Any] = field(default_factory=dict)
    #: the ``[[axes]]`` tables (``--axes`` replaces them); empty: one axis, the file's own
    axes: list[Any] = field(default_factory=list)
    #: ``--axis NAME``: the axis :meth:`one_axis` picks
    axis_name: str | None = None
    #: the ``--signal`` options of each axis's ``--axis NAME`` group (after the others)
    axis_signals: dict[str, list[str]] = field(default_factory=dict)
    #: on the bus (``canrls run``): reads an EDS drive's mapping and ratings from its
    #: node over SDO (None: the EDS's defaults)
    nodes: NodeReader | None = None

    # -- loading ----------------------------------------------------------------------
    @classmethod
    def load(cls, path: str | Path | None) -> AppConfig:
        """Read a TOML file (``None``: all defaults)."""
        if path is None:
            return cls()
        p = Path(path)
        d = read_toml(p)
        cfg = cls(source=str(p), base_dir=p.resolve().parent)
        for key, value in d.items():
            if key not in _SECTIONS:
                raise ConfigError(f"{p}: unknown section [{key}] (valid: {', '.join(_SECTIONS)})")
            if key == "axes":
                parse_axes(value, str(p))  # checked at the edge, kept as written
                cfg.axes = list(value)
                continue
            if not isinstance(value, dict):
                raise ConfigError(f"{p}: {key} must be a table, got {value!r}")
            setattr(cfg, key, dict(value))
        cfg.check()
        return cfg

    def check(self) -> None:
        """Every key of ``[estimator]``, ``[fixed]``, ``[can]`` and ``[monitor]`` is one
        canrls knows (a :class:`ConfigError` naming the first that is not)."""
        src = self.source
        for k in self.estimator:
            if k not in _ESTIMATOR_KEYS:
                raise ConfigError(f"{src}: unknown key estimator.{k} = {self.estimator[k]!r} "
                                  f"(valid: {', '.join(_ESTIMATOR_KEYS)})")
        for k in self.fixed:
            if k not in _FIXED_KEYS:
                raise ConfigError(f"{src}: unknown key fixed.{k} = {self.fixed[k]!r} "
                                  f"(valid: {', '.join(_FIXED_KEYS)})")
        for k in self.can:
            if k not in _CAN_KEYS:
                raise ConfigError(f"{src}: unknown key can.{k} = {self.can[k]!r} "
                                  f"(valid: {', '.join(_CAN_KEYS)})")
        for k, v in self.monitor.items():
            want = _MONITOR_KEYS.get(k)
            if want is None:
                raise ConfigError(f"{src}: unknown key monitor.{k} = {v!r} "
                                  f"(valid: {', '.join(_MONITOR_KEYS)})")
            ok = isinstance(v, bool) if k == "plain" else is_positive(v)
            if not ok:
                raise ConfigError(f"{src}: monitor.{k} = {v!r}: must be {want}")

    # -- command line -----------------------------------------------------------------
    def apply(self, over: Overrides) -> AppConfig:
        """Let the command line's :class:`Overrides` override the file."""
        if over.dbc:
            self.can["dbc"] = str(Path(over.dbc).resolve())
        if over.eds:
            self.can["eds"] = str(Path(over.eds).resolve())
        if over.signals:
            self.signal_overrides = list(over.signals)
        if over.effects:
            self.model["effects"] = [e.strip() for e in over.effects.split(",") if e.strip()]
            self.flags["model.effects"] = f"--effects {_typed(over.effects)}"
        for attr, flag, section, key in _FLAGS:
            v = getattr(over, attr)
            if v is not None:
                getattr(self, section)[key] = v
                self.flags[f"{section}.{key}"] = f"{flag} {_typed(v)}"
        self.bus.update(over.bus)
        if over.axes is not None:
            self.axes = short_form(over.axes)
            self.flags["axes"] = f"--axes {over.axes}"
        if over.groups:  # the command line never gives both (--axes: --axis picks)
            self.axes, self.axis_signals = group_tables(over.groups)
            self.flags["axes"] = "--axis groups"
        if over.axis_name is not None:
            self.axis_name = over.axis_name
        return self

    # -- axes -------------------------------------------------------------------------
    def axis_specs(self) -> tuple[AxisSpec, ...]:
        """The checked ``[[axes]]`` (or ``--axes``) of the configuration; () for one axis."""
        return parse_axes(self.axes, self.flags.get("axes") or self.source)

    def axis_configs(self) -> dict[str, AppConfig]:
        """Each axis's own configuration (its ``signals`` and ``model`` over the file's, its
        ID rule as ``[can] ids``), every axis's protocol built and no feedback signal
        shared: the whole machine checked before any axis starts."""
        specs = self.axis_specs()
        configs: dict[str, AppConfig] = {}
        protocols: dict[str, Protocol] = {}
        base: dict[str, Protocol] = {}  # one DBC read per distinct mapping, not per axis
        for spec in specs:
            c = dataclasses.replace(
                self, model={**self.model, **spec.model}, can=dict(self.can),
                signals={**self.signals, **spec.signals}, axes=[], axis_name=None,
                flags=dict(self.flags), source=f"{self.source} [axis {spec.name}]",
                signal_overrides=[*self.signal_overrides,
                                  *self.axis_signals.get(spec.name, ())], axis_signals={})
            if spec.rule is not None:
                c.can["ids"] = str(spec.rule)
            for k, other in (("dbc", "eds"), ("eds", "dbc")):  # the axis's own DBC or EDS
                if getattr(spec, k) is not None:
                    c.can[k] = getattr(spec, k)
                    c.can.pop(other, None)
            c.daemon = {**self.daemon, "own_ids": f"offset:{spec.own:#x}"}
            # an EDS read from each node: its own mapping, no rule to move it
            live = self.nodes is not None and self.can.get("eds") is not None
            key = repr((c.signals, c.signal_overrides,
                        {k: v for k, v in c.can.items() if k != "ids" or live},
                        c.model.get("axis")))
            try:
                proto = base.get(key)
                if proto is None:
                    proto = base[key] = c.protocol(with_rule=live)
                protocols[spec.name] = proto if live else c._moved(proto)
            except ConfigError as e:
                group = self.flags.get("axes") == "--axis groups"
                raise type(e)(f"{'--axis' if group else 'axis'} {spec.name}: {e}") from e
            configs[spec.name] = c
        check_shared(protocols)
        check_own({f"axis {n}": p for n, p in protocols.items()},
                  {f"axis {n}": own_offset(c.daemon["own_ids"], f"axis {n}: own")
                   for n, c in configs.items()})
        return configs

    def axis(self, name: str | None) -> AppConfig:
        """The configuration of axis ``name`` (None: of the only one, or of an axis-less
        configuration): :meth:`one_axis` with ``--axis NAME``."""
        return dataclasses.replace(self, axis_name=name).one_axis()

    def one_axis(self) -> AppConfig:
        """The configuration of the one axis a command works on: this one without axes,
        else the axis ``--axis NAME`` picks (or the only one), the others checked too."""
        if not self.axes:
            if self.axis_name is not None:
                raise ConfigError(f"--axis {self.axis_name}: the configuration declares no "
                                  f"axes ([[axes]] or --axes); --axis rotary|linear sets the "
                                  f"kind of axis")
            return self
        configs = self.axis_configs()
        if self.axis_name is None:
            if len(configs) == 1:
                return next(iter(configs.values()))
            raise ConfigError(f"{len(configs)} axes ({', '.join(configs)}): give --axis NAME "
                              f"for one")
        if self.axis_name not in configs:
            raise ConfigError(f"--axis {self.axis_name}: no such axis (axes: "
                              f"{', '.join(configs)})")
        return configs[self.axis_name]

    def _flagged(self, e: ConfigError) -> ConfigError:
        """``e`` with a configuration key set from the command line replaced by the flag
        and value typed: ``"--effects inertia,foo: unknown effect 'foo'..."``."""
        msg = str(e)
        for key, flag in self.flags.items():
            m = re.match(re.escape(f"{self.source}: {key}") + r"(\[\d+\])?( = .*?)?: ", msg)
            if m:
                return type(e)(f"{flag}: {msg[m.end():]}")
        return e

    # -- building ---------------------------------------------------------------------
    def _where(self, key: str) -> str:
        return f"{self.source}: {key}"

    def dbc_path(self) -> Path | None:
        dbc = self.can.get("dbc")
        if dbc is None:
            return None
        if not isinstance(dbc, str) or "\0" in dbc:
            raise ConfigError(f"{self._where('can.dbc')} = {dbc!r}: must be a file path"
                              + (" (no NUL byte)" if isinstance(dbc, str) else ""))
        p = Path(dbc)
        return p if p.is_absolute() else self.base_dir / p

    def ratings(self) -> Ratings:
        """What relative units refer to: ``[signals]`` ``rated_torque``, ``rated_current``,
        ``increments_per_rev`` (``--rated-torque``, ... override them)."""
        given = {}
        for key, (_, _, unit) in RATING_OPTIONS.items():
            if key not in self.signals:
                continue
            v = self.signals[key]
            if not is_positive(v):
                where = (self.flags.get(f"signals.{key}")
                         or f"{self._where('signals.' + key)} = {v!r}")
                raise ConfigError(f"{where}: must be a positive number ({unit})")
            given[key] = float(v)
        return Ratings(**given)

    def _eds(self) -> tuple[Path, EdsDrive] | None:
        """``[can] eds`` (``--eds``): the path and what the EDS tells (on the bus, with
        :attr:`nodes`, read from the node of ``[can] ids = "cia402:N"``, node 1 without
        a rule); None without one."""
        eds = self.can.get("eds")
        if eds is None:
            return None
        if not isinstance(eds, str) or "\0" in eds:
            raise ConfigError(f"{self._where('can.eds')} = {eds!r}: must be a file path")
        if self.can.get("dbc") is not None:
            raise ConfigError(f"{self._where('can.eds')} = {eds}: give a DBC (can.dbc, "
                              f"--dbc) or an EDS (can.eds, --eds), not both")
        p = Path(eds) if Path(eds).is_absolute() else self.base_dir / eds
        node = None
        if self.nodes is not None:
            ids = self.can.get("ids")
            rule = None if ids is None else parse_rule(ids, self._where("can.ids"))
            node = 1 if rule is None else rule.node if rule.kind == "cia402" else None
        return p, read_eds(p, node=node, reader=self.nodes)

    def protocol(self, *, with_rule: bool = True) -> Protocol:
        """The DBC and signal mapping (``--signal`` options replace roles of ``[signals]``),
        its messages moved by the ID rule ``[can] ids`` unless ``with_rule`` is false. With
        an EDS, its TPDOs and the roles of its 402 objects, the ratings it gives under
        those configured."""
        mapping: SignalMapping | None = None
        ratings = self.ratings()
        eds = self._eds()
        if eds is not None:
            # the node's own values, else the flags, else the EDS's defaults
            node = {k: v for k, v in eds[1].ratings.as_dict().items() if k in eds[1].from_node}
            ratings = Ratings(**{**eds[1].ratings.as_dict(), **ratings.as_dict(), **node})
            mapping = SignalMapping.from_strings(eds[1].signals)
        table = {k: v for k, v in self.signals.items() if k not in RATING_OPTIONS}
        if table:
            own = SignalMapping.from_config(table, source=f"{self.source} [signals]")
            mapping = own if mapping is None else dataclasses.replace(
                mapping, roles={**mapping.roles, **own.roles})
        if self.signal_overrides:
            base = mapping if mapping is not None else (
                SignalMapping.default() if self.dbc_path() is None else None)
            mapping = SignalMapping.from_strings(self.signal_overrides, base=base)
        if ratings.as_dict():
            mapping = dataclasses.replace(mapping or SignalMapping.default(), ratings=ratings)
        period = self.can.get("period")
        opts = {k: self.can[k] for k in ("strict_range", "check_crc", "check_counter")
                if k in self.can}
        for k, v in opts.items():
            if not isinstance(v, bool):
                raise ConfigError(f"{self._where('can.' + k)} = {v!r}: must be true or false")
        where = self.flags.get("can.period") or self._where("can.period")
        axis = self.model.get("axis")
        proto = Protocol.load(eds[0] if eds else self.dbc_path(), mapping, period=period,
                              period_source=where, axis=axis if isinstance(axis, str) else None,
                              dbc_bytes=eds[1].dbc_text.encode("cp1252") if eds else None,
                              **opts)
        if eds is not None and eds[1].node is not None:
            return proto  # the TPDOs on the IDs the node itself reported
        return self._moved(proto) if with_rule else proto

    def _moved(self, proto: Protocol) -> Protocol:
        """``proto`` on the IDs of the rule ``[can] ids`` (as it is without one)."""
        if "ids" not in self.can:
            return proto
        return proto.with_ids(parse_rule(self.can["ids"], self._where("can.ids")))

    def model_for(self, protocol: Protocol | None = None,
                  data_ranges: Mapping[str, Any] | None = None) -> Model:
        """The model.

        Signal ranges for the normalisation, by priority: ``[model.ranges]``, then
        ``data_ranges`` (e.g. :func:`canrls.processor.scan_ranges`), then the defaults
        of :data:`canrls.estimation.model.DEFAULT_RANGES`. The DBC's min/max are the protocol's
        limits (often ten times what the drive reaches) and serve strict decoding only:
        normalising by them would leave the regressors tiny, costing fixed-point
        resolution and letting the ridge prior bias the weakly scaled parameters.
        """
        d = dict(self.model)
        d.setdefault("effects", list(DEFAULT_EFFECTS))
        kt = d.get("kt")
        if isinstance(kt, int | float) and not isinstance(kt, bool) and not kt > 0:
            where = self.flags.get("model.kt") or f"{self._where('model.kt')} = {kt!r}"
            raise ConfigError(f"{where}: the torque constant must be positive (a motor "
                              f"turning the other way: swap the sign of the current signal)")
        if "axis" not in d and protocol is not None and protocol.axis is not None:
            d["axis"] = protocol.axis  # from the DBC units of speed and position
        torque = protocol is not None and protocol.has("torque")
        if torque:
            # the torque the drive reports is the mechanical output: no Kt
            key = OLD_OUTPUT_KEY if OLD_OUTPUT_KEY in d else "output"
            d.setdefault(key, "torque")
            if d[key] == "torque" and d.get("kt") is not None:
                assert protocol is not None
                where = self.flags.get("model.kt") or f"{self._where('model.kt')} = {kt!r}"
                sig = protocol.roles["torque"]
                raise ConfigError(
                    f"{where}: the drive reports its torque ({sig.message}.{sig.signal}), "
                    f"the mechanical output: the parameters come out in N·m (linear axis: "
                    f"N) without Kt; leave Kt out, or set [model] output = \"current\" to "
                    f"identify on the current with Kt")
        filt = d.get("filter", {})
        if isinstance(filt, Mapping):
            filt = dict(filt)
            # a reported torque follows the held current reference as the current does
            filt.setdefault("held", list(DEFAULT_HELD) + (["torque"] if torque else []))
            d["filter"] = filt
        available = None
        if protocol is not None:
            available = [r for r in ROLES if protocol.has(r)]
        ranges = d.get("ranges", {})
        if isinstance(ranges, Mapping) and data_ranges:
            ranges = dict(ranges)
            for role, r in data_ranges.items():
                ranges.setdefault(role, list(r))
            d["ranges"] = ranges
        try:
            return Model.from_dict(d, source=self.source, available_signals=available)
        except ConfigError as e:
            raise self._flagged(e) from e

    def settings(self) -> EstimatorSettings:
        kw: dict[str, Any] = {}
        for k, v in self.estimator.items():
            if not is_real(v):
                raise self._flagged(ConfigError(
                    f"{self._where('estimator.' + k)} = {v!r}: must be a number"))
            kw[_ESTIMATOR_KEYS[k]] = v
        for k in ("word_bits", "acc_bits", "input_bits"):
            if k in self.fixed:
                v = self.fixed[k]
                if isinstance(v, bool) or not isinstance(v, int):
                    raise ConfigError(f"{self._where('fixed.' + k)} = {v!r}: must be an integer")
                kw[k] = v
        if "theta_max" in self.fixed:
            v = self.fixed["theta_max"]
            if not is_positive(v):
                raise ConfigError(f"{self._where('fixed.theta_max')} = {v!r}: must be a "
                                  f"positive number")
            kw["theta_max"] = float(v)
        formats = self.fixed.get("formats", {})
        if not isinstance(formats, Mapping):
            raise ConfigError(f"{self._where('fixed.formats')} = {formats!r}: must be a table")
        overrides = {}
        for name, v in formats.items():
            where = self._where('fixed.formats.' + name)
            if name not in QUANTITIES:
                raise ConfigError(f"{where}: no such quantity (valid: {', '.join(QUANTITIES)})")
            if (not isinstance(v, list) or len(v) != 2
                    or not all(isinstance(x, int) and not isinstance(x, bool) for x in v)):
                raise ConfigError(f"{where} = {v!r}: must be [bits, frac]")
            try:
                overrides[name] = QFormat(v[0], v[1])
            except FixedPointError as e:  # the one rule of a Q format's bits and frac
                raise ConfigError(f"{where} = {v!r}: {e}") from e
        kw["fixed_overrides"] = overrides
        try:
            return EstimatorSettings(**kw)
        except ConfigError as e:
            raise self._flagged(ConfigError(f"{self.source}: {e}")) from e


def _typed(value: object, most: int = 200) -> str:
    """A value typed on the command line as an error repeats it: at most ``most``
    characters (5,000 digits are named by their count)."""
    text = str(value)
    return text if len(text) <= most else f"{text[:most]}... ({len(text)} characters)"


def load_config(path: str | Path | None, overrides: Overrides | None = None) -> AppConfig:
    """Read the file (if any) and apply the command line's overrides."""
    cfg = AppConfig.load(path)
    return cfg.apply(overrides) if overrides is not None else cfg
