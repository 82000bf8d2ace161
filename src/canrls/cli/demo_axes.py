"""``canrls demo --axes N``: the demo's story on a machine of N simulated drives on one bus.

One axis, picked by the seed, has an effect its model lacks; the others have none. The
machine's frames (:func:`canrls.sim.machine.machine`, axis k on the default DBC's IDs +
k x 0x10) are sent on a ``virtual`` bus in steps of half a simulated second, one daemon per
axis serving them (:class:`~canrls.live.machine_daemon.MachineDaemon`, each axis its own frames
and own IDs, + k x 0x40). After 40 % of the time each axis's feedback is diagnosed, the
effect the diagnosis names is added with an ``RlsCommand`` on that axis's command ID only,
and each axis's residual RMS (its ``RlsStatus``) is compared before and after. The first
line printed is the answer; the story follows.
"""

from __future__ import annotations

import math
import os
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, TextIO

import numpy as np

from canrls.cli.demo_common import BASE as _BASE
from canrls.cli.demo_common import diagnosis
from canrls.core.errors import ConfigError

if TYPE_CHECKING:
    from canrls.can.frameblock import FrameBlock
    from canrls.live.daemon import Daemon
    from canrls.live.machine_daemon import MachineDaemon

__all__ = ["AxisStory", "MachineDemoResult", "run_machine_demo"]

#: simulated seconds sent at once; each daemon catches up and publishes between steps
STEP_S = 0.5


@dataclass
class AxisStory:
    """One axis of the machine demo: the effect it hides ("" none), the one the diagnosis
    named (None none), the residual RMS before and after the fix and its final model."""

    name: str
    hidden: str
    diagnosed: str | None
    rms_before: float
    rms_after: float
    effects: list[str]

    @property
    def change(self) -> float:
        """Relative change of the residual RMS (-0.8: a fifth of what it was)."""
        return self.rms_after / self.rms_before - 1.0 if self.rms_before > 0 else math.nan


@dataclass
class MachineDemoResult:
    """What the machine demo found (:func:`run_machine_demo`)."""

    axes: list[AxisStory]
    #: the axis the effect was added to (None: the diagnosis named none)
    fixed_axis: str | None
    added: str | None
    unit: str
    wall_s: float
    sim_s: float
    answer: str = ""

    def to_dict(self) -> dict[str, Any]:
        return {"answer": self.answer, "fixed_axis": self.fixed_axis, "added": self.added,
                "unit": self.unit, "wall_s": self.wall_s, "sim_s": self.sim_s,
                "axes": {a.name: {"hidden": a.hidden, "diagnosed": a.diagnosed,
                                  "rms_before": a.rms_before, "rms_after": a.rms_after,
                                  "change": a.change, "effects": a.effects}
                         for a in self.axes}}


