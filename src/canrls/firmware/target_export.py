"""``canrls export-c``'s whole estimator: the files the target runs, a README and tests.

:func:`export_target` writes, beside the kernel and the configuration that
:func:`canrls.firmware.kernel_export.export_c` writes:

* ``canrls_target.h``, ``canrls_target.c``, ``canrls_target_math.h``,
  ``canrls_target_tables.h`` -- the whole per-frame path (a copy of ``canrls/c/firmware``);
  ``canrls_target_check.h``, ``canrls_target_check.c`` -- the check of a restored state;
* ``canrls_front.c`` -- its front end (decode, pair, filters, columns, selection) in
  straight-line code for this model and DBC (:mod:`canrls.firmware.front`);
* ``canrls_model.h``, ``canrls_model.c`` -- the constant ``canrls_model`` of this model
  and DBC (:mod:`canrls.firmware.cgen`);
* ``README.md`` -- what to compile, the call order, the numbers; ``Makefile`` -- the
  host test and the check that the fixed build holds no floating point (``nm``);
* with vectors from logs: ``canrls_vectors.h`` (:mod:`canrls.firmware.vectors`),
  ``canrls_replay.h``/``.c`` and ``canrls_test.c``: ``make test`` replays them and says
  whether the C is bit-exact with the specification.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from importlib import resources
from pathlib import Path

from canrls.core.c_escape import check_text
from canrls.core.files import write_texts
from canrls.firmware.cgen import bounds_file, model_files
from canrls.firmware.front import front_file
from canrls.firmware.load import Source
from canrls.firmware.target_model import SOURCE_NAMES, TargetModel
from canrls.firmware.vectors import Vectors, log_frames, record, vectors_header

__all__ = ["TARGET_FILES", "TEST_FILES", "TargetExport", "export_target", "readme",
           "target_texts"]

#: the whole path's files, copied from the package (``canrls/c/firmware``)
TARGET_FILES = ("canrls_target.h", "canrls_target.c", "canrls_target_math.h",
                "canrls_target_tables.h", "canrls_target_check.h", "canrls_target_check.c")
#: the replay of test vectors and its host program
TEST_FILES = ("canrls_replay.h", "canrls_replay.c", "canrls_test.c")
#: the least firmware, linked for its size (``make size-m4``)
SIZE_FILES = ("example/size_main.c",)
#: the replay on a Cortex-M4 under QEMU (``make test-m4``, ``make count-m4``): the
#: bare-metal example's files and the instruction counter, from ``c/firmware``
M4_FILES = ("example/startup.c", "example/target_main.c", "example/semihost.h",
            "example/mps2_an386.ld", "example/count_m4.sh", "drivers/count_exec.c")


@dataclass(frozen=True)
class TargetExport:
    """What :func:`export_target` wrote."""

    out: Path
    files: tuple[Path, ...]
    model: TargetModel
    vectors: Vectors | None

    def __str__(self) -> str:
        s = (f"{self.out}: the whole estimator ({', '.join(p.name for p in self.files)}; "
             f"{self.model.n_params} parameters, period {self.model.dt * 1e3:.6g} ms)")
        if self.vectors is not None:
            v = self.vectors
            s += (f"\ntest vectors: {len(v.frames)} frames, {v.samples} samples, "
                  f"{len(v.checkpoints)} state records, {len(v.publications)} publications "
                  f"(make -C {self.out} test)")
        return s


def _text(s: str, what: str) -> str:
    """A user's name or unit in the README: printable text (``canrls.core.c_escape``), with the
    Markdown code span's backticks taken out."""
    return check_text(s, what).replace("`", "'")


def _tables(tm: TargetModel) -> tuple[str, str, str, str]:
    """The README's tables: parameters, messages, filters and Q formats (rows only)."""
    rows = []
    k = 0
    for e in tm.equations:
        for p, s in zip(e.parameters, e.exponents, strict=False):
            rows.append(f"| {k} | `{_text(p.name, 'parameter')}` | {_text(p.unit, 'unit')} | "
                        f"{e.name} | {s} |")
            k += 1
    msgs = "\n".join(f"| {_text(m.name, 'message')} | {m.id:#x}{' (29-bit)' if m.extended else ''}"
                     f" | {m.dlc} | {'yes' if m.crc else 'no'} | "
                     f"{'yes' if m.counter else 'no'} |" for m in tm.messages)
    filters = "\n".join(f"| {i} | {SOURCE_NAMES[f.kind]} | {f.role or '-'} | "
                        f"{'zero-order' if f.hold else 'straight line'} | {f.fx} |"
                        for i, f in enumerate(tm.filters))
    fmts = "\n".join(f"| {e.name} | Q.{e.f_phi} | Q.{e.f_y} | Q.{e.f_theta} | Q.{e.f_eps} | "
                     f"{e.lam!r} | {e.selection.warmup} |" for e in tm.equations)
    return "\n".join(rows), msgs, filters, fmts


