"""Flash and instructions per call of the anticogging map's C on a Cortex-M4.

Exports the map of a saved model (``canrls export-c --feedforward N``, as a table or as
harmonics), compiles ``canrls_feedforward.c`` with ``arm-none-eabi-gcc -mcpu=cortex-m4
-mthumb -O2`` and prints the code and table bytes and the instructions of the function
from the disassembly: it has no loop and no branch, so a call executes them all
(docs/tune.md)::

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


def measure(model: str, points: int, form: str, tmp: Path) -> tuple[int, int, int, bool]:
    """(code bytes, table bytes, instructions, has a branch) of one map."""
    out = tmp / f"c{points}{form}"
    with contextlib.redirect_stdout(io.StringIO()):
        rc = main(["export-c", "--model", model, "--out", str(out), "--kernel-only",
                   "--feedforward", str(points), "--feedforward-form", form])
    if rc != 0:
        raise SystemExit(f"export-c failed ({rc})")
    obj = out / "ff.o"
    subprocess.run([CC, *FLAGS, "-c", str(out / "canrls_feedforward.c"), "-o", str(obj)],
                   check=True)
    sizes = subprocess.run(["arm-none-eabi-size", "-A", str(obj)], capture_output=True,
                           text=True, check=True).stdout
    code = sum(int(m.group(1)) for m in re.finditer(r"^\.text\S*\s+(\d+)", sizes, re.M))
    table = sum(int(m.group(1)) for m in re.finditer(r"^\.rodata\S*\s+(\d+)", sizes, re.M))
    dis = subprocess.run(["arm-none-eabi-objdump", "-d", str(obj)], capture_output=True,
                         text=True, check=True).stdout
    ins = [ln for ln in dis.splitlines()
           if re.match(r"^\s+[0-9a-f]+:\s", ln) and ".word" not in ln]  # not the pool
    branch = any(re.search(r"\s(b|beq|bne|bcc|bcs|bhi|bls|cbz|cbnz)\s", ln) for ln in ins)
    return code, table, len(ins), branch


def run(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--model", required=True)
    ap.add_argument("--points", type=int, nargs="+", default=[1024])
    ap.add_argument("--form", choices=("table", "harmonics"), default="table")
    args = ap.parse_args(argv)
    print(f"{'points':>7} {'code B':>7} {'table B':>8} {'instructions':>12} {'branch':>6}")
    with tempfile.TemporaryDirectory() as d:
        for n in args.points:
            code, table, ins, br = measure(args.model, n, args.form, Path(d))
            print(f"{n:7d} {code:7d} {table:8d} {ins:12d} {'yes' if br else 'no':>6}")
    return 0


if __name__ == "__main__":
    sys.exit(run())
