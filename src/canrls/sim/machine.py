"""The simulated machine: several simulated drives on one bus, each its own parameters,
hidden effect, seed and ID rule (:func:`machine`), their frames in time order
(:func:`machine_frames`). ``canrls sim --axes N`` writes its log (docs/simulator.md).
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np

from canrls.can.frameblock import FrameBlock
from canrls.can.idrules import IdRule
from canrls.can.protocol import Protocol
from canrls.core.errors import ConfigError
from canrls.sim.scenario import DEFAULT_EFFECTS, Scenario, Simulator, default_params, scenario

__all__ = ["AXIS_ID_STEP", "HIDDEN", "MAX_SIM_AXES", "MachineAxis", "machine",
           "machine_frames"]

#: IDs between two simulated axes: axis k's frames are the default DBC's + k * 0x10
#: (``--axes offset:0,0x10,...``), below canrls' own frames at 0x300
AXIS_ID_STEP = 0x10
#: Most axes of a simulated machine: the last one's DriveSpeed at 0x102 + 31 * 0x10 = 0x2F2
MAX_SIM_AXES = 32
#: The effect each axis has beyond the default ones, in turn ("" none): what
#: ``canrls diagnose --axis`` should find on it
HIDDEN: tuple[str, ...] = ("", "unbalance", "cogging:6", "offset")


@dataclass(frozen=True)
class MachineAxis:
    """One simulated drive of the machine: its name (``axis1`` ..), ID rule, hidden effect
    (empty: none) and scenario (the truth in ``scenario.truth``)."""

    name: str
    rule: IdRule
    hidden: str
    scenario: Scenario


def machine(n: int, *, duration: float, seed: int = 0, scenario_name: str = "standard"
            ) -> tuple[MachineAxis, ...]:
    """``n`` drives: axis k (0-based) has inertia and friction scaled by ``1 + 0.5 k``
    and ``1 + 0.25 k``, the hidden effect ``HIDDEN[k % 4]``, seed ``seed * 1000 + k`` and
    the rule ``offset:k * 0x10``."""
    if not 1 <= n <= MAX_SIM_AXES:
        raise ConfigError(f"--axes {n}: a simulated machine has 1 to {MAX_SIM_AXES} axes")
    axes = []
    base = tuple(DEFAULT_EFFECTS.split(","))
    for k in range(n):
        hidden = HIDDEN[k % len(HIDDEN)]
        effects = base + ((hidden,) if hidden else ())
        params = default_params(",".join(effects))
        for key in params:
            if key.startswith("inertia."):
                params[key] *= 1.0 + 0.5 * k
            elif key.startswith(("viscous.", "coulomb.")):
                params[key] *= 1.0 + 0.25 * k
        sc = scenario(scenario_name, effects=",".join(effects), params=params,
                      duration=duration, seed=seed * 1000 + k)
        axes.append(MachineAxis(f"axis{k + 1}", IdRule("offset", k * AXIS_ID_STEP), hidden, sc))
    return tuple(axes)


def machine_frames(axes: tuple[MachineAxis, ...], t0: float = 0.0, size: int = 65536
                   ) -> Iterator[FrameBlock]:
    """The frames of every axis, each on its rule's IDs (E2E CRC over its own ID), merged
    in time order, ``size`` periods at a time."""
    proto = Protocol.load()
    sims = [Simulator(a.scenario, t0=t0, protocol=proto.with_ids(a.rule)) for a in axes]
    while any(s.remaining for s in sims):
        blocks = [s.encode(s.step(size)) for s in sims if s.remaining]
        block = FrameBlock.concat(blocks)
        # a stable sort: at equal times the first axis's frame first
        yield block.take(np.argsort(block.t, kind="stable"))