def _floats(tm: TargetModel) -> str:
    """The README's paragraph on the float signals (empty without one)."""
    said = [f"{role} (float{f.length}, raw = round(v 2^{f.frac}))"
            for role, f in tm.roles.items() if f.is_float]
    if not said:
        return ""
    return ("\nFloat signals are decoded with integer operations into fixed point: "
            + ", ".join(said) + ", half away from zero; a NaN, an infinity or a value "
            "outside the DBC's range rejects the frame (`CANRLS_R_RANGE`).\n")


def _use(tm: TargetModel) -> str:
    """The README's C example: start, the call per frame and what to do with the
    parameters (sent in canrls' frames, or read by the caller)."""
    tick = f"/* every CAN frame received (extended: 1 for a 29-bit ID), t its receive time in\n" \
           f"   ticks of {tm.tick_s!r} s (mod 2^32) */"
    if tm.out:
        return f"""static canrls_can_frame out[CANRLS_PUBLISH_MAX];

void can_send(const canrls_can_frame *f);   /* the firmware's: f->id, f->dlc, f->data */

/* once: CANRLS_OK, or CANRLS_EINVAL for a model beyond the build's bounds */
int start(void) {{ return canrls_target_init(&S, &canrls_model); }}

{tick}
void on_frame(uint32_t id, uint32_t extended, const uint8_t *data, uint32_t len, uint32_t t)
{{
    if (canrls_target_frame(&S, id, extended, data, len, t) & CANRLS_PUBLISH) {{
        /* RlsEstimate of every parameter, RlsStatus, RlsHealth (RlsParamInfo every
           tenth publication) */
        uint32_t i, n = canrls_target_publish(&S, out, CANRLS_PUBLISH_MAX);
        for (i = 0; i < n; i++) {{
            can_send(&out[i]);
        }}
    }}
}}"""
    return f"""/* once: CANRLS_OK, or CANRLS_EINVAL for a model beyond the build's bounds */
int start(void) {{ return canrls_target_init(&S, &canrls_model); }}

{tick}
void on_frame(uint32_t id, uint32_t extended, const uint8_t *data, uint32_t len, uint32_t t)
{{
    (void)canrls_target_frame(&S, id, extended, data, len, t);
}}

/* parameter i (canrls_target_theta index below) as word 2^exp in SI units */
void parameter(uint32_t i, int32_t *word, int32_t *exp)
{{
    canrls_target_theta(&S, i, word, exp);
}}"""


def _test_section(vectors: Vectors | None) -> str:
    """The README's section on the test vectors ("" without them)."""
    if vectors is None:
        return ""
    return f"""
## The test: bit for bit against the specification

`canrls_vectors.h` holds the {len(vectors.frames)} frames of {_text(vectors.source, 'log')}
and what the Python specification (`canrls.firmware.spec`) computes from them: the whole
integer state every {vectors.every} samples
({len(vectors.checkpoints)} records) and the {len(vectors.publications)} publications.

```sh
make test          # the host compiler: prints "... bit-exact with the specification"
make test-arm      # 32-bit ARM Linux under qemu-arm (arm-linux-gnueabihf-gcc, qemu-user)
make test-m4       # a Cortex-M4 under QEMU (mps2-an386, bare metal): bit for bit, then
                   # "stack: N bytes; state (canrls_target): M bytes"
make count-m4      # the same with every instruction counted: per sample and per update,
                   # mean and worst (slow; gcc-arm-none-eabi, libnewlib-arm-none-eabi,
                   # qemu-system-arm)
```

`canrls_test.c` is a plain `main()` around `canrls_replay()` (`canrls_replay.c`), which
any board can call too: it replays the frames through `canrls_target_frame()` and
compares every record and every published frame word for word. A replay that fails
prints the first sample that differs and which value: a word of the state record by
name (`theta[2] of equation 0`, expected and computed) or a publication's frame. The
stack `make test-m4` prints is the deepest of the whole replay below `main` (painted
before, scanned after: `target_main.c`), the replay's own frames included.
"""


