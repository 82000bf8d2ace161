"""What the CLI tests share: run ``canrls`` in-process and expect one clear error."""

from __future__ import annotations

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
