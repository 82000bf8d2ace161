/*
 * candump.c -- canrls._candump: candump text to frame arrays, and frame arrays to text.
 *
 * SPDX-License-Identifier: MIT
 *
 * The loops of canrls.can.candump (which documents what a line may hold, and which
 * lines are handed back to the per-line Python path of canrls.can.logs):
 *
 *   parse         "(SECONDS.FRACTION) CHANNEL ID#DATA" lines -> t, id, flags, dlc, data
 *   format_lines  the rows of a frame block -> "(sec.usec) channel ID#DATA" lines
 *
 * A timestamp's digits form an integer N <= 2^53, an exact double, and the time is
 * N / 10^d, one correctly rounded division of two exact doubles: what Python's
 * float("SECONDS.FRACTION") returns. The loops run without the GIL.
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>

#include <stdint.h>

#include "pyargs.h"

/* Linux SocketCAN error-frame flag in the 32-bit CAN ID, and the 29-bit ID mask */
#define CAN_ERR_FLAG 0x20000000u
#define EFF_MASK 0x1FFFFFFFu
/* the largest timestamp of a frame [s]: a line beyond it is a bad line (the module's
 * canrls.core.checks.MAX_TIMESTAMP) */
#define MAX_TIMESTAMP 1e10
/* most digits of a timestamp, and the largest integer they may form (an exact double) */
#define MAX_DIGITS 16
#define MAX_EXACT (UINT64_C(1) << 53)

/* exact powers of ten as doubles (10^22 is the largest exactly representable one) */
static double pow10_[23];
/* value of a hex digit, -1 for any other byte */
static int hexval[256];
static const char hexchars[] = "0123456789ABCDEF";

static void init_tables(void)
{
    double x = 1.0;
    for (int k = 0; k < 23; k++, x *= 10.0)
        pow10_[k] = x;
    for (int c = 0; c < 256; c++)
        hexval[c] = -1;
    for (int k = 0; k < 16; k++)
        hexval[(unsigned char)"0123456789ABCDEF"[k]] = k;
    for (int k = 0; k < 6; k++)
        hexval[(unsigned char)"abcdef"[k]] = 10 + k;
}

/* The output arrays of parse: one row per frame; slow (cap, 4) the lines handed back. */
typedef struct {
    double *t;
    uint32_t *aid;
    uint8_t *ext, *err, *dlc, *data; /* data: 8 bytes a row */
    int64_t *slow;
    Py_ssize_t cap;
} Rows;

/* Write row `row` from the parsed fields; the data bytes are already in place (nb). */
static inline void put_row(Rows *r, Py_ssize_t row, double t, uint64_t ident, Py_ssize_t nid,
                           Py_ssize_t nb)
{
    uint8_t *d = r->data + 8 * row;
    for (Py_ssize_t j = nb; j < 8; j++)
        d[j] = 0;
    const int is_err = nid == 8 && (ident & CAN_ERR_FLAG) != 0;
    r->t[row] = t;
    r->aid[row] = (uint32_t)(ident & EFF_MASK);
    r->ext[row] = nid == 8 && !is_err;
    r->err[row] = (uint8_t)is_err;
    r->dlc[row] = (uint8_t)nb;
}

/* The data bytes of a line (nb bytes, two hex digits each, from q) into the row;
 * negative when a digit is not hex. */
static inline int get_data(const uint8_t *q, Py_ssize_t nb, uint8_t *d)
{
    int bad = 0;
    for (Py_ssize_t j = 0; j < nb; j++) {
        const int hi = hexval[q[2 * j]], lo = hexval[q[2 * j + 1]];
        bad |= hi | lo;
        d[j] = (uint8_t)((hi * 16 + lo) & 255);
    }
    return bad;
}

