"""A live view of what a canrls daemon publishes (``canrls monitor``).

:class:`Monitor` is a python-can :class:`~can.Listener`: give it to a
:class:`~can.Notifier` on any bus (SocketCAN, virtual, ``remote`` from another
process) and call :meth:`Monitor.snapshot` whenever a view is wanted::

    mon = Monitor(units=LibraryUnits.for_model(model))
    with can.Notifier(bus, [mon]):
        time.sleep(2)
        print(mon.snapshot().format())

A snapshot has every parameter (fixed-point value, ±σ, float reference, their
difference, the unit), the residual RMS with its recent trend, frame rates by kind,
the loss and rejection counters (by reason, from ``RlsRejects``, with the clock
steps and gaps of the feedback's timestamps, and ``time`` from ``RlsHealth``), the
health flags (``clock_fault`` among
them), the active effects and the last command acknowledgement. Parameter names come
from ``RlsParamInfo`` and the units from the effect library (:class:`LibraryUnits`),
which needs the axis, ``kt`` and the user terms of the daemon's model: the monitor
takes the same ``--config``.
"""

from __future__ import annotations

import collections
import math
import threading
import time
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import can

from canrls.can.estimator_frames import (
    CommandAck,
    CommandCode,
    FrameDecoder,
    ParameterReport,
    StatusReport,
    frame_ids,
)
from canrls.core.checks import check_lambda
from canrls.core.effect_names import EffectId
from canrls.core.errors import ConfigError
from canrls.estimation.effects import output_unit, parse_effect
from canrls.estimation.model import Model
from canrls.live.bus_link import moved

__all__ = ["AxesMonitor", "AxesView", "LibraryUnits", "Monitor", "MonitorView", "axis_rows",
           "parse_command_text"]

_IDS = frame_ids()  # of the default DBC, which the daemon publishes with
_ESTIMATOR_IDS = _IDS.published
_COMMAND_ID = _IDS.command
_ACK_ID = _IDS.ack
_KINDS = ("feedback", "estimator", "command", "error", "other")


class LibraryUnits(Mapping[str, str]):
    """Parameter name -> unit, from the effect library, for one axis, output and terms.

    ``units["cogging:24.sin"] == "N·m"`` (rotary, kt known); any effect the library
    can build is answered, so a monitor started before an effect is added still knows
    its unit. Unknown names are absent.
    """

    def __init__(self, options: Mapping[str, Any] | None = None, kt_known: bool = True) -> None:
        self.options = dict(options or {"axis": "rotary"})
        self.kt_known = kt_known
        self._cache: dict[str, str | None] = {}

    @classmethod
    def for_model(cls, model: Model) -> LibraryUnits:
        return cls(model.effect_options, model.torque_known)

    def _lookup(self, name: str) -> str | None:
        if name in self._cache:
            return self._cache[name]
        effect, _, _sym = name.rpartition(".")
        unit = None
        try:
            eff = parse_effect(effect, self.options)
            for p in eff.parameters(self.kt_known):
                if p.name == name:
                    unit = p.unit
        except (ConfigError, KeyError, TypeError, ValueError):
            unit = None
        self._cache[name] = unit
        return unit

    def __getitem__(self, name: str) -> str:
        u = self._lookup(name)
        if u is None:
            raise KeyError(name)
        return u

    def __iter__(self) -> Iterator[str]:
        return iter(k for k, v in self._cache.items() if v is not None)

    def __len__(self) -> int:
        return sum(1 for v in self._cache.values() if v is not None)

    def output_unit(self) -> str:
        return output_unit("mechanical", self.options.get("axis", "rotary"), self.kt_known)


