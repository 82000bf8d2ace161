"""What a command loads: one kernel language, and nothing a command does not use.

The kernels are C extensions built at installation (``setup.py``): no module of canrls
imports a JIT compiler. ``canrls run`` loads neither the simulator nor the diagnosis (nor,
of one axis or a machine's, the fleet without a ``[history]``), ``canrls fit`` none of
matplotlib, scipy, jinja2 and tqdm (a progress bar loads tqdm when it is drawn), and
``canrls fit --help`` neither numpy nor cantools: what a process does not import costs it
no start-up time (docs/architecture.md, *Start-up*); a command's process runs numpy's
BLAS in one thread unless told otherwise. Each command runs in a fresh interpreter, so
other tests' imports do not count.
"""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

SRC = Path(__file__).resolve().parent.parent / "src"

#: runs the command line in ``ARGV`` with main() and prints, as JSON, the watched
#: packages it loaded (canrls's own by their first two names)
REPORT = """
import contextlib, io, json, sys
from canrls.cli.main import main
with contextlib.redirect_stdout(io.StringIO()):
    try:
        code = main(ARGV)
    except SystemExit as e:  # --help
        code = e.code
assert code == 0, code
WATCH = {"numba", "llvmlite", "numpy", "cantools", "matplotlib", "scipy", "jinja2", "tqdm",
         "canrls.sim", "canrls.diagnosis", "canrls.fleet"}
names = {".".join(m.split(".")[:2]) if m.startswith("canrls.") else m.split(".")[0]
         for m in sys.modules}
print(json.dumps(sorted(names & WATCH)))
"""


def _loaded(argv: list[str], cwd: Path) -> set[str]:
    env = {**os.environ, "PYTHONPATH": str(SRC)}
    r = subprocess.run([sys.executable, "-c", f"ARGV = {argv!r}\n" + REPORT], cwd=cwd,
                       env=env, capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    return set(json.loads(r.stdout.strip().splitlines()[-1]))


def test_no_module_imports_a_jit_compiler() -> None:
    where = [f"{p.relative_to(SRC)}:{k}" for p in sorted(SRC.rglob("*.py"))
             for k, line in enumerate(p.read_text(encoding="utf-8").splitlines(), 1)
             if re.match(r"\s*(import|from)\s+(numba|llvmlite)\b", line)]
    assert not where, f"a JIT compiler is imported at {', '.join(where)}"


def test_the_daemon_loads_neither_the_simulator_nor_the_diagnosis(tmp_path: Path) -> None:
    loaded = _loaded(["run", "-i", "virtual", "-c", f"canrls-startup-{os.getpid()}",
                      "--duration", "0.5"], tmp_path)
    assert loaded == {"numpy", "cantools"}


def test_a_machine_daemon_loads_neither_the_fleet_nor_the_simulator(tmp_path: Path) -> None:
    cfg = tmp_path / "machine.toml"
    cfg.write_text('[model]\nkt = 0.1\n[[axes]]\nname = "a"\n'
                   '[[axes]]\nname = "b"\nids = "offset:0x10"\n')
    loaded = _loaded(["run", "--config", str(cfg), "-i", "virtual", "-c",
                      f"canrls-startup-m-{os.getpid()}", "--duration", "0.2"], tmp_path)
    assert loaded == {"numpy", "cantools"}


@pytest.fixture(scope="module")
def log(tmp_path_factory: pytest.TempPathFactory) -> Path:
    from canrls.cli.main import main

    path = tmp_path_factory.mktemp("startup") / "drive.log"
    assert main(["sim", "--out", str(path), "--duration", "4", "--seed", "1"]) == 0
    return path


def test_fit_loads_no_plotting_templating_or_progress_bar(log: Path) -> None:
    assert _loaded(["fit", str(log), "--kt", "0.1", "--quiet"], log.parent) == {
        "numpy", "cantools"}
    assert "tqdm" not in _loaded(["fit", str(log), "--kt", "0.1"], log.parent)  # no terminal


def test_diagnose_without_a_report_loads_no_plotting_or_templating(log: Path) -> None:
    assert _loaded(["diagnose", str(log), "--kt", "0.1", "--max-order", "4", "--quiet"],
                   log.parent) == {"numpy", "cantools", "canrls.diagnosis"}


@pytest.mark.parametrize("command", ["fit", "validate", "export-c", "monitor", "run", "tune"])
def test_help_loads_neither_numpy_nor_cantools(command: str, tmp_path: Path) -> None:
    assert _loaded([command, "--help"], tmp_path) == set()


#: prints OPENBLAS_NUM_THREADS as main() leaves it, called as the console script or
#: with an argv
BLAS = """
import os, sys
from canrls.cli.main import main
sys.argv = ["canrls", "--version"]
try:
    main(None if HOW == "process" else ["--version"])
except SystemExit:
    pass
print(os.environ.get("OPENBLAS_NUM_THREADS", "unset"))
"""


@pytest.mark.parametrize("how, given, want", [("process", None, "1"),
                                               ("process", "4", "4"),
                                               ("call", None, "unset")])
def test_a_command_process_runs_blas_in_one_thread_unless_told(how: str, given: str | None,
                                                               want: str) -> None:
    env = {k: v for k, v in os.environ.items() if k != "OPENBLAS_NUM_THREADS"}
    env["PYTHONPATH"] = str(SRC)
    if given is not None:
        env["OPENBLAS_NUM_THREADS"] = given
    r = subprocess.run([sys.executable, "-c", f"HOW = {how!r}\n" + BLAS], env=env,
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip().splitlines()[-1] == want
