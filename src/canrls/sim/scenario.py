"""Scenarios of the simulated drive and the :func:`simulate` entry point.

A :class:`Scenario` is everything a run needs: the true physics (:class:`Truth`), the
excitation, the controller, the sensors, the control period, the duration, the seed
and the faults on the frames; :func:`scenario` builds one by name (:data:`SCENARIOS`)::

    res = simulate(scenario("standard", effects="inertia,viscous,coulomb", seed=3))

The scenarios, their true values and the noise floor: docs/simulator.md.
"""

from __future__ import annotations

import functools
import logging
import math
from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
import numpy.typing as npt

from canrls.can.frameblock import FrameBlock
from canrls.core.checks import is_positive
from canrls.core.errors import ConfigError, EffectError
from canrls.core.samples import Signals
from canrls.sim.excitation import Excitation
from canrls.sim.excitation import excitation as make_excitation
from canrls.sim.faults import (
    DEFAULT_COMMAND_ID,
    DEFAULT_PROTECTED,
    FaultInjector,
    FaultLog,
    FaultSpec,
)
from canrls.sim.plant import (
    EFFECT_PARAMS,
    Controller,
    Plant,
    PlantBlock,
    Sensors,
    Truth,
    parse_effects,
)

__all__ = [
    "SCENARIOS",
    "DEFAULT_EFFECTS",
    "default_params",
    "Scenario",
    "scenario",
    "SimChunk",
    "SimResult",
    "Simulator",
    "simulate",
]

F64 = npt.NDArray[np.float64]

log = logging.getLogger(__name__)

#: True physics of a scenario when none is chosen.
DEFAULT_EFFECTS = "inertia,viscous,coulomb"

# default true values by axis; cogging:K takes the "cogging" values for any K
_DEFAULTS: dict[str, dict[str, float]] = {
    "rotary": {
        "inertia.J": 2e-4, "viscous.B": 1e-4, "coulomb.Tc": 0.02, "stribeck.Ts": 0.01,
        "offset.T0": 0.005, "unbalance.sin": 0.008, "unbalance.cos": -0.004,
        "cogging.sin": 0.003, "cogging.cos": 0.0015,
        "electrical.R": 0.5, "electrical.L": 1.5e-3, "electrical.Ke": 0.1,
    },
    "linear": {
        "inertia.J": 2.0, "viscous.B": 5.0, "coulomb.Tc": 3.0, "stribeck.Ts": 1.5,
        "offset.T0": 1.0, "unbalance.sin": 0.8, "unbalance.cos": -0.4,
        "cogging.sin": 0.3, "cogging.cos": 0.15,
        "electrical.R": 2.0, "electrical.L": 8e-3, "electrical.Ke": 20.0,
    },
}

#: Named scenarios and their settings (docs/simulator.md).
SCENARIOS: dict[str, dict[str, Any]] = {
    "standard": dict(axis="rotary", kt=0.1, pitch=1.0, coulomb_band=1e-3, stribeck_speed=1.0,
                     excitation="standard", speed_scale=1.0, duration=60.0,
                     sensors=Sensors(current_noise=0.005, speed_noise=0.02),
                     controller=Controller(i_max=10.0, u_max=48.0)),
    "linear": dict(axis="linear", kt=20.0, pitch=0.1, coulomb_band=1e-4, stribeck_speed=0.005,
                   excitation="standard", speed_scale=0.005, duration=60.0,
                   sensors=Sensors(current_noise=0.005, speed_noise=1e-4),
                   controller=Controller(i_max=10.0, u_max=48.0)),
    "poor": dict(axis="rotary", kt=0.1, pitch=1.0, coulomb_band=1e-3, stribeck_speed=1.0,
                 excitation="poor", speed_scale=1.0, duration=60.0,
                 sensors=Sensors(current_noise=0.005, speed_noise=0.02),
                 controller=Controller(i_max=10.0, u_max=48.0)),
}


def default_params(effects: str | tuple[str, ...], axis: str = "rotary") -> dict[str, float]:
    """Default true values of ``effects`` on ``axis`` (library parameter names)."""
    if axis not in _DEFAULTS:
        raise ConfigError(f"axis: {axis!r} is not one of rotary, linear")
    d = _DEFAULTS[axis]
    out: dict[str, float] = {}
    for eff in parse_effects(effects):
        base = eff.split(":", 1)[0]
        for sym in EFFECT_PARAMS[base]:
            out[f"{eff}.{sym}"] = d[f"{base}.{sym}"]
    return out


