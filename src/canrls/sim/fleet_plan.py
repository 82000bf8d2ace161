"""A simulated fleet of drives: many drives, each recorded again and again, a few wearing.

:func:`make_fleet` draws a :class:`FleetPlan` (which drives, their types, their physics
and excitation, which of them wear and how) and :func:`write_fleet` writes it as a
plant's logs would arrive: ``DIR/<type>/<drive>/<drive>-<k>.log`` (candump, epoch
times, one recording a week or so per drive; ``'DIR/{type}/{drive}/*.log'`` is the
pattern of ``canrls fleet ingest``), ``DIR/manifest.csv`` (``path,drive,type``) and
``DIR/truth.json`` (every drive's class, true parameters per recording, what wears and
from which recording). ``canrls sim fleet`` runs it; ``docs/fleet.md`` describes the
spread, the wear and the truth file.

The drives' differences are those of a real plant: three types (sizes) with a
log-normal spread of inertia and friction around each type's nominal values, a load
offset of either sign, sensor noise and speed-loop excitation of their own; from one
recording to the next the friction drifts with temperature and lubrication by a few
per cent (scatter that a single recording's sigma cannot see: the fleet's detection
has to measure it), and the operating profile's speeds and PRBS change.
"""

from __future__ import annotations

import csv
import datetime
import json
import math
import os
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from canrls.can.logs import write_log
from canrls.core.errors import ConfigError
from canrls.sim.excitation import Excitation, prbs, reversals
from canrls.sim.plant import Controller
from canrls.sim.scenario import Simulator, scenario

__all__ = ["DriveType", "TYPES", "WEAR_CLASSES", "DrivePlan", "RecordingPlan", "FleetPlan",
           "make_fleet", "write_fleet", "FLEET_EFFECTS", "FLEET_KT", "FIRST_DAY"]

#: the effects every simulated drive has (and the model a fleet is ingested with)
FLEET_EFFECTS = "inertia,viscous,coulomb,offset"
#: torque constant of every simulated drive [N·m/A] (``--kt`` of the ingest)
FLEET_KT = 0.1
#: the first recording day of a fleet (UTC)
FIRST_DAY = datetime.datetime(2026, 1, 5, 6, 0, tzinfo=datetime.UTC)


@dataclass(frozen=True)
class DriveType:
    """A kind of drive in the plant: nominal physics and how it is run."""

    name: str
    J: float
    B: float
    Tc: float
    #: top speed of its reversals [rad/s] and their acceleration [rad/s²]
    speed: float
    accel: float


#: the plant's drive types (a small servo, a larger one, a conveyor's)
TYPES: tuple[DriveType, ...] = (
    DriveType("servo-s", 2.0e-4, 1.0e-4, 0.020, 30.0, 400.0),
    DriveType("servo-m", 6.0e-4, 2.5e-4, 0.045, 25.0, 300.0),
    DriveType("conveyor", 1.5e-3, 6.0e-4, 0.090, 18.0, 150.0),
)

#: wear and fault classes, with the share of a fleet's drives in each: friction rising
#: over the recordings, a load (inertia) change, a new harmonic (unbalance or a bearing
#: order), a drive unlike its siblings from the start
WEAR_CLASSES: dict[str, float] = {"friction": 0.08, "load": 0.06, "harmonic": 0.06,
                                  "outlier": 0.04}

#: recording-to-recording scatter of a healthy drive (relative standard deviations):
#: friction with temperature and lubrication, the load offset with the process
SCATTER = {"inertia.J": 0.002, "viscous.B": 0.03, "coulomb.Tc": 0.02}
#: scatter of the load offset, as a share of the drive's Coulomb friction
OFFSET_SCATTER = 0.02


@dataclass(frozen=True)
class RecordingPlan:
    """One recording of one drive: when, which physics, which excitation."""

    drive: str
    type: str
    index: int
    start: float
    params: Mapping[str, float]
    effects: str
    speed: float
    accel: float
    hold: float
    prbs_amplitude: float
    seed: int
    #: the PRBS's mean speed [rad/s]: the drive travels (a conveyor, a spindle) while it
    #: reverses, so a once-per-revolution term sees whole revolutions
    travel: float = 0.0

    @property
    def file(self) -> str:
        return f"{self.type}/{self.drive}/{self.drive}-{self.index:02d}.log"

    def excitation(self) -> Excitation:
        return (reversals(self.speed, self.accel, self.hold)
                + prbs(self.prbs_amplitude, 0.04, order=7, offset=self.travel,
                       seed=self.seed))


