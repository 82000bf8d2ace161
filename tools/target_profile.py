"""Where the whole estimator's instructions go on the Cortex-M4: a flat profile.

The simulated drive with the model of n parameters (``tools/target_whole.py``'s cases)
is exported with vectors and replayed on QEMU ``mps2-an386`` under its execution log
(``-singlestep -d exec,nochain``: one line per instruction); each executed address is
given to its innermost function, inlined ones included (``addr2line -i``), and the
functions are summed by the stage of the path they belong to (:data:`STAGES`).
Prints instructions per sample by stage (mean, and the worst sample of each stage)
and by function; the figures of docs/target.md. Needs ``arm-none-eabi-gcc`` and
``qemu-system-arm`` (``make target`` installs them)::

    .venv/bin/python tools/target_profile.py [--n 6] [--duration 3]
"""

from __future__ import annotations

import argparse
import collections
import re
import subprocess
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import target_whole as tw  # noqa: E402

#: the stage of each function of canrls_target.c (the rest: the kernel, canrls_fixed.c,
#: or the replay that feeds the frames and compares the records)
STAGES = {
    "decode and pair": ("canrls_target_frame", "cr_extract", "cr_bswap32",
                        "cr_popcount", "cr_float", "cr_float_word", "canrls_target_pair",
                        "canrls_target_reject", "cr_pair"),
    "filters (SVF, tanh, exp, sin/cos)": (
        "cr_filter", "cr_svf_row", "cr_svf_row32", "cr_split_input", "cr_inputs",
        "cr_table_eval",
        "cr_quarter", "cr_tanh_q24", "cr_tanh_q24_wide", "cr_exp2_neg_q24", "cr_exp_neg_q24",
        "cr_sincos_q64"),
    "columns, selection, rescale": (
        "cr_sample", "cr_update", "cr_values", "cr_changes", "cr_state", "cr_mul_rsh",
        "cr_sat", "cr_rsh", "cr_rsh32", "cr_shl", "cr_bitlen64", "cr_clog2", "cr_clog2_mul",
        "cr_adapt",
        "cr_scaled", "cr_restore", "cr_P_scale", "cr_isqrt", "cr_restart", "cr_trace_bound",
        "cr_floor_scaled", "cr_ceil_scaled", "fr_sample", "fr_update_0", "fr_update_1",
        "fr_changes_0", "fr_changes_1", "canrls_target_step",
        "cr_step", "cr_sat32", "cr_sampled",
        "canrls_target_adapt", "canrls_target_restart", "canrls_target_sampled"),
    "publication": ("canrls_target_publish", "cr_f32_bits", "cr_put", "cr_frame", "cr_emit"),
    "replay (the test harness)": ("canrls_replay_frames", "canrls_replay", "record", "memcmp",
                                  "canrls_mark", "main"),
}


KERNEL_STAGE = "kernel (canrls_fixed.c, memset, memcpy)"


def _functions(elf: Path) -> dict[int, str]:
    """The innermost function (inlined ones included) of every instruction of ``elf``."""
    dis = subprocess.run(["arm-none-eabi-objdump", "-d", "--no-show-raw-insn", str(elf)],
                         capture_output=True, text=True, check=True).stdout
    addrs = [m.group(1) for m in re.finditer(r"^\s+([0-9a-f]+):", dis, re.M)]
    r = subprocess.run(["arm-none-eabi-addr2line", "-a", "-f", "-i", "-e", str(elf)],
                       input="".join(f"0x{p}\n" for p in addrs), capture_output=True,
                       text=True, check=True)
    func: dict[int, str] = {}
    addr = None
    lines = r.stdout.splitlines()
    i = 0
    while i < len(lines):
        if lines[i].startswith("0x"):
            addr = int(lines[i], 16)
            i += 1
            continue
        if addr is not None and addr not in func:
            func[addr] = lines[i]  # the innermost (inlined) function comes first
        i += 2
    return func


def profile(n: int, duration: float, work: Path
            ) -> tuple[collections.Counter[str], list[dict[str, int]]]:
    """Instructions by innermost function over the replay, and each sample's by stage
    (a sample: the instructions from the first frame or the replay's last mark to its
    next one: its frames' calls, the replay around them, a publication it asked for)."""
    src = tw.export_case(work, n, duration)
    elf = work / "profile.elf"
    tw.build_example(src, elf, defines=(f"-DCANRLS_N={n}",))
    func = _functions(elf)
    stage_of = {f: s for s, fs in STAGES.items() for f in fs}
    stage = {a: stage_of.get(f, KERNEL_STAGE) for a, f in func.items()}
    syms = tw._symbols(elf)
    mark, first = syms["canrls_mark"][0], syms["canrls_target_frame"][0]
    q = subprocess.Popen([*tw.QEMU, "-singlestep", "-d", "exec,nochain", "-kernel", str(elf)],
                         stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    assert q.stderr is not None
    pcs: collections.Counter[int] = collections.Counter()
    samples: list[dict[str, int]] = []
    cur: collections.Counter[str] = collections.Counter()
    started = False
    pat = re.compile(r"\[[0-9a-f]+/([0-9a-f]+)/")
    for line in q.stderr:
        m = pat.search(line)
        if m:
            pc = int(m.group(1), 16)
            pcs[pc] += 1
            if not started:
                # the samples begin with the first frame (not the initialisation)
                started = pc == first
                if not started:
                    continue
            if pc == mark:
                samples.append(dict(cur))
                cur = collections.Counter()
            else:
                cur[stage.get(pc, "?")] += 1
    if q.wait() != 0:
        raise SystemExit("the replay on QEMU is not bit-exact")
    by = collections.Counter[str]()
    for p, c in pcs.items():
        by[func.get(p, "?")] += c
    return by, samples


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--n", type=int, default=6, choices=sorted(tw.CASES))
    ap.add_argument("--duration", type=float, default=3.0)
    a = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        by, samples = profile(a.n, a.duration, Path(tmp))
    stage_of = {f: s for s, fs in STAGES.items() for f in fs}
    total = collections.Counter[str]()
    worst = collections.Counter[str]()
    for smp in samples:
        for s, c in smp.items():
            total[s] += c
            worst[s] = max(worst[s], c)
    k = len(samples)
    print(f"instructions per sample, n = {a.n}, {k} samples of {a.duration:g} s "
          f"(start-up included), -O2 -DCANRLS_N={a.n}: mean, worst sample of the stage")
    for s, c in total.most_common():
        print(f"  {c / k:>8.0f} {worst[s]:>8}  {s}")
    print("by function (innermost, inlined included):")
    for f, c in by.most_common(30):
        print(f"  {c / k:>8.1f}  {f}  [{stage_of.get(f, 'kernel')}]")


if __name__ == "__main__":
    main()
