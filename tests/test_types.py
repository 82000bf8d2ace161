"""The package's type hints hold: mypy finds no error in it, and the stubs of the C
extensions (``src/canrls/_*.pyi``) name what the extensions hold; ruff finds nothing in
the package, the tests and the tools.

They run where mypy and ruff are installed (``make test`` installs both with the ``test``
extra) and are skipped elsewhere. mypy takes its settings from ``[tool.mypy]`` in pyproject.toml and
keeps its cache in ``build/mypy``: a run after a change re-checks only what it touches.
"""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
EXTENSIONS = ("_can", "_candump", "_fixed", "_fixedspec", "_kernels", "_rx", "_sim",
              "_target")

def _run(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", *args], cwd=ROOT, capture_output=True,
                          text=True, timeout=600)


def test_mypy_finds_no_error() -> None:
    pytest.importorskip("mypy")
    r = _run("mypy")
    assert r.returncode == 0, r.stdout + r.stderr
    assert r.stdout.startswith("Success: no issues found"), r.stdout


def test_ruff_finds_nothing() -> None:
    # the rules and the line length of [tool.ruff] in pyproject.toml
    pytest.importorskip("ruff")
    r = _run("ruff", "check", "--no-cache", "src", "tests", "tools")
    assert r.returncode == 0, r.stdout + r.stderr


def test_stubs_match_the_extensions() -> None:
    pytest.importorskip("mypy")
    r = _run("mypy.stubtest", "--mypy-config-file", "pyproject.toml",
             *(f"canrls.{m}" for m in EXTENSIONS))
    assert r.returncode == 0, r.stdout + r.stderr


def test_every_extension_has_a_stub() -> None:
    built = set(re.findall(r'Extension\("canrls\.(\w+)"', (ROOT / "setup.py").read_text()))
    stubs = {p.stem for p in (ROOT / "src" / "canrls").glob("_*.pyi")}
    assert built == set(EXTENSIONS) == stubs
