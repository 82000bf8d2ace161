/*
 * canrls_bounds.h -- the compile-time bounds of the build: the largest model its state
 * and its buffers hold.
 *
 * SPDX-License-Identifier: MIT
 *
 * This copy (src/canrls/c/firmware) holds the maxima: every model the table-driven
 * estimator and the host extension canrls._target take. `canrls export-c` writes its
 * own canrls_bounds.h instead, with the bounds of the one model it exports, so that the
 * state (canrls_target, canrls_rls_q31) holds what that model has and the loops over its
 * equations run to them. Each bound is #ifndef-overridable (-DCANRLS_N_MAX=12, ...);
 * every file of one build must see the same bounds (the state's layout depends on them).
 */
#ifndef CANRLS_BOUNDS_H
#define CANRLS_BOUNDS_H

/** Largest number of parameters of an equation (the kernel's instance arrays). */
#ifndef CANRLS_N_MAX
#define CANRLS_N_MAX 12
#endif

/** Mapped feedback messages. */
#ifndef CANRLS_TARGET_MSG_MAX
#define CANRLS_TARGET_MSG_MAX 4
#endif

/** Filters of the bank. */
#ifndef CANRLS_TARGET_FILTER_MAX
#define CANRLS_TARGET_FILTER_MAX 16
#endif

/** Equations (mechanical, electrical). */
#ifndef CANRLS_TARGET_EQ_MAX
#define CANRLS_TARGET_EQ_MAX 2
#endif

#endif /* CANRLS_BOUNDS_H */
