"""The simulated drive's physics: true parameters, load torque, controllers, sensors.

The plant follows the equations of ``docs/architecture.md`` exactly (a contract shared
with :mod:`canrls.estimation.effects`); each control period samples the sensors, runs
the speed (and with ``electrical`` the current) controller and integrates the state
with RK4, in C (``canrls._sim``). The physics and the order of one period:
docs/simulator.md, "Physics".
"""

from __future__ import annotations

import math
import re
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from types import MappingProxyType

import numpy as np
import numpy.typing as npt

from canrls import _sim
from canrls.core.checks import is_positive
from canrls.core.errors import ConfigError, EffectError

__all__ = [
    "AXES",
    "EFFECT_PARAMS",
    "Truth",
    "Controller",
    "Compensation",
    "Sensors",
    "PlantBlock",
    "Plant",
    "load_torque",
    "parse_effects",
    "param_unit",
]

F64 = npt.NDArray[np.float64]

AXES: tuple[str, ...] = ("rotary", "linear")

#: Parameter symbols of each effect, in the order the library lists them.
EFFECT_PARAMS: Mapping[str, tuple[str, ...]] = MappingProxyType({
    "inertia": ("J",),
    "viscous": ("B",),
    "coulomb": ("Tc",),
    "stribeck": ("Ts",),
    "offset": ("T0",),
    "unbalance": ("sin", "cos"),
    "cogging": ("sin", "cos"),
    "electrical": ("R", "L", "Ke"),
})

_COGGING = re.compile(r"^cogging:([1-9][0-9]*)$")
#: Most integration sub-steps per control period (the stiffest part: Coulomb friction
#: at standstill, ~ (Tc + |Ts|) / (band J)): the standard drive takes 50-75, J = 1e-6
#: 10,000-15,000 (1.5 s of CPU for 5 s of drive); J = 1e-8 took 11 minutes.
MAX_SUBSTEPS = 20_000

# SI units of each parameter symbol: (rotary, linear)
_UNITS: dict[str, tuple[str, str]] = {
    "J": ("kg·m²", "kg"),
    "B": ("N·m·s/rad", "N·s/m"),
    "Tc": ("N·m", "N"),
    "Ts": ("N·m", "N"),
    "T0": ("N·m", "N"),
    "sin": ("N·m", "N"),
    "cos": ("N·m", "N"),
    "R": ("Ohm", "Ohm"),
    "L": ("H", "H"),
    "Ke": ("V·s/rad", "V·s/m"),
}


def param_unit(name: str, axis: str = "rotary") -> str:
    """SI unit of parameter ``name`` (``"coulomb.Tc"`` -> ``"N·m"``) on ``axis``."""
    sym = name.rsplit(".", 1)[-1]
    if sym not in _UNITS:
        raise EffectError(f"unknown parameter {name!r}")
    return _UNITS[sym][AXES.index(axis)]


def _effect_key(name: str) -> tuple[int, int]:
    base = name.split(":", 1)[0]
    order = list(EFFECT_PARAMS).index(base)
    k = int(name.split(":", 1)[1]) if ":" in name else 0
    return order, k


def parse_effects(effects: str | Iterable[str]) -> tuple[str, ...]:
    """Validate effect names (``"inertia,viscous,cogging:24"``) and return them in canonical order.

    Raises :class:`~canrls.core.errors.EffectError` naming the offending entry.
    """
    items = [s.strip() for s in effects.split(",")] if isinstance(effects, str) else [
        str(s).strip() for s in effects]
    items = [s for s in items if s]
    out: list[str] = []
    for name in items:
        if name == "cogging":
            raise EffectError("effect 'cogging' needs its order: write cogging:K (e.g. cogging:24)")
        if name.startswith("user:"):
            raise EffectError(f"effect {name!r}: user terms are not simulated by the drive")
        if name not in EFFECT_PARAMS and not _COGGING.match(name):
            raise EffectError(f"unknown effect {name!r}; known: {', '.join(EFFECT_PARAMS)} "
                              "(cogging as cogging:K)")
        if name in out:
            raise EffectError(f"effect {name!r} listed twice")
        out.append(name)
    return tuple(sorted(out, key=_effect_key))


def _param_names(effect: str) -> tuple[str, ...]:
    base = effect.split(":", 1)[0]
    return tuple(f"{effect}.{sym}" for sym in EFFECT_PARAMS[base])


