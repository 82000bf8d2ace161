"""``canrls sim``: write a log of the simulated drive, or the logs of a simulated fleet.

    canrls sim --out drive.log --duration 60 --effects inertia,viscous,coulomb,cogging:24 \\
               --seed 3 --faults drop=0.01,silence=0.5s@10s
    canrls sim fleet --drives 50 --recordings 10 --out fleet/ --seed 1

The log holds the drive's feedback frames (``DriveCurrent``, ``DriveSpeed`` of the
default DBC, CRC and alive counter included), timestamps from ``--start-time``
(default 0) in steps of the control period. ``.log`` is candump; other suffixes
(``.asc``, ``.blf``, ``.trc``, ``.csv``) go through python-can's writers. One summary
line goes to stdout (``> truth.txt`` keeps it): frames written, duration, scenario,
truth and faults.

``canrls sim fleet`` writes ``DIR/<drive>/<drive>-<k>.log`` for every drive and
recording (``--duration`` seconds each, default 6), ``DIR/manifest.csv`` and
``DIR/truth.json`` (:mod:`canrls.sim.fleet_plan`; docs/fleet.md): a spread of drive types,
physics, noise and excitation, a few drives wearing.
"""

from __future__ import annotations

import argparse
import math
import signal
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from canrls.core.checks import is_positive
from canrls.core.errors import ConfigError

__all__ = ["add_subparser", "run", "MAX_DURATION"]

#: Longest simulated run [s]: a day, some 7 GB of candump at 1 kHz (the simulator
#: writes about 86 MB/s; beyond a day a run is a disk filling up, not a test log).
MAX_DURATION = 86400.0


def _param(text: str) -> tuple[str, float]:
    name, eq, value = text.partition("=")
    if not eq:
        raise argparse.ArgumentTypeError(f"{text!r} is not NAME=VALUE (e.g. coulomb.Tc=0.03)")
    try:
        return name.strip(), float(value)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r}: {value!r} is not a number") from None


def add_subparser(subparsers: Any) -> argparse.ArgumentParser:
    from canrls.sim.excitation import PRESETS
    from canrls.sim.scenario import DEFAULT_EFFECTS, SCENARIOS

    p = subparsers.add_parser(
        "sim", help="write a CAN log of the simulated drive (or a simulated fleet's logs)",
        description="Simulate the drive and write its feedback frames to a log "
                    "(candump .log, or any format python-can writes); 'canrls sim fleet' "
                    "writes the logs of a fleet of drives, a few of them wearing, with a "
                    "manifest and a truth file.")
    p.add_argument("mode", nargs="?", choices=("drive", "fleet"), default="drive",
                   help="'fleet': many drives, each recorded again and again (default: "
                        "one drive)")
    p.add_argument("--out", "-o", required=True, type=Path, metavar="LOG",
                   help="log file to write (.log, .asc, .blf, .csv, .trc; written to a "
                        "temporary beside it and renamed when complete; fleet: the "
                        "directory)")
    p.add_argument("--duration", "-d", type=float, default=None, metavar="SECONDS",
                   help=f"simulated time [s], at most {MAX_DURATION:g} (a day; required; "
                        f"fleet: of each recording, default 6)")
    f = p.add_argument_group("fleet (canrls sim fleet)")
    f.add_argument("--drives", type=int, default=50, metavar="N",
                   help="drives of the fleet (default 50)")
    f.add_argument("--recordings", type=int, default=10, metavar="M",
                   help="recordings of each drive (default 10)")
    f.add_argument("--days", type=float, default=7.0, metavar="D",
                   help="days between a drive's recordings (default 7)")
    p.add_argument("--effects", "-e", default=None, metavar="NAME,...",
                   help=f"true physics (default {DEFAULT_EFFECTS}); names: inertia, viscous, "
                        "coulomb, stribeck, offset, unbalance, cogging:K, electrical")
    p.add_argument("--seed", "-s", type=int, default=0,
                   help="seed, a non-negative integer (default 0)")
    p.add_argument("--faults", "-f", default=None, metavar="SPEC",
                   help="faults, e.g. drop=0.01,dup=0.005,reorder=0.01,corrupt=0.001,"
                        "silence=0.5s@10s")
    p.add_argument("--scenario", default="standard", choices=sorted(SCENARIOS),
                   help="scenario (default standard)")
    p.add_argument("--axis", choices=["rotary", "linear"], default=None,
                   help="axis (default: the scenario's)")
    p.add_argument("--axes", type=int, default=None, metavar="N",
                   help="a machine of N drives on one bus (1 to 32): axis k's frames on the "
                        "default DBC's IDs + (k-1)*0x10 (canrls fit --axes offset:0,0x10,...), "
                        "its own parameters and seed, axes 2, 3, 4 with a hidden unbalance, "
                        "cogging:6, offset (and so on in turn); one line per axis with its "
                        "truth")
    p.add_argument("--ids", choices=("offset", "cia402", "cansimple"), default="offset",
                   help="--axes: the machine's drives: the default DBC's moved by an offset "
                        "(default), CiA 402 nodes 1..N (canrls/data/cia402.dbc, current in "
                        "per mille of 5 A, 131072 increments a turn) or ODrive CANSimple "
                        "nodes 0..N-1 (canrls/data/odrive_cansimple.dbc)"),
    p.add_argument("--excitation", "-x", default=None, metavar="PROFILE",
                   help=f"excitation preset or sum (a+b) of {', '.join(PRESETS)}")
    p.add_argument("--param", "-p", action="append", type=_param, default=[],
                   metavar="NAME=VALUE", help="true parameter value (repeatable), e.g. "
                                              "coulomb.Tc=0.03")
    p.add_argument("--channel", default="can0",
                   help="channel name written in the log: printable ASCII, no spaces "
                        "(default can0)")
    p.add_argument("--start-time", type=float, default=0.0, metavar="T0",
                   help="timestamp of the first period [s] (default 0)")
    p.add_argument("--feedforward", metavar="FILE",
                   help="the speed controller adds this feedforward (feedforward.json of "
                        "'canrls tune --out'): its map at the measured position, its "
                        "friction at the speed reference")
    p.add_argument("--gains", metavar="FILE",
                   help="the speed controller's PI gains and inertia feed-forward from "
                        "this file (gains.json of 'canrls tune --out')")
    p.set_defaults(func=run, sim_parser=p)
    return p


