/*
 * kernels_rls.h -- the float RLS block kernels, written once for both precisions.
 *
 * SPDX-License-Identifier: MIT
 *
 * Included twice by kernels.c: with REAL = double, RLS(name) = name##_f64 and with
 * REAL = float, RLS(name) = name##_f32. Every operation is in REAL: C evaluates float
 * operands in float (FLT_EVAL_METHOD == 0, checked in kernels.c) and no constant is
 * written as a double literal, so the float32 path rounds every operation to float32.
 * Built with -ffp-contract=off and without -ffast-math: no fused multiply-add, no
 * reassociation, so the results are reproducible bit for bit.
 *
 * Per sample, with lambda_k in {lambda, 1} (1 when the trace bound holds the step):
 *   eps   = y - phi' theta
 *   v     = P phi,   g = 1 / (lambda_k + phi' v)
 *   K     = g v
 *   theta = theta + K eps
 *   P     = (P - g v v') / lambda_k
 *
 * Symmetric form: element (i, j) is computed as (P[i][j] - g (v[i] v[j])) / lambda_k.
 * Element (j, i) takes the same operations on the same operands (v[i] v[j] == v[j] v[i]
 * exactly in IEEE arithmetic, and P[i][j] == P[j][i] by induction), so P stays
 * symmetric bit for bit: the same bits as computing the upper triangle and mirroring
 * it, but over whole contiguous rows (the loop vectorises), and the pass that writes
 * row i also accumulates P phi of the *next* sample (the next row of the block), which
 * saves a second pass over P. P phi is always summed over the rows of P in ascending
 * order, fused or not, so the result does not depend on how a stream is cut into
 * blocks (RLS.update runs a block of one row, RLS.run the whole block).
 *
 * Trace bound: the trace the step would give, (tr P - g |v|^2) / lambda, costs O(n)
 * from quantities at hand; when it exceeds trace_max the step is taken with
 * lambda_k = 1 (flag WINDUP). A non-finite error or phi' P phi rejects the row (flag
 * NONFINITE, state untouched); frozen computes the error only (flag FROZEN). A division
 * by zero gives inf as IEEE says (only a broken, non positive definite P gets there).
 *
 * Arrays (all C-contiguous, the caller checked the shapes):
 *   Phi (N, n), Y (N), theta (n), P (n, n), work (3, n), acc (2),
 *   eps_out (N), theta_out (N, n) when record, trace_out (N), flags_out (N).
 */

/* Trace of P summed in index order (the order the block kernels use). */
static REAL RLS(trace_of)(Py_ssize_t n, const REAL *P)
{
    REAL tr = (REAL)0;
    for (Py_ssize_t i = 0; i < n; i++)
        tr += P[i * n + i];
    return tr;
}

/* v = P' phi accumulated over the rows of P in ascending order. */
static void RLS(p_phi)(Py_ssize_t n, const REAL *P, const REAL *phi, REAL *v)
{
    for (Py_ssize_t i = 0; i < n; i++)
        v[i] = (REAL)0;
    for (Py_ssize_t j = 0; j < n; j++) {
        const REAL pj = phi[j];
        const REAL *Pj = P + j * n;
        for (Py_ssize_t i = 0; i < n; i++)
            v[i] += Pj[i] * pj;
    }
}

/* a' b summed in index order. */
static REAL RLS(dot)(Py_ssize_t n, const REAL *a, const REAL *b)
{
    REAL s = (REAL)0;
    for (Py_ssize_t i = 0; i < n; i++)
        s += a[i] * b[i];
    return s;
}

/* The flags of a row before its step: NONFINITE when the error or phi' P phi is not
 * finite (non-finite phi or y, or an overflow: the row is rejected, the state stays
 * untouched), FROZEN when the estimator is frozen (the error only). */
static uint8_t RLS(row_flags)(REAL eps, REAL s, int frozen)
{
    uint8_t flag = 0;
    if (!(isfinite(eps) && isfinite(s)))
        flag = FLAG_NONFINITE;
    if (frozen)
        flag |= FLAG_FROZEN;
    return flag;
}