@dataclass(frozen=True)
class Truth:
    """The true physics of a simulated drive.

    Attributes
    ----------
    params : true parameter values by their library names (``inertia.J``, ``coulomb.Tc``,
        ``cogging:24.sin``, ``electrical.R``, ...); exactly the parameters of ``effects``.
    kt : torque constant [N·m/A] (linear axis: force constant [N/A])
    axis : ``"rotary"`` or ``"linear"``
    pitch : linear axis only: metres per period of the position-periodic terms
    coulomb_band : ``e`` of ``sgn_e(w) = tanh(w/e)`` [rad/s or m/s]. The simulated drive
        uses a tiny band (default 1e-3) so that its friction is practically a true
        Coulomb step; the estimator may use its own (architecture default 0.01).
    stribeck_speed : ``ws`` [rad/s or m/s]
    effects : (derived) the effects of ``params`` in canonical order
    """

    params: Mapping[str, float]
    kt: float = 0.1
    axis: str = "rotary"
    pitch: float = 1.0
    coulomb_band: float = 1e-3
    stribeck_speed: float = 1.0
    effects: tuple[str, ...] = field(default=(), init=False, compare=False)

    def __post_init__(self) -> None:
        if self.axis not in AXES:
            raise ConfigError(f"axis: {self.axis!r} is not one of {', '.join(AXES)}")
        effects: list[str] = []
        for name in self.params:
            eff, _, _sym = name.rpartition(".")
            if not eff:
                raise EffectError(f"parameter {name!r} is not <effect>.<symbol>")
            if eff not in effects:
                effects.append(eff)
        canon = parse_effects(effects)
        for eff in canon:
            for pname in _param_names(eff):
                if pname not in self.params:
                    raise EffectError(f"parameter {pname!r} of effect {eff!r} has no true value")
        for name, v in self.params.items():
            if name not in {p for e in canon for p in _param_names(e)}:
                raise EffectError(f"unknown parameter {name!r}")
            if not math.isfinite(v):
                raise ConfigError(f"parameter {name!r}: value {v!r} is not finite")
        if "inertia" not in canon:
            raise EffectError("the simulated drive needs the 'inertia' effect (its equation of "
                              "motion has no solution without a mass)")
        for key in ("kt", "pitch", "coulomb_band", "stribeck_speed"):
            v = getattr(self, key)
            if not is_positive(v):
                raise ConfigError(f"{key}: {v!r} must be a positive number")
        if self.params["inertia.J"] <= 0:
            raise ConfigError(f"inertia.J: {self.params['inertia.J']!r} must be > 0")
        if "electrical" in canon and self.params["electrical.L"] <= 0:
            raise ConfigError(f"electrical.L: {self.params['electrical.L']!r} must be > 0")
        object.__setattr__(self, "params", MappingProxyType(
            {p: float(self.params[p]) for e in canon for p in _param_names(e)}))
        object.__setattr__(self, "effects", canon)

    # ------------------------------------------------------------------ access
    def __getitem__(self, name: str) -> float:
        return self.params[name]

    def get(self, name: str, default: float = 0.0) -> float:
        """A true parameter, ``default`` when its effect is not part of the truth."""
        return self.params.get(name, default)

    @property
    def has_electrical(self) -> bool:
        return "electrical" in self.effects

    @property
    def cogging_orders(self) -> tuple[int, ...]:
        return tuple(int(e.split(":", 1)[1]) for e in self.effects if e.startswith("cogging:"))

    @property
    def angle_scale(self) -> float:
        """Radians of the periodic terms' angle per unit of position (1, or 2*pi/pitch)."""
        return 1.0 if self.axis == "rotary" else 2.0 * math.pi / self.pitch

    def unit(self, name: str) -> str:
        return param_unit(name, self.axis)

    def divided_by_kt(self) -> dict[str, float]:
        """The mechanical parameters as an estimator without ``kt`` sees them (target = current)."""
        return {k: (v if k.startswith("electrical.") else v / self.kt)
                for k, v in self.params.items()}

    def summary(self) -> str:
        """``inertia.J=0.0002 viscous.B=0.0001 ... (Kt=0.1)``"""
        body = " ".join(f"{k}={v:.6g}" for k, v in self.params.items())
        kname = "Kt" if self.axis == "rotary" else "Kf"
        extra = f" pitch={self.pitch:g}" if self.axis == "linear" else ""
        return f"{body} {kname}={self.kt:g}{extra}"

    def load_torque(self, theta: npt.ArrayLike, omega: npt.ArrayLike) -> F64:
        """See :func:`load_torque`."""
        return load_torque(self, theta, omega)

    # ------------------------------------------------------------------ kernel view
    def _kernel_params(self) -> tuple[F64, F64, F64, F64]:
        """The physics as the C loop takes it: ``p`` in the order of ``sim.c``'s
        ``P_J .. P_ELEC``, and the cogging orders with their sine and cosine amplitudes."""
        g = self.get
        p = np.array([
            g("inertia.J"), g("viscous.B"), g("coulomb.Tc"), g("stribeck.Ts"),
            self.stribeck_speed, self.coulomb_band, g("offset.T0"),
            g("unbalance.sin"), g("unbalance.cos"),
            g("electrical.R"), g("electrical.L", 1.0), g("electrical.Ke"),
            self.kt, self.angle_scale, 1.0 if self.has_electrical else 0.0,
        ], dtype=np.float64)
        orders = self.cogging_orders
        ck = np.array(orders, dtype=np.float64)
        cs = np.array([self.params[f"cogging:{k}.sin"] for k in orders], dtype=np.float64)
        cc = np.array([self.params[f"cogging:{k}.cos"] for k in orders], dtype=np.float64)
        return p, ck, cs, cc


