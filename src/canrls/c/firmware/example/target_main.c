/*
 * target_main.c -- the whole estimator on a Cortex-M4: a log's frames through
 * canrls_target_frame(), bit for bit against the Python specification.
 *
 * SPDX-License-Identifier: MIT
 *
 * Built by `make target` (tools/build_target.py) with the files `canrls export-c
 * --vectors LOG` writes (canrls_model.c, canrls_vectors.h, canrls_replay.c): it replays
 * every frame, compares every state record and every published frame with the
 * specification's, prints one line and exits 0 only if all are the same. Built with
 * -DCANRLS_REPLAY_MARK=canrls_mark, the replay calls canrls_mark() after each frame that
 * completed a sample: the instruction count finds the samples by it.
 */
#include <stdint.h>

#include "canrls_replay.h"
#include "semihost.h"

static canrls_target S; /* the caller owns the state */

/* after each frame that completed a sample (see above); does nothing */
__attribute__((noinline)) void canrls_mark(uint32_t r)
{
    __asm__ volatile("" : : "r"(r) : "memory");
}

static void say(const char *s)
{
    sh_write0(s);
}

int main(void)
{
    return canrls_replay(&S, say) ? 0 : 1;
}