@dataclass(frozen=True)
class MonitorView:
    """One snapshot of the monitor (render with :meth:`format` or :meth:`to_dict`)."""

    time: float
    parameters: tuple[ParameterReport, ...]
    count: int | None
    status: StatusReport | None
    rms_unit: str
    rms_trend: float | None          # relative change of the residual RMS over trend_s
    rms_min: float | None
    rms_max: float | None
    trend_s: float
    rates: Mapping[str, float]       # frames/s by kind over the last window
    totals: Mapping[str, int]        # frames by kind since start
    last_ack: CommandAck | None
    malformed: int
    source: str = ""
    extra: Mapping[str, Any] = field(default_factory=dict)

    @property
    def complete(self) -> bool:
        """Every parameter of the last RlsParamInfo has a value, and a status arrived."""
        if self.count is None or self.status is None:
            return False
        got = [p for p in self.parameters if p.index < self.count]
        return len(got) == self.count and all(
            p.name and (p.float_value is not None or p.fixed_value is not None or not p.valid)
            for p in got)

    def effects(self) -> list[str]:
        if self.status is None:
            return []
        return [e.effect_name for e in sorted(self.status.effects())]

    def to_dict(self) -> dict[str, Any]:
        s = self.status
        return {
            "source": self.source,
            "parameters": {(p.name or f"#{p.index}"): {
                "index": p.index, "fixed": p.fixed_value, "sigma": p.sigma,
                "float": p.float_value, "unit": p.unit, "valid": p.valid}
                for p in self.parameters},
            "count": self.count,
            "residual_rms": None if s is None else s.residual_rms,
            "rms_unit": self.rms_unit,
            "rms_trend": self.rms_trend,
            "update_count": None if s is None else s.update_count,
            "flags": [] if s is None else list(s.flags),
            "effects": self.effects(),
            "divergence": None if s is None else s.divergence,
            "counters": {} if s is None else {
                "frames_rejected": s.frames_rejected, "frames_lost": s.frames_lost,
                "saturations": s.saturations, "tx_dropped": s.tx_dropped},
            "rejects": {} if s is None else dict(s.rejects),
            "rates": dict(self.rates),
            "totals": dict(self.totals),
            "last_ack": None if self.last_ack is None else {
                "command": _command_name(self.last_ack.command),
                "result": self.last_ack.result.name.lower()},
            "malformed": self.malformed,
        }

    def format(self, color: bool = False) -> str:
        """Readable text (a table of parameters, then status lines)."""
        lines = []
        stamp = time.strftime("%H:%M:%S", time.localtime(self.time))
        head = f"canrls monitor  {self.source}  {stamp}"
        lines.append(head)
        params = [p for p in self.parameters if self.count is None or p.index < self.count]
        if not params:
            lines.append("  (no parameter frames yet)")
        else:
            w = max([len(p.name or f"#{p.index}") for p in params] + [9])
            lines.append(f"  {'parameter':<{w}}  {'fixed':>12}  {'± sigma':>10}  "
                         f"{'float':>12}  {'fix-flt':>8}  unit")
            for p in params:
                name = p.name or f"#{p.index}"
                lines.append(f"  {name:<{w}}  {_num(p.fixed_value, p.valid):>12}  "
                             f"{_num(p.sigma):>10}  {_num(p.float_value):>12}  "
                             f"{_rel(p.fixed_value, p.float_value, p.valid):>8}  {p.unit}")
        s = self.status
        if s is None:
            lines.append("  (no status frames yet)")
        else:
            trend = ""
            if self.rms_trend is not None and math.isfinite(self.rms_trend):
                arrow = "↓" if self.rms_trend < -0.05 else "↑" if self.rms_trend > 0.05 else "→"
                trend = f"  {arrow} {self.rms_trend * 100:+.0f} % over {self.trend_s:g} s"
                if self.rms_min is not None and self.rms_max is not None:
                    trend += f" (min {self.rms_min:.4g}, max {self.rms_max:.4g})"
            lines.append(f"  residual RMS {_num(s.residual_rms)} {self.rms_unit}{trend}")
            lines.append(f"  updates {s.update_count}   float-vs-fixed divergence "
                         f"{s.divergence:.2e}   effects: {', '.join(self.effects()) or '-'}")
            flags = ", ".join(s.flags)
            if color and flags:
                flags = f"\x1b[31m{flags}\x1b[0m"
            lines.append(f"  health: {flags or 'ok'}")
            lines.append(f"  counters: rejected {s.frames_rejected}  lost {s.frames_lost}  "
                         f"saturations {s.saturations}  tx dropped {s.tx_dropped}")
            odd = [f"{k.replace('_', ' ')} {v}" for k, v in s.rejects.items() if v]
            if odd:  # RlsRejects, by reason (wrapping counters)
                lines.append(f"  rejects: {'  '.join(odd)}")
        rates = "  ".join(f"{k} {self.rates.get(k, 0.0):.0f}" for k in _KINDS
                          if self.totals.get(k))
        lines.append(f"  frames/s: {rates or '-'}")
        if self.last_ack is not None:
            lines.append(f"  last command: {_command_name(self.last_ack.command)} -> "
                         f"{self.last_ack.result.name.lower()}")
        return "\n".join(lines)

    __str__ = format


#: the commands a tool can send, as :func:`parse_command_text` reads them
COMMAND_WORDS = "reset, freeze, resume, add EFFECT, remove EFFECT, lambda L, save"


@dataclass(frozen=True)
class AxesView:
    """One snapshot of every axis's monitor (:class:`AxesMonitor`)."""

    views: Mapping[str, MonitorView]

    @property
    def complete(self) -> bool:
        """Every axis's view is complete."""
        return all(v.complete for v in self.views.values())

    def to_dict(self) -> dict[str, Any]:
        return {"axes": {n: v.to_dict() for n, v in self.views.items()}}

    def format(self, color: bool = False) -> str:
        return axis_rows(self.views)