def load_torque(truth: Truth | Mapping[str, float], theta: npt.ArrayLike, omega: npt.ArrayLike,
                axis: str | None = None, *, pitch: float | None = None,
                band: float | None = None, stribeck_speed: float | None = None) -> F64:
    r"""The load the motor must supply at position ``theta`` and speed ``omega`` (vectorised).

    .. math::

        B\omega + T_c \tanh(\omega/e) + T_s \tanh(\omega/e) e^{-(\omega/\omega_s)^2} + T_0
        + T_g^s \sin\vartheta + T_g^c \cos\vartheta
        + \sum_k T_k^s \sin k\vartheta + T_k^c \cos k\vartheta

    i.e. the right-hand side of the mechanical equation without the inertia term, with
    ``vartheta = theta`` (rotary) or ``2*pi*theta/pitch`` (linear). Effects absent from
    ``truth`` contribute nothing. ``truth`` is a :class:`Truth` or a mapping of parameter
    names to values (then ``axis``, ``pitch``, ``band`` and ``stribeck_speed`` take the
    architecture defaults: rotary, 1 m, 0.01, 1.0 unless given). Keyword arguments
    override what a :class:`Truth` carries.
    """
    if isinstance(truth, Truth):
        params: Mapping[str, float] = truth.params
        axis = axis or truth.axis
        pitch = truth.pitch if pitch is None else pitch
        band = truth.coulomb_band if band is None else band
        ws = truth.stribeck_speed if stribeck_speed is None else stribeck_speed
    else:
        params = truth
        axis = axis or "rotary"
        pitch = 1.0 if pitch is None else pitch
        band = 0.01 if band is None else band
        ws = 1.0 if stribeck_speed is None else stribeck_speed
    if axis not in AXES:
        raise ConfigError(f"axis: {axis!r} is not one of {', '.join(AXES)}")
    th = np.asarray(theta, dtype=np.float64)
    w = np.asarray(omega, dtype=np.float64)
    ang = th if axis == "rotary" else th * (2.0 * np.pi / pitch)
    g = params.get
    out = np.zeros(np.broadcast(th, w).shape, dtype=np.float64)
    # viscous: B*omega
    out += g("viscous.B", 0.0) * w
    sgn = np.tanh(w / band)
    # coulomb: Tc*sgn_e(omega)
    out += g("coulomb.Tc", 0.0) * sgn
    # stribeck: Ts*sgn_e(omega)*exp(-(omega/ws)^2)
    if "stribeck.Ts" in params:
        out += params["stribeck.Ts"] * sgn * np.exp(-(w / ws) ** 2)
    # offset: T0
    out += g("offset.T0", 0.0)
    # unbalance: Tg_sin*sin(theta) + Tg_cos*cos(theta)
    if "unbalance.sin" in params or "unbalance.cos" in params:
        out += g("unbalance.sin", 0.0) * np.sin(ang) + g("unbalance.cos", 0.0) * np.cos(ang)
    # cogging:k: Tk_sin*sin(k*theta) + Tk_cos*cos(k*theta)
    for name in params:
        m = re.match(r"^cogging:([0-9]+)\.sin$", name)
        if m:
            k = int(m.group(1))
            out += params[name] * np.sin(k * ang) + g(f"cogging:{k}.cos", 0.0) * np.cos(k * ang)
    return out


