"""The simulated drive as a python-can interface: ``can.Bus(interface="canrls-sim")``.

:class:`SimBus` is python-can's ``virtual`` bus with a drive on it: one simulated drive
per channel sends its feedback frames (CRC and alive counter included) to every
``canrls-sim`` and ``virtual`` bus on the channel, so the daemon, ``python -m
can.logger``, ``cantools monitor`` and a test's ``virtual`` bus run against it
unchanged. Channels, timing and keyword arguments: docs/simulator.md, "The python-can
interface ``canrls-sim``".
"""

from __future__ import annotations

import logging
import math
import queue
import threading
import time
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import can
from can.interfaces import virtual as _virtual
from can.interfaces.virtual import VirtualBus

from canrls.can.frameblock import FrameBlock
from canrls.core.errors import ConfigError
from canrls.sim.faults import FaultLog, FaultSpec
from canrls.sim.scenario import DEFAULT_EFFECTS, SCENARIOS, Scenario, Simulator, scenario

__all__ = ["SimBus"]

log = logging.getLogger(__name__)

#: Control periods simulated per chunk in real time (10 ms) and as fast as consumed.
_CHUNK_REALTIME = 10
_CHUNK_FAST = 200


def _parse_bool(key: str, v: Any) -> bool:
    if isinstance(v, bool):
        return v
    if isinstance(v, (int, float)) and v in (0, 1):
        return bool(v)
    if isinstance(v, str) and v.strip().lower() in ("1", "true", "yes", "on"):
        return True
    if isinstance(v, str) and v.strip().lower() in ("0", "false", "no", "off"):
        return False
    raise ConfigError(f"canrls-sim: {key}: {v!r} is not a boolean")


def _parse_float(key: str, v: Any) -> float:
    try:
        f = float(str(v).strip().rstrip("s")) if isinstance(v, str) else float(v)
    except (TypeError, ValueError) as e:
        raise ConfigError(f"canrls-sim: {key}: {v!r} is not a number") from e
    if math.isnan(f):
        raise ConfigError(f"canrls-sim: {key}: {v!r} is not a number")
    return f


def _parse_int(key: str, v: Any) -> int:
    try:
        f = float(v)
        iv = int(f)
    except (TypeError, ValueError) as e:
        raise ConfigError(f"canrls-sim: {key}: {v!r} is not an integer") from e
    if f != iv:
        raise ConfigError(f"canrls-sim: {key}: {v!r} is not an integer")
    return iv


def _machine_given(axes: Any, ids: Any, given: dict[str, Any]) -> dict[str, Any]:
    """``axes`` and ``ids`` of a machine, checked (one drive's options refused)."""
    from canrls.sim.machine import KINDS, MAX_SIM_AXES

    n = _parse_int("axes", axes)
    if not 1 <= n <= MAX_SIM_AXES:
        raise ConfigError(f"canrls-sim: axes: {n} is not 1 to {MAX_SIM_AXES}")
    kind = "offset" if ids is None else str(ids)
    if kind not in KINDS:
        raise ConfigError(f"canrls-sim: ids: {kind!r} is not one of {', '.join(KINDS)}")
    one = [k for k in ("effects", "faults", "axis", "excitation", "params") if k in given]
    if one:
        raise ConfigError(f"canrls-sim: {one[0]}: a machine's drives have their own "
                          f"(axes={n})")
    return {"axes": n, "ids": kind}


def _scenario_of_channel(channel: Any) -> str:
    name = str(channel)
    if name in SCENARIOS:
        return name
    head = name.split(":", 1)[0]
    return head if head in SCENARIOS else "standard"


@dataclass(frozen=True)
class _DriveConfig:
    scenario: str
    effects: str
    seed: int
    faults: str
    duration: float
    realtime: bool
    axis: str | None
    excitation: str | None
    params: tuple[tuple[str, float], ...]
    #: a machine of this many drives (0: one drive), of kind ``ids``
    axes: int = 0
    ids: str = "offset"


