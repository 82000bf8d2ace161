r"""Compiled kernels of the float recursive least squares (private).

:class:`canrls.estimation.rls.RLS` owns the state and validates every argument; these
functions only run the recursion over a block of samples, in place, on
preallocated arrays and plain scalars. ``RLS.update`` calls its kernel
(:func:`rls_block_symmetric`, or :func:`rls_block_literal` for comparison) with a
block of one row, ``RLS.run`` with the whole block, so both execute the same
machine code, and the result does not depend on how a stream is cut into
blocks (every quantity carried from one row to the next is computed by the same
operations in the same order whether or not a block boundary falls between them).

Precision: numba specialises on the dtype of the arrays and scalars. For the
float32 path every array *and* the scalars ``lam`` and ``trace_max`` are float32,
and the kernels never write a float literal (a literal ``1.0`` is float64 and
would promote the arithmetic): the constants are derived from ``lam`` instead
(``zero = lam - lam``, ``one = lam / lam``, both exact). No ``fastmath``: the
compiler may not reassociate or contract, so results are reproducible bit for bit.
``error_model="numpy"`` makes a division by zero give ``inf`` as IEEE says
instead of raising (only a broken, non positive definite ``P`` can get there).

Per sample, with :math:`\lambda_k \in \{\lambda, 1\}` (1 when the trace bound
holds the step, see below):

.. math::

    \varepsilon &= y - \varphi^\top\theta \\
    v &= P\varphi, \quad g = 1 / (\lambda_k + \varphi^\top v) \\
    K &= g\, v \\
    \theta &\leftarrow \theta + K\varepsilon \\
    P &\leftarrow (P - g\, v v^\top) / \lambda_k

Symmetric form: element :math:`(i, j)` is computed as
``(P[i, j] - g * (v[i] * v[j])) * (1/lambda)``. Element :math:`(j, i)` takes the
same operations on the same operands (``v[i] * v[j] == v[j] * v[i]`` exactly in
IEEE arithmetic, and ``P[i, j] == P[j, i]`` by induction), so ``P`` stays
symmetric bit for bit: the same bits as computing the upper triangle and
mirroring it, but with whole contiguous rows the loop vectorises (at n = 8 it
measured about twice as fast as the triangle and the strided mirror), and the pass
that writes row ``i`` also accumulates ``P phi`` of the *next* sample (the next
row of the block), which saves a second pass over ``P``. ``P phi`` is always
summed over the rows of ``P`` in ascending order, fused or not.

Trace bound: the trace the step would give, :math:`(\mathrm{tr}P - g|v|^2)/\lambda`,
costs O(n) from quantities already at hand. When it exceeds ``trace_max`` the
step is taken with :math:`\lambda_k = 1` (forgetting switched off for that step,
flag ``WINDUP``): still an exact RLS step, just without forgetting, so the
directions that are not excited keep their uncertainty instead of winding up.
"""

from __future__ import annotations

import numba
import numpy as np

__all__ = [
    "FLAG_WINDUP",
    "FLAG_FROZEN",
    "FLAG_NONFINITE",
    "KERNELS",
    "rls_block_symmetric",
    "rls_block_literal",
    "trace_of",
]

# Flag bits; the same values as canrls.estimation.rls.RLSFlag (checked by a test).
FLAG_WINDUP = 1
FLAG_FROZEN = 8
FLAG_NONFINITE = 16

_JIT = {"cache": True, "error_model": "numpy", "nogil": True}


@numba.njit(**_JIT)
def trace_of(P: np.ndarray, zero: float) -> float:  # pragma: no cover - compiled
    """Trace of ``P`` summed in index order (the order the block kernels use)."""
    tr = zero
    for i in range(P.shape[0]):
        tr += P[i, i]
    return tr


@numba.njit(**_JIT)
def _p_phi(P: np.ndarray, phi: np.ndarray, v: np.ndarray, zero: float) -> None:  # pragma: no cover
    """``v = P' phi`` accumulated over the rows of ``P`` in ascending order."""
    n = v.shape[0]
    for i in range(n):
        v[i] = zero
    for j in range(n):
        pj = phi[j]
        for i in range(n):
            v[i] += P[j, i] * pj


