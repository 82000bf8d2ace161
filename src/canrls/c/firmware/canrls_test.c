/*
 * canrls_test.c -- the host test of an export: the vectors of a log through the whole
 * estimator, bit for bit against the Python specification.
 *
 * SPDX-License-Identifier: MIT
 *
 * cc -std=c99 -O2 -Wall -Wextra -Werror -DCANRLS_FRONT canrls_test.c canrls_replay.c \
 *    canrls_target.c canrls_front.c canrls_model.c canrls_fixed.c -o canrls_test && ./canrls_test
 * (`make test`; without -DCANRLS_FRONT and canrls_front.c, the table-driven front end:
 * `make test-tables`). Exit status 0 when bit-exact.
 */
#include <stdio.h>

#include "canrls_replay.h"

static canrls_target S; /* the caller owns the state */

static void say(const char *s)
{
    fputs(s, stdout);
}

int main(void)
{
    return canrls_replay(&S, say) ? 0 : 1;
}
