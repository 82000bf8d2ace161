r"""Change, drift, new-effect and outlier detection on a fleet's history.

Each series (per model, parameter and drive) is tested against the drive's own normal
week-to-week scatter, learned robustly from its history and shrunk toward its type's
(:math:`\tau`), with each recording's sigma. A drive is alerted when a change or drift
is both unlikely for a healthy drive (over its splits, onsets and series, under their
own correlation) and large enough to matter (:class:`DetectionSettings`, the
``[fleet]`` table), and it is compared with its siblings. The statistics, the defaults
and the figures: docs/fleet.md, "Finding what changes".
"""

from __future__ import annotations

import dataclasses
import datetime
import functools
import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, ClassVar

import numpy as np
import numpy.typing as npt

from canrls.core.checks import in_range, is_epoch, is_positive
from canrls.core.errors import ConfigError
from canrls.estimation.effects import library
from canrls.fleet.multiplicity import family_p, phi_tail, t_equivalent, t_tail, tree_links
from canrls.fleet.records import SOURCE_LIVE, Recording

__all__ = ["ALPHA", "OUTLIER_Z", "MIN_RECORDINGS", "MIN_SIBLINGS", "RESIDUAL", "Alert",
           "Evidence", "DriveAssessment", "FleetAssessment", "Baseline", "assess",
           "estimate_tau", "to_rank", "POSITIVE_EFFECTS", "DetectionSettings",
           "MIN_CHANGE", "MIN_TIMES_USUAL", "PRIOR_PAIRS", "when"]

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
#: how many of a drive's own successive pairs its type's scatter weighs like: a drive
#: with few recordings takes its type's, one with many mostly its own
PRIOR_PAIRS = 16
#: the share of a drive's own standardised differences whose mean estimates its scatter
#: (the largest left out: a step)
OWN_KEEP = 0.8
#: the series name of the residual RMS
RESIDUAL = "residual_rms"
#: the least change that matters, relative, per effect (positive parameters) and for the
#: residual RMS (a rise by half: its scatter from one excitation to the next has heavier
#: tails than a normal's); ``[fleet] min_change`` overrides them
MIN_CHANGE: Mapping[str, float] = {"inertia": 0.05, "viscous": 0.10, "coulomb": 0.10,
                                   "stribeck": 0.10, "electrical": 0.05, RESIDUAL: 0.5}
#: the least change that matters against the drive's usual week-to-week change (the
#: only size test of an offset or a harmonic, whose size has no natural scale)
MIN_TIMES_USUAL = 2.0
#: least share of the residual after a change that an effect must explain to be named
#: the new effect (and rise by half as much)
NEW_EFFECT_SHARE = 0.2
#: effects whose parameters are positive by physics: compared in logs (relative scale)
POSITIVE_EFFECTS = ("inertia", "viscous", "coulomb", "stribeck", "electrical")
#: the quantile of the standardised differences that tau matches to a chi-square's: the
#: median, so that one step or the later half of a drift does not move it
TAU_QUANTILE = 0.5
#: a recording whose sigma is this many times its series' median pins the parameter
#: too poorly to say how much the drive moves (a PRBS alone for friction)
POORLY_PINNED = 10.0
#: a recording starts this many typical intervals before the fleet's latest: the drive
#: stopped recording (renamed in the manifest, or retired)
STALE_INTERVALS = 3.0


@functools.lru_cache(maxsize=64)
def _chi2_1_quantile(q: float) -> float:
    """The quantile ``q`` of a chi-square with one degree of freedom (bisection on erf)."""
    lo, hi = 0.0, 100.0
    for _ in range(200):
        mid = 0.5 * (lo + hi)
        # P(chi2_1 <= x) = erf(sqrt(x / 2))
        if math.erf(math.sqrt(mid / 2.0)) < q:
            lo = mid
        else:
            hi = mid
    return hi


def when(t: float) -> str | None:
    """The date of an epoch time (``2026-03-02``), None for a log's own clock."""
    if not is_epoch(t):
        return None
    return datetime.datetime.fromtimestamp(t, tz=datetime.UTC).strftime("%Y-%m-%d")