@dataclass(frozen=True)
class DrivePlan:
    """A drive: its type, class (``healthy`` or a :data:`WEAR_CLASSES` key), what
    changes (``parameter`` or ``effect``) from which recording (``onset``), and its
    recordings."""

    name: str
    type: str
    cls: str
    base: Mapping[str, float]
    current_noise: float
    speed_noise: float
    recordings: tuple[RecordingPlan, ...]
    parameter: str | None = None
    effect: str | None = None
    onset: int | None = None
    detail: str = ""

    def truth(self) -> dict[str, Any]:
        return {"type": self.type, "class": self.cls, "parameter": self.parameter,
                "effect": self.effect, "onset": self.onset, "detail": self.detail,
                "base": dict(self.base), "current_noise": self.current_noise,
                "speed_noise": self.speed_noise,
                "recordings": [{"file": r.file, "start": r.start, "effects": r.effects,
                                "params": dict(r.params)} for r in self.recordings]}


@dataclass(frozen=True)
class FleetPlan:
    """A whole fleet (:func:`make_fleet`); :func:`write_fleet` writes it."""

    drives: tuple[DrivePlan, ...]
    duration: float
    seed: int
    dt: float = 1e-3
    extra: dict[str, Any] = field(default_factory=dict)

    def truth(self) -> dict[str, Any]:
        return {"seed": self.seed, "duration": self.duration, "dt": self.dt,
                "effects": FLEET_EFFECTS, "kt": FLEET_KT,
                "drives": {d.name: d.truth() for d in self.drives}}


def _classes(n: int, rng: np.random.Generator) -> list[str]:
    """Each drive's class: the shares of :data:`WEAR_CLASSES` (at least one each from
    10 drives on), the rest healthy, in a random order."""
    out: list[str] = []
    for cls, share in WEAR_CLASSES.items():
        out += [cls] * (max(1, round(share * n)) if n >= 10 else int(share * n))
    out += ["healthy"] * (n - len(out))
    rng.shuffle(out)
    return out


