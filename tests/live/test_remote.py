"""Across processes: simulated drive -> daemon -> parameter frames -> monitor.

Three processes share one bus through python-can-remote, bound to 127.0.0.1 only: a
``RemoteServer`` hosting the simulated drive (interface ``canrls-sim``), ``canrls run
-i remote`` and ``canrls monitor -i remote``.
"""

from __future__ import annotations

import json
import subprocess
import sys
import time
from pathlib import Path

import pytest
from daemon_tool import daemon_process, remote_sim_server

pytest.importorskip("can_remote")


@pytest.fixture
def remote_server(tmp_path: Path):
    with remote_sim_server(tmp_path, "remote-test") as url:
        yield url


@pytest.mark.slow
def test_sim_daemon_monitor_across_processes(remote_server: str, tmp_path: Path) -> None:
    assert remote_server.startswith("ws://127.0.0.1:")
    with daemon_process(["run", "-i", "remote", "-c", remote_server, "--kt", "0.1",
                         "--publish-interval", "0.05", "--duration", "60", "--json",
                         "--commands"], tmp_path) as d:
        # the drive runs in real time: a view each time until the estimates have settled
        # (Coulomb's Tc, the slowest, within its bound) or 60 s have passed
        end = time.monotonic() + 60
        while True:
            mon = subprocess.run(
                [sys.executable, "-m", "canrls", "monitor", "-i", "remote", "-c",
                 remote_server, "--kt", "0.1", "--once", "--json", "--timeout", "60"],
                capture_output=True, text=True, timeout=120)
            assert mon.returncode == 0, mon.stderr
            view = json.loads(mon.stdout)
            tc = view["parameters"].get("coulomb.Tc", {}).get("float")
            if tc == pytest.approx(0.02, rel=0.2) or time.monotonic() > end:
                break
        cmd = subprocess.run(
            [sys.executable, "-m", "canrls", "monitor", "-i", "remote", "-c", remote_server,
             "--command", "freeze", "--timeout", "30"],
            capture_output=True, text=True, timeout=120)
        assert cmd.returncode == 0 and cmd.stdout.strip() == "freeze: ok", cmd.stderr
        out, err = d.stop()
    assert d.proc.returncode == 0, err
    assert set(view["parameters"]) == {"inertia.J", "viscous.B", "coulomb.Tc"}
    tc = view["parameters"]["coulomb.Tc"]
    assert tc["unit"] == "N·m" and tc["float"] == pytest.approx(0.02, rel=0.2)
    assert view["update_count"] > 0 and view["rates"]["feedback"] > 100
    assert view["effects"] == ["inertia", "viscous", "coulomb"]
    final = json.loads(out)
    assert final["daemon"]["commands"] == 1 and final["daemon"]["frames"] > 1000
    assert final["status"]["flags"].count("frozen") == 1
