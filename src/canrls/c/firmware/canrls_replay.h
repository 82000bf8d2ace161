/*
 * canrls_replay.h -- replay test vectors through the whole estimator (canrls_replay.c).
 *
 * SPDX-License-Identifier: MIT
 */
#ifndef CANRLS_REPLAY_H
#define CANRLS_REPLAY_H

#include <stdint.h>

#include "canrls_target.h"

/** What a replay compared: state records and publications checked, differences, and
 * the first difference: at sample `at_sample` (frame `at_frame`), `what` 1 a word of the
 * state record (`index` its position in the record), 2 publication `pub` (`index` its
 * frame, or its count of frames when that differs), the expected and the computed value. */
typedef struct {
    uint32_t checked, published, pub_base, bad;
    uint32_t what, at_sample, at_frame, index, pub;
    int64_t expected, got;
} canrls_replay_counts;

#ifdef CANRLS_REPLAY_MARK
/** Called after each frame that completed a sample, where the build defines it (the
 * instruction count of `make target`). */
void CANRLS_REPLAY_MARK(uint32_t r);
#endif

/** Frames a..b-1 of the vectors through canrls_target_frame(), compared as they come. */
void canrls_replay_frames(canrls_target *S, uint32_t a, uint32_t b, canrls_replay_counts *R);

/**
 * Every frame of canrls_vectors.h through a fresh estimator (canrls_model), each state
 * record and publication compared with the specification's; a one-line report through
 * `say`. Returns 1 when everything is bit-exact, else 0.
 */
int canrls_replay(canrls_target *S, void (*say)(const char *));

#endif /* CANRLS_REPLAY_H */
