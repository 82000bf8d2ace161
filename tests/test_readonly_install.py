"""A read-only installation and a read-only home: every command starts, ``fit`` and
``diagnose`` run, the daemon runs, and nothing is written into either.

We run as root, who writes through any mode bits, and a read-only bind mount needs
privileges the tests do not take; so the installation is made unwritable the way that
binds root too: the package is copied into ``tmp_path`` with a regular FILE named
``__pycache__`` in each of its directories (nothing can be made there: ENOTDIR), HOME
and XDG_CACHE_HOME lie under a regular file and Python writes no bytecode. Everything
stays inside ``tmp_path`` (TMPDIR too). The home is also made read-only by its mode
bits (skipped as root) and by a read-only mount of its own (where ``unshare`` may make
one), for the daemon as systemd's ``ProtectSystem=strict`` runs it.
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
        (d / "__pycache__").write_text("a file: no bytecode can go here")
    blocker = root / "blocker"
    blocker.write_text("a regular file: nothing can be made under it, even by root")
    tmp = root / "tmp"
    tmp.mkdir()
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "XDG_CACHE_HOME")}
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
    assert _files(site) == before  # nothing written into the installation
    assert not list(Path(env["TMPDIR"]).iterdir())  # the diagnosis's spill files removed


def test_commands_write_nothing_into_the_home(tmp_path: Path) -> None:
    """Importing canrls and running commands makes no directory in the user's home or
    cache directory (canrls keeps no cache: its kernels are compiled at installation)."""
    env = {**os.environ, "HOME": str(tmp_path / "home"),
           "XDG_CACHE_HOME": str(tmp_path / "xdg"), "PYTHONPATH": str(SRC.parent)}
    log = tmp_path / "work" / "drive.log"
    log.parent.mkdir()
    for args in (["--version"], ["fit", "--help"],
                 ["sim", "--out", str(log), "--duration", "4", "--seed", "1"],
                 ["fit", "--kt", "0.1", "--quiet", str(log)]):
        out = subprocess.run([sys.executable, "-m", "canrls", *args], cwd=log.parent, env=env,
                             capture_output=True, text=True, timeout=300)
        assert out.returncode == 0, f"{args}: {out.stderr}"
    assert not (tmp_path / "home").exists() and not (tmp_path / "xdg").exists()


def _blocked_home(tmp_path: Path, how: str) -> tuple[Path, list[str]]:
    """A home directory nothing can be written under, and the prefix of a command that
    sees it so (a read-only mount needs a mount namespace of its own)."""
    home = tmp_path / "home"
    if how == "read-only":
        home.mkdir()
        home.chmod(0o555)
        if os.access(home, os.W_OK):
            home.chmod(0o755)
            pytest.skip("this user (root) writes into read-only directories")
        return home, []
    if how == "not-a-directory":
        home.write_text("a file, not a directory")  # nothing can be made under it, even by root
        return home, []
    home.mkdir()
    (home / "cache").mkdir()
    unshare = shutil.which("unshare")
    if unshare is None:
        pytest.skip("no unshare(1) for a read-only mount")
    prefix = [unshare, "-m", "sh", "-c", READ_ONLY_MOUNT, "sh"]
    probe = subprocess.run([*prefix, "touch", str(home / "cache" / "probe")],
                           env={**os.environ, "RO": str(home)}, capture_output=True, text=True)
    if "Read-only file system" not in probe.stderr:
        pytest.skip(f"cannot make a read-only mount here: {probe.stderr.strip()}")
    return home, prefix


#: runs a command with the directory $RO mounted read-only (a mount namespace of its own)
READ_ONLY_MOUNT = 'mount --bind "$RO" "$RO" && mount -o remount,bind,ro "$RO" && exec "$@"'


@pytest.mark.parametrize("how", ["read-only", "not-a-directory", "read-only mount"])
def test_the_daemon_starts_with_a_read_only_home(tmp_path: Path, how: str) -> None:
    """``canrls run`` (a virtual bus, two seconds), ``canrls --version`` and ``canrls fit
    --help`` with HOME and XDG_CACHE_HOME where nothing can be written: all start and
    write nothing there (what ``ProtectSystem=strict`` without a cache directory gives).
    As root, permissions do not stop writes: a read-only mount does."""
    home, prefix = _blocked_home(tmp_path, how)
    env = {**os.environ, "HOME": str(home), "XDG_CACHE_HOME": str(home / "cache"),
           "PYTHONPATH": str(SRC.parent), "PYTHONDONTWRITEBYTECODE": "1", "RO": str(home)}
    before = _files(tmp_path)
    try:
        run = subprocess.run([*prefix, sys.executable, "-m", "canrls", "run", "-i", "virtual",
                              "-c", f"canrls-ro-{os.getpid()}-{how}", "--duration", "2",
                              "--json"], env=env, capture_output=True, text=True, timeout=300)
        assert run.returncode == 0, run.stderr
        assert '"frames"' in run.stdout
        for cmd in (["--version"], ["fit", "--help"]):
            r = subprocess.run([*prefix, sys.executable, "-m", "canrls", *cmd], env=env,
                               capture_output=True, text=True, timeout=300)
            assert r.returncode == 0, r.stderr
        assert _files(tmp_path) == before
    finally:
        if home.is_dir():
            home.chmod(0o755)