class _Drive:
    """The simulated drive of one channel, shared by the SimBus instances on it."""

    def __init__(self, channel: Any, config: _DriveConfig, start_time: float) -> None:
        self.channel = channel
        self.config = config
        self.scenario: Scenario = scenario(
            config.scenario, effects=config.effects, seed=config.seed, faults=config.faults,
            duration=config.duration, axis=config.axis, excitation=config.excitation,
            params=dict(config.params))
        self.sim = Simulator(self.scenario, t0=start_time)
        #: a machine's drives (:mod:`canrls.sim.machine`); empty: the one drive ``sim``
        self.sims: list[Simulator] = []
        if config.axes:
            from canrls.sim.machine import machine, simulators

            self.sims = simulators(machine(
                config.axes, duration=config.duration, seed=config.seed,
                scenario_name=config.scenario, kind=config.ids), start_time)
            self.sim = self.sims[0]
        self.start_time = start_time
        self.realtime = config.realtime
        self.lock = threading.Lock()
        self.refs = 0
        self.frames_sent = 0
        self.overflows = 0
        self._pending = FrameBlock.empty()
        self._next = 0
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    # -------------------------------------------------------------- generation
    def _refill(self, periods: int) -> bool:
        """Simulate the next periods into the pending frames; False at the end of duration."""
        if self.sims:
            from canrls.sim.machine import step_all

            block = step_all(self.sims, periods)
            if block is None:
                return False
            self._pending, self._next = block, 0
            return True
        if self.sim.remaining == 0:
            return False
        chunk = self.sim.step(periods)
        self._pending = self.sim.encode(chunk)
        self._next = 0
        return True

    def _deliver(self, block: FrameBlock) -> None:
        with _virtual.channels_lock:
            queues = list(_virtual.channels.get(self.channel, ()))
        for q in queues:
            for msg in block.to_messages(channel=self.channel):
                try:
                    q.put_nowait(msg)
                except queue.Full:
                    self.overflows += 1
        self.frames_sent += len(block)

    def pump(self) -> bool:
        """As fast as consumed: deliver the next chunk; False when the drive has ended."""
        with self.lock:
            if not self._refill(_CHUNK_FAST):
                return False
            block, self._pending = self._pending, FrameBlock.empty()
            self._deliver(block)
            return True

    def _run(self) -> None:
        """Real time: deliver each frame once the wall clock reaches its timestamp."""
        try:
            while not self._stop.is_set():
                now = time.time()
                with self.lock:
                    while True:
                        if self._next >= len(self._pending) and not self._refill(_CHUNK_REALTIME):
                            return  # end of duration: the drive falls silent
                        ts = self._pending.t
                        j = self._next
                        while j < len(ts) and ts[j] <= now:
                            j += 1
                        if j > self._next:
                            self._deliver(self._pending.take(slice(self._next, j)))
                            self._next = j
                        if j < len(ts):
                            wait = float(ts[j]) - now
                            break
                self._stop.wait(min(max(wait, 0.0), 0.05))
        except Exception:  # pragma: no cover - a crash must not pass silently
            log.exception("canrls-sim drive on channel %r stopped", self.channel)

    def start(self) -> None:
        if self.realtime:
            self._thread = threading.Thread(target=self._run, daemon=True,
                                            name=f"canrls-sim drive {self.channel}")
            self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join()
            self._thread = None


_drives: dict[Any, _Drive] = {}
_drives_lock = threading.Lock()


