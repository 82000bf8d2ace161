"""``canrls tune`` on a saved model: the feedforward and the speed-loop gains it supports.

:func:`tune` takes a :class:`~canrls.processor.modelfile.SavedModel` and the user's requests (map
points, the share of sigma, a bandwidth or the symmetric optimum) and returns a
:class:`TuneResult` that renders to text and JSON and writes the files a drive and
``canrls sim --feedforward/--gains`` load (:func:`read_feedforward`, :func:`read_gains`).
docs/tune.md.
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from canrls.control.feedforward import Feedforward, check_points, feedforward
from canrls.control.gains import Loop, SpeedGains, for_bandwidth, symmetric_optimum
from canrls.control.tune_limits import DEFAULT_DELAY, DEFAULT_MARGIN, DEFAULT_POINTS, DEFAULT_SHARE
from canrls.core.checks import is_positive, is_real
from canrls.core.errors import ConfigError
from canrls.core.files import MAX_MODEL_BYTES, atomic_writer, check_writable, read_text
from canrls.estimation.model import Model
from canrls.processor.modelfile import SavedModel
from canrls.processor.period import control_period

__all__ = ["TuneRequest", "TuneResult", "tune", "read_feedforward", "read_gains", "compensation",
           "found_ripple",
           "FEEDFORWARD_FILE", "MAP_FILE", "GAINS_FILE"]

FEEDFORWARD_FILE = "feedforward.json"
MAP_FILE = "anticogging.csv"
GAINS_FILE = "gains.json"


@dataclass(frozen=True)
class TuneRequest:
    """What the user asks for (None: the default or what the model says)."""

    points: int = DEFAULT_POINTS
    share: float = DEFAULT_SHARE
    bandwidth: float | None = None  # Hz; None: the symmetric optimum
    symmetric_optimum: bool = False  # asked for: an error without the current loop's tau
    margin: float = DEFAULT_MARGIN
    delay: float = DEFAULT_DELAY  # control periods
    current_tau: float | None = None  # s; None: L/R of the electrical equation, else 0
    period: float | None = None  # s; None: the model's calibration.period
    rated_speed: float | None = None
    rated_torque: float | None = None


@dataclass(frozen=True)
class TuneResult:
    """The feedforward, the gains (None: ``no_gains`` says why) and their notes."""

    feedforward: Feedforward
    gains: SpeedGains | None
    no_gains: str
    notes: tuple[str, ...]
    points: int
    base: tuple[float, float] | None  # (torque, speed) of the per-unit gains
    lead: float  # s: read the map at theta + omega lead (the loop's delay)

    @property
    def position_unit(self) -> str:
        """rad, or m on a linear axis."""
        return "rad" if self.feedforward.model.axis == "rotary" else "m"

    def headline(self) -> str:
        """The answer, on one line."""
        ff, parts = self.feedforward, []
        used = ", ".join(t.effect for t in ff.used) or "nothing"
        r = ff.ripple
        if r is not None:
            parts.append(f"compensate {used}: torque ripple {r.describe(ff.unit)}")
        else:
            parts.append(f"compensate {used}")
        g = self.gains
        if g is not None:
            x = self.position_unit
            parts.append(f"speed PI kp {g.kp:.4g}, ki {g.ki:.4g} ({g.unit} per {x}/s, per "
                         f"{x}) for {g.bandwidth_hz:.3g} Hz, phase margin "
                         f"{g.phase_margin:.0f} deg")
        else:
            parts.append(f"no gains: {self.no_gains}")
        return "canrls tune: " + "; ".join(parts)

    def format(self) -> str:
        ff, out = self.feedforward, [self.headline()]
        for t in ff.terms:
            vals = ", ".join(f"{p} {v:.6g} ± {s:.2g}" for p, v, s in
                             zip(t.parameters, t.values, t.sigmas, strict=True))
            out.append(f"  {'used' if t.used else 'left out':9} {t.effect}: {vals}"
                       + ("" if t.used else f" ({t.reason})"))
        out.append(f"  terms whose sigma is above {ff.share:.0%} of their size are left out")
        if not ff.has_map:
            out.append(f"  no anticogging map: {ff.no_map_reason()}")
        else:
            out.append(f"  anticogging map: {self.points} points per "
                       + ("revolution" if ff.model.axis == "rotary" else "pitch"))
        for h in ff.harmonics():
            out.append(f"  harmonic {h.order}: {h.amplitude:.4g} {ff.unit} at phase "
                       f"{h.phase:+.4f} rad (sin {h.sin:.4g}, cos {h.cos:.4g})")
        g = self.gains
        if g is not None:
            lp = g.loop
            x = self.position_unit
            out.append(f"  speed loop ({g.method}): kp {g.kp:.6g} {g.unit}·s/{x}, ki "
                       f"{g.ki:.6g} {g.unit}/{x} (Tn {g.integral_time:.4g} s); crossover "
                       f"{g.crossover_hz:.3g} Hz, bandwidth {g.bandwidth_hz:.3g} Hz "
                       f"({g.bandwidth_range_hz[0]:.3g} to {g.bandwidth_range_hz[1]:.3g} "
                       f"Hz for J ± 2 sigma)")
            out.append(f"  assumed: inertia {lp.J:.6g} ± {lp.J_sigma:.2g}, period "
                       f"{lp.dt:g} s, delay {lp.Td:g} s, current loop {lp.Ti:g} s")
            if self.base is not None:
                kp, ki = g.per_unit(*self.base)
                out.append(f"  per unit (torque {self.base[0]:g}, speed {self.base[1]:g}): "
                           f"kp {kp:.6g}, ki {ki:.6g} 1/s")
        out.extend(f"  {n}" for n in self.notes)
        return "\n".join(out)

    def to_dict(self) -> dict[str, Any]:
        d: dict[str, Any] = {"feedforward": self.feedforward.to_dict(),
                             "gains": None if self.gains is None else self.gains.to_dict(),
                             "no_gains": self.no_gains or None, "notes": list(self.notes)}
        if self.gains is not None and self.base is not None:
            kp, ki = self.gains.per_unit(*self.base)
            d["gains"]["per_unit"] = {"torque": self.base[0], "speed": self.base[1],
                                      "kp": kp, "ki": ki}
        return d

    def files(self) -> dict[str, bytes]:
        """The files ``--out DIR`` holds, by name."""
        ff = self.feedforward
        out = {FEEDFORWARD_FILE: _json({**ff.to_dict(self.points), "lead": self.lead})}
        if ff.has_map:
            pos, tau = ff.position_map(self.points)
            rows = [f"position_{self.position_unit},torque_{ff.unit.replace('·', '')}"]
            rows += [f"{p!r},{t!r}" for p, t in zip(pos.tolist(), tau.tolist(), strict=True)]
            out[MAP_FILE] = ("\n".join(rows) + "\n").encode("utf-8")
        if self.gains is not None:
            out[GAINS_FILE] = _json(self.to_dict()["gains"])
        return out

    @staticmethod
    def earlier(directory: str | Path, written: Sequence[Path]) -> list[Path]:
        """Files of a tune in ``directory`` that this run did not write (``written``: what
        :meth:`write` returned): an earlier run's, kept, such as a ``gains.json`` left from
        a run with ``--bandwidth``."""
        d, names = Path(directory), {p.name for p in written}
        return [d / n for n in (FEEDFORWARD_FILE, MAP_FILE, GAINS_FILE)
                if n not in names and (d / n).is_file()]

    def write(self, directory: str | Path) -> list[Path]:
        """Write :meth:`files` into ``directory`` (each whole, never through a link)."""
        files = self.files()
        d = Path(directory)
        if not d.is_dir():
            raise ConfigError(f"--out {d}: not a directory")
        paths = [check_writable(d / name, f"--out {d / name}") for name in files]
        for p, data in zip(paths, files.values(), strict=True):
            with atomic_writer(p, f"--out {p}") as f:
                f.write(data)
        return paths


def _json(d: Any) -> bytes:
    return (json.dumps(d, indent=2, ensure_ascii=False, allow_nan=False) + "\n").encode()


def _param(saved: SavedModel, name: str) -> tuple[float, float, bool] | None:
    p = saved.parameters.get(name)
    if p is None:
        return None
    s = p.get("sigma")
    return (float(p["value"]), math.nan if s is None else float(s),
            p.get("identifiable") is not False)


def _current_tau(saved: SavedModel, req: TuneRequest) -> tuple[float, str]:
    """The current loop's time constant and where it comes from."""
    if req.current_tau is not None:
        if not (math.isfinite(req.current_tau) and req.current_tau >= 0):
            raise ConfigError(f"--current-tau {req.current_tau!r}: must be a number of "
                              f"seconds >= 0")
        return req.current_tau, "stated (--current-tau)"
    R, L = _param(saved, "electrical.R"), _param(saved, "electrical.L")
    if R and L and R[2] and L[2] and R[0] > 0 and L[0] > 0:
        # tau_e = L / R: the winding's time constant
        return L[0] / R[0], "L/R of the electrical equation"
    return math.nan, ""


