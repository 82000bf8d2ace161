r"""How much the residual's colour inflates the parameters' standard deviations.

The RLS covariance :math:`\hat\sigma^2 P` assumes independent residuals. After the
state-variable filter they are not: noise on the output and on the columns leaves the
filter low-passed, so neighbouring residuals are correlated and ``N`` samples carry the
information of fewer. With the residual's autocorrelation :math:`\rho_l`, the variance of
a least-squares estimate grows by about

.. math::

    \kappa = 1 + 2\sum_{l=1}^{L}\rho_l \qquad (\kappa \ge 1),

the inverse of the effective share of samples :math:`N_{eff}/N`, with ``L`` the
filter's memory (its warm-up: five time constants). :class:`ResidualTail` keeps the
last ``window`` used rows :math:`(\varphi, y)`, so :math:`\rho_l` is measured on the
residual of the current estimate, :math:`r = y - \varphi^\top\theta`, when asked
(a publication, a fit result), never in the per-sample loop. It is carried across
blocks, so any cut of the stream gives the same value (live and offline alike).

What no sigma can make honest: a parameter the data cannot tell apart from the others
(Coulomb friction and an offset while the speed never reverses). Along that direction
the estimate is the ridge prior's, and its sigma is the prior's width scaled by the
residual noise, not knowledge. :func:`prior_share` measures, per parameter, the share
of its variance the prior still holds,

.. math::

    s_j = \alpha_j P_{jj} = \frac{\alpha_j}{\alpha_j + d_j}

(:math:`P_0 = \mathrm{diag}(1/\alpha_j)`, :math:`d_j` the information the data add to
parameter ``j`` once the others are estimated too); above :data:`MAX_PRIOR_SHARE` (the
data added less than ten times the prior's information, the test of
:meth:`canrls.estimation.rls.RLS.excitation` taken per parameter) the parameter is
reported as not identifiable from these data, beside its value and sigma.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np
import numpy.typing as npt

__all__ = ["MAX_PRIOR_SHARE", "ResidualTail", "prior_share"]

#: Share of a parameter's variance the prior may hold at most for the parameter to be
#: identified by the data: the data added at least ten times the prior's information.
MAX_PRIOR_SHARE = 1.0 / 11.0

F64 = npt.NDArray[np.float64]


class ResidualTail:
    """The last ``window`` used rows of one equation, for :meth:`inflation`.

    Parameters
    ----------
    n : number of columns
    lags : ``L``, the longest lag summed (the filter's memory in samples)
    window : rows kept (default ``64 L``, at least 256)
    """

    def __init__(self, n: int, lags: int, window: int | None = None) -> None:
        self.lags = max(1, int(lags))
        self.window = max(256, 64 * self.lags) if window is None else int(window)
        self._phi = np.zeros((self.window, n))
        self._y = np.zeros(self.window)
        self._next = 0      # ring position of the next row
        self.rows = 0       # rows held (<= window)

    def reset(self) -> None:
        self._next = 0
        self.rows = 0

    def push(self, phi: F64, y: F64) -> None:
        """Append used rows (normalised), oldest first."""
        k = len(y)
        if k >= self.window:
            phi, y, k = phi[-self.window:], y[-self.window:], self.window
        first = min(k, self.window - self._next)
        self._phi[self._next:self._next + first] = phi[:first]
        self._y[self._next:self._next + first] = y[:first]
        self._phi[:k - first] = phi[first:]
        self._y[:k - first] = y[first:]
        self._next = (self._next + k) % self.window
        self.rows = min(self.window, self.rows + k)

    def rescale(self, d: npt.NDArray[np.int64], dy: int) -> None:
        """The rows held in new units: column ``j`` times ``2**-d_j``, the output
        ``2**-dy`` (exact)."""
        self._phi = np.ldexp(self._phi, -d)
        self._y = np.ldexp(self._y, -int(dy))

    def _ordered(self) -> tuple[F64, F64]:
        if self.rows < self.window:
            return self._phi[:self.rows], self._y[:self.rows]
        order = np.r_[self._next:self.window, 0:self._next]
        return self._phi[order], self._y[order]

    def inflation(self, theta: F64) -> float:
        r"""``kappa`` of the residual of ``theta`` on the rows held (1 with fewer than
        ``4 L`` rows: too few to tell)."""
        L = self.lags
        if self.rows < 4 * L:
            return 1.0
        phi, y = self._ordered()
        # r = y - phi theta, about its mean
        r = y - phi @ theta
        r = r - r.mean()
        c0 = float(r @ r)
        if not c0 > 0.0:
            return 1.0
        # kappa = 1 + 2 sum_{l=1..L} rho_l,  rho_l = sum_k r_k r_{k-l} / sum_k r_k^2
        s = sum(float(r[lag:] @ r[:-lag]) for lag in range(1, L + 1))
        return max(1.0, 1.0 + 2.0 * s / c0)

    def state(self) -> dict[str, Any]:
        phi, y = self._ordered()
        return {"phi": phi.copy(), "y": y.copy()}

    def restore(self, d: Mapping[str, Any]) -> None:
        self.reset()
        phi = np.asarray(d["phi"], dtype=np.float64)
        y = np.asarray(d["y"], dtype=np.float64)
        if phi.ndim == 2 and phi.shape[1] == self._phi.shape[1] and len(y) == len(phi):
            self.push(phi, y)


def prior_share(P: npt.ArrayLike, ridge: npt.ArrayLike) -> F64:
    """``alpha_j P_jj`` of every parameter: 1 where the data said nothing about it (its
    value is the prior's), near 0 where the data alone determine it."""
    # s_j = alpha_j P_jj  (P0 = diag(1 / alpha_j))
    d = np.diag(np.asarray(P, dtype=np.float64)) * np.asarray(ridge, dtype=np.float64)
    return np.where(np.isfinite(d), d, 1.0)