/* The step's gain g and forgetting lambda_k (with il = 1 / lambda_k): g = 1/(lambda + s)
 * and lambda_k = lambda, unless the trace the step would give, (tr P - g q) / lambda,
 * exceeds trace_max: then lambda_k = 1, g = 1/(1 + s) and the flag WINDUP is returned.
 * q = |P phi|^2 (symmetric form) or (P phi)'(phi' P)' (literal form). */
static uint8_t RLS(gain)(REAL trP, REAL s, REAL q, REAL lam, REAL inv_lam, REAL trace_max,
                         REAL *g, REAL *lam_k, REAL *il)
{
    const REAL one = (REAL)1;
    *lam_k = lam;
    *il = inv_lam;
    /* g = 1 / (lambda + phi' P phi) */
    *g = one / (lam + s);
    /* tr P_new = (tr P - g q) / lambda */
    if ((trP - *g * q) * inv_lam > trace_max) {
        /* trace bound: take this step with lambda_k = 1 (no forgetting) */
        *lam_k = one;
        *il = one;
        *g = one / (one + s);
        return FLAG_WINDUP;
    }
    return 0;
}

/* The step's gain and estimate, and the noise accumulators: K = g P phi,
 * theta <- theta + K eps, V <- lambda_k V + eps e_post, W <- lambda_k W + 1. */
static void RLS(gain_step)(Py_ssize_t n, const REAL *v, REAL g, REAL lam_k, REAL eps,
                           REAL *K, REAL *theta, REAL *acc)
{
    /* K = P phi / (lambda + phi' P phi) */
    for (Py_ssize_t i = 0; i < n; i++)
        K[i] = g * v[i];
    /* theta <- theta + K eps */
    for (Py_ssize_t i = 0; i < n; i++)
        theta[i] += K[i] * eps;
    /* e_post = y - phi' theta_new = eps lambda / (lambda + phi' P phi) */
    const REAL e_post = eps * (lam_k * g);
    /* V <- lambda V + eps e_post   (the minimised weighted cost, exactly) */
    acc[0] = lam_k * acc[0] + eps * e_post;
    /* W <- lambda W + 1            (the sum of the weights) */
    acc[1] = lam_k * acc[1] + (REAL)1;
}

/* The outputs of row k: its error, trace of P, flags and (when recording) theta. */
static void RLS(put_row)(Py_ssize_t n, Py_ssize_t k, REAL eps, REAL trP, uint8_t flag,
                         int record, const REAL *theta, REAL *eps_out, REAL *trace_out,
                         uint8_t *flags_out, REAL *theta_out)
{
    eps_out[k] = eps;
    trace_out[k] = trP;
    flags_out[k] = flag;
    if (record)
        memcpy(theta_out + k * n, theta, (size_t)n * sizeof(REAL));
}

/* The symmetric update over the N rows of Phi; returns the number of rows applied.
 * Row i of P is computed as (P[i][j] - g (v[i] v[j])) / lambda_k for every j, so P
 * stays symmetric bit for bit, and the pass that writes row i also accumulates
 * P phi of the next row. */
