/*
 * sim.c -- canrls._sim: the simulated drive's loop (canrls.sim.plant.Plant.run).
 *
 * SPDX-License-Identifier: MIT
 *
 * Per control period: the sensors sample the state, the speed PI (and with the
 * electrical equation the current PI) set the current or the voltage, and the state
 * (theta, omega, i) is integrated over the period with RK4 in sub-steps (split further
 * near zero speed, where the friction's tanh is stiff). canrls.sim.plant documents the
 * equations and the vectors (p, gains, quant); this is that loop, the operations in the
 * order the Python wrote them (the equation beside each line), built with
 * -ffp-contract=off and without -ffast-math, and libm's tanh, exp, sin and cos: the
 * simulated logs are those of the numba kernel it replaces, bit for bit.
 *
 * min() and max() are Python's: max(a, b) is b only when b > a, min(a, b) b only when
 * b < a (a NaN in a stays).
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>

#include <math.h>
#include <stdint.h>

#include "pyargs.h"

/* indices into the parameter vector p (canrls.sim.plant: Truth._kernel_params) */
enum { P_J, P_B, P_TC, P_TS, P_WS, P_E, P_T0, P_USIN, P_UCOS, P_R, P_L, P_KE, P_KT, P_ASC,
       P_ELEC, P_COUNT };

static double py_max(double a, double b) { return b > a ? b : a; }
static double py_min(double a, double b) { return b < a ? b : a; }

/* The plant: the parameter vector and the cogging harmonics (orders ck, sine and
 * cosine amplitudes cs, cc). */
typedef struct {
    const double *p;
    Py_ssize_t m;
    const double *ck, *cs, *cc;
} Physics;

/* The derivative of (theta, omega, i) at (th, w, i) with the voltage u held. */
static inline void deriv(const Physics *ph, double th, double w, double i, double u,
                         double *dth, double *dw, double *di)
{
    const double *p = ph->p;
    const double ang = th * p[P_ASC];
    const double x = w / p[P_E];
    /* sgn_e(w) = tanh(w/e); tanh(x) rounds to exactly +-1.0 for |x| > 19.1 */
    const double sg = x > 20.0 ? 1.0 : (x < -20.0 ? -1.0 : tanh(x));
    /* load = B w + Tc sgn_e(w) + Ts sgn_e(w) exp(-(w/ws)^2) + T0 + unbalance + cogging */
    double load = p[P_B] * w + p[P_TC] * sg + p[P_T0];
    if (p[P_TS] != 0.0) {
        const double r = w / p[P_WS];
        if (r * r < 746.0) /* exp(-746) underflows to exactly 0 */
            load += p[P_TS] * sg * exp(-r * r);
    }
    if (p[P_USIN] != 0.0 || p[P_UCOS] != 0.0)
        load += p[P_USIN] * sin(ang) + p[P_UCOS] * cos(ang);
    for (Py_ssize_t j = 0; j < ph->m; j++) {
        const double a = ph->ck[j] * ang;
        load += ph->cs[j] * sin(a) + ph->cc[j] * cos(a);
    }
    *dth = w;
    /* J dw/dt = Kt i - load */
    *dw = (p[P_KT] * i - load) / p[P_J];
    /* L di/dt = u - R i - Ke w */
    *di = p[P_ELEC] != 0.0 ? (u - p[P_R] * i - p[P_KE] * w) / p[P_L] : 0.0;
}

/* One RK4 step of length h from (th, w, i), given the derivative (a1, b1, c1) there. */
static inline void rk4(const Physics *ph, double *th, double *w, double *i, double u,
                       double h, double a1, double b1, double c1)
{
    double a2, b2, c2, a3, b3, c3, a4, b4, c4;
    deriv(ph, *th + 0.5 * h * a1, *w + 0.5 * h * b1, *i + 0.5 * h * c1, u, &a2, &b2, &c2);
    deriv(ph, *th + 0.5 * h * a2, *w + 0.5 * h * b2, *i + 0.5 * h * c2, u, &a3, &b3, &c3);
    deriv(ph, *th + h * a3, *w + h * b3, *i + h * c3, u, &a4, &b4, &c4);
    /* x <- x + h/6 (k1 + 2 k2 + 2 k3 + k4) */
    *th = *th + h / 6.0 * (a1 + 2.0 * a2 + 2.0 * a3 + a4);
    *w = *w + h / 6.0 * (b1 + 2.0 * b2 + 2.0 * b3 + b4);
    *i = *i + h / 6.0 * (c1 + 2.0 * c2 + 2.0 * c3 + c4);
}

