/*
 * state_driver.c -- restored states of the target against canrls_target_check_state().
 *
 * SPDX-License-Identifier: MIT
 *
 * Built with the C of `canrls export-c` (canrls_model.c, the table-driven canrls_target.c,
 * canrls_fixed.c, canrls_target_check.c), under -fsanitize=address,undefined in the tests
 * (tests/firmware/test_target_state.py).
 *
 * usage: state_driver FRAMES K save OUT         the state after the first K frames
 *        state_driver FRAMES K bad NAME OUT     that state with field NAME set outside its
 *                                               invariant; prints the field the check names
 *        state_driver FRAMES K fuzz COUNT SEED  COUNT copies of it with 1..8 random bytes
 *                                               flipped: each refused, or the rest of the
 *                                               frames run on it; prints "accepted refused"
 *
 * FRAMES: one record of 20 bytes per frame, little endian: receive tick (u32), ID (u32),
 * extended (u8), length (u8), 8 data bytes, 2 bytes of padding. A restored state gets the
 * pointers of this run (model, plan copies) as a firmware restoring from flash sets them.
 * save and fuzz also check that the unchanged state is taken and continues bit for bit.
 * Exit status 0, 1 on a failed check of the driver's own, 2 on a usage error.
 */
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "canrls_model.h"
#include "canrls_target.h"
#include "canrls_target_check.h"
#include "canrls_target_math.h"

#define REC 20

static uint8_t *frames;
static long nframes;

static void run(canrls_target *S, long from, long to)
{
    canrls_can_frame out[CANRLS_PUBLISH_MAX];
    long k;
    for (k = from; k < to; k++) {
        const uint8_t *r = frames + REC * k;
        const uint32_t t = (uint32_t)r[0] | (uint32_t)r[1] << 8 | (uint32_t)r[2] << 16
                           | (uint32_t)r[3] << 24;
        const uint32_t id = (uint32_t)r[4] | (uint32_t)r[5] << 8 | (uint32_t)r[6] << 16
                            | (uint32_t)r[7] << 24;
        if (canrls_target_frame(S, id, r[8], r + 10, r[9] <= 8u ? r[9] : 8u, t)
            & CANRLS_PUBLISH) {
            (void)canrls_target_publish(S, out, CANRLS_PUBLISH_MAX);
        }
    }
}

/* the pointers of this run, as a restore sets them */
static void repoint(canrls_target *S)
{
    uint32_t i;
    S->model = &canrls_model;
    for (i = 0; i < CANRLS_TARGET_EQ_MAX; i++) {
        S->eq[i].rls.plan = i < canrls_model.neq ? &S->eq[i].plan : NULL;
    }
}

/* A and B the same bytes but their pointers (each points into its own state) */
static int same(const canrls_target *A, const canrls_target *B)
{
    static canrls_target a, b;
    uint32_t i;
    memcpy(&a, A, sizeof a);
    memcpy(&b, B, sizeof b);
    for (i = 0; i < CANRLS_TARGET_EQ_MAX; i++) {
        a.eq[i].rls.plan = NULL;
        b.eq[i].rls.plan = NULL;
    }
    return memcmp(&a, &b, sizeof a) == 0;
}

static int write_state(const char *path, const canrls_target *S)
{
    canrls_target c = *S;
    uint32_t i;
    FILE *f = fopen(path, "wb");
    c.model = NULL;
    for (i = 0; i < CANRLS_TARGET_EQ_MAX; i++) {
        c.eq[i].rls.plan = NULL;
    }
    if (f == NULL || fwrite(&c, sizeof c, 1, f) != 1 || fclose(f) != 0) {
        fprintf(stderr, "state_driver: cannot write %s\n", path);
        return 1;
    }
    return 0;
}

