/*
 * target_module.c -- canrls._target: the target's whole integer path (canrls_target.c
 * and canrls_fixed.c, the C that `canrls export-c` writes) as a CPython extension.
 *
 * SPDX-License-Identifier: MIT
 *
 * Target(layout vector) builds a canrls_target_model from the integers of a Python
 * TargetModel, passed in at run time as one int64 vector (the tables of canrls_model.c,
 * as data: nothing is compiled for a model), and runs canrls_target_init() on it.
 * Target.run() takes a block of frames (receive ticks, IDs, payloads) through
 * canrls_target_frame(), with canrls_target_publish() when a publication is due, as
 * the firmware calls them; record() gives the state as the specification's
 * state_record() lays it out (canrls.firmware.vectors), theta() each parameter in SI;
 * state() and set_state() save and restore the state (a daemon's checkpoint).
 *
 * The vector's layout is named here once, in X-macros (S: one value, A: an array), and
 * exported as LAYOUT: {section: ((name, count), ...)}; canrls.firmware.native fills it
 * by these names. Every value is checked against its C field's range (ValueError naming
 * the section and the field), so no vector makes the C index or shift out of bounds.
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>

#include <string.h>

#include "canrls_target.h"
#include "canrls_target_check.h"
#include "pyargs.h"

#define R32 INT32_MIN, INT32_MAX
#define R64 INT64_MIN, INT64_MAX
#define FLAG 0, 1
#define PARAMS_MAX (CANRLS_TARGET_EQ_MAX * CANRLS_N_MAX)

/* the model's scalars (canrls_target_model; u64 fields as their int64 bits) */
#define MODEL_F(XS, XA)                                                                    \
    XS(nmsg, 1, CANRLS_TARGET_MSG_MAX) XS(nfilters, 0, CANRLS_TARGET_FILTER_MAX)           \
    XS(neq, 1, CANRLS_TARGET_EQ_MAX) XS(nparams, 0, PARAMS_MAX) XS(match_counters, FLAG)    \
    XS(dt_ticks, R32) XS(gap_ticks, R32) XS(tol_ticks, R32) XS(tanh_m, R32) XS(tanh_sh, R32)   \
    XS(tanh_b, R64) XS(strib_m, R32) XS(strib_sh, R32) XS(strib_b, R64) XS(phase_m, R64)      \
    XS(phase_o, R64) XS(w_offset, R64) XA(A, 4, R32) XA(G, 8, R32)                         \
    XS(publish_every, 1, UINT32_MAX) XS(active_effects, 0, UINT32_MAX) XS(has_frames, FLAG)
/* a signal's bit field (canrls_field): the roles', then each message's counter */
#define FIELD_F(XS, XA)                                                                    \
    XS(msg, 0, CANRLS_TARGET_MSG_MAX - 1) XS(length, 0, 64) XS(is_float, FLAG)              \
    XS(frac, INT8_MIN, INT8_MAX) XS(is_signed, FLAG) XS(biased, FLAG) XS(big_endian, FLAG)   \
    XS(shift, 0, 63) XS(lo, R32) XS(hi, R32)
/* an estimator frame (canrls_out_frame): RlsEstimate, RlsParamInfo, RlsStatus, RlsHealth */
#define OUT_F(XS, XA) XS(id, 0, 0x7FF) XA(start, 8, 0, 63) XA(length, 8, 0, 64)
/* a mapped message (canrls_message; its counter follows as a field) */
#define MESSAGE_F(XS, XA)                                                                  \
    XS(id, 0, 0x1FFFFFFF) XS(extended, FLAG) XS(dlc, 0, 8) XS(crc, FLAG) XS(has_counter, FLAG) \
    XS(nroles, 0, CANRLS_TARGET_ROLES) XA(roles, CANRLS_TARGET_ROLES, 0, CANRLS_TARGET_ROLES - 1)
/* a filter of the bank (canrls_filter) */
#define FILTER_F(XS, XA)                                                                   \
    XS(kind, CANRLS_SRC_RAW, CANRLS_SRC_CONST) XS(role, 0, CANRLS_TARGET_ROLES - 1)         \
    XS(order, 0, UINT8_MAX) XS(hold, FLAG) XS(fx, 0, 40)