static Py_ssize_t RLS(rls_block_symmetric)(
    Py_ssize_t N, Py_ssize_t n, const REAL *Phi, const REAL *Y, REAL *theta, REAL *P,
    REAL *work, REAL *acc, REAL lam, REAL trace_max, int frozen, int record,
    REAL *eps_out, REAL *theta_out, REAL *trace_out, uint8_t *flags_out)
{
    REAL *v = work;              /* P phi of this row */
    REAL *K = work + n;          /* gain of the last row */
    REAL *vn = work + 2 * n;     /* P phi of the next row, accumulated while P is updated */
    const REAL inv_lam = (REAL)1 / lam;
    REAL trP = RLS(trace_of)(n, P);
    Py_ssize_t applied = 0;
    if (N > 0)
        /* v = P phi */
        RLS(p_phi)(n, P, Phi, v);

    for (Py_ssize_t k = 0; k < N; k++) {
        const REAL *phi = Phi + k * n;
        /* eps = y - phi' theta */
        const REAL eps = Y[k] - RLS(dot)(n, phi, theta);
        /* s = phi' P phi */
        const REAL s = RLS(dot)(n, phi, v);
        uint8_t flag = RLS(row_flags)(eps, s, frozen);
        const int has_next = k + 1 < N;

        if (flag != 0) {
            memset(K, 0, (size_t)n * sizeof(REAL));
            if (has_next)
                /* v_next = P phi_next   (P unchanged) */
                RLS(p_phi)(n, P, Phi + (k + 1) * n, vn);
        } else {
            REAL g, lam_k, il;
            /* the trace bound with q = |P phi|^2 */
            flag = RLS(gain)(trP, s, RLS(dot)(n, v, v), lam, inv_lam, trace_max, &g, &lam_k,
                             &il);
            RLS(gain_step)(n, v, g, lam_k, eps, K, theta, acc);
            /* the next row's phi (on the last row: this row, the result is unused) */
            const REAL *phin = Phi + (has_next ? k + 1 : k) * n;
            memset(vn, 0, (size_t)n * sizeof(REAL));
            trP = (REAL)0;
            for (Py_ssize_t i = 0; i < n; i++) {
                const REAL vi = v[i];
                const REAL pni = phin[i];
                REAL *Pi = P + i * n;
                for (Py_ssize_t j = 0; j < n; j++) {
                    /* P <- (P - g (P phi)(P phi)') / lambda */
                    const REAL x = (Pi[j] - g * (vi * v[j])) * il;
                    Pi[j] = x;
                    /* v_next = P phi_next   (row i of the sum) */
                    vn[j] += x * pni;
                }
                trP += Pi[i];
            }
            applied++;
        }
        REAL *swap = v;
        v = vn;
        vn = swap;
        RLS(put_row)(n, k, eps, trP, flag, record, theta, eps_out, trace_out, flags_out,
                     theta_out);
    }
    return applied;
}

/* The textbook update, as written (kept for comparison): P phi and phi' P are formed
 * separately and differ once rounding has made P asymmetric. */
static Py_ssize_t RLS(rls_block_literal)(
    Py_ssize_t N, Py_ssize_t n, const REAL *Phi, const REAL *Y, REAL *theta, REAL *P,
    REAL *work, REAL *acc, REAL lam, REAL trace_max, int frozen, int record,
    REAL *eps_out, REAL *theta_out, REAL *trace_out, uint8_t *flags_out)
{
    REAL *v = work;              /* P phi */
    REAL *K = work + n;
    REAL *w = work + 2 * n;      /* (phi' P)' */
    const REAL inv_lam = (REAL)1 / lam;
    REAL trP = RLS(trace_of)(n, P);
    Py_ssize_t applied = 0;

    for (Py_ssize_t k = 0; k < N; k++) {
        const REAL *phi = Phi + k * n;
        /* eps = y - phi' theta */
        const REAL eps = Y[k] - RLS(dot)(n, phi, theta);
        /* v = P phi   (row dot products) */
        for (Py_ssize_t i = 0; i < n; i++)
            v[i] = RLS(dot)(n, P + i * n, phi);
        /* w' = phi' P */
        RLS(p_phi)(n, P, phi, w);
        /* s = phi' P phi */
        const REAL s = RLS(dot)(n, phi, v);
        uint8_t flag = RLS(row_flags)(eps, s, frozen);
        if (flag != 0) {
            memset(K, 0, (size_t)n * sizeof(REAL));
        } else {
            REAL g, lam_k, il;
            /* the trace bound with q = tr(v w') */
            flag = RLS(gain)(trP, s, RLS(dot)(n, v, w), lam, inv_lam, trace_max, &g, &lam_k,
                             &il);
            RLS(gain_step)(n, v, g, lam_k, eps, K, theta, acc);
            trP = (REAL)0;
            for (Py_ssize_t i = 0; i < n; i++) {
                const REAL Ki = K[i];
                REAL *Pi = P + i * n;
                for (Py_ssize_t j = 0; j < n; j++)
                    /* P <- (P - K phi' P) / lambda */
                    Pi[j] = (Pi[j] - Ki * w[j]) * il;
                trP += Pi[i];
            }
            applied++;
        }
        RLS(put_row)(n, k, eps, trP, flag, record, theta, eps_out, trace_out, flags_out,
                     theta_out);
    }
    return applied;
}