/* Parse whole lines of buf[0:stop) into rows (canrls.can.candump.parse says what). */
static void parse(const uint8_t *buf, Py_ssize_t stop, int final, Rows *r,
                  Py_ssize_t *used, Py_ssize_t *nrows, Py_ssize_t *nslow, Py_ssize_t *nlines)
{
    const Py_ssize_t cap = r->cap;
    Py_ssize_t p = 0, rows = 0, slow = 0, lines = 0;
    /* layout of the last line parsed, relative to its start lay_p: lines of a log mostly
     * share it, and a line that has it (checked byte by byte) is read at fixed offsets
     * without searching. lay_nl < 0: none yet. */
    Py_ssize_t lay_p = 0, lay_nl = -1, lay_dot = -1, lay_close = 0, lay_sp2 = 0,
               lay_hash = 0;
    int lay_cr = 0;
    while (p < stop && rows + slow < cap) {
        if (lay_nl >= 0) {
            const Py_ssize_t nl = p + lay_nl;
            int good = nl < stop && buf[nl] == '\n' && (buf[nl - 1] == '\r') == lay_cr
                       && buf[p] == '(' && buf[p + lay_close] == ')'
                       && buf[p + lay_close + 1] == ' ' && buf[p + lay_sp2] == ' '
                       && buf[p + lay_hash] == '#';
            uint64_t num = 0;
            if (good) {
                /* the same digits and dot; at most MAX_DIGITS digits: no overflow */
                for (Py_ssize_t i = 1; i < lay_close; i++) {
                    const uint8_t c = buf[p + i];
                    if (i == lay_dot) {
                        if (c != '.') {
                            good = 0;
                            break;
                        }
                    } else if (c >= '0' && c <= '9') {
                        num = num * 10 + (uint64_t)(c - '0');
                    } else {
                        good = 0;
                        break;
                    }
                }
                good = good && num <= MAX_EXACT;
            }
            if (good) /* the same channel */
                for (Py_ssize_t i = lay_close + 2; i < lay_sp2; i++)
                    if (buf[p + i] != buf[lay_p + i]) {
                        good = 0;
                        break;
                    }
            uint64_t ident = 0;
            if (good)
                for (Py_ssize_t i = lay_sp2 + 1; i < lay_hash; i++) {
                    const int v = hexval[buf[p + i]];
                    if (v < 0) {
                        good = 0;
                        break;
                    }
                    ident = ident * 16 + (uint64_t)v;
                }
            if (good) {
                const Py_ssize_t nb = (lay_nl - lay_cr - lay_hash - 1) / 2;
                const int bad = get_data(buf + p + lay_hash + 1, nb, r->data + 8 * rows);
                const Py_ssize_t frac = lay_dot >= 0 ? lay_close - lay_dot - 1 : 0;
                /* float("int.frac") = (int 10^d + frac) / 10^d: one rounding */
                const double t = (double)num / pow10_[frac];
                if (bad >= 0 && t <= MAX_TIMESTAMP) {
                    put_row(r, rows, t, ident, lay_hash - lay_sp2 - 1, nb);
                    rows++;
                    lines++;
                    lay_p = p;
                    p = nl + 1;
                    continue;
                }
            }
        }
        Py_ssize_t e = p;
        while (e < stop && buf[e] != '\n')
            e++;
        if (e == stop && !final)
            break;
        const Py_ssize_t nxt = e + 1;
        const int cr = e > p && buf[e - 1] == '\r';
        if (cr) /* "\r\n" */
            e--;
        int ok = 0;
        /* "(" digits [. digits] ")" */
        if (e - p >= 8 && buf[p] == '(') {
            Py_ssize_t q = p + 1, nd = 0, frac = 0, dot = -1;
            uint64_t num = 0; /* wraps beyond 19 digits: refused by nd anyway */
            while (q < e) {
                const uint8_t c = buf[q];
                if (c >= '0' && c <= '9') {
                    num = num * 10 + (uint64_t)(c - '0');
                    nd++;
                    frac += dot >= 0;
                } else if (c == '.' && dot < 0) {
                    dot = q - p;
                } else {
                    break;
                }
                q++;
            }
            if (0 < nd && nd <= MAX_DIGITS && num <= MAX_EXACT && q + 2 < e && buf[q] == ')'
                && buf[q + 1] == ' ') {
                const Py_ssize_t close = q - p;
                /* " " channel (printable, no space) " " */
                q += 2;
                const Py_ssize_t c0 = q;
                while (q < e && buf[q] >= 33 && buf[q] <= 126)
                    q++;
                if (c0 < q && q < e && buf[q] == ' ') {
                    const Py_ssize_t sp2 = q - p;
                    /* 3 or 8 hex digits "#" */
                    q++;
                    const Py_ssize_t i0 = q;
                    uint64_t ident = 0;
                    while (q < e) {
                        const int v = hexval[buf[q]];
                        if (v < 0)
                            break;
                        ident = ident * 16 + (uint64_t)v;
                        q++;
                    }
                    const Py_ssize_t nid = q - i0;
                    if ((nid == 3 || nid == 8) && q < e && buf[q] == '#') {
                        const Py_ssize_t hash = q - p;
                        /* 0..8 data bytes, two hex digits each, to the end of the line */
                        q++;
                        const Py_ssize_t nhex = e - q;
                        if (nhex % 2 == 0 && nhex <= 16) {
                            const Py_ssize_t nb = nhex / 2;
                            const int bad = get_data(buf + q, nb, r->data + 8 * rows);
                            const double t = (double)num / pow10_[frac];
                            if (bad >= 0 && t <= MAX_TIMESTAMP) {
                                put_row(r, rows, t, ident, nid, nb);
                                ok = 1;
                                if (nxt <= stop) {
                                    /* a newline ends it: remember the layout */
                                    lay_p = p;
                                    lay_nl = nxt - 1 - p;
                                    lay_cr = cr;
                                    lay_dot = dot;
                                    lay_close = close;
                                    lay_sp2 = sp2;
                                    lay_hash = hash;
                                }
                            }
                        }
                    }
                }
            }
        }
        if (e > p) {
            if (ok) {
                rows++;
            } else {
                int64_t *s = r->slow + 4 * slow;
                s[0] = rows;
                s[1] = p;
                s[2] = e;
                s[3] = lines;
                slow++;
            }
        }
        lines++;
        p = nxt;
    }
    *used = p < stop ? p : stop;
    *nrows = rows;
    *nslow = slow;
    *nlines = lines;
}