# ---------------------------------------------------------------------------- controller


@dataclass(frozen=True)
class Compensation:
    """The speed controller's feedforward (``canrls sim --feedforward``, made by
    ``canrls tune``): a map of the torque over one period of the position (``period``:
    2 pi rad, or the pitch), read at the measured position between its points, and the
    friction ``B w + (Tc + Ts exp(-(w/ws)^2)) tanh(w/e)`` at the speed reference;
    ``scale`` turns the torque into the current reference (1/Kt, or 1 for a model
    identified per ampere); ``lead`` [s] reads the map ahead by the measured speed times
    it (the loop's delay: the current is held over the coming period); ``T0`` a constant
    torque the map does not hold (a model without a position term has no map)."""

    map: tuple[float, ...] = ()
    period: float = 2.0 * math.pi
    scale: float = 1.0
    B: float = 0.0
    Tc: float = 0.0
    Ts: float = 0.0
    ws: float = 1.0
    band: float = 1e-3
    lead: float = 0.0
    T0: float = 0.0

    def __post_init__(self) -> None:
        for key in ("period", "scale", "B", "Tc", "Ts", "ws", "band", "lead", "T0"):
            v = getattr(self, key)
            if not math.isfinite(v) or (key in ("period", "ws", "band") and v <= 0):
                raise ConfigError(f"feedforward.{key}: {v!r} must be a finite number"
                                  + (" > 0" if key in ("period", "ws", "band") else ""))
        if not all(math.isfinite(x) for x in self.map):
            raise ConfigError("feedforward.map: every point must be a finite number")

    def kernel(self) -> tuple[F64, F64]:
        """The kernel's ``ffv`` (``sim.c``'s ``F_ON .. F_IDX``) and ``ffmap``."""
        n = len(self.map)
        ffv = np.array([1.0, self.scale, self.B, self.Tc, self.Ts, self.ws, self.band,
                        n / self.period, self.lead, self.T0], dtype=np.float64)
        return ffv, np.array(self.map, dtype=np.float64)


#: the kernel's vectors without a feedforward
_NO_FEEDFORWARD = (np.zeros(10, dtype=np.float64), np.zeros(0, dtype=np.float64))


@dataclass(frozen=True)
class Controller:
    """Speed and current controllers of the simulated drive.

    The gains follow from bandwidths unless given explicitly (in the units of the
    equations: A·s/rad, A/rad, V/A, V/(A·s)):

    * speed PI (+ inertia feed-forward ``ff * J * alpha_ref / Kt``):
      ``kp_speed = J*wb/Kt``, ``ki_speed = kp_speed*wb/4`` with ``wb = 2*pi*speed_bandwidth``;
    * current PI (+ back-EMF feed-forward ``Ke*omega``):
      ``kp_current = L*wc``, ``ki_current = R*wc`` with ``wc = 2*pi*current_bandwidth``.

    ``i_max`` limits the current reference [A], ``u_max`` the voltage [V]; both PIs stop
    integrating while saturated (conditional integration). ``inertia_ff`` replaces the
    true inertia in the feed-forward (the identified one, ``canrls sim --gains``);
    ``compensation`` adds a feedforward of the load (:class:`Compensation`).
    """

    speed_bandwidth: float = 20.0
    current_bandwidth: float = 100.0
    feedforward: float = 1.0
    i_max: float = 10.0
    u_max: float = 48.0
    kp_speed: float | None = None
    ki_speed: float | None = None
    kp_current: float | None = None
    ki_current: float | None = None
    inertia_ff: float | None = None
    compensation: Compensation | None = None

    def gains(self, truth: Truth) -> F64:
        """Kernel gain vector: kp_w, ki_w, jff, kp_i, ki_i, ke_ff, i_max, u_max."""
        wb = 2.0 * math.pi * self.speed_bandwidth
        wc = 2.0 * math.pi * self.current_bandwidth
        J = truth["inertia.J"]
        kp_w = J * wb / truth.kt if self.kp_speed is None else self.kp_speed
        ki_w = kp_w * wb / 4.0 if self.ki_speed is None else self.ki_speed
        R, L, Ke = truth.get("electrical.R"), truth.get("electrical.L"), truth.get("electrical.Ke")
        kp_i = L * wc if self.kp_current is None else self.kp_current
        ki_i = R * wc if self.ki_current is None else self.ki_current
        for key, v in (("i_max", self.i_max), ("u_max", self.u_max)):
            if not is_positive(v):
                raise ConfigError(f"controller.{key}: {v!r} must be a positive number")
        jff = self.feedforward * (J if self.inertia_ff is None else self.inertia_ff)
        return np.array([kp_w, ki_w, jff, kp_i, ki_i, Ke,
                         self.i_max, self.u_max], dtype=np.float64)


