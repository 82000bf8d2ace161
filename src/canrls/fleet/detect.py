r"""Change, drift, new-effect and outlier detection on a fleet's history, respecting sigma.

Each series (per model, parameter and drive) is weighed by its sigma and by the
between-recording scatter the fleet shows and sigma does not (:math:`\tau`); a drive is
alerted when its largest change or drift is unlikely for a healthy drive (Bonferroni
over its splits, onsets and series), and compared with its siblings. The statistics,
with their formulas and figures: docs/fleet.md, "Finding what changes".
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt

from canrls.core.checks import is_positive
from canrls.fleet.records import SOURCE_LIVE, Recording

__all__ = ["ALPHA", "OUTLIER_Z", "MIN_RECORDINGS", "MIN_SIBLINGS", "RESIDUAL", "Alert",
           "Evidence", "DriveAssessment", "FleetAssessment", "Baseline", "assess",
           "estimate_tau", "to_rank", "POSITIVE_EFFECTS"]

F64 = npt.NDArray[np.float64]

#: family-wise false-alert probability per healthy drive and history
ALPHA = 1e-3
#: robust z beyond which a drive is an outlier among its siblings
OUTLIER_Z = 4.5
#: fewest recordings of a series tested for a change
MIN_RECORDINGS = 4
#: fewest drives of a type and model compared with each other
MIN_SIBLINGS = 5
#: fewest successive pairs of a type that estimate its own scatter (else the fleet's)
MIN_PAIRS = 40
#: fewest pairs of one drive whose own scatter can raise its offsets' tau
MIN_OWN_PAIRS = 5
#: the series name of the residual RMS
RESIDUAL = "residual_rms"
#: least rise of the residual RMS that is a new effect (its scatter from one excitation
#: to the next has heavier tails than a normal's: a rise must also matter)
MIN_RESIDUAL_RISE = 0.5
#: least share of the residual after a change that an effect must explain to be named
#: the new effect (and rise by half as much)
NEW_EFFECT_SHARE = 0.2
#: effects whose parameters are positive by physics: compared in logs (relative scale)
POSITIVE_EFFECTS = ("inertia", "viscous", "coulomb", "stribeck", "electrical")
#: the quantile of the standardised differences that tau matches to a chi-square's:
#: above the median, so that the drives that scatter more than the typical one (an
#: offset that follows a drive's own friction, a noisier installation) set tau, not the
#: quietest; below the tail, which the few changing drives hold
TAU_QUANTILE = 0.8
#: that quantile of a chi-square with one degree of freedom
_CHI2_Q = 1.6423744151498062


def _phi_tail(z: float) -> float:
    """2 Phi(-|z|)."""
    return math.erfc(abs(z) / math.sqrt(2.0))


@dataclass(frozen=True)
class Evidence:
    """One recording behind an alert: its value and sigma (physical units)."""

    recording_id: int | None
    path: str
    t: float
    value: float
    sigma: float

    def to_dict(self) -> dict[str, Any]:
        return {"recording_id": self.recording_id, "path": self.path, "t": self.t,
                "value": self.value, "sigma": self.sigma}


@dataclass(frozen=True)
class Alert:
    """Something about a drive that needs a look.

    ``kind``: ``change`` (a step), ``drift`` (a slope since a recording), ``new effect``
    (the residual changed and the ranking names the effect that appeared), ``residual``
    (the residual changed, no ranking to name why), ``outlier`` (unlike its siblings).
    ``at``: the index (0-based, in time order) of the first recording after the change
    or of the drift's onset. ``before``/``after``: the levels (physical units; for a
    drift, at the onset and at the last recording). ``tau``: the between-recording
    scatter used (relative for a positive parameter, else in its unit).
    """

    drive: str
    kind: str
    series: str
    z: float
    p: float
    message: str
    at: int | None = None
    before: float = math.nan
    after: float = math.nan
    tau: float = math.nan
    effect: str | None = None
    unit: str = ""
    evidence: tuple[Evidence, ...] = ()

    @property
    def severity(self) -> float:
        """-log10 p (large: sure); the drives are ranked by it."""
        return -math.log10(max(self.p, 1e-300))

    def to_dict(self) -> dict[str, Any]:
        return {"drive": self.drive, "kind": self.kind, "series": self.series,
                "effect": self.effect, "z": self.z, "p": self.p, "severity": self.severity,
                "message": self.message, "at": self.at, "before": self.before,
                "after": self.after, "tau": self.tau, "unit": self.unit,
                "evidence": [e.to_dict() for e in self.evidence]}


@dataclass(frozen=True)
class Series:
    """One drive's values of one parameter (or the residual), in time order."""

    name: str
    t: F64
    y: F64
    s: F64
    value: F64
    sigma: F64
    ids: tuple[int | None, ...]
    paths: tuple[str, ...]
    log: bool
    unit: str = ""