/* field NAME of S set outside its invariant (0: no such name) */
static int spoil(canrls_target *S, const char *name)
{
    canrls_target_eq *q = &S->eq[0];
    const uint32_t n = canrls_model.equations[0].n;
    const canrls_filter *fl = canrls_model.filters;
    uint32_t i = 0, w = 0;
    while (i < canrls_model.nfilters && fl[i].kind == CANRLS_SRC_CONST) {
        i++; /* the first filter with a state */
    }
    while (w < canrls_model.nfilters && !cr_narrow(&fl[w])) {
        w++; /* the first narrow filter (32-bit states) */
    }
#define CASE(s, stmt)                                                                        \
    if (strcmp(name, s) == 0) {                                                              \
        stmt;                                                                                \
        return 1;                                                                            \
    }
    CASE("model", S->model = NULL)
    CASE("last_counter", S->last_counter[0] = 0x7FFFFFF0)
    CASE("last_counter.unused", S->last_counter[CANRLS_TARGET_MSG_MAX - 1] = 3)
    CASE("open_mask", S->open_mask = (1u << canrls_model.nmsg) - 1u)
    CASE("open_counter", S->open_counter = -7)
    CASE("raw", S->raw[CANRLS_SPEED] = canrls_model.roles[CANRLS_SPEED].hi + 1)
    CASE("has_t", S->has_t = 2u)
    CASE("frame_loss", S->frame_loss = 2u)
    CASE("primed", S->primed[i] = 2u)
    CASE("since_publish", S->since_publish = canrls_model.publish_every)
    CASE("x1", S->x1[i] = (int64_t)1 << 61)
    CASE("x2", S->x2[i] = -((int64_t)1 << 61))
    CASE("uph", S->uph[i] = fl[i].fx < 31 ? (int32_t)1 << fl[i].fx : 1)
    CASE("upl", S->upl[i] = fl[i].fx < 31 && fl[i].fx > 0 ? 1 : -1)
    CASE("x1.unused", S->x1[CANRLS_TARGET_FILTER_MAX - 1] = 1)
    CASE("x1.narrow", S->x1[w < canrls_model.nfilters ? w : 0] = (int64_t)1 << 31)
    CASE("plan.e_max", q->plan.e_max += 1)
    CASE("plan.phi_ps", q->plan.phi_ps = 99)
    CASE("plan.trace_max_lam", q->plan.trace_max_lam -= 1)
    CASE("rls.plan", q->rls.plan = &canrls_model.equations[0].plan[0])
    CASE("rls.n", q->rls.n = CANRLS_N_MAX + 1u)
    CASE("rls.frozen", q->rls.frozen = 2u)
    CASE("rls.e", q->rls.e = q->plan.e_max + 1)
    CASE("rls.e.negative", q->rls.e = -1)
    CASE("rls.c.half", q->rls.c = q->plan.one_lam / 2)
    CASE("rls.c.above", q->rls.c = q->plan.one_lam + 1)
    /* a word outside theta_lo..theta_hi, or where the word is the whole int32_t, one
     * beyond n */
    CASE("rls.theta", if (q->plan.theta_hi < INT32_MAX) q->rls.theta_q[0].word = q->plan.theta_hi + 1;
                      else if (q->plan.theta_lo > INT32_MIN) q->rls.theta_q[0].word = q->plan.theta_lo - 1;
                      else q->rls.theta_q[n].frac = 1u)
    CASE("rls.P", if (q->plan.P_lo > INT32_MIN) q->rls.P[0].word = q->plan.P_lo - 1;
                  else q->rls.P[CANRLS_TRI(n)].word = 1)
    CASE("rls.trw", q->rls.trw += 1)
    CASE("rls.wu_lo", q->rls.wu_lo -= 1)
    CASE("rls.wide", q->rls.wide ^= 1u)
    CASE("rls.theta.unused", q->rls.theta_q[n].word = 1)
    CASE("sh", q->sh[0] += 200)
    CASE("sh.low", q->sh[0] = -40)
    CASE("exponents", q->exponents[0] += 1)
    CASE("sh_y", q->sh_y = -1000)
    CASE("exponents.y", q->exponents[n] += 1)
    CASE("sh.unused", q->sh[n] = 1)
    CASE("pending", q->pending[0] = 2u)
    CASE("ridge.m", q->ridge[0].m ^= 1u)
    CASE("ridge.e", q->ridge[0].e += 1)
    CASE("terms", q->terms[0] = -1)
    CASE("left", q->left = canrls_model.equations[0].warmup + 1)
    CASE("left.negative", q->left = -1)
    CASE("w_last", q->w_last = INT64_MAX)
    CASE("flags", q->flags = 16u)
    CASE("ms", q->ms = -1)
    CASE("eq.unused", S->eq[CANRLS_TARGET_EQ_MAX - 1].updates += 1u)
#undef CASE
    return 0;
}

