/* canrls._can: the per-frame loops of the CAN layer (strict decoding and pairing).
 *
 * The live path (canrls run) and the offline replay run the same code, so a log
 * replayed offline gives the samples the daemon built, bit for bit. Each function is the loop of one Python caller, which
 * owns the arrays (allocation, growth, dtypes) and documents the layout:
 *
 *   crc8          canrls.can.protocol._crc_vector     E2E CRC-8 of every row
 *   gather_check  canrls.can.protocol.Decoder         payload bytes + remote/length/CRC
 *   counters      canrls.can.protocol._counter_kernel alive-counter classification
 *   decode_fast   canrls.can.protocol._fast_kernel    one-pass decoding of a block
 *   push          canrls.processor.pairing.Pairer           merge into stream order + pairing
 *
 * Arrays arrive through the buffer protocol (C-contiguous numpy arrays; each checked
 * for its item size, format and length before the loop, which runs without the GIL).
 * Floating point: IEEE double, no contraction (-ffp-contract=off), the operations in
 * the order the Python documentation of each function states.
 */

#define PY_SSIZE_T_CLEAN
#include <Python.h>

#include <math.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>

/* ------------------------------------------------------------------------- */
/* buffers                                                                     */
/* ------------------------------------------------------------------------- */

enum { K_U8, K_BOOL, K_U32, K_I64, K_F64 };

typedef struct {
    Py_buffer view;
    int held;
} Buf;

static int kind_ok(const Py_buffer *v, int kind)
{
    const char *f = v->format ? v->format : "B";
    if (*f == '<' || *f == '=' || *f == '@')
        f++;
    switch (kind) {
    case K_U8:
        return v->itemsize == 1 && (strcmp(f, "B") == 0);
    case K_BOOL:
        return v->itemsize == 1 && (strcmp(f, "?") == 0 || strcmp(f, "B") == 0);
    case K_U32:
        return v->itemsize == 4 && (strcmp(f, "I") == 0 || strcmp(f, "L") == 0);
    case K_I64:
        return v->itemsize == 8 && (strcmp(f, "l") == 0 || strcmp(f, "q") == 0 ||
                                    strcmp(f, "n") == 0);
    case K_F64:
        return v->itemsize == 8 && strcmp(f, "d") == 0;
    }
    return 0;
}

/* Take the buffer of ``obj``: C-contiguous, of ``kind``, at least ``min_items`` items,
 * writable when asked. Sets a Python error and returns 0 on failure. */
static int get(Buf *b, PyObject *obj, int kind, Py_ssize_t min_items, int writable,
               const char *name)
{
    int flags = PyBUF_C_CONTIGUOUS | PyBUF_FORMAT | (writable ? PyBUF_WRITABLE : 0);
    b->held = 0;
    if (PyObject_GetBuffer(obj, &b->view, flags) < 0)
        return 0;
    b->held = 1;
    if (!kind_ok(&b->view, kind)) {
        PyErr_Format(PyExc_TypeError, "canrls._can: %s has the wrong dtype (format %s)",
                     name, b->view.format ? b->view.format : "?");
        return 0;
    }
    if (b->view.len / b->view.itemsize < min_items) {
        PyErr_Format(PyExc_ValueError, "canrls._can: %s holds %zd items, needs %zd", name,
                     b->view.len / b->view.itemsize, min_items);
        return 0;
    }
    return 1;
}

static Py_ssize_t items(const Buf *b) { return b->view.len / b->view.itemsize; }

static void release(Buf *bufs, int n)
{
    for (int k = 0; k < n; k++)
        if (bufs[k].held) {
            PyBuffer_Release(&bufs[k].view);
            bufs[k].held = 0;
        }
}

#define U8P(b) ((uint8_t *)(b).view.buf)
#define I64P(b) ((int64_t *)(b).view.buf)
#define F64P(b) ((double *)(b).view.buf)
#define U32P(b) ((uint32_t *)(b).view.buf)

/* messages of a protocol, at most (the pairing keeps a bit mask of them), and roles */
#define MAX_MESSAGES 62
#define MAX_ROLES 64

#if defined(__GNUC__)
#define NOINLINE __attribute__((noinline)) /* a loop in a function of its own: registers */
#define INLINE __attribute__((always_inline)) inline /* a step of a frame loop */
#else
#define NOINLINE
#define INLINE inline
#endif

/* Python's floor modulo for a positive modulus */
static int64_t pymod(int64_t a, int64_t m)
{
    int64_t r = a % m;
    return r < 0 ? r + m : r;
}

/* ------------------------------------------------------------------------- */
/* CRC (canrls.can.e2e.e2e_crc)                                                */
/* ------------------------------------------------------------------------- */

/* The CRC is a table walk, c = T[c ^ byte], with the table T of canrls.can.e2e. T is
 * linear over GF(2) (T[a ^ b] = T[a] ^ T[b]), so the register after the bytes b_1..b_m
 * from c is T^m[c ^ b_1] ^ T^(m-1)[b_2] ^ ... ^ T[b_m]: for m <= 8 the lookups are
 * independent instead of a chain. ``powers`` (8, 256) holds T, T^2, ..., T^8
 * (canrls.can.protocol._CRC8_POWERS); row k - 1 is T^k. */
#define CRC_POWERS 8

/* The CRC-8 register after the frame ID: init 0xFF, ID low then high byte. */
static uint8_t crc_id(int64_t frame_id, const uint8_t *powers)
{
    uint8_t c = powers[0xFF ^ (frame_id & 0xFF)];
    return powers[c ^ ((frame_id >> 8) & 0xFF)];
}

/* The CRC byte of a payload row from the register ``c`` after the ID (crc_id): payload
 * bytes 1..length-1, xor 0xFF. */
static INLINE uint8_t crc_payload(uint8_t c, const uint8_t *restrict row, int64_t length,
                                  const uint8_t *restrict powers)
{
    int64_t m = length - 1;
    if (m >= 1 && m <= CRC_POWERS) {
        uint8_t x = powers[256 * (m - 1) + (uint8_t)(c ^ row[1])];
        for (int64_t j = 2; j <= m; j++)
            x ^= powers[256 * (m - j) + row[j]];
        return (uint8_t)(x ^ 0xFF);
    }
    for (int64_t j = 1; j < length; j++)
        c = powers[c ^ row[j]];
    return (uint8_t)(c ^ 0xFF);
}

static uint8_t crc_row(int64_t frame_id, const uint8_t *row, int64_t length,
                       const uint8_t *powers)
{
    return crc_payload(crc_id(frame_id, powers), row, length, powers);
}