@dataclass(frozen=True)
class Sensors:
    """Sensor noise (white, Gaussian, standard deviation) and quantisation.

    The quantisation steps default to the resolutions of the default DBC: current
    1e-4 A, speed 1e-4 rad/s (m/s), voltage 0.01 V and the 16-bit single-turn position
    (``2*pi/65536`` rad). The measured position wraps every ``position_wrap`` (default
    2*pi, the span of the DBC's single-turn field, on both axes: a linear axis sends
    metres in that field); ``position_step=None`` means 1/65536 of the wrap. A step of 0
    disables quantisation.
    """

    current_noise: float = 0.005
    speed_noise: float = 0.02
    position_noise: float = 0.0
    current_step: float = 1e-4
    speed_step: float = 1e-4
    voltage_step: float = 0.01
    position_step: float | None = None
    position_wrap: float = 2.0 * math.pi

    def __post_init__(self) -> None:
        for key in ("current_noise", "speed_noise", "position_noise", "current_step",
                    "speed_step", "voltage_step"):
            v = getattr(self, key)
            if not (math.isfinite(v) and v >= 0):
                raise ConfigError(f"sensors.{key}: {v!r} must be a number >= 0")

    def quant(self) -> F64:
        """Kernel vector: q_i, q_w, q_th, q_u, wrap."""
        wrap = self.position_wrap
        if not is_positive(wrap):
            raise ConfigError(f"sensors.position_wrap: {wrap!r} must be > 0")
        q_th = wrap / 65536.0 if self.position_step is None else self.position_step
        return np.array([self.current_step, self.speed_step, q_th, self.voltage_step, wrap],
                        dtype=np.float64)


# ---------------------------------------------------------------------------- plant


@dataclass(frozen=True)
class PlantBlock:
    """``n`` control periods of the plant (arrays of length n, sample k at ``t[k]``).

    True state: ``current``, ``speed``, ``position`` (unwrapped), ``voltage`` (None without
    the electrical effect). Measured: ``*_meas`` (noisy and quantised; position wrapped).
    ``current_ref`` is the speed controller's output, ``speed_ref`` the excitation.
    """

    t: F64
    current: F64
    speed: F64
    position: F64
    voltage: F64 | None
    current_meas: F64
    speed_meas: F64
    position_meas: F64
    voltage_meas: F64 | None
    current_ref: F64
    speed_ref: F64

    def __len__(self) -> int:
        return len(self.t)


