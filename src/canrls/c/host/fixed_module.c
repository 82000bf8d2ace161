/*
 * fixed_module.c -- canrls._fixed: the C kernel (canrls_fixed.c) as a CPython extension.
 *
 * SPDX-License-Identifier: MIT
 *
 * run_block() runs canrls_update_q31() over a block of rows with the state of a Python
 * FixedRLS (symmetric update), taking every array through the buffer protocol (no numpy
 * C API): the int64 arrays of FixedRLS are converted to the kernel's instance on entry
 * and written back on exit. It computes what canrls.estimation.fixed.kernels.fixed_block
 * computes (mode symmetric), bit for bit (tests/firmware/test_fixed_ext.py). round_saturate()
 * rounds the float inputs to their words before (FixedRLS.quantize_block).
 *
 * PLAN_FIELDS (a tuple of names) is the order in which run_block() reads the plan
 * vector: FixedRLS builds it from its named constants, so the two cannot drift.
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>

#include <math.h>
#include <string.h>

#include "canrls_fixed.h"

#define COUNT_FIELD(name) +1
enum { NPLAN = 0 CANRLS_PLAN_FIELDS(COUNT_FIELD) };

/* a buffer of `count` items of `itemsize` bytes, C-contiguous (writable if asked) */
static int get_buf(PyObject *obj, Py_buffer *b, Py_ssize_t itemsize, Py_ssize_t count,
                   int writable, const char *name)
{
    if (PyObject_GetBuffer(obj, b, PyBUF_C_CONTIGUOUS | (writable ? PyBUF_WRITABLE : 0))
        != 0) {
        return -1;
    }
    if (b->itemsize != itemsize || b->len != itemsize * count) {
        PyErr_Format(PyExc_ValueError, "%s: expected %zd items of %zd bytes, got %zd bytes",
                     name, count, itemsize, b->len);
        PyBuffer_Release(b);
        return -1;
    }
    return 0;
}

static int32_t clamp_in(int64_t x, int32_t lo, int32_t hi, int64_t *n)
{
    if (x > hi) {
        *n += 1;
        return hi;
    }
    if (x < lo) {
        *n += 1;
        return lo;
    }
    return (int32_t)x;
}

PyDoc_STRVAR(run_block_doc,
"run_block(Phi, Y, theta, theta_frac, P, P_frac, scale, K, counts, plan, frozen, eps,\n"
"          theta_out, trace, exp, flags) -> applied\n\n"
"canrls_update_q31 over the N rows of Phi (int64, N x n) and Y (int64, N): theta (int64,\n"
"n), theta_frac (int64, n, 0..2^32-1), P and P_frac (int64, n x n, upper triangle; P_frac\n"
"-2^31..2^31-1), scale (int64, [e, c]), K (int64, n) and counts (int64, NSITES) updated\n"
"in place; plan: int64 in PLAN_FIELDS order; eps, trace, exp (int64, N) and flags\n"
"(uint8, N) written; theta_out (int64, N x n) or None.");

