/* canrls._rx: the bulk receive of SocketCAN frames (the daemon's reader of a
 * can.interfaces.socketcan.SocketcanBus, canrls.live.socketcan).
 *
 * python-can opens, binds, filters and sends on the raw CAN socket as before; its
 * receive path costs a wake-up, a select, a recvmsg, a dissect_can_frame and a
 * can.Message for every frame. recv() here waits on the same socket with the GIL
 * released (ppoll with a timeout), then takes every frame waiting with recvmmsg
 * (MSG_DONTWAIT) and writes them into the arrays of a canrls FrameBlock, field for
 * field as python-can's capture_message + canrls.live.bus_link.messages_to_block:
 *
 *   t               seconds + nanoseconds * 1e-9 of the SO_TIMESTAMPNS control message
 *                   (python-can's "@ll" timespec, the same two double operations)
 *   arbitration_id  can_id & 0x1FFFFFFF if CAN_EFF_FLAG, else can_id & 0x7FF
 *   is_extended     CAN_EFF_FLAG     is_remote  CAN_RTR_FLAG     is_error  CAN_ERR_FLAG
 *   dlc             bytes of data: frame[8 : 8 + len] as Python slices it, len (byte 4)
 *                   rounded up to the next CAN FD length (0..8, 12, 16, 20, 24, 32, 48, 64);
 *                   0 in a remote frame (can.Message keeps no data for it)
 *   data            those bytes, zeros after them (row of 64 bytes)
 *   aux[k, 0]       bit 0: CAN FD (a 72-byte datagram, CANFD_MTU), bit 1: CANFD_BRS,
 *                   bit 2: CANFD_ESI (both only in FD frames), bit 3: not received
 *                   (MSG_DONTROUTE: sent by this host), as python-can's Message fields
 *   aux[k, 1]       python-can's Message.dlc (len, or len8_dlc 9..15 of a classic
 *                   frame of 8 bytes)
 *
 * A datagram python-can would refuse (shorter than the 8-byte header, len above 64, no
 * SO_TIMESTAMPNS message, nanoseconds >= 1e9) is skipped, and returned as a ValueError
 * beside the frames taken: the caller delivers the frames, then raises it (python-can
 * raises it from recv, the frames before and after it come out of later calls).
 *
 * Linux only (recvmmsg, ppoll); elsewhere AVAILABLE is False and recv raises
 * NotImplementedError: the caller reads the bus through python-can instead.
 */

#define _GNU_SOURCE
#define PY_SSIZE_T_CLEAN
#include <Python.h>

#include <stdint.h>
#include <string.h>

#if defined(__linux__)
#include <errno.h>
#include <poll.h>
#include <sys/socket.h>
#include <time.h>
#define HAVE_RECVMMSG 1
#else
#define HAVE_RECVMMSG 0
#endif

/* linux/can.h */
#define CAN_EFF_FLAG 0x80000000U
#define CAN_RTR_FLAG 0x40000000U
#define CAN_ERR_FLAG 0x20000000U
#define CAN_EFF_MASK 0x1FFFFFFFU
#define CAN_SFF_MASK 0x000007FFU
#define CANFD_BRS 0x01
#define CANFD_ESI 0x02
#define CAN_MAX_DLEN 8
#define CAN_MAX_RAW_DLC 15
#define CANFD_MAX_DLEN 64
#define CANFD_MTU 72
#define HEADER 8
/* python-can's constants.SO_TIMESTAMPNS (SO_TIMESTAMPNS_OLD: a timespec of two longs) */
#define PYCAN_SO_TIMESTAMPNS 35

/* aux[k, 0] bits */
#define AUX_FD 1
#define AUX_BRS 2
#define AUX_ESI 4
#define AUX_TX 8

/* frames one recvmmsg call takes at most (the buffers live on the stack); recv loops */
#define CHUNK 64

/* ------------------------------------------------------------------------- */

typedef struct {
    Py_buffer view;
    int held;
} Buf;

static int get(Buf *b, PyObject *obj, Py_ssize_t itemsize, const char *fmt, const char *name)
{
    b->held = 0;
    if (PyObject_GetBuffer(obj, &b->view, PyBUF_C_CONTIGUOUS | PyBUF_FORMAT | PyBUF_WRITABLE)
        < 0)
        return 0;
    b->held = 1;
    const char *f = b->view.format ? b->view.format : "B";
    if (*f == '<' || *f == '=' || *f == '@')
        f++;
    if (b->view.itemsize != itemsize || !strchr(fmt, *f) || f[1] != '\0') {
        PyErr_Format(PyExc_TypeError, "canrls._rx: %s has the wrong dtype (format %s)", name,
                     b->view.format ? b->view.format : "?");
        return 0;
    }
    return 1;
}

#if HAVE_RECVMMSG

