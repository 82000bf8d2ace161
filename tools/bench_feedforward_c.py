"""Flash and instructions per call of the anticogging map's C on a Cortex-M4.

Exports the map of a saved model (``canrls export-c --feedforward N``, as a table or as
harmonics), compiles ``canrls_feedforward.c`` with ``arm-none-eabi-gcc -mcpu=cortex-m4
-mthumb -O2`` and prints, per function, the code and table bytes and the instructions
from the disassembly: none has a loop, so a call executes at most that many, and all of
them where there is no branch (docs/tune.md)::

    python tools/bench_feedforward_c.py --model drive.json --points 1024 4096
    python tools/bench_feedforward_c.py --model drive.json --form harmonics
"""

from __future__ import annotations

import argparse
import contextlib
import io
import re
import subprocess
import sys
import tempfile
from pathlib import Path

from canrls.cli.main import main

CC = "arm-none-eabi-gcc"
FLAGS = ["-std=c99", "-O2", "-mcpu=cortex-m4", "-mthumb", "-Wall", "-Wextra", "-Werror",
         "-ffunction-sections", "-fdata-sections"]


def sections(obj: Path) -> dict[str, int]:
    """Bytes of each section of an object file (``.text.NAME``, ``.rodata.NAME``)."""
    out = subprocess.run(["arm-none-eabi-size", "-A", str(obj)], capture_output=True,
                         text=True, check=True).stdout
    return {m.group(1): int(m.group(2))
            for m in re.finditer(r"^(\.(?:text|rodata)\S*)\s+(\d+)", out, re.M)}


def functions(obj: Path) -> dict[str, tuple[int, bool]]:
    """Each function's instructions (the literal pool left out) and whether it branches."""
    dis = subprocess.run(["arm-none-eabi-objdump", "-d", str(obj)], capture_output=True,
                         text=True, check=True).stdout
    out: dict[str, tuple[int, bool]] = {}
    for name, body in re.findall(r"^[0-9a-f]+ <(\w+)>:\n((?:\s+[0-9a-f]+:.*\n?)*)", dis,
                                 re.M):
        ins = [ln for ln in body.splitlines() if ln.strip() and ".word" not in ln]
        branch = any(re.search(r"\s(b|beq|bne|bcc|bcs|bhi|bls|bge|blt|bgt|ble|cbz|cbnz)"
                               r"(\.n|\.w)?\s", ln) for ln in ins)
        out[name] = (len(ins), branch)
    return out


def measure(model: str, points: int, form: str, tmp: Path) -> list[str]:
    """One row per exported function: code, its table, instructions, branch."""
    out = tmp / f"c{points}{form}"
    with contextlib.redirect_stdout(io.StringIO()):
        rc = main(["export-c", "--model", model, "--out", str(out), "--kernel-only",
                   "--feedforward", str(points), "--feedforward-form", form])
    if rc != 0:
        raise SystemExit(f"export-c failed ({rc})")
    obj = out / "ff.o"
    subprocess.run([CC, *FLAGS, "-c", str(out / "canrls_feedforward.c"), "-o", str(obj)],
                   check=True)
    size = sections(obj)
    rows = []
    tables = {"canrls_ff_map_q": ("canrls_ff_table",), "canrls_ff_harmonics_q":
              ("canrls_ff_sine",), "canrls_ff_friction_q": ("canrls_ff_tanh", "canrls_ff_exp")}
    for name, (n, branch) in functions(obj).items():
        if name not in tables:
            continue  # inlined helpers are counted in their callers
        code = size.get(f".text.{name}", 0)
        table = sum(size.get(f".rodata.{t}", 0) for t in tables[name])
        rows.append(f"{points:7d} {name:22} {code:7d} {table:8d} {n:12d} "
                    f"{'yes' if branch else 'no':>6}")
    return rows


def run(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--model", required=True)
    ap.add_argument("--points", type=int, nargs="+", default=[1024])
    ap.add_argument("--form", choices=("table", "harmonics"), default="table")
    args = ap.parse_args(argv)
    print(f"{'points':>7} {'function':22} {'code B':>7} {'table B':>8} {'instructions':>12} "
          f"{'branch':>6}")
    with tempfile.TemporaryDirectory() as d:
        for n in args.points:
            print("\n".join(measure(args.model, n, args.form, Path(d))))
    return 0


if __name__ == "__main__":
    sys.exit(run())