def readme(tm: TargetModel, label: str, vectors: Vectors | None, single_n: int | None) -> str:
    """The README of an export: what to compile, the call order, the numbers."""
    nflag = f" -DCANRLS_N={single_n}" if single_n else ""
    rows, msgs, filters, fmts = _tables(tm)
    use = _use(tm)
    pairing = " and carry its alive counter" if tm.match_counters else ""
    test = _test_section(vectors)
    return f"""# The whole estimator on the target

Generated by `canrls export-c` from {_text(label, 'source')}: the identification of the
model below from the drive's own CAN frames to canrls' parameter and status frames, in
integers only (no floating point, no malloc; C99 with `<stdint.h>`, `<stddef.h>`,
`<string.h>`). It computes the same integers, bit for bit, as the Python specification
`canrls.firmware.spec.TargetEstimator` (`docs/target.md` of canrls).

## Build

Add these files to the firmware and build every file with the same defines:

```sh
cc -std=c99 -O2{nflag} -DCANRLS_FRONT -c canrls_target.c canrls_front.c canrls_model.c canrls_fixed.c
```

| file | what it holds |
|---|---|
| `canrls_front.c` | `canrls_target_frame()` for this model and DBC in straight-line code: each message's ID, length and CRC, each field's bytes, shifts and masks, each filter's coefficients and the model's columns as constants |
| `canrls_target.h`, `canrls_target.c`, `canrls_target_math.h`, `canrls_target_tables.h` | the rest of the path (pairing, restart, rescale, update, publish) and the arithmetic; built without `-DCANRLS_FRONT` (and without `canrls_front.c`) it is the whole path, driven by the tables of `canrls_model` (`make test-tables`: the same integers) |
| `canrls_target_check.h`, `canrls_target_check.c` | `canrls_target_check_state()`: whether a state restored from flash is one the estimator can reach on this model (every field against its invariant); for a firmware that keeps its state across a reset (add `canrls_target_check.c` to the build) |
| `canrls_model.h`, `canrls_model.c` | `canrls_model`: every constant of this model and DBC |
| `canrls_bounds.h` | the build's bounds, this model's own (parameters, messages, filters, equations): the state `canrls_target` holds this model alone; each is `#ifndef`-overridable, for every file alike (the state's layout depends on them); a model of one equation also gives its plan, `CANRLS_PLAN_CONST`, which the kernel folds into its code (`canrls_init_q31` then refuses any other plan; `-DCANRLS_PLAN_RUNTIME` reads it at run time, as `make test-tables` does: the same integers) |
| `canrls_fixed.h`, `canrls_fixed.c` | the recursive least squares kernel |
| `canrls_config.h`, `canrls_config.c` | the kernel's plan and prior alone (for a firmware that builds its own regressors) |
| `canrls_frames.h`, `canrls_frames.c` | cantools' codecs of canrls' frames: they use `double`, and the estimator does not need them (it packs its frames in integers) |

{"All equations have " + str(single_n) + " parameters: `-DCANRLS_N=" + str(single_n) + "` builds the kernel made for that n (the same integers in fewer instructions); `canrls_model.h` stops a build with another." if single_n else "The equations have different n: build without `-DCANRLS_N`."}
`make check-float` compiles the three sources for a Cortex-M4 with software floating
point and fails if `arm-none-eabi-nm` finds a floating-point routine among their symbols.

## Use

```c
#include "canrls_model.h"

static canrls_target S;                     /* the caller owns the state */
{use}
```

`canrls_target_theta(&S, i, &word, &exp)` gives parameter `i` at any time: `word 2^exp`
in SI units. The frames are canrls' own (its DBC: RlsEstimate 0x300 ...; `canrls
monitor` reads them){"" if tm.out else ": none here (exported with --frames none), the caller sends the estimate itself"}.
A publication is due every {tm.publish_every} samples; the control period is
{tm.dt_ticks} ticks.

## The model

Feedback messages (every one is needed for a sample; frames pair into one sample when
they arrive within half a control period of its first{pairing}):

| message | ID | DLC | E2E CRC | alive counter |
|---|---|---|---|---|
{msgs}
{_floats(tm)}
Parameters (`canrls_target_theta` index; column exponent at the start):

| i | parameter | unit | equation | exponent |
|---|---|---|---|---|
{rows}

Filters (state-variable filter, 64-bit states `F[u] 2^FX`, Q30 coefficients):

| filter | input | signal | hold | FX |
|---|---|---|---|---|
{filters}

Q formats of the kernel per equation (`phi`, `y`, `theta`, `eps`), forgetting factor and
warm-up samples:

| equation | phi | y | theta | eps | lambda | warm-up |
|---|---|---|---|---|---|---|
{fmts}

## Memory and cost

`canrls_target` holds one kernel instance and one plan per equation and the filters'
states; `.data` and `.bss` are empty (the caller owns everything). Instruction counts
and sizes on a Cortex-M4 (worst sample of a whole log, start-up included) are in
canrls' `docs/target.md` (`make target`).

Two goals of canrls for the whole path on a Cortex-M4, each for its own build: speed at
`-O2` (a worst sample of at most 1,500 instructions, start-up included) and size at `-Os`
(`.text` + `.rodata` of what a firmware links under 12 KB). Measured at n = 6 on canrls'
simulated drive and an HSM150 run (`make target`, `docs/target.md`), this code gives
**the size, not the speed**: at `-O2` the worst sample is about 1,650 to 1,800
instructions (the kernel's update alone up to about 1,020 with its plan a constant, within
1.2 times its mean; the generated front end under 750), at `-Os` the linked library is
about 11.8 KB (the kernel,
built for size with its loops, about 3.9 KB of it). The `-Os` build is smaller and slower
(at n = 6 about 4,100 instructions a sample on average, 5,300 at worst). {"`make count-m4` (at `M4_OPT`, `-O2`) and " if vectors else ""}`make size-m4` (at `-Os`, linked with
`size_main.c`, the least program that calls the API, and `--gc-sections`)
measure{"" if vectors else "s"} this export and say met or missed.
{test}"""