/* crc8(frame_id, data (N, W) uint8, width W, length, powers (8, 256) uint8, out (N,) uint8) */
static PyObject *py_crc8(PyObject *self, PyObject *args)
{
    (void)self;
    long long frame_id, width, length;
    PyObject *o_data, *o_table, *o_out;
    if (!PyArg_ParseTuple(args, "LOLLOO", &frame_id, &o_data, &width, &length, &o_table,
                          &o_out))
        return NULL;
    Buf b[3];
    memset(b, 0, sizeof b);
    if (!get(&b[0], o_data, K_U8, 0, 0, "data") || !get(&b[1], o_table, K_U8, 256 * CRC_POWERS, 0, "powers") ||
        !get(&b[2], o_out, K_U8, 0, 1, "out"))
        goto fail;
    Py_ssize_t n = items(&b[2]);
    if (width < length || length < 1 || items(&b[0]) < n * width) {
        PyErr_SetString(PyExc_ValueError, "canrls._can.crc8: data too small");
        goto fail;
    }
    Py_BEGIN_ALLOW_THREADS
    for (Py_ssize_t k = 0; k < n; k++)
        U8P(b[2])[k] = crc_row(frame_id, U8P(b[0]) + k * width, length, U8P(b[1]));
    Py_END_ALLOW_THREADS
    release(b, 3);
    Py_RETURN_NONE;
fail:
    release(b, 3);
    return NULL;
}

/* ------------------------------------------------------------------------- */
/* gather and check (Decoder._decode_message)                                  */
/* ------------------------------------------------------------------------- */

/* gather_check(data (N, W), width, rows (R,) int64, length, is_remote (N,), dlc (N,),
 *              check_crc, frame_id, powers, out (R, length) uint8, flags (R,) uint8) -> int
 * Copy data[rows, :length] into out; flag the first check each row fails: 1 remote,
 * 2 length (DLC), 4 CRC (only when check_crc). Returns the flagged rows. */
static PyObject *py_gather_check(PyObject *self, PyObject *args)
{
    (void)self;
    PyObject *o_data, *o_rows, *o_remote, *o_dlc, *o_table, *o_out, *o_flags;
    long long width, length, frame_id;
    int check_crc;
    if (!PyArg_ParseTuple(args, "OLOLOOpLOOO", &o_data, &width, &o_rows, &length, &o_remote,
                          &o_dlc, &check_crc, &frame_id, &o_table, &o_out, &o_flags))
        return NULL;
    Buf b[7];
    memset(b, 0, sizeof b);
    if (!get(&b[0], o_data, K_U8, 0, 0, "data") || !get(&b[1], o_rows, K_I64, 0, 0, "rows") ||
        !get(&b[2], o_remote, K_BOOL, 0, 0, "is_remote") ||
        !get(&b[3], o_dlc, K_U8, 0, 0, "dlc") || !get(&b[4], o_table, K_U8, 256 * CRC_POWERS, 0, "powers"))
        goto fail;
    Py_ssize_t n_rows = items(&b[1]);
    if (!get(&b[5], o_out, K_U8, n_rows * length, 1, "out") ||
        !get(&b[6], o_flags, K_U8, n_rows, 1, "flags"))
        goto fail;
    Py_ssize_t n = items(&b[2]);
    if (items(&b[3]) < n || items(&b[0]) < n * width || width < length) {
        PyErr_SetString(PyExc_ValueError, "canrls._can.gather_check: arrays too small");
        goto fail;
    }
    const int64_t *rows = I64P(b[1]);
    for (Py_ssize_t i = 0; i < n_rows; i++)
        if (rows[i] < 0 || rows[i] >= n) {
            PyErr_SetString(PyExc_IndexError, "canrls._can.gather_check: row out of range");
            goto fail;
        }
    long long bad = 0;
    Py_BEGIN_ALLOW_THREADS
    const uint8_t *data = U8P(b[0]), *remote = U8P(b[2]), *dlc = U8P(b[3]);
    uint8_t *out = U8P(b[5]), *flags = U8P(b[6]);
    for (Py_ssize_t i = 0; i < n_rows; i++) {
        int64_t r = rows[i];
        const uint8_t *row = data + r * width;
        memcpy(out + i * length, row, (size_t)length);
        uint8_t f = 0;
        if (remote[r])
            f = 1;
        else if (dlc[r] != length)
            f = 2;
        else if (check_crc && crc_row(frame_id, row, length, U8P(b[4])) != row[0])
            f = 4;
        flags[i] = f;
        if (f)
            bad++;
    }
    Py_END_ALLOW_THREADS
    release(b, 7);
    return PyLong_FromLongLong(bad);
fail:
    release(b, 7);
    return NULL;
}

/* ------------------------------------------------------------------------- */
/* alive counters (canrls.can.protocol._counter_step)                          */
/* ------------------------------------------------------------------------- */

enum { STATUS_OK = 0, STATUS_REPEATED = 1, STATUS_STALE = 2, STATUS_SEQUENCE = 3 };

/* longest time [s] between two accepted frames from which whole counter wraps are
 * inferred (canrls.processor.pairing.FORWARD_STEP: a longer jump is a clock step) */
#define COUNTER_MAX_DT 1.0

/* the counter state of one message, as canrls.can.protocol._counter_kernel lays it out:
 * [last, run, prev, skipped, trusted] (int64) and last_t (double) */
enum { ST_LAST, ST_RUN, ST_PREV, ST_SKIPPED, ST_TRUSTED, ST_COUNTER_COLS };
/* the decoder's row per message: the counter state, then the running sequence number of a
 * message without counter (canrls.can.protocol.Decoder._counters) */
enum { ST_SEQ = ST_COUNTER_COLS, ST_COLS };

typedef struct {
    /* last: the counter of the last accepted frame (-1: none yet); run: consecutive frames
     * rejected for their counter that count up by one, prev: the last one's counter;
     * skipped: frames received since the last accepted one and rejected (they are not
     * lost); trusted: the last accepted frame's time agreed with its counter */
    int64_t last, run, prev, skipped, trusted;
    double last_t;
} CounterState;

static INLINE CounterState counter_load(const int64_t *st, double t)
{
    CounterState s = {st[ST_LAST], st[ST_RUN], st[ST_PREV], st[ST_SKIPPED], st[ST_TRUSTED], t};
    return s;
}

static INLINE void counter_store(const CounterState *s, int64_t *st, double *t)
{
    st[ST_LAST] = s->last;
    st[ST_RUN] = s->run;
    st[ST_PREV] = s->prev;
    st[ST_SKIPPED] = s->skipped;
    st[ST_TRUSTED] = s->trusted;
    *t = s->last_t;
}

/* Classify one alive counter c received at t (see _counter_kernel's docstring); updates
 * the state, returns the status and sets *lost. */