static PyObject *run_block(PyObject *self, PyObject *args)
{
    PyObject *o[15];
    Py_buffer b[15];
    int nb = 0;
    int frozen;
    PyObject *result = NULL;
    canrls_plan_q31 plan;
    canrls_rls_q31 S;
    Py_ssize_t N, n, k, i, j, m;
    const int64_t *pv, *Phi, *Y;
    int64_t *theta, *thf, *P, *Pf, *scale, *K, *counts, *eps, *tho = NULL, *trace, *ex;
    uint8_t *flags;
    int32_t p0[CANRLS_N_MAX], th32[CANRLS_N_MAX], Pup[CANRLS_TRI(CANRLS_N_MAX)],
        Pfup[CANRLS_TRI(CANRLS_N_MAX)];
    uint32_t tf32[CANRLS_N_MAX];
    int32_t phi[CANRLS_N_MAX];
    int64_t c_phi = 0, c_y = 0;
    long applied = 0;
    (void)self;

    memset(o, 0, sizeof o);
    /* o[13]: theta_frac (the fourth argument), o[14]: P_frac (the sixth) */
    if (!PyArg_ParseTuple(args, "OOOOOOOOOOpOOOOO:run_block", &o[0], &o[1], &o[2], &o[13],
                          &o[3], &o[14], &o[4], &o[5], &o[6], &o[7], &frozen, &o[8], &o[9],
                          &o[10], &o[11], &o[12])) {
        return NULL;
    }
    /* theta gives n, Y gives N */
    if (PyObject_GetBuffer(o[2], &b[nb], PyBUF_C_CONTIGUOUS | PyBUF_WRITABLE) != 0) {
        return NULL;
    }
    n = b[nb].len / 8;
    PyBuffer_Release(&b[nb]);
    if (PyObject_GetBuffer(o[1], &b[nb], PyBUF_C_CONTIGUOUS) != 0) {
        return NULL;
    }
    N = b[nb].len / 8;
    PyBuffer_Release(&b[nb]);
    if (n < 1 || n > CANRLS_N_MAX) {
        PyErr_Format(PyExc_ValueError, "n = %zd outside 1..%d", n, CANRLS_N_MAX);
        return NULL;
    }
    {
        /* the buffers: argument index, item size, item count, writable, name */
        const struct { int idx, size; Py_ssize_t count; int w; const char *name; } spec[] = {
            {0, 8, N * n, 0, "Phi"},   {1, 8, N, 0, "Y"},
            {2, 8, n, 1, "theta"},     {3, 8, n * n, 1, "P"},
            {4, 8, 2, 1, "scale"},     {5, 8, n, 1, "K"},
            {6, 8, CANRLS_NSITES, 1, "counts"}, {7, 8, NPLAN, 0, "plan"},
            {8, 8, N, 1, "eps"},       {9, 8, N * n, 1, "theta_out"},
            {10, 8, N, 1, "trace"},    {11, 8, N, 1, "exp"},
            {12, 1, N, 1, "flags"},    {13, 8, n, 1, "theta_frac"},
            {14, 8, n * n, 1, "P_frac"},
        };
        void *ptr[15];
        int k2;
        for (k2 = 0; k2 < 15; k2++) {
            ptr[k2] = NULL;
            if (spec[k2].idx == 9 && o[9] == Py_None) {
                continue; /* theta_out: None when not recorded */
            }
            if (get_buf(o[spec[k2].idx], &b[nb], spec[k2].size, spec[k2].count, spec[k2].w,
                        spec[k2].name) != 0) {
                goto done;
            }
            ptr[k2] = b[nb++].buf;
        }
        Phi = ptr[0];
        Y = ptr[1];
        theta = ptr[2];
        P = ptr[3];
        scale = ptr[4];
        K = ptr[5];
        counts = ptr[6];
        pv = ptr[7];
        eps = ptr[8];
        tho = ptr[9];
        trace = ptr[10];
        ex = ptr[11];
        flags = ptr[12];
        thf = ptr[13];
        Pf = ptr[14];
    }

    /* the plan, field by field; every value must fit its field */
    k = 0;
#define SET_FIELD(name)                                                          \
    plan.name = pv[k];                                                           \
    if ((int64_t)plan.name != pv[k]) {                                           \
        PyErr_Format(PyExc_ValueError, "plan field %s out of range", #name);     \
        goto done;                                                               \
    }                                                                            \
    k++;
    CANRLS_PLAN_FIELDS(SET_FIELD)
#undef SET_FIELD

    /* the instance from the Python state: diag(P) then the full checkpoint */
    m = 0;
    for (i = 0; i < n; i++) {
        p0[i] = (int32_t)P[i * n + i];
        th32[i] = (int32_t)theta[i];
        if (thf[i] < 0 || thf[i] > (int64_t)0xFFFFFFFF) {
            PyErr_SetString(PyExc_ValueError, "theta_frac outside 0..2^32-1");
            goto done;
        }
        tf32[i] = (uint32_t)thf[i];
        for (j = i; j < n; j++) {
            if (Pf[i * n + j] < INT32_MIN || Pf[i * n + j] > INT32_MAX) {
                PyErr_SetString(PyExc_ValueError, "P_frac outside -2^31..2^31-1");
                goto done;
            }
            Pfup[m] = (int32_t)Pf[i * n + j];
            Pup[m++] = (int32_t)P[i * n + j];
        }
    }
    if (canrls_init_q31(&S, &plan, (uint32_t)n, p0, (int32_t)scale[0]) != CANRLS_OK
        || canrls_restore_q31(&S, th32, tf32, Pup, Pfup, (int32_t)scale[0], (int32_t)scale[1])
               != CANRLS_OK) {
        PyErr_SetString(PyExc_ValueError, "state outside the words of the plan");
        goto done;
    }
    S.frozen = (uint32_t)frozen;

    /* the rows touch only the buffers held above: other threads (the daemon's bus
     * reader) run meanwhile */
    Py_BEGIN_ALLOW_THREADS
    for (k = 0; k < N; k++) {
        canrls_step_q31 st;
        const int64_t before = c_phi + c_y;
        /* phi, y <- sat(phi), sat(y): the int64 inputs clamped here, counted */
        for (j = 0; j < n; j++) {
            phi[j] = clamp_in(Phi[k * n + j], plan.phi_lo, plan.phi_hi, &c_phi);
        }
        applied += canrls_update_q31(&S, phi, clamp_in(Y[k], plan.y_lo, plan.y_hi, &c_y),
                                     &st);
        eps[k] = st.eps;
        trace[k] = st.trace;
        ex[k] = st.e;
        flags[k] = (uint8_t)(st.flags | (c_phi + c_y > before ? CANRLS_FLAG_SATURATION : 0u));
        if (tho != NULL) {
            for (j = 0; j < n; j++) {
                tho[k * n + j] = canrls_theta_q31(&S, (uint32_t)j);
            }
        }
    }
    Py_END_ALLOW_THREADS

    /* the state back into the Python arrays (P, P_frac: the upper triangle only) */
    m = 0;
    for (i = 0; i < n; i++) {
        theta[i] = canrls_theta_q31(&S, (uint32_t)i);
        thf[i] = canrls_theta_frac_q31(&S, (uint32_t)i);
        K[i] = S.K[i];
        for (j = i; j < n; j++) {
            Pf[i * n + j] = canrls_P_frac_q31(&S, (size_t)m);
            P[i * n + j] = canrls_P_q31(&S, (size_t)m++);
        }
    }
    scale[0] = S.e;
    scale[1] = S.c;
    for (i = 0; i < CANRLS_NSITES; i++) {
        counts[i] += S.counts[i];
    }
    counts[CANRLS_S_PHI_IN] += c_phi;
    counts[CANRLS_S_Y_IN] += c_y;
    result = PyLong_FromLong(applied);

done:
    while (nb > 0) {
        PyBuffer_Release(&b[--nb]);
    }
    return result;
}

PyDoc_STRVAR(round_saturate_doc,
"round_saturate(x, scale, lo, hi, out) -> int\n\n"
"out = clip(floor(x * scale + 1/2), lo, hi) for the float64 items of x into the int64\n"
"items of out (as many); the number clamped, or -1 (out untouched) when x holds a NaN.\n"
"The inputs of the fixed-point RLS rounded to their words\n"
"(canrls.estimation.fixed.estimator._round_saturate).");

static PyObject *round_saturate(PyObject *self, PyObject *args)
{
    PyObject *xo, *outo;
    double scale, lo, hi;
    Py_buffer xb, ob;
    Py_ssize_t N, k, nsat = -1;
    (void)self;
    if (!PyArg_ParseTuple(args, "OdddO:round_saturate", &xo, &scale, &lo, &hi, &outo)) {
        return NULL;
    }
    if (PyObject_GetBuffer(xo, &xb, PyBUF_C_CONTIGUOUS) != 0) {
        return NULL;
    }
    if (xb.itemsize != 8) {
        PyErr_SetString(PyExc_ValueError, "round_saturate: x must hold float64 items");
        PyBuffer_Release(&xb);
        return NULL;
    }
    N = xb.len / 8;
    if (get_buf(outo, &ob, 8, N, 1, "out") != 0) {
        PyBuffer_Release(&xb);
        return NULL;
    }
    {
        const double *x = xb.buf;
        int64_t *out = ob.buf;
        Py_BEGIN_ALLOW_THREADS
        for (k = 0; k < N && !isnan(x[k]); k++) {
        }
        if (k == N) {
            nsat = 0;
            for (k = 0; k < N; k++) {
                /* round half up: floor(x 2^frac + 1/2), then saturate to the word, counted */
                double v = floor(x[k] * scale + 0.5);
                if (v < lo) {
                    v = lo;
                    nsat++;
                } else if (v > hi) {
                    v = hi;
                    nsat++;
                }
                out[k] = (int64_t)v;
            }
        }
        Py_END_ALLOW_THREADS
    }
    PyBuffer_Release(&ob);
    PyBuffer_Release(&xb);
    return PyLong_FromSsize_t(nsat);
}

static PyMethodDef methods[] = {
    {"run_block", run_block, METH_VARARGS, run_block_doc},
    {"round_saturate", round_saturate, METH_VARARGS, round_saturate_doc},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {
    PyModuleDef_HEAD_INIT, "canrls._fixed",
    "The fixed-point RLS C kernel (src/canrls/c/firmware/canrls_fixed.c) for canrls.estimation.fixed.estimator.",
    -1, methods, NULL, NULL, NULL, NULL,
};

PyMODINIT_FUNC PyInit__fixed(void)
{
    PyObject *mod = PyModule_Create(&module);
    PyObject *names;
    Py_ssize_t k = 0;
    if (mod == NULL) {
        return NULL;
    }
    names = PyTuple_New(NPLAN);
    if (names == NULL) {
        Py_DECREF(mod);
        return NULL;
    }
#define ADD_NAME(name) PyTuple_SET_ITEM(names, k, PyUnicode_FromString(#name)); k++;
    CANRLS_PLAN_FIELDS(ADD_NAME)
#undef ADD_NAME
    if (PyModule_AddObject(mod, "PLAN_FIELDS", names) != 0
        || PyModule_AddIntConstant(mod, "N_MAX", CANRLS_N_MAX) != 0
        || PyModule_AddIntConstant(mod, "NSITES", CANRLS_NSITES) != 0) {
        Py_DECREF(names);
        Py_DECREF(mod);
        return NULL;
    }
    return mod;
}
