/*
 * count_exec.c -- instructions per sample of the whole estimator, from QEMU's execution
 * log (make target: tools/build_target.py).
 *
 * SPDX-License-Identifier: MIT
 *
 * usage: count_exec FRAME CALLER_LO CALLER_HI MARK PUBLISH UPDATE KLO KHI [KLO KHI ...] < log
 * (addresses in hex): stdin is `qemu-system-arm -singlestep -d exec,nochain`'s log, one
 * line per executed instruction ("Trace N: HOST [CS/PC/FLAGS/...] ..."). A call of the
 * function at FRAME (canrls_target_frame) runs from its entry to the first instruction
 * back in [CALLER_LO, CALLER_HI) (the replay loop); the loop calls MARK after each frame
 * that completed a sample, so a sample is every frame call since the last mark. PUBLISH
 * (canrls_target_publish) is counted the same way, on its own. A call of UPDATE
 * (canrls_update_q31) runs from its entry to the first instruction outside the kernel's
 * ranges [KLO, KHI) (its own functions and the library's memset and memcpy).
 * stdout: "sample N" per sample (the instructions of its frames), "update N" per update,
 * "publish N" per publication.
 */
#include <inttypes.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#define MAXR 64

static uint32_t klo[MAXR], khi[MAXR];
static int nk;

static int in_kernel(uint32_t pc)
{
    int i;
    for (i = 0; i < nk; i++) {
        if (pc >= klo[i] && pc < khi[i]) {
            return 1;
        }
    }
    return 0;
}

int main(int argc, char **argv)
{
    char line[512];
    uint32_t frame, clo, chi, mark, publish, update;
    int i, in_frame = 0, in_pub = 0, in_upd = 0;
    uint64_t nframe = 0, nsample = 0, npub = 0, nupd = 0;
    if (argc < 9 || (argc - 7) % 2 != 0) {
        fprintf(stderr, "usage: count_exec FRAME CLO CHI MARK PUBLISH UPDATE KLO KHI ...\n");
        return 2;
    }
    frame = (uint32_t)strtoul(argv[1], NULL, 16);
    clo = (uint32_t)strtoul(argv[2], NULL, 16);
    chi = (uint32_t)strtoul(argv[3], NULL, 16);
    mark = (uint32_t)strtoul(argv[4], NULL, 16);
    publish = (uint32_t)strtoul(argv[5], NULL, 16);
    update = (uint32_t)strtoul(argv[6], NULL, 16);
    for (i = 7; i + 1 < argc && nk < MAXR; i += 2, nk++) {
        klo[nk] = (uint32_t)strtoul(argv[i], NULL, 16);
        khi[nk] = (uint32_t)strtoul(argv[i + 1], NULL, 16);
    }
    while (fgets(line, sizeof line, stdin) != NULL) {
        const char *b = strchr(line, '[');
        const char *s;
        uint32_t pc;
        if (strncmp(line, "Trace ", 6) != 0 || b == NULL || (s = strchr(b, '/')) == NULL) {
            continue;
        }
        pc = (uint32_t)strtoul(s + 1, NULL, 16);
        if (in_upd) {
            if (in_kernel(pc)) {
                nupd++;
            } else {
                printf("update %" PRIu64 "\n", nupd);
                in_upd = 0;
            }
        }
        if (!in_upd && pc == update && (in_frame || in_pub)) {
            in_upd = 1;
            nupd = 1;
        }
        if (in_frame) {
            if (pc >= clo && pc < chi) {
                nsample += nframe;
                in_frame = 0;
            } else {
                nframe++;
            }
        } else if (in_pub) {
            if (pc >= clo && pc < chi) {
                printf("publish %" PRIu64 "\n", npub);
                in_pub = 0;
            } else {
                npub++;
            }
        }
        if (!in_frame && !in_pub) {
            if (pc == frame) {
                in_frame = 1;
                nframe = 1;
            } else if (pc == publish) {
                in_pub = 1;
                npub = 1;
            } else if (pc == mark) {
                printf("sample %" PRIu64 "\n", nsample);
                nsample = 0;
            }
        }
    }
    return 0;
}