@numba.njit(**_JIT)
def rls_block_symmetric(
    Phi: np.ndarray,
    Y: np.ndarray,
    theta: np.ndarray,
    P: np.ndarray,
    work: np.ndarray,
    acc: np.ndarray,
    lam: float,
    trace_max: float,
    frozen: bool,
    record: bool,
    eps_out: np.ndarray,
    theta_out: np.ndarray,
    trace_out: np.ndarray,
    flags_out: np.ndarray,
) -> int:  # pragma: no cover - compiled
    r"""Run the symmetric RLS update over the rows of ``Phi``, updating the state in place.

    Parameters
    ----------
    Phi : ndarray, shape (N, n), C-contiguous
        Regressor rows :math:`\varphi_k^\top`.
    Y : ndarray, shape (N,)
        Targets :math:`y_k`.
    theta : ndarray, shape (n,)
        Parameter estimate, updated in place.
    P : ndarray, shape (n, n), C-contiguous
        Covariance-like matrix, exactly symmetric, updated in place.
    work : ndarray, shape (3, n)
        Scratch. On return ``work[1]`` holds the gain :math:`K` of the last row
        (zeros if that row was not applied).
    acc : ndarray, shape (2,)
        Noise accumulators ``[V, W]``: the minimised weighted cost
        :math:`V \leftarrow \lambda_k V + \varepsilon e_{post}` and the weight sum
        :math:`W \leftarrow \lambda_k W + 1`, updated in place.
    lam, trace_max : scalar of the state dtype
        Forgetting factor :math:`\lambda` and trace bound.
    frozen : bool
        Compute :math:`\varepsilon` only; the state stays untouched.
    record : bool
        Write ``theta`` after each row into ``theta_out`` (shape (N, n)); when
        false ``theta_out`` may have zero rows.
    eps_out, trace_out : ndarray, shape (N,)
        A-priori error and trace of ``P`` after each row.
    flags_out : ndarray of uint8, shape (N,)
        ``FLAG_*`` bits of each row.

    Returns
    -------
    int
        Number of rows that updated the state.
    """
    n = theta.shape[0]
    N = Phi.shape[0]
    K = work[1]
    v = work[0]  # P phi of this row
    vn = work[2]  # P phi of the next row, accumulated while P is updated
    # Constants in the state dtype (a float literal would be float64).
    zero = lam - lam
    one = lam / lam
    inv_lam = one / lam
    trP = trace_of(P, zero)
    applied = 0
    if N > 0:
        # v = P phi
        _p_phi(P, Phi[0], v, zero)

    for k in range(N):
        phi = Phi[k]
        # eps = y - phi' theta
        yhat = zero
        for j in range(n):
            yhat += phi[j] * theta[j]
        eps = Y[k] - yhat
        # s = phi' P phi
        s = zero
        for i in range(n):
            s += phi[i] * v[i]

        flag = 0
        if not (np.isfinite(eps) and np.isfinite(s)):
            # non-finite phi or y (or overflow): reject, state untouched
            flag = FLAG_NONFINITE
        if frozen:
            flag |= FLAG_FROZEN
        has_next = k + 1 < N

        if flag != 0:
            for i in range(n):
                K[i] = zero
            if has_next:
                # v_next = P phi_next   (P unchanged)
                _p_phi(P, Phi[k + 1], vn, zero)
        else:
            lam_k = lam
            il = inv_lam
            # g = 1 / (lambda + phi' P phi)
            g = one / (lam + s)
            # tr P_new = (tr P - g |P phi|^2) / lambda
            vv = zero
            for i in range(n):
                vv += v[i] * v[i]
            if (trP - g * vv) * inv_lam > trace_max:
                # trace bound: take this step with lambda_k = 1 (no forgetting)
                lam_k = one
                il = one
                g = one / (one + s)
                flag = FLAG_WINDUP
            # K = P phi / (lambda + phi' P phi)
            for i in range(n):
                K[i] = g * v[i]
            # theta <- theta + K eps
            for i in range(n):
                theta[i] += K[i] * eps
            # the next row's phi (on the last row: this row, the result is unused)
            phin = Phi[k + 1 if has_next else k]
            for i in range(n):
                vn[i] = zero
            trP = zero
            for i in range(n):
                vi = v[i]
                pni = phin[i]
                for j in range(n):
                    # P <- (P - g (P phi)(P phi)') / lambda
                    x = (P[i, j] - g * (vi * v[j])) * il
                    P[i, j] = x
                    # v_next = P phi_next   (row i of the sum)
                    vn[j] += x * pni
                trP += P[i, i]
            # e_post = y - phi' theta_new = eps lambda / (lambda + phi' P phi)
            e_post = eps * (lam_k * g)
            # V <- lambda V + eps e_post   (the minimised weighted cost, exactly)
            acc[0] = lam_k * acc[0] + eps * e_post
            # W <- lambda W + 1            (the sum of the weights)
            acc[1] = lam_k * acc[1] + one
            applied += 1
        v, vn = vn, v

        eps_out[k] = eps
        trace_out[k] = trP
        flags_out[k] = flag
        if record:
            for i in range(n):
                theta_out[k, i] = theta[i]
    return applied