/* an equation's scalars (canrls_equation); then its plan, its output and its columns */
#define EQUATION_F(XS, XA)                                                                 \
    XS(n, 1, CANRLS_N_MAX) XS(index, 0, UINT8_MAX) XS(cross, FLAG) XS(trace_follows, FLAG)   \
    XS(warmup, 0, INT32_MAX) XS(min_w, R64) XS(max_w, R64) XS(e0, R32) XS(f_phi, 0, 62)       \
    XS(f_y, 0, 62) XS(f_theta, R32) XS(f_eps, R32) XS(theta_h, R32) XS(rms_shift, 0, 63)       \
    XS(trace_cap, R64) XS(floor_term, R64) XS(first_term, R64)
/* the dyadic ridges of an equation (canrls_dyadic: m as its int64 bits) */
#define PRIORS_F(XS, XA) XS(floor_m, R64) XS(floor_e, R32) XS(first_m, R64) XS(first_e, R32)
/* a column or the output (canrls_column) */
#define COLUMN_F(XS, XA)                                                                   \
    XS(offset, R64) XS(m, R32) XS(sh, R32) XS(exponent, R32) XS(filter, 0, CANRLS_TARGET_FILTER_MAX - 1) \
    XS(derivative, FLAG) XS(adaptive, FLAG) XS(pending, FLAG)
/* a column's prior: P0 word, trace term, ridge m 2^e */
#define PRIOR_F(XS, XA) XS(p0, R32) XS(term, R64) XS(ridge_m, R64) XS(ridge_e, R32)
/* a parameter's RlsParamInfo (param_info, param_order) */
#define PARAM_F(XS, XA)                                                                    \
    XS(effect, 0, UINT8_MAX) XS(component, 0, UINT8_MAX) XS(equation, 0, UINT8_MAX)         \
    XS(order, 0, UINT16_MAX)

/* the sections of the vector, in this order (plan: PLAN_FIELDS) */
#define SECTIONS(X)                                                                      \
    X(model, MODEL_F) X(field, FIELD_F) X(out, OUT_F) X(message, MESSAGE_F)              \
    X(filter, FILTER_F) X(equation, EQUATION_F) X(priors, PRIORS_F) X(column, COLUMN_F)  \
    X(prior, PRIOR_F) X(param, PARAM_F)

/* ------------------------------------------------------------------ reading the vector */

typedef struct {
    const int64_t *v;
    Py_ssize_t n, k;
    const char *section;
} Cursor;

/* the next value, within lo..hi (ValueError naming the field otherwise) */
static int next(Cursor *c, const char *name, int64_t lo, int64_t hi, int64_t *out)
{
    if (c->k >= c->n) {
        PyErr_Format(PyExc_ValueError, "Target: the vector ends before %s.%s", c->section,
                     name);
        return 0;
    }
    *out = c->v[c->k++];
    if (*out < lo || *out > hi) {
        PyErr_Format(PyExc_ValueError, "Target: %s.%s = %lld outside %lld..%lld", c->section,
                     name, (long long)*out, (long long)lo, (long long)hi);
        return 0;
    }
    return 1;
}

/* ------------------------------------------------------------------ the readers */