@dataclass(frozen=True)
class Scenario:
    """A complete description of one simulated run (see :func:`scenario`)."""

    name: str
    truth: Truth
    excitation: Excitation
    dt: float = 1e-3
    duration: float = 60.0
    controller: Controller = field(default_factory=Controller)
    sensors: Sensors = field(default_factory=Sensors)
    seed: int | None = 0
    faults: FaultSpec = field(default_factory=FaultSpec)
    nsub: int = 5

    def __post_init__(self) -> None:
        if not is_positive(self.dt):
            raise ConfigError(f"scenario {self.name}: dt {self.dt!r} must be > 0 s")
        if not (self.duration >= 0 and not math.isnan(self.duration)):
            raise ConfigError(f"scenario {self.name}: duration {self.duration!r} must be >= 0 s")

    @property
    def periods(self) -> int:
        """Control periods in ``duration`` (infinite duration: -1)."""
        if math.isinf(self.duration):
            return -1
        return int(round(self.duration / self.dt))

    @property
    def noise_floor(self) -> float:
        """Kt * sqrt(sigma_i^2 + q_i^2/12): RMS target noise [N·m] (linear: N)."""
        s = self.sensors
        return self.truth.kt * math.sqrt(s.current_noise ** 2 + s.current_step ** 2 / 12.0)

    def replace(self, **changes: Any) -> Scenario:
        return replace(self, **changes)


def _int_or_none(key: str, v: Any) -> int | None:
    if v is None:
        return None
    try:
        iv = int(v)
    except (TypeError, ValueError) as e:
        raise ConfigError(f"{key}: {v!r} is not an integer") from e
    if isinstance(v, float) and v != iv:
        raise ConfigError(f"{key}: {v!r} is not an integer")
    return iv


def _float(key: str, v: Any) -> float:
    try:
        f = float(v)
    except (TypeError, ValueError) as e:
        raise ConfigError(f"{key}: {v!r} is not a number") from e
    if math.isnan(f):
        raise ConfigError(f"{key}: {v!r} is not a number")
    return f


def scenario(name: str = "standard", *, effects: str | tuple[str, ...] | None = None,
             params: Mapping[str, float] | None = None, axis: str | None = None,
             kt: float | None = None, pitch: float | None = None,
             coulomb_band: float | None = None, stribeck_speed: float | None = None,
             excitation: str | Excitation | None = None, duration: float | None = None,
             dt: float | None = None, seed: int | None = 0,
             faults: FaultSpec | str | None = None, controller: Controller | None = None,
             sensors: Sensors | None = None, current_noise: float | None = None,
             speed_noise: float | None = None, nsub: int = 5) -> Scenario:
    """A named scenario (``standard``, ``linear``, ``poor``) with overrides.

    Parameters
    ----------
    effects : the true physics, ``"inertia,viscous,coulomb,cogging:24"`` (default
        ``inertia,viscous,coulomb``); ``inertia`` is required.
    params : true values by library name (``{"coulomb.Tc": 0.03}``), overriding the
        defaults; each must belong to a selected effect.
    axis : ``rotary`` or ``linear``: switches a named scenario's axis (``scenario("standard",
        axis="linear")`` is the ``linear`` scenario).
    kt, pitch, coulomb_band, stribeck_speed : as in :class:`Truth`.
    excitation : a preset name (see :mod:`canrls.sim.excitation`) or an :class:`Excitation`
        (then in the axis's units, not scaled).
    duration, dt : seconds (``duration=math.inf`` for an endless stream).
    seed : seeds the sensor noise (``numpy.random.default_rng(seed)``), the PRBS and the
        faults; the same seed gives identical output.
    faults : a :class:`FaultSpec` or its string, applied to the frames.
    controller, sensors : replace the scenario's; ``current_noise``/``speed_noise`` set the
        sensor noise standard deviations [A], [rad/s or m/s].
    """
    if name not in SCENARIOS:
        raise ConfigError(f"unknown scenario {name!r}; known: {', '.join(SCENARIOS)}")
    base = dict(SCENARIOS[name])
    if axis is not None and axis != base["axis"]:
        if axis == "linear":
            base = dict(SCENARIOS["linear"], excitation=base["excitation"])
        elif axis == "rotary":
            base = dict(SCENARIOS["standard"], excitation=base["excitation"])
        else:
            raise ConfigError(f"axis: {axis!r} is not one of rotary, linear")
    ax = base["axis"]
    seed = _int_or_none("seed", seed)
    effs = parse_effects(DEFAULT_EFFECTS if effects is None else effects)
    if not effs:
        raise EffectError("effects: no effect selected (the drive needs at least 'inertia')")
    true_params = default_params(effs, ax)
    for key, v in (params or {}).items():
        if key not in true_params:
            eff = key.rpartition(".")[0]
            if eff and eff not in effs:
                raise EffectError(f"params: {key!r} belongs to effect {eff!r}, which is not among "
                                  f"the true effects ({','.join(effs)})")
            raise EffectError(f"params: unknown parameter {key!r}")
        true_params[key] = _float(f"params.{key}", v)
    truth = Truth(
        params=true_params,
        kt=_float("kt", base["kt"] if kt is None else kt),
        axis=ax,
        pitch=_float("pitch", base["pitch"] if pitch is None else pitch),
        coulomb_band=_float("coulomb_band",
                            base["coulomb_band"] if coulomb_band is None else coulomb_band),
        stribeck_speed=_float("stribeck_speed",
                              base["stribeck_speed"] if stribeck_speed is None else stribeck_speed),
    )
    if isinstance(excitation, Excitation):
        ex = excitation
    else:
        ex = make_excitation(base["excitation"] if excitation is None else excitation,
                             scale=base["speed_scale"], seed=seed or 0)
    sens = sensors or base["sensors"]
    if current_noise is not None:
        sens = replace(sens, current_noise=_float("current_noise", current_noise))
    if speed_noise is not None:
        sens = replace(sens, speed_noise=_float("speed_noise", speed_noise))
    return Scenario(
        name=name if axis is None or axis == SCENARIOS[name]["axis"] else f"{name}-{ax}",
        truth=truth,
        excitation=ex,
        dt=_float("dt", 1e-3 if dt is None else dt),
        duration=_float("duration", base["duration"] if duration is None else duration),
        controller=controller or base["controller"],
        sensors=sens,
        seed=seed,
        faults=FaultSpec.parse(faults),
        nsub=nsub,
    )


