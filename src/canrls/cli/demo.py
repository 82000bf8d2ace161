"""``canrls demo``: the whole story in one command, no hardware.

    canrls demo                       # hidden unbalance, seed 1, 60 s of simulated drive
    canrls demo --hidden cogging:6 --seed 3 --duration 90

In one process: the simulated drive (python-can interface ``canrls-sim``, faster than
real time) whose physics include an effect the model lacks, the daemon estimating on
that bus, and a monitor on a ``virtual`` bus of the same channel, reading what the
daemon publishes like any tool would. The demo prints, as readable text:

1. the model failing: the residual RMS from the daemon's status frames, well above
   what the sensors explain;
2. the diagnosis naming the missing effect (``canrls.diagnosis.analysis`` on the feedback
   frames recorded from the bus; without it, the demo says so and uses the
   simulated drive's hidden effect);
3. the effect added with an ``RlsCommand`` frame, acknowledged by the daemon;
4. the error falling, and the parameters with the drive's true values beside them.
"""

from __future__ import annotations

import argparse
import math
import os
import sys
import threading
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, TextIO

from canrls.cli.demo_common import BASE as _BASE
from canrls.cli.demo_common import diagnosis
from canrls.cli.run import daemon_for
from canrls.core.errors import ConfigError

if TYPE_CHECKING:
    from canrls.can.protocol import Protocol
    from canrls.estimation.model import Model
    from canrls.estimation.settings import EstimatorSettings

__all__ = ["add_subparser", "run", "run_demo", "DemoResult"]

#: the single drive's speed profile (``--excitation``)
_EXCITATION = "reversals+chirp"
_counter = 0
_counter_lock = threading.Lock()


def add_subparser(subparsers: Any) -> argparse.ArgumentParser:
    p = subparsers.add_parser(
        "demo", help="simulated drive + daemon + monitor: find a missing effect (no hardware)",
        description="Run the simulated drive with a hidden effect, the daemon and the monitor "
                    "in one process: watch the model fail, the diagnosis name the missing "
                    "effect, the effect added by a command frame and the error fall.")
    p.add_argument("--duration", "-d", type=float, default=60.0, metavar="S",
                   help="simulated seconds in all (default 60; 40 %% before the fix)")
    p.add_argument("--seed", "-s", type=int, default=1, help="seed of the drive (default 1)")
    p.add_argument("--hidden", default="unbalance", metavar="EFFECT",
                   help="the effect the drive has and the model lacks: unbalance, cogging:K, "
                        "offset, stribeck (default unbalance)")
    p.add_argument("--excitation", default=None, metavar="PROFILE",
                   help="speed profile of the drive (default reversals+chirp: reversals at "
                        "20 rad/s plus a chirp, every few seconds alike; see docs/simulator.md)")
    p.add_argument("--axes", type=int, default=1, metavar="N",
                   help="a machine of N simulated drives on one bus, one daemon per axis; "
                        "the axis picked by the seed hides the effect, the others none; "
                        "the first line says which axis lacks what; the drives run the "
                        "simulated machine's profile, not --excitation (default 1: one "
                        "drive)")
    p.add_argument("--json", action="store_true", help="print one JSON summary at the end")
    p.set_defaults(func=run)
    return p


@dataclass
class DemoResult:
    """What the demo found (``run_demo``)."""

    hidden: str
    diagnosed: str | None
    added: str
    ack: str | None
    rms_before: float
    rms_after: float
    unit: str
    wall_s: float
    sim_s: float
    parameters: dict[str, dict[str, Any]] = field(default_factory=dict)

    @property
    def improvement(self) -> float:
        """Relative fall of the residual RMS (0.75: a quarter of what it was)."""
        if not (self.rms_before > 0 and math.isfinite(self.rms_after)):
            return math.nan
        return 1.0 - self.rms_after / self.rms_before

    def to_dict(self) -> dict[str, Any]:
        return {"hidden": self.hidden, "diagnosed": self.diagnosed, "added": self.added,
                "ack": self.ack, "rms_before": self.rms_before, "rms_after": self.rms_after,
                "unit": self.unit, "improvement": self.improvement, "wall_s": self.wall_s,
                "sim_s": self.sim_s, "parameters": self.parameters}


class _Timeline:
    """A listener on the monitor's bus: the drive's time (last feedback timestamp) and the
    residual RMS of every RlsStatus, and the feedback frames for the diagnosis."""

    def __init__(self, feedback_ids: frozenset[int]) -> None:
        from canrls.can.estimator_frames import frame_ids

        self.feedback_ids = feedback_ids
        self.status_id = frame_ids().status
        self.sim_t = 0.0
        self.rms: list[tuple[float, float]] = []
        self.frames: list[Any] = []
        self.keep = True
        self._lock = threading.Lock()

    def __call__(self, msg: Any) -> None:
        aid = msg.arbitration_id
        if aid in self.feedback_ids:
            self.sim_t = msg.timestamp
            if self.keep:
                self.frames.append(msg)
        elif aid == self.status_id and not msg.is_error_frame:
            import struct

            rms = struct.unpack_from("<f", bytes(msg.data), 0)[0]
            with self._lock:
                self.rms.append((self.sim_t, rms))

    def mean_rms(self, t0: float, t1: float) -> float:
        with self._lock:
            vals = [r for t, r in self.rms if t0 <= t <= t1 and math.isfinite(r)]
        return sum(vals) / len(vals) if vals else math.nan


