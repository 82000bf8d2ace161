r"""How unlikely a drive's largest change or drift is for a healthy drive: the normal and
Student t tails of one test, and the family-wise p of many correlated tests (the
tests of a series are linear in its values, so their correlation is known exactly).
The method and its figures: docs/fleet.md, "Finding what changes".
"""

from __future__ import annotations

import math
from collections.abc import Iterable

import numpy as np
import numpy.typing as npt

__all__ = ["phi_tail", "t_equivalent", "t_tail", "tree_links", "both_beyond", "beyond",
           "family_p"]

F64 = npt.NDArray[np.float64]

#: Gauss-Legendre nodes and weights on [-1, 1] for :func:`both_beyond`
_GL = np.polynomial.legendre.leggauss(32)


def phi_tail(z: float) -> float:
    """2 Phi(-|z|)."""
    return math.erfc(abs(z) / math.sqrt(2.0))


def t_equivalent(t: float, dof: float) -> float:
    r"""Wallace's normal equivalent of a Student t with ``dof`` degrees of freedom,
    :math:`z = \sqrt{\nu \ln(1 + t^2/\nu)}\,(8\nu + 1)/(8\nu + 3)` (a z whose scale
    is itself estimated from few pairs has heavier tails)."""
    if not math.isfinite(dof):
        return abs(t)
    # z = sqrt(nu ln(1 + t^2 / nu)) (8 nu + 1) / (8 nu + 3)
    return math.sqrt(dof * math.log1p(t * t / dof)) * (8 * dof + 1) / (8 * dof + 3)


def t_tail(t: float, dof: float) -> float:
    """2 P(T > |t|) of a Student t with ``dof`` degrees of freedom (:func:`t_equivalent`)."""
    return phi_tail(t_equivalent(t, dof))


def tree_links(A: F64, v: F64) -> F64:
    r"""The correlations, in absolute value, that hold the tests ``z = A y`` of one
    series together: the edges of the maximum spanning tree of :math:`|R|`,
    :math:`R = A \operatorname{diag}(v) A^T` (each z has variance 1 for a healthy
    drive, :math:`\operatorname{Var} y = \operatorname{diag}(v)`; Prim's algorithm)."""
    # R = A diag(v) A^T
    R = np.abs((A * v) @ A.T)
    k = len(R)
    used = np.zeros(k, dtype=bool)
    used[0] = True
    key = R[0].copy()
    links = np.empty(k - 1)
    for e in range(k - 1):
        j = int(np.argmax(np.where(used, -1.0, key)))
        links[e] = key[j]
        used[j] = True
        key = np.maximum(key, R[j])
    return np.minimum(links, 1.0)


def both_beyond(c: float, rho: F64) -> F64:
    r""":math:`P(|Z_1| \ge c, |Z_2| \ge c)` of two standard normals of correlation
    ``rho``: :math:`2[U(\rho) + U(-\rho)]`, with Plackett's
    :math:`U(\rho) = P(Z_1 \ge c, Z_2 \ge c) = Q(c)^2 + \frac{1}{2\pi}
    \int_0^{\arcsin\rho} e^{-c^2/(1 + \sin\theta)}\,d\theta` (Gauss-Legendre)."""
    q = 0.5 * math.erfc(c / math.sqrt(2.0))
    x, wt = _GL
    out = np.zeros_like(rho)
    for sign in (1.0, -1.0):
        h = np.arcsin(sign * rho)[:, None] / 2.0  # half the interval [0, asin rho]
        theta = h * (x + 1.0)
        # U = Q^2 + 1/(2 pi) int_0^asin(rho) exp(-c^2 / (1 + sin theta)) dtheta
        u = q * q + (h * wt * np.exp(-c * c / (1.0 + np.sin(theta)))).sum(axis=1) \
            / (2.0 * math.pi)
        out += 2.0 * np.maximum(u, 0.0)
    return out


def beyond(c: float, tests: int, links: F64) -> float:
    r"""An upper bound of the probability that any of a healthy series' ``tests``
    reaches :math:`|z| \ge c`: Hunter and Worsley's
    :math:`\sum_i P(|z_i| \ge c) - \sum_{(i, j) \in T} P(|z_i| \ge c, |z_j| \ge c)`,
    T the maximum spanning tree of the tests' correlations (``links``,
    :func:`tree_links`)."""
    if tests == 0:
        return 0.0
    q = phi_tail(c)
    # P(max |z| >= c) <= k q - sum_T P(|z_i| >= c, |z_j| >= c)
    bound = tests * q - float(both_beyond(c, links).sum())
    return min(1.0, max(q, bound))


def family_p(c: float, series: Iterable[tuple[int, F64]]) -> float:
    r"""The family-wise p of a normal-equivalent :math:`|z| = c` over every test of a
    drive's series (``(tests, links)`` each): :math:`1 - \prod_s (1 - P_s)`,
    :math:`P_s` each series' bound (:func:`beyond`; the product holds for correlated
    series too, by the Gaussian correlation inequality)."""
    # p = 1 - prod_s (1 - P_s(max |z| >= c))
    return -math.expm1(sum(math.log1p(-min(beyond(c, k, links), 1.0 - 1e-16))
                           for k, links in series))