static INLINE int counter_step(int64_t c, double t, int64_t mod, int64_t window, double period,
                        CounterState *s, int64_t *lost)
{
    *lost = 0;
    if (s->last < 0) {
        s->last = c;
        s->run = 0;
        s->skipped = 0;
        s->trusted = 1;
        s->last_t = t;
        return STATUS_OK;
    }
    int64_t d = pymod(c - s->last, mod);
    double dt = t - s->last_t;
    /* the time tells wraps only up to a clock step: a jump beyond COUNTER_MAX_DT is one
     * (canrls.processor.pairing.FORWARD_STEP), not thousands of frames lost */
    int timed = period > 0.0 && isfinite(dt) && dt <= COUNTER_MAX_DT;
    if (d == 0 && !(timed && dt >= ((double)mod - 0.5) * period)) {
        /* a copy of the last frame arrives with it (no place of its own in the
         * sequence); a period or more later it took a frame's place (a wrong counter) */
        if (timed && dt >= 0.5 * period)
            s->skipped += 1;
        return STATUS_REPEATED;
    }
    if (d == 0)
        d = mod;
    /* time enough since the last accepted frame for a jump of d: d - 1 frames lost */
    int in_time = timed && dt >= ((double)d - 0.5) * period;
    int status = STATUS_OK;
    if (d >= mod - window && !in_time)
        status = STATUS_STALE; /* a jump backwards */
    else if (d >= 2 && timed && s->trusted && !in_time)
        status = STATUS_SEQUENCE; /* ahead of the time: a wrong counter, not a loss */
    if (status != STATUS_OK) {
        int64_t run = s->run;
        if (run > 0 && c == pymod(s->prev + 1, mod))
            run += 1;
        else
            run = 1;
        s->run = run;
        s->prev = c;
        if (status == STATUS_STALE && run >= 3) {
            d = 1; /* resynchronise on a consistent new sequence (loss unknown) */
        } else if (status == STATUS_SEQUENCE && run >= 2) {
            /* continues the sequence of the frame rejected before it: frames were lost
             * after all (timestamps bunched by the receiver), d - 1 less the skipped */
        } else {
            s->skipped += 1;
            return status;
        }
    }
    int64_t gap = d;
    if (timed) {
        /* k = floor((dt / period - d) / M + 0.5) whole wraps, when k > 0 (x >= 1) and the
         * time agrees with them, |dt / period - d - k M| < 1/2: otherwise the time
         * stepped (a clock step forward under 1 s) and says nothing of wraps */
        double x = (dt / period - (double)d) / (double)mod + 0.5;
        if (x >= 1.0) {
            double k = floor(x);
            if (fabs(dt / period - (double)d - k * (double)mod) < 0.5)
                gap += (int64_t)k * mod;
        }
    }
    /* lost = gap - 1 - skipped (>= 0): a frame received and rejected is not lost */
    *lost = gap - 1 - s->skipped;
    if (*lost < 0)
        *lost = 0;
    /* the next frame's jump is held against this one's time only if this time agrees
     * with this counter: |dt - gap T| < T / 2 (a swapped frame arrives a period late) */
    s->trusted = !timed || fabs(dt - (double)gap * period) < 0.5 * period;
    s->last = c;
    s->run = 0;
    s->skipped = 0;
    s->last_t = t;
    return STATUS_OK;
}

/* counters(c (N,) int64, t (N,) f64, mod, window, period, state (5,) int64,
 *          state_t (1,) f64, status (N,) uint8, lost (N,) int64[, skip (N,) bool])
 * skip: frames rejected before the counter check (length, CRC): their counters are not
 * read, they count as received (CounterState.skipped), status 0 and lost 0. */
static PyObject *py_counters(PyObject *self, PyObject *args)
{
    (void)self;
    PyObject *o_c, *o_t, *o_state, *o_state_t, *o_status, *o_lost, *o_skip = Py_None;
    long long mod, window;
    double period;
    if (!PyArg_ParseTuple(args, "OOLLdOOOO|O", &o_c, &o_t, &mod, &window, &period, &o_state,
                          &o_state_t, &o_status, &o_lost, &o_skip))
        return NULL;
    Buf b[7];
    memset(b, 0, sizeof b);
    if (!get(&b[0], o_c, K_I64, 0, 0, "c"))
        goto fail;
    Py_ssize_t n = items(&b[0]);
    if (!get(&b[1], o_t, K_F64, n, 0, "t") ||
        !get(&b[2], o_state, K_I64, ST_COUNTER_COLS, 1, "state") ||
        !get(&b[3], o_state_t, K_F64, 1, 1, "state_t") ||
        !get(&b[4], o_status, K_U8, n, 1, "status") || !get(&b[5], o_lost, K_I64, n, 1, "lost"))
        goto fail;
    if (o_skip != Py_None && !get(&b[6], o_skip, K_BOOL, n, 0, "skip"))
        goto fail;
    if (mod < 1) {
        PyErr_SetString(PyExc_ValueError, "canrls._can.counters: modulo must be >= 1");
        goto fail;
    }
    Py_BEGIN_ALLOW_THREADS
    int64_t *st = I64P(b[2]);
    CounterState s = counter_load(st, F64P(b[3])[0]);
    const int64_t *c = I64P(b[0]);
    const double *t = F64P(b[1]);
    const uint8_t *skip = o_skip != Py_None ? U8P(b[6]) : NULL;
    uint8_t *status = U8P(b[4]);
    int64_t *lost = I64P(b[5]);
    for (Py_ssize_t i = 0; i < n; i++) {
        if (skip && skip[i]) {
            s.skipped += s.last >= 0; /* received, rejected: not lost */
            status[i] = STATUS_OK;
            lost[i] = 0;
            continue;
        }
        status[i] = (uint8_t)counter_step(c[i], t[i], mod, window, period, &s, &lost[i]);
    }
    counter_store(&s, st, F64P(b[3]));
    Py_END_ALLOW_THREADS
    release(b, 7);
    Py_RETURN_NONE;
fail:
    release(b, 7);
    return NULL;
}

/* ------------------------------------------------------------------------- */
/* one-pass decoding (canrls.can.protocol._FastPlan)                           */
/* ------------------------------------------------------------------------- */

/* columns of _FastPlan.msg */
enum { M_ID, M_EXT, M_LEN, M_CRC, M_CHECK, M_MOD, M_WINDOW, M_COUNTER, M_SIG0, M_SIG1, M_TROW,
       M_COLS };
/* columns of _FastPlan.sig */
enum { S_SIGNED, S_FLOAT, S_MODE, S_LEN, S_BE, S_POS, S_SCALE, S_OFFSET, S_ROW, S_COLS };
/* columns of _FastPlan.sig_f */
enum { F_SCALE, F_OFFSET, F_LO, F_HI, F_SI, F_COLS };
/* SignalCodec.scaling modes */
enum { PHYS_IDENTITY, PHYS_INT, PHYS_FLOAT };

