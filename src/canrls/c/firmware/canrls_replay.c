/*
 * canrls_replay.c -- replays test vectors through the whole estimator and compares.
 *
 * SPDX-License-Identifier: MIT
 *
 * canrls_vectors.h (`canrls export-c --vectors LOG`) holds the frames of a log and
 * what the Python specification (canrls.firmware.spec) computes from them: the integer
 * state every N samples and every frame of every publication. canrls_replay() feeds
 * the frames to canrls_target_frame() one by one, publishes when asked and compares
 * each state record and each published frame with the expected ones, word for word.
 * The host test (canrls_test.c) and the Cortex-M4 example (src/canrls/c/firmware/example) call it.
 */
#include "canrls_replay.h"

#include <string.h>

#include "canrls_model.h"
#include "canrls_vectors.h"

/* the state as the specification's state_record() lays it out */
static uint32_t record(const canrls_target *S, int64_t *out)
{
    const canrls_target_model *M = S->model;
    uint32_t k = 0u, i, j;
    out[k++] = S->samples;
    for (i = 0; i < CANRLS_NREJECTS; i++) {
        out[k++] = S->rejects[i];
    }
    for (i = 0; i < M->nfilters; i++) {
        out[k++] = S->x1[i];
    }
    for (i = 0; i < M->nfilters; i++) {
        out[k++] = S->x2[i];
    }
    for (i = 0; i < M->neq; i++) {
        const canrls_target_eq *q = &S->eq[i];
        const uint32_t n = M->equations[i].n;
        for (j = 0; j < n; j++) {
            out[k++] = canrls_theta_q31(&q->rls, j);
        }
        for (j = 0; j < n; j++) {
            out[k++] = canrls_theta_frac_q31(&q->rls, j);
        }
        for (j = 0; j < CANRLS_TRI(n); j++) {
            out[k++] = canrls_P_q31(&q->rls, j);
        }
        for (j = 0; j < CANRLS_TRI(n); j++) {
            out[k++] = canrls_P_frac_q31(&q->rls, j);
        }
        out[k++] = q->rls.e;
        out[k++] = q->rls.c;
        for (j = 0; j < CANRLS_NSITES; j++) {
            out[k++] = q->rls.counts[j];
        }
        for (j = 0; j < n; j++) {
            out[k++] = q->sh[j];
        }
        out[k++] = q->sh_y;
        out[k++] = q->updates;
        out[k++] = q->ms;
        out[k++] = q->rescales;
    }
    return k;
}

static void put_int(void (*say)(const char *), int64_t x)
{
    char buf[24];
    char *s = buf + sizeof buf - 1;
    /* the magnitude in 64 bits unsigned (INT64_MIN included) */
    uint64_t v = x < 0 ? 0u - (uint64_t)x : (uint64_t)x;
    *s = '\0';
    do {
        *--s = (char)('0' + (int)(v % 10u));
        v /= 10u;
    } while (v != 0u);
    if (x < 0) {
        *--s = '-';
    }
    say(s);
}

static void put_uint(void (*say)(const char *), uint32_t v)
{
    put_int(say, (int64_t)v);
}

/* the name of word j of the state record (its layout: record() above) */
static void say_word(const canrls_target_model *M, uint32_t j, void (*say)(const char *))
{
    static const char *const eq_part[] = {"theta", "theta_frac", "P", "P_frac", "e", "c",
                                          "counts", "sh", "sh_y", "updates", "ms",
                                          "rescales"};
    uint32_t i, p;
    if (j == 0u) {
        say("samples");
        return;
    }
    j -= 1u;
    if (j < CANRLS_NREJECTS) {
        say("rejects[");
        put_uint(say, j);
        say("]");
        return;
    }
    j -= CANRLS_NREJECTS;
    if (j < 2u * M->nfilters) {
        say(j < M->nfilters ? "x1[" : "x2[");
        put_uint(say, j % M->nfilters);
        say("]");
        return;
    }
    j -= 2u * M->nfilters;
    for (i = 0; i < M->neq; i++) {
        const uint32_t n = M->equations[i].n;
        const uint32_t len[12] = {n, n, CANRLS_TRI(n), CANRLS_TRI(n), 1u, 1u, CANRLS_NSITES,
                                  n, 1u, 1u, 1u, 1u};
        for (p = 0; p < 12u; p++) {
            if (j < len[p]) {
                say(eq_part[p]);
                if (len[p] > 1u) {
                    say("[");
                    put_uint(say, j);
                    say("]");
                }
                say(" of equation ");
                put_uint(say, i);
                return;
            }
            j -= len[p];
        }
    }
    say("a word beyond the record");
}

/* keeps the first difference */
static void differ(canrls_replay_counts *R, const canrls_target *S, uint32_t k, uint32_t what,
                   uint32_t index, int64_t expected, int64_t got)
{
    if (R->bad++ == 0u) {
        R->what = what;
        R->at_sample = S->samples;
        R->at_frame = k;
        R->index = index;
        R->pub = R->published;
        R->expected = expected;
        R->got = got;
    }
}