class Plant:
    """A stateful simulated drive: :meth:`run` advances it block by block.

    The result does not depend on how the periods are split into blocks (the noise
    comes from one ``numpy.random.default_rng(seed)`` drawn three normals per period,
    and the kernel carries its state).
    """

    def __init__(self, truth: Truth, dt: float = 1e-3, controller: Controller | None = None,
                 sensors: Sensors | None = None, seed: int | None = 0, nsub: int = 5) -> None:
        if not is_positive(dt):
            raise ConfigError(f"dt: {dt!r} must be a positive number of seconds")
        if nsub < 1:
            raise ConfigError(f"nsub: {nsub!r} must be >= 1")
        self.truth = truth
        self.dt = float(dt)
        self.controller = controller or Controller()
        self.sensors = sensors or Sensors()
        self.seed = seed
        self._rng = np.random.default_rng(seed)
        self._p, self._ck, self._cs, self._cc = truth._kernel_params()
        self._gains = self.controller.gains(truth)
        self._quant = self.sensors.quant()
        comp = self.controller.compensation
        self._ff = _NO_FEEDFORWARD if comp is None else comp.kernel()
        self._sigma = np.array([self.sensors.current_noise, self.sensors.speed_noise,
                                self.sensors.position_noise])
        self.nsub, self.h_stiff = self._substeps(nsub)
        self._state = np.zeros(5, dtype=np.float64)
        self.k = 0  # periods simulated so far

    def _substeps(self, nsub: int) -> tuple[int, float]:
        """Sub-steps per period, and the largest step in the stiff zero-speed zone."""
        tr, dt = self.truth, self.dt
        J = tr["inertia.J"]
        # smooth stiffness: electrical pole, viscous pole, electromechanical and
        # position-periodic oscillations; keep h*lambda <= 0.5 for accuracy
        lam = abs(tr.get("viscous.B")) / J
        if tr.has_electrical:
            R, L, Ke = tr["electrical.R"], tr["electrical.L"], tr["electrical.Ke"]
            lam += abs(R) / L + math.sqrt(abs(tr.kt * Ke) / (J * L))
        sc = tr.angle_scale
        kk = abs(tr.get("unbalance.sin")) + abs(tr.get("unbalance.cos"))
        kk += sum(k * k * (abs(tr[f"cogging:{k}.sin"]) + abs(tr[f"cogging:{k}.cos"]))
                  for k in tr.cogging_orders)
        lam += math.sqrt(kk * sc * sc / J)
        vmax = 100.0 if tr.axis == "rotary" else 1.0
        lam += max([k * sc * vmax for k in tr.cogging_orders] + [0.0])
        n = max(nsub, math.ceil(dt * lam / 0.5))
        h = dt / n
        # friction stiffness at zero speed: d/dw (Tc + Ts) tanh(w/e) -> (Tc+|Ts|)/e
        lam_f = (abs(tr.get("coulomb.Tc")) + abs(tr.get("stribeck.Ts"))) / tr.coulomb_band
        lam_f += abs(tr.get("stribeck.Ts")) / tr.stribeck_speed
        lam_f /= J
        h_stiff = 2.0 / lam_f if lam_f > 0 else h
        # the most sub-steps of a period: all of them in the stiff zone near standstill
        most = max(n, math.ceil(dt / min(h_stiff, h)))
        if most > MAX_SUBSTEPS:
            # every stiffness above is proportional to 1/J: the J that brings it in bound
            raise ConfigError(
                f"inertia.J = {J:g}: the simulated drive would need {most} integration "
                f"steps per {dt * 1e3:g} ms period (its friction, cogging and poles are "
                f"stiff in proportion to 1/J), more than the simulator's {MAX_SUBSTEPS}: "
                f"give inertia.J >= {J * most / MAX_SUBSTEPS:.2g} with these parameters")
        return n, h_stiff

    @property
    def state(self) -> tuple[float, float, float]:
        """Current true (theta, omega, i)."""
        return float(self._state[0]), float(self._state[1]), float(self._state[2])

    def run(self, speed_ref: npt.ArrayLike, accel_ref: npt.ArrayLike | None = None) -> PlantBlock:
        """Advance ``len(speed_ref)`` control periods tracking ``speed_ref``.

        ``accel_ref`` is the reference's derivative, fed forward (zero when None).
        """
        w_ref = np.ascontiguousarray(speed_ref, dtype=np.float64)
        a_ref = (np.zeros_like(w_ref) if accel_ref is None
                 else np.ascontiguousarray(accel_ref, dtype=np.float64))
        n = len(w_ref)
        if a_ref.shape != w_ref.shape:
            raise ValueError(f"accel_ref has shape {a_ref.shape}, speed_ref {w_ref.shape}")
        noise = self._rng.standard_normal((n, 3)) * self._sigma
        out = np.empty((n, 9), dtype=np.float64)
        _sim.plant_run(self.dt, self.nsub, self.h_stiff, self._state, self._p, self._ck,
                       self._cs, self._cc, self._gains, self._quant, *self._ff, w_ref, a_ref,
                       noise, out)
        t = (self.k + np.arange(n, dtype=np.float64)) * self.dt
        self.k += n
        elec = self.truth.has_electrical
        cols = [np.ascontiguousarray(out[:, j]) for j in range(9)]
        return PlantBlock(
            t=t, current=cols[0], speed=cols[1], position=cols[2],
            voltage=cols[3] if elec else None,
            current_meas=cols[4], speed_meas=cols[5], position_meas=cols[6],
            voltage_meas=cols[7] if elec else None,
            current_ref=cols[8], speed_ref=w_ref,
        )