static INLINE uint64_t field(uint64_t le, uint64_t be, const int64_t *sig)
{
    int64_t L = sig[S_LEN];
    uint64_t mask = L >= 64 ? UINT64_MAX : (((uint64_t)1 << L) - 1);
    return ((sig[S_BE] ? be : le) >> sig[S_POS]) & mask;
}

/* The payload bytes 0..7 of a row (``length`` of them, the rest zero) as the
 * little-endian word ``*le`` and the big-endian word ``*be``. */
static INLINE void payload_words(const uint8_t *restrict row, int64_t length, int64_t width,
                          uint64_t *le, uint64_t *be)
{
#if defined(__GNUC__) && defined(__BYTE_ORDER__) && __BYTE_ORDER__ == __ORDER_LITTLE_ENDIAN__
    if (width >= 8) { /* one load, one byte swap */
        uint64_t w;
        memcpy(&w, row, 8);
        if (length < 8)
            w &= ((uint64_t)1 << (8 * length)) - 1;
        *le = w;
        *be = __builtin_bswap64(w);
        return;
    }
#else
    (void)width;
#endif
    uint64_t l = 0, b = 0;
    for (int64_t j = 0; j < (length < 8 ? length : 8); j++) {
        uint64_t byte = row[j];
        l |= byte << (8 * j);
        b |= byte << (56 - 8 * j);
    }
    *le = l;
    *be = b;
}

/* The loop of decode_fast over the n frames of a block: returns the frames decoded. */
NOINLINE static int64_t decode_block(int64_t n, const double *restrict t, const uint32_t *restrict aid,
                            const uint8_t *restrict ext, const uint8_t *restrict rtr,
                            const uint8_t *restrict err, const uint8_t *restrict dlc,
                            const uint8_t *restrict data, int64_t width, int64_t K,
                            const int64_t *restrict msg, const double *restrict period,
                            const int64_t *restrict sig, const double *restrict sig_f,
                            const uint8_t *restrict table, int64_t *restrict state,
                            double *restrict state_t, int64_t base, double *restrict out_f,
                            int64_t cols, int64_t *restrict out_i, int64_t *restrict counts)
{
    int64_t done;
    uint8_t crc0[MAX_MESSAGES]; /* the CRC register after each message's ID */
    for (int64_t k = 0; k < K; k++)
        crc0[k] = crc_id(msg[k * M_COLS + M_ID], table);
    for (int64_t k = 0; k < 2 * K + 1; k++)
        counts[k] = 0;
    done = n;
    for (int64_t i = 0; i < n; i++) {
        if (err[i]) {
            done = i;
            break;
        }
        int64_t k = 0;
        while (k < K && !((int64_t)aid[i] == msg[k * M_COLS + M_ID] &&
                          (ext[i] != 0) == (msg[k * M_COLS + M_EXT] != 0)))
            k++;
        if (k == K) {
            counts[2 * K] += 1; /* foreign */
            continue;
        }
        const int64_t *mk = msg + k * M_COLS;
        int64_t length = mk[M_LEN];
        const uint8_t *row = data + i * width;
        if (rtr[i] || dlc[i] != length || width < length ||
            (mk[M_CRC] && crc_payload(crc0[k], row, length, table) != row[0])) {
            done = i;
            break;
        }
        uint64_t le, be; /* payload bytes 0..7 as little- and big-endian words */
        payload_words(row, length, width, &le, &be);
        int64_t c = counts[k];
        int64_t q = mk[M_COUNTER];
        int check = q >= 0 && mk[M_CHECK] != 0;
        int64_t *sk = state + ST_COLS * k;
        CounterState cs = counter_load(sk, state_t[k]);
        int64_t lost = 0, counter;
        int status = STATUS_OK;
        if (q >= 0) {
            counter = (int64_t)field(le, be, sig + q * S_COLS);
            if (check)
                status = counter_step(counter, t[i], mk[M_MOD], mk[M_WINDOW], period[k], &cs,
                                      &lost);
        } else {
            counter = sk[ST_SEQ] + c;
        }
        if (status != STATUS_OK) {
            done = i;
            break;
        }
        int ok = 1;
        for (int64_t s = mk[M_SIG0]; s < mk[M_SIG1]; s++) {
            const int64_t *ss = sig + s * S_COLS;
            const double *sf = sig_f + s * F_COLS;
            uint64_t acc = field(le, be, ss);
            int64_t L = ss[S_LEN];
            int64_t raw = 0;
            double x, v;
            if (ss[S_FLOAT]) {
                if (L == 32) {
                    uint32_t u = (uint32_t)acc;
                    float f;
                    memcpy(&f, &u, sizeof f);
                    x = (double)f;
                } else {
                    memcpy(&x, &acc, sizeof x);
                }
            } else if (ss[S_SIGNED]) {
                uint64_t u = acc << (64 - L);
                memcpy(&raw, &u, sizeof raw);
                raw >>= (64 - L); /* arithmetic shift: sign extension */
                x = (double)raw;
            } else {
                raw = (int64_t)acc; /* exact below 64 bits: all unsigned PHYS_INT fields */
                x = (double)acc;
            }
            int64_t mode = ss[S_MODE];
            if (mode == PHYS_INT)
                v = (double)(int64_t)((uint64_t)raw * (uint64_t)ss[S_SCALE] +
                                      (uint64_t)ss[S_OFFSET]);
            else if (mode == PHYS_FLOAT)
                v = x * sf[F_SCALE] + sf[F_OFFSET];
            else
                v = x;
            if (!isfinite(v) || v < sf[F_LO] || v > sf[F_HI]) {
                ok = 0;
                break;
            }
            out_f[ss[S_ROW] * cols + c] = v * sf[F_SI];
        }
        if (!ok) {
            done = i;
            break;
        }
        if (check) {
            counter_store(&cs, sk, &state_t[k]);
            counts[K + k] += lost;
        }
        out_f[mk[M_TROW] * cols + c] = t[i];
        out_i[2 * k * cols + c] = base + i;
        out_i[(2 * k + 1) * cols + c] = counter;
        counts[k] = c + 1;
    }
    for (int64_t k = 0; k < K; k++)
        if (msg[k * M_COLS + M_COUNTER] < 0)
            state[ST_COLS * k + ST_SEQ] += counts[k];
    return done;
}

/* decode_fast(t, arbitration_id, is_extended, is_remote, is_error, dlc, data, width,
 *             msg (K, M_COLS), period (K,), sig (S, S_COLS), sig_f (S, F_COLS), powers,
 *             state (K, 6) int64, state_t (K,), base, out_f (n_float, cols),
 *             out_i (2K, cols), counts (2K + 1,)) -> frames decoded
 * See canrls.can.protocol._fast_kernel. */
