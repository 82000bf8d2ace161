"""The live path runs without a JIT compiler (issue 14, item 6).

``canrls run`` imports neither numba nor llvmlite: its per-frame work runs in the C
extensions and numpy. The CAN layer (strict decoding, pairing: :mod:`canrls._can`) is
checked on its own, then the whole daemon, started for a moment on a virtual bus.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from canrls import _can

SRC = Path(__file__).resolve().parent.parent / "src"

#: prints, as JSON, whether a JIT compiler is loaded and which loaded canrls modules
#: import one at module level (module:line), after running the code before it
REPORT = """
import json, re, sys
jit = [m for m in ("numba", "llvmlite") if m in sys.modules]
where = []
for name, mod in sorted(sys.modules.items()):
    path = getattr(mod, "__file__", None) or ""
    if name.startswith("canrls") and path.endswith(".py"):
        with open(path, encoding="utf-8") as fh:
            for k, line in enumerate(fh, 1):
                if re.match(r"(import|from)\\s+(numba|llvmlite)\\b", line):
                    where.append(f"{name}:{k}")
print(json.dumps({"jit": jit, "where": where}))
"""

#: the CAN layer of the live path: a python-can frame to a sample
CAN_LAYER = """
import canrls.can.frameblock, canrls.can.protocol, canrls.can.pairing, canrls.can.frames
import canrls.can.period, canrls.live.cache
"""

#: the daemon, as ``canrls run`` starts it, for a moment on a virtual bus
DAEMON = """
import contextlib, io
from canrls.cli.main import main
with contextlib.redirect_stdout(io.StringIO()):
    assert main(["run", "-i", "virtual", "-c", CHANNEL, "--duration", "0.5"]) == 0
"""


def _jit_report(code: str) -> dict[str, list[str]]:
    env = {**os.environ, "PYTHONPATH": str(SRC)}
    r = subprocess.run([sys.executable, "-c", code + REPORT], env=env, capture_output=True,
                       text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    return json.loads(r.stdout.strip().splitlines()[-1])


def test_the_can_layer_imports_no_jit() -> None:
    report = _jit_report(CAN_LAYER)
    assert report == {"jit": [], "where": []}, (
        f"the CAN layer loaded {report['jit']}, imported at {', '.join(report['where'])}")


@pytest.mark.xfail(strict=True, reason="the estimation kernels (canrls.estimation: model, "
                   "svf, selection, float_kernels, fixed, fixed_kernels, pipeline) still "
                   "import numba until the C extension canrls._kernels replaces them")
def test_the_daemon_imports_no_jit() -> None:
    code = f"CHANNEL = 'canrls-jitfree-{os.getpid()}'\n" + DAEMON
    report = _jit_report(code)
    assert report == {"jit": [], "where": []}, (
        f"the daemon loaded {report['jit']}, imported at {', '.join(report['where'])}")


# -- the C module's guard rails: a wrong array is an error, never a stray memory access --


def test_c_module_rejects_wrong_dtypes_and_short_arrays() -> None:
    table = np.zeros((8, 256), np.uint8)
    data = np.zeros((4, 8), np.uint8)
    with pytest.raises(TypeError, match="dtype"):
        _can.crc8(0x100, data.astype(np.int64), 8, 8, table, np.empty(4, np.uint8))
    with pytest.raises(ValueError, match="too small"):
        _can.crc8(0x100, data, 8, 8, table, np.empty(5, np.uint8))
    with pytest.raises(ValueError, match="needs"):
        _can.counters(np.zeros(3, np.int64), np.zeros(2), 16, 7, 0.001,
                      np.zeros(3, np.int64), np.zeros(1), np.empty(3, np.uint8),
                      np.empty(3, np.int64))
    with pytest.raises(IndexError):
        _can.gather_check(data, 8, np.array([4], np.int64), 8, np.zeros(4, np.bool_),
                          np.full(4, 8, np.uint8), True, 0x100, table,
                          np.empty((1, 8), np.uint8), np.empty(1, np.uint8))
    with pytest.raises(ValueError, match="read-only"):
        out = np.empty(4, np.uint8)
        out.flags.writeable = False
        _can.crc8(0x100, data, 8, 8, table, out)