/* the frame loop, out of line so that a trace finds each call of canrls_target_frame:
 * frames a..b-1, the comparisons counted in R */
__attribute__((noinline)) void canrls_replay_frames(canrls_target *S, uint32_t a, uint32_t b,
                                                    canrls_replay_counts *R)
{
    static canrls_can_frame out[CANRLS_PUBLISH_MAX];
    static int64_t rec[VEC_RECORD + 1u];
    uint32_t k, r, n, i;
    for (k = a; k < b; k++) {
        r = canrls_target_frame(S, vec_id[k] & 0x7FFFFFFFu, vec_id[k] >> 31, vec_data[k],
                                vec_len[k], vec_t[k]);
#ifdef CANRLS_REPLAY_MARK
        /* a hook of the instruction count (make target): the frame completed a sample */
        if ((r & CANRLS_SAMPLE) != 0u) {
            CANRLS_REPLAY_MARK(r);
        }
#endif
        if ((r & CANRLS_PUBLISH) != 0u) {
            n = canrls_target_publish(S, out, CANRLS_PUBLISH_MAX);
            /* published + 1 > VEC_PUBLICATIONS, not published >= VEC_PUBLICATIONS: a log
             * too short for a publication has VEC_PUBLICATIONS 0, and the comparison must
             * not be constant (-Werror=type-limits) */
            if (R->published + 1u > VEC_PUBLICATIONS || vec_pub_frame[R->published] != k
                || vec_pub_count[R->published] != n) {
                /* a publication where none is expected, or of another count of frames */
                differ(R, S, k, 2u, n, R->published + 1u > VEC_PUBLICATIONS
                       ? 0 : (int64_t)vec_pub_count[R->published], (int64_t)n);
            } else {
                for (i = 0; i < n; i++) {
                    if (out[i].id != vec_pub_id[R->pub_base + i]
                        || memcmp(out[i].data, vec_pub_data[R->pub_base + i], 8) != 0) {
                        /* the frame's first 4 bytes, little endian, expected and sent */
                        const uint8_t *x = vec_pub_data[R->pub_base + i];
                        differ(R, S, k, 2u, i,
                               (int64_t)((uint32_t)x[0] | (uint32_t)x[1] << 8
                                         | (uint32_t)x[2] << 16 | (uint32_t)x[3] << 24),
                               (int64_t)((uint32_t)out[i].data[0] | (uint32_t)out[i].data[1] << 8
                                         | (uint32_t)out[i].data[2] << 16
                                         | (uint32_t)out[i].data[3] << 24));
                        break;
                    }
                }
                R->pub_base += n;
            }
            R->published++;
        }
        if (R->checked < VEC_CHECKPOINTS && vec_cp_frame[R->checked] == k) {
            const uint32_t m = record(S, rec);
            const int64_t *want = &vec_cp[R->checked * VEC_RECORD];
            for (i = 0; i < VEC_RECORD && i < m && rec[i] == want[i]; i++) {
            }
            if (i < VEC_RECORD) {
                differ(R, S, k, 1u, i, want[i], i < m ? rec[i] : 0);
            } else if (m != VEC_RECORD) {
                differ(R, S, k, 1u, i, 0, rec[i]);
            }
            R->checked++;
        }
    }
}

int canrls_replay(canrls_target *S, void (*say)(const char *))
{
    canrls_replay_counts R;
    memset(&R, 0, sizeof R);
    if (canrls_target_init(S, &canrls_model) != CANRLS_OK) {
        say("canrls_target_init failed\n");
        return 0;
    }
    canrls_replay_frames(S, 0u, VEC_FRAMES, &R);
    say("canrls replay: ");
    put_uint(say, VEC_FRAMES);
    say(" frames, ");
    put_uint(say, S->samples);
    say(" samples, ");
    put_uint(say, R.checked);
    say(" state records, ");
    put_uint(say, R.published);
    say(" publications: ");
    if (R.bad != 0u || R.checked != VEC_CHECKPOINTS || R.published != VEC_PUBLICATIONS
        || S->samples != VEC_SAMPLES) {
        put_uint(say, R.bad);
        say(" differ from the specification\n");
        if (R.what != 0u) {
            say("first difference: sample ");
            put_uint(say, R.at_sample);
            say(" (frame ");
            put_uint(say, R.at_frame);
            say("), ");
            if (R.what == 1u) {
                say("state ");
                say_word(&canrls_model, R.index, say);
            } else {
                say("publication ");
                put_uint(say, R.pub);
                say(", frame ");
                put_uint(say, R.index);
                say(" (bytes 0..3 little endian)");
            }
            say(": expected ");
            put_int(say, R.expected);
            say(", got ");
            put_int(say, R.got);
            say("\n");
        } else {
            say("records or publications missing at the end of the frames\n");
        }
        return 0;
    }
    say("bit-exact with the specification\n");
    return 1;
}
