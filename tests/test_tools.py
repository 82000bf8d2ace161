"""tools/: the SocketCAN set-up script and the systemd unit.

This kernel has no CAN support, so ``setup_can.sh`` runs against stand-ins for ``ip``
and ``modprobe`` placed first on PATH: they record their arguments (and answer ``ip
link show`` as the test says), and the test checks the exact commands the script
would give on a real machine. The unit file goes through ``systemd-analyze verify``
where that tool is installed.
"""

from __future__ import annotations

import os
import shutil
import stat
import subprocess
from pathlib import Path

import pytest

TOOLS = Path(__file__).resolve().parent.parent / "tools"
SETUP = TOOLS / "setup_can.sh"
UNIT = TOOLS / "canrls.service"

_STANDIN = """#!/bin/sh
echo "$(basename "$0") $*" >> "{log}"
if [ "$1 $2" = "link show" ] && [ -e "{dir}/exists-$3" ]; then exit 0; fi
if [ "$1 $2" = "link show" ]; then exit 1; fi
exit 0
"""


def _run(tmp_path: Path, *args: str, existing: tuple[str, ...] = ()
         ) -> tuple[int, list[str], str]:
    """Run setup_can.sh with ``args``; (exit code, commands run, stderr)."""
    bin_dir = tmp_path / "bin"
    bin_dir.mkdir(exist_ok=True)
    log = tmp_path / "commands.log"
    log.write_text("")
    for name in ("ip", "modprobe"):
        p = bin_dir / name
        p.write_text(_STANDIN.format(log=log, dir=tmp_path))
        p.chmod(p.stat().st_mode | stat.S_IXUSR)
    for iface in existing:
        (tmp_path / f"exists-{iface}").touch()
    env = {**os.environ, "PATH": f"{bin_dir}{os.pathsep}{os.environ.get('PATH', '')}"}
    r = subprocess.run(["sh", str(SETUP), *args], env=env, capture_output=True, text=True,
                       timeout=30)
    return r.returncode, log.read_text().splitlines(), r.stderr


def test_setup_script_parses() -> None:
    assert subprocess.run(["sh", "-n", str(SETUP)], capture_output=True).returncode == 0


def test_setup_real_controller_with_bitrate_restart_and_error_reporting(tmp_path: Path
                                                                         ) -> None:
    rc, cmds, _ = _run(tmp_path, "can0", "500000", "200")
    assert rc == 0
    assert cmds == [
        "ip link set can0 down",
        "ip link set can0 type can bitrate 500000 restart-ms 200 berr-reporting on",
        "ip link set can0 txqueuelen 1000",
        "ip link set can0 up",
        "ip -details link show can0",
    ]
    rc, cmds, _ = _run(tmp_path, "can1")  # defaults: 1 Mbit/s, restart after 100 ms
    assert rc == 0 and cmds[1] == ("ip link set can1 type can bitrate 1000000 restart-ms 100 "
                                   "berr-reporting on")


def test_setup_virtual_interface_created_once(tmp_path: Path) -> None:
    rc, cmds, _ = _run(tmp_path, "vcan0")
    assert rc == 0
    assert cmds == ["modprobe vcan", "ip link show vcan0", "ip link add dev vcan0 type vcan",
                    "ip link set vcan0 up", "ip -details link show vcan0"]
    rc, cmds, _ = _run(tmp_path, "vcan0", existing=("vcan0",))
    assert rc == 0 and "ip link add dev vcan0 type vcan" not in cmds


def test_setup_down_and_usage(tmp_path: Path) -> None:
    rc, cmds, _ = _run(tmp_path, "down", "vcan0")
    assert rc == 0 and cmds == ["ip link set vcan0 down", "ip link delete vcan0"]
    rc, cmds, _ = _run(tmp_path, "down", "can0")
    assert rc == 0 and cmds == ["ip link set can0 down"]
    for args in ((), ("down",), ("down", "a", "b")):
        rc, cmds, err = _run(tmp_path, *args)
        assert rc == 2 and cmds == [] and "usage:" in err


@pytest.mark.skipif(shutil.which("systemd-analyze") is None,
                    reason="systemd-analyze is not installed")
def test_systemd_unit_verifies_without_warnings(tmp_path: Path) -> None:
    r = subprocess.run(["systemd-analyze", "verify", str(UNIT)], capture_output=True,
                       text=True, timeout=60, cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    assert r.stderr.strip() == "" and r.stdout.strip() == ""


def test_systemd_unit_is_notify_with_watchdog_and_restart() -> None:
    text = UNIT.read_text()
    lines = {line.split("=", 1)[0]: line.split("=", 1)[1]
             for line in text.splitlines() if "=" in line and not line.startswith("#")}
    assert lines["Type"] == "notify" and lines["Restart"] == "on-failure"
    assert lines["WatchdogSec"].endswith("s") and lines["KillSignal"] == "SIGTERM"
    assert "--log-level" in lines["ExecStart"] and " run " in lines["ExecStart"]