/* Decimal digits of v >= 0, at least `width` of them (zero-padded), at out; the end. */
static inline Py_ssize_t put_uint(uint8_t *out, Py_ssize_t o, int64_t v, int width)
{
    int n = 1;
    for (int64_t x = v / 10; x > 0; x /= 10)
        n++;
    if (n < width)
        n = width;
    for (int k = n - 1; k >= 0; k--) {
        out[o + k] = (uint8_t)('0' + v % 10);
        v /= 10;
    }
    return o + n;
}

/* Digits of v >= 0 in base b */
static inline Py_ssize_t ndigits(int64_t v, int b)
{
    Py_ssize_t n = 1;
    for (v /= b; v > 0; v /= b)
        n++;
    return n;
}

/* The arrays of a block for format_lines; data is (rows, width). */
typedef struct {
    const int64_t *sec, *usec;
    const uint32_t *aid;
    const uint8_t *ext, *rtr, *err, *dlc, *data;
    Py_ssize_t width;
    const uint8_t *channel;
    Py_ssize_t chlen;
} Block;

/* Bytes of the line of row k */
static Py_ssize_t line_length(const Block *b, Py_ssize_t k)
{
    const Py_ssize_t us = ndigits(b->usec[k], 10);
    Py_ssize_t len = 1 + ndigits(b->sec[k], 10) + 1 + (us < 6 ? 6 : us) + 2 + b->chlen + 1;
    int64_t cid = b->aid[k];
    Py_ssize_t w = 3;
    if (b->err[k]) {
        cid |= CAN_ERR_FLAG;
        w = 8;
    } else if (b->ext[k]) {
        w = 8;
    }
    const Py_ssize_t nid = ndigits(cid, 16);
    len += (nid < w ? w : nid) + 1;
    if (b->rtr[k]) {
        len += 1;
    } else {
        const Py_ssize_t d = b->dlc[k] > b->width ? b->width : b->dlc[k];
        len += (b->dlc[k] > 8 ? 2 : 0) + 2 * d;
    }
    return len + 1;
}

/* Write "(sec.usec) channel ID#DATA\n" per row into out; the length, or -1 when a row
 * would not fit (nothing is written beyond cap). */
