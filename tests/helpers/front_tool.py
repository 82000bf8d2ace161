"""The two front ends of an export, frame by frame: the generated one and the tables.

:func:`both_paths` builds a small program twice from an export with vectors (``canrls
export-c --vectors``): with the generated ``canrls_front.c`` (``-DCANRLS_FRONT``) and with
the table-driven ``canrls_target_frame`` of ``canrls_target.c``. The program feeds every
frame of ``canrls_vectors.h`` to ``canrls_target_frame`` and prints, after each one, what
it returned and a 64-bit FNV-1a hash of the whole state (``canrls_target`` without its
pointers), and every frame of every publication: equal output means the two paths
computed the same integers after every frame.
"""

from __future__ import annotations

import re
import subprocess
from pathlib import Path

from debian import need_tool

__all__ = ["HARNESS", "both_paths"]

HARNESS = r"""
#include <stdio.h>
#include <string.h>

#include "canrls_model.h"
#include "canrls_vectors.h"

static canrls_target S, T;

int main(void)
{
    static canrls_can_frame out[CANRLS_PUBLISH_MAX];
    uint32_t k, i, j, n;
    if (canrls_target_init(&S, &canrls_model) != CANRLS_OK) {
        return 2;
    }
    for (k = 0; k < VEC_FRAMES; k++) {
        const uint32_t r = canrls_target_frame(&S, vec_id[k] & 0x7FFFFFFFu, vec_id[k] >> 31,
                                               vec_data[k], vec_len[k], vec_t[k]);
        const unsigned char *b = (const unsigned char *)&T;
        unsigned long long h = 14695981039346656037ull;
        size_t m;
        /* the state without its pointers (addresses differ between the two programs) */
        memcpy(&T, &S, sizeof T);
        T.model = NULL;
        for (m = 0; m < CANRLS_TARGET_EQ_MAX; m++) {
            T.eq[m].rls.plan = NULL;
        }
        for (m = 0; m < sizeof T; m++) {
            h = (h ^ b[m]) * 1099511628211ull;
        }
        printf("%u %u %016llx\n", (unsigned)k, (unsigned)r, h);
        if (r & CANRLS_PUBLISH) {
            n = canrls_target_publish(&S, out, CANRLS_PUBLISH_MAX);
            for (i = 0; i < n; i++) {
                printf("  %x", (unsigned)out[i].id);
                for (j = 0; j < 8u; j++) {
                    printf(" %02x", (unsigned)out[i].data[j]);
                }
                printf("\n");
            }
        }
    }
    return 0;
}
"""


def both_paths(out: Path) -> tuple[str, str]:
    """The harness's output with the generated front end and with the tables."""
    need_tool("cc", ["gcc"])
    (out / "front_harness.c").write_text(HARNESS)
    m = re.search(r"^TABLE_DEFS \?=(.*)$", (out / "Makefile").read_text(), re.M)
    assert m is not None
    ndefs = m.group(1).split()
    cc = ["cc", "-std=c99", "-O2", "-Wall", "-Wextra", "-Werror", *ndefs, "-I", str(out)]
    # the kernel (canrls_fixed.c reads no front-end define) compiled once for both builds
    kernel = out / "harness_fixed.o"
    r = subprocess.run([*cc, "-c", str(out / "canrls_fixed.c"), "-o", str(kernel)],
                       capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    common = [*cc, str(out / "front_harness.c"), str(out / "canrls_target.c"),
              str(out / "canrls_model.c"), str(kernel)]
    texts = []
    for name, extra in (("front", ["-DCANRLS_FRONT", str(out / "canrls_front.c")]),
                        ("tables", [])):
        exe = out / f"harness_{name}"
        r = subprocess.run([*common, *extra, "-o", str(exe)], capture_output=True, text=True)
        assert r.returncode == 0, r.stderr
        run = subprocess.run([str(exe)], capture_output=True, text=True, timeout=600)
        assert run.returncode == 0, run.stderr
        texts.append(run.stdout)
    return texts[0], texts[1]
