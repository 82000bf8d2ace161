"""A fleet's parameter history simulated directly, without logs: per recording the
estimates a fit would give, with their sigma and the bias of the recording's
excitation and length, for the statistical tests of ``canrls.fleet.detect`` (and the
plant-size benchmark, which needs 52,000 recordings in seconds).

What is simulated (:func:`simulated_fleet`), the model ``inertia,viscous,coulomb,offset``:

* two drive types (20 drives each by default), every drive within ±10 % of its type
  (J, B, Tc; uniform), a load offset of ±30 % of Tc;
* weekly recordings (±1 day), each with its own excitation (standard, steps, prbs,
  chirp) and length (10, 20, 40 s);
* each estimate = truth × exp(bias + sigma·N(0, 1)): sigma (relative, as the estimator
  reports it) depends on the excitation and shrinks as 1/sqrt(length) (a PRBS alone
  reports a far larger sigma of the friction than its actual error, :data:`ERROR`); the bias
  (errors-in-variables, :data:`BIAS`) depends on the excitation, grows as the length
  shrinks and with the square of the drive's own speed noise (a drive's bias from a
  ninth to twice the typical), and is NOT in the reported sigma;
* week-to-week jitter ±``jitter`` (uniform, independent each week, as temperature
  moves friction): Coulomb ±``jitter``, viscous ±``jitter / 2`` (the issue's ±2 % /
  ±1 %; ``gaussian=True``: normal with those standard deviations, a harder fleet), each
  drive's from half to 1.5 times that (its place in the plant), the load offset 2 % of
  Tc (a standard deviation); inertia none;
* the residual RMS: the drive's noise (2 % of its Tc ±25 %) by the excitation's factor,
  ±5 % a recording; a new harmonic of amplitude A adds A²/2 to its square;
* a candidate ranking on every recording (as ``--rank all``): small shares of effects
  the model lacks before, the new harmonic's share (1 - rms_before² / rms_after²) after;
* five changing drives: Coulomb +3 % a week from the second or third recording, inertia
  ×1.25 (a load), a small unbalance (15 % of Tc), cogging of order 5 (10 % of Tc), and
  viscous ×1.4, each step from a recording in the middle (4th to 7th).

Every number is drawn from ``numpy.random.default_rng(seed)``.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np

from canrls.fleet.records import CandidateValue, ParameterValue, Recording

__all__ = ["simulated_fleet", "SimulatedFleet", "CHANGES", "EXCITATIONS", "LENGTHS",
           "bookkeeping_fleet"]

EXCITATIONS = ("standard", "steps", "prbs", "chirp")
LENGTHS = (10.0, 20.0, 40.0)
MODEL_KEY = "f" * 64
MODEL = "inertia,viscous,coulomb,offset kt=0.1"
#: the types: (name, J [kg·m²], B [N·m·s/rad], Tc [N·m])
TYPES = (("servo-m", 6.0e-4, 2.5e-4, 0.045), ("conveyor", 1.5e-3, 6.0e-4, 0.090))
#: relative sigma of a 20 s recording, per excitation (standard, steps, prbs, chirp), and
#: the relative bias at 20 s (twice at 10 s, half at 40 s): as the fits of the simulated
#: drive give them (a servo-m drive, docs/fleet.md), a PRBS alone pinning the friction
#: poorly
SIGMA = {"inertia.J": (0.0002, 0.0004, 0.0025, 0.0004),
         "viscous.B": (0.0005, 0.002, 0.5, 0.01),
         "coulomb.Tc": (0.0002, 0.0002, 0.15, 0.0016)}
#: the estimate's actual error where it is much smaller than the sigma reported: a PRBS
#: alone reports a friction sigma of 15-50 % (its prior, barely moved) while its
#: estimate lands within a few per cent (the fits: 933 % reported, 13 % off at 10 s;
#: 465 % reported, 1.2 % off at 20 s)
ERROR = {"viscous.B": (None, None, 0.03, None), "coulomb.Tc": (None, None, 0.005, None)}
BIAS = {"inertia.J": (0.0, -0.0005, -0.001, 0.0),
        "viscous.B": (0.0, 0.001, 0.01, -0.01),
        "coulomb.Tc": (0.0, 0.0, -0.001, 0.001)}
#: the residual RMS per excitation, relative to a drive's noise
RESIDUAL_FACTOR = (1.0, 1.15, 0.9, 1.05)
#: what changes on the changing drives (the truth's ``parameter`` or ``effect``)
CHANGES = ("coulomb.Tc", "inertia.J", "unbalance", "cogging:5", "viscous.B")
DAY = 86400.0
T0 = 1.7675e9  # 2026-01-05


@dataclass(frozen=True)
class SimulatedFleet:
    """The recordings and the truth: per drive ``None`` (healthy) or what changes, and
    from which recording (0-based)."""

    recordings: tuple[Recording, ...]
    changing: dict[str, tuple[str, int]]
    healthy: tuple[str, ...]


def simulated_fleet(seed: int, jitter: float, drives: int = 40, recordings: int = 10,
                    start_id: int = 1, gaussian: bool = False) -> SimulatedFleet:
    """A fleet of ``drives`` drives (five of them changing) with ``recordings`` weekly
    recordings each (module docstring); ``gaussian``: the jitter a normal of standard
    deviation ``jitter`` instead of uniform within ±``jitter``."""

    def jitter_of(rng: np.random.Generator, j: float) -> float:
        return float(rng.normal(0, j) if gaussian else rng.uniform(-j, j))

    rng = np.random.default_rng(seed)
    order = rng.permutation(drives)
    recs: list[Recording] = []
    changing: dict[str, tuple[str, int]] = {}
    healthy: list[str] = []
    rid = start_id
    for i in range(drives):
        name = f"d{i + 1:04d}"
        ty, J0, B0, Tc0 = TYPES[i % len(TYPES)]
        base = {"inertia.J": J0 * (1 + rng.uniform(-0.1, 0.1)),
                "viscous.B": B0 * (1 + rng.uniform(-0.1, 0.1)),
                "coulomb.Tc": Tc0 * (1 + rng.uniform(-0.1, 0.1))}
        offset = base["coulomb.Tc"] * rng.uniform(-0.3, 0.3)
        noise = 0.02 * base["coulomb.Tc"] * rng.uniform(0.8, 1.25)
        # the errors-in-variables bias grows with the square of the drive's speed noise
        # (its sensor and installation): from a ninth to twice the typical
        bias_scale = rng.uniform(1 / 3, math.sqrt(2)) ** 2
        # how much temperature moves this drive's friction (its place in the plant)
        exposure = rng.uniform(0.5, 1.5)
        k = int(np.where(order == i)[0][0])
        change = CHANGES[k] if k < len(CHANGES) else None
        if change is None:
            onset = -1
            healthy.append(name)
        else:
            lo, hi = ((1, 3) if change == "coulomb.Tc" else
                      (recordings // 3, max(recordings // 3 + 1, recordings - 3)))
            onset = int(rng.integers(lo, hi))
            changing[name] = (change, onset)
        t_first = T0 + rng.uniform(0, 7) * DAY
        for w in range(recordings):
            e = int(rng.integers(len(EXCITATIONS)))
            length = float(LENGTHS[int(rng.integers(len(LENGTHS)))])
            truth = dict(base)
            truth["coulomb.Tc"] *= 1.0 + jitter_of(rng, exposure * jitter)
            truth["viscous.B"] *= 1.0 + jitter_of(rng, exposure * jitter / 2)
            t0 = offset + rng.normal(0, 0.02) * base["coulomb.Tc"]
            harmonic = 0.0
            if change is not None and w >= onset:
                if change == "coulomb.Tc":
                    truth["coulomb.Tc"] *= 1.0 + 0.03 * (w - onset + 1)
                elif change == "inertia.J":
                    truth["inertia.J"] *= 1.25
                elif change == "viscous.B":
                    truth["viscous.B"] *= 1.4
                else:
                    harmonic = (0.15 if change == "unbalance" else 0.10) * base["coulomb.Tc"]
            params = []
            for p, x in truth.items():
                s = SIGMA[p][e] * math.sqrt(20.0 / length)
                bias = BIAS[p][e] * 20.0 / length * bias_scale
                err = ERROR.get(p, (None,) * 4)[e]
                err = s if err is None else err * math.sqrt(20.0 / length)
                v = x * math.exp(bias + err * rng.normal())
                params.append(ParameterValue(p, v, s * v, _unit(p)))
            s_off = 0.01 * base["coulomb.Tc"] * math.sqrt(20.0 / length)
            params.append(ParameterValue("offset.T0", t0 + s_off * rng.normal(), s_off, "N·m"))
            r_healthy = noise * RESIDUAL_FACTOR[e] * math.exp(rng.normal(0, 0.05))
            # rms^2 = rms_healthy^2 + A^2 / 2
            rms = math.sqrt(r_healthy ** 2 + harmonic ** 2 / 2.0)
            cands = _ranking(rng, change if harmonic > 0 else None,
                             1.0 - (r_healthy / rms) ** 2)
            t = t_first + (w * 7 + rng.uniform(-1, 1)) * DAY
            recs.append(Recording(
                drive=name, drive_type=ty, content_hash=f"{seed:08x}{rid:056x}",
                model_key=MODEL_KEY, model=MODEL, path=f"{ty}/{name}/{name}-{w + 1:02d}.log",
                t_start=t, t_end=t + length, samples=int(length * 1000),
                frames=int(length * 3000), residual_rms=rms, fit_percent=95.0, unit="N·m",
                verdicts={"excitation": EXCITATIONS[e]},
                parameters=tuple(sorted(params, key=lambda p: p.name)),
                candidates=cands, id=rid))
            rid += 1
    return SimulatedFleet(tuple(recs), changing, tuple(healthy))


def bookkeeping_fleet(seed: int = 102) -> tuple[list[Recording], dict[str, str]]:
    """A fleet (:func:`simulated_fleet`, jitter 2 %) with the bookkeeping's cases on five
    healthy drives: one recording, recordings under two models, two at the same start
    time, recordings stored out of time order, and a drive renamed half-way (its later
    recordings under ``NAME-new``). Returns the recordings and, per drive, a phrase
    its note says."""
    f = simulated_fleet(seed, 0.02)
    mine = {d: sorted((r for r in f.recordings if r.drive == d), key=lambda r: r.t_start)
            for d in f.healthy[:5]}
    one, models, same, order, renamed = mine
    rest = [r for r in f.recordings if r.drive not in mine]
    rest.append(mine[one][0])
    rest += mine[models][:5] + [dataclasses.replace(
        r, model_key="e" * 64, model="inertia,viscous,coulomb") for r in mine[models][5:]]
    rest += mine[same] + [dataclasses.replace(mine[same][4], id=10 ** 7,
                                              content_hash="c" * 64)]
    rest += [dataclasses.replace(r, id=10 ** 6 - k) for k, r in enumerate(mine[order])]
    rest += mine[renamed][:5] + [dataclasses.replace(r, drive=renamed + "-new")
                                 for r in mine[renamed][5:]]
    return rest, {one: "1 recording of this model", models: "under 2 models",
                  same: "share a start time", order: "out of time order",
                  renamed: "no recording since", renamed + "-new": "recorded since"}


def _unit(p: str) -> str:
    return {"inertia.J": "kg·m²", "viscous.B": "N·m·s/rad"}.get(p, "N·m")


def _ranking(rng: np.random.Generator, new: str | None, share: float
             ) -> tuple[CandidateValue, ...]:
    """A ranking of the effects the model lacks: small shares, and ``new``'s ``share``."""
    shares = {"stribeck": rng.uniform(0.02, 0.10), "unbalance": rng.uniform(0.0, 0.05),
              "cogging:3": rng.uniform(0.0, 0.05), "cogging:5": rng.uniform(0.0, 0.05),
              "cogging:7": rng.uniform(0.0, 0.05)}
    if new is not None:
        shares[new] = share
    ranked = sorted(shares.items(), key=lambda kv: -kv[1])
    return tuple(CandidateValue(rank=i + 1, effect=e, explained=float(x),
                                delta_bic=-1000.0 * x, rms_after=math.nan,
                                identifiable=True, suggested=x > 0.2)
                 for i, (e, x) in enumerate(ranked))
