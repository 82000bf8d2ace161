/*
 * pyargs.h -- the argument checks of canrls's C extensions (kernels.c, candump.c,
 * sim.c, fixed_spec.c).
 *
 * SPDX-License-Identifier: MIT
 *
 * A wrapper names its array arguments in a table of Spec (position, name, item type,
 * dimensions, written or not); take() gets their C-contiguous buffers and checks the
 * item type and the number of dimensions, need() and at_least() the sizes the loop
 * indexes, so a wrong call raises TypeError or ValueError naming the argument and never
 * reads or writes out of bounds. release() gives the buffers back. Static functions: each
 * extension compiles its own copy.
 */
#ifndef CANRLS_PYARGS_H
#define CANRLS_PYARGS_H

#define PY_SSIZE_T_CLEAN
#include <Python.h>

#include <stdint.h>

/* The item types the wrappers take: float64, float32, int64, uint8, bool, uint32, and
 * REAL: the precision of the call (an RLS state's dtype, float64 elsewhere). */
enum kind { F64, F32, I64, U8, BOOL, U32, REAL_ };

static const char *kind_name[] = {"float64", "float32", "int64", "uint8", "bool", "uint32"};

/* Whether a buffer's format and item size are those of kind k (native byte order). */
static inline int is_kind(const Py_buffer *b, enum kind k)
{
    const char *f = b->format ? b->format : "B";
    if (*f == '@' || *f == '=')
        f++;
    if (f[0] == '\0' || f[1] != '\0')
        return 0;
    switch (k) {
    case F64: return f[0] == 'd' && b->itemsize == 8;
    case F32: return f[0] == 'f' && b->itemsize == 4;
    case I64: return (f[0] == 'q' || f[0] == 'l') && b->itemsize == 8;
    case U8: return f[0] == 'B' && b->itemsize == 1;
    case BOOL: return f[0] == '?' && b->itemsize == 1;
    case U32: return (f[0] == 'I' || f[0] == 'L') && b->itemsize == 4;
    case REAL_: break;
    }
    return 0;
}

#define MAX_BUFS 20
enum { RO = 0, RW = 1 };

/* One array argument: its position, name, item type, dimensions, whether written. */
typedef struct {
    int arg;
    const char *name;
    enum kind kind;
    int ndim;
    int writable;
} Spec;

/* The buffers one call holds (released together by release()). */
typedef struct {
    const char *fn;
    Py_buffer b[MAX_BUFS];
    int count;
} Args;

static inline void release(Args *a)
{
    for (int i = 0; i < a->count; i++)
        PyBuffer_Release(&a->b[i]);
    a->count = 0;
}

/* Whether the call has `want` arguments (TypeError otherwise). */
static inline int start(Args *a, Py_ssize_t nargs, Py_ssize_t want)
{
    if (nargs == want)
        return 1;
    PyErr_Format(PyExc_TypeError, "%s() takes %zd arguments (%zd given)", a->fn, want, nargs);
    return 0;
}

/* The C-contiguous buffers of the array arguments in spec, into b[0..count) (REAL_
 * items are `real`); 0 with TypeError or ValueError set when one is not as spec says. */
static inline int take(Args *a, PyObject *const *args, const Spec *spec, int count,
                Py_buffer **b, enum kind real)
{
    for (int i = 0; i < count; i++) {
        const Spec *s = &spec[i];
        const enum kind k = s->kind == REAL_ ? real : s->kind;
        PyObject *o = args[s->arg];
        if (a->count == MAX_BUFS) {
            PyErr_Format(PyExc_SystemError, "%s: more than %d arrays", a->fn, MAX_BUFS);
            return 0;
        }
        Py_buffer *v = &a->b[a->count];
        int flags = PyBUF_C_CONTIGUOUS | PyBUF_FORMAT | (s->writable ? PyBUF_WRITABLE : 0);
        if (PyObject_GetBuffer(o, v, flags) < 0) {
            PyErr_Clear();
            PyErr_Format(PyExc_TypeError,
                         "%s: %s must be a C-contiguous%s %s array, got %.100s", a->fn,
                         s->name, s->writable ? " writable" : "", kind_name[k],
                         Py_TYPE(o)->tp_name);
            return 0;
        }
        a->count++;
        if (!is_kind(v, k)) {
            PyErr_Format(PyExc_TypeError, "%s: %s must be a %s array, got format '%s'",
                         a->fn, s->name, kind_name[k], v->format ? v->format : "B");
            return 0;
        }
        if (v->ndim != s->ndim) {
            PyErr_Format(PyExc_ValueError, "%s: %s must have %d dimension(s), got %d", a->fn,
                         s->name, s->ndim, v->ndim);
            return 0;
        }
        b[i] = v;
    }
    return 1;
}

/* Size of dimension d of a buffer (1 beyond its dimensions). */
static inline Py_ssize_t dim(const Py_buffer *b, int d)
{
    return d < b->ndim ? b->shape[d] : 1;
}

/* Whether buffer b has `rows` rows (dimension 0) and, when cols >= 0, `cols` columns
 * (dimension 1); ValueError naming the shape otherwise. */
static inline int need(Args *a, const Py_buffer *b, const char *name, Py_ssize_t rows,
                Py_ssize_t cols)
{
    if (dim(b, 0) == rows && (cols < 0 || dim(b, 1) == cols))
        return 1;
    if (cols >= 0)
        PyErr_Format(PyExc_ValueError, "%s: %s must have shape (%zd, %zd)", a->fn, name, rows,
                     cols);
    else
        PyErr_Format(PyExc_ValueError, "%s: %s must have shape (%zd,)", a->fn, name, rows);
    return 0;
}

/* Whether buffer b has at least `rows` rows (ValueError saying `what` otherwise). */
static inline int at_least(Args *a, const Py_buffer *b, const char *name, Py_ssize_t rows,
                    const char *what)
{
    if (dim(b, 0) >= rows)
        return 1;
    PyErr_Format(PyExc_ValueError, "%s: %s must have %s", a->fn, name, what);
    return 0;
}

static inline int as_double(PyObject *o, double *x)
{
    *x = PyFloat_AsDouble(o);
    return !(*x == -1.0 && PyErr_Occurred());
}

static inline int as_int64(PyObject *o, int64_t *x)
{
    long long v = PyLong_AsLongLong(o);
    if (v == -1 && PyErr_Occurred())
        return 0;
    *x = (int64_t)v;
    return 1;
}

static inline int as_bool(PyObject *o, int *x)
{
    *x = PyObject_IsTrue(o);
    return *x >= 0;
}

#define D(b) ((double *)(b)->buf)
#define F(b) ((float *)(b)->buf)
#define U(b) ((uint8_t *)(b)->buf)
#define I(b) ((int64_t *)(b)->buf)
#define W(b) ((uint32_t *)(b)->buf)
#define COUNT(spec) ((int)(sizeof spec / sizeof spec[0]))

#endif /* CANRLS_PYARGS_H */
