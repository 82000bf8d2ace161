"""The tests' shared helpers are used: no test file starts ``canrls run`` in a process of
its own but through ``daemon_tool.daemon_process`` (start, readiness, signals, stop and
clean-up in one place; before, four test files each copied them)."""

from __future__ import annotations

import ast
from pathlib import Path

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