class AxesMonitor:
    """The monitors of a machine's axes, by name (each a listener of the same bus): a
    snapshot of them all is one row per axis."""

    def __init__(self, monitors: Mapping[str, Monitor]) -> None:
        self.monitors = dict(monitors)
        self.source = next(iter(self.monitors.values())).source if self.monitors else ""

    @property
    def error(self) -> Exception | None:
        return next((m.error for m in self.monitors.values() if m.error is not None), None)

    def snapshot(self) -> AxesView:
        return AxesView({n: m.snapshot() for n, m in self.monitors.items()})


def axis_rows(views: Mapping[str, MonitorView]) -> str:
    """The view of a machine's axes: a head line, then one row per axis (residual RMS,
    updates, health, effects, frames/s of its feedback and of its own frames)."""
    w = max([len(n) for n in views] + [4])
    first = next(iter(views.values()), None)
    stamp = time.strftime("%H:%M:%S", time.localtime(first.time)) if first else ""
    lines = [f"canrls monitor  {first.source if first else ''}  {stamp}  {len(views)} axes",
             f"  {'axis':<{w}}  {'residual RMS':>12}  {'updates':>8}  {'feedback/s':>10}  "
             f"{'canrls/s':>8}  health  effects"]
    for name, v in views.items():
        s = v.status
        rms = "-" if s is None else f"{_num(s.residual_rms)} {v.rms_unit}".strip()
        lines.append(f"  {name:<{w}}  {rms:>12}  {'-' if s is None else s.update_count:>8}  "
                     f"{v.rates.get('feedback', 0.0):>10.0f}  "
                     f"{v.rates.get('estimator', 0.0):>8.0f}  "
                     f"{'-' if s is None else ', '.join(s.flags) or 'ok'}  "
                     f"{', '.join(v.effects()) or '-'}")
    return "\n".join(lines)


def _num(x: float | None, valid: bool = True) -> str:
    if x is None or not valid:
        return "-"
    if isinstance(x, float) and math.isnan(x):
        return "nan"
    return f"{x:.5g}"


def _rel(a: float | None, b: float | None, valid: bool = True) -> str:
    if a is None or b is None or not valid or not (math.isfinite(a) and math.isfinite(b)):
        return "-"
    ref = max(abs(a), abs(b))
    return "0 %" if ref == 0 else f"{(a - b) / ref * 100:+.2f} %"


def _command_name(code: int) -> str:
    try:
        return CommandCode(code).name.lower()
    except ValueError:
        return f"code {code}"


