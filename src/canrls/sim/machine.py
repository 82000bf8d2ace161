"""The simulated machine: several simulated drives on one bus, each its own parameters,
hidden effect, seed and ID rule (:func:`machine`), their frames in time order
(:func:`machine_frames`): drives of the default DBC moved by an offset, CiA 402 nodes or
ODrive CANSimple nodes (:data:`KINDS`). ``canrls sim --axes N`` writes its log
(docs/simulator.md).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from canrls.can.frameblock import FrameBlock
from canrls.can.idrules import IdRule
from canrls.can.mapping import SignalMapping
from canrls.can.protocol import DEFAULT_DBC, Protocol
from canrls.core.errors import ConfigError
from canrls.core.units import Ratings
from canrls.sim.scenario import DEFAULT_EFFECTS, Scenario, Simulator, default_params, scenario

__all__ = ["AXIS_ID_STEP", "CIA402_RATINGS", "HIDDEN", "KINDS", "MAX_SIM_AXES", "MachineAxis",
           "axis_params", "kind_dbc", "kind_protocol", "machine", "machine_frames", "simulators",
           "step_all"]

#: IDs between two simulated axes: axis k's frames are the default DBC's + k * 0x10
#: (``--axes offset:0,0x10,...``), below canrls' own frames at 0x300
AXIS_ID_STEP = 0x10
#: Most axes of a simulated machine: the last one's DriveSpeed at 0x102 + 31 * 0x10 = 0x2F2
MAX_SIM_AXES = 32
#: The effect each axis has beyond the default ones, in turn ("" none): what
#: ``canrls diagnose --axis`` should find on it
HIDDEN: tuple[str, ...] = ("", "unbalance", "cogging:6", "offset")
#: The drives a machine can have: kind -> (DBC shipped in canrls/data, None: the default
#: one; the mapping of its signals with the ratings of its relative units)
KINDS: dict[str, tuple[str | None, tuple[str, ...]]] = {
    "offset": (None, ()),
    # CiA 402: TPDO1 torque and current actual 0x6077, 0x6078 in per mille of the rated
    # torque 0x6076 (0.32 N·m) and current 0x6075 (5 A), TPDO2 position and velocity
    # actual 0x6064, 0x606C in increments (2^17 a turn)
    "cia402": ("cia402.dbc", ("torque=TPDO1.TorqueActual", "current=TPDO1.CurrentActual",
                              "speed=TPDO2.VelocityActual", "position=TPDO2.PositionActual")),
    "cansimple": ("odrive_cansimple.dbc", ("current=Get_Iq.Iq_Measured",
                                           "speed=Get_Encoder_Estimates.Vel_Estimate",
                                           "position=Get_Encoder_Estimates.Pos_Estimate")),
}
#: what the CiA 402 nodes' relative units refer to (``--rated-current``, ...)
CIA402_RATINGS = {"rated_torque": 0.32, "rated_current": 5.0, "increments_per_rev": 131072.0}


@dataclass(frozen=True)
class MachineAxis:
    """One simulated drive of the machine: its name (``axis1`` ..), ID rule, hidden effect
    (empty: none) and scenario (the truth in ``scenario.truth``)."""

    name: str
    rule: IdRule
    hidden: str
    scenario: Scenario


def kind_dbc(kind: str) -> Path:
    """The DBC of the drives of ``kind`` (a key of :data:`KINDS`)."""
    name = KINDS[kind][0]
    return DEFAULT_DBC if name is None else DEFAULT_DBC.with_name(name)


def kind_protocol(kind: str) -> Protocol:
    """The protocol of the drives of ``kind``, on the IDs of its DBC (node 1 for CiA 402,
    node 0 for CANSimple)."""
    name, signals = KINDS[kind]
    if name is None:
        return Protocol.load()
    ratings = CIA402_RATINGS if kind == "cia402" else {}
    mapping = dataclasses.replace(SignalMapping.from_strings(signals),
                                  ratings=Ratings(**ratings))
    return Protocol.load(kind_dbc(kind), mapping)


def machine(n: int, *, duration: float, seed: int = 0, scenario_name: str = "standard",
            kind: str = "offset", hidden: Sequence[str] | None = None
            ) -> tuple[MachineAxis, ...]:
    """``n`` drives of ``kind``: axis k (0-based) has inertia and friction scaled by
    ``1 + 0.5 k`` and ``1 + 0.25 k`` (:func:`axis_params`), the hidden effect ``hidden[k]`` (default
    ``HIDDEN[k % 4]``), seed ``seed * 1000 + k`` and the rule ``offset:k * 0x10``
    (``cia402``: node k + 1; ``cansimple``: node k)."""
    if not 1 <= n <= MAX_SIM_AXES:
        raise ConfigError(f"--axes {n}: a simulated machine has 1 to {MAX_SIM_AXES} axes")
    if kind not in KINDS:
        raise ConfigError(f"--ids {kind}: the simulated drives are {', '.join(KINDS)}")
    if hidden is not None and len(hidden) != n:
        raise ConfigError(f"{len(hidden)} hidden effects for a machine of {n} axes")
    axes = []
    base = tuple(DEFAULT_EFFECTS.split(","))
    for k in range(n):
        extra = HIDDEN[k % len(HIDDEN)] if hidden is None else hidden[k]
        effects = base + ((extra,) if extra else ())
        params = axis_params(",".join(effects), k)
        sc = scenario(scenario_name, effects=",".join(effects), params=params,
                      duration=duration, seed=seed * 1000 + k)
        rule = (IdRule("offset", k * AXIS_ID_STEP) if kind == "offset" else
                IdRule(kind, k + 1 if kind == "cia402" else k))
        name = f"axis{k + 1}" if kind == "offset" else f"node{rule.node}"
        axes.append(MachineAxis(name, rule, extra, sc))
    return tuple(axes)


def axis_params(effects: str, k: int) -> dict[str, float]:
    """The true values of axis ``k`` (0-based) of a simulated machine: the defaults of
    ``effects``, inertia scaled by ``1 + 0.5 k``, viscous and Coulomb friction by
    ``1 + 0.25 k``."""
    params = default_params(effects)
    for key in params:
        if key.startswith("inertia."):
            params[key] *= 1.0 + 0.5 * k
        elif key.startswith(("viscous.", "coulomb.")):
            params[key] *= 1.0 + 0.25 * k
    return params


def machine_frames(axes: tuple[MachineAxis, ...], t0: float = 0.0, size: int = 65536
                   ) -> Iterator[FrameBlock]:
    """The frames of every axis, each on its rule's IDs (E2E CRC over its own ID), merged
    in time order, ``size`` periods at a time."""
    sims = simulators(axes, t0)
    while (block := step_all(sims, size)) is not None:
        yield block


def simulators(axes: tuple[MachineAxis, ...], t0: float = 0.0) -> list[Simulator]:
    """One :class:`Simulator` per axis, encoding on its rule's IDs."""
    protos = {kind: kind_protocol(kind) for kind in {_kind(a.rule) for a in axes}}
    return [Simulator(a.scenario, t0=t0, protocol=protos[_kind(a.rule)].with_ids(a.rule))
            for a in axes]


def step_all(sims: list[Simulator], periods: int) -> FrameBlock | None:
    """The next ``periods`` of every drive's frames in time order (None: all ended)."""
    blocks = [s.encode(s.step(periods)) for s in sims if s.remaining != 0]
    if not blocks:
        return None
    block = FrameBlock.concat(blocks)
    # a stable sort: at equal times the first axis's frame first
    return block.take(np.argsort(block.t, kind="stable"))


def _kind(rule: IdRule) -> str:
    """The kind of drive of an axis's rule (its DBC and mapping)."""
    return rule.kind if rule.kind in KINDS else "offset"
