"""What an engineer measures on the simulated drive's speed loop, as on a rig.

:func:`speed_ripple` (the measured speed's part periodic in the measured position) and
:func:`step_bandwidth` (the closed loop's -3 dB bandwidth from speed steps); the tests
and ``tools/bench_tune.py`` of ``canrls tune`` measure with them (docs/tune.md).
"""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt

from canrls.sim.plant import Plant

__all__ = ["speed_ripple", "step_bandwidth"]


def speed_ripple(position: npt.ArrayLike, speed: npt.ArrayLike, orders: int = 24) -> float:
    r"""RMS of the part of ``speed`` periodic in ``position`` (harmonics 1..``orders``,
    least squares with a constant): the ripple without the sensor's white noise.

    :math:`w \approx c_0 + \sum_k a_k \sin k\vartheta + b_k \cos k\vartheta`, ripple
    :math:`\sqrt{\overline{(\sum_k a_k \sin k\vartheta + b_k \cos k\vartheta)^2}}`."""
    th = np.asarray(position, dtype=np.float64)
    w = np.asarray(speed, dtype=np.float64)
    cols = [f(k * th) for k in range(1, orders + 1) for f in (np.sin, np.cos)]
    A = np.column_stack([*cols, np.ones_like(th)])
    c, *_ = np.linalg.lstsq(A, w, rcond=None)
    return float(np.sqrt(np.mean((A[:, :-1] @ c[:-1]) ** 2)))


def step_bandwidth(plant: Plant, low: float, high: float, steps: int = 6,
                   settle: int = 1000, hold: int = 500) -> float:
    r"""The closed speed loop's -3 dB bandwidth [Hz] from ``steps`` steps between
    ``low`` and ``high`` [rad/s] (no reference feed-forward), on the true speed.

    The impulse response :math:`h_k = \Delta y_k / \Delta r` averaged over the steps;
    :math:`|T(e^{j\omega dt})| = |\sum_k h_k e^{-j\omega k dt}|`, the lowest frequency
    (1 Hz to Nyquist) where it falls to :math:`1/\sqrt 2`."""
    dt = plant.dt
    plant.run(np.full(settle, low))
    hs = []
    for k in range(steps):
        a, b = (low, high) if k % 2 == 0 else (high, low)
        y = np.concatenate([[a], plant.run(np.full(hold, b)).speed])
        hs.append(np.diff(y) / (b - a))
    h = np.mean(hs, axis=0)
    w = 2 * np.pi * np.geomspace(1.0, 0.5 / dt, 4000)
    T = np.abs(np.exp(-1j * np.outer(w, np.arange(len(h)) * dt)) @ h)
    below = np.nonzero(T <= 1 / math.sqrt(2))[0]
    return float(w[below[0]] / (2 * np.pi)) if len(below) else math.inf
