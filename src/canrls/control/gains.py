"""Speed-loop PI gains from the identified inertia.

The loop a drive closes around the identified mechanics, :math:`L(s) = (k_p + k_i/s)
e^{-s T_d} / (J s (1 + s T_i))` (a delay ``T_d`` of the control period, the current loop
a first-order lag ``T_i``): :func:`for_bandwidth` places the crossover so that the
closed loop reaches a requested bandwidth with a stated phase margin, and
:func:`symmetric_optimum` tunes for the sum of the small time constants. Both state the
inertia they assume (with its sigma) and the margin the model gives. docs/tune.md.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from canrls.control.tune_limits import DEFAULT_MARGIN
from canrls.core.errors import ConfigError

__all__ = ["Loop", "SpeedGains", "for_bandwidth", "symmetric_optimum", "check_bandwidth"]

#: |T| at the closed loop's bandwidth: -3 dB.
_HALF_POWER = 1.0 / math.sqrt(2.0)


def _bisect_log(lo: float, hi: float, above: Callable[[float], bool]) -> float:
    """Where ``above`` turns false between ``lo`` and ``hi``: 60 bisections on a log scale."""
    for _ in range(60):
        mid = math.sqrt(lo * hi)
        if above(mid):
            lo = mid
        else:
            hi = mid
    return math.sqrt(lo * hi)


@dataclass(frozen=True)
class Loop:
    """What the loop is assumed to be: inertia ``J`` (target unit s²/rad) with ``sigma``,
    the control period ``dt`` [s], the delay ``Td`` [s] and the current loop's time
    constant ``Ti`` [s] (0: ideal)."""

    J: float
    J_sigma: float
    dt: float
    Td: float
    Ti: float

    def open_loop(self, kp: float, ki: float, w: np.ndarray, J: float | None = None) -> Any:
        """L(jw) = (kp + ki/(jw)) e^{-jw Td} / (J jw (1 + jw Ti))."""
        s = 1j * w
        return (kp + ki / s) * np.exp(-s * self.Td) / ((self.J if J is None else J) * s
                                                       * (1.0 + s * self.Ti))

    def bandwidth(self, kp: float, ki: float, J: float | None = None) -> float:
        """The closed loop's -3 dB bandwidth [rad/s]: the lowest w with |L/(1+L)| <= 1/sqrt 2."""
        w = np.geomspace(1e-2, math.pi / self.dt, 4000)
        L = self.open_loop(kp, ki, w, J)
        T = np.abs(L / (1.0 + L))
        below = np.nonzero(T <= _HALF_POWER)[0]
        if len(below) == 0:
            return math.inf
        k = int(below[0])
        if k == 0:
            return float(w[0])

        def above(x: float) -> bool:  # |T(jx)| > 1/sqrt 2
            Lx = self.open_loop(kp, ki, np.array([x]), J)[0]
            return bool(abs(Lx / (1.0 + Lx)) > _HALF_POWER)

        return _bisect_log(float(w[k - 1]), float(w[k]), above)

    def margin(self, kp: float, ki: float) -> tuple[float, float]:
        """(crossover [rad/s], phase margin [deg]) where |L| = 1."""
        w = np.geomspace(1e-2, math.pi / self.dt, 4000)
        mag = np.abs(self.open_loop(kp, ki, w))
        k = int(np.nonzero(mag <= 1.0)[0][0]) if np.any(mag <= 1.0) else len(w) - 1
        wc = _bisect_log(float(w[max(k - 1, 0)]), float(w[k]),  # |L(j wc)| = 1
                         lambda x: bool(abs(self.open_loop(kp, ki, np.array([x]))[0]) > 1.0))
        # PM = 180 deg + arg L(j wc), the phase unwrapped from -90 deg at low frequency
        phase = -90.0 - math.degrees(math.atan2(ki, kp * wc)) - math.degrees(
            wc * self.Td + math.atan(wc * self.Ti))
        return wc, 180.0 + phase


@dataclass(frozen=True)
class SpeedGains:
    """PI gains of the speed loop (target unit per rad/s and per rad), what they were
    tuned for and what they assume."""

    method: str
    kp: float
    ki: float
    unit: str
    loop: Loop
    bandwidth_hz: float
    crossover_hz: float
    phase_margin: float
    bandwidth_range_hz: tuple[float, float]
    requested_hz: float | None = None

    @property
    def integral_time(self) -> float:
        """Tn = kp / ki [s]."""
        return self.kp / self.ki

    def per_unit(self, base_torque: float, base_speed: float) -> tuple[float, float]:
        """(kp, ki) per unit of the drive's rating: kp w_b / T_b, ki w_b / T_b [1/s]."""
        return self.kp * base_speed / base_torque, self.ki * base_speed / base_torque

    def to_dict(self) -> dict[str, Any]:
        lp = self.loop
        return {"format": "canrls-gains", "version": 1, "method": self.method,
                "kp": self.kp, "ki": self.ki, "unit": self.unit,
                "requested_hz": self.requested_hz, "bandwidth_hz": self.bandwidth_hz,
                "crossover_hz": self.crossover_hz, "phase_margin_deg": self.phase_margin,
                "bandwidth_range_hz": list(self.bandwidth_range_hz),
                "inertia": lp.J, "inertia_sigma": lp.J_sigma, "period": lp.dt,
                "delay": lp.Td, "current_time_constant": lp.Ti}