class Monitor(can.Listener):
    """Collects the daemon's frames (thread-safe); :meth:`snapshot` renders them.

    :param units: parameter name -> unit (e.g. :class:`LibraryUnits`).
    :param user_names: names of user terms by order (1-based), as the configuration.
    :param feedback_ids: arbitration IDs of the drive's feedback (counted as ``feedback``).
    :param window_s: frame rates are averaged over this window.
    :param trend_s: the residual RMS trend compares now with this long ago.
    """

    def __init__(self, units: Mapping[str, str] | None = None, user_names: Sequence[str] = (),
                 feedback_ids: Sequence[int] = _IDS.feedback, window_s: float = 2.0,
                 trend_s: float = 10.0, rms_unit: str | None = None,
                 source: str = "", own_offset: int = 0) -> None:
        self.decoder = FrameDecoder(user_names=tuple(user_names),
                                    units=units if units is not None else {})
        self.feedback_ids = frozenset(feedback_ids)
        #: the axis's own frames are the shipped IDs + this (``[daemon] own_ids``)
        self.own_offset = own_offset
        self._own = frozenset(i + own_offset for i in _IDS.own)
        self.window_s = window_s
        self.trend_s = trend_s
        if rms_unit is None:
            rms_unit = units.output_unit() if isinstance(units, LibraryUnits) else ""
        self.rms_unit = rms_unit
        self.source = source
        self._lock = threading.Lock()
        self._arrivals: dict[str, collections.deque[float]] = {
            k: collections.deque() for k in _KINDS}
        self._totals: collections.Counter[str] = collections.Counter()
        self._rms: collections.deque[tuple[float, float]] = collections.deque()
        self._ack_event = threading.Condition(self._lock)
        #: The last exception raised by the bus's ``recv`` (None: none).
        self.error: Exception | None = None

    # -- listener ----------------------------------------------------------------------
    def on_message_received(self, msg: can.Message) -> None:
        now = time.monotonic()
        aid = msg.arbitration_id
        if msg.is_error_frame:
            kind = "error"
        elif msg.is_extended_id:
            kind = "other"
        elif aid in self.feedback_ids:
            kind = "feedback"
        elif self.own_offset and aid not in self._own:
            kind = "other"  # another axis's own frames, or none of canrls'
        else:
            if self.own_offset:  # this axis's own frame, as the shipped DBC has it
                msg = moved(msg, -self.own_offset)
                aid = msg.arbitration_id
            kind = ("estimator" if aid in _ESTIMATOR_IDS or aid == _ACK_ID else
                    "command" if aid == _COMMAND_ID else "other")
        with self._lock:
            self._totals[kind] += 1
            q = self._arrivals[kind]
            q.append(now)
            while q and q[0] < now - self.window_s:
                q.popleft()
            if kind in ("estimator", "command"):
                out = self.decoder.feed(msg)
                if aid == _IDS.status and isinstance(out, StatusReport):
                    self._rms.append((now, out.residual_rms))
                    while self._rms and self._rms[0][0] < now - 3 * self.trend_s:
                        self._rms.popleft()
                elif isinstance(out, CommandAck):
                    self._ack_event.notify_all()

    def on_error(self, exc: Exception) -> None:
        """The bus's ``recv`` raised (interface gone): remembered in :attr:`error`."""
        self.error = exc
        time.sleep(0.1)  # the notifier retries at once: do not spin

    # -- views -------------------------------------------------------------------------
    def snapshot(self) -> MonitorView:
        now = time.monotonic()
        with self._lock:
            d = self.decoder
            rates = {}
            for k, q in self._arrivals.items():
                while q and q[0] < now - self.window_s:
                    q.popleft()
                if q:
                    span = min(self.window_s, max(now - q[0], 1e-3))
                    rates[k] = len(q) / span if len(q) > 1 else 0.0
            trend = rmin = rmax = None
            recent = [(t, r) for t, r in self._rms
                      if t >= now - self.trend_s and math.isfinite(r)]
            if recent:
                rmin = min(r for _, r in recent)
                rmax = max(r for _, r in recent)
                old = recent[0][1]
                if len(recent) > 1 and old > 0:
                    trend = recent[-1][1] / old - 1.0
            return MonitorView(
                time=time.time(), parameters=tuple(d.table()), count=d.count, status=d.status,
                rms_unit=self.rms_unit, rms_trend=trend, rms_min=rmin, rms_max=rmax,
                trend_s=self.trend_s, rates=rates, totals=dict(self._totals),
                last_ack=d.acks[-1] if d.acks else None, malformed=d.malformed,
                source=self.source)

    def rms_history(self) -> list[tuple[float, float]]:
        """(monotonic time, residual RMS) of every RlsStatus of the last 3 trend windows."""
        with self._lock:
            return list(self._rms)

    @property
    def acks(self) -> list[CommandAck]:
        with self._lock:
            return list(self.decoder.acks)

    def wait_ack(self, after: int, timeout: float) -> CommandAck | None:
        """Wait until more than ``after`` acknowledgements arrived; the newest or None."""
        end = time.monotonic() + timeout
        with self._lock:
            while len(self.decoder.acks) <= after:
                left = end - time.monotonic()
                if left <= 0:
                    return None
                self._ack_event.wait(left)
            return self.decoder.acks[-1]


def parse_command_text(text: str) -> tuple[CommandCode, EffectId, int, float]:
    """``"add cogging:6"``, ``"remove unbalance"``, ``"lambda 0.999"``, ``"reset"``...

    Returns (code, effect, order, lambda). Raises :class:`ConfigError` when it does not
    parse.
    """
    from canrls.can.estimator_frames import parse_effect as parse_effect_id

    words = text.strip().split()
    if not words:
        raise ConfigError(f"empty command ({COMMAND_WORDS})")
    verb = words[0].lower().replace("-", "_")
    aliases = {"add": "add_effect", "remove": "remove_effect", "lambda": "set_lambda",
               "save": "save_model"}
    verb = aliases.get(verb, verb)
    try:
        code = CommandCode[verb.upper()]
    except KeyError:
        raise ConfigError(f"unknown command {words[0]!r} ({COMMAND_WORDS})") from None
    if code in (CommandCode.ADD_EFFECT, CommandCode.REMOVE_EFFECT):
        if len(words) != 2:
            raise ConfigError(f"{text!r}: {verb} needs one effect, e.g. '{words[0]} cogging:6'")
        try:
            eid, order = parse_effect_id(words[1])
        except ValueError as e:
            raise ConfigError(f"{text!r}: {e}") from e
        return code, eid, order, 0.0
    if code is CommandCode.SET_LAMBDA:
        try:
            lam = float(words[1]) if len(words) == 2 else math.nan
        except ValueError:
            lam = math.nan
        try:
            return code, EffectId.NONE, 0, check_lambda(lam, f"{text!r}: lambda")
        except ConfigError as e:
            raise ConfigError(f"{e} (e.g. 'lambda 0.9995')") from None
    if len(words) != 1:
        raise ConfigError(f"{text!r}: {verb} takes no argument")
    return code, EffectId.NONE, 0, 0.0