@dataclass(frozen=True)
class Baseline:
    """The between-recording scatter of a series over the fleet (one model)."""

    series: str
    tau: float
    log: bool
    pairs: int

    def to_dict(self) -> dict[str, Any]:
        return {"series": self.series, "tau": self.tau, "relative": self.log,
                "pairs": self.pairs}


@dataclass(frozen=True)
class DriveAssessment:
    """A drive, its recordings and its alerts (most severe first)."""

    drive: str
    drive_type: str
    model_key: str
    model: str
    recordings: int
    errors: int
    alerts: tuple[Alert, ...]
    series: Mapping[str, Series] = field(default_factory=dict)
    #: the largest |z| of any test, alerted or not (ranks the quiet drives)
    max_z: float = 0.0

    @property
    def headline(self) -> Alert | None:
        return self.alerts[0] if self.alerts else None

    @property
    def score(self) -> float:
        return self.alerts[0].severity if self.alerts else 0.0

    def to_dict(self) -> dict[str, Any]:
        return {"drive": self.drive, "type": self.drive_type, "model_key": self.model_key,
                "model": self.model, "recordings": self.recordings, "errors": self.errors,
                "score": self.score, "max_z": self.max_z,
                "alerts": [a.to_dict() for a in self.alerts]}


@dataclass(frozen=True)
class FleetAssessment:
    """Every drive (ranked: what needs a look first), the scatter used per model, and the
    fleet's spread per parameter (each drive's level)."""

    drives: tuple[DriveAssessment, ...]
    baselines: Mapping[str, Mapping[str, Baseline]]
    spread: Mapping[str, Mapping[str, Mapping[str, tuple[str, float]]]]
    alpha: float = ALPHA

    @property
    def alerts(self) -> list[Alert]:
        return [a for d in self.drives for a in d.alerts]

    def drive(self, name: str) -> DriveAssessment:
        for d in self.drives:
            if d.drive == name:
                return d
        raise KeyError(name)

    def to_dict(self) -> dict[str, Any]:
        return {"alpha": self.alpha,
                "drives": [d.to_dict() for d in self.drives],
                "alerts": len(self.alerts),
                "baselines": {k: {s: b.to_dict() for s, b in v.items()}
                              for k, v in self.baselines.items()},
                "spread": {k: {p: {d: {"type": t, "level": v} for d, (t, v) in dv.items()}
                               for p, dv in v.items()} for k, v in self.spread.items()}}


# ---------------------------------------------------------------------------- series
def _positive(name: str) -> bool:
    return name.split(".", 1)[0].split(":", 1)[0] in POSITIVE_EFFECTS


def _collapse_live(recs: Sequence[Recording]) -> list[Recording]:
    """A daemon's snapshots of one session (cumulative estimates) count once: its last."""
    last: dict[tuple[str, str], Recording] = {}
    out = []
    for r in recs:
        if r.source == SOURCE_LIVE and r.session:
            key = (r.drive, r.session)
            if key not in last or (r.t_end, r.id or 0) >= (last[key].t_end, last[key].id or 0):
                last[key] = r
        else:
            out.append(r)
    return out + list(last.values())


def _time(r: Recording) -> float:
    return r.t_start if math.isfinite(r.t_start) else float(r.id or 0)


