/* semihost.h -- the two semihosting calls of the bare-metal example. SPDX-License-Identifier: MIT */
#ifndef SEMIHOST_H
#define SEMIHOST_H

/** Print a NUL-terminated string on the host (SYS_WRITE0). */
void sh_write0(const char *s);
/** End the program: QEMU exits with status 0 if ok, else 1 (SYS_EXIT). */
void sh_exit(int ok);

#endif
