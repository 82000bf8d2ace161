"""Tools the tests need from Debian's packages (cross-compilers, QEMU).

:func:`need_tool` installs a missing tool with ``apt-get`` when the tests run as root
(as CI does on a fresh machine), otherwise the test that needs it skips.
"""

from __future__ import annotations

import os
import shutil
import subprocess

import pytest

__all__ = ["need_tool"]

_apt_updated = False


def need_tool(tool: str, packages: list[str]) -> str:
    """Path of ``tool``; installed from Debian when missing and root, else skip."""
    global _apt_updated
    path = shutil.which(tool)
    if path is None and hasattr(os, "geteuid") and os.geteuid() == 0 \
            and shutil.which("apt-get"):
        env = {**os.environ, "DEBIAN_FRONTEND": "noninteractive"}
        if not _apt_updated:
            subprocess.run(["apt-get", "update", "-qq"], env=env, capture_output=True,
                           timeout=600)
            _apt_updated = True
        subprocess.run(["apt-get", "install", "-y", "-qq", *packages], env=env,
                       capture_output=True, timeout=1200)
        path = shutil.which(tool)
    if path is None:
        pytest.skip(f"{tool} is missing and could not be installed (Debian: "
                    f"{' '.join(packages)})")
    return path