static PyObject *py_decode_fast(PyObject *self, PyObject *args)
{
    (void)self;
    PyObject *o[17];
    long long width, base;
    if (!PyArg_ParseTuple(args, "OOOOOOOLOOOOOOOLOOO", &o[0], &o[1], &o[2], &o[3], &o[4],
                          &o[5], &o[6], &width, &o[7], &o[8], &o[9], &o[10], &o[11], &o[12],
                          &o[13], &base, &o[14], &o[15], &o[16]))
        return NULL;
    Buf b[17];
    memset(b, 0, sizeof b);
    long long done = 0;
    if (!get(&b[0], o[0], K_F64, 0, 0, "t"))
        goto fail;
    Py_ssize_t n = items(&b[0]);
    if (!get(&b[1], o[1], K_U32, n, 0, "arbitration_id") ||
        !get(&b[2], o[2], K_BOOL, n, 0, "is_extended") ||
        !get(&b[3], o[3], K_BOOL, n, 0, "is_remote") ||
        !get(&b[4], o[4], K_BOOL, n, 0, "is_error") || !get(&b[5], o[5], K_U8, n, 0, "dlc") ||
        !get(&b[6], o[6], K_U8, n * width, 0, "data") || !get(&b[7], o[7], K_I64, 0, 0, "msg"))
        goto fail;
    Py_ssize_t K = items(&b[7]) / M_COLS;
    if (K > MAX_MESSAGES) {
        PyErr_SetString(PyExc_ValueError, "canrls._can.decode_fast: too many messages");
        goto fail;
    }
    if (!get(&b[8], o[8], K_F64, K, 0, "period") || !get(&b[9], o[9], K_I64, 0, 0, "sig") ||
        !get(&b[10], o[10], K_F64, 0, 0, "sig_f") || !get(&b[11], o[11], K_U8, 256 * CRC_POWERS, 0, "powers") ||
        !get(&b[12], o[12], K_I64, ST_COLS * K, 1, "state") ||
        !get(&b[13], o[13], K_F64, K, 1, "state_t") || !get(&b[14], o[14], K_F64, 0, 1, "out_f") ||
        !get(&b[15], o[15], K_I64, 0, 1, "out_i") ||
        !get(&b[16], o[16], K_I64, 2 * K + 1, 1, "counts"))
        goto fail;
    Py_ssize_t S = items(&b[9]) / S_COLS;
    Py_ssize_t cols = K ? items(&b[15]) / (2 * K) : 0;
    const int64_t *msg = I64P(b[7]), *sig = I64P(b[9]);
    /* every index the loop takes from the tables lies in its array */
    for (Py_ssize_t k = 0; k < K; k++) {
        const int64_t *mk = msg + k * M_COLS;
        if (mk[M_SIG0] < 0 || mk[M_SIG1] > S || mk[M_SIG0] > mk[M_SIG1] || mk[M_COUNTER] >= S ||
            mk[M_TROW] < 0 || (mk[M_TROW] + 1) * cols > items(&b[14]) ||
            (mk[M_COUNTER] >= 0 && mk[M_MOD] < 1) || mk[M_LEN] < 0) {
            PyErr_SetString(PyExc_ValueError, "canrls._can.decode_fast: bad message table");
            goto fail;
        }
    }
    for (Py_ssize_t s = 0; s < S; s++) {
        const int64_t *ss = sig + s * S_COLS;
        if (ss[S_LEN] < 1 || ss[S_LEN] > 64 || ss[S_POS] < 0 || ss[S_POS] > 63 || ss[S_ROW] < 0 ||
            (ss[S_ROW] + 1) * cols > items(&b[14])) {
            PyErr_SetString(PyExc_ValueError, "canrls._can.decode_fast: bad signal table");
            goto fail;
        }
    }
    for (Py_ssize_t k = 0; k < K; k++)
        for (int64_t s = msg[k * M_COLS + M_SIG0]; s < msg[k * M_COLS + M_SIG1]; s++)
            if ((s + 1) * F_COLS > items(&b[10])) {
                PyErr_SetString(PyExc_ValueError, "canrls._can.decode_fast: sig_f too small");
                goto fail;
            }
    if (cols < n) {
        PyErr_SetString(PyExc_ValueError, "canrls._can.decode_fast: outputs too small");
        goto fail;
    }
    Py_BEGIN_ALLOW_THREADS
    done = decode_block(n, F64P(b[0]), U32P(b[1]), U8P(b[2]), U8P(b[3]), U8P(b[4]), U8P(b[5]),
                        U8P(b[6]), width, K, I64P(b[7]), F64P(b[8]), I64P(b[9]), F64P(b[10]),
                        U8P(b[11]), I64P(b[12]), F64P(b[13]), base, F64P(b[14]), cols,
                        I64P(b[15]), I64P(b[16]));
    Py_END_ALLOW_THREADS
    release(b, 17);
    return PyLong_FromLongLong(done);
fail:
    release(b, 17);
    return NULL;
}

/* ------------------------------------------------------------------------- */
/* pairing (canrls.processor.pairing)                                                */
/* ------------------------------------------------------------------------- */

#define GI(g, c) gi[3 * (g) + (c)]
#define GF(g, c) gf[gcols * (g) + (c)]

/* kinds of clock fault (rows of ``clock``, canrls.processor.pairing.CLOCK_KINDS) */
enum { CLOCK_STEP_BACK, CLOCK_STEP_FORWARD, CLOCK_GAP, CLOCK_KINDS };

/* Finalise the open period in slot g: emit it when complete, else count its frames as
 * unpaired and its missing ones as lost; whole periods missing since the last finalised
 * period count as lost (unless the time base was re-anchored since: sf[3] = 0). The
 * last open slot moves into slot g (the slots stay compact). */
static INLINE void finalise(int64_t g, double *restrict gf, int64_t gcols,
                            int64_t *restrict gi, int64_t *restrict open, int64_t n_msg,
                            int64_t n_roles, int64_t full, double period, double *restrict sf,
                            int64_t *restrict si, int64_t *restrict counts,
                            double *restrict out_t, double *restrict out_v,
                            int64_t *restrict n_out)
{
    int complete = GI(g, 2) == full;
    if (sf[3] > 0 && period > 0.0) {
        /* gap = floor((t_min - t_min of the last period) / period + 0.5) - 1 whole
         * periods missing, when gap > 0 (y >= 2) */
        double y = (GF(g, 0) - sf[1]) / period + 0.5;
        if (y >= 2.0) {
            int64_t gap = (int64_t)floor(y) - 1;
            for (int64_t k = 0; k < n_msg; k++)
                counts[1 * n_msg + k] += gap;
        }
    }
    if (complete) {
        out_t[*n_out] = GF(g, 1);
        for (int64_t r = 0; r < n_roles; r++)
            out_v[*n_out * n_roles + r] = GF(g, 2 + r);
        *n_out += 1;
    } else {
        for (int64_t k = 0; k < n_msg; k++) {
            if (GI(g, 2) & ((int64_t)1 << k))
                counts[0 * n_msg + k] += 1;
            else
                counts[1 * n_msg + k] += 1;
        }
    }
    sf[1] = GF(g, 0);
    sf[2] = GF(g, 1);
    sf[3] = 1.0;
    for (int64_t k = 0; k < n_msg; k++)
        si[k] = ((GI(g, 2) >> k) & 1) ? GI(g, 1) : -2;
    int64_t last = *open - 1; /* keep the open slots compact: move the last one here */
    if (g != last) {
        for (int64_t c = 0; c < gcols; c++)
            GF(g, c) = GF(last, c);
        for (int64_t c = 0; c < 3; c++)
            GI(g, c) = GI(last, c);
    }
    *open = last;
}

