"""The tests' shared helpers are used: no test file starts ``canrls run`` in a process of
its own but through ``daemon_tool.daemon_process`` (start, readiness, signals, stop and
clean-up in one place; before, four test files each copied them). And they hold when
``make test`` runs the tests in two processes (``debian.need_tool``'s apt-get)."""

from __future__ import annotations

import ast
import subprocess
import threading
import time
from pathlib import Path
from typing import Any

import pytest

TESTS = Path(__file__).resolve().parent


def daemon_popens(tree: ast.Module) -> list[int]:
    """Lines of ``subprocess.Popen([... "canrls", ..., "run", ...])`` in ``tree``."""
    out = []
    for node in ast.walk(tree):
        if (isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute | ast.Name)
                and (getattr(node.func, "attr", None) or getattr(node.func, "id", None))
                == "Popen" and node.args and isinstance(node.args[0], ast.List)):
            words = {e.value for e in node.args[0].elts if isinstance(e, ast.Constant)}
            if {"canrls", "run"} <= words:
                out.append(node.lineno)
    return out


def test_daemons_are_started_through_the_one_helper() -> None:
    bad = [f"{p.relative_to(TESTS)}:{line}" for p in sorted(TESTS.rglob("test_*.py"))
           for line in daemon_popens(ast.parse(p.read_text()))]
    assert not bad, ("start `canrls run` with daemon_tool.daemon_process:\n"
                     + "\n".join(bad))


def test_the_check_sees_a_daemon_started_by_hand() -> None:
    t = ast.parse('subprocess.Popen([sys.executable, "-m", "canrls", "run", "-i", "x"])\n'
                  'subprocess.Popen([sys.executable, "-m", "canrls", "sim"])\n')
    assert daemon_popens(t) == [1]


def test_two_processes_needing_a_tool_run_one_apt_get_at_a_time(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """make test runs two processes: when both miss a tool, one installs it (dpkg's lock
    would fail a second apt-get at once) and the other then finds it installed. Two
    threads stand for the two processes (each opens the lock file: flock holds them
    apart as it holds processes); apt-get is a stand-in that takes 0.2 s."""
    import debian

    installed = threading.Event()
    running: list[int] = []
    calls: list[list[str]] = []
    most = 0

    def apt_get(argv: list[str], **_: Any) -> subprocess.CompletedProcess[str]:
        nonlocal most
        calls.append(argv)
        running.append(1)
        most = max(most, len(running))
        time.sleep(0.2)
        running.pop()
        if "install" in argv:
            installed.set()
        return subprocess.CompletedProcess(argv, 0, "", "")

    def which(name: str) -> str | None:
        return "/usr/bin/apt-get" if name == "apt-get" else (
            "/usr/bin/made-up-tool" if installed.is_set() else None)

    lock = tmp_path / "apt.lock"
    lock.touch()
    monkeypatch.setattr(debian, "_APT_LOCK", lock)
    monkeypatch.setattr(debian, "_apt_updated", False)
    monkeypatch.setattr(debian.os, "geteuid", lambda: 0)
    monkeypatch.setattr(debian.shutil, "which", which)
    monkeypatch.setattr(debian.subprocess, "run", apt_get)
    found: list[str] = []
    threads = [threading.Thread(target=lambda: found.append(
        debian.need_tool("made-up-tool", ["made-up-package"]))) for _ in range(2)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert found == ["/usr/bin/made-up-tool"] * 2
    assert most == 1, "two apt-get at once"
    assert [c for c in calls if "install" in c] == [calls[-1]], calls  # installed once
