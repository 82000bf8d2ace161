"""The simulated drive: plant, excitation, scenarios, faults and a python-can interface.

* :func:`simulate` runs a :class:`Scenario` (from :func:`scenario`) and returns a
  :class:`SimResult`: true and measured :class:`~canrls.core.samples.Signals`, the
  :class:`Truth`, the noise floor and the feedback frames.
* :class:`~canrls.sim.interface.SimBus` is the same drive as a python-can interface
  (``can.Bus(interface="canrls-sim", channel="standard")``); it is imported lazily
  (``canrls.sim.interface``) so that the physics do not pull in the bus machinery.
* :mod:`canrls.sim.faults` injects drops, duplicates, reordering, corruption and silence.

The physics follow ``docs/architecture.md``; see ``docs/simulator.md``.
"""

from __future__ import annotations

from canrls.sim.excitation import PRESETS, Excitation, excitation
from canrls.sim.faults import FaultInjector, FaultLog, FaultSpec, inject
from canrls.sim.plant import Controller, Plant, Sensors, Truth, load_torque, parse_effects
from canrls.sim.scenario import (
    DEFAULT_EFFECTS,
    SCENARIOS,
    Scenario,
    SimChunk,
    SimResult,
    Simulator,
    default_params,
    scenario,
    simulate,
)

__all__ = [
    "PRESETS",
    "Excitation",
    "excitation",
    "FaultInjector",
    "FaultLog",
    "FaultSpec",
    "inject",
    "Controller",
    "Plant",
    "Sensors",
    "Truth",
    "load_torque",
    "parse_effects",
    "DEFAULT_EFFECTS",
    "SCENARIOS",
    "Scenario",
    "SimChunk",
    "SimResult",
    "Simulator",
    "default_params",
    "scenario",
    "simulate",
]
