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
 * completed a sample: the instruction count finds the samples by it. It then prints the
 * deepest stack the replay used (painted before it, scanned after) and the size of the
 * state.
 */
#include <stdint.h>

#include "canrls_replay.h"
#include "semihost.h"

static canrls_target S; /* the caller owns the state */

/* the stack below main's frame painted with this word before the replay */
#define PAINT 0xC5A1C5A1u
#define PAINTED 16384u

static uint32_t *stack_here(void)
{
    uint32_t *sp;
    __asm__ volatile("mov %0, sp" : "=r"(sp));
    return sp;
}

/* paints PAINTED bytes below its caller's frame (less a margin for its own), returns the
 * top of the painted area */
__attribute__((noinline)) static uint32_t *paint(void)
{
    uint32_t *top = stack_here() - 16;
    uint32_t *p;
    for (p = top - PAINTED / 4u; p < top; p++) {
        *p = PAINT;
    }
    return top;
}

/* bytes of the painted area written since (the deepest stack of the replay) */
static uint32_t stack_used(const uint32_t *top)
{
    const uint32_t *p = top - PAINTED / 4u;
    while (p < top && *p == PAINT) {
        p++;
    }
    return (uint32_t)(top - p) * 4u;
}

static void say_uint(uint32_t v)
{
    char buf[12];
    char *s = buf + sizeof buf - 1;
    *s = '\0';
    do {
        *--s = (char)('0' + v % 10u);
        v /= 10u;
    } while (v != 0u);
    sh_write0(s);
}

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
    uint32_t *top = paint();
    const int ok = canrls_replay(&S, say);
    /* the deepest stack below main: canrls_target_frame, canrls_target_publish and the
     * replay's own frames (a few words); the state: the caller's canrls_target */
    sh_write0("stack: ");
    say_uint(stack_used(top));
    sh_write0(" bytes; state (canrls_target): ");
    say_uint((uint32_t)sizeof S);
    sh_write0(" bytes\n");
    return ok ? 0 : 1;
}