/* The open slot with the oldest period (-1: none open). */
static INLINE int64_t oldest_open(const double *restrict gf, int64_t gcols, int64_t n_open)
{
    int64_t oldest = -1;
    for (int64_t g = 0; g < n_open; g++)
        if (oldest < 0 || GF(g, 0) < GF(oldest, 0))
            oldest = g;
    return oldest;
}

/* Process frames one at a time; return the number of samples written to out_*.
 * See canrls.processor.pairing (the module docstring and Pairer) for the rules and the state:
 * open periods are the slots 0 .. gi[0]-1 (kept compact): gi row 1 + g = [unused,
 * counter (-1: none), mask of messages present]; gf row g = [t_min, t_max, values of the
 * roles...]; sf = [newest frame time, t_min and t_max of the last finalised period,
 * whether there is one, offset of the time base]; si = per message: -2 if absent from
 * that period, else its counter (-1: none); counts[kind, message]; clock[kind].
 *
 * Time base: a frame's time is its timestamp + sf[4]. A frame more than ``back`` before
 * the newest is a clock step back: the open periods are finalised, and sf[4] re-anchored
 * so that the frame lies ``back`` after the newest (time stays monotonic, and the gap
 * restarts the filter downstream). A frame more than ``fwd`` after the newest is a clock
 * step forward (or a silence as long), more than ``gap`` a gap: open periods are
 * finalised; after a step no whole periods are counted lost across it. */
NOINLINE static int64_t pair_frames(const int64_t *restrict msg, const double *restrict t,
                           const int64_t *restrict cnt, const double *restrict vals,
                           const int64_t *restrict role_msg, int64_t n_roles, int64_t n_msg,
                           const double *restrict times, int flush, int64_t n,
                           double *restrict gf, int64_t G, int64_t *restrict gi_all,
                           double *restrict sf, int64_t *restrict si, int64_t *restrict counts,
                           int64_t *restrict clock, double *restrict out_t,
                           double *restrict out_v)
{
    const double tol = times[0], wait = times[1], period = times[2];
    const double back = times[3], fwd = times[4], gapb = times[5];
    const int64_t gcols = 2 + n_roles;
    const int64_t full = ((int64_t)1 << n_msg) - 1;
    int64_t n_out = 0;
    int64_t open_slots = gi_all[0];
    int64_t *open = &open_slots;
    int64_t *restrict gi = gi_all + 3; /* GI(g, .) is row 1 + g */
    for (int64_t f = 0; f < n + (flush ? 1 : 0); f++) {
        if (f < n) {
            int64_t m = msg[f];
            if (!isfinite(t[f])) {
                counts[4 * n_msg + m] += 1; /* no time: dropped as late */
                continue;
            }
            double tf = t[f] + sf[4];
            int64_t cf = cnt[f];
            double newest = sf[0];
            /* --- clock steps and gaps (none before the first frame: newest = -inf) */
            if (isfinite(newest) && (tf < newest - back || tf > newest + gapb)) {
                int step_back = tf < newest - back;
                if (step_back) {
                    clock[CLOCK_STEP_BACK] += 1;
                    /* re-anchor: tf' = newest + back */
                    sf[4] = newest + back - t[f];
                    tf = t[f] + sf[4];
                } else {
                    clock[tf > newest + fwd ? CLOCK_STEP_FORWARD : CLOCK_GAP] += 1;
                }
                /* the open periods cannot complete across the step: finalise them */
                int64_t g;
                while ((g = oldest_open(gf, gcols, *open)) >= 0)
                    finalise(g, gf, gcols, gi, open, n_msg, n_roles, full, period, sf, si,
                             counts, out_t, out_v, &n_out);
                if (step_back || tf > newest + fwd)
                    sf[3] = 0.0; /* no periods counted lost across a step */
                sf[0] = tf;
                newest = tf;
            }
            /* --- find the open period this frame belongs to (closest in time) */
            int64_t best = -1;
            double best_d = INFINITY;
            for (int64_t g = 0; g < *open; g++) {
                if (tf < GF(g, 1) - tol || tf > GF(g, 0) + tol)
                    continue;
                if (cf >= 0 && GI(g, 1) >= 0 && GI(g, 1) != cf)
                    continue;
                double d = fabs(tf - GF(g, 0));
                if (d < best_d) {
                    best_d = d;
                    best = g;
                }
            }
            int64_t g;
            if (best >= 0) {
                if (GI(best, 2) & ((int64_t)1 << m)) {
                    counts[2 * n_msg + m] += 1; /* duplicated */
                    continue;
                }
                g = best;
            } else {
                if (sf[3] > 0 && tf <= sf[1] + tol) {
                    /* at or before the last finalised period: a repeat of its frame, or late */
                    if (si[m] != -2 && tf >= sf[2] - tol && (cf < 0 || si[m] < 0 || si[m] == cf))
                        counts[2 * n_msg + m] += 1;
                    else
                        counts[4 * n_msg + m] += 1;
                    continue;
                }
                if (tf < newest - wait) {
                    counts[4 * n_msg + m] += 1; /* would be given up at once */
                    continue;
                }
                /* a free slot exists: finalisation keeps fewer than G periods open */
                g = *open;
                *open += 1;
                GI(g, 1) = -1;
                GI(g, 2) = 0;
                GF(g, 0) = tf;
                GF(g, 1) = tf;
                for (int64_t r = 0; r < n_roles; r++)
                    GF(g, 2 + r) = NAN;
            }
            if (tf + tol < newest)
                counts[3 * n_msg + m] += 1; /* reordered: a later period's frame came first */
            GI(g, 2) |= (int64_t)1 << m;
            if (cf >= 0 && GI(g, 1) < 0)
                GI(g, 1) = cf;
            if (tf < GF(g, 0))
                GF(g, 0) = tf;
            if (tf > GF(g, 1))
                GF(g, 1) = tf;
            for (int64_t r = 0; r < n_roles; r++)
                if (role_msg[r] == m)
                    GF(g, 2 + r) = vals[f * n_roles + r];
            if (tf > newest)
                sf[0] = tf;
        }
        /* --- finalise periods in time order */
        for (;;) {
            int64_t n_open = *open;
            int64_t g = oldest_open(gf, gcols, n_open);
            if (g < 0)
                break;
            int complete = GI(g, 2) == full;
            int expired = sf[0] - GF(g, 0) > wait;
            if (!(complete || expired || f >= n || n_open >= G))
                break;
            finalise(g, gf, gcols, gi, open, n_msg, n_roles, full, period, sf, si, counts,
                     out_t, out_v, &n_out);
        }
    }
    gi_all[0] = open_slots;
    return n_out;
}