@numba.njit(**_JIT)
def rls_block_literal(
    Phi: np.ndarray,
    Y: np.ndarray,
    theta: np.ndarray,
    P: np.ndarray,
    work: np.ndarray,
    acc: np.ndarray,
    lam: float,
    trace_max: float,
    frozen: bool,
    record: bool,
    eps_out: np.ndarray,
    theta_out: np.ndarray,
    trace_out: np.ndarray,
    flags_out: np.ndarray,
) -> int:  # pragma: no cover - compiled
    """The textbook update, as written; arguments of :func:`rls_block_symmetric`.

    Kept for comparison: here ``P phi`` and ``phi' P`` are formed separately and
    differ once rounding has made ``P`` asymmetric; the asymmetry grows with
    windup (see :mod:`canrls.estimation.rls`).
    """
    n = theta.shape[0]
    N = Phi.shape[0]
    v = work[0]  # P phi
    K = work[1]
    w = work[2]  # (phi' P)'
    zero = lam - lam
    one = lam / lam
    inv_lam = one / lam
    trP = trace_of(P, zero)
    applied = 0

    for k in range(N):
        phi = Phi[k]
        # eps = y - phi' theta
        yhat = zero
        for j in range(n):
            yhat += phi[j] * theta[j]
        eps = Y[k] - yhat
        # v = P phi
        for i in range(n):
            a = zero
            for j in range(n):
                a += P[i, j] * phi[j]
            v[i] = a
        # w' = phi' P
        _p_phi(P, phi, w, zero)
        # s = phi' P phi
        s = zero
        for i in range(n):
            s += phi[i] * v[i]

        flag = 0
        if not (np.isfinite(eps) and np.isfinite(s)):
            flag = FLAG_NONFINITE
        if frozen:
            flag |= FLAG_FROZEN
        if flag != 0:
            for i in range(n):
                K[i] = zero
        else:
            lam_k = lam
            il = inv_lam
            # g = 1 / (lambda + phi' P phi)
            g = one / (lam + s)
            # tr P_new = (tr P - g tr(v w')) / lambda
            vw = zero
            for i in range(n):
                vw += v[i] * w[i]
            if (trP - g * vw) * inv_lam > trace_max:
                lam_k = one
                il = one
                g = one / (one + s)
                flag = FLAG_WINDUP
            # K = P phi / (lambda + phi' P phi)
            for i in range(n):
                K[i] = g * v[i]
            # theta <- theta + K eps
            for i in range(n):
                theta[i] += K[i] * eps
            trP = zero
            for i in range(n):
                Ki = K[i]
                for j in range(n):
                    # P <- (P - K phi' P) / lambda
                    P[i, j] = (P[i, j] - Ki * w[j]) * il
                trP += P[i, i]
            # e_post = eps lambda / (lambda + phi' P phi) ; V, W as in the symmetric form
            e_post = eps * (lam_k * g)
            acc[0] = lam_k * acc[0] + eps * e_post
            acc[1] = lam_k * acc[1] + one
            applied += 1

        eps_out[k] = eps
        trace_out[k] = trP
        flags_out[k] = flag
        if record:
            for i in range(n):
                theta_out[k, i] = theta[i]
    return applied


#: The block kernel of each ``RLS(update=...)``. The estimator picks its kernel
#: once, so only the kernels in use are compiled (about 2 s each, then cached).
KERNELS = {"symmetric": rls_block_symmetric, "literal": rls_block_literal}