# ---------------------------------------------------------------------------- running


@dataclass(frozen=True)
class SimChunk:
    """A block of consecutive control periods: true and measured samples and references."""

    true: Signals
    measured: Signals
    speed_ref: F64
    current_ref: F64

    def __len__(self) -> int:
        return len(self.true)


def _chunk(b: PlantBlock) -> SimChunk:
    return SimChunk(
        true=Signals(b.t, b.current, b.speed, b.position, b.voltage),
        measured=Signals(b.t.copy(), b.current_meas, b.speed_meas, b.position_meas,
                         b.voltage_meas),
        speed_ref=b.speed_ref,
        current_ref=b.current_ref,
    )


@functools.lru_cache(maxsize=1)
def _default_protocol() -> Any:
    from canrls.can.protocol import Protocol
    return Protocol.load()


#: Time between the DriveCurrent and DriveSpeed frames of one period [s] (about one
#: classic frame at 1 Mbit/s).
FRAME_STAGGER = 1e-4


class Simulator:
    """Run a scenario incrementally: :meth:`step` advances the drive by ``n`` periods.

    The output does not depend on how the run is split into steps. :meth:`frames`
    encodes the measured samples into the feedback frames of the default DBC
    (``canrls.can.protocol.FeedbackEncoder``) and applies the scenario's faults
    (``fault_log`` counts them). ``t0`` offsets the frame timestamps (the samples
    keep ``t = k*dt``). The alive-counter faults hit the ``protocol``'s frames that
    carry a CRC and a counter (the default DBC's without one); the inserted commands
    go to ``command_id`` (an axis's ``RlsCommand``, :func:`canrls.live.bus_link.command_id`).
    """

    def __init__(self, sc: Scenario, t0: float = 0.0, protocol: Any = None, *,
                 command_id: int = DEFAULT_COMMAND_ID) -> None:
        self.scenario = sc
        self.t0 = float(t0)
        self.plant = Plant(sc.truth, sc.dt, sc.controller, sc.sensors, sc.seed, sc.nsub)
        self._protocol = protocol
        self._encoder: Any = None
        protected = DEFAULT_PROTECTED if protocol is None else frozenset(
            m.frame_id for m in protocol.messages if m.crc is not None and m.counter is not None)
        self._faults = FaultInjector(sc.faults, seed=None if sc.seed is None else (sc.seed, 1),
                                     t0=self.t0, protected=protected, command_id=command_id)
        self.clipped = 0

    @property
    def k(self) -> int:
        """Periods simulated so far."""
        return self.plant.k

    @property
    def remaining(self) -> int | None:
        """Periods left before ``duration`` (None: endless)."""
        n = self.scenario.periods
        return None if n < 0 else max(0, n - self.plant.k)

    @property
    def fault_log(self) -> FaultLog:
        return self._faults.log

    def step(self, n: int) -> SimChunk:
        """The next ``n`` control periods (fewer at the end of ``duration``)."""
        rem = self.remaining
        if rem is not None:
            n = min(n, rem)
        dt = self.scenario.dt
        t = (self.plant.k + np.arange(n, dtype=np.float64)) * dt
        w_ref, a_ref = self.scenario.excitation.reference(t)
        return _chunk(self.plant.run(w_ref, a_ref))

    def chunks(self, size: int = 65536) -> Iterator[SimChunk]:
        """Step to the end of ``duration`` in chunks of ``size`` periods."""
        if self.remaining is None:
            raise ConfigError("chunks(): the scenario's duration is endless")
        while self.remaining:
            yield self.step(size)

    def encode(self, chunk: SimChunk) -> FrameBlock:
        """The feedback frames of ``chunk`` (timestamps ``t0 + t``), faults applied."""
        if self._encoder is None:
            from canrls.can.encoder import FeedbackEncoder
            proto = self._protocol or _default_protocol()
            self._encoder = FeedbackEncoder(proto, clip=True, stagger=FRAME_STAGGER)
        m = chunk.measured
        assert m.current is not None  # the simulated drive measures its current
        # a drive that reports its torque (CiA 402) reports Kt times its current
        torque = m.current * self.scenario.truth.kt if self._encoder.protocol.has("torque") \
            else None
        block = self._encoder.encode(m.t + self.t0, m.current, m.speed, m.position, m.voltage,
                                     torque)
        clipped = sum(self._encoder.clipped.values())
        if clipped > self.clipped:
            log.warning("simulated drive: %d values clipped to the DBC range so far (%s)",
                        clipped, ", ".join(f"{k}: {v}" for k, v in self._encoder.clipped.items()))
        self.clipped = clipped
        return self._faults.apply(block)

    def frames(self, size: int = 65536) -> Iterator[FrameBlock]:
        """Frames to the end of ``duration``, ``size`` periods at a time."""
        for c in self.chunks(size):
            yield self.encode(c)


