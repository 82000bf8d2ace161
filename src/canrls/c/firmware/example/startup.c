/*
 * startup.c -- vector table, reset handler and semihosting for a bare Cortex-M4.
 *
 * SPDX-License-Identifier: MIT
 *
 * For QEMU's mps2-an386 (Cortex-M4, code at 0x00000000, RAM at 0x20000000; see
 * mps2_an386.ld). Output goes through ARM semihosting (QEMU:
 * -semihosting-config enable=on,target=native): SYS_WRITE0 prints a string, SYS_EXIT
 * ends the emulation with status 0 (application exit) or 1 (run-time error).
 */
#include <stdint.h>

#include "semihost.h"

extern uint32_t __etext, __data_start__, __data_end__, __bss_start__, __bss_end__;
extern uint32_t __stack_top__;
extern int main(void);

/* semihosting call: r0 = operation, r1 = argument, BKPT 0xAB */
static uint32_t semihost(uint32_t op, const void *arg)
{
    register uint32_t r0 __asm__("r0") = op;
    register const void *r1 __asm__("r1") = arg;
    __asm__ volatile("bkpt 0xAB" : "+r"(r0) : "r"(r1) : "memory");
    return r0;
}

void sh_write0(const char *s)
{
    (void)semihost(0x04u /* SYS_WRITE0 */, s);
}

void sh_exit(int ok)
{
    /* SYS_EXIT with ADP_Stopped_ApplicationExit or ADP_Stopped_RunTimeErrorUnknown */
    (void)semihost(0x18u, (const void *)(uintptr_t)(ok ? 0x20026u : 0x20023u));
    for (;;) {
    }
}

void Reset_Handler(void)
{
    uint32_t *src = &__etext;
    uint32_t *dst = &__data_start__;
    /* .data from flash to RAM, .bss zeroed */
    while (dst < &__data_end__) {
        *dst++ = *src++;
    }
    for (dst = &__bss_start__; dst < &__bss_end__; dst++) {
        *dst = 0u;
    }
    sh_exit(main() == 0);
}

static void Fault_Handler(void)
{
    sh_write0("fault\n");
    sh_exit(0);
}

__attribute__((section(".vectors"), used))
static void (*const vectors[16])(void) = {
    (void (*)(void))(&__stack_top__), /* initial stack pointer */
    Reset_Handler,                    /* reset */
    Fault_Handler,                    /* NMI */
    Fault_Handler,                    /* HardFault */
    Fault_Handler,                    /* MemManage */
    Fault_Handler,                    /* BusFault */
    Fault_Handler,                    /* UsageFault */
    0, 0, 0, 0,                       /* reserved */
    Fault_Handler,                    /* SVCall */
    Fault_Handler,                    /* DebugMonitor */
    0,                                /* reserved */
    Fault_Handler,                    /* PendSV */
    Fault_Handler,                    /* SysTick */
};