/* K-way merge of the messages' frames, each sorted by stream index, into stream order;
 * equal indices keep message order, as a stable sort of the concatenation would. The
 * inputs are the arrays of each message (lens[k] frames of message k: idx[k], t[k],
 * cnt[k], or -1 without counters; vals[j] of role j, of message role_msg[j], NaN in the
 * rows of the other messages). 0 (nothing written) when a message's indices are not
 * ascending. */
NOINLINE static int merge_messages(int64_t K, const int64_t *restrict lens,
                                   const int64_t *const *idx, const double *const *t,
                                   const int64_t *const *cnt, int64_t R,
                                   const int64_t *restrict role_msg,
                                   const double *const *vals, int64_t *restrict out_msg,
                                   double *restrict out_t, int64_t *restrict out_cnt,
                                   double *restrict out_vals)
{
    int64_t pos[MAX_MESSAGES], n = 0;
    for (int64_t k = 0; k < K; k++) {
        const int64_t *ix = idx[k];
        for (int64_t i = 1; i < lens[k]; i++)
            if (ix[i] < ix[i - 1])
                return 0;
        pos[k] = 0;
        n += lens[k];
    }
    for (int64_t o = 0; o < n; o++) {
        int64_t best = -1, best_index = 0;
        for (int64_t k = 0; k < K; k++)
            if (pos[k] < lens[k] && (best < 0 || idx[k][pos[k]] < best_index)) {
                best = k;
                best_index = idx[k][pos[k]];
            }
        int64_t i = pos[best]++;
        out_msg[o] = best;
        out_t[o] = t[best][i];
        out_cnt[o] = cnt ? cnt[best][i] : -1;
        for (int64_t r = 0; r < R; r++)
            out_vals[o * R + r] = role_msg[r] == best ? vals[r][i] : NAN;
    }
    return 1;
}

/* Stable merge sort of the positions 0..n-1 by key[]: order (n,), tmp (n,) scratch. */
static void stable_order(const int64_t *key, int64_t n, int64_t *order, int64_t *tmp)
{
    for (int64_t i = 0; i < n; i++)
        order[i] = i;
    for (int64_t w = 1; w < n; w *= 2) {
        for (int64_t lo = 0; lo < n; lo += 2 * w) {
            int64_t mid = lo + w < n ? lo + w : n, hi = lo + 2 * w < n ? lo + 2 * w : n;
            int64_t a = lo, b = mid, o = lo;
            while (a < mid && b < hi)
                tmp[o++] = key[order[b]] < key[order[a]] ? order[b++] : order[a++];
            while (a < mid)
                tmp[o++] = order[a++];
            while (b < hi)
                tmp[o++] = order[b++];
        }
        memcpy(order, tmp, (size_t)n * sizeof(int64_t));
    }
}

/* push(index, t, cnt, vals (tuples: one array per message, vals one per role),
 *      use_counters, role_msg (R,), times [tolerance, wait, period, back, fwd, gap], flush,
 *      gf (G, 2 + R), gi (G + 1, 3), sf (5,), si (K,), counts (5, K), clock (3,),
 *      iwork (4, C) int64, fwork (3, C), vwork (3, C, R)) -> samples
 * The frames of one push in stream order (merge, else a stable sort by index), through
 * the pairing; the samples are in fwork[2, :samples] (times) and vwork[2, :samples]. */