def _period(saved: SavedModel, req: TuneRequest) -> float:
    """The control period: stated, else the one the model was fitted at
    (:func:`~canrls.processor.period.control_period`; never the default: a loop tuned
    for a period nobody said is no answer)."""
    measured = (saved.calibration or {}).get("period")
    if req.period is None and measured is None:
        named = f"the model file {saved.origin}" if saved.origin else "the model file"
        raise ConfigError(f"--period: {named} holds no control period (calibration.period); "
                          f"state it with --period SECONDS")
    dt = control_period(given=req.period, given_by="--period", measured=measured).value
    if not (math.isfinite(req.delay) and req.delay >= 0):
        raise ConfigError(f"--delay {req.delay!r}: must be a number of periods >= 0")
    return float(dt)


def _gains(saved: SavedModel, req: TuneRequest, dt: float, unit: str,
           notes: list[str]) -> tuple[SpeedGains | None, str]:
    J = _param(saved, "inertia.J")
    if J is None:
        return None, "the model has no inertia (add the effect inertia)"
    if not J[2]:
        return None, "inertia.J NOT IDENTIFIABLE"
    if not (J[0] > 0 and J[1] <= req.share * J[0]):
        return None, (f"inertia.J {J[0]:.3g} ± {J[1]:.2g}: sigma above {req.share:.0%} of "
                      f"its value" if J[0] > 0 else f"inertia.J {J[0]:.3g} is not positive")
    if req.bandwidth is not None and req.symmetric_optimum:
        raise ConfigError("--bandwidth, --symmetric-optimum: one or the other")
    Ti, where = _current_tau(saved, req)
    if math.isnan(Ti):
        if req.bandwidth is None:
            why = ("the symmetric optimum needs the current loop's time constant; the "
                   "model has no electrical equation to take it from: give --current-tau "
                   "SECONDS (or --bandwidth HZ)")
            if req.symmetric_optimum:
                raise ConfigError(f"--current-tau: {why}")
            return None, why
        Ti, where = 0.0, "none given, no electrical equation: taken as ideal"
    notes.append(f"current loop time constant {Ti:.4g} s: {where}")
    loop = Loop(J[0], J[1], dt, req.delay * dt, Ti)
    if req.bandwidth is None:
        return symmetric_optimum(loop, unit=unit), ""
    return for_bandwidth(loop, req.bandwidth, req.margin, unit=unit), ""