/* python-can's dissect_can_frame: len not a CAN FD length -> the next one up */
static int fd_len(int len)
{
    static const uint8_t up[65] = {
        0,  1,  2,  3,  4,  5,  6,  7,  8,  12, 12, 12, 12, 16, 16, 16, 16,
        20, 20, 20, 20, 24, 24, 24, 24, 32, 32, 32, 32, 32, 32, 32, 32,
        48, 48, 48, 48, 48, 48, 48, 48, 48, 48, 48, 48, 48, 48, 48, 48,
        64, 64, 64, 64, 64, 64, 64, 64, 64, 64, 64, 64, 64, 64, 64, 64};
    return len <= 64 ? up[len] : -1;
}

typedef struct {
    double *t;
    uint32_t *id;
    uint8_t *ext, *rtr, *err, *dlc, *data, *aux;
    Py_ssize_t cap;
} Out;

/* why the first refused datagram was refused (static strings) */
typedef struct {
    const char *why;
    long value;
} Refusal;

/* Decode the ``got`` datagrams of one recvmmsg into rows n.. of ``o``; returns the new n. */
static Py_ssize_t take(const Out *o, Py_ssize_t n, struct mmsghdr *mm, const uint8_t *hdr,
                       int got, Refusal *bad)
{
    const Py_ssize_t base = n; /* datagram i's payload went to row base + i */
    for (int i = 0; i < got; i++) {
        const struct msghdr *h = &mm[i].msg_hdr;
        size_t size = mm[i].msg_len; /* bytes received (at most CANFD_MTU) */
        const uint8_t *head = hdr + (size_t)i * HEADER;
        uint8_t *row = o->data + (size_t)n * CANFD_MAX_DLEN;
        const uint8_t *payload = o->data + (size_t)(base + i) * CANFD_MAX_DLEN;
        if (size < HEADER) {
            if (!bad->why) {
                bad->why = "datagram shorter than the 8-byte can_frame header";
                bad->value = (long)size;
            }
            continue;
        }
        /* the timestamp: python-can wants exactly one SO_TIMESTAMPNS message */
        long ts[2] = {0, 0};
        int have_ts = 0;
        for (struct cmsghdr *c = CMSG_FIRSTHDR(h); c; c = CMSG_NXTHDR((struct msghdr *)h, c))
            if (c->cmsg_level == SOL_SOCKET && c->cmsg_type == PYCAN_SO_TIMESTAMPNS &&
                c->cmsg_len >= CMSG_LEN(sizeof ts)) {
                memcpy(ts, CMSG_DATA(c), sizeof ts);
                have_ts = 1;
            }
        uint32_t can_id;
        memcpy(&can_id, head, 4); /* "=I": native order */
        int len = fd_len(head[4]);
        if (!have_ts || ts[1] >= 1000000000L || len < 0) {
            if (!bad->why) {
                bad->why = !have_ts ? "no SO_TIMESTAMPNS control message"
                           : len < 0 ? "length byte above 64"
                                     : "timestamp nanoseconds out of range";
                bad->value = !have_ts ? 0 : len < 0 ? (long)head[4] : ts[1];
            }
            continue;
        }
        int fd = size == CANFD_MTU;
        int flags = fd ? head[5] : 0; /* flags only in FD frames */
        int msg_dlc = len;
        if (!fd && len == CAN_MAX_DLEN && head[7] > CAN_MAX_DLEN && head[7] <= CAN_MAX_RAW_DLC)
            msg_dlc = head[7];
        /* frame[8 : 8 + len]: what the datagram holds of it; none in a remote frame
         * (can.Message drops the data of a remote frame) */
        size_t have = size - HEADER;
        int bytes = (size_t)len < have ? len : (int)have;
        if (can_id & CAN_RTR_FLAG)
            bytes = 0;
        if (row != payload) /* a refused datagram before it: one row up per refusal */
            memmove(row, payload, (size_t)bytes);
        memset(row + bytes, 0, CANFD_MAX_DLEN - (size_t)bytes);
        /* timestamp = seconds + nanoseconds * 1e-9 (python-can, in this order) */
        o->t[n] = (double)ts[0] + (double)ts[1] * 1e-9;
        int eff = (can_id & CAN_EFF_FLAG) != 0;
        o->id[n] = can_id & (eff ? CAN_EFF_MASK : CAN_SFF_MASK);
        o->ext[n] = (uint8_t)eff;
        o->rtr[n] = (can_id & CAN_RTR_FLAG) != 0;
        o->err[n] = (can_id & CAN_ERR_FLAG) != 0;
        o->dlc[n] = (uint8_t)bytes;
        o->aux[2 * n] = (uint8_t)((fd ? AUX_FD : 0) | (flags & CANFD_BRS ? AUX_BRS : 0) |
                                  (flags & CANFD_ESI ? AUX_ESI : 0) |
                                  (h->msg_flags & MSG_DONTROUTE ? AUX_TX : 0));
        o->aux[2 * n + 1] = (uint8_t)msg_dlc;
        n++;
    }
    return n;
}