def _series(recs: Sequence[Recording], name: str, log: bool) -> Series | None:
    t, y, s, v, sg, ids, paths = [], [], [], [], [], [], []
    unit = ""
    for r in recs:
        if name == RESIDUAL:
            x, sig = r.residual_rms, 0.0
            if not is_positive(x):
                continue
            yy, ss = math.log(x), 0.0
            unit = r.unit
        else:
            p = r.parameter(name)
            if p is None or not p.identifiable or not (math.isfinite(p.value)
                                                       and math.isfinite(p.sigma)):
                continue
            x, sig = p.value, p.sigma
            unit = p.unit
            if log:
                if x <= 0:
                    continue
                yy, ss = math.log(x), sig / x
            else:
                yy, ss = x, sig
        t.append(_time(r))
        y.append(yy)
        s.append(ss)
        v.append(x)
        sg.append(sig)
        ids.append(r.id)
        paths.append(r.path)
    if not t:
        return None
    return Series(name, np.array(t), np.array(y), np.array(s), np.array(v), np.array(sg),
                  tuple(ids), tuple(paths), log or name == RESIDUAL, unit)


def estimate_tau(pairs: Sequence[tuple[float, float]]) -> float:
    r"""The between-recording scatter :math:`\tau` from ``(d_k^2, s_k^2 + s_{k+1}^2)``
    of successive recordings: the quantile :data:`TAU_QUANTILE` of the standardised
    squared differences matched to a chi-square's (docs/fleet.md)."""
    if not pairs:
        return 0.0
    d2 = np.array([p[0] for p in pairs])
    v = np.array([p[1] for p in pairs])

    def quantile(tau: float) -> float:
        with np.errstate(divide="ignore", invalid="ignore"):
            q = np.where(v + 2 * tau * tau > 0, d2 / (v + 2 * tau * tau), np.inf)
        return float(np.quantile(q, TAU_QUANTILE, method="inverted_cdf"))

    if quantile(0.0) <= _CHI2_Q:
        return 0.0
    lo, hi = 0.0, max(1e-12, math.sqrt(float(np.max(d2))))
    while quantile(hi) > _CHI2_Q:
        hi *= 2.0
    for _ in range(80):
        mid = 0.5 * (lo + hi)
        if quantile(mid) > _CHI2_Q:
            lo = mid
        else:
            hi = mid
    return hi


# ---------------------------------------------------------------------------- tests
@dataclass(frozen=True)
class _Found:
    kind: str
    z: float
    at: int
    before: float
    after: float


def _weighted_mean(y: F64, w: F64) -> tuple[float, float]:
    W = float(w.sum())
    return float((w * y).sum() / W), W


def _tests(se: Series, tau: float, rises: bool = False) -> tuple[_Found | None, int]:
    """The largest change or drift of a series (``rises``: the largest rise), and how
    many splits and onsets were tried."""
    n = len(se.y)
    if n < MIN_RECORDINGS:
        return None, 0
    v = se.s ** 2 + tau ** 2
    if not np.all(v > 0):  # no scatter at all (a series with neither sigma nor tau)
        return None, 0
    w = 1.0 / v
    best: _Found | None = None
    tried = 0
    for m in range(2, n - 1):  # change: >= 2 before, >= 2 after
        mb, Wb = _weighted_mean(se.y[:m], w[:m])
        ma, Wa = _weighted_mean(se.y[m:], w[m:])
        z = (ma - mb) / math.sqrt(1.0 / Wb + 1.0 / Wa)
        tried += 1
        if best is None or _larger(z, best.z, rises):
            best = _Found("change", z, m, mb, ma)
    days = (se.t - se.t[0]) / 86400.0
    for c in range(0, n - 2):  # drift: flat to recording c, then a slope (>= 3 on it)
        g = np.maximum(0.0, days - days[c])
        W = float(w.sum())
        gbar = float((w * g).sum() / W)
        sgg = float((w * (g - gbar) ** 2).sum())
        if sgg <= 0:
            continue
        ybar = float((w * se.y).sum() / W)
        b = float((w * (g - gbar) * (se.y - ybar)).sum()) / sgg
        z = b * math.sqrt(sgg)
        tried += 1
        if best is None or _larger(z, best.z, rises):
            a = ybar - b * gbar
            best = _Found("drift", z, c, a, a + b * float(g[-1]))
    return best, tried


def _larger(z: float, than: float, rises: bool) -> bool:
    return z > than if rises else abs(z) > abs(than)


def _phys(se: Series, y: float) -> float:
    return math.exp(y) if se.log else y