# ---------------------------------------------------------------------------- settings
@dataclass(frozen=True)
class DetectionSettings:
    """What counts as an alert: the statistical test's level and the sizes that matter
    (the ``[fleet]`` table of a configuration file, :meth:`from_table`)."""

    alpha: float = ALPHA
    outlier_z: float = OUTLIER_Z
    #: least relative change per effect (``coulomb``) or parameter (``coulomb.Tc``), and
    #: for ``residual_rms``; the defaults :data:`MIN_CHANGE` for the others
    min_change: Mapping[str, float] = field(default_factory=dict)
    min_times_usual: float = MIN_TIMES_USUAL
    prior_pairs: int = PRIOR_PAIRS

    KEYS: ClassVar[tuple[str, ...]] = ("alpha", "outlier_z", "min_change", "min_times_usual",
                                      "prior_pairs")

    @classmethod
    def from_table(cls, table: Mapping[str, Any], source: str = "[fleet]"
                   ) -> DetectionSettings:
        """The settings of a ``[fleet]`` table.

        :raises ConfigError: an unknown key, effect or value, naming the file and key.
        """
        kw: dict[str, Any] = {}
        for k, v in table.items():
            if k not in cls.KEYS:
                raise ConfigError(f"{source}: unknown key fleet.{k} = {v!r} (valid: "
                                  f"{', '.join(cls.KEYS)})")
            if k == "min_change":
                kw[k] = _min_change(v, source)
            elif k == "prior_pairs":
                if isinstance(v, bool) or not isinstance(v, int) or v < 0:
                    raise ConfigError(f"{source}: fleet.prior_pairs = {v!r}: must be an "
                                      f"integer >= 0")
                kw[k] = v
            else:
                hi = 1.0 if k == "alpha" else math.inf
                if not in_range(v, 0, hi, lo_open=True, hi_open=True):
                    want = "between 0 and 1" if k == "alpha" else "a number > 0"
                    raise ConfigError(f"{source}: fleet.{k} = {v!r}: must be {want}")
                kw[k] = float(v)
        return cls(**kw)

    @classmethod
    def from_file(cls, path: str | None) -> DetectionSettings:
        """The settings of the ``[fleet]`` table of the TOML file ``path`` (the defaults
        without a file or a table).

        :raises ConfigError: the file cannot be read, or its ``[fleet]`` table is bad.
        """
        if path is None:
            return cls()
        from canrls.processor.config import AppConfig

        return cls.from_table(AppConfig.load(path).fleet, path)

    def least_change(self, series: str) -> float:
        """The least relative change of ``series`` that matters (0: none but the
        drive's usual scatter, for an offset or a harmonic)."""
        base = _effect_of(series)
        for key in (series, base):
            if key in self.min_change:
                return self.min_change[key]
        return MIN_CHANGE.get(series, MIN_CHANGE.get(base, 0.0))

    def to_dict(self) -> dict[str, Any]:
        return {"alpha": self.alpha, "outlier_z": self.outlier_z,
                "min_change": {**MIN_CHANGE, **self.min_change},
                "min_times_usual": self.min_times_usual, "prior_pairs": self.prior_pairs}


def _min_change(v: Any, source: str) -> dict[str, float]:
    if not isinstance(v, dict):
        raise ConfigError(f"{source}: fleet.min_change = {v!r}: must be a table of "
                          f"effect = fraction (coulomb = 0.1)")
    known = {c.NAME for c in library()}
    out = {}
    for name, x in v.items():
        base = _effect_of(str(name))
        if base not in known and name != RESIDUAL:
            raise ConfigError(f"{source}: fleet.min_change.{name}: unknown effect {base!r} "
                              f"(valid: {', '.join(sorted(known))}, {RESIDUAL})")
        if not in_range(x, 0, 100, hi_open=True):
            raise ConfigError(f"{source}: fleet.min_change.{name} = {x!r}: must be a "
                              f"fraction >= 0 (0.1 for 10 %)")
        out[str(name)] = float(x)
    return out


def _effect_of(series: str) -> str:
    """``coulomb`` of ``coulomb.Tc``, ``cogging`` of ``cogging:5.sin``."""
    return series.split(".", 1)[0].split(":", 1)[0]


# ---------------------------------------------------------------------------- results
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
                "date": when(self.t), "value": self.value, "sigma": self.sigma}