/* Sleep ``pause`` s, wait up to ``timeout`` s for the socket, then take up to o->cap
 * frames. Runs without the GIL. Returns the rows written; *err: errno of a failure (0: none). */
static Py_ssize_t receive(int fd, double pause, double timeout, const Out *o, Refusal *bad,
                          int *err)
{
    *err = 0;
    if (pause > 0.0) { /* the reader's batched sleep: frames gather in the socket */
        struct timespec ps;
        ps.tv_sec = (time_t)pause;
        ps.tv_nsec = (long)((pause - (double)ps.tv_sec) * 1e9);
        while (nanosleep(&ps, &ps) < 0 && errno == EINTR)
            ;
    }
    if (timeout > 0.0) {
        struct pollfd p = {fd, POLLIN, 0};
        struct timespec ts;
        ts.tv_sec = (time_t)timeout;
        ts.tv_nsec = (long)((timeout - (double)ts.tv_sec) * 1e9);
        int r = ppoll(&p, 1, &ts, NULL);
        if (r < 0) {
            *err = errno == EINTR ? 0 : errno;
            return 0;
        }
        if (r == 0)
            return 0;
        if (p.revents & POLLNVAL) {
            *err = EBADF;
            return 0;
        }
    }
    struct mmsghdr mm[CHUNK];
    struct iovec iov[CHUNK][2];
    uint8_t hdr[CHUNK * HEADER];
    /* room for SO_TIMESTAMPNS and one more control message */
    union {
        struct cmsghdr align;
        char buf[2 * CMSG_SPACE(2 * sizeof(long))];
    } ctrl[CHUNK];
    Py_ssize_t n = 0;
    while (n < o->cap) {
        int want = o->cap - n < CHUNK ? (int)(o->cap - n) : CHUNK;
        for (int i = 0; i < want; i++) {
            /* the header to hdr, the payload straight into its row of data */
            iov[i][0].iov_base = hdr + (size_t)i * HEADER;
            iov[i][0].iov_len = HEADER;
            iov[i][1].iov_base = o->data + (size_t)(n + i) * CANFD_MAX_DLEN;
            iov[i][1].iov_len = CANFD_MAX_DLEN;
            memset(&mm[i], 0, sizeof mm[i]);
            mm[i].msg_hdr.msg_iov = iov[i];
            mm[i].msg_hdr.msg_iovlen = 2;
            mm[i].msg_hdr.msg_control = ctrl[i].buf;
            mm[i].msg_hdr.msg_controllen = sizeof ctrl[i].buf;
        }
        int got = recvmmsg(fd, mm, (unsigned)want, MSG_DONTWAIT, NULL);
        if (got < 0) {
            if (errno != EAGAIN && errno != EWOULDBLOCK && errno != EINTR)
                *err = errno; /* after frames taken: the caller delivers them first */
            break;
        }
        n = take(o, n, mm, hdr, got, bad);
        if (got < want)
            break; /* the socket is empty */
    }
    return n;
}

#endif /* HAVE_RECVMMSG */

PyDoc_STRVAR(recv_doc,
"recv(fd, pause, timeout, offset, most, command_id, t, arbitration_id, is_extended,\n"
"     is_remote, is_error, dlc, data, aux) -> (n, commands, error)\n\n"
"Sleep pause seconds, then wait up to timeout seconds (0: not at all) for the socket fd,\n"
"the GIL released throughout, then take every frame waiting, at most ``most``, into rows\n"
"offset..offset+n-1 of the arrays: t float64, arbitration_id uint32,\n"
"is_extended/is_remote/is_error bool, dlc uint8, data uint8 (N, 64), aux uint8 (N, 2)\n"
"(see the module's source). commands: how many of them are standard frames with the id\n"
"command_id. error: None, or the exception (OSError of the socket, ValueError of a\n"
"refused datagram) to raise once the n frames are delivered. An OSError before any\n"
"frame is raised at once.");