/* indices into the feedforward vector ffv (canrls.sim.plant: Compensation.kernel) */
enum { F_ON, F_SCALE, F_B, F_TC, F_TS, F_WS, F_E, F_IDX, F_LEAD, F_T0, F_COUNT };

/* The speed controller's feedforward (canrls tune): the map over the measured position
 * led by the measured speed times the loop's delay, theta_m + w_m T_lead (linear between
 * its points, periodic), and the friction at the speed reference, with an offset T0 the
 * map does not hold: tau_ff = map(theta_m) + T0 + B w_r + (Tc + Ts exp(-(w_r/ws)^2))
 * tanh(w_r/e), in current. */
static double feedforward(const double *f, const double *map, Py_ssize_t nmap, double pos,
                          double w_r)
{
    double tau = f[F_T0];
    if (nmap > 0) {
        /* x = pos N / period, reduced to [0, N) */
        double x = pos * f[F_IDX];
        x -= (double)nmap * floor(x / (double)nmap);
        Py_ssize_t j = (Py_ssize_t)floor(x);
        if (j >= nmap)
            j = nmap - 1;
        const double fr = x - (double)j;
        const Py_ssize_t j1 = j + 1 < nmap ? j + 1 : 0;
        /* map(x) = m_j + fr (m_{j+1} - m_j) */
        tau += map[j] + fr * (map[j1] - map[j]);
    }
    const double sg = tanh(w_r / f[F_E]);
    const double r = w_r / f[F_WS];
    tau += f[F_B] * w_r + f[F_TC] * sg + f[F_TS] * sg * exp(-r * r);
    return tau * f[F_SCALE];
}

/* x rounded to the nearest multiple of q (q <= 0: x itself) */
static inline double quantise(double x, double q)
{
    if (q <= 0.0)
        return x;
    return floor(x / q + 0.5) * q;
}

/* RK4 sub-steps between two looks at the signals (py_plant_run): a few milliseconds */
#define STEPS_PER_CHECK 100000

/* Advance control periods k0.. of n, stopping after the period in which the sub-steps
 * reach `budget`; returns the next period. st = [theta, omega, i, integ_w, integ_i] in
 * and out. noise (n, 3): the sensors' noise (current, speed, position), already scaled.
 * out (n, 9): i, omega, theta, u, i_meas, omega_meas, theta_meas, u_meas, i_ref. */