def _wait_sim(tl: _Timeline, t: float, timeout: float,
              tick: Callable[[float], None] | None = None, every: float = 5.0) -> bool:
    end = time.monotonic() + timeout
    next_tick = (math.floor(tl.sim_t / every) + 1) * every
    while tl.sim_t < t:
        if time.monotonic() > end:
            return False
        if tick is not None and tl.sim_t >= next_tick:
            tick(next_tick)
            next_tick += every
        time.sleep(0.01)
    return True


def run_demo(duration: float = 60.0, seed: int = 1, hidden: str = "unbalance",
             excitation: str = _EXCITATION, out: TextIO | None = None,
             timeout: float = 600.0) -> DemoResult:
    """Run the demo; print the story to ``out`` (default stdout); return the figures."""
    import can

    from canrls.can.estimator_frames import encode_command, parse_effect
    from canrls.live.daemon_settings import DaemonSettings
    from canrls.live.monitor_listener import LibraryUnits, Monitor
    from canrls.processor.config import AppConfig, prepare
    from canrls.sim.plant import parse_effects
    from canrls.sim.scenario import scenario

    w = out or sys.stdout

    def say(text: str = "") -> None:
        w.write(text + "\n")
        w.flush()

    if not (math.isfinite(duration) and duration >= 10.0):
        raise ConfigError(f"--duration: {duration!r} must be at least 10 simulated seconds")
    hidden = ",".join(parse_effects(hidden))
    if hidden in _BASE or "," in hidden:
        raise ConfigError(f"--hidden: {hidden!r} must be one effect not among {', '.join(_BASE)}")
    effects = ",".join((*_BASE, hidden))
    sc = scenario("standard", effects=effects, seed=seed, excitation=excitation,
                  duration=duration)
    kt = sc.truth.kt
    cfg = AppConfig()
    cfg.model = {"effects": list(_BASE), "kt": kt}
    protocol, model, settings = prepare(cfg)
    units = LibraryUnits.for_model(model)
    unit = units.output_unit()
    global _counter
    with _counter_lock:
        _counter += 1
        channel = f"canrls-demo-{os.getpid()}-{_counter}"
    sim = dict(interface="canrls-sim", channel=channel, effects=effects, seed=seed,
               excitation=excitation, realtime=False, start_time=0.0, duration=None)
    fix_at = 0.4 * duration
    say(f"canrls demo: a simulated drive ({sc.truth.summary()}),")
    say(f"seed {seed}, excitation '{excitation}', about {duration:g} s simulated, "
        "faster than real time.")
    say(f"The model knows only {', '.join(_BASE)}: the drive's {hidden} is hidden from it.")
    say()
    dset = DaemonSettings(publish_interval=0.05, queue_size=20000, block_interval=0.005,
                          commands=True)
    daemon = daemon_for(protocol, model, settings, dset, bus=sim, backpressure=True)
    mon = Monitor(units=units, feedback_ids=[m.frame_id for m in protocol.messages],
                  source=f"virtual:{channel}")
    tl = _Timeline(frozenset(m.frame_id for m in protocol.messages))
    t_wall = time.monotonic()
    daemon.start()
    bus = can.Bus(interface="virtual", channel=channel, ignore_config=True)
    notifier = can.Notifier(bus, [mon, tl], timeout=0.1)
    diagnosed = None
    ack_text = None
    try:
        def tick(t: float) -> None:
            v = mon.snapshot()
            rms = v.status.residual_rms if v.status else math.nan
            text = f"{rms:.3g} {unit}" if math.isfinite(rms) else "- (filter warming up)"
            say(f"  t = {t:4.0f} s   residual RMS {text}")

        say(f"1. Estimating with the incomplete model ({fix_at:g} s):")
        if not _wait_sim(tl, fix_at, timeout, tick):
            raise TimeoutError("the simulated drive did not advance")
        tl.keep = False
        before = tl.mean_rms(fix_at / 2, fix_at)
        floor = sc.noise_floor
        say(f"   the residual RMS stays at {before:.3g} {unit} "
            f"({before / floor:.0f}x the sensor noise of {floor:.2g} {unit}): "
            f"something is missing.")
        say()
        say("2. Diagnosis of the feedback recorded from the bus (the drive is held meanwhile):")
        daemon.hold_input(True)
        frames = list(tl.frames)
        tl.frames.clear()
        diagnosed = _diagnose(frames, protocol, model, settings, hidden, say)
        add = diagnosed or hidden
        del frames
        say()
        eid, order = parse_effect(add)
        say(f"3. Sending RlsCommand add_effect {add} to the daemon (as canrls monitor "
            f"--command 'add {add}' would):")
        n_acks = len(mon.acks)
        bus.send(encode_command(4, eid, order))
        daemon.hold_input(False)
        ack = mon.wait_ack(n_acks, 30.0)
        ack_text = None if ack is None else ack.result.name.lower()
        say(f"   RlsCommandAck: {ack_text or 'none received'}; the daemon now estimates "
            f"{', '.join(daemon.model.effect_names)}")
        t_fix = tl.sim_t
        # the drive ran on while the diagnosis was computed: give the completed model the
        # same time the incomplete one had after it
        end_t = t_fix + (duration - fix_at)
        say()
        say(f"4. Estimating with the completed model (until {end_t:.0f} s):")
        _wait_sim(tl, end_t - 0.05, timeout, tick)
        deadline = time.monotonic() + 5.0
        while daemon.stats().backlog and time.monotonic() < deadline:
            time.sleep(0.01)
        time.sleep(0.15)
        after = tl.mean_rms(t_fix + (end_t - t_fix) / 2, end_t)
        view = mon.snapshot()
    finally:
        notifier.stop()
        bus.shutdown()
        daemon.stop()
    wall = time.monotonic() - t_wall
    fall = 1.0 - after / before if before > 0 else math.nan
    say(f"   the residual RMS falls from {before:.3g} to {after:.3g} {unit} "
        f"({fall * 100:.0f} % lower).")
    say()
    params = _final_estimates(view.parameters, sc.truth.params, say)
    say(f"({wall:.1f} s wall clock for {tl.sim_t:.0f} s of simulated drive)")
    return DemoResult(hidden=hidden, diagnosed=diagnosed, added=add, ack=ack_text,
                      rms_before=before, rms_after=after, unit=unit, wall_s=wall,
                      sim_s=tl.sim_t, parameters=params)


