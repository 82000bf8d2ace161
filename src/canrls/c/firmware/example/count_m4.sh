#!/bin/sh
# count_m4.sh ELF KERNEL_OBJ -- instructions per sample of the whole estimator on the
# Cortex-M4 (QEMU mps2-an386), from QEMU's execution log through ./count_exec.
#
# SPDX-License-Identifier: MIT
#
# ELF: the replay built with -DCANRLS_REPLAY_MARK=canrls_mark (make canrls_m4.elf);
# KERNEL_OBJ: canrls_fixed.c compiled alone, whose functions (with memset and memcpy) are
# the update. QEMU runs one instruction per translation block (-singlestep -d
# exec,nochain), so its log has a line per executed instruction. Prints the mean and the
# worst sample (every canrls_target_frame call of its frames), the same of the update
# (canrls_update_q31), the worst publication, and the front end's share (a sample less
# its updates) with the goal of a worst sample of at most 1500 instructions.
set -e
elf=$1
kobj=$2
NM=${ARM_NM:-arm-none-eabi-nm}
QEMU_M4=${QEMU_M4:-qemu-system-arm -M mps2-an386 -nographic -monitor none -semihosting-config enable=on,target=native}
syms=$($NM -S --defined-only "$elf")

# "lo hi" of a function of the ELF (the Thumb bit cleared), nothing if it has none
range() {
    echo "$syms" | while read -r a s t n; do
        if [ "$n" = "$1" ] && { [ "$t" = t ] || [ "$t" = T ]; }; then
            lo=$((0x$a & ~1))
            printf '0x%x 0x%x\n' "$lo" $((lo + 0x$s))
            break
        fi
    done
}
first() { set -- $(range "$1"); echo "$1"; }

kernel=""
for f in $($NM "$kobj" | awk '$2 == "t" || $2 == "T" { print $3 }') memset memcpy; do
    kernel="$kernel $(range "$f")"
done
# shellcheck disable=SC2086
$QEMU_M4 -singlestep -d exec,nochain -kernel "$elf" 2>&1 >/dev/null \
    | ./count_exec "$(first canrls_target_frame)" $(range canrls_replay_frames) \
        "$(first canrls_mark)" "$(first canrls_target_publish)" \
        "$(first canrls_update_q31)" $kernel \
    | awk '$1 == "sample" { n++; s += $2; if ($2 > ms) { ms = $2; at = n - 1 }
                            f = $2 - cur; sf += f; if (f > mf) mf = f; cur = 0 }
           $1 == "update" { u++; su += $2; if ($2 > mu) mu = $2; cur += $2 }
           $1 == "publish" { if ($2 > mp) mp = $2 }
           END {
               if (n == 0 || u == 0) { print "count_m4.sh: no sample or update counted"; exit 1 }
               printf "instructions per sample: mean %.0f, worst %d (sample %d); update: mean %.0f, worst %d (worst/mean %.2f); publication: worst %d\n", s / n, ms, at, su / u, mu, mu / (su / u), mp
               printf "front end (a sample less its updates): mean %.0f, worst %d; the goal of a worst sample <= 1500: %s\n", sf / n, mf, ms <= 1500 ? "met" : "missed"
           }'