def _makefile(single_n: int | None, vectors: bool) -> str:
    n = f" -DCANRLS_N={single_n}" if single_n else ""
    lines = ["# generated by `canrls export-c`: the host test and the floating-point check",
             "CC ?= cc", "CFLAGS ?= -std=c99 -O2 -Wall -Wextra -Wconversion -Wpedantic -Werror",
             f"DEFS ?={n} -DCANRLS_FRONT",
             "SRC = canrls_target.c canrls_front.c canrls_model.c canrls_fixed.c",
             "# the table-driven front end of canrls_target.c instead of canrls_front.c, and the",
             "# kernel's plan read at run time, not the constant of canrls_bounds.h",
             f"TABLE_DEFS ?={n} -DCANRLS_PLAN_RUNTIME", "TABLE_SRC = canrls_target.c canrls_model.c canrls_fixed.c",
             "ARM_CC ?= arm-none-eabi-gcc", "ARM_NM ?= arm-none-eabi-nm",
             "ARM_SIZE ?= arm-none-eabi-size",
             "ARM_FLAGS ?= -mcpu=cortex-m4 -mthumb -mfloat-abi=soft -Os", "",
             ".PHONY: check-float size-m4" + (" test test-tables test-arm test-m4 count-m4"
                                              if vectors else ""),
             ""]
    if vectors:
        lines += ["test: canrls_test", "\t./canrls_test", "",
                  "canrls_test: $(SRC) canrls_replay.c canrls_test.c $(wildcard *.h)",
                  "\t$(CC) $(CFLAGS) $(DEFS) -o $@ canrls_test.c canrls_replay.c $(SRC)",
                  "\t$(CC) $(CFLAGS) $(DEFS) -c -o canrls_target_check.o canrls_target_check.c",
                  "",
                  "# the same vectors through the table-driven front end: both paths give the "
                  "same integers",
                  "test-tables: canrls_test_tables", "\t./canrls_test_tables", "",
                  "canrls_test_tables: $(TABLE_SRC) canrls_replay.c canrls_test.c $(wildcard *.h)",
                  "\t$(CC) $(CFLAGS) $(TABLE_DEFS) -o $@ canrls_test.c canrls_replay.c $(TABLE_SRC)",
                  "",
                  "test-arm:",
                  "\tarm-linux-gnueabihf-gcc -static $(CFLAGS) $(DEFS) -o canrls_test_arm "
                  "canrls_test.c canrls_replay.c $(SRC)",
                  "\tqemu-arm ./canrls_test_arm", "",
                  "# the Cortex-M4 (QEMU mps2-an386, bare metal): the replay, its deepest "
                  "stack and the state",
                  "M4_OPT ?= -O2",
                  "QEMU_M4 ?= qemu-system-arm -M mps2-an386 -nographic -monitor none "
                  "-semihosting-config enable=on,target=native",
                  "test-m4: canrls_m4.elf", "\t$(QEMU_M4) -kernel canrls_m4.elf 2>&1", "",
                  "canrls_m4.elf: $(SRC) canrls_replay.c startup.c target_main.c "
                  "mps2_an386.ld $(wildcard *.h)",
                  "\t$(ARM_CC) -mcpu=cortex-m4 -mthumb $(M4_OPT) -std=c99 -Wall -Wextra "
                  "-Werror $(DEFS) -DCANRLS_REPLAY_MARK=canrls_mark -ffunction-sections -I. "
                  "-nostartfiles --specs=nano.specs -T mps2_an386.ld -Wl,--gc-sections "
                  "startup.c target_main.c canrls_replay.c $(SRC) -o $@", "",
                  "# instructions per sample and per update, mean and worst (slow: QEMU logs "
                  "every instruction)",
                  "count-m4: canrls_m4.elf count_exec",
                  "\t$(ARM_CC) -mcpu=cortex-m4 -mthumb $(M4_OPT) -std=c99 $(DEFS) -c "
                  "canrls_fixed.c -o canrls_fixed_m4.o",
                  "\tARM_NM='$(ARM_NM)' QEMU_M4='$(QEMU_M4)' sh count_m4.sh canrls_m4.elf "
                  "canrls_fixed_m4.o", "",
                  "count_exec: count_exec.c", "\t$(CC) -O2 -o $@ count_exec.c", ""]
    lines += ["# .text + .rodata that a firmware links for a Cortex-M4 at -Os (size_main.c calls "
              "the API;",
              "# every function and constant in its own section, the unused ones dropped), and "
              "the goal of 12 KB",
              "size-m4:",
              "\t$(ARM_CC) $(ARM_FLAGS) $(DEFS) -std=c99 -Wall -Wextra -Werror -ffunction-sections "
              "-fdata-sections -nostartfiles --specs=nano.specs -Wl,--entry=main -Wl,--gc-sections "
              "-o canrls_size.elf size_main.c $(SRC)",
              "\t$(ARM_SIZE) -A canrls_size.elf | "
              "awk '/^\\.(text|rodata)/ { s += $$2 } END { printf \"-Os .text + .rodata linked: "
              "%d B (the goal of under 12288 B: %s)\\n\", s, s < 12288 ? \"met\" : \"missed\" }'",
              "",
              "# no floating-point routine (soft-float calls: __aeabi_d*, __aeabi_f*, ...)",
              "check-float:",
              "\t$(ARM_CC) $(ARM_FLAGS) $(DEFS) -std=c99 -Wall -Wextra -Werror -c $(SRC) "
              "canrls_target_check.c",
              "\t! $(ARM_NM) canrls_target.o canrls_front.o canrls_model.o canrls_fixed.o "
              "canrls_target_check.o | "
              "grep -E '__aeabi_[df]|__(add|sub|mul|div)[sd]f3|__(float|fix)'",
              "\t@echo 'no floating point in the fixed build'", ""]
    return "\n".join(lines)