class SimResult:
    """What :func:`simulate` returns.

    Attributes
    ----------
    scenario : the :class:`Scenario` that ran
    true, measured : :class:`~canrls.core.samples.Signals` (true: unwrapped position, exact
        current; measured: noisy, quantised, position wrapped at 2*pi as the DBC sends it).
        ``voltage`` is None unless ``electrical`` is among the true effects.
    speed_ref, current_ref : the excitation and the speed controller's output
    truth : the :class:`Truth`; ``params`` its true parameter values
    noise_floor : see docs/simulator.md
    frames : the feedback frames (encoded on first access; faults applied)
    fault_log : what the faults did to ``frames``
    """

    def __init__(self, sc: Scenario, chunk: SimChunk, sim: Simulator) -> None:
        self.scenario = sc
        self.true = chunk.true
        self.measured = chunk.measured
        self.speed_ref = chunk.speed_ref
        self.current_ref = chunk.current_ref
        self.truth = sc.truth
        self.noise_floor = sc.noise_floor
        self._sim = sim
        self._frames: FrameBlock | None = None

    @property
    def params(self) -> dict[str, float]:
        return dict(self.truth.params)

    @property
    def noise_floor_measured(self) -> float:
        measured, true = self.measured.current, self.true.current
        assert measured is not None and true is not None  # the simulation has both
        d = measured - true
        return float(self.truth.kt * np.sqrt(np.mean(d * d))) if len(d) else 0.0

    @property
    def frames(self) -> FrameBlock:
        if self._frames is None:
            self._frames = self._sim.encode(SimChunk(self.true, self.measured, self.speed_ref,
                                                     self.current_ref))
        return self._frames

    @property
    def fault_log(self) -> FaultLog:
        self.frames  # noqa: B018 - encoding counts the faults
        return self._sim.fault_log

    def __len__(self) -> int:
        return len(self.true)

    def __repr__(self) -> str:
        return (f"<SimResult {self.scenario.name}: {len(self)} periods, "
                f"{self.scenario.duration:g} s, {self.truth.summary()}>")


def simulate(sc: Scenario | str = "standard", **kwargs: Any) -> SimResult:
    """Run a scenario (or ``scenario(name, **kwargs)``) to the end of its duration."""
    if isinstance(sc, str):
        sc = scenario(sc, **kwargs)
    elif kwargs:
        raise TypeError("simulate(): keyword arguments only with a scenario name")
    if sc.periods < 0:
        raise ConfigError("simulate(): the scenario's duration is endless; use Simulator")
    sim = Simulator(sc)
    chunk = sim.step(sc.periods)
    return SimResult(sc, chunk, sim)
