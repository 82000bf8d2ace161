"""What the CLI tests share: run ``canrls`` in-process and expect one clear error; write
any value as inline TOML for the configurations they hand it; start a module as a
process that Ctrl-C stops."""

from __future__ import annotations

import json
import math
import sys
from typing import Any

import pytest

from canrls.cli.main import main


def cli_error(capsys: pytest.CaptureFixture[str], argv: list[str]) -> str:
    """Run the CLI; expect exit status 1, one ``error:`` line and no traceback; return
    the line."""
    capsys.readouterr()
    rc = main(argv)
    err = capsys.readouterr().err
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert rc == 1, err
    assert len(lines) == 1 and lines[0].startswith("error: "), err
    assert "Traceback" not in err
    return lines[0]


def python_module(module: str) -> list[str]:
    """``python -m module`` with Ctrl-C restored: a shell without job control starts
    background jobs with SIGINT ignored (``make test &`` too), and a child inherits
    that."""
    code = ("import runpy, signal, sys; signal.signal(signal.SIGINT, signal.default_int_handler); "
            f"sys.argv[0] = {module!r}; runpy.run_module({module!r}, run_name='__main__', "
            "alter_sys=True)")
    return [sys.executable, "-c", code]


def inline_toml(v: Any) -> str:
    """A value as inline TOML (JSON's strings are TOML basic strings)."""
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        return "nan" if math.isnan(v) else ("inf" if v > 0 else "-inf") if math.isinf(v) \
            else repr(v)
    if isinstance(v, str):
        return json.dumps(v)
    if isinstance(v, list):
        return "[" + ", ".join(inline_toml(x) for x in v) + "]"
    return "{" + ", ".join(f"{json.dumps(k)} = {inline_toml(x)}" for k, x in v.items()) + "}"