static Py_ssize_t format_lines(Py_ssize_t n, const Block *b, uint8_t *out, Py_ssize_t cap)
{
    Py_ssize_t o = 0;
    for (Py_ssize_t k = 0; k < n; k++) {
        if (line_length(b, k) > cap - o)
            return -1;
        out[o] = '(';
        o = put_uint(out, o + 1, b->sec[k], 1);
        out[o] = '.';
        o = put_uint(out, o + 1, b->usec[k], 6);
        out[o] = ')';
        out[o + 1] = ' ';
        o += 2;
        for (Py_ssize_t j = 0; j < b->chlen; j++)
            out[o + j] = b->channel[j];
        o += b->chlen;
        out[o++] = ' ';
        /* ID: %08X of id | CAN_ERR_FLAG for error frames, %08X extended, %03X standard */
        int64_t cid = b->aid[k];
        Py_ssize_t w = 3;
        if (b->err[k]) {
            cid |= CAN_ERR_FLAG;
            w = 8;
        } else if (b->ext[k]) {
            w = 8;
        }
        Py_ssize_t nid = ndigits(cid, 16);
        if (nid < w)
            nid = w;
        for (Py_ssize_t j = nid - 1; j >= 0; j--) {
            out[o + j] = (uint8_t)hexchars[cid & 15];
            cid >>= 4;
        }
        o += nid;
        out[o++] = '#';
        /* DATA: R remote, "#0" + hex beyond 8 bytes (CAN FD), else the hex bytes */
        if (b->rtr[k]) {
            out[o++] = 'R';
        } else {
            Py_ssize_t d = b->dlc[k];
            if (d > 8) {
                out[o] = '#';
                out[o + 1] = '0';
                o += 2;
            }
            if (d > b->width)
                d = b->width;
            const uint8_t *row = b->data + k * b->width;
            for (Py_ssize_t j = 0; j < d; j++) {
                out[o] = (uint8_t)hexchars[row[j] >> 4];
                out[o + 1] = (uint8_t)hexchars[row[j] & 15];
                o += 2;
            }
        }
        out[o++] = '\n';
    }
    return o;
}

/* ================================================================= Python glue */
PyDoc_STRVAR(parse_doc,
"parse(buf, stop, final, t, aid, ext, err, dlc, data, slow, /)\n"
"--\n\n"
"Parse whole lines of buf[:stop] into the rows of the output arrays\n"
"(canrls.can.candump.parse); returns (used, rows, slow, lines).");

static PyObject *py_parse(PyObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    (void)self;
    static const Spec spec[] = {
        {0, "buf", U8, 1, RO}, {3, "t", F64, 1, RW}, {4, "aid", U32, 1, RW},
        {5, "ext", BOOL, 1, RW}, {6, "err", BOOL, 1, RW}, {7, "dlc", U8, 1, RW},
        {8, "data", U8, 2, RW}, {9, "slow", I64, 2, RW},
    };
    Args a = {.fn = "parse", .count = 0};
    Py_buffer *b[COUNT(spec)];
    int64_t stop;
    int final;
    PyObject *res = NULL;
    if (!start(&a, nargs, 10) || !as_int64(args[1], &stop) || !as_bool(args[2], &final))
        return NULL;
    if (take(&a, args, spec, COUNT(spec), b, F64)) {
        const Py_ssize_t cap = dim(b[1], 0);
        if (stop < 0 || stop > dim(b[0], 0)) {
            PyErr_Format(PyExc_ValueError, "parse: stop %lld is outside buf (%zd bytes)",
                         (long long)stop, dim(b[0], 0));
        } else if (need(&a, b[2], "aid", cap, -1) && need(&a, b[3], "ext", cap, -1)
                   && need(&a, b[4], "err", cap, -1) && need(&a, b[5], "dlc", cap, -1)
                   && need(&a, b[6], "data", cap, 8) && need(&a, b[7], "slow", cap, 4)) {
            Rows r = {.t = D(b[1]), .aid = W(b[2]), .ext = U(b[3]), .err = U(b[4]),
                      .dlc = U(b[5]), .data = U(b[6]), .slow = I(b[7]), .cap = cap};
            Py_ssize_t used, rows, slow, lines;
            Py_BEGIN_ALLOW_THREADS
            parse(U(b[0]), (Py_ssize_t)stop, final, &r, &used, &rows, &slow, &lines);
            Py_END_ALLOW_THREADS
            res = Py_BuildValue("(nnnn)", used, rows, slow, lines);
        }
    }
    release(&a);
    return res;
}