def _diagnose(frames: list[Any], protocol: Protocol, model: Model,
              settings: EstimatorSettings, hidden: str,
              say: Callable[[str], None]) -> str | None:
    """Diagnose the recorded feedback frames and say so; the effect the diagnosis names
    (None: none, or the diagnosis is not available or failed)."""
    try:
        report = diagnosis(frames, protocol, model, settings)
        if report is None:
            say("   (canrls.diagnosis.analysis is not available in this build: using the "
                f"effect the simulated drive hides, {hidden})")
            return None
        say("   " + report.format().replace("\n", "\n   "))
        if not report.suggestion:
            say(f"   -> the diagnosis names no effect from these data; adding the one "
                f"the simulated drive hides, {hidden}, to show the error fall")
            return None
        diagnosed = str(report.suggestion[0])
        say(f"   -> the diagnosis names {diagnosed}"
            + (" (the hidden effect)" if diagnosed == hidden else
               f" (the drive hides {hidden})"))
        return diagnosed
    except Exception as e:  # the demo goes on: the user still sees the fix
        say(f"   diagnosis failed ({e}); using the hidden effect {hidden}")
        return None


def _final_estimates(parameters: Sequence[Any], truth: Mapping[str, float],
                     say: Callable[[str], None]) -> dict[str, dict[str, Any]]:
    """Say the monitor's final estimates beside the truth; return them by parameter."""
    say("Final estimates (fixed point on the bus, ± sigma, float reference, truth):")
    params: dict[str, dict[str, Any]] = {}
    width = max([len(p.name) for p in parameters] + [9])
    for p in parameters:
        tv = truth.get(p.name)
        params[p.name] = {"fixed": p.fixed_value, "sigma": p.sigma, "float": p.float_value,
                          "truth": tv, "unit": p.unit}
        say(f"  {p.name:<{width}}  {_g(p.fixed_value):>11}  ± {_g(p.sigma):>9}  "
            f"{_g(p.float_value):>11}  truth {_g(tv):>10}  {p.unit}")
    return params


def _g(x: float | None) -> str:
    return "-" if x is None else f"{x:.4g}"


def run(args: argparse.Namespace) -> int:
    from canrls.cli._common import print_json

    if args.axes != 1:
        from canrls.cli.demo_axes import run_machine_demo

        if args.excitation is not None:
            raise ConfigError(f"--excitation {args.excitation}: the drives of --axes "
                              f"{args.axes} run the simulated machine's own profile")

        mres = run_machine_demo(args.axes, args.duration, args.seed, args.hidden,
                                out=sys.stderr if args.json else sys.stdout)
        if args.json:
            print_json(mres.to_dict())
        return 0 if mres.fixed_axis is not None else 1
    res = run_demo(args.duration, args.seed, args.hidden, args.excitation or _EXCITATION,
                   out=sys.stderr if args.json else sys.stdout)
    if args.json:
        print_json(res.to_dict())
    return 0 if res.ack == "ok" else 1