def check_args(args: argparse.Namespace) -> None:
    """The options' values, before anything is simulated or written."""
    from canrls.can.logs import check_channel
    from canrls.can.writers import RECORD_SUFFIXES
    from canrls.core.checks import MAX_TIMESTAMP, in_range
    from canrls.core.errors import LogFormatError
    from canrls.core.files import check_writable

    if not in_range(args.duration, 0, MAX_DURATION, lo_open=True):
        raise ConfigError(f"--duration: {args.duration!r} must be a positive number of "
                          f"seconds, at most {MAX_DURATION:g} (a day of the drive, some "
                          f"7 GB of candump at 1 kHz; for more, several runs with "
                          f"--start-time)")
    if not (math.isfinite(args.start_time)
            and abs(args.start_time) + args.duration <= MAX_TIMESTAMP):
        raise ConfigError(f"--start-time {args.start_time!r}: the log's times must stay "
                          f"within {MAX_TIMESTAMP:g} s (what the log readers take)")
    if args.seed < 0:
        raise ConfigError(f"--seed {args.seed}: must be a non-negative integer")
    try:
        check_channel(args.channel, "--channel")
    except LogFormatError as e:
        raise ConfigError(str(e)) from e
    suffix = Path(args.out).suffix.lower()
    if suffix not in RECORD_SUFFIXES:
        raise ConfigError(f"--out {args.out}: unknown log format {suffix or '(no suffix)'!r}"
                          f" (canrls writes {', '.join(RECORD_SUFFIXES)})")
    check_writable(args.out, f"--out {args.out}")


@contextmanager
def _terminated_as_exit() -> Iterator[None]:
    """SIGTERM raises SystemExit(143) while the log is written, so that its temporary
    is removed (the default action would leave it); the handler is restored after."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def stop(signum: int, frame: Any) -> None:
        raise SystemExit(128 + signum)

    old = signal.signal(signal.SIGTERM, stop)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, old)


def run(args: argparse.Namespace) -> int:
    from canrls.can.logs import write_log
    from canrls.sim.scenario import Simulator, scenario

    if args.mode == "fleet":
        return run_fleet(args)
    if args.duration is None:
        args.sim_parser.error("the following arguments are required: --duration/-d")
    check_args(args)
    if args.axes is not None:
        return run_machine(args)
    sc = scenario(args.scenario, effects=args.effects, seed=args.seed, faults=args.faults,
                  axis=args.axis, excitation=args.excitation, duration=args.duration,
                  params=dict(args.param))
    sc = with_tuning(sc, args.feedforward, args.gains)
    sim = Simulator(sc, t0=args.start_time)
    with _terminated_as_exit():
        n = write_log(args.out, sim.frames(), channel=args.channel, what=f"--out {args.out}")
    faults = f"; faults {sc.faults}: {sim.fault_log.summary()}" if sc.faults.active else ""
    clipped = f"; {sim.clipped} values clipped to the DBC range" if sim.clipped else ""
    tuned = "".join(f"; {what} {path}" for what, path in (
        ("feedforward", args.feedforward), ("gains", args.gains)) if path is not None)
    print(f"canrls sim: wrote {n} frames to {args.out} ({sc.duration:g} s, scenario {sc.name}, "
          f"seed {sc.seed}); truth: {sc.truth.summary()}{faults}{clipped}{tuned}")
    return 0


def with_tuning(sc: Any, feedforward: str | None, gains: str | None) -> Any:
    """The scenario with the speed controller of ``canrls tune``'s files: the torques
    of a file in N·m (N) become current through the simulated drive's Kt."""
    from dataclasses import replace

    from canrls.control.tuner import read_feedforward, read_gains
    from canrls.sim.plant import Compensation

    ctl = sc.controller
    kt = sc.truth.kt
    if feedforward is not None:
        d = read_feedforward(feedforward)
        sp, m = d["speed"], d.get("map") or {}
        par = sp["parameters"]
        ctl = replace(ctl, compensation=Compensation(
            map=tuple(m.get("torque", ())), period=m.get("period", 2.0 * math.pi),
            scale=1.0 if d["unit"] == "A" else 1.0 / kt, B=par.get("viscous.B", 0.0),
            Tc=par.get("coulomb.Tc", 0.0), Ts=par.get("stribeck.Ts", 0.0),
            ws=sp["stribeck_speed"], band=sp["coulomb_band"], lead=d["lead"],
            T0=par.get("offset.T0", 0.0)))
    if gains is not None:
        g = read_gains(gains)
        per_amp = g["unit"] == "A"
        ctl = replace(ctl, kp_speed=g["kp"] if per_amp else g["kp"] / kt,
                      ki_speed=g["ki"] if per_amp else g["ki"] / kt,
                      inertia_ff=g["inertia"] * kt if per_amp else g["inertia"])
    return sc.replace(controller=ctl)


