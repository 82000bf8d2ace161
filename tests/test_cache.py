"""numba's cache of compiled kernels lives in the user's cache directory, never in the package."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

import canrls
from canrls.errors import ConfigError
from canrls.live.cache import configured_cache_dir, preload
from canrls.live.settings import DaemonSettings

ROOT = Path(__file__).resolve().parent.parent
SRC = ROOT / "src"

#: compiles one small kernel (cache=True) and prints where numba caches it (a kernel of
#: the simulated drive, which stays in numba; the estimation's kernels are C)
COMPILE = """
import numba
from canrls.sim.plant import _quantise
_quantise(1.0, 0.1)
print(numba.config.CACHE_DIR)
"""


def _files(root: Path) -> set[Path]:
    return {p for p in root.rglob("*") if p.is_file()}


def _blocked_home(tmp_path: Path, how: str) -> Path:
    """A home directory nothing can be written under (as far as this user goes)."""
    home = tmp_path / "home"
    if how == "read-only":
        home.mkdir()
        home.chmod(0o555)
        if os.access(home, os.W_OK):
            home.chmod(0o755)
            pytest.skip("this user (root) writes into read-only directories")
        return home
    home.write_text("a file, not a directory")  # nothing can be made under it, even by root
    return home


def _env(home: Path, pythonpath: Path) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if k != "NUMBA_CACHE_DIR"}
    env.update(HOME=str(home), XDG_CACHE_HOME=str(home / "cache"), PYTHONPATH=str(pythonpath),
               PYTHONDONTWRITEBYTECODE="1")
    return env


def test_the_cache_is_in_the_users_cache_directory_not_in_the_package() -> None:
    import numba

    d = Path(numba.config.CACHE_DIR)
    assert numba.config.CACHE_DIR and d.is_absolute()
    assert not d.resolve().is_relative_to(SRC.resolve())
    assert not d.resolve().is_relative_to(Path(canrls.__file__).resolve().parent)


def test_xdg_cache_home_and_a_user_setting(tmp_path: Path) -> None:
    env = {k: v for k, v in os.environ.items() if k != "NUMBA_CACHE_DIR"}
    env.update(XDG_CACHE_HOME=str(tmp_path / "xdg"), PYTHONPATH=str(SRC))
    show = [sys.executable, "-c",
            "import canrls, numba, os; print(os.environ['NUMBA_CACHE_DIR'])"]
    out = subprocess.run(show, env=env, capture_output=True, text=True, check=True).stdout
    assert Path(out.strip()) == tmp_path / "xdg" / "canrls" / "numba"
    assert (tmp_path / "xdg" / "canrls" / "numba").is_dir()
    env["NUMBA_CACHE_DIR"] = str(tmp_path / "mine")  # the user's choice stays
    out = subprocess.run(show, env=env, capture_output=True, text=True, check=True).stdout
    assert Path(out.strip()) == tmp_path / "mine"


@pytest.mark.parametrize("how", ["read-only", "not-a-directory"])
def test_every_command_starts_on_a_read_only_installation(tmp_path: Path, how: str) -> None:
    home = _blocked_home(tmp_path, how)
    inst = tmp_path / "site-packages"
    shutil.copytree(SRC / "canrls", inst / "canrls",
                    ignore=shutil.ignore_patterns("__pycache__"))
    for p in [inst, *inst.rglob("*")]:
        p.chmod(0o555 if p.is_dir() else 0o444)
    before, src_before = _files(inst), _files(SRC)
    try:
        env = _env(home, inst)
        v = subprocess.run([sys.executable, "-m", "canrls", "--version"], env=env,
                           capture_output=True, text=True, timeout=120)
        assert v.returncode == 0, v.stderr
        assert v.stdout.strip() == f"canrls {canrls.__version__}"
        c = subprocess.run([sys.executable, "-c", COMPILE], env=env, capture_output=True,
                           text=True, timeout=300)
        assert c.returncode == 0, c.stderr
        used = Path(c.stdout.strip())
        # the fallback: a temporary directory of its own, removed at exit
        assert used.name.startswith("canrls-numba-") and not used.exists()
        assert not used.is_relative_to(home) and not used.is_relative_to(inst)
        assert _files(inst) == before
        # the same from the source tree: no kernel file appears under src/
        c = subprocess.run([sys.executable, "-c", COMPILE], env=_env(home, SRC),
                           capture_output=True, text=True, timeout=300)
        assert c.returncode == 0, c.stderr
        assert not {p for p in _files(SRC) - src_before if p.suffix in (".nbi", ".nbc")}
    finally:
        for p in [inst, *inst.rglob("*")]:
            p.chmod(0o755 if p.is_dir() else 0o644)
        if home.is_dir():
            home.chmod(0o755)


def test_daemon_cache_dir_is_read_before_the_kernels_load(tmp_path: Path) -> None:
    conf = tmp_path / "etc" / "canrls.toml"
    conf.parent.mkdir()
    conf.write_text('[daemon]\ncache_dir = "kernels"\n')
    assert configured_cache_dir(conf) == tmp_path / "etc" / "kernels"
    assert DaemonSettings.from_table({"cache_dir": "kernels"}, str(conf),
                                     conf.parent).cache_dir == tmp_path / "etc" / "kernels"
    with pytest.raises(ConfigError, match="directory path"):
        DaemonSettings.from_table({"cache_dir": 3}, str(conf))
    assert configured_cache_dir(tmp_path / "none.toml") is None
    assert preload(["run", "-i", "virtual"]) is None
    # a whole command: the kernels it compiles are cached where the file says
    env = {k: v for k, v in os.environ.items() if k != "NUMBA_CACHE_DIR"}
    env.update(PYTHONPATH=str(SRC), PYTHONDONTWRITEBYTECODE="1")
    code = ("import sys, numba\nfrom canrls.cli.main import main\n"
            "try:\n    main(sys.argv[1:])\nexcept SystemExit:\n    pass\n"
            f"{COMPILE}")
    r = subprocess.run([sys.executable, "-c", code, "fit", "-C", str(conf), "--help"],
                       env=env, capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    assert Path(r.stdout.strip().splitlines()[-1]) == tmp_path / "etc" / "kernels"
    assert any(p.suffix == ".nbi" for p in _files(tmp_path / "etc" / "kernels"))


def test_importing_canrls_makes_no_cache_directory(tmp_path: Path) -> None:
    """The directory is chosen (and made) when numba loads, not when canrls does: a
    process that never imports numba (the daemon) touches no cache directory."""
    env = {k: v for k, v in os.environ.items() if k != "NUMBA_CACHE_DIR"}
    env.update(XDG_CACHE_HOME=str(tmp_path / "xdg"), PYTHONPATH=str(SRC))
    code = ("import os, canrls, canrls.can.pairing, canrls.live.cache\n"
            "print(os.environ.get('NUMBA_CACHE_DIR', ''))")
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True,
                         text=True, check=True).stdout
    assert out.strip() == ""
    assert not (tmp_path / "xdg").exists()


#: runs a command with the directory $RO mounted read-only (a mount namespace of its own)
READ_ONLY_MOUNT = 'mount --bind "$RO" "$RO" && mount -o remount,bind,ro "$RO" && exec "$@"'


def _read_only_mount(home: Path) -> list[str]:
    """The prefix that runs a command with ``home`` on a read-only mount (skips the test
    where this machine cannot make one)."""
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
    return prefix


@pytest.mark.parametrize("how", ["read-only", "not-a-directory", "read-only mount"])
def test_the_daemon_starts_with_read_only_cache_and_home(tmp_path: Path, how: str) -> None:
    """``canrls run`` (a virtual bus, two seconds), ``canrls --version`` and ``canrls fit
    --help`` with HOME and XDG_CACHE_HOME where nothing can be written: all start and
    write nothing there (what ``ProtectSystem=strict`` without a cache directory gives).
    As root, permissions do not stop writes: a read-only mount does."""
    if how == "read-only mount":
        home = tmp_path / "home"
        prefix = _read_only_mount(home)
    else:
        home, prefix = _blocked_home(tmp_path, how), []
    env = {**_env(home, SRC), "RO": str(home)}
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