def tune(saved: SavedModel, req: TuneRequest, source: str = "model") -> TuneResult:
    """The feedforward and the gains a saved model supports."""
    check_points(req.points)
    model = saved.build_model()
    ff = feedforward(model, saved.parameters, share=req.share, source=source)
    notes: list[str] = []
    dt = _period(saved, req)
    gains, why = _gains(saved, req, dt, ff.unit, notes)
    base = None
    rated = req.rated_torque
    if rated is None:
        sig = saved.configuration.get("signals") or {}
        rated = sig.get("rated_current" if ff.unit == "A" else "rated_torque")
    if gains is not None:
        if req.rated_speed is not None and isinstance(rated, int | float):
            for key, v in (("--rated-speed", req.rated_speed), ("--rated-torque", rated)):
                if not is_positive(v):
                    raise ConfigError(f"{key} {v!r}: must be a positive number")
            base = (float(rated), float(req.rated_speed))
        else:
            notes.append("per unit: give --rated-speed (and --rated-torque where the model "
                         "file holds no rating)")
    return TuneResult(ff, gains, why, tuple(notes), req.points, base, req.delay * dt)


def compensation(model: Model, parameters: Mapping[str, Mapping[str, Any]],
                 share: float = DEFAULT_SHARE) -> tuple[str, dict[str, Any]] | None:
    """The line the diagnosis prints beside the effects found ("with this compensation,
    the ripple would fall from X to Y") and its JSON; None without a position term.
    A parameter the estimator left without a finite value counts as not identifiable."""
    clean = {}
    for name, p in parameters.items():
        ok = all(is_real(p.get(k)) for k in ("value", "sigma"))
        clean[name] = dict(p) if ok else {**p, "value": 0.0, "sigma": None,
                                          "identifiable": False}
    ff = feedforward(model, clean, share=share)
    r = ff.ripple
    if r is None:
        return None
    used = ", ".join(t.effect for t in ff.used if t.of_position) or "nothing"
    line = (f"with this compensation ({used}; canrls tune), the torque ripple would fall: "
            f"{r.describe(ff.unit)}")
    return line, {"effects": [t.effect for t in ff.used if t.of_position], "unit": ff.unit,
                  **r.to_dict()}