static Py_ssize_t plant_run(Py_ssize_t k0, Py_ssize_t n, int64_t budget, double dt,
                            int64_t nsub, double h_stiff, double *st, const Physics *ph,
                            const double *gains, const double *quant, const double *ffv,
                            const double *ffmap, Py_ssize_t nmap, const double *w_ref,
                            const double *a_ref, const double *noise, double *out)
{
    const int ff_on = ffv[F_ON] != 0.0;
    const double *p = ph->p;
    double th = st[0], w = st[1], i = st[2], integ_w = st[3], integ_i = st[4];
    const double kp_w = gains[0], ki_w = gains[1], jff = gains[2], kp_i = gains[3],
                 ki_i = gains[4], ke_ff = gains[5], i_max = gains[6], u_max = gains[7];
    const double q_i = quant[0], q_w = quant[1], q_th = quant[2], q_u = quant[3],
                 wrap = quant[4];
    const double m_wrap = q_th > 0.0 ? wrap / q_th : 1.0;
    const double kt = p[P_KT];
    const int elec = p[P_ELEC] != 0.0;
    const double h = dt / (double)nsub;
    /* zero-speed zone where the tanh makes the equation stiff: |w| < 10 e */
    const double zone = 10.0 * p[P_E];
    const int stiff = p[P_TC] != 0.0 || p[P_TS] != 0.0;
    const double h_min = dt * 1e-6;
    int64_t steps = 0;
    Py_ssize_t k = k0;
    for (; k < n && steps < budget; k++) {
        const double *nz = noise + 3 * k;
        double *o = out + 9 * k;
        /* ---- sensors at t_k (ideal source: i is the current over the coming period) */
        const double w_m = quantise(w + nz[1], q_w);
        double th_m = th + nz[2];
        if (q_th > 0.0) {
            /* wrap the count (exact in float for an integral counts-per-turn), then scale */
            double cnt = floor(th_m / q_th + 0.5);
            cnt -= m_wrap * floor(cnt / m_wrap);
            th_m = cnt * q_th;
        } else {
            th_m -= wrap * floor(th_m / wrap);
        }
        if (th_m >= wrap)
            th_m -= wrap;
        /* ---- speed PI + inertia feed-forward -> current reference */
        const double e = w_ref[k] - w_m;
        double i_un = jff * a_ref[k] / kt + kp_w * e + integ_w;
        if (ff_on) /* + tau_ff(theta_m, w_ref) / Kt; the position unwrapped, quantised */
            i_un += feedforward(ffv, ffmap, nmap,
                                quantise(th + nz[2], q_th) + w_m * ffv[F_LEAD], w_ref[k]);
        const double i_ref = py_min(py_max(i_un, -i_max), i_max);
        if (i_un == i_ref || (i_un > i_max && e < 0.0) || (i_un < -i_max && e > 0.0))
            integ_w += ki_w * e * dt;
        /* ---- current PI + back-EMF feed-forward -> voltage (or ideal current source) */
        double i_m, u, u_m;
        if (elec) {
            i_m = quantise(i + nz[0], q_i);
            const double ei = i_ref - i_m;
            const double u_un = kp_i * ei + integ_i + ke_ff * w_m;
            u = py_min(py_max(u_un, -u_max), u_max);
            if (u_un == u || (u_un > u_max && ei < 0.0) || (u_un < -u_max && ei > 0.0))
                integ_i += ki_i * ei * dt;
            u_m = quantise(u, q_u);
        } else {
            i = i_ref;
            i_m = quantise(i + nz[0], q_i);
            u = 0.0;
            u_m = 0.0;
        }
        o[0] = i;
        o[1] = w;
        o[2] = th;
        o[3] = u;
        o[4] = i_m;
        o[5] = w_m;
        o[6] = th_m;
        o[7] = u_m;
        o[8] = i_ref;
        /* ---- integrate the plant over [t_k, t_k + dt] with u (or i) held */
        double rem = dt;
        while (rem > 0.0) {
            double a1, b1, c1;
            deriv(ph, th, w, i, u, &a1, &b1, &c1);
            double hs = h;
            if (stiff) {
                /* bound on |domega/dt| over a sub-step (the current may move too) */
                const double acc = fabs(b1) + h * fabs(c1) * kt / p[P_J] + 1e-300;
                const double dist = fabs(w) - zone;
                if (dist < 3.0 * h * acc) {
                    /* at the friction's kink: omega moves by at most half a band per step,
                     * and h lambda <= 2 for the tanh's stiffness; approaching it: halve
                     * the distance per step */
                    hs = py_min(h_stiff, 0.5 * p[P_E] / acc);
                    if (dist > 0.0)
                        hs = py_max(hs, 0.5 * dist / acc);
                    hs = py_max(py_min(hs, h), h_min);
                }
            }
            if (hs >= rem - 1e-9 * dt)
                hs = rem;
            rk4(ph, &th, &w, &i, u, hs, a1, b1, c1);
            rem = hs == rem ? 0.0 : rem - hs;
            steps++;
        }
    }
    st[0] = th;
    st[1] = w;
    st[2] = i;
    st[3] = integ_w;
    st[4] = integ_i;
    return k;
}