@dataclass(frozen=True)
class Alert:
    """Something about a drive that needs a look.

    ``kind``: ``change`` (a step), ``drift`` (a slope since a recording), ``new effect``
    (the residual rose and the ranking names the effect that appeared), ``residual``
    (the residual rose, no ranking to name why), ``outlier`` (unlike its siblings).
    ``at``: the index (0-based, in time order) of the first recording after the change
    or of the drift's onset; ``since``/``seen``: its time and that of the last recording.
    ``before``/``after``: the levels (physical units; for a drift, at the onset and at
    the last recording); ``relative``: after/before - 1 (NaN for an offset or a
    harmonic); ``times_usual``: the change over the drive's usual week-to-week change.
    ``tau``: the between-recording scatter used (relative for a positive parameter,
    else in its unit). ``cause`` and ``check``: in the words of the effect library.
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
    since: float = math.nan
    seen: float = math.nan
    relative: float = math.nan
    times_usual: float = math.nan
    cause: str = ""
    check: str = ""

    @property
    def severity(self) -> float:
        """-log10 p (large: sure); the drives are ranked by it."""
        return -math.log10(max(self.p, 1e-300))

    def to_dict(self) -> dict[str, Any]:
        return {"drive": self.drive, "kind": self.kind, "series": self.series,
                "effect": self.effect, "z": self.z, "p": self.p, "severity": self.severity,
                "message": self.message, "at": self.at, "since": self.since,
                "since_date": when(self.since), "seen": self.seen,
                "seen_date": when(self.seen), "before": self.before, "after": self.after,
                "relative": self.relative, "times_usual": self.times_usual,
                "tau": self.tau, "unit": self.unit, "cause": self.cause,
                "check": self.check, "evidence": [e.to_dict() for e in self.evidence]}


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
    """A drive, its recordings and its alerts (most severe first).

    ``scatter``: per series the normal week-to-week scatter tau used for this drive;
    ``notes``: what the bookkeeping says (too few recordings, two models, equal times,
    no recent recording), never an alert.
    """

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
    scatter: Mapping[str, float] = field(default_factory=dict)
    notes: tuple[str, ...] = ()

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
                "alerts": [a.to_dict() for a in self.alerts],
                "scatter": dict(self.scatter), "notes": list(self.notes)}


@dataclass(frozen=True)
class FleetAssessment:
    """Every drive (ranked: what needs a look first), the scatter used per model, and the
    fleet's spread per parameter (each drive's level)."""

    drives: tuple[DriveAssessment, ...]
    baselines: Mapping[str, Mapping[str, Baseline]]
    spread: Mapping[str, Mapping[str, Mapping[str, tuple[str, float]]]]
    alpha: float = ALPHA
    settings: DetectionSettings = field(default_factory=DetectionSettings)

    @property
    def alerts(self) -> list[Alert]:
        return [a for d in self.drives for a in d.alerts]

    def drive(self, name: str, model_key: str | None = None) -> DriveAssessment:
        for d in self.drives:
            if d.drive == name and (model_key is None or d.model_key == model_key):
                return d
        raise KeyError(name)

    def to_dict(self) -> dict[str, Any]:
        return {"alpha": self.alpha, "settings": self.settings.to_dict(),
                "drives": [d.to_dict() for d in self.drives],
                "alerts": len(self.alerts),
                "baselines": {k: {s: b.to_dict() for s, b in v.items()}
                              for k, v in self.baselines.items()},
                "spread": {k: {p: {d: {"type": t, "level": v} for d, (t, v) in dv.items()}
                               for p, dv in v.items()} for k, v in self.spread.items()}}


# ---------------------------------------------------------------------------- series
def _positive(name: str) -> bool:
    return _effect_of(name) in POSITIVE_EFFECTS


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


def _pinned(se: Series, s_ref: float) -> npt.NDArray[np.intp]:
    """The recordings of a series that pin it down: sigma within :data:`POORLY_PINNED`
    times ``s_ref``, the median of its drive type's (a recording whose excitation cannot
    tell the parameter tells nothing of how much the drive moves either)."""
    return np.flatnonzero(se.s <= POORLY_PINNED * s_ref)


def _pairs(se: Series, keep: npt.NDArray[np.intp]) -> list[tuple[float, float]]:
    r"""``((d_k - \tilde d)^2, s_k^2 + s_{k+1}^2)`` of the successive recordings ``keep``
    of a series at different times (two at the same time are not a week apart), the
    differences less their median :math:`\tilde d` (so that a drift, which moves every
    difference alike, does not pass for scatter; a step moves one)."""
    i = np.array([a for a, b in zip(keep, keep[1:], strict=False) if se.t[b] != se.t[a]],
                 dtype=np.intp)
    if not len(i):
        return []
    j = keep[np.searchsorted(keep, i) + 1]
    d = se.y[j] - se.y[i]
    if len(d) >= MIN_RECORDINGS:
        d = d - float(np.median(d))
    v = se.s[i] ** 2 + se.s[j] ** 2
    return list(zip((d ** 2).tolist(), v.tolist(), strict=True))


def estimate_tau(pairs: Sequence[tuple[float, float]], quantile: float = TAU_QUANTILE
                 ) -> float:
    r"""The between-recording scatter :math:`\tau` from ``(d_k^2, s_k^2 + s_{k+1}^2)``
    of successive recordings: the ``quantile`` of the standardised squared differences
    :math:`d_k^2 / (s_k^2 + s_{k+1}^2 + 2\tau^2)` matched to a chi-square's with one
    degree of freedom (docs/fleet.md)."""
    if not pairs:
        return 0.0
    target = _chi2_1_quantile(quantile)
    d2 = np.array([p[0] for p in pairs])
    v = np.array([p[1] for p in pairs])
    # each pair's standardised difference d^2 / (v + 2 tau^2) falls to the target at
    # tau_k^2 = (d^2 / target - v) / 2; the quantile of the standardised differences
    # equals the target where tau^2 is that quantile of the tau_k^2 (both monotone)
    tau2 = float(np.quantile((d2 / target - v) / 2.0, quantile, method="inverted_cdf"))
    return math.sqrt(tau2) if tau2 > 0 else 0.0


def _own_tau(pairs: Sequence[tuple[float, float]]) -> float:
    r"""A drive's own scatter :math:`\tau` from its few pairs: the mean of the smallest
    :data:`OWN_KEEP` of the standardised squared differences
    :math:`d_k^2 / (s_k^2 + s_{k+1}^2 + 2\tau^2)` matched to that of a chi-square with
    one degree of freedom below the same quantile (the largest, a step, left out; more
    efficient than the median on nine pairs)."""
    if not pairs:
        return 0.0
    d2 = [p[0] for p in pairs]
    v = [p[1] for p in pairs]
    k = max(1, math.floor(OWN_KEEP * len(d2) + 1e-9))
    q = _chi2_1_quantile(k / len(d2))
    # E[X | X < q] of X ~ chi2_1 = P(chi2_3 < q) / P(chi2_1 < q)
    target = (math.erf(math.sqrt(q / 2)) - math.sqrt(2 * q / math.pi) * math.exp(-q / 2)) \
        / (k / len(d2))

    def trimmed(tau: float) -> float:
        # a few pairs: plain Python is faster than numpy here
        t2 = 2 * tau * tau
        z = sorted(a / (b + t2) if b + t2 > 0 else math.inf for a, b in zip(d2, v,
                                                                           strict=True))
        return sum(z[:k]) / k

    if trimmed(0.0) <= target:
        return 0.0
    lo, hi = 0.0, max(1e-12, math.sqrt(max(d2)))
    while trimmed(hi) > target:
        hi *= 2.0
    for _ in range(50):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if trimmed(mid) > target else (lo, mid)
    return hi


def _shrunk(own: float, own_pairs: int, prior: float, prior_pairs: int) -> float:
    r"""A drive's scatter, shrunk toward its type's:
    :math:`\tau_d^2 = (m \hat\tau_d^2 + m_0 \tau_{type}^2) / (m + m_0)`."""
    m, m0 = own_pairs, prior_pairs
    if m + m0 == 0:
        return prior
    # tau_d^2 = (m tau_own^2 + m0 tau_type^2) / (m + m0)
    return math.sqrt((m * own ** 2 + m0 * prior ** 2) / (m + m0))


# ---------------------------------------------------------------------------- tests
@dataclass(frozen=True)
class _Found:
    kind: str
    z: float
    at: int
    before: float
    after: float


@dataclass(frozen=True)
class _Scale:
    """A drive's normal scatter of one series: tau, its usual week-to-week change, and
    the degrees of freedom tau rests on (its own pairs and its type's weight)."""

    tau: float
    usual: float
    dof: float


def _weighted_mean(y: F64, w: F64) -> tuple[float, float]:
    W = float(w.sum())
    return float((w * y).sum() / W), W


@dataclass(frozen=True)
class _Family:
    """Every change and drift tested on a series, and the correlations that hold them
    together (:func:`~canrls.fleet.multiplicity.tree_links`)."""

    found: list[_Found]
    links: F64


def _tests(se: Series, tau: float) -> _Family:
    """Every change (a split with two or more recordings on each side) and drift (flat
    to an onset, then a slope with three or more recordings on it) of a series, never
    between two recordings of the same time, and the correlations that hold them
    together."""
    n = len(se.y)
    if n < MIN_RECORDINGS:
        return _Family([], np.empty(0))
    v = se.s ** 2 + tau ** 2
    if not np.all(v > 0):  # no scatter at all (a series with neither sigma nor tau)
        return _Family([], np.empty(0))
    w = 1.0 / v
    y = se.y
    out: list[_Found] = []
    rows: list[F64] = []  # each z = a^T y, one row a per test
    cw, cwy = np.cumsum(w), np.cumsum(w * y)
    W, Wy = float(cw[-1]), float(cwy[-1])
    idx = np.arange(n)
    for m in range(2, n - 1):
        if se.t[m] == se.t[m - 1]:
            continue
        Wb, Wa = float(cw[m - 1]), W - float(cw[m - 1])
        mb, ma = float(cwy[m - 1]) / Wb, (Wy - float(cwy[m - 1])) / Wa
        # z_m = (ybar_{>=m} - ybar_{<m}) / sqrt(1/W_{<m} + 1/W_{>=m}) = a_m^T y
        a = np.where(idx >= m, w / Wa, -w / Wb) / math.sqrt(1.0 / Wb + 1.0 / Wa)
        rows.append(a)
        out.append(_Found("change", float(a @ y), m, mb, ma))
    days = (se.t - se.t[0]) / 86400.0
    ybar = Wy / W
    for c in range(0, n - 2):
        if c > 0 and se.t[c] == se.t[c - 1]:
            continue
        g = np.maximum(0.0, days - days[c])
        gbar = float((w * g).sum() / W)
        sgg = float((w * (g - gbar) ** 2).sum())
        if sgg <= 0:
            continue
        # z_c = b / se(b) = b sqrt(S_gg) = a_c^T y,  a_c = w (g - gbar) / sqrt(S_gg)
        a = w * (g - gbar) / math.sqrt(sgg)
        z = float(a @ y)
        # b = sum w (g - gbar)(y - ybar) / S_gg
        b = z / math.sqrt(sgg)
        lvl = ybar - b * gbar
        rows.append(a)
        out.append(_Found("drift", z, c, lvl, lvl + b * float(g[-1])))
    return _Family(out, tree_links(np.array(rows), v) if rows else np.empty(0))


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


def _at(se: Series, k: int) -> str:
    """When recording ``k`` of a series was made: its date, else its place."""
    return when(float(se.t[k])) or f"recording {k + 1} of {len(se.y)}"


def _cause(series: str, rises: bool) -> tuple[str, str]:
    """``(likely cause, what to check)`` of a change of ``series`` in the words of the
    effect library (a harmonic's sine or cosine: the term appearing or growing)."""
    base = _effect_of(series)
    for cls in library():
        if cls.NAME == base:
            periodic = base in ("unbalance", "cogging")
            cause = cls.CHANGE_CAUSE[0 if rises or periodic else 1]
            if base == "cogging" and ":" in series:
                order = series.split(":", 1)[1].split(".", 1)[0]
                cause = cause.replace("this order", f"order {order}")
            return cause, cls.CHANGE_CHECK
    return "", ""


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


def _usual(se: Series, keep: npt.NDArray[np.intp], tau: float) -> float:
    r"""The drive's usual week-to-week change of a series: the standard deviation of the
    difference of two healthy recordings that pin it down,
    :math:`\sqrt{2(\tau^2 + \tilde s^2)}`."""
    s2 = float(np.median(se.s[keep] ** 2)) if len(keep) else float(np.median(se.s ** 2))
    # u = sqrt(2 (tau^2 + median s^2))
    return math.sqrt(2.0 * (tau ** 2 + s2))


def _drive_alerts(drive: str, recs: Sequence[Recording], series: Mapping[str, Series],
                  scale: Mapping[str, _Scale], cfg: DetectionSettings
                  ) -> tuple[list[Alert], float]:
    """A drive's alerts: per series the most significant change or drift that is large
    enough to matter, when it is unlikely for a healthy drive: the family-wise p of
    its z over every test of every series of the drive
    (:func:`~canrls.fleet.multiplicity.family_p`)."""
    families = {name: _tests(se, scale[name].tau) for name, se in series.items()}
    found = {name: fam.found for name, fam in families.items()}
    max_z = max((abs(f.z) for fs in found.values() for f in fs), default=0.0)
    alerts = []
    for name, fs in found.items():
        se, tau, usual = series[name], scale[name].tau, scale[name].usual
        least = cfg.least_change(name)
        best: tuple[_Found, float, float] | None = None
        for f in fs:
            delta = f.after - f.before  # in logs for a positive parameter, the residual
            rel = math.expm1(delta) if se.log else math.nan
            times = abs(delta) / usual if usual > 0 else math.inf
            matters = (times >= cfg.min_times_usual
                       and (not se.log or abs(rel) >= least)
                       and (name != RESIDUAL or delta > 0))  # the residual: a rise
            if matters and (best is None or abs(f.z) > abs(best[0].z)):
                best = (f, rel, times)
        if best is None:
            continue
        f, rel, times = best
        # the family's p is never below the test's own: most need no more
        if t_tail(f.z, scale[name].dof) >= cfg.alpha:
            continue
        p = family_p(t_equivalent(f.z, scale[name].dof),
                     [(len(fam.found), fam.links) for fam in families.values()])
        if p < cfg.alpha:
            alerts.append(_alert(drive, recs, se, f, p, tau, rel, times))
    return alerts, max_z


def _alert(drive: str, recs: Sequence[Recording], se: Series, f: _Found, p: float,
           tau: float, rel: float, times: float) -> Alert:
    """An alert a person acts on: when, what, how much, since when, why, what to check."""
    name = se.name
    b, a = _phys(se, f.before), _phys(se, f.after)
    last = len(se.y) - 1
    seen, since = _at(se, last), _at(se, f.at)
    size = (f"{100 * rel:+.0f} %" if se.log else
            f"{'+' if a >= b else '-'}{_fmt(abs(a - b), se.unit)}")
    against = f"{times:.0f}× its usual week-to-week change" if math.isfinite(times) else \
        "its usual week-to-week change is nil"
    how = "a step" if f.kind == "change" else "drifting"
    kind, effect = f.kind, None
    cause, check = _cause(name, a >= b)
    if name == RESIDUAL:
        effect, ranked = _new_effect(recs, f.at)
        if effect is not None:
            kind = "new effect"
            cause, check = _cause(effect, True)
            head = (f"{seen}: a new effect, {effect}, since {since}: the residual "
                    f"{size} ({against}, z = {f.z:.1f}); {ranked}")
        else:
            kind = "residual"
            head = (f"{seen}: the residual {size} since {since} ({how}: "
                    f"{_fmt(b, se.unit)} -> {_fmt(a, se.unit)}, {against}, "
                    f"z = {f.z:.1f}); "
                    + (ranked or "a missing effect? rank the candidates (canrls fleet "
                       "ingest --rank auto) to name it"))
            cause, check = "an effect the model lacks", "canrls diagnose on a recent log"
    else:
        head = (f"{seen}: {name} {size} since {since} ({how}: {_fmt(b, se.unit)} -> "
                f"{_fmt(a, se.unit)}, {against}, z = {f.z:.1f})")
    msg = head + (f". Likely cause: {cause}. Check {check}." if cause else ".")
    return Alert(drive=drive, kind=kind, series=name, z=f.z, p=p, message=msg, at=f.at,
                 before=b, after=a, tau=tau, effect=effect, unit=se.unit,
                 evidence=_evidence(se, f.at), since=float(se.t[f.at]),
                 seen=float(se.t[last]), relative=rel, times_usual=times, cause=cause,
                 check=check)


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


# ---------------------------------------------------------------------------- the fleet
def _scatter(names: Sequence[str], ser: Mapping[str, Mapping[str, Series]],
             types: Mapping[str, str], cfg: DetectionSettings
             ) -> tuple[dict[str, dict[str, _Scale]], dict[str, Baseline]]:
    """Each drive's normal week-to-week scatter tau per series (its own, shrunk toward
    its type's) and its usual week-to-week change; the fleet's and types' tau (the
    baselines)."""
    scales: dict[str, dict[str, _Scale]] = {d: {} for d in ser}
    baselines: dict[str, Baseline] = {}
    for n in names:
        has = [d for d in ser if n in ser[d]]
        s_ref: dict[str, float] = {}
        for ty in {types[d] for d in has}:
            s_ref[ty] = float(np.median(np.concatenate(
                [ser[d][n].s for d in has if types[d] == ty])))
        keep = {d: _pinned(ser[d][n], s_ref[types[d]]) for d in has}
        own = {d: _pairs(ser[d][n], keep[d]) for d in has}
        by_type: dict[str, list[tuple[float, float]]] = {}
        for d, ps in own.items():
            by_type.setdefault(types[d], []).extend(ps)
        everything = [p for ps in by_type.values() for p in ps]
        pooled = estimate_tau(everything)
        log = n == RESIDUAL or _positive(n)
        baselines[n] = Baseline(n, pooled, log, len(everything))
        per_type = {}
        for ty, ps in by_type.items():
            # the median of the type's pairs: a few drives that change do not move it;
            # a type with few pairs takes the larger of its own and the fleet's
            t_own = estimate_tau(ps)
            per_type[ty] = t_own if len(ps) >= MIN_PAIRS else max(t_own, pooled)
            if len(by_type) > 1:
                baselines[f"{n}@{ty}"] = Baseline(n, per_type[ty], log, len(ps))
        for d, ps in own.items():
            tau = _shrunk(_own_tau(ps), len(ps), per_type[types[d]], cfg.prior_pairs)
            scales[d][n] = _Scale(tau, _usual(ser[d][n], keep[d], tau),
                                  OWN_KEEP * len(ps) + cfg.prior_pairs)
    return scales, baselines


def _outliers(names: Sequence[str], per_drive: Mapping[str, Sequence[Recording]],
              ser: Mapping[str, Mapping[str, Series]], types: Mapping[str, str],
              taus: Mapping[str, Mapping[str, float]],
              assessed: Mapping[str, tuple[list[Alert], float]], cfg: DetectionSettings
              ) -> dict[str, dict[str, tuple[str, float]]]:
    """Each drive's level before any change per positive parameter (the spread), and an
    outlier alert for a drive far from its siblings' median (appended to ``assessed``)."""
    spread: dict[str, dict[str, tuple[str, float]]] = {}
    first_change = {d: min((a.at for a in assessed[d][0] if a.at is not None),
                           default=None) for d in per_drive}
    for n in names:
        if n == RESIDUAL or not _positive(n):
            continue  # offsets and harmonics depend on the load, not the drive
        levels: dict[str, tuple[float, float]] = {}
        for d in per_drive:
            se = ser[d].get(n)
            if se is None:
                continue
            upto = first_change[d]
            levels[d] = _level(se, taus[d][n], upto if upto and upto >= 2 else None)
        spread[n] = {d: (types[d], math.exp(m)) for d, (m, _) in levels.items()}
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
            if abs(z) < cfg.outlier_z:
                continue
            se = ser[d][n]
            lvl, sib = math.exp(levels[d][0]), math.exp(levels[d][0] - x)
            _, check = _cause(n, lvl > sib)
            assessed[d][0].append(Alert(
                drive=d, kind="outlier", series=n, z=z, p=min(1.0, phi_tail(z)),
                message=(f"{n} = {_fmt(lvl, se.unit)} against {_fmt(sib, se.unit)} of its "
                         f"{len(groups[types[d]]) - 1} siblings ({types[d] or 'no type'}) "
                         f"({lvl / sib:.2f} x), z = {z:.1f}, since its first recording"
                         + (f". Check {check}." if check else ".")),
                before=sib, after=lvl, tau=scale, unit=se.unit,
                evidence=_evidence(se, None), since=float(se.t[0]), seen=float(se.t[-1]),
                relative=lvl / sib - 1.0, check=check))
    return spread


def _notes(lst: Sequence[Recording], models: int, earliest: float, latest: float,
           interval: float) -> tuple[str, ...]:
    """What the bookkeeping says about a drive's recordings of one model."""
    out = []
    n = len(lst)
    if n < MIN_RECORDINGS:
        out.append(f"{n} recording{'s' if n != 1 else ''} of this model: no trend is "
                   f"tested before {MIN_RECORDINGS}")
    if models > 1:
        out.append(f"recordings under {models} models: each model's are assessed on "
                   f"their own, never one against the other")
    times = [_time(r) for r in lst]
    same = n - len(set(times))
    if same:
        dup = sorted({t for t in times if times.count(t) > 1})
        out.append(f"{same + len(dup)} recordings share a start time "
                   f"({', '.join(when(t) or f'{t:g}' for t in dup[:3])}): no change is "
                   f"placed between them and they are not a week apart")
    ids = [r.id for r in lst if r.id is not None]
    if ids != sorted(ids):
        out.append("recordings stored out of time order: assessed in the order of their "
                   "start times")
    if times and is_positive(interval) and when(times[0]) is not None:
        first, last = min(times), max(times)
        if first - earliest > STALE_INTERVALS * interval:
            out.append(f"recorded since {when(first)} only (the fleet since "
                       f"{when(earliest)}): a new drive, or one renamed in the manifest?")
        if latest - last > STALE_INTERVALS * interval:
            out.append(f"no recording since {when(last)} (the fleet's latest: "
                       f"{when(latest)}): renamed in the manifest, or out of service?")
    return tuple(out)


def assess(recordings: Iterable[Recording], *, alpha: float | None = None,
           outlier_z: float | None = None,
           settings: DetectionSettings | None = None) -> FleetAssessment:
    """Assess every drive of a history's recordings (docs/fleet.md); ``alpha`` and
    ``outlier_z`` override those of ``settings``."""
    cfg = settings or DetectionSettings()
    if alpha is not None or outlier_z is not None:
        cfg = dataclasses.replace(cfg, alpha=cfg.alpha if alpha is None else alpha,
                                  outlier_z=cfg.outlier_z if outlier_z is None
                                  else outlier_z)
    recs = list(recordings)
    errors: dict[tuple[str, str], int] = {}
    for r in recs:
        if not r.ok:
            errors[(r.model_key, r.drive)] = errors.get((r.model_key, r.drive), 0) + 1
    ok = _collapse_live([r for r in recs if r.ok])
    by_model: dict[str, dict[str, list[Recording]]] = {}
    for r in ok:
        by_model.setdefault(r.model_key, {}).setdefault(r.drive, []).append(r)
    models_of: dict[str, int] = {}
    for per in by_model.values():
        for d in per:
            models_of[d] = models_of.get(d, 0) + 1
    drives: list[DriveAssessment] = []
    baselines: dict[str, dict[str, Baseline]] = {}
    spread: dict[str, dict[str, dict[str, tuple[str, float]]]] = {}
    for key, per_drive in by_model.items():
        for lst in per_drive.values():
            lst.sort(key=lambda r: (_time(r), r.id or 0))
        earliest, latest, interval = _cadence(per_drive)
        names = sorted({p.name for lst in per_drive.values() for r in lst
                        for p in r.parameters}) + [RESIDUAL]
        # positive by physics: in logs; a value <= 0 of such a parameter (impossible
        # physics, a recording gone wrong) is left out of its series
        ser: dict[str, dict[str, Series]] = {}
        for d, lst in per_drive.items():
            ser[d] = {}
            for n in names:
                se = _series(lst, n, n == RESIDUAL or _positive(n))
                if se is not None:
                    ser[d][n] = se
        types = {d: lst[0].drive_type for d, lst in per_drive.items()}
        scales, baselines[key] = _scatter(names, ser, types, cfg)
        taus = {d: {n: sc.tau for n, sc in per.items()} for d, per in scales.items()}
        assessed = {d: _drive_alerts(d, lst, ser[d], scales[d], cfg)
                    for d, lst in per_drive.items()}
        spread[key] = _outliers(names, per_drive, ser, types, taus, assessed, cfg)
        for d, lst in per_drive.items():
            al, max_z = assessed[d]
            drives.append(DriveAssessment(
                drive=d, drive_type=types[d], model_key=key, model=lst[0].model,
                recordings=len(lst), errors=errors.get((key, d), 0), alerts=_ordered(al),
                series=ser[d], max_z=max_z, scatter=taus[d],
                notes=_notes(lst, models_of[d], earliest, latest, interval)))
    for (key, d), n_err in errors.items():
        if key not in by_model or d not in by_model[key]:
            drives.append(DriveAssessment(
                drive=d, drive_type="", model_key=key, model="", recordings=0, errors=n_err,
                alerts=(), notes=("no recording of this model could be fitted",)))
    drives.sort(key=lambda a: (-a.score, -a.errors, -a.max_z, a.drive))
    return FleetAssessment(drives=tuple(drives), baselines=baselines, spread=spread,
                           alpha=cfg.alpha, settings=cfg)


def _cadence(per_drive: Mapping[str, Sequence[Recording]]) -> tuple[float, float, float]:
    """The earliest and latest start time of a model's recordings and the drives'
    median interval between two."""
    gaps, earliest, latest = [], math.inf, -math.inf
    for lst in per_drive.values():
        t = sorted({_time(r) for r in lst})
        if t:
            earliest, latest = min(earliest, t[0]), max(latest, t[-1])
        gaps += [b - a for a, b in zip(t, t[1:], strict=False)]
    return earliest, latest, float(np.median(gaps)) if gaps else math.nan


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