def found_ripple(model: Model, found: Mapping[str, Mapping[str, float]]
                 ) -> tuple[str, dict[str, Any]] | None:
    """The line for effects the diagnosis found but the model lacks (``found``: effect
    -> parameter -> value of its candidate fit, no sigma): the torque ripple of their
    position terms, and that adding them tells what compensation would leave."""
    names = [e for e in found if e.split(":", 1)[0] in ("unbalance", "cogging")]
    if not names:
        return None
    grown = model.with_effects(add=names)
    params = {p: {"value": v, "sigma": 0.0} for e in names for p, v in found[e].items()}
    params.update({p.name: {"value": 0.0, "sigma": 0.0} for p in grown.parameters
                   if p.name not in params})
    r = feedforward(grown, params, share=1.0).ripple
    if r is None:
        return None
    unit = "N·m" if model.axis == "rotary" else "N"
    unit = unit if model.torque_known else "A"
    add = " ".join(f"--add {e}" for e in names)
    line = (f"{', '.join(names)} (found): a torque ripple of {r.before:.3g} {unit} RMS; "
            f"add it ({add}) to learn what compensation (canrls tune) would leave")
    return line, {"effects": names, "unit": unit, "before": r.before, "before_sigma": None,
                  "after": None, "after_sigma": None, "reduction": None}


def _read(path: str | Path, fmt: str, what: str) -> dict[str, Any]:
    p = Path(path)
    text = read_text(p, f"{what} {p}", limit=MAX_MODEL_BYTES)
    try:
        d = json.loads(text, parse_constant=lambda c: math.nan)
    except (json.JSONDecodeError, RecursionError, ValueError) as e:
        raise ConfigError(f"{what} {p}: invalid JSON: {e}") from e
    if not isinstance(d, dict) or d.get("format") != fmt:
        raise ConfigError(f"{what} {p}: not a {fmt} file (no \"format\": \"{fmt}\"; "
                          f"written by canrls tune --out)")
    if d.get("version") != 1:
        raise ConfigError(f"{what} {p}: version {d.get('version')!r} (this canrls reads 1)")
    return d


def _number(v: Any, where: str, *, positive: bool = False) -> float:
    """``v``, a finite (positive) number, or an error naming ``where``."""
    if not (is_positive(v) if positive else is_real(v)):
        raise ConfigError(f"{where} = {v!r}: must be a finite"
                          f"{' positive' if positive else ''} number")
    return float(v)


def _finite(d: Any, key: str, where: str, *, positive: bool = False) -> float:
    return _number(d.get(key) if isinstance(d, dict) else None, f"{where}.{key}",
                   positive=positive)


def read_feedforward(path: str | Path) -> dict[str, Any]:
    """A feedforward file, checked: ``unit``, ``lead``, ``map`` (``period``, ``torque``)
    and the ``speed`` parameters and speeds as finite numbers; user terms of the speed refused
    (a drive or the simulator evaluates no expression)."""
    what = f"--feedforward {path}"
    d = _read(path, "canrls-feedforward", "--feedforward")
    if d.get("unit") not in ("N·m", "N", "A"):
        raise ConfigError(f"{what}: unit = {d.get('unit')!r}: must be N·m, N or A")
    lead = _finite(d, "lead", what)
    if lead < 0:
        raise ConfigError(f"{what}: lead = {lead!r}: must be >= 0 s")
    sp = d.get("speed")
    if not isinstance(sp, dict) or not isinstance(sp.get("parameters"), dict):
        raise ConfigError(f"{what}: speed.parameters: must be a table")
    for key in ("coulomb_band", "stribeck_speed"):
        _finite(sp, key, f"{what}: speed", positive=True)
    for k in sp["parameters"]:
        _finite(sp["parameters"], k, f"{what}: speed.parameters")
    if sp.get("user"):
        raise ConfigError(f"{what}: speed.user = {sp['user']!r}: user terms of the speed "
                          f"cannot be loaded into a table or the simulator")
    m = d.get("map")
    if m is not None:
        _finite(m, "period", f"{what}: map", positive=True)
        tau = m.get("torque") if isinstance(m, dict) else None
        if not isinstance(tau, list):
            raise ConfigError(f"{what}: map.torque: must be a list of numbers")
        check_points(len(tau), f"{what}: map.torque has")
        for k, v in enumerate(tau):
            _number(v, f"{what}: map.torque[{k}]")
    return d


def read_gains(path: str | Path) -> dict[str, Any]:
    """A gains file, checked: ``kp``, ``ki``, ``inertia`` positive, ``unit``."""
    what = f"--gains {path}"
    d = _read(path, "canrls-gains", "--gains")
    for key in ("kp", "ki", "inertia"):
        _finite(d, key, what, positive=True)
    if d.get("unit") not in ("N·m", "N", "A"):
        raise ConfigError(f"{what}: unit = {d.get('unit')!r}: must be N·m, N or A")
    return d