class SimBus(VirtualBus):
    """A python-can bus with a simulated drive on it (interface ``canrls-sim``).

    :param channel: the bus (frames reach every ``canrls-sim``/``virtual`` bus on it) and
        the scenario: ``standard``, ``linear``, ``poor``, or ``NAME:TAG`` for another
        independent drive of that scenario; any other name runs ``standard``.
    :param effects: the drive's true physics, e.g. ``"inertia,viscous,coulomb,cogging:24"``
        (default ``inertia,viscous,coulomb``).
    :param seed: seed of the sensor noise, PRBS and faults (default 0).
    :param faults: a fault spec (``"drop=0.01,silence=0.5s@10s"``, see
        :mod:`canrls.sim.faults`) applied to the drive's frames.
    :param duration: seconds of simulated time, then the drive falls silent (default: endless).
    :param realtime: pace frames by the wall clock (default) or deliver them as fast as
        ``recv`` consumes them.
    :param receive_own_messages: as for python-can's virtual bus.
    :param scenario: the scenario when the channel does not name it.
    :param axis: ``rotary`` or ``linear`` (overrides the scenario's).
    :param excitation: an excitation preset (``standard``, ``poor``, ``chirp``...).
    :param params: true values by library name (a mapping, or ``"coulomb.Tc=0.03;viscous.B=2e-4"``).
    :param start_time: timestamp of the first period (default: the wall clock now).
    :param rx_queue_size: receive queue length (0: unbounded); a full queue drops the
        drive's frames (counted in ``overflows``).
    :param axes: a machine of this many drives instead of one (``canrls sim --axes``:
        each its own parameters, hidden effect and IDs), of kind ``ids``: ``offset``
        (default), ``cia402`` or ``cansimple``; ``effects``, ``faults``, ``axis``,
        ``excitation`` and ``params`` are the machine's then.

    Other keyword arguments (``bitrate``, ``fd``, ...) are accepted and ignored.
    """

    def __init__(self, channel: Any = "standard", effects: str | None = None,
                 seed: int | str | None = None, faults: str | FaultSpec | None = None,
                 duration: float | str | None = None, realtime: bool | str | None = None,
                 receive_own_messages: bool = False, scenario: str | None = None,
                 axis: str | None = None, excitation: str | None = None,
                 params: Mapping[str, float] | str | None = None,
                 start_time: float | None = None, rx_queue_size: int = 0,
                 axes: int | str | None = None, ids: str | None = None,
                 **kwargs: Any) -> None:
        if channel is None or channel == "":
            channel = "standard"
        for k in ("bitrate", "data_bitrate", "fd", "timing", "app_name", "serial"):
            kwargs.pop(k, None)
        given = self._given(channel, effects, seed, faults, duration, realtime, scenario, axis,
                            excitation, params)
        if axes is not None:
            given.update(_machine_given(axes, ids, given))
        elif ids is not None:
            raise ConfigError("canrls-sim: ids: the kind of a machine's drives, with axes=N")
        super().__init__(channel=channel, receive_own_messages=_parse_bool(
            "receive_own_messages", receive_own_messages), rx_queue_size=rx_queue_size,
            preserve_timestamps=False, **kwargs)
        self.channel_info = f"canrls simulated drive, channel {channel}"
        try:
            self._drive = self._attach(channel, given, start_time)
        except BaseException:
            VirtualBus.shutdown(self)
            raise
        self._released = False

    # -------------------------------------------------------------- config
    @staticmethod
    def _given(channel: Any, effects: Any, seed: Any, faults: Any, duration: Any,
               realtime: Any, scen: Any, axis: Any, excitation: Any,
               params: Any) -> dict[str, Any]:
        """The drive settings this bus states explicitly, parsed and normalised."""
        g: dict[str, Any] = {}
        if scen is not None:
            if str(scen) not in SCENARIOS:
                raise ConfigError(f"canrls-sim: scenario: unknown {scen!r}; known: "
                                  f"{', '.join(SCENARIOS)}")
            g["scenario"] = str(scen)
        if effects is not None:
            from canrls.sim.plant import parse_effects
            g["effects"] = ",".join(parse_effects(str(effects)))
        if seed is not None:
            g["seed"] = _parse_int("seed", seed)
        if faults is not None:
            g["faults"] = str(FaultSpec.parse(faults))
        if duration is not None:
            d = _parse_float("duration", duration)
            if d < 0:
                raise ConfigError(f"canrls-sim: duration: {duration!r} must be >= 0")
            g["duration"] = d
        if realtime is not None:
            g["realtime"] = _parse_bool("realtime", realtime)
        if axis is not None:
            g["axis"] = str(axis)
        if excitation is not None:
            g["excitation"] = str(excitation)
        if params is not None:
            if isinstance(params, str):
                items: dict[str, float] = {}
                for part in params.replace(",", ";").split(";"):
                    if not part.strip():
                        continue
                    k, eq, v = part.partition("=")
                    if not eq:
                        raise ConfigError(f"canrls-sim: params: {part!r} is not NAME=VALUE")
                    items[k.strip()] = _parse_float(f"params.{k.strip()}", v)
                params = items
            g["params"] = tuple(sorted((str(k), float(v)) for k, v in params.items()))
        return g

    def _attach(self, channel: Any, given: dict[str, Any], start_time: float | None) -> _Drive:
        with _drives_lock:
            drive = _drives.get(channel)
            if drive is not None:
                for key, v in given.items():
                    have = getattr(drive.config, key)
                    if have != v:
                        raise ConfigError(
                            f"canrls-sim: channel {channel!r} already has a drive with {key}="
                            f"{have!r}; this bus asks for {key}={v!r} (open it without {key} to "
                            "join, or use another channel)")
            else:
                cfg = _DriveConfig(
                    scenario=given.get("scenario", _scenario_of_channel(channel)),
                    effects=given.get("effects", DEFAULT_EFFECTS),
                    seed=given.get("seed", 0),
                    faults=given.get("faults", "none"),
                    duration=given.get("duration", math.inf),
                    realtime=given.get("realtime", True),
                    axis=given.get("axis"),
                    excitation=given.get("excitation"),
                    params=given.get("params", ()),
                    axes=given.get("axes", 0),
                    ids=given.get("ids", "offset"),
                )
                drive = _Drive(channel, cfg, time.time() if start_time is None
                               else _parse_float("start_time", start_time))
                _drives[channel] = drive
                drive.start()
            drive.refs += 1
            return drive

    # -------------------------------------------------------------- introspection
    @property
    def simulator(self) -> Simulator:
        """The drive's :class:`~canrls.sim.scenario.Simulator` (truth, scenario, state)."""
        return self._drive.sim

    @property
    def scenario(self) -> Scenario:
        return self._drive.scenario

    @property
    def fault_log(self) -> FaultLog:
        return self._drive.sim.fault_log

    @property
    def frames_sent(self) -> int:
        """Frames the drive has put on the channel so far."""
        return self._drive.frames_sent

    @property
    def overflows(self) -> int:
        return self._drive.overflows

    # -------------------------------------------------------------- BusABC
    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        self._check_if_open()
        if not self._drive.realtime:
            try:
                return self.queue.get_nowait(), False
            except queue.Empty:
                pass
            # simulate until a frame arrives (a silent fault window yields none) or the end
            while self._drive.pump():
                try:
                    return self.queue.get_nowait(), False
                except queue.Empty:
                    continue
        return super()._recv_internal(timeout)

    def shutdown(self) -> None:
        if not getattr(self, "_released", True):
            self._released = True
            drive = self._drive
            with _drives_lock:
                drive.refs -= 1
                last = drive.refs == 0
                if last and _drives.get(drive.channel) is drive:
                    del _drives[drive.channel]
            if last:
                drive.stop()
        super().shutdown()

    @staticmethod
    def _detect_available_configs() -> list[Any]:
        return [{"interface": "canrls-sim", "channel": name} for name in SCENARIOS]