def _finish(method: str, kp: float, ki: float, unit: str, loop: Loop,
            requested: float | None) -> SpeedGains:
    wc, pm = loop.margin(kp, ki)
    # the bandwidth if the true inertia is J -+ 2 sigma (the loop gain scales with 1/J)
    lo_J, hi_J = loop.J + 2.0 * loop.J_sigma, max(loop.J - 2.0 * loop.J_sigma, 1e-300)
    rng = (loop.bandwidth(kp, ki, lo_J) / (2 * math.pi),
           loop.bandwidth(kp, ki, hi_J) / (2 * math.pi))
    return SpeedGains(method, kp, ki, unit, loop, loop.bandwidth(kp, ki) / (2 * math.pi),
                      wc / (2 * math.pi), pm, rng, requested)


def check_bandwidth(hz: float, dt: float) -> None:
    """A bandwidth is positive and below the sample rate's Nyquist frequency."""
    nyquist = 0.5 / dt
    if not (math.isfinite(hz) and 0 < hz < nyquist):
        raise ConfigError(f"--bandwidth {hz!r}: must be a positive number of Hz below "
                          f"the Nyquist frequency {nyquist:g} Hz of the control period "
                          f"{dt:g} s")


def for_bandwidth(loop: Loop, hz: float, margin: float = DEFAULT_MARGIN,
                  unit: str = "N·m") -> SpeedGains:
    r"""PI gains whose closed loop has the bandwidth ``hz`` with phase margin ``margin``.

    For a crossover :math:`\omega_c` with lag :math:`\varphi_l = \omega_c T_d +
    \arctan \omega_c T_i`: :math:`k_p = J \omega_c \sqrt{1 + (\omega_c T_i)^2}
    \sin(\varphi_m + \varphi_l)`, :math:`k_i = k_p \omega_c \cot(\varphi_m +
    \varphi_l)`; :math:`\omega_c` by bisection until the closed loop's -3 dB point is
    :math:`2 \pi` ``hz``.
    """
    check_bandwidth(hz, loop.dt)
    if not (math.isfinite(margin) and 0 < margin < 90):
        raise ConfigError(f"--phase-margin {margin!r}: must be between 0 and 90 degrees")
    pm = math.radians(margin)

    def gains(wc: float) -> tuple[float, float]:
        x = pm + wc * loop.Td + math.atan(wc * loop.Ti)
        # kp = J wc sqrt(1 + (wc Ti)^2) sin(x); ki = kp wc cot(x)
        kp = loop.J * wc * math.sqrt(1.0 + (wc * loop.Ti) ** 2) * math.sin(x)
        return kp, kp * wc * math.cos(x) / math.sin(x)

    # the largest crossover the margin allows: pm + wc Td + atan(wc Ti) < 90 deg
    lo, hi = 1e-6, math.pi / loop.dt
    for _ in range(100):
        mid = 0.5 * (lo + hi)
        if pm + mid * loop.Td + math.atan(mid * loop.Ti) < 0.5 * math.pi:
            lo = mid
        else:
            hi = mid
    w_max = lo * 0.999
    target = 2.0 * math.pi * hz
    best = loop.bandwidth(*gains(w_max))
    if best < target:
        raise ConfigError(f"--bandwidth {hz:g}: with a phase margin of {margin:g} deg, a "
                          f"delay of {loop.Td:g} s and a current loop of {loop.Ti:g} s the "
                          f"speed loop reaches at most {best / (2 * math.pi):.3g} Hz")
    lo, hi = 1e-9, w_max
    for _ in range(80):  # the closed loop's bandwidth grows with the crossover
        mid = math.sqrt(lo * hi)
        if loop.bandwidth(*gains(mid)) < target:
            lo = mid
        else:
            hi = mid
    kp, ki = gains(hi)
    return _finish("bandwidth", kp, ki, unit, loop, hz)


def symmetric_optimum(loop: Loop, a: float = 2.0, unit: str = "N·m") -> SpeedGains:
    r"""The symmetric optimum for the sum of small time constants
    :math:`T_\sigma = T_d + T_i`: :math:`k_p = J / (a T_\sigma)`, integral time
    :math:`a^2 T_\sigma` (``a = 2``: crossover :math:`1/(2 T_\sigma)`, margin 37 deg)."""
    if not (math.isfinite(a) and a > 1):
        raise ConfigError(f"symmetric optimum: a = {a!r} must be above 1")
    Ts = loop.Td + loop.Ti
    # kp = J / (a Tsigma); ki = kp / (a^2 Tsigma)
    kp = loop.J / (a * Ts)
    ki = kp / (a * a * Ts)
    return _finish("symmetric optimum", kp, ki, unit, loop, None)
