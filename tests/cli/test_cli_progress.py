"""The progress bar of long replays: tqdm on stderr, silent with --quiet or without a
terminal."""

from __future__ import annotations

import pytest

from canrls.cli._common import Progress
from canrls.cli.main import build_parser


def test_the_bar_draws_on_stderr_and_closes_at_the_end(capsys: pytest.CaptureFixture[str]
                                                       ) -> None:
    p = Progress("replay", enabled=True)
    assert p.callback is p
    for done in (0, 4096, 65536, 1 << 20):
        p(done, 1 << 20)
    err = capsys.readouterr()
    assert err.out == ""
    assert "replay" in err.err and "100%" in err.err and "1.00M/1.00M" in err.err
    p(512, 1024)  # a second pass starts a new bar
    p.close()
    assert "replay" in capsys.readouterr().err


def test_quiet_or_no_terminal_means_no_bar(capsys: pytest.CaptureFixture[str]) -> None:
    assert Progress("replay", quiet=True).callback is None
    assert Progress("replay").callback is None  # pytest's stderr is not a terminal
    off = Progress("replay", enabled=False)
    off(10, 100)
    assert capsys.readouterr().err == ""


@pytest.mark.parametrize("command", ["fit", "diagnose", "fixed-sweep"])
def test_long_replays_take_quiet(command: str) -> None:
    parser = build_parser()
    args = parser.parse_args([command, "x.log", "--quiet"])
    assert args.quiet is True
    assert parser.parse_args([command, "x.log"]).quiet is False