static PyObject *py_recv(PyObject *self, PyObject *args)
{
    (void)self;
    int fd;
    double pause, timeout;
    Py_ssize_t offset, most;
    long command_id;
    PyObject *obj[8];
    if (!PyArg_ParseTuple(args, "iddnnlOOOOOOOO", &fd, &pause, &timeout, &offset, &most,
                          &command_id, &obj[0], &obj[1], &obj[2], &obj[3], &obj[4], &obj[5],
                          &obj[6], &obj[7]))
        return NULL;
#if !HAVE_RECVMMSG
    (void)fd;
    (void)pause;
    (void)timeout;
    (void)offset;
    (void)most;
    (void)command_id;
    PyErr_SetString(PyExc_NotImplementedError, "canrls._rx: no recvmmsg on this platform");
    return NULL;
#else
    static const char *names[8] = {"t",   "arbitration_id", "is_extended", "is_remote",
                                   "is_error", "dlc",        "data",        "aux"};
    static const Py_ssize_t sizes[8] = {8, 4, 1, 1, 1, 1, 1, 1};
    static const char *fmts[8] = {"d", "IL", "?B", "?B", "?B", "B", "B", "B"};
    Buf b[8];
    PyObject *result = NULL;
    int nb = 0;
    for (; nb < 8; nb++)
        if (!get(&b[nb], obj[nb], sizes[nb], fmts[nb], names[nb])) {
            nb++;
            goto done;
        }
    Py_ssize_t cap = b[0].view.len / 8;
    for (int k = 1; k < 6; k++)
        if (b[k].view.len / b[k].view.itemsize < cap)
            cap = b[k].view.len / b[k].view.itemsize;
    if (b[6].view.len < cap * CANFD_MAX_DLEN || b[7].view.len < cap * 2) {
        PyErr_Format(PyExc_ValueError, "canrls._rx: data must hold (%zd, 64) bytes and aux "
                     "(%zd, 2)", cap, cap);
        goto done;
    }
    if (offset < 0 || most < 0 || offset > cap) {
        PyErr_Format(PyExc_ValueError, "canrls._rx: offset %zd, most %zd: outside the %zd "
                     "rows", offset, most, cap);
        goto done;
    }
    cap = cap - offset < most ? cap - offset : most;
    if (fd < 0) {
        errno = EBADF;
        PyErr_SetFromErrno(PyExc_OSError);
        goto done;
    }
    Out o = {(double *)b[0].view.buf + offset, (uint32_t *)b[1].view.buf + offset,
             (uint8_t *)b[2].view.buf + offset, (uint8_t *)b[3].view.buf + offset,
             (uint8_t *)b[4].view.buf + offset, (uint8_t *)b[5].view.buf + offset,
             (uint8_t *)b[6].view.buf + offset * CANFD_MAX_DLEN,
             (uint8_t *)b[7].view.buf + offset * 2, cap};
    Refusal bad = {NULL, 0};
    int err = 0;
    Py_ssize_t n, commands = 0;
    Py_BEGIN_ALLOW_THREADS
    n = receive(fd, pause, timeout, &o, &bad, &err);
    for (Py_ssize_t k = 0; k < n; k++)
        commands += !o.ext[k] && !o.err[k] && (long)o.id[k] == command_id;
    Py_END_ALLOW_THREADS
    PyObject *exc = NULL;
    if (err) {
        errno = err;
        PyErr_SetFromErrno(PyExc_OSError);
        if (n == 0)
            goto done;
        PyObject *type, *tb;
        PyErr_Fetch(&type, &exc, &tb);
        PyErr_NormalizeException(&type, &exc, &tb);
        Py_XDECREF(type);
        Py_XDECREF(tb);
    } else if (bad.why) {
        PyObject *msg = PyUnicode_FromFormat("SocketCAN datagram refused: %s (%ld)", bad.why,
                                             bad.value);
        if (!msg)
            goto done;
        exc = PyObject_CallOneArg(PyExc_ValueError, msg);
        Py_DECREF(msg);
        if (!exc)
            goto done;
    }
    result = Py_BuildValue("(nnN)", n, commands, exc ? exc : Py_NewRef(Py_None));
#endif
#if HAVE_RECVMMSG
done:
    for (int k = 0; k < nb; k++)
        if (b[k].held)
            PyBuffer_Release(&b[k].view);
    return result;
#endif
}

static PyMethodDef methods[] = {
    {"recv", py_recv, METH_VARARGS, recv_doc},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {
    PyModuleDef_HEAD_INIT, "canrls._rx",
    "The bulk receive of SocketCAN frames into the arrays of a FrameBlock (recvmmsg).", -1,
    methods, NULL, NULL, NULL, NULL,
};

PyMODINIT_FUNC PyInit__rx(void)
{
    PyObject *m = PyModule_Create(&module);
    if (!m)
        return NULL;
    if (PyModule_AddIntConstant(m, "AVAILABLE", HAVE_RECVMMSG) < 0 ||
        PyModule_AddIntConstant(m, "DATA_WIDTH", 64) < 0 ||
        PyModule_AddIntConstant(m, "AUX_FD", 1) < 0 ||
        PyModule_AddIntConstant(m, "AUX_BRS", 2) < 0 ||
        PyModule_AddIntConstant(m, "AUX_ESI", 4) < 0 ||
        PyModule_AddIntConstant(m, "AUX_TX", 8) < 0) {
        Py_DECREF(m);
        return NULL;
    }
    return m;
}