def run_machine_demo(n: int = 4, duration: float = 30.0, seed: int = 1,
                     hidden: str = "unbalance", out: TextIO | None = None,
                     timeout: float = 600.0) -> MachineDemoResult:
    """Run the machine demo; print the answer, then the story, to ``out`` (default
    stdout); return the figures."""
    import can

    from canrls.can.estimator_frames import CommandCode, encode_command, parse_effect
    from canrls.live.bus_link import COMMAND_ID, moved
    from canrls.live.daemon import Daemon
    from canrls.live.daemon_settings import DaemonSettings
    from canrls.live.machine_daemon import MachineDaemon
    from canrls.live.monitor_listener import LibraryUnits
    from canrls.processor.axes import OWN_STEP
    from canrls.processor.config import AppConfig, prepare
    from canrls.sim.machine import MAX_SIM_AXES, kind_protocol, machine, simulators
    from canrls.sim.plant import parse_effects

    if not 2 <= n <= MAX_SIM_AXES:
        raise ConfigError(f"--axes {n}: the machine demo has 2 to {MAX_SIM_AXES} axes")
    if not (math.isfinite(duration) and duration >= 10.0):
        raise ConfigError(f"--duration: {duration!r} must be at least 10 simulated seconds")
    hidden = ",".join(parse_effects(hidden))
    if hidden in _BASE or "," in hidden:
        raise ConfigError(f"--hidden: {hidden!r} must be one effect not among {', '.join(_BASE)}")
    which = int(np.random.default_rng(seed).integers(n))
    axes = machine(n, duration=duration, seed=seed,
                   hidden=[hidden if k == which else "" for k in range(n)])
    lines: list[str] = []
    say: Callable[[str], None] = lines.append
    base = kind_protocol("offset")
    cfg = AppConfig()
    cfg.model = {"effects": list(_BASE), "kt": axes[0].scenario.truth.kt}
    _, model, settings = prepare(cfg)
    unit = LibraryUnits.for_model(model).output_unit()
    channel = f"canrls-demo-axes-{os.getpid()}-{time.monotonic_ns()}"
    bus = {"interface": "virtual", "channel": channel}
    daemons: dict[str, Daemon] = {}
    for k, a in enumerate(axes):
        dset = DaemonSettings(publish_interval=0.05, block_interval=0.005, commands=True,
                              own_offset=k * OWN_STEP, rx_filter=True)
        daemons[a.name] = Daemon(base.with_ids(a.rule), model, settings, dset, bus=bus)
    md = MachineDaemon(daemons)
    say(f"{n} simulated drives on one bus, seed {seed}, {duration:g} s simulated; each "
        f"axis's model knows only {', '.join(_BASE)}:")
    for k, a in enumerate(axes):
        say(f"  {a.name}: feedback on the default IDs + {k * 0x10:#x}, own frames + "
            f"{k * OWN_STEP:#x}; {a.scenario.truth.summary()}")
    fix_at = 0.4 * duration
    sims = simulators(axes)
    feed = can.Bus(interface="virtual", channel=channel, preserve_timestamps=True,
                   ignore_config=True)
    ids = {a.name: frozenset(m.frame_id for m in daemons[a.name].protocol.messages)
           for a in axes}
    feeder = _Feeder(sims, feed, md, ids, timeout)
    t_wall = time.monotonic()
    diagnosed: dict[str, str | None] = {}
    fixed_axis = added = None
    try:
        md.start()
        feeder.advance(fix_at, keep=True)
        before = {a.name: feeder.mean(a.name, fix_at / 2, fix_at) for a in axes}
        say("")
        say(f"1. Residual RMS of each axis after {feeder.sim_t:.0f} s (its RlsStatus):")
        for a in axes:
            floor = a.scenario.noise_floor
            say(f"  {a.name}: {before[a.name]:.3g} {unit} ({before[a.name] / floor:.1f}x the "
                f"sensor noise of {floor:.2g} {unit})")
        say("")
        say("2. Diagnosis of each axis's feedback recorded from the bus:")
        from canrls.can.frameblock import FrameBlock

        everything = FrameBlock.concat(feeder.recorded)
        feeder.recorded.clear()
        for a in axes:
            mine = everything.take(np.isin(everything.arbitration_id, list(ids[a.name])))
            report = diagnosis(mine, daemons[a.name].protocol, model, settings)
            sugg = str(report.suggestion[0]) if report is not None and report.suggestion \
                else None
            diagnosed[a.name] = sugg
            say(f"  {a.name}: " + (f"{sugg} is missing" if sugg else "nothing missing"))
        del everything
        named = [(k, a) for k, a in enumerate(axes) if diagnosed[a.name]]
        say("")
        if named:
            k, a = max(named, key=lambda ka: before[ka[1].name])
            fixed_axis, added = a.name, diagnosed[a.name]
            eid, order = parse_effect(added)
            own = COMMAND_ID + k * OWN_STEP
            say(f"3. RlsCommand add_effect {added} to {a.name} only (ID {own:#x}):")
            feed.send(moved(encode_command(CommandCode.ADD_EFFECT, eid, order), k * OWN_STEP))
            d = daemons[a.name]
            if not d.wait_for(lambda x: added in x.model.effect_names, 30.0):
                say(f"  {a.name} did not add {added} within 30 s")
            say(f"  {a.name} now estimates {', '.join(d.model.effect_names)}; the others "
                f"{', '.join(_BASE)}")
        else:
            say("3. The diagnosis names no effect on any axis: nothing is added.")
        t_fix = feeder.sim_t
        feeder.advance(duration, keep=False)
        say("")
        say(f"4. Residual RMS of each axis before and after (until {feeder.sim_t:.0f} s):")
        stories = []
        for a in axes:
            after = feeder.mean(a.name, t_fix + (feeder.sim_t - t_fix) / 2, feeder.sim_t)
            s = AxisStory(a.name, a.hidden, diagnosed[a.name], before[a.name], after,
                          list(daemons[a.name].model.effect_names))
            stories.append(s)
            say(f"  {a.name}: {s.rms_before:.3g} -> {s.rms_after:.3g} {unit} "
                f"({s.change * 100:+.0f} %)" + (f"   {added} added" if a.name == fixed_axis
                                                 else ""))
    finally:
        md.stop()
        feed.shutdown()
    wall = time.monotonic() - t_wall
    say("")
    say(f"({wall:.1f} s wall clock for {feeder.sim_t:.0f} s of a simulated machine)")
    answer = _answer(stories, fixed_axis, added, {a.name: a.scenario.noise_floor for a in axes})
    w = out or sys.stdout
    w.write("\n".join([answer, *lines]) + "\n")
    w.flush()
    return MachineDemoResult(stories, fixed_axis, added, unit, wall, feeder.sim_t, answer)