/* one struct's fields from the cursor: S sets a field, A each element of an array */
#define READ_S(...) READ_S3(__VA_ARGS__)
#define READ_S3(name, lo, hi)                                                             \
    if (!next(c, #name, (int64_t)(lo), (int64_t)(hi), &x))                               \
        return 0;                                                                        \
    s->name = x;
#define READ_A(...) READ_A4(__VA_ARGS__)
#define READ_A4(name, count, lo, hi)                                                      \
    for (i = 0; i < (count); i++) {                                                      \
        if (!next(c, #name, (int64_t)(lo), (int64_t)(hi), &x))                           \
            return 0;                                                                    \
        s->name[i] = x;                                                                  \
    }

/* the model's scalars (G flat: per hold G0_1, G0_2, G1_1, G1_2) */
typedef struct {
    uint32_t nmsg, nfilters, neq, nparams, match_counters;
    int32_t dt_ticks, gap_ticks, tol_ticks, tanh_m, tanh_sh, strib_m, strib_sh, A[4], G[8];
    int64_t tanh_b, strib_b, phase_m, phase_o, w_offset;
    uint32_t publish_every, active_effects, has_frames;
} model_t;
typedef struct { int64_t floor_m; int32_t floor_e; int64_t first_m; int32_t first_e; } priors_t;
typedef struct { int32_t p0; int64_t term, ridge_m; int32_t ridge_e; } prior_t;
typedef struct { uint32_t effect, component, equation, order; } param_t;

#define READER(sec, type, FIELDS)                                                        \
    static int read_##sec(Cursor *c, type *s)                                            \
    {                                                                                    \
        int64_t x;                                                                       \
        int i = 0;                                                                       \
        (void)i;                                                                         \
        c->section = #sec;                                                               \
        FIELDS(READ_S, READ_A)                                                           \
        return 1;                                                                        \
    }
READER(model, model_t, MODEL_F)
READER(field, canrls_field, FIELD_F)
READER(out, canrls_out_frame, OUT_F)
READER(message, canrls_message, MESSAGE_F)
READER(filter, canrls_filter, FILTER_F)
READER(equation, canrls_equation, EQUATION_F)
READER(priors, priors_t, PRIORS_F)
READER(column, canrls_column, COLUMN_F)
READER(prior, prior_t, PRIOR_F)
READER(param, param_t, PARAM_F)

/* the plan, field by field: each value must fit its field */
static int read_plan(Cursor *c, canrls_plan_q31 *plan)
{
    c->section = "plan";
#define READ_PLAN(name)                                                                  \
    if (!next(c, #name, INT64_MIN, INT64_MAX, &x))                                       \
        return 0;                                                                        \
    plan->name = x;                                                                      \
    if ((int64_t)plan->name != x) {                                                      \
        PyErr_Format(PyExc_ValueError, "Target: plan.%s = %lld outside its field", #name, \
                     (long long)x);                                                      \
        return 0;                                                                        \
    }
    int64_t x;
    CANRLS_PLAN_FIELDS(READ_PLAN)
#undef READ_PLAN
    return 1;
}

/* ------------------------------------------------------------------ the object */

typedef struct {
    PyObject_HEAD
    canrls_target_model M;
    canrls_message msgs[CANRLS_TARGET_MSG_MAX];
    canrls_filter filters[CANRLS_TARGET_FILTER_MAX];
    canrls_equation eqs[CANRLS_TARGET_EQ_MAX];
    canrls_column cols[CANRLS_TARGET_EQ_MAX][CANRLS_N_MAX];
    canrls_plan_q31 plans[CANRLS_TARGET_EQ_MAX];
    int32_t p0[CANRLS_TARGET_EQ_MAX][CANRLS_N_MAX];
    int64_t terms[CANRLS_TARGET_EQ_MAX][CANRLS_N_MAX];
    canrls_dyadic ridge[CANRLS_TARGET_EQ_MAX][CANRLS_N_MAX];
    uint8_t info[PARAMS_MAX][4];
    uint16_t order[PARAMS_MAX];
    canrls_target S;
    int ready; /* canrls_target_init() took the model */
} TargetObject;

/* whether the object holds a model (ValueError otherwise: Target.__new__ alone) */
static int ready(const TargetObject *o)
{
    if (!o->ready) {
        PyErr_SetString(PyExc_ValueError, "Target: no model (call Target(vector))");
    }
    return o->ready;
}

static int bad(const char *what)
{
    PyErr_Format(PyExc_ValueError, "Target: %s", what);
    return 0;
}

/* a field the decoder reads: an integer of 1..32 bits or a float of 32 or 64, inside
 * the payload's word (message msg) */
static int check_field(const canrls_field *f, uint32_t msg)
{
    const int ok = f->is_float ? (f->length == 32u || f->length == 64u)
                               : (f->length >= 1u && f->length <= 32u);
    if (!ok || f->shift + f->length > 64u || f->msg != msg) {
        return bad("a field's length, shift or message is not one the decoder reads");
    }
    return 1;
}

/* the model of the vector into the object (every pointer into its own arrays) */
static int build(TargetObject *o, Cursor *c)
{
    canrls_target_model *M = &o->M;
    model_t m;
    uint32_t i, j, params = 0u;
    if (!read_model(c, &m)) {
        return 0;
    }
    memset(M, 0, sizeof *M);
    M->nmsg = m.nmsg;
    M->nfilters = m.nfilters;
    M->neq = m.neq;
    M->nparams = m.nparams;
    M->match_counters = (uint8_t)m.match_counters;
    M->dt_ticks = m.dt_ticks;
    M->gap_ticks = m.gap_ticks;
    M->tol_ticks = m.tol_ticks;
    M->tanh_m = m.tanh_m;
    M->tanh_sh = m.tanh_sh;
    M->tanh_b = m.tanh_b;
    M->strib_m = m.strib_m;
    M->strib_sh = m.strib_sh;
    M->strib_b = m.strib_b;
    M->phase_m = (uint64_t)m.phase_m;
    M->phase_o = (uint64_t)m.phase_o;
    M->w_offset = m.w_offset;
    memcpy(M->A, m.A, sizeof M->A);
    memcpy(M->G, m.G, sizeof M->G);
    M->publish_every = m.publish_every;
    M->active_effects = m.active_effects;
    M->has_frames = (uint8_t)m.has_frames;
    for (i = 0; i < CANRLS_TARGET_ROLES; i++) {
        if (!read_field(c, &M->roles[i])) {
            return 0;
        }
    }
    if (!read_out(c, &M->estimate) || !read_out(c, &M->info) || !read_out(c, &M->status)
        || !read_out(c, &M->health)) {
        return 0;
    }
    for (i = 0; i < 4u; i++) {
        const canrls_out_frame *f = (&M->estimate) + i;
        for (j = 0; j < 8u; j++) {
            if (f->start[j] + f->length[j] > 64u) {
                return bad("an estimator frame's signal beyond its 8 bytes");
            }
        }
    }
    for (i = 0; i < M->nmsg; i++) {
        canrls_message *g = &o->msgs[i];
        if (!read_message(c, g) || !read_field(c, &g->counter)) {
            return 0;
        }
        if (g->has_counter && (g->counter.is_float || !check_field(&g->counter, i))) {
            return bad("an alive counter that is not an integer field of its message");
        }
        for (j = 0; j < g->nroles; j++) {
            if (!check_field(&M->roles[g->roles[j]], i)) {
                return 0;
            }
        }
    }
    for (i = 0; i < M->nfilters; i++) {
        if (!read_filter(c, &o->filters[i])) {
            return 0;
        }
    }
    for (i = 0; i < M->neq; i++) {
        canrls_equation *e = &o->eqs[i];
        priors_t pr;
        if (!read_equation(c, e) || !read_priors(c, &pr) || !read_plan(c, &o->plans[i])
            || !read_column(c, &e->output)) {
            return 0;
        }
        e->floor_ridge.m = (uint64_t)pr.floor_m;
        e->floor_ridge.e = pr.floor_e;
        e->first_ridge.m = (uint64_t)pr.first_m;
        e->first_ridge.e = pr.first_e;
        e->plan = &o->plans[i];
        e->columns = o->cols[i];
        e->p0 = o->p0[i];
        e->trace_terms = o->terms[i];
        e->ridge = o->ridge[i];
        for (j = 0; j < e->n; j++) {
            prior_t p;
            if (!read_column(c, &o->cols[i][j]) || !read_prior(c, &p)) {
                return 0;
            }
            o->p0[i][j] = p.p0;
            o->terms[i][j] = p.term;
            o->ridge[i][j].m = (uint64_t)p.ridge_m;
            o->ridge[i][j].e = p.ridge_e;
            if (o->cols[i][j].filter >= M->nfilters) {
                return bad("a column reads a filter the bank does not have");
            }
        }
        if (e->output.filter >= M->nfilters) {
            return bad("the output reads a filter the bank does not have");
        }
        params += e->n;
    }
    if (params != M->nparams) {
        return bad("nparams is not the equations' parameters");
    }
    for (i = 0; i < M->nparams; i++) {
        param_t p;
        if (!read_param(c, &p)) {
            return 0;
        }
        o->info[i][0] = (uint8_t)p.effect;
        o->info[i][1] = (uint8_t)p.component;
        o->info[i][2] = (uint8_t)p.equation;
        o->info[i][3] = 0u;
        o->order[i] = (uint16_t)p.order;
    }
    if (c->k != c->n) {
        return bad("values beyond the model's end");
    }
    M->messages = o->msgs;
    M->filters = o->filters;
    M->equations = o->eqs;
    M->param_info = (const uint8_t(*)[4])o->info;
    M->param_order = o->order;
    return 1;
}

static int Target_init(TargetObject *self, PyObject *args, PyObject *kwds)
{
    PyObject *vo;
    Py_buffer vb;
    Cursor c;
    int ok;
    static char *kwlist[] = {"vector", NULL};
    if (!PyArg_ParseTupleAndKeywords(args, kwds, "O:Target", kwlist, &vo)) {
        return -1;
    }
    if (PyObject_GetBuffer(vo, &vb, PyBUF_C_CONTIGUOUS | PyBUF_FORMAT) != 0) {
        return -1;
    }
    if (!is_kind(&vb, I64) || vb.ndim != 1) {
        PyBuffer_Release(&vb);
        PyErr_SetString(PyExc_TypeError, "Target: the vector must be a 1-D int64 array");
        return -1;
    }
    c.v = vb.buf;
    c.n = vb.len / 8;
    c.k = 0;
    c.section = "model";
    self->ready = 0;
    ok = build(self, &c);
    PyBuffer_Release(&vb);
    if (!ok) {
        return -1;
    }
    if (canrls_target_init(&self->S, &self->M) != CANRLS_OK) {
        PyErr_SetString(PyExc_ValueError,
                        "Target: canrls_target_init refused the model (beyond the build's "
                        "bounds, or a prior outside its words)");
        return -1;
    }
    self->ready = 1;
    return 0;
}

/* ------------------------------------------------------------------ frames in */

/* the frames of a publication as [(id, payload)] */
static PyObject *frames_list(const canrls_can_frame *out, uint32_t n)
{
    PyObject *list = PyList_New(n);
    uint32_t i;
    if (list == NULL) {
        return NULL;
    }
    for (i = 0; i < n; i++) {
        PyObject *item = Py_BuildValue("(ky#)", (unsigned long)out[i].id,
                                       (const char *)out[i].data, (Py_ssize_t)out[i].dlc);
        if (item == NULL) {
            Py_DECREF(list);
            return NULL;
        }
        PyList_SET_ITEM(list, i, item);
    }
    return list;
}

static const Spec run_spec[] = {
    {0, "ticks", U32, 1, RO}, {1, "arbitration_id", U32, 1, RO},
    {2, "is_extended", BOOL, 1, RO}, {3, "skip", BOOL, 1, RO}, {4, "dlc", U8, 1, RO},
    {5, "data", U8, 2, RO},
};

PyDoc_STRVAR(run_doc,
"run(ticks, arbitration_id, is_extended, skip, dlc, data, publications) -> samples\n\n"
"Every row of a block through canrls_target_frame() (skip: rows the target never sees,\n"
"error and remote frames), canrls_target_publish() where a publication is due; with a\n"
"list as publications, (row, [(id, payload)]) appended for each (None: discarded).\n"
"Returns the samples the block completed.");

static PyObject *Target_run(TargetObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    Args a = {.fn = "run", .count = 0};
    Py_buffer *b[COUNT(run_spec)];
    PyObject *pubs, *res = NULL;
    Py_ssize_t N, width, k, samples = 0;
    int bad_row = 0;
    if (!ready(self) || !start(&a, nargs, 7)) {
        return NULL;
    }
    pubs = args[6];
    if (pubs != Py_None && !PyList_Check(pubs)) {
        PyErr_SetString(PyExc_TypeError, "run: publications must be a list or None");
        return NULL;
    }
    if (take(&a, args, run_spec, COUNT(run_spec), b, I64)) {
        N = dim(b[0], 0);
        width = dim(b[5], 1);
        if (need(&a, b[1], "arbitration_id", N, -1) && need(&a, b[2], "is_extended", N, -1)
            && need(&a, b[3], "skip", N, -1) && need(&a, b[4], "dlc", N, -1)
            && need(&a, b[5], "data", N, width)) {
            const uint32_t *t = W(b[0]), *id = W(b[1]);
            const uint8_t *ext = U(b[2]), *skip = U(b[3]), *dlc = U(b[4]), *data = U(b[5]);
            canrls_target *S = &self->S;
            canrls_can_frame out[CANRLS_PUBLISH_MAX];
            PyThreadState *ts = pubs == Py_None ? PyEval_SaveThread() : NULL;
            for (k = 0; k < N; k++) {
                uint32_t r;
                if (skip[k]) {
                    continue;
                }
                if (dlc[k] > width) {
                    bad_row = 1;
                    break;
                }
                r = canrls_target_frame(S, id[k], ext[k], data + k * width, dlc[k], t[k]);
                samples += (r & CANRLS_SAMPLE) != 0u;
                if (r & CANRLS_PUBLISH) {
                    const uint32_t n = canrls_target_publish(S, out, CANRLS_PUBLISH_MAX);
                    if (pubs != Py_None) {
                        PyObject *fr = frames_list(out, n), *item;
                        item = fr == NULL ? NULL : Py_BuildValue("(nN)", k, fr);
                        if (item == NULL || PyList_Append(pubs, item) != 0) {
                            Py_XDECREF(item);
                            break;
                        }
                        Py_DECREF(item);
                    }
                }
            }
            if (ts != NULL) {
                PyEval_RestoreThread(ts);
            }
            if (bad_row) {
                PyErr_Format(PyExc_ValueError, "run: row %zd has a dlc beyond the data's %zd "
                             "bytes", k, width);
            } else if (!PyErr_Occurred()) {
                res = PyLong_FromSsize_t(samples);
            }
        }
    }
    release(&a);
    return res;
}

/* ------------------------------------------------------------------ state out */

PyDoc_STRVAR(record_doc,
"record() -> list[int]\n\n"
"The integer state as canrls.firmware.vectors.state_record() lays it out: samples, the\n"
"rejection counters, the filters' states, then per equation theta, its fractions, the\n"
"upper triangle of P, its fractions, e, c, the kernel's counters, the shifts, updates,\n"
"the residual's mean square and the rescales.");

static PyObject *Target_record(TargetObject *self, PyObject *unused)
{
    const canrls_target *S = &self->S;
    const canrls_target_model *M = &self->M;
    PyObject *list = PyList_New(0);
    uint32_t i, j;
    (void)unused;
    if (list == NULL || !ready(self)) {
        Py_XDECREF(list);
        return NULL;
    }
#define PUT(v)                                                                           \
    do {                                                                                 \
        PyObject *x_ = PyLong_FromLongLong((long long)(v));                              \
        if (x_ == NULL || PyList_Append(list, x_) != 0) {                                \
            Py_XDECREF(x_);                                                              \
            Py_DECREF(list);                                                             \
            return NULL;                                                                 \
        }                                                                                \
        Py_DECREF(x_);                                                                   \
    } while (0)
    PUT(S->samples);
    for (i = 0; i < CANRLS_NREJECTS; i++) {
        PUT(S->rejects[i]);
    }
    for (i = 0; i < M->nfilters; i++) {
        PUT(S->x1[i]);
    }
    for (i = 0; i < M->nfilters; i++) {
        PUT(S->x2[i]);
    }
    for (i = 0; i < M->neq; i++) {
        const canrls_target_eq *q = &S->eq[i];
        const uint32_t n = M->equations[i].n;
        for (j = 0; j < n; j++) {
            PUT(canrls_theta_q31(&q->rls, j));
        }
        for (j = 0; j < n; j++) {
            PUT(canrls_theta_frac_q31(&q->rls, j));
        }
        for (j = 0; j < CANRLS_TRI(n); j++) {
            PUT(canrls_P_q31(&q->rls, j));
        }
        for (j = 0; j < CANRLS_TRI(n); j++) {
            PUT(canrls_P_frac_q31(&q->rls, j));
        }
        PUT(q->rls.e);
        PUT(q->rls.c);
        for (j = 0; j < CANRLS_NSITES; j++) {
            PUT(q->rls.counts[j]);
        }
        for (j = 0; j < n; j++) {
            PUT(q->sh[j]);
        }
        PUT(q->sh_y);
        PUT(q->updates);
        PUT(q->ms);
        PUT(q->rescales);
    }
#undef PUT
    return list;
}

PyDoc_STRVAR(theta_doc,
"theta() -> list[float]\n\n"
"Every parameter in SI: word 2^exp of canrls_target_theta(), equations in order.");

static PyObject *Target_theta(TargetObject *self, PyObject *unused)
{
    PyObject *list;
    uint32_t i;
    (void)unused;
    if (!ready(self) || (list = PyList_New(self->M.nparams)) == NULL) {
        return NULL;
    }
    for (i = 0; i < self->M.nparams; i++) {
        int32_t word, ex;
        PyObject *x;
        canrls_target_theta(&self->S, i, &word, &ex);
        x = PyFloat_FromDouble(ldexp((double)word, ex));
        if (x == NULL) {
            Py_DECREF(list);
            return NULL;
        }
        PyList_SET_ITEM(list, i, x);
    }
    return list;
}

PyDoc_STRVAR(counts_doc,
"counts() -> (samples, rejects, updates, rescales, saturations)\n\n"
"The counters: samples, the rejections by reason (REJECTS), and per equation its\n"
"updates, rescales and the kernel's saturations per site (SITES).");

static PyObject *Target_counts(TargetObject *self, PyObject *unused)
{
    const canrls_target *S = &self->S;
    PyObject *rej, *upd, *res, *sat;
    uint32_t i, j;
    (void)unused;
    if (!ready(self)) {
        return NULL;
    }
    rej = PyTuple_New(CANRLS_NREJECTS);
    upd = PyTuple_New(self->M.neq);
    res = PyTuple_New(self->M.neq);
    sat = PyTuple_New(self->M.neq);
    if (rej == NULL || upd == NULL || res == NULL || sat == NULL) {
        goto fail;
    }
    for (i = 0; i < CANRLS_NREJECTS; i++) {
        PyTuple_SET_ITEM(rej, i, PyLong_FromUnsignedLong(S->rejects[i]));
    }
    for (i = 0; i < self->M.neq; i++) {
        PyObject *c = PyTuple_New(CANRLS_NSITES);
        if (c == NULL) {
            goto fail;
        }
        for (j = 0; j < CANRLS_NSITES; j++) {
            PyTuple_SET_ITEM(c, j, PyLong_FromUnsignedLong(S->eq[i].rls.counts[j]));
        }
        PyTuple_SET_ITEM(upd, i, PyLong_FromUnsignedLong(S->eq[i].updates));
        PyTuple_SET_ITEM(res, i, PyLong_FromUnsignedLong(S->eq[i].rescales));
        PyTuple_SET_ITEM(sat, i, c);
    }
    if (PyErr_Occurred()) {
        goto fail;
    }
    return Py_BuildValue("(kNNNN)", (unsigned long)S->samples, rej, upd, res, sat);
fail:
    Py_XDECREF(rej);
    Py_XDECREF(upd);
    Py_XDECREF(res);
    Py_XDECREF(sat);
    return NULL;
}

PyDoc_STRVAR(freeze_doc,
"freeze(on) -> None\n\n"
"Every equation's kernel frozen (updates compute eps only, the flag FROZEN) or not: the\n"
"field `frozen` of canrls_rls_q31, which the firmware writes as a plain field.");

static PyObject *Target_freeze(TargetObject *self, PyObject *arg)
{
    const int on = PyObject_IsTrue(arg);
    uint32_t i;
    if (on < 0 || !ready(self)) {
        return NULL;
    }
    for (i = 0; i < self->M.neq; i++) {
        self->S.eq[i].rls.frozen = (uint32_t)on;
    }
    Py_RETURN_NONE;
}

PyDoc_STRVAR(state_doc,
"state() -> bytes\n\n"
"The whole canrls_target state as its bytes (the pointers into the model written as 0):\n"
"what set_state() takes back on an object built from the same vector by the same build.");

/* the state with its pointers (the model, each kernel's plan) cleared */
static PyObject *Target_state(TargetObject *self, PyObject *unused)
{
    PyObject *out;
    canrls_target *S;
    uint32_t i;
    (void)unused;
    if (!ready(self)) {
        return NULL;
    }
    out = PyBytes_FromStringAndSize((const char *)&self->S, (Py_ssize_t)sizeof self->S);
    if (out == NULL) {
        return NULL;
    }
    S = (canrls_target *)(void *)PyBytes_AS_STRING(out);
    S->model = NULL;
    for (i = 0; i < CANRLS_TARGET_EQ_MAX; i++) {
        S->eq[i].rls.plan = NULL;
    }
    return out;
}

PyDoc_STRVAR(set_state_doc,
"set_state(state: bytes) -> None\n\n"
"Continue from a state() of an object built from the same vector by the same build:\n"
"its bytes taken, the pointers and each kernel's size kept. ValueError: another size,\n"
"kernels of another size, or a field canrls_target_check_state() refuses (named).");

static PyObject *Target_set_state(TargetObject *self, PyObject *arg)
{
    Py_buffer b;
    canrls_target next;
    uint32_t i;
    int field;
    if (!ready(self) || PyObject_GetBuffer(arg, &b, PyBUF_SIMPLE) != 0) {
        return NULL;
    }
    if (b.len != (Py_ssize_t)sizeof next) {
        PyBuffer_Release(&b);
        PyErr_Format(PyExc_ValueError, "Target: a state of %zd bytes, this build's has %zu",
                     b.len, sizeof next);
        return NULL;
    }
    memcpy(&next, b.buf, sizeof next);
    PyBuffer_Release(&b);
    for (i = 0; i < CANRLS_TARGET_EQ_MAX; i++) {
        if (next.eq[i].rls.n != self->S.eq[i].rls.n) {
            PyErr_Format(PyExc_ValueError, "Target: the state's equation %u has %u "
                         "parameters, the model's %u", i, next.eq[i].rls.n,
                         self->S.eq[i].rls.n);
            return NULL;
        }
        /* the pointers of this object: to the model and to the state's own plan copy */
        next.eq[i].rls.plan = i < self->M.neq ? &next.eq[i].plan : NULL;
    }
    next.model = self->S.model;
    field = canrls_target_check_state(&next, next.model);
    if (field != CANRLS_OK) {
        PyErr_Format(PyExc_ValueError, "Target: the state's %s is not one the estimator "
                     "reaches on this model (canrls_target_check_state)",
                     canrls_target_state_field(field));
        return NULL;
    }
    self->S = next;
    for (i = 0; i < self->M.neq; i++) {
        self->S.eq[i].rls.plan = &self->S.eq[i].plan;
    }
    Py_RETURN_NONE;
}

static PyMethodDef Target_methods[] = {
    {"run", (PyCFunction)(void (*)(void))Target_run, METH_FASTCALL, run_doc},
    {"record", (PyCFunction)Target_record, METH_NOARGS, record_doc},
    {"theta", (PyCFunction)Target_theta, METH_NOARGS, theta_doc},
    {"counts", (PyCFunction)Target_counts, METH_NOARGS, counts_doc},
    {"freeze", (PyCFunction)Target_freeze, METH_O, freeze_doc},
    {"state", (PyCFunction)Target_state, METH_NOARGS, state_doc},
    {"set_state", (PyCFunction)Target_set_state, METH_O, set_state_doc},
    {NULL, NULL, 0, NULL},
};

static PyTypeObject TargetType = {
    PyVarObject_HEAD_INIT(NULL, 0)
    .tp_name = "canrls._target.Target",
    .tp_basicsize = sizeof(TargetObject),
    .tp_flags = Py_TPFLAGS_DEFAULT,
    .tp_doc = "Target(vector): the target's estimator (canrls_target) on a model given as "
              "data (LAYOUT)",
    .tp_new = PyType_GenericNew,
    .tp_init = (initproc)Target_init,
    .tp_methods = Target_methods,
};

/* ------------------------------------------------------------------ the module */

/* LAYOUT[section] = ((name, count), ...) */
#define NAME_S(...) NAME_S3(__VA_ARGS__)
#define NAME_S3(name, lo, hi) {#name, 1},
#define NAME_A(...) NAME_A4(__VA_ARGS__)
#define NAME_A4(name, count, lo, hi) {#name, count},
typedef struct {
    const char *name;
    int count;
} NameCount;

static PyObject *names_tuple(const NameCount *f, size_t n)
{
    PyObject *t = PyTuple_New((Py_ssize_t)n);
    size_t i;
    if (t == NULL) {
        return NULL;
    }
    for (i = 0; i < n; i++) {
        PyObject *item = Py_BuildValue("(si)", f[i].name, f[i].count);
        if (item == NULL) {
            Py_DECREF(t);
            return NULL;
        }
        PyTuple_SET_ITEM(t, (Py_ssize_t)i, item);
    }
    return t;
}

static PyObject *layout(void)
{
    PyObject *d = PyDict_New(), *t;
#define ADD_NAME(name) {#name, 1},
    static const NameCount plan[] = {CANRLS_PLAN_FIELDS(ADD_NAME)};
#undef ADD_NAME
    if (d == NULL) {
        return NULL;
    }
#define ADD_SECTION(sec, FIELDS)                                                     \
    {                                                                                    \
        static const NameCount f[] = {FIELDS(NAME_S, NAME_A)};                           \
        t = names_tuple(f, sizeof f / sizeof f[0]);                                      \
        if (t == NULL || PyDict_SetItemString(d, #sec, t) != 0) {                    \
            Py_XDECREF(t);                                                               \
            Py_DECREF(d);                                                                \
            return NULL;                                                                 \
        }                                                                                \
        Py_DECREF(t);                                                                    \
    }
    SECTIONS(ADD_SECTION)
#undef ADD_SECTION
    t = names_tuple(plan, sizeof plan / sizeof plan[0]);
    if (t == NULL || PyDict_SetItemString(d, "plan", t) != 0) {
        Py_XDECREF(t);
        Py_DECREF(d);
        return NULL;
    }
    Py_DECREF(t);
    return d;
}

static struct PyModuleDef module = {
    PyModuleDef_HEAD_INIT, "canrls._target",
    "The target's whole integer path (src/canrls/c/firmware/canrls_target.c) for "
    "canrls.firmware.native.",
    -1, NULL, NULL, NULL, NULL, NULL,
};

PyMODINIT_FUNC PyInit__target(void)
{
    PyObject *mod, *lay;
    if (PyType_Ready(&TargetType) < 0) {
        return NULL;
    }
    mod = PyModule_Create(&module);
    if (mod == NULL) {
        return NULL;
    }
    lay = layout();
    Py_INCREF(&TargetType);
    if (lay == NULL || PyModule_AddObject(mod, "LAYOUT", lay) != 0
        || PyModule_AddObject(mod, "Target", (PyObject *)&TargetType) != 0
        || PyModule_AddIntConstant(mod, "N_MAX", CANRLS_N_MAX) != 0
        || PyModule_AddIntConstant(mod, "STATE_BYTES", (long)sizeof(canrls_target)) != 0) {
        Py_XDECREF(lay);
        Py_DECREF(&TargetType);
        Py_DECREF(mod);
        return NULL;
    }
    return mod;
}