/* ================================================================= Python glue */
PyDoc_STRVAR(plant_run_doc,
"plant_run(dt, nsub, h_stiff, st, p, ck, cs, cc, gains, quant, ffv, ffmap, w_ref, a_ref,\n"
"          noise, out, /)\n"
"--\n\n"
"Advance len(w_ref) control periods of the simulated drive (canrls.sim.plant), in place.\n\n"
"st (5,): [theta, omega, i, integ_w, integ_i], updated; p (15,): the physics;\n"
"ck, cs, cc (m,): cogging orders and amplitudes; gains (8,); quant (5,);\n"
"ffv (10,): the feedforward (ffv[0] = 0: none); ffmap (N,): its map over the position;\n"
"w_ref, a_ref (n,); noise (n, 3); out (n, 9) written (float64 throughout).");

static PyObject *py_plant_run(PyObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    (void)self;
    static const Spec spec[] = {
        {3, "st", F64, 1, RW}, {4, "p", F64, 1, RO}, {5, "ck", F64, 1, RO},
        {6, "cs", F64, 1, RO}, {7, "cc", F64, 1, RO}, {8, "gains", F64, 1, RO},
        {9, "quant", F64, 1, RO}, {10, "ffv", F64, 1, RO}, {11, "ffmap", F64, 1, RO},
        {12, "w_ref", F64, 1, RO}, {13, "a_ref", F64, 1, RO},
        {14, "noise", F64, 2, RO}, {15, "out", F64, 2, RW},
    };
    Args a = {.fn = "plant_run", .count = 0};
    Py_buffer *b[COUNT(spec)];
    double dt, h_stiff;
    int64_t nsub;
    PyObject *res = NULL;
    if (!start(&a, nargs, 16) || !as_double(args[0], &dt) || !as_int64(args[1], &nsub)
        || !as_double(args[2], &h_stiff))
        return NULL;
    if (nsub < 1) {
        PyErr_SetString(PyExc_ValueError, "plant_run: nsub must be >= 1");
        return NULL;
    }
    if (take(&a, args, spec, COUNT(spec), b, F64)) {
        const Py_ssize_t n = dim(b[9], 0), m = dim(b[2], 0), nmap = dim(b[8], 0);
        if (need(&a, b[0], "st", 5, -1) && need(&a, b[1], "p", P_COUNT, -1)
            && need(&a, b[3], "cs", m, -1) && need(&a, b[4], "cc", m, -1)
            && need(&a, b[5], "gains", 8, -1) && need(&a, b[6], "quant", 5, -1)
            && need(&a, b[7], "ffv", F_COUNT, -1)
            && need(&a, b[10], "a_ref", n, -1) && need(&a, b[11], "noise", n, 3)
            && need(&a, b[12], "out", n, 9)) {
            const Physics ph = {.p = D(b[1]), .m = m, .ck = D(b[2]), .cs = D(b[3]),
                                .cc = D(b[4])};
            /* in pieces of STEPS_PER_CHECK sub-steps, the signals looked at between them:
             * SIGTERM or SIGINT is acted on within milliseconds (the state carries
             * over exactly: the pieces change nothing) */
            Py_ssize_t k = 0;
            int stopped = 0;
            while (k < n && !stopped) {
                Py_BEGIN_ALLOW_THREADS
                k = plant_run(k, n, STEPS_PER_CHECK, dt, nsub, h_stiff, D(b[0]), &ph, D(b[5]),
                              D(b[6]), D(b[7]), D(b[8]), nmap, D(b[9]), D(b[10]), D(b[11]),
                              D(b[12]));
                Py_END_ALLOW_THREADS
                stopped = PyErr_CheckSignals() < 0;
            }
            res = stopped ? NULL : Py_NewRef(Py_None);
        }
    }
    release(&a);
    return res;
}

/* ================================================================== module */
static PyMethodDef methods[] = {
    {"plant_run", (PyCFunction)(void (*)(void))py_plant_run, METH_FASTCALL, plant_run_doc},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {
    PyModuleDef_HEAD_INIT,
    .m_name = "canrls._sim",
    .m_doc = "The simulated drive's loop (C, see src/canrls/c/host/sim.c).",
    .m_size = 0,
    .m_methods = methods,
};

PyMODINIT_FUNC PyInit__sim(void) { return PyModule_Create(&module); }
