/*
 * canrls_target_check.h -- is a restored canrls_target a state the estimator can reach?
 *
 * SPDX-License-Identifier: MIT
 *
 * A state kept in flash or in a checkpoint file comes back as bytes; before the first
 * canrls_target_frame() on it, canrls_target_check_state() holds every field against
 * its invariant (docs/target.md, "Restore"), so that no damaged or forged state puts an
 * out-of-range shift, index or counter into the estimator.
 *
 * Restore on the target:
 *   memcpy(&S, flash, sizeof S);                 the bytes of an earlier state
 *   S.model = &canrls_model;                     the pointers of this run, not the file's
 *   for (i = 0; i < canrls_model.neq; i++) S.eq[i].rls.plan = &S.eq[i].plan;
 *   if (canrls_target_check_state(&S, &canrls_model) != CANRLS_OK)
 *       canrls_target_init(&S, &canrls_model);   refused: start again from the prior
 */
#ifndef CANRLS_TARGET_CHECK_H
#define CANRLS_TARGET_CHECK_H

#include "canrls_target.h"

#ifdef __cplusplus
extern "C" {
#endif

/** The first field a check refused (canrls_target_check_state's return value). */
enum canrls_state_field {
    CANRLS_SF_MODEL = 1,    /**< S->model is not the model */
    CANRLS_SF_LAST_COUNTER, /**< an alive counter outside its field (or -1) */
    CANRLS_SF_OPEN,         /**< open_mask, open_counter: the period being paired */
    CANRLS_SF_RAW,          /**< a role's raw value outside its DBC range (or 0) */
    CANRLS_SF_FLAGS,        /**< has_t, frame_loss, primed, frozen, pending: 0 or 1 */
    CANRLS_SF_PUBLISH,      /**< since_publish at or beyond publish_every */
    CANRLS_SF_FILTER,       /**< a filter's state x1, x2 or its last input uph, upl */
    CANRLS_SF_PLAN,         /**< an equation's plan copy: not its model's */
    CANRLS_SF_KERNEL,       /**< the kernel: plan pointer, n, e, c, theta, P, trw, windup
                                 interval, wide words, the words beyond n */
    CANRLS_SF_SHIFT,        /**< a column's or the output's shift and exponent */
    CANRLS_SF_PRIOR,        /**< a column's ridge or trace term */
    CANRLS_SF_WARMUP,       /**< left outside 0..warmup, w_last outside the speed's range */
    CANRLS_SF_RESIDUAL,     /**< ms outside 0..the largest eps^2, flags beyond the kernel's */
    CANRLS_SF_UNUSED        /**< an equation, filter or message beyond the model not zero */
};

/**
 * Whether S (its pointers set to model and to its own plan copies) is a state that
 * canrls_target_init() and canrls_target_frame() can reach for this model: every plan
 * copy the model's (its trace bound the one its terms give), every shift, exponent,
 * index, counter and flag within the range the code produces. Reads S only.
 * @return CANRLS_OK, or the first enum canrls_state_field refused
 */
int canrls_target_check_state(const canrls_target *S, const canrls_target_model *model);

/** The trace bound of equation e's plan copy at the state q (canrls_target.c): with
 * trace_follows the sum of q's trace terms (saturated), at most trace_cap; else the
 * model plan's. */
int32_t canrls_target_trace_bound(const canrls_equation *e, const canrls_target_eq *q);

/** The name of an enum canrls_state_field ("?" for another value). */
const char *canrls_target_state_field(int field);

#ifdef __cplusplus
}
#endif

#endif /* CANRLS_TARGET_CHECK_H */
