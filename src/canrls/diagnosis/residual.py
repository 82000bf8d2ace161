r"""Where the model fails: statistics of the residual over the used samples.

Everything is computed on the *filtered* equation the estimators see (the state-variable
filter applied to output and columns, :mod:`canrls.estimation.svf`), over the samples the
estimators used (:class:`~canrls.diagnosis.record.RecordSamples`), in the output's unit:

* :func:`whiteness`: whiteness of the residual and its cross-correlation with the
  inputs (:class:`~canrls.diagnosis.results.Whiteness`);
* :func:`all_bins`: residual mean and RMS binned by speed (both directions), position
  (one revolution, or the travel of a linear axis), current, acceleration and time
  (:class:`~canrls.diagnosis.results.Binned`), :func:`find_regions` the worst regions in
  words;
* :func:`order_spectrum`: the residual's rotation-order spectrum, from
  :func:`harmonic_fit`;
* :func:`excitation_summary`: how the data excite the model (directions, reversals,
  acceleration against the speed-sensor noise, revolutions covered);
* :func:`residual_structure`: structure left in a residual (a constant offset,
  dependence on speed, position, current, acceleration, drift in time, periodicity).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator, Mapping, Sequence

import numpy as np
import numpy.typing as npt

from canrls import _kernels
from canrls.core.spill import PackedMask, Sliced
from canrls.diagnosis.record import BLOCK, RecordSamples
from canrls.diagnosis.results import (
    Binned,
    ExcitationSummary,
    OrderSpectrum,
    Region,
    StructureItem,
    Whiteness,
    share_text,
    value_text,
)
from canrls.estimation.model import Model
from canrls.estimation.svf import SVF

__all__ = [
    "MIN_BIN",
    "MIN_EXPLAINED",
    "MIN_STRUCTURE",
    "ORDER_STEP",
    "WHITENESS_LAGS",
    "Z99",
    "all_bins",
    "bin_residual",
    "chi2_sf",
    "excitation_summary",
    "find_regions",
    "harmonic_fit",
    "median",
    "moments",
    "nice_magnitudes",
    "PEAK_SHARE",
    "joint_shares",
    "order_spectrum",
    "percentiles",
    "residual_structure",
    "spectrum_orders",
    "spectrum_peaks",
    "whiteness",
]

F64 = npt.NDArray[np.float64]
#: a mask over the record's rows: an array, or packed (read in blocks)
B = npt.NDArray[np.bool_] | PackedMask

#: Share of the residual variance a candidate (or an order of the spectrum left in the
#: residual) must explain to be suggested (reported).
MIN_EXPLAINED = 0.05
#: Share of the residual variance a binned mean or an order must explain to count as
#: structure.
MIN_STRUCTURE = 0.25
#: Two-sided 99 % point of the standard normal distribution.
Z99 = 2.5758293035489004
#: Lags of the whiteness test (in decimated samples).
WHITENESS_LAGS = 20
#: Orders per unit of the rotation-order spectrum.
ORDER_STEP = 0.25
#: Fewest samples in a bin for its mean to count.
MIN_BIN = 20


# ----------------------------------------------------------------------------- whiteness
def chi2_sf(q: float, k: int) -> float:
    """Upper tail of chi-square with k degrees of freedom (Wilson-Hilferty)."""
    if k <= 0 or not math.isfinite(q):
        return math.nan
    if q <= 0:
        return 1.0
    c = 2.0 / (9.0 * k)
    z = ((q / k) ** (1.0 / 3.0) - (1.0 - c)) / math.sqrt(c)
    return 0.5 * math.erfc(z / math.sqrt(2.0))


def _every(x: Sliced, rows: B, D: int) -> F64:
    """``x[rows][::D]``, gathered block by block (no copy of ``x[rows]``)."""
    parts = []
    seen = 0  # rows passed so far
    for a in range(0, len(x), BLOCK):
        idx = np.flatnonzero(rows[a:a + BLOCK])
        # the rows whose rank among all rows is a multiple of D
        parts.append(x[a:a + BLOCK][idx[(-seen) % D::D]])
        seen += len(idx)
    return np.concatenate(parts) if parts else np.zeros(0)


def whiteness(r: Sliced, used: B, inputs: Mapping[str, Sliced], h: F64,
               lags: int) -> Whiteness | None:
    # decimation: the lag after which |rho_h| stays below 0.02
    hh = float(np.dot(h, h))
    if hh <= 0:
        return None
    m = len(h)
    rho = np.array([float(np.dot(h[: m - k], h[k:])) / hh for k in range(m)])
    big = np.flatnonzero(np.abs(rho) >= 0.02)
    D = int(big[-1]) + 1 if len(big) else 1
    x = _every(r, used, D)
    N = len(x)
    if N < 3 * lags + 10:
        return None
    x = x - x.mean()
    den = float(np.dot(x, x))
    if den <= 0:
        return None
    ac = np.array([float(np.dot(x[: N - k], x[k:])) / den for k in range(1, lags + 1)])
    bound = Z99 / math.sqrt(N)
    q = float(N * (N + 2) * np.sum(ac * ac / (N - np.arange(1, lags + 1))))
    p = chi2_sf(q, lags)
    cross: dict[str, F64] = {}
    outside: dict[str, int] = {}
    for name, sig in inputs.items():
        u = _every(sig, used, D)
        u = u - u.mean()
        du = float(np.dot(u, u))
        if du <= 0:
            continue
        norm = math.sqrt(den * du)
        cc = np.empty(2 * lags + 1)
        for j, k in enumerate(range(-lags, lags + 1)):
            # rho_ru(k) = sum r[i] u[i - k] / sqrt(sum r^2 sum u^2)
            cc[j] = (float(np.dot(x[k:], u[: N - k])) if k >= 0
                     else float(np.dot(x[: N + k], u[-k:]))) / norm
        cross[name] = cc
        outside[name] = int(np.sum(np.abs(cc) > bound))
    return Whiteness(decimation=D, lags=lags, samples=N, autocorr=ac, bound=bound,
                     outside=int(np.sum(np.abs(ac) > bound)), q=q, p_value=p,
                     white=bool(p >= 0.01), cross=cross, cross_outside=outside)



# ------------------------------------------------------------- record in blocks, exactly
def _true_rows(rows: B) -> int:
    """True rows of a mask (a packed one counted block by block, not unpacked)."""
    return rows.count() if isinstance(rows, PackedMask) else int(np.count_nonzero(rows))


def _spans(n: int) -> range:
    """Starts of the blocks of :data:`~canrls.diagnosis.record.BLOCK` rows."""
    return range(0, n, BLOCK)


def _kth(x: Sliced, rows: B | None, ks: list[int]) -> list[float]:
    """The ``k``-th smallest (0-based) of ``x[rows]`` for each ``k`` (finite values),
    exactly, without the copy of ``x[rows]``: a count on a fixed grid of bins finds the
    bin that holds the ``k``-th value, the search goes on inside it (its own values'
    range) until the values left are few (then sorted) or all equal."""
    n = len(x)
    grid = 4096
    few = 65536
    out = []
    for k in ks:
        lo, hi = math.inf, -math.inf
        for a in _spans(n):
            v = x[a:a + BLOCK] if rows is None else x[a:a + BLOCK][rows[a:a + BLOCK]]
            if len(v):
                lo, hi = min(lo, float(v.min())), max(hi, float(v.max()))
        below = 0  # values < lo
        while True:
            if lo == hi:
                out.append(lo)
                break
            scale = grid / (hi - lo)
            cnt = np.zeros(grid, np.int64)

            def cells(v: F64, lo: float = lo, hi: float = hi,
                      scale: float = scale) -> tuple[F64, npt.NDArray[np.int64]]:
                v = v[(v >= lo) & (v <= hi)]
                return v, np.minimum(((v - lo) * scale).astype(np.int64), grid - 1)

            for a in _spans(n):
                v = x[a:a + BLOCK] if rows is None else x[a:a + BLOCK][rows[a:a + BLOCK]]
                cnt += np.bincount(cells(v)[1], minlength=grid)
            if int(cnt.sum()) <= few:
                vals = [cells(x[a:a + BLOCK] if rows is None
                              else x[a:a + BLOCK][rows[a:a + BLOCK]])[0] for a in _spans(n)]
                out.append(float(np.sort(np.concatenate(vals))[k - below]))
                break
            cum = np.cumsum(cnt)
            b = int(np.searchsorted(cum, k - below, side="right"))
            below += int(cum[b - 1]) if b else 0
            nlo, nhi = math.inf, -math.inf
            for a in _spans(n):
                v = x[a:a + BLOCK] if rows is None else x[a:a + BLOCK][rows[a:a + BLOCK]]
                v, c = cells(v)
                v = v[c == b]
                if len(v):
                    nlo, nhi = min(nlo, float(v.min())), max(nhi, float(v.max()))
            lo, hi = nlo, nhi
    return out


def _finite(x: Sliced, rows: B | None) -> bool:
    for a in _spans(len(x)):
        v = x[a:a + BLOCK] if rows is None else x[a:a + BLOCK][rows[a:a + BLOCK]]
        if not np.isfinite(v).all():
            return False
    return True


def _copy(x: Sliced, rows: B | None) -> F64:
    return np.concatenate([x[a:a + BLOCK] if rows is None else
                           x[a:a + BLOCK][rows[a:a + BLOCK]] for a in _spans(len(x))])


def percentiles(x: Sliced, rows: B | None, qs: list[float]) -> list[float]:
    """``np.percentile(x[rows], qs)`` (its default, linear interpolation), bit for bit,
    from :func:`_kth` (no record-long copy unless a value is not finite). ``x[rows]``
    must not be empty."""
    if not _finite(x, rows):
        return [float(v) for v in np.percentile(_copy(x, rows), qs)]
    n = len(x) if rows is None else _true_rows(rows)
    ks: list[tuple[int, int, float]] = []
    for q in qs:
        # numpy's virtual index (n - 1) q and its neighbours
        v = (n - 1) * (q / 100.0)
        if v >= n - 1:
            ks.append((n - 1, n - 1, 0.0))
        else:
            lo = max(math.floor(v), 0)
            ks.append((lo, lo + 1, v - lo if v >= 0 else 0.0))
    want = sorted({k for a, b, _ in ks for k in (a, b)})
    got = dict(zip(want, _kth(x, rows, want), strict=True))
    out = []
    for a, b, g in ks:
        xa, xb = got[a], got[b]
        d = xb - xa
        # numpy's lerp: from the nearer end
        out.append(xb - d * (1.0 - g) if g >= 0.5 else xa + d * g)
    return out


def median(x: Sliced, rows: B | None = None) -> float:
    """``np.median(x[rows])``, bit for bit, without the copy (unless a value is not
    finite)."""
    if not _finite(x, rows):
        return float(np.median(_copy(x, rows)))
    n = len(x) if rows is None else _true_rows(rows)
    if n % 2:
        return _kth(x, rows, [n // 2])[0]
    a, b = _kth(x, rows, [n // 2 - 1, n // 2])
    return float(np.mean(np.array([a, b])))

# ----------------------------------------------------------------------------- binning
def nice_magnitudes(vmax: float) -> F64:
    """Bin edges in |value|: 0, 1-2-5 steps from vmax/300 to vmax, closed at the top."""
    if not (vmax > 0 and math.isfinite(vmax)):
        return np.array([0.0, 1.0])
    out = [0.0]
    lo = vmax / 300.0
    e = math.floor(math.log10(lo))
    while True:
        for m in (1.0, 2.0, 5.0):
            v = m * 10.0 ** e
            if v <= lo:
                continue
            if v >= vmax * 0.8:
                out.append(vmax * (1 + 1e-9))
                return np.array(out)
            out.append(v)
        e += 1


def bin_residual(values: Sliced, r: Sliced, edges: F64, quantity: str, label: str,
                 unit: str, rows: B | None = None) -> Binned:
    """Mean and RMS of ``r[rows]`` in the bins ``edges`` of ``values[rows]`` (every row
    when ``rows`` is None), block by block: the sums of each bin run in the order of
    the rows, as one pass over the record adds them (no record-long copy)."""
    nb = len(edges) - 1
    cnt = np.zeros(nb, np.int64)
    s1 = np.zeros(nb)
    s2 = np.zeros(nb)
    for a in _spans(len(values)):
        v = values[a:a + BLOCK]
        rr = r[a:a + BLOCK]
        if rows is not None:
            u = rows[a:a + BLOCK]
            v, rr = v[u], rr[u]
        idx = np.searchsorted(edges, v, side="right") - 1
        # the end bins are closed at the extremes
        idx = np.where(v == edges[-1], nb - 1, idx)
        ok = (idx >= 0) & (idx < nb) & np.isfinite(v)
        idx = idx[ok]
        rr = rr[ok]
        cnt += np.bincount(idx, minlength=nb)
        # s1 += r, s2 += r^2 per bin, row after row
        np.add.at(s1, idx, rr)
        np.add.at(s2, idx, rr * rr)
    good = cnt >= MIN_BIN
    mean = np.full(nb, np.nan)
    rms = np.full(nb, np.nan)
    mean[good] = s1[good] / cnt[good]
    rms[good] = np.sqrt(s2[good] / cnt[good])
    tot = int(cnt[good].sum())
    share = 0.0
    if tot > 1:
        mu = float(s1[good].sum()) / tot
        ss = float(s2[good].sum()) - tot * mu * mu
        between = float(np.sum(cnt[good] * (mean[good] - mu) ** 2))
        share = between / ss if ss > 0 else 0.0
    return Binned(quantity, label, unit, edges, cnt, mean, rms, min(max(share, 0.0), 1.0))


def _extremes(x: Sliced, rows: B) -> tuple[float, float]:
    """(min, max) of ``x[rows]``, block by block."""
    lo, hi = math.inf, -math.inf
    for a in _spans(len(x)):
        v = x[a:a + BLOCK][rows[a:a + BLOCK]]
        if len(v):
            lo, hi = min(lo, float(v.min())), max(hi, float(v.max()))
    return lo, hi


def moments(r: Sliced, rows: B) -> tuple[int, float, float, float]:
    """(N, mean, sum of squares, sum of squares about the mean) of ``r[rows]``, block by
    block (the deviations in a second pass, as ``np.std`` takes them)."""
    n = _true_rows(rows)
    s1 = s2 = 0.0
    for a in _spans(len(r)):
        v = r[a:a + BLOCK][rows[a:a + BLOCK]]
        s1 += float(np.sum(v))
        s2 += float(np.dot(v, v))
    if not n:
        return 0, math.nan, 0.0, 0.0
    mu = s1 / n
    ss = 0.0
    for a in _spans(len(r)):
        d = r[a:a + BLOCK][rows[a:a + BLOCK]] - mu
        ss += float(np.dot(d, d))
    return n, mu, s2, ss


def _edges_linear(v: Sliced, rows: B, nb: int) -> F64:
    """``nb`` bins from the 0.5 to the 99.5 percentile of ``v[rows]`` (exact:
    :func:`percentiles`), the end bins stretched to the extremes."""
    if _finite(v, rows):
        vmin, vmax = _extremes(v, rows)
    else:  # a non-finite value: numpy's extremes (nan), from the copy
        vmin, vmax = float(np.min(_copy(v, rows))), float(np.max(_copy(v, rows)))
    lo, hi = percentiles(v, rows, [0.5, 99.5])
    if not hi > lo:
        lo, hi = vmin, vmax
    if not hi > lo:
        return np.array([vmin - 0.5, vmin + 0.5])
    inner = np.linspace(lo, hi, nb + 1)
    inner[0] = min(vmin, lo)
    inner[-1] = max(vmax, hi)
    return inner


class _Mapped:
    """``f(x)`` elementwise, computed on the slices taken (a record-long array's
    stand-in for :func:`bin_residual` and :func:`percentiles`, which take only slices)."""

    def __init__(self, x: Sliced, f: Callable[[F64], F64]) -> None:
        self.x = x
        self.f = f

    def __len__(self) -> int:
        return len(self.x)

    def __getitem__(self, s: slice) -> F64:
        return self.f(self.x[s])


class _SecondDifference:
    """``|w[k+2] - 2 w[k+1] + w[k]|``, computed on the slices taken."""

    def __init__(self, w: Sliced) -> None:
        self.w = w

    def __len__(self) -> int:
        return max(len(self.w) - 2, 0)

    def __getitem__(self, s: slice) -> F64:
        a, b, _ = s.indices(len(self))
        w = self.w
        return np.abs(w[a + 2:b + 2] - 2.0 * w[a + 1:b + 1] + w[a:b])


def all_bins(ctx: RecordSamples, r: Sliced, used: B, unit: str) -> dict[str, Binned]:
    """The residual binned by speed, position, current, acceleration and time over the
    ``used`` rows, block by block (bin edges from exact extremes and percentiles)."""
    out: dict[str, Binned] = {}
    if not used.any():
        return out
    lo, hi = _extremes(ctx.speed, used)
    vmax = max(abs(lo), abs(hi))
    mags = nice_magnitudes(vmax)
    edges = np.concatenate([-mags[:0:-1], mags])
    out["speed"] = bin_residual(ctx.speed, r, edges, "speed", "speed", ctx.speed_unit, used)
    if ctx.position is not None:
        if ctx.axis == "rotary":
            pos = _Mapped(ctx.position, lambda x: np.mod(x, 2.0 * math.pi))
            pe = np.linspace(0.0, 2.0 * math.pi, 37)
            out["position"] = bin_residual(pos, r, pe, "position",
                                           "position in the revolution", "rad", used)
        else:
            out["position"] = bin_residual(ctx.position, r,
                                           _edges_linear(ctx.position, used, 40),
                                           "position", "position along the travel", "m", used)
    eff = ctx.effort  # the current, or the torque a torque-reporting drive sends
    out[eff] = bin_residual(ctx.current, r, _edges_linear(ctx.current, used, 20),
                            eff, eff, ctx.effort_unit, used)
    out["acceleration"] = bin_residual(ctx.acceleration, r,
                                       _edges_linear(ctx.acceleration, used, 20),
                                       "acceleration", "acceleration", ctx.acc_unit, used)
    t = ctx.t
    first = int(np.argmax(used))
    last = len(used) - 1 - int(np.argmax(used[::-1]))
    te = (np.linspace(float(t[first]), float(t[last]), 21) if last > first
          else np.array([0.0, 1.0]))
    if not te[-1] > te[0]:
        te = np.array([te[0] - 0.5, te[0] + 0.5])
    out["time"] = bin_residual(t, r, te, "time", "time", "s", used)
    return out


def _range_text(quantity: str, lo: float, hi: float, full_lo: float, full_hi: float,
                unit: str) -> str:
    lo_end = lo <= full_lo
    hi_end = hi >= full_hi
    if quantity == "time":
        if lo_end and hi_end:
            return "over the whole record"
        return f"from {lo:.3g} s to {hi:.3g} s"
    noun = {"speed": "speed", "position": "position", "current": "current",
            "torque": "torque", "acceleration": "acceleration"}[quantity]
    if lo_end and hi_end:
        return f"at every {noun}"
    if quantity == "speed":
        if lo <= 0.0:
            return f"below {hi:.3g} {unit}"
        if hi_end:
            return f"above {lo:.3g} {unit}"
        return f"between {lo:.3g} and {hi:.3g} {unit}"
    plural = {"position": "positions", "current": "currents", "torque": "torques",
              "acceleration": "accelerations"}[quantity]
    if lo_end:
        return f"at {plural} below {hi:.3g} {unit}"
    if hi_end:
        return f"at {plural} above {lo:.3g} {unit}"
    return f"at {plural} between {lo:.3g} and {hi:.3g} {unit}"


def _notable(mean: float, n: int, sd: float, rms: float, tau: float) -> bool:
    """A bin mean that stands out: large against the residual and not noise."""
    if not (n >= MIN_BIN and math.isfinite(mean)):
        return False
    se = sd / math.sqrt(max(n / tau, 1.0))
    return abs(mean) >= 0.2 * rms and abs(mean) >= 4.0 * se


def find_regions(bins: Mapping[str, Binned], ru: Sliced, tau: float, unit: str,
                 ctx: RecordSamples, rows: B | None = None) -> tuple[Region, ...]:
    """The worst regions in words; ``ru`` the residual on the used rows, or with
    ``rows`` the residual on every row and the used ones (read block by block)."""
    if rows is None:
        rows = np.ones(len(ru), np.bool_)
    n, _, energy, ss = moments(ru, rows)
    if not n:
        return ()
    sd = math.sqrt(ss / n)
    rms = math.sqrt(energy / n)
    if energy <= 0:
        return ()
    found: list[Region] = []
    # speed: magnitude bands with the mean forward and backward
    sb = bins.get("speed")
    if sb is not None:
        nm = (len(sb.edges) - 1) // 2
        mags = sb.edges[nm:]
        bands = []
        for j in range(nm):
            f = nm + j
            bk = nm - 1 - j
            nf, nb_ = int(sb.count[f]), int(sb.count[bk])
            mf, mb = float(sb.mean[f]), float(sb.mean[bk])
            sig_f = _notable(mf, nf, sd, rms, tau)
            sig_b = _notable(mb, nb_, sd, rms, tau)
            key = (int(np.sign(mf)) if sig_f else 0, int(np.sign(mb)) if sig_b else 0)
            bands.append((j, key, nf, mf, nb_, mb))
        groups: list[list[tuple[int, tuple[int, int], int, float, int, float]]] = []
        for band in bands:
            if band[1] == (0, 0):
                continue
            if groups and groups[-1][-1][0] == band[0] - 1 and groups[-1][-1][1] == band[1]:
                groups[-1].append(band)
            else:
                groups.append([band])
        for g in groups:
            nf = sum(x[2] for x in g if x[2] >= MIN_BIN)
            nb_ = sum(x[4] for x in g if x[4] >= MIN_BIN)
            mf = (sum(x[2] * x[3] for x in g if x[2] >= MIN_BIN) / nf) if nf else math.nan
            mb = (sum(x[4] * x[5] for x in g if x[4] >= MIN_BIN) / nb_) if nb_ else math.nan
            share = ((nf * mf * mf if nf else 0.0) + (nb_ * mb * mb if nb_ else 0.0)) / energy
            lo, hi = float(mags[g[0][0]]), float(mags[g[-1][0] + 1])
            rt = _range_text("speed", lo, hi, 0.0, float(mags[-1]), ctx.speed_unit)
            if nf and nb_:
                text = (f"{rt} the residual is {value_text(mf, unit, True)} moving forward "
                        f"and {value_text(mb, unit, True)} moving backward")
            else:  # one direction: say which, and that the other has no samples
                m, way, other = (mf, "forward", "backward") if nf else \
                    (mb, "backward", "forward")
                text = (f"{rt} the residual is {value_text(m, unit, True)} moving {way}, "
                        f"with no samples moving {other}")
            found.append(Region("speed", text, lo, hi, share, nf + nb_,
                                mean_forward=None if not nf else mf,
                                mean_backward=None if not nb_ else mb))
    # the other quantities: runs of notable bins of the same sign
    for qn in ("position", "current", "torque", "acceleration", "time"):
        bq = bins.get(qn)
        if bq is None:
            continue
        nbins = len(bq.count)
        runs: list[list[int]] = []
        for j in range(nbins):
            m = float(bq.mean[j])
            if not _notable(m, int(bq.count[j]), sd, rms, tau):
                continue
            if runs and runs[-1][-1] == j - 1 and np.sign(bq.mean[runs[-1][-1]]) == np.sign(m):
                runs[-1].append(j)
            else:
                runs.append([j])
        qr = []
        for run in runs:
            n = int(sum(bq.count[j] for j in run))
            m = float(sum(bq.count[j] * bq.mean[j] for j in run)) / n
            lo, hi = float(bq.edges[run[0]]), float(bq.edges[run[-1] + 1])
            rt = _range_text(qn, lo, hi, float(bq.edges[0]), float(bq.edges[-1]), bq.unit)
            text = f"{rt} the residual is {value_text(m, unit, True)}"
            if qn == "position" and ctx.axis == "rotary":
                text = text.replace("at positions", "at angles")
            qr.append(Region(qn, text, lo, hi, n * m * m / energy, n, mean=m))
        qr.sort(key=lambda x: -x.share)
        found.extend(qr[:3])
    found.sort(key=lambda x: -x.share)
    # one whole-range statement is enough (an offset shows in every quantity)
    out: list[Region] = []
    whole = False
    for reg in found:
        is_whole = ("every" in reg.text or "whole record" in reg.text)
        if is_whole and whole:
            continue
        whole = whole or is_whole
        out.append(reg)
    return tuple(out[:6])


# --------------------------------------------------------------------- order spectrum
def order_spectrum(ctx: RecordSamples, r: Sliced, used: B, unit: str) -> OrderSpectrum:
    assert ctx.angle_raw is not None
    K = ctx.max_order
    orders = spectrum_orders(K)
    amp, expl = harmonic_fit(ctx, r, used, orders)
    peaks = spectrum_peaks(orders, expl)
    shares = joint_shares(ctx, r, used, peaks)
    return OrderSpectrum(orders, amp, expl, peaks, unit, ctx.per, shares)


def spectrum_orders(max_order: int) -> F64:
    """Steps of 1/4 up to order 16 (fractional orders: gears, belts), integers above."""
    fine = np.arange(1, int(round(min(max_order, 16) / ORDER_STEP)) + 1) * ORDER_STEP
    coarse = np.arange(17, max_order + 1, dtype=np.float64)
    return np.concatenate([fine, coarse])


def _harmonic_blocks(ctx: RecordSamples, r: Sliced, filled_used: B, orders: F64,
                     mean_r: float) -> Iterator[tuple[F64, F64]]:
    """Per block of rows: the filtered columns ``F[sin q a]``, ``F[cos q a]`` of every
    order ``q`` (interleaved) on the used rows (``filled_used``: the used rows spread
    onto the filled record), and the residual less ``mean_r`` there.

    The columns are filtered on the filled record, as the pipeline filters its columns
    (the filter's state carried from block to block, reset at each segment); the
    residual (measured rows) is placed on the filled rows block by block.
    """
    real = ctx.selected.real
    qs = np.ascontiguousarray(orders, dtype=np.float64)
    m = len(qs)
    svf = SVF(ctx.cutoff_hz, ctx.dt, ctx.zeta, ctx.position_hold)
    m0 = 0  # measured rows before the block
    seg_starts = {sa for sa, _ in ctx.segments()}
    # the angle unwrapped again block by block (the blocks of each segment)
    for b0, b1, ang in ctx.angle_filled_blocks():
        if b0 in seg_starts:
            svf.reset()
        raw = np.empty((b1 - b0, 2 * m))
        # raw[i, 2j] = sin(q_j a_i), raw[i, 2j + 1] = cos(q_j a_i)
        _kernels.sincos(np.ascontiguousarray(ang, np.float64), qs, raw)
        f, _ = svf.process(raw)
        u = filled_used[b0:b1]
        if real is None:
            rb = r[b0:b1] - mean_r
        else:
            k = int(np.count_nonzero(real[b0:b1]))
            rb = np.zeros(b1 - b0)
            rb[real[b0:b1]] = r[m0:m0 + k] - mean_r
            m0 += k
        if u.any():
            yield f[u], rb[u]
        # freed before the next block's are made (one block's at a time)
        del raw, f, _


def harmonic_fit(ctx: RecordSamples, r: Sliced, used: B, orders: F64) -> tuple[F64, F64]:
    """Per order q: LS fit of r by a constant, F[sin q a] and F[cos q a].

    Returns the amplitude of the sine/cosine pair (output unit) and the share of the
    residual's variance (about its mean) it explains. The columns are built and filtered
    in blocks of rows (:func:`_harmonic_blocks`), so memory does not grow with the
    record; only sums over the used rows are kept.
    """
    assert ctx.angle_raw is not None
    amp = np.zeros(len(orders))
    expl = np.zeros(len(orders))
    # den: the centred residual's sum of squares over the used rows
    n_used, mean_r, _, den = moments(r, used)
    if n_used < 3:
        return amp, expl
    if den <= 0:
        return amp, expl
    filled_used = ctx.spread(used)
    chunk = 16  # orders at a time: BLOCK x 2 chunk float64 per working array
    for c0 in range(0, len(orders), chunk):
        qs = orders[c0:c0 + chunk]
        m = len(qs)
        # sums over the used rows: g, g g' (per order: ss, cc, sc), g r
        s1 = np.zeros(2 * m)
        ss = np.zeros(m)
        cc = np.zeros(m)
        sc = np.zeros(m)
        sr = np.zeros(m)
        cr = np.zeros(m)
        for G, ru in _harmonic_blocks(ctx, r, filled_used, qs, mean_r):
            gs, gc = G[:, 0::2], G[:, 1::2]
            s1 += G.sum(axis=0)
            ss += np.einsum("ij,ij->j", gs, gs)
            cc += np.einsum("ij,ij->j", gc, gc)
            sc += np.einsum("ij,ij->j", gs, gc)
            sr += gs.T @ ru
            cr += gc.T @ ru
        # centre the columns: sum (g - mean g)(h - mean h) = sum g h - n mean g mean h
        ms, mc = s1[0::2] / n_used, s1[1::2] / n_used
        ss -= n_used * ms * ms
        cc -= n_used * mc * mc
        sc -= n_used * ms * mc
        # normal equations per order: [[ss sc] [sc cc]] x = [sr cr]
        det = ss * cc - sc * sc
        ok = det > 1e-12 * np.maximum(ss * cc, 1e-300)
        xs = np.zeros(m)
        xc = np.zeros(m)
        xs[ok] = (cc[ok] * sr[ok] - sc[ok] * cr[ok]) / det[ok]
        xc[ok] = (ss[ok] * cr[ok] - sc[ok] * sr[ok]) / det[ok]
        amp[c0:c0 + chunk] = np.hypot(xs, xc)
        expl[c0:c0 + chunk] = np.clip((xs * sr + xc * cr) / den, 0.0, 1.0)
    return amp, expl


def joint_shares(ctx: RecordSamples, r: Sliced, used: B, peaks: Sequence[float]
                 ) -> tuple[float, ...]:
    """The share of the residual variance each of ``peaks`` explains beyond the peaks
    before it (fitted together: sequential, so the shares add up to the joint fit's,
    at most 1; an order that is leakage of a stronger one gets next to nothing).

    With G_k the centred filtered sin/cos columns of the first k peaks and
    x_k = (G_k' G_k)^-1 G_k' r, share_k = (x_k' G_k' r - x_{k-1}' G_{k-1}' r) / r'r.
    """
    if not peaks:
        return ()
    n_used, mean_r, _, den = moments(r, used)
    if n_used < 3 or den <= 0:
        return tuple(0.0 for _ in peaks)
    m2 = 2 * len(peaks)
    s1 = np.zeros(m2)
    A = np.zeros((m2, m2))
    g = np.zeros(m2)
    qs = np.asarray(peaks, np.float64)
    for G, ru in _harmonic_blocks(ctx, r, ctx.spread(used), qs, mean_r):
        s1 += G.sum(axis=0)
        A += G.T @ G
        g += G.T @ ru
    # centred: sum (g - mean g)(h - mean h) = sum g h - n mean g mean h
    A -= np.outer(s1, s1) / n_used
    out = []
    before = 0.0
    for k in range(1, len(peaks) + 1):
        Ak, gk = A[:2 * k, :2 * k], g[:2 * k]
        # x = A_k^+ g_k (least squares: a pair the others span gets nothing new)
        x = np.linalg.lstsq(Ak, gk, rcond=1e-10)[0]
        joint = min(max(float(x @ gk) / den, before), 1.0)
        out.append(joint - before)
        before = joint
    return tuple(out)


#: a peak of the order spectrum explains at least this share of the residual variance
#: (alone, and beyond the stronger peaks to be named as an order of its own)
PEAK_SHARE = 0.01


def spectrum_peaks(orders: F64, expl: F64, limit: int = 5) -> tuple[float, ...]:
    if not len(expl):
        return ()
    med = float(np.median(expl))
    out = []
    for j in range(len(expl)):
        e = expl[j]
        left = expl[j - 1] if j > 0 else -1.0
        right = expl[j + 1] if j + 1 < len(expl) else -1.0
        if e >= left and e >= right and e >= PEAK_SHARE and e >= 10.0 * med:
            out.append((float(e), float(orders[j])))
    out.sort(reverse=True)
    return tuple(o for _, o in out[:limit])


# ------------------------------------------------------------------------- excitation
def excitation_summary(ctx: RecordSamples, model: Model, used: B,
                       stribeck_speed: float | None) -> ExcitationSummary:
    """How the ``used`` rows excite the model, block by block (exact order statistics:
    :func:`percentiles`, :func:`median`; sums block by block); the time at low speed
    below twice ``stribeck_speed`` (None: not said)."""
    N = _true_rows(used)
    ws = stribeck_speed
    if not N:
        return ExcitationSummary(0.0, 0.0, 0, math.nan, math.nan, math.nan, math.nan,
                                 math.nan, None if ws is None else math.nan, None, None,
                                 ctx.speed_unit, ctx.per, ws)
    speed = ctx.speed
    vmax = percentiles(_Mapped(speed, np.abs), used, [99.0])[0]
    eps = max(model.coulomb_band, 0.01 * vmax)
    n_fwd = n_bwd = n_low = rev = 0
    last_sign = 0.0  # sign of the last sample beyond eps (0: none yet)
    s_sp = s_acc2 = 0.0
    sp_max = 0.0
    for a in _spans(len(speed)):
        u = used[a:a + BLOCK]
        sp = speed[a:a + BLOCK][u]
        if not len(sp):
            continue
        n_fwd += int(np.count_nonzero(sp > eps))
        n_bwd += int(np.count_nonzero(sp < -eps))
        sg = np.sign(sp[np.abs(sp) > eps])
        if len(sg):
            # reversals: sign changes, the previous block's last sign carried
            rev += int(np.count_nonzero(sg[1:] != sg[:-1])) + int(
                last_sign != 0.0 and sg[0] != last_sign)
            last_sign = float(sg[-1])
        # samples where the Stribeck shape exp(-(w/ws)^2) is more than e^-4
        if ws is not None:
            n_low += int(np.count_nonzero(np.abs(sp) < 2.0 * ws))
        s_sp += float(np.sum(sp))
        sp_max = max(sp_max, float(np.max(np.abs(sp))))
        acc = ctx.acceleration[a:a + BLOCK][u]
        s_acc2 += float(np.dot(acc, acc))
    mean = s_sp / N
    ss = 0.0
    for a in _spans(len(speed)):
        d = speed[a:a + BLOCK][used[a:a + BLOCK]] - mean
        ss += float(np.dot(d, d))
    # speed-sensor noise from the second differences of the measured speed (robust:
    # var(w[k+1] - 2 w[k] + w[k-1]) = 6 sigma^2 for white noise), through sF
    w = ctx.signals.speed
    assert w is not None, "a record without rows"  # the speed is every record's
    d2 = _SecondDifference(w)  # read in slices
    sigma_w = 1.4826 * median(d2) / math.sqrt(6.0) if len(d2) else 0.0
    h_sf = ctx.impulse(ctx.speed_hold, derivative=True)
    acc_noise = sigma_w * float(np.sqrt(np.dot(h_sf, h_sf)))
    revs = cov = None
    if ctx.angle is not None:
        # sum |diff angle| over the used rows, the previous block's last angle carried
        tot = 0.0
        prev: float | None = None
        for a in _spans(len(speed)):
            an = ctx.angle[a:a + BLOCK][used[a:a + BLOCK]]
            if not len(an):
                continue
            if prev is not None:
                tot += abs(float(an[0]) - prev)
            tot += float(np.sum(np.abs(np.diff(an))))
            prev = float(an[-1])
        revs = tot / (2 * math.pi) if N > 1 else 0.0
        lo, hi = _extremes(ctx.angle, used)
        cov = (hi - lo) / (2 * math.pi)
    return ExcitationSummary(
        forward=n_fwd / N, backward=n_bwd / N, reversals=rev, speed_mean=mean,
        speed_std=math.sqrt(ss / N), speed_max=sp_max,
        acceleration_rms=math.sqrt(s_acc2 / N),
        acceleration_noise=acc_noise, low_speed=None if ws is None else n_low / N,
        revolutions=revs, coverage=cov, speed_unit=ctx.speed_unit, per=ctx.per,
        stribeck_speed=ws)


# ------------------------------------------------------------------------- structure
def residual_structure(ctx: RecordSamples, r: Sliced, used: B, unit: str, h2: float,
               spectrum: OrderSpectrum | None,
               output: str = "current") -> tuple[StructureItem, ...]:
    """Structure of the residual ``r`` (``spectrum``: its order spectrum, if computed).

    The residual is not tested against the equation's own output signal (``output``):
    it holds the output's noise, so its bin means follow the output trivially.
    """
    out: list[StructureItem] = []
    n, mu, energy, ss = moments(r, used)
    if not n:
        return ()
    sd = math.sqrt(ss / n)
    if energy <= 0:
        return ()
    tau = 1.0 / h2 if h2 > 0 else 1.0
    share_mean = n * mu * mu / energy
    if share_mean >= MIN_STRUCTURE and abs(mu) >= 4 * sd / math.sqrt(n / tau):
        out.append(StructureItem("offset", f"a constant offset: mean residual "
                                           f"{value_text(mu, unit, True)}", share_mean))
    bins = all_bins(ctx, r, used, unit)
    words = {"speed": "speed-dependent", "position": "position-dependent",
             "current": "current-dependent", "torque": "torque-dependent",
             "acceleration": "acceleration-dependent",
             "time": "drifting in time"}
    for qn, b in bins.items():
        if b.share < MIN_STRUCTURE or qn == output:
            continue
        ok = b.count >= MIN_BIN
        c = b.centers[ok]
        m = b.mean[ok]
        jmin, jmax = int(np.argmin(m)), int(np.argmax(m))
        text = (f"{words[qn]}: the mean residual ranges from "
                f"{value_text(float(m[jmin]), unit, True)}"
                f" (at {c[jmin]:.3g} {b.unit}) to {value_text(float(m[jmax]), unit, True)} (at "
                f"{c[jmax]:.3g} {b.unit}); {share_text(b.share)} of the variance")
        out.append(StructureItem(qn, text, b.share))
    if ctx.angle_raw is not None:
        if spectrum is not None:
            orders, expl = spectrum.orders, spectrum.explained
        else:
            orders = spectrum_orders(ctx.max_order)
            _, expl = harmonic_fit(ctx, r, used, orders)
        for q in spectrum_peaks(orders, expl, 3):
            e = float(expl[int(np.argmin(np.abs(orders - q)))])
            if e < MIN_EXPLAINED:
                continue
            integer = abs(q - round(q)) < 1e-9
            tag = "" if not integer else (
                " (unbalance)" if round(q) == 1 else f" (cogging:{int(round(q))})")
            out.append(StructureItem(
                "periodic", f"periodic at order {q:g} per {ctx.per}{tag}: "
                            f"{share_text(e)} of the variance", e))
    out.sort(key=lambda s: -s.share)
    return tuple(out)