def target_texts(src: Source, tm: TargetModel, *, vectors: Sequence[str | Path] = (),
                 every: int = 1000) -> tuple[list[tuple[str, str]], Vectors | None]:
    """Every file of the whole estimator of ``tm`` (built from ``src``), ``(name, text)``,
    with test vectors from the logs ``vectors`` (a state record every ``every``
    samples): generated before anything is written."""
    kernel = resources.files("canrls") / "c" / "firmware"
    names = TARGET_FILES + SIZE_FILES + (TEST_FILES + M4_FILES if vectors else ())
    texts = [(name.rpartition("/")[2], (kernel / name).read_text()) for name in names]
    h, c = model_files(tm, src.label)
    texts += [("canrls_bounds.h", bounds_file(tm, src.label)),
              ("canrls_model.h", h), ("canrls_model.c", c),
              ("canrls_front.c", front_file(tm, src.label))]
    v = None
    if vectors:
        v = record(tm, log_frames(vectors, tm.tick_s), every=every,
                   source=", ".join(Path(x).name for x in vectors))
        texts.append(("canrls_vectors.h", vectors_header(v)))
    sizes = {e.n for e in tm.equations}
    single = sizes.pop() if len(sizes) == 1 else None
    texts += [("README.md", readme(tm, src.label, v, single)),
              ("Makefile", _makefile(single, v is not None))]
    return texts, v


def export_target(src: Source, out: str | Path, tm: TargetModel, *,
                  vectors: Sequence[str | Path] = (), every: int = 1000,
                  what: str | None = None,
                  texts: tuple[list[tuple[str, str]], Vectors | None] | None = None
                  ) -> TargetExport:
    """Write the whole estimator of ``tm`` into the directory ``out`` (made if missing;
    ``what`` names it in errors): :func:`target_texts` (or ``texts``, its result), each
    file written to a temporary and renamed (:func:`canrls.core.files.atomic_writer`)."""
    label = what or str(out)
    files_texts, v = texts if texts is not None else target_texts(
        src, tm, vectors=vectors, every=every)
    files = write_texts(out, files_texts, label)
    return TargetExport(Path(out), tuple(files), tm, v)