static uint64_t rng = 0;

/* xorshift64* (seeded): the fuzz's bytes */
static uint64_t next_random(void)
{
    rng ^= rng >> 12;
    rng ^= rng << 25;
    rng ^= rng >> 27;
    return rng * 0x2545F4914F6CDD1DULL;
}

int main(int argc, char **argv)
{
    static canrls_target S0, A, B;
    FILE *f;
    long k, size;
    if (argc < 4) {
        fprintf(stderr, "usage: state_driver FRAMES K save OUT | bad NAME OUT | fuzz COUNT SEED\n");
        return 2;
    }
    f = fopen(argv[1], "rb");
    if (f == NULL || fseek(f, 0, SEEK_END) != 0 || (size = ftell(f)) < 0
        || fseek(f, 0, SEEK_SET) != 0) {
        fprintf(stderr, "state_driver: cannot read %s\n", argv[1]);
        return 2;
    }
    nframes = size / REC;
    frames = malloc((size_t)size + 1u);
    if (frames == NULL || fread(frames, 1, (size_t)size, f) != (size_t)size) {
        return 2;
    }
    fclose(f);
    k = strtol(argv[2], NULL, 10);
    k = k < 0 ? 0 : k > nframes ? nframes : k;
    if (canrls_target_init(&S0, &canrls_model) != CANRLS_OK) {
        return 2;
    }
    run(&S0, 0, k);
    if (canrls_target_check_state(&S0, &canrls_model) != CANRLS_OK) {
        fprintf(stderr, "state_driver: a reached state refused\n");
        return 1;
    }
    /* the reference: on from S0; the unchanged state restored (as bytes) continues the same */
    memcpy(&A, &S0, sizeof A);
    repoint(&A);
    run(&A, k, nframes);
    memcpy(&B, &S0, sizeof B);
    repoint(&B);
    if (canrls_target_check_state(&B, &canrls_model) != CANRLS_OK) {
        return 1;
    }
    run(&B, k, nframes);
    if (!same(&A, &B)) {
        fprintf(stderr, "state_driver: the restored state did not continue bit for bit\n");
        return 1;
    }
    if (strcmp(argv[3], "save") == 0 && argc == 5) {
        return write_state(argv[4], &S0);
    }
    if (strcmp(argv[3], "bad") == 0 && argc == 6) {
        int r;
        memcpy(&B, &S0, sizeof B);
        repoint(&B);
        if (!spoil(&B, argv[4])) {
            fprintf(stderr, "state_driver: no field %s\n", argv[4]);
            return 2;
        }
        r = canrls_target_check_state(&B, &canrls_model);
        printf("%s\n", r == CANRLS_OK ? "accepted" : canrls_target_state_field(r));
        return write_state(argv[5], &B);
    }
    if (strcmp(argv[3], "fuzz") == 0 && argc == 6) {
        const long count = strtol(argv[4], NULL, 10);
        long c, accepted = 0, refused = 0;
        rng = (uint64_t)strtoull(argv[5], NULL, 10) * 0x9E3779B97F4A7C15ULL + 1u;
        for (c = 0; c < count; c++) {
            uint8_t *b = (uint8_t *)(void *)&B;
            const uint32_t flips = 1u + (uint32_t)(next_random() % 8u);
            uint32_t j;
            memcpy(&B, &S0, sizeof B);
            for (j = 0; j < flips; j++) {
                const uint64_t r = next_random();
                b[(r >> 8) % sizeof B] ^= (uint8_t)(1u + r % 255u);
            }
            repoint(&B);
            if (canrls_target_check_state(&B, &canrls_model) != CANRLS_OK) {
                refused++;
                continue;
            }
            accepted++;
            run(&B, k, k + 2000 < nframes ? k + 2000 : nframes);
        }
        printf("%ld %ld\n", accepted, refused);
        return 0;
    }
    fprintf(stderr, "usage: state_driver FRAMES K save OUT | bad NAME OUT | fuzz COUNT SEED\n");
    return 2;
}
