"""Tools the tests need from Debian's packages (cross-compilers, QEMU).

:func:`need_tool` installs a missing tool with ``apt-get`` when the tests run as root
(as CI does on a fresh machine), otherwise the test that needs it skips. ``make test``
runs the tests in two processes (pytest-xdist): a lock on this file around every ``apt-get``
lets one process install at a time (dpkg's lock would fail the other's), and a tool the
other process installed meanwhile is found, not installed again.
"""

from __future__ import annotations

import fcntl
import os
import shutil
import subprocess
from pathlib import Path

import pytest

__all__ = ["need_tool"]

_apt_updated = False
#: the file the test processes lock around apt-get: this module's own (it exists wherever
#: the tests run, and a lock leaves no file behind)
_APT_LOCK = Path(__file__)


def need_tool(tool: str, packages: list[str]) -> str:
    """Path of ``tool``; installed from Debian when missing and root, else skip."""
    global _apt_updated
    path = shutil.which(tool)
    if path is None and hasattr(os, "geteuid") and os.geteuid() == 0 \
            and shutil.which("apt-get"):
        env = {**os.environ, "DEBIAN_FRONTEND": "noninteractive"}
        # dpkg's own lock held by anything else (an unattended upgrade): wait for it
        wait = ["-o", "DPkg::Lock::Timeout=600"]
        with open(_APT_LOCK, "rb") as lock:
            fcntl.flock(lock, fcntl.LOCK_EX)
            try:
                path = shutil.which(tool)  # installed by the other process meanwhile
                if path is None:
                    if not _apt_updated:
                        subprocess.run(["apt-get", *wait, "update", "-qq"], env=env,
                                       capture_output=True, timeout=600)
                        _apt_updated = True
                    subprocess.run(["apt-get", *wait, "install", "-y", "-qq", *packages],
                                   env=env, capture_output=True, timeout=1200)
                    path = shutil.which(tool)
            finally:
                fcntl.flock(lock, fcntl.LOCK_UN)
    if path is None:
        pytest.skip(f"{tool} is missing and could not be installed (Debian: "
                    f"{' '.join(packages)})")
    return path