class _Feeder:
    """Sends the machine's frames on the feed bus, a step at a time, each daemon caught up
    and published before the next step; keeps each axis's RlsStatus RMS by time."""

    def __init__(self, sims: list[Any], feed: Any, md: MachineDaemon,
                 ids: dict[str, frozenset[int]], timeout: float) -> None:
        self.sims, self.feed, self.md, self.ids, self.timeout = sims, feed, md, ids, timeout
        self.sim_t = 0.0
        self.sent = dict.fromkeys(ids, 0)
        self.rms: dict[str, list[tuple[float, float]]] = {n: [] for n in ids}
        #: the frames sent while ``keep``: the feedback the diagnosis reads
        self.recorded: list[FrameBlock] = []

    def advance(self, until: float, keep: bool) -> None:
        """Send the frames up to ``until`` simulated seconds."""
        from canrls.sim.machine import step_all

        while self.sim_t < until - 1e-9:
            block = step_all(self.sims, int(round(STEP_S * 1000)))
            if block is None:
                break
            if keep:
                self.recorded.append(block)
            for name, fids in self.ids.items():
                self.sent[name] += int(np.isin(block.arbitration_id, list(fids)).sum())
            for m in block.to_messages("demo"):
                self.feed.send(m)
            self.sim_t = float(block.t[-1])
            if not self.md.wait_for(lambda x: all(
                    x.daemons[n].stats().frames >= k for n, k in self.sent.items()),
                    self.timeout):
                raise TimeoutError("the daemons did not take the machine's frames")
            time.sleep(0.12)  # > 2 publications: each RlsStatus covers this step
            for name, d in self.md.daemons.items():
                st = d.last_status
                if st is not None and math.isfinite(st.residual_rms):
                    self.rms[name].append((self.sim_t, st.residual_rms))

    def mean(self, name: str, t0: float, t1: float) -> float:
        """Mean RMS of axis ``name`` published between ``t0`` and ``t1`` s (NaN: none)."""
        vals = [r for t, r in self.rms[name] if t0 <= t <= t1]
        return sum(vals) / len(vals) if vals else math.nan


def _answer(stories: list[AxisStory], fixed_axis: str | None, added: str | None,
            floors: dict[str, float]) -> str:
    """The first line: which axis lacked what, how its error fell, the others' state."""
    others = [s for s in stories if s.name != fixed_axis]
    if fixed_axis is None:
        return f"canrls demo: no effect diagnosed on any of the {len(stories)} axes"
    s = next(s for s in stories if s.name == fixed_axis)
    near = [o.rms_after / floors[o.name] for o in others]
    return (f"canrls demo: {fixed_axis} lacks {added}; added to it alone, its residual RMS "
            f"fell {-s.change * 100:.0f} % ({s.rms_before / floors[s.name]:.1f}x -> "
            f"{s.rms_after / floors[s.name]:.1f}x the sensor noise); the other {len(others)} "
            f"axes kept their model, at {min(near):.1f}-{max(near):.1f}x theirs")