PyDoc_STRVAR(format_lines_doc,
"format_lines(sec, usec, aid, ext, rtr, err, dlc, data, channel, out) -> int\n"
"--\n\n"
"Write '(sec.usec) channel ID#DATA\\n' per row into out; return the length\n"
"(canrls.can.candump.format_lines). ValueError when out is too small.");

static PyObject *py_format_lines(PyObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    (void)self;
    static const Spec spec[] = {
        {0, "sec", I64, 1, RO}, {1, "usec", I64, 1, RO}, {2, "aid", U32, 1, RO},
        {3, "ext", BOOL, 1, RO}, {4, "rtr", BOOL, 1, RO}, {5, "err", BOOL, 1, RO},
        {6, "dlc", U8, 1, RO}, {7, "data", U8, 2, RO}, {8, "channel", U8, 1, RO},
        {9, "out", U8, 1, RW},
    };
    Args a = {.fn = "format_lines", .count = 0};
    Py_buffer *b[COUNT(spec)];
    PyObject *res = NULL;
    if (!start(&a, nargs, 10))
        return NULL;
    if (take(&a, args, spec, COUNT(spec), b, F64)) {
        const Py_ssize_t n = dim(b[0], 0);
        if (need(&a, b[1], "usec", n, -1) && need(&a, b[2], "aid", n, -1)
            && need(&a, b[3], "ext", n, -1) && need(&a, b[4], "rtr", n, -1)
            && need(&a, b[5], "err", n, -1) && need(&a, b[6], "dlc", n, -1)
            && need(&a, b[7], "data", n, dim(b[7], 1))) {
            const Block blk = {.sec = I(b[0]), .usec = I(b[1]), .aid = W(b[2]),
                               .ext = U(b[3]), .rtr = U(b[4]), .err = U(b[5]),
                               .dlc = U(b[6]), .data = U(b[7]), .width = dim(b[7], 1),
                               .channel = U(b[8]), .chlen = dim(b[8], 0)};
            int negative = 0;
            for (Py_ssize_t k = 0; k < n; k++)
                negative |= blk.sec[k] < 0 || blk.usec[k] < 0;
            Py_ssize_t len = -1;
            if (negative) {
                PyErr_SetString(PyExc_ValueError,
                                "format_lines: sec and usec must be >= 0");
            } else {
                Py_BEGIN_ALLOW_THREADS
                len = format_lines(n, &blk, U(b[9]), dim(b[9], 0));
                Py_END_ALLOW_THREADS
                if (len < 0)
                    PyErr_SetString(PyExc_ValueError, "format_lines: out is too small");
                else
                    res = PyLong_FromSsize_t(len);
            }
        }
    }
    release(&a);
    return res;
}

/* ================================================================== module */
static PyMethodDef methods[] = {
    {"parse", (PyCFunction)(void (*)(void))py_parse, METH_FASTCALL, parse_doc},
    {"format_lines", (PyCFunction)(void (*)(void))py_format_lines, METH_FASTCALL,
     format_lines_doc},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {
    PyModuleDef_HEAD_INIT,
    .m_name = "canrls._candump",
    .m_doc = "The candump reader's and writer's loops (C, see src/canrls/c/host/candump.c).",
    .m_size = 0,
    .m_methods = methods,
};

PyMODINIT_FUNC PyInit__candump(void)
{
    init_tables();
    PyObject *m = PyModule_Create(&module);
    if (!m)
        return NULL;
    PyObject *max_t = PyFloat_FromDouble(MAX_TIMESTAMP);
    if (PyModule_AddIntConstant(m, "CAN_ERR_FLAG", CAN_ERR_FLAG) < 0
        || PyModule_AddIntConstant(m, "EFF_MASK", EFF_MASK) < 0
        || PyModule_AddObjectRef(m, "MAX_TIMESTAMP", max_t) < 0) {
        Py_XDECREF(max_t);
        Py_DECREF(m);
        return NULL;
    }
    Py_DECREF(max_t);
    return m;
}