#: options of one drive that a fleet draws for each of its drives
_DRIVE_ONLY = ("effects", "faults", "axis", "excitation", "feedforward", "gains")


def _refuse_drive_options(args: argparse.Namespace, command: str, why: str) -> None:
    """The options of one drive, refused by ``command`` (a fleet, a machine)."""
    for opt in _DRIVE_ONLY:
        if getattr(args, opt) is not None:
            raise ConfigError(f"--{opt}: not an option of '{command}' ({why})")
    if args.param:
        raise ConfigError(f"--param: not an option of '{command}'")


def run_machine(args: argparse.Namespace) -> int:
    """``canrls sim --axes N``: the log of a simulated machine."""
    from canrls.can.logs import write_log
    from canrls.sim.machine import machine, machine_frames

    _refuse_drive_options(args, "canrls sim --axes", "each axis's physics are the machine's")
    axes = machine(args.axes, duration=args.duration, seed=args.seed,
                   scenario_name=args.scenario, kind=args.ids)
    with _terminated_as_exit():
        n = write_log(args.out, machine_frames(axes, t0=args.start_time),
                      channel=args.channel, what=f"--out {args.out}")
    print(f"canrls sim: wrote {n} frames of {len(axes)} {'axes' if len(axes) > 1 else 'axis'} "
          f"to {args.out} "
          f"({args.duration:g} s, scenario {args.scenario}, seed {args.seed}; canrls fit "
          f"{_fit_options(axes, args.ids)})")
    for a in axes:
        print(f"  {a.name} ({a.rule}, hidden: {a.hidden or 'none'}): truth: "
              f"{a.scenario.truth.summary()}")
    return 0


def _fit_options(axes: Any, kind: str) -> str:
    """The options of ``canrls fit`` that read the machine's log back."""
    from canrls.sim.machine import CIA402_RATINGS, KINDS, kind_dbc

    if kind == "offset":
        return "--axes offset:" + ",".join(f"{a.rule.node:#x}" for a in axes)
    nodes = [a.rule.node for a in axes]
    out = [f"--dbc {kind_dbc(kind)}", *(f"--signal {s}" for s in KINDS[kind][1])]
    if kind == "cia402":
        out += [f"--{k.replace('_', '-')} {v:g}" for k, v in CIA402_RATINGS.items()]
    return " ".join([*out, f"--axes {kind}:{nodes[0]}-{nodes[-1]}"])


def run_fleet(args: argparse.Namespace) -> int:
    """``canrls sim fleet``."""
    from canrls.cli._common import Progress
    from canrls.sim.fleet_plan import make_fleet, write_fleet

    _refuse_drive_options(args, "canrls sim fleet",
                          "each drive's physics, faults and excitation are drawn")
    duration = 6.0 if args.duration is None else args.duration
    if args.drives < 1 or args.recordings < 1:
        raise ConfigError(f"--drives {args.drives} --recordings {args.recordings}: at least 1")
    if not is_positive(args.days):
        raise ConfigError(f"--days: {args.days!r} must be a positive number of days")
    plan = make_fleet(args.drives, args.recordings, duration, args.seed, days=args.days)
    bar = Progress("sim fleet", unit="log")
    out = write_fleet(plan, args.out, progress=bar.callback)
    bar.close()
    classes: dict[str, int] = {}
    for d in plan.drives:
        classes[d.cls] = classes.get(d.cls, 0) + 1
    print(f"canrls sim fleet: wrote {args.drives * args.recordings} logs of {args.drives} "
          f"drives ({duration:g} s each, seed {args.seed}) to {out}: "
          + ", ".join(f"{n} {c}" for c, n in sorted(classes.items()))
          + f"; truth in {out / 'truth.json'}, manifest {out / 'manifest.csv'}")
    return 0
