"""A read-only installation: every command starts, ``fit`` and ``diagnose`` run.

We run as root, who writes through any mode bits, and a read-only bind mount needs
privileges the tests do not take; so the installation is made unwritable the way that
binds root too: the package is copied into ``tmp_path`` with a regular FILE named
``__pycache__`` in each of its directories (nothing can be made there: ENOTDIR), HOME
and XDG_CACHE_HOME lie under a regular file, ``NUMBA_CACHE_DIR`` is unset and Python
writes no bytecode. Everything stays inside ``tmp_path`` (TMPDIR too).
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from canrls.cli.main import SUBCOMMANDS

SRC = Path(__file__).resolve().parent.parent / "src" / "canrls"


def _files(root: Path) -> dict[Path, int]:
    return {p: p.stat().st_mtime_ns for p in root.rglob("*") if p.is_file()}


@pytest.fixture(scope="module")
def install(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, dict[str, str]]:
    root = tmp_path_factory.mktemp("readonly")
    site = root / "site"
    shutil.copytree(SRC, site / "canrls",
                    ignore=shutil.ignore_patterns("__pycache__", "*.pyc", "*.c", "*.h"))
    for d in [site / "canrls", *(p for p in (site / "canrls").rglob("*") if p.is_dir())]:
        (d / "__pycache__").write_text("a file: no bytecode or numba cache can go here")
    blocker = root / "blocker"
    blocker.write_text("a regular file: nothing can be made under it, even by root")
    tmp = root / "tmp"
    tmp.mkdir()
    env = {k: v for k, v in os.environ.items()
           if k not in ("NUMBA_CACHE_DIR", "PYTHONPATH", "XDG_CACHE_HOME")}
    env.update(HOME=str(blocker / "home"), XDG_CACHE_HOME=str(blocker / "cache"),
               PYTHONPATH=str(site), PYTHONDONTWRITEBYTECODE="1", TMPDIR=str(tmp))
    return site, env


def _canrls(install: tuple[Path, dict[str, str]], *args: str, cwd: Path
            ) -> subprocess.CompletedProcess[str]:
    site, env = install
    return subprocess.run([sys.executable, "-m", "canrls", *args], cwd=cwd, env=env,
                          capture_output=True, text=True, timeout=600)


def test_the_copy_is_imported_and_blocked(install: tuple[Path, dict[str, str]],
                                          tmp_path: Path) -> None:
    site, env = install
    out = subprocess.run([sys.executable, "-c", "import canrls; print(canrls.__file__)"],
                         cwd=tmp_path, env=env, capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert Path(out.stdout.strip()).is_relative_to(site)
    with pytest.raises(OSError):
        (site / "canrls" / "__pycache__" / "x").mkdir(parents=True)
    with pytest.raises(OSError):
        Path(env["HOME"], ".cache").mkdir(parents=True)


def test_every_command_starts(install: tuple[Path, dict[str, str]], tmp_path: Path) -> None:
    site, _ = install
    before = _files(site)
    out = _canrls(install, "--version", cwd=tmp_path)
    assert out.returncode == 0 and out.stdout.startswith("canrls "), out.stderr
    for name in SUBCOMMANDS:
        out = _canrls(install, name.replace("_", "-"),
                      "--help", cwd=tmp_path)
        assert out.returncode == 0, f"{name} --help: {out.stderr}"
        assert "usage: canrls" in out.stdout
        assert "error" not in out.stderr.lower(), out.stderr
    assert _files(site) == before


def test_sim_fit_and_diagnose_run(install: tuple[Path, dict[str, str]],
                                  tmp_path: Path) -> None:
    site, env = install
    before = _files(site)
    log = tmp_path / "drive.log"
    out = _canrls(install, "sim", "--out", str(log), "--duration", "8", "--seed", "2",
                  cwd=tmp_path)
    assert out.returncode == 0, out.stderr
    out = _canrls(install, "fit", "--kt", "0.1", "--json", "--quiet", str(log), cwd=tmp_path)
    assert out.returncode == 0, out.stderr
    assert '"parameters"' in out.stdout
    out = _canrls(install, "diagnose", "--kt", "0.1", "--max-order", "8", "--quiet", str(log),
                  cwd=tmp_path)
    assert out.returncode == 0, out.stderr
    assert "cannot cache" not in out.stderr
    assert _files(site) == before  # nothing written into the installation
    assert not list(Path(env["TMPDIR"]).iterdir())  # the temporary cache is removed at exit
