/*
 * size_main.c -- the least a firmware links of the whole estimator, for its size.
 *
 * SPDX-License-Identifier: MIT
 *
 * Calls every function of canrls_target.h that a firmware calls (canrls_target_init,
 * canrls_target_frame, canrls_target_publish, canrls_target_theta), so that a link with
 * -ffunction-sections -fdata-sections -Wl,--gc-sections keeps what those need and nothing
 * else: the `.text` + `.rodata` of that image (startup.c and this file included, with the
 * C library's memcpy and memset) is the size of the estimator in a firmware (`make
 * size-m4` of an export, `make target`). It is linked, never run.
 */
#include <stdint.h>

#include "canrls_model.h"
#include "canrls_target.h"

static canrls_target S;
static canrls_can_frame out[CANRLS_PUBLISH_MAX];
/* what the calls return, kept so that the compiler keeps the calls */
volatile uint32_t canrls_size_sink;

int main(void)
{
    static const uint8_t data[8] = {0u, 0u, 0u, 0u, 0u, 0u, 0u, 0u};
    int32_t word = 0, exp = 0;
    (void)canrls_target_init(&S, &canrls_model);
    if ((canrls_target_frame(&S, canrls_size_sink, 0u, data, 8u, 0u) & CANRLS_PUBLISH) != 0u) {
        canrls_size_sink = canrls_target_publish(&S, out, CANRLS_PUBLISH_MAX);
    }
    canrls_target_theta(&S, 0u, &word, &exp);
    canrls_size_sink = (uint32_t)word + (uint32_t)exp;
    return 0;
}
