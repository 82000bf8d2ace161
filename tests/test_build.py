"""The build of the C extensions (setup.py): without a compiler it stops with one
``error:`` line naming what to install, and clang builds them (no GCC-only flag) to the
same results as GCC.

Each build runs ``setup.py build_ext`` on a copy of the sources in ``tmp_path`` (the
metadata, the C), so nothing is written into the repository.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from conftest import ROOT

SRC = ROOT / "src" / "canrls"


def _setuptools_reads_pyproject() -> bool:
    """pyproject.toml's ``license = "MIT"`` needs setuptools >= 77 (pip's isolated build
    has it; a venv may carry an older one)."""
    import setuptools

    return int(setuptools.__version__.split(".")[0]) >= 77


pytestmark = pytest.mark.skipif(not _setuptools_reads_pyproject(),
                                reason="setup.py build_ext needs setuptools >= 77 here "
                                       "(pip install 'setuptools>=77')")


def _build(tmp: Path, cc: str) -> subprocess.CompletedProcess[str]:
    """``setup.py build_ext`` with ``CC=cc`` in a copy of the tree under ``tmp``; the
    modules land in ``tmp/lib/canrls``."""
    tree = tmp / "tree"
    for name in ("setup.py", "pyproject.toml", "README.md", "LICENSE"):
        (tree / name).parent.mkdir(parents=True, exist_ok=True)
        shutil.copy2(ROOT / name, tree / name)
    shutil.copytree(SRC / "c", tree / "src" / "canrls" / "c")
    env = {**os.environ, "CC": cc}
    return subprocess.run([sys.executable, "setup.py", "build_ext", "--build-lib",
                           str(tmp / "lib"), "--build-temp", str(tmp / "obj")],
                          cwd=tree, env=env, capture_output=True, text=True, timeout=300,
                          check=False)


def test_no_compiler_says_what_to_install(tmp_path: Path) -> None:
    cc = tmp_path / "no-such-cc"
    r = _build(tmp_path, str(cc))
    lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert r.returncode == 1, r.stderr
    assert "Traceback" not in r.stderr
    assert lines[-1] == (f"error: canrls builds C extensions and needs a C compiler: "
                         f"'{cc}' was not found; install one (Debian/Ubuntu: apt-get "
                         f"install build-essential; or clang) or name it in CC"), r.stderr
    assert not list(tmp_path.rglob("*.so"))


@pytest.mark.skipif(shutil.which("clang") is None,
                    reason="clang is not installed (Debian: apt-get install clang)")
def test_clang_builds_the_same_results(tmp_path: Path) -> None:
    """clang builds every extension (GCC's -fvect-cost-model left out), and ``canrls fit``
    with them prints the parameters GCC's build prints, to the bit."""
    r = _build(tmp_path, "clang")
    assert r.returncode == 0, r.stderr[-3000:]
    assert "-fvect-cost-model" not in r.stdout + r.stderr
    site = tmp_path / "site"
    shutil.copytree(SRC, site / "canrls",
                    ignore=shutil.ignore_patterns("__pycache__", "*.so", "c"))
    built = sorted((tmp_path / "lib" / "canrls").glob("*.so"))
    assert {p.name.split(".")[0] for p in built} == {
        "_kernels", "_can", "_candump", "_rx", "_fixed", "_target", "_fixedspec",
        "_sim"}
    for so in built:
        shutil.copy2(so, site / "canrls" / so.name)

    log = tmp_path / "drive.log"
    cli = [sys.executable, "-m", "canrls"]
    subprocess.run([*cli, "sim", "--out", str(log), "--duration", "6", "--seed", "1",
                    "--effects", "inertia,viscous,coulomb,offset,cogging:6"],
                   check=True, capture_output=True, timeout=120)
    fit = [*cli, "fit", str(log), "--kt", "0.1", "--effects",
           "inertia,viscous,coulomb,offset", "--json"]

    def params(pythonpath: str | None) -> dict[str, object]:
        env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
        if pythonpath:
            env["PYTHONPATH"] = pythonpath
        out = subprocess.run(fit, env=env, check=True, capture_output=True, text=True,
                             timeout=120, cwd=tmp_path).stdout
        return dict(json.loads(out)["parameters"])

    probe = subprocess.run([sys.executable, "-c", "import canrls._kernels as k; print(k.__file__)"],
                           env={**os.environ, "PYTHONPATH": str(site)}, check=True,
                           capture_output=True, text=True, cwd=tmp_path).stdout
    assert Path(probe.strip()).parent == site / "canrls"
    assert params(str(site)) == params(None)