static PyObject *py_push(PyObject *self, PyObject *args)
{
    (void)self;
    PyObject *o_index, *o_t, *o_cnt, *o_vals, *o_role, *o_times, *o_gf, *o_gi, *o_sf, *o_si,
        *o_counts, *o_clock, *o_iwork, *o_fwork, *o_vwork;
    int use_counters, flush;
    if (!PyArg_ParseTuple(args, "O!O!O!O!pOOpOOOOOOOOO", &PyTuple_Type, &o_index, &PyTuple_Type,
                          &o_t, &PyTuple_Type, &o_cnt, &PyTuple_Type, &o_vals, &use_counters,
                          &o_role, &o_times, &flush, &o_gf, &o_gi, &o_sf, &o_si, &o_counts, &o_clock,
                          &o_iwork, &o_fwork, &o_vwork))
        return NULL;
    Py_ssize_t K = PyTuple_GET_SIZE(o_index), R = PyTuple_GET_SIZE(o_vals);
    if (K < 1 || K > MAX_MESSAGES || PyTuple_GET_SIZE(o_t) != K || PyTuple_GET_SIZE(o_cnt) != K) {
        PyErr_SetString(PyExc_ValueError, "canrls._can.push: index, t, cnt: one per message "
                                          "(1..62)");
        return NULL;
    }
    Py_ssize_t nb = 3 * K + R + 11;
    Buf *b = calloc((size_t)nb, sizeof(Buf));
    int64_t *offsets = calloc((size_t)K + 1, sizeof(int64_t));
    int64_t *sort = NULL;
    long long n_out = -1;
    if (!b || !offsets) {
        PyErr_NoMemory();
        goto done;
    }
    Buf *bi = b, *bt = b + K, *bc = b + 2 * K, *bv = b + 3 * K, *rest = b + 3 * K + R;
    for (Py_ssize_t k = 0; k < K; k++) {
        if (!get(&bi[k], PyTuple_GET_ITEM(o_index, k), K_I64, 0, 0, "index"))
            goto done;
        offsets[k + 1] = offsets[k] + items(&bi[k]);
        if (!get(&bt[k], PyTuple_GET_ITEM(o_t, k), K_F64, items(&bi[k]), 0, "t") ||
            (use_counters &&
             !get(&bc[k], PyTuple_GET_ITEM(o_cnt, k), K_I64, items(&bi[k]), 0, "cnt")))
            goto done;
    }
    Py_ssize_t n = offsets[K];
    if (!get(&rest[0], o_role, K_I64, R, 0, "role_msg") ||
        !get(&rest[1], o_times, K_F64, 6, 0, "times"))
        goto done;
    const int64_t *role_msg = I64P(rest[0]);
    for (Py_ssize_t j = 0; j < R; j++) {
        int64_t m = role_msg[j];
        if (m < 0 || m >= K) {
            PyErr_SetString(PyExc_ValueError, "canrls._can.push: role_msg out of range");
            goto done;
        }
        if (!get(&bv[j], PyTuple_GET_ITEM(o_vals, j), K_F64, offsets[m + 1] - offsets[m], 0,
                 "vals"))
            goto done;
    }
    if (!get(&rest[2], o_gf, K_F64, 0, 1, "gf"))
        goto done;
    Py_ssize_t G = items(&rest[2]) / (2 + R);
    if (!get(&rest[3], o_gi, K_I64, 3 * (G + 1), 1, "gi") ||
        !get(&rest[4], o_sf, K_F64, 5, 1, "sf") || !get(&rest[5], o_si, K_I64, K, 1, "si") ||
        !get(&rest[6], o_counts, K_I64, 5 * K, 1, "counts") ||
        !get(&rest[10], o_clock, K_I64, CLOCK_KINDS, 1, "clock") ||
        !get(&rest[7], o_iwork, K_I64, 0, 1, "iwork"))
        goto done;
    Py_ssize_t C = items(&rest[7]) / 4;
    if (!get(&rest[8], o_fwork, K_F64, 3 * C, 1, "fwork") ||
        !get(&rest[9], o_vwork, K_F64, 3 * C * R, 1, "vwork"))
        goto done;
    if (C < n + G || G < 1) {
        PyErr_SetString(PyExc_ValueError, "canrls._can.push: scratch space too small");
        goto done;
    }
    {
        int64_t *gi = I64P(rest[3]);
        if (gi[0] < 0 || gi[0] > G) {
            PyErr_SetString(PyExc_ValueError, "canrls._can.push: bad open-period count");
            goto done;
        }
    }
    if (R > MAX_ROLES) {
        PyErr_SetString(PyExc_ValueError, "canrls._can.push: too many roles");
        goto done;
    }
    const int64_t *idx_p[MAX_MESSAGES], *cnt_p[MAX_MESSAGES];
    const double *t_p[MAX_MESSAGES], *val_p[MAX_ROLES];
    int64_t lens[MAX_MESSAGES];
    for (Py_ssize_t k = 0; k < K; k++) {
        lens[k] = offsets[k + 1] - offsets[k];
        idx_p[k] = I64P(bi[k]);
        t_p[k] = F64P(bt[k]);
        cnt_p[k] = use_counters ? I64P(bc[k]) : NULL;
    }
    for (Py_ssize_t j = 0; j < R; j++)
        val_p[j] = F64P(bv[j]);
    int sorted = 1;
    Py_BEGIN_ALLOW_THREADS
    int64_t *iw = I64P(rest[7]);
    double *fw = F64P(rest[8]), *vw = F64P(rest[9]);
    int64_t *all_index = iw, *all_cnt = iw + C, *msg = iw + 2 * C, *m_cnt = iw + 3 * C;
    double *all_t = fw, *m_t = fw + C, *out_t = fw + 2 * C;
    double *all_vals = vw, *m_vals = vw + C * R, *out_v = vw + 2 * C * R;
    if (!merge_messages(K, lens, idx_p, t_p, use_counters ? cnt_p : NULL, R, role_msg, val_p,
                        msg, m_t, m_cnt, m_vals)) {
        /* a message's frames out of stream order: a stable sort of the concatenation */
        for (Py_ssize_t k = 0; k < K; k++) {
            Py_ssize_t len = lens[k];
            memcpy(all_index + offsets[k], idx_p[k], (size_t)len * sizeof(int64_t));
            memcpy(all_t + offsets[k], t_p[k], (size_t)len * sizeof(double));
            for (Py_ssize_t i = 0; i < len; i++)
                all_cnt[offsets[k] + i] = use_counters ? cnt_p[k][i] : -1;
        }
        for (Py_ssize_t i = 0; i < n * R; i++)
            all_vals[i] = NAN;
        for (Py_ssize_t j = 0; j < R; j++) {
            int64_t m = role_msg[j];
            for (int64_t i = offsets[m]; i < offsets[m + 1]; i++)
                all_vals[i * R + j] = val_p[j][i - offsets[m]];
        }
        sort = malloc(2 * (size_t)(n > 0 ? n : 1) * sizeof(int64_t));
        if (!sort) {
            sorted = 0;
        } else {
            int64_t *order = sort, *tmp = sort + n;
            stable_order(all_index, n, order, tmp);
            for (Py_ssize_t k = 0; k < K; k++)
                for (int64_t i = offsets[k]; i < offsets[k + 1]; i++)
                    tmp[i] = k;
            for (Py_ssize_t o = 0; o < n; o++) {
                int64_t i = order[o];
                msg[o] = tmp[i];
                m_t[o] = all_t[i];
                m_cnt[o] = all_cnt[i];
                memcpy(m_vals + o * R, all_vals + i * R, (size_t)R * sizeof(double));
            }
        }
    }
    if (sorted) {
        const double *times = F64P(rest[1]);
        n_out = pair_frames(msg, m_t, m_cnt, m_vals, role_msg, R, K, times, flush, n,
                            F64P(rest[2]), G, I64P(rest[3]), F64P(rest[4]), I64P(rest[5]),
                            I64P(rest[6]), I64P(rest[10]), out_t, out_v);
    }
    Py_END_ALLOW_THREADS
    if (!sorted) {
        PyErr_NoMemory();
        n_out = -1;
    }
done:
    if (b)
        release(b, (int)nb);
    free(b);
    free(offsets);
    free(sort);
    return n_out < 0 ? NULL : PyLong_FromLongLong(n_out);
}

/* ------------------------------------------------------------------------- */

static PyMethodDef methods[] = {
    {"crc8", py_crc8, METH_VARARGS, "E2E CRC-8 of every payload row."},
    {"gather_check", py_gather_check, METH_VARARGS,
     "Gather the payload of rows and flag the first failing check (remote, length, CRC)."},
    {"counters", py_counters, METH_VARARGS, "Classify alive counters, carrying state."},
    {"decode_fast", py_decode_fast, METH_VARARGS,
     "Decode a block in one pass up to the first frame that is not well-formed."},
    {"push", py_push, METH_VARARGS, "Merge frames into stream order and pair them."},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {
    PyModuleDef_HEAD_INIT, "canrls._can",
    "The per-frame loops of canrls' CAN layer (strict decoding, pairing) in C.", -1, methods,
    NULL, NULL, NULL, NULL,
};

PyMODINIT_FUNC PyInit__can(void) { return PyModule_Create(&module); }