def _evidence(se: Series, at: int | None, k: int = 12) -> tuple[Evidence, ...]:
    idx = list(range(len(se.y)))
    if at is not None and len(idx) > k:
        lo = max(0, min(at - k // 2, len(idx) - k))
        idx = idx[lo:lo + k]
    return tuple(Evidence(se.ids[i], se.paths[i], float(se.t[i]), float(se.value[i]),
                          float(se.sigma[i])) for i in idx)


def _fmt(x: float, unit: str) -> str:
    return f"{x:.4g} {unit}".rstrip()


def _new_effect(recs: Sequence[Recording], at: int) -> tuple[str | None, str]:
    """The effect whose share of the residual rose most from before ``at`` to after,
    from the stored candidate rankings (None when there is none after)."""
    before = [r for r in recs[:at] if r.candidates is not None]
    after = [r for r in recs[at:] if r.candidates is not None]
    if not after:
        return None, ""

    def share(rs: Sequence[Recording], identifiable: bool) -> dict[str, float]:
        out: dict[str, float] = {}
        for r in rs:
            for c in r.candidates or ():
                if (c.identifiable or not identifiable) and math.isfinite(c.explained):
                    out[c.effect] = out.get(c.effect, 0.0) + c.explained / len(rs)
        return out

    sb, sa = share(before, False), share(after, True)
    caveat = ""
    if not sa or max(sa.values()) < NEW_EFFECT_SHARE:
        # an effect these logs cannot identify (too little travel for a once-per-
        # revolution term) that explains most of the residual is still named, with why
        loose = share(after, False)
        if loose and max(loose.values()) >= 2 * NEW_EFFECT_SHARE:
            sa = loose
            caveat = " (not identifiable in these logs alone: see canrls diagnose)"
    if not sa:
        return None, ""
    eff = max(sa, key=lambda e: sa[e] - sb.get(e, 0.0))
    how = (f"{eff} explains {100 * sa[eff]:.0f} % of the residual after"
           + (f", {100 * sb.get(eff, 0.0):.0f} % before" if before else
              " (no ranking before)") + caveat)
    if sa[eff] < NEW_EFFECT_SHARE or sa[eff] - sb.get(eff, 0.0) < NEW_EFFECT_SHARE / 2:
        return None, f"the ranking names no effect that appeared (best: {how})"
    return eff, how


def _drive_alerts(drive: str, recs: Sequence[Recording], series: Mapping[str, Series],
                  taus: Mapping[str, float], alpha: float) -> tuple[list[Alert], float]:
    found: dict[str, tuple[_Found, int]] = {}
    total = 0
    for name, se in series.items():
        f, tried = _tests(se, taus.get(name, 0.0), rises=name == RESIDUAL)
        total += tried
        if f is not None and name == RESIDUAL and (
                f.z < 0 or f.after - f.before < math.log1p(MIN_RESIDUAL_RISE)):
            f = dataclasses.replace(f, z=min(f.z, 0.0))  # not a rise that matters
        if f is not None:
            found[name] = (f, tried)
    alerts = []
    max_z = max((abs(f.z) for f, _ in found.values()), default=0.0)
    for name, (f, _) in found.items():
        p = min(1.0, _phi_tail(f.z) * total)
        if p >= alpha:
            continue
        se = series[name]
        b, a = _phys(se, f.before), _phys(se, f.after)
        rel = f" ({100 * (a / b - 1):+.0f} %)" if se.log and b > 0 else ""
        when = f"recording {f.at + 1} of {len(se.y)}"
        if f.kind == "change":
            msg = (f"{name} changed at {when}: {_fmt(b, se.unit)} -> {_fmt(a, se.unit)}"
                   f"{rel}, z = {f.z:.1f}")
        else:
            msg = (f"{name} drifts since {when}: {_fmt(b, se.unit)} -> {_fmt(a, se.unit)}"
                   f"{rel} at the last, z = {f.z:.1f}")
        kind, effect = f.kind, None
        if name == RESIDUAL:
            effect, how = _new_effect(recs, f.at)
            if effect is not None:
                kind = "new effect"
                msg = f"new effect {effect}: the residual rose at {when}{rel}; {how}"
            elif how:
                kind = "residual"
                msg += f"; {how}"
            else:
                kind = "residual"
                msg += ("; a missing effect? rank the candidates (canrls fleet ingest "
                        "--rank auto) to name it")
        alerts.append(Alert(drive=drive, kind=kind, series=name, z=f.z, p=p, message=msg,
                            at=f.at, before=b, after=a, tau=taus.get(name, 0.0),
                            effect=effect, unit=se.unit, evidence=_evidence(se, f.at)))
    return alerts, max_z


def _ordered(alerts: Iterable[Alert]) -> tuple[Alert, ...]:
    """Most severe first; a new effect before the parameter changes it may cause."""
    return tuple(sorted(alerts, key=lambda a: (a.kind != "new effect", -a.severity)))


def _level(se: Series, tau: float, upto: int | None) -> tuple[float, float]:
    y, s = (se.y, se.s) if upto is None else (se.y[:upto], se.s[:upto])
    v = s ** 2 + tau ** 2
    if not np.all(v > 0):
        return float(np.mean(y)), 0.0
    m, W = _weighted_mean(y, 1.0 / v)
    return m, 1.0 / math.sqrt(W)


def assess(recordings: Iterable[Recording], *, alpha: float = ALPHA,
           outlier_z: float = OUTLIER_Z) -> FleetAssessment:
    """Assess every drive of a history's recordings (docs/fleet.md)."""
    recs = [r for r in recordings]
    errors: dict[tuple[str, str], int] = {}
    for r in recs:
        if not r.ok:
            errors[(r.model_key, r.drive)] = errors.get((r.model_key, r.drive), 0) + 1
    ok = _collapse_live([r for r in recs if r.ok])
    by_model: dict[str, dict[str, list[Recording]]] = {}
    for r in ok:
        by_model.setdefault(r.model_key, {}).setdefault(r.drive, []).append(r)
    drives: list[DriveAssessment] = []
    baselines: dict[str, dict[str, Baseline]] = {}
    spread: dict[str, dict[str, dict[str, tuple[str, float]]]] = {}
    for key, per_drive in by_model.items():
        for lst in per_drive.values():
            lst.sort(key=lambda r: (_time(r), r.id or 0))
        names = sorted({p.name for lst in per_drive.values() for r in lst
                        for p in r.parameters}) + [RESIDUAL]
        # positive by physics: in logs; a value <= 0 of such a parameter (impossible
        # physics, a recording gone wrong) is left out of its series
        logs = {n: n == RESIDUAL or _positive(n) for n in names}
        ser: dict[str, dict[str, Series]] = {}
        for d, lst in per_drive.items():
            ser[d] = {}
            for n in names:
                se = _series(lst, n, logs[n])
                if se is not None:
                    ser[d][n] = se
        types = {d: lst[0].drive_type for d, lst in per_drive.items()}
        # the scatter per type (drives of a size scatter alike), the fleet's for a type
        # with too few pairs
        taus: dict[str, dict[str, float]] = {d: {} for d in per_drive}
        baselines[key] = {}
        for n in names:
            pairs: dict[str, list[tuple[float, float]]] = {}
            for d in ser:
                se = ser[d].get(n)
                if se is None:
                    continue
                pairs.setdefault(types[d], []).extend(
                    (float((se.y[k + 1] - se.y[k]) ** 2),
                     float(se.s[k] ** 2 + se.s[k + 1] ** 2)) for k in range(len(se.y) - 1))
            everything = [p for ps in pairs.values() for p in ps]
            pooled = estimate_tau(everything)
            baselines[key][n] = Baseline(n, pooled, logs[n], len(everything))
            per_type = {}
            for ty, ps in pairs.items():
                # a type with few pairs: its own estimate is noisy, the fleet's may be
                # of another scale (an offset of a larger drive): the larger of the two
                own = estimate_tau(ps)
                per_type[ty] = own if len(ps) >= MIN_PAIRS else max(own, pooled)
                if len(pairs) > 1:
                    baselines[key][f"{n}@{ty}"] = Baseline(n, per_type[ty], logs[n], len(ps))
            for d in per_drive:
                taus[d][n] = per_type.get(types[d], pooled)
                se = ser[d].get(n)
                if not logs[n] and se is not None and len(se.y) > MIN_OWN_PAIRS:
                    # an offset or a harmonic follows what the drive moves: its scatter
                    # differs from drive to drive, and the drive's own (the same
                    # quantile of its own differences) counts when it is larger
                    own = estimate_tau([(float((se.y[k + 1] - se.y[k]) ** 2),
                                         float(se.s[k] ** 2 + se.s[k + 1] ** 2))
                                        for k in range(len(se.y) - 1)])
                    taus[d][n] = max(taus[d][n], own)
        assessed: dict[str, tuple[list[Alert], float]] = {}
        for d, lst in per_drive.items():
            assessed[d] = _drive_alerts(d, lst, ser[d], taus[d], alpha)
        # outliers among siblings: each drive's level before any change
        spread[key] = {}
        first_change = {d: min((a.at for a in assessed[d][0] if a.at is not None),
                               default=None) for d in per_drive}
        for n in names:
            if n == RESIDUAL or not logs[n]:
                continue  # offsets and harmonics depend on the load, not the drive
            levels: dict[str, tuple[float, float]] = {}
            for d in per_drive:
                se = ser[d].get(n)
                if se is None:
                    continue
                upto = first_change[d]
                levels[d] = _level(se, taus[d][n], upto if upto and upto >= 2 else None)
            spread[key][n] = {d: (types[d], math.exp(m) if logs[n] else m)
                              for d, (m, _) in levels.items()}
            groups: dict[str, list[str]] = {}
            for d in levels:
                groups.setdefault(types[d], []).append(d)
            dev: dict[str, float] = {}
            for members in groups.values():
                if len(members) < MIN_SIBLINGS:
                    continue
                med = float(np.median([levels[d][0] for d in members]))
                for d in members:
                    dev[d] = levels[d][0] - med
            if len(dev) < MIN_SIBLINGS:
                continue
            scale = 1.4826 * float(np.median(np.abs(list(dev.values()))))
            for d, x in dev.items():
                se_d = levels[d][1]
                den = math.sqrt(scale ** 2 + se_d ** 2)
                if den <= 0:
                    continue
                z = x / den
                if abs(z) < outlier_z:
                    continue
                se = ser[d][n]
                lvl = math.exp(levels[d][0]) if logs[n] else levels[d][0]
                sib = math.exp(levels[d][0] - x) if logs[n] else levels[d][0] - x
                rel = f" ({lvl / sib:.2f} x)" if logs[n] and sib > 0 else ""
                assessed[d][0].append(Alert(
                    drive=d, kind="outlier", series=n, z=z, p=min(1.0, _phi_tail(z)),
                    message=(f"{n} = {_fmt(lvl, se.unit)} against {_fmt(sib, se.unit)} of its "
                             f"{len(groups[types[d]]) - 1} siblings ({types[d] or 'no type'})"
                             f"{rel}, z = {z:.1f}"),
                    before=sib, after=lvl, tau=scale, unit=se.unit,
                    evidence=_evidence(se, None)))
        for d, lst in per_drive.items():
            al, max_z = assessed[d]
            drives.append(DriveAssessment(
                drive=d, drive_type=types[d], model_key=key, model=lst[0].model,
                recordings=len(lst), errors=errors.get((key, d), 0), alerts=_ordered(al),
                series=ser[d], max_z=max_z))
    for (key, d), n_err in errors.items():
        if key not in by_model or d not in by_model[key]:
            drives.append(DriveAssessment(drive=d, drive_type="", model_key=key, model="",
                                          recordings=0, errors=n_err, alerts=()))
    drives.sort(key=lambda a: (-a.score, -a.errors, -a.max_z, a.drive))
    return FleetAssessment(drives=tuple(drives), baselines=baselines, spread=spread,
                           alpha=alpha)


def to_rank(fleet: FleetAssessment, around: int = 2) -> list[tuple[int, str]]:
    """``(recording id, path)`` of the recordings to rank for the residual changes that
    have no ranking yet: up to ``around`` before each change and ``around`` after."""
    out: list[tuple[int, str]] = []
    seen: set[int] = set()
    for d in fleet.drives:
        for a in d.alerts:
            if a.kind != "residual" or a.at is None:
                continue
            se = d.series.get(RESIDUAL)
            if se is None:
                continue
            n = len(se.y)
            picks = [*range(max(0, a.at - around), a.at), *range(max(a.at, n - around), n)]
            for i in picks:
                rid = se.ids[i]
                if rid is not None and rid not in seen:
                    seen.add(rid)
                    out.append((rid, se.paths[i]))
    return out