def make_fleet(drives: int = 50, recordings: int = 10, duration: float = 6.0,
               seed: int = 0, *, days: float = 7.0) -> FleetPlan:
    """Draw a fleet of ``drives`` drives with ``recordings`` recordings of ``duration``
    seconds each, one every ``days`` days (±1 day), from ``seed``."""
    if drives < 1 or recordings < 1:
        raise ConfigError(f"fleet: need at least one drive and one recording "
                          f"(drives {drives}, recordings {recordings})")
    if not (math.isfinite(duration) and duration >= 3.0):
        raise ConfigError(f"fleet: duration {duration!r} must be at least 3 s (2 s of "
                          f"calibration window and the fit)")
    rng = np.random.default_rng(seed)
    classes = _classes(drives, rng)
    width = max(3, len(str(drives)))
    plans = []
    for i, cls in enumerate(classes):
        t = TYPES[int(rng.integers(len(TYPES)))]
        name = f"d{i + 1:0{width}d}"
        base = {"inertia.J": t.J * math.exp(rng.normal(0, 0.10)),
                "viscous.B": t.B * math.exp(rng.normal(0, 0.15)),
                "coulomb.Tc": t.Tc * math.exp(rng.normal(0, 0.12)),
                "offset.T0": t.Tc * rng.uniform(-0.3, 0.3)}
        speed = t.speed * rng.uniform(0.8, 1.25)
        accel = t.accel * rng.uniform(0.8, 1.25)
        hold = rng.uniform(0.2, 0.6)
        amp = rng.uniform(2.0, 5.0)
        travel = float(rng.choice([-1.0, 1.0])) * rng.uniform(8.0, 12.0)
        cnoise, snoise = rng.uniform(0.003, 0.008), rng.uniform(0.01, 0.03)
        parameter = effect = onset = None
        detail = ""
        change: Callable[[int, dict[str, float]], str] | None = None
        if cls in ("friction", "load", "harmonic"):
            # the recording the change starts at
            onset = k_on = int(rng.integers(max(1, recordings // 3), max(2, recordings - 2)))
        if cls == "friction":
            parameter = str(rng.choice(["coulomb.Tc", "viscous.B"]))
            rate = rng.uniform(0.06, 0.12)
            detail = f"{parameter} rises {100 * rate:.1f} % of its value per recording"

            def change(k: int, p: dict[str, float], par: str = parameter,
                       r: float = rate, k0: int = k_on) -> str:
                p[par] *= 1.0 + r * max(0, k - k0 + 1)
                return FLEET_EFFECTS
        elif cls == "load":
            parameter = "inertia.J"
            factor = rng.uniform(1.3, 1.6)
            detail = f"the load changes: inertia x{factor:.2f}"

            def change(k: int, p: dict[str, float], f: float = factor,
                       k0: int = k_on) -> str:
                if k >= k0:
                    p["inertia.J"] *= f
                return FLEET_EFFECTS
        elif cls == "harmonic":
            effect = str(rng.choice(["unbalance", "cogging:3", "cogging:5", "cogging:7"]))
            amp_h = base["coulomb.Tc"] * rng.uniform(0.15, 0.35)
            phase = rng.uniform(0, 2 * math.pi)
            detail = (f"a new {effect} term of {amp_h:.3g} N·m "
                      + ("(once per revolution)" if effect == "unbalance" else
                         f"(order {effect.split(':')[1]}, a bearing)"))

            def change(k: int, p: dict[str, float], e: str = effect, a: float = amp_h,
                       ph: float = phase, k0: int = k_on) -> str:
                if k < k0:
                    return FLEET_EFFECTS
                p[f"{e}.sin"] = a * math.cos(ph)
                p[f"{e}.cos"] = a * math.sin(ph)
                return f"{FLEET_EFFECTS},{e}"
        elif cls == "outlier":
            parameter = str(rng.choice(["viscous.B", "coulomb.Tc", "inertia.J"]))
            factor = float(rng.choice([rng.uniform(3.0, 4.0), rng.uniform(0.22, 0.3)]))
            base[parameter] *= factor
            detail = f"{parameter} x{factor:.2f} of its siblings' from the start"
        t0 = FIRST_DAY.timestamp() + rng.uniform(0, days) * 86400.0
        recs = []
        for k in range(recordings):
            p = dict(base)
            for key, rel in SCATTER.items():
                p[key] *= math.exp(rng.normal(0, rel))
            p["offset.T0"] += rng.normal(0, OFFSET_SCATTER) * base["coulomb.Tc"]
            effects = change(k, p) if change is not None else FLEET_EFFECTS
            start = t0 + (k * days + rng.uniform(-1, 1) * (days > 1)) * 86400.0
            recs.append(RecordingPlan(
                drive=name, type=t.name, index=k + 1, start=round(start, 3), params=p,
                effects=effects,
                speed=speed * rng.uniform(0.9, 1.1), accel=accel, hold=hold,
                prbs_amplitude=amp, seed=int(rng.integers(2**31)), travel=travel))
        plans.append(DrivePlan(name=name, type=t.name, cls=cls, base=base,
                               current_noise=cnoise, speed_noise=snoise,
                               recordings=tuple(recs), parameter=parameter, effect=effect,
                               onset=None if onset is None else onset + 1, detail=detail))
    return FleetPlan(drives=tuple(plans), duration=float(duration), seed=seed)


def write_recording(path: str | os.PathLike[str], drive: DrivePlan, rec: RecordingPlan,
                    duration: float, dt: float = 1e-3, *,
                    profile: Excitation | None = None) -> int:
    """Simulate one recording and write it as a candump log (epoch times); returns the
    number of frames. ``profile``: another excitation than the recording's own (a
    preset of :func:`canrls.sim.excitation.excitation`, as a plant's recordings vary)."""
    sc = scenario("standard", effects=rec.effects, params=dict(rec.params), seed=rec.seed,
                  duration=duration, dt=dt,
                  excitation=rec.excitation() if profile is None else profile, kt=FLEET_KT,
                  current_noise=drive.current_noise, speed_noise=drive.speed_noise,
                  controller=_commissioned(drive))
    return write_log(path, Simulator(sc, t0=rec.start).frames())


def _commissioned(drive: DrivePlan) -> Controller:
    """The speed loop as commissioned, on the drive's first inertia (a load change later
    leaves it as it was)."""
    wb = 2.0 * math.pi * Controller.speed_bandwidth
    kp = drive.base["inertia.J"] * wb / FLEET_KT
    return Controller(kp_speed=kp, ki_speed=kp * wb / 4.0)


def write_fleet(plan: FleetPlan, out: str | os.PathLike[str], *,
                progress: Callable[[int, int], None] | None = None) -> Path:
    """Write every recording of ``plan`` under ``out`` with ``manifest.csv`` and
    ``truth.json``; returns the directory. ``progress(done, total)`` after each log."""
    root = Path(out)
    root.mkdir(parents=True, exist_ok=True)
    total = sum(len(d.recordings) for d in plan.drives)
    done = 0
    rows = []
    for d in plan.drives:
        (root / d.type / d.name).mkdir(parents=True, exist_ok=True)
        for r in d.recordings:
            write_recording(root / r.file, d, r, plan.duration, plan.dt)
            rows.append((r.file, d.name, d.type))
            done += 1
            if progress is not None:
                progress(done, total)
    with open(root / "manifest.csv", "w", newline="", encoding="utf-8") as f:
        w = csv.writer(f)
        w.writerow(["path", "drive", "type"])
        w.writerows(rows)
    (root / "truth.json").write_text(json.dumps(plan.truth(), indent=1) + "\n",
                                     encoding="utf-8")
    return root
