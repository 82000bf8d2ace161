"""The pages of docs/ call the command line as the README does: a page that shows a
``canrls`` (or ``python``) command says, before it, how ``canrls`` gets on ``PATH``."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from conftest import ROOT

#: a command line in a fenced block, as on a user's PATH
_COMMAND = re.compile(r"^(?:\$ )?(?:canrls|python) ")
#: what a page says before its first such command (the README's way: the activation)
_ON_PATH = "`source .venv/bin/activate`"
PAGES = sorted((ROOT / "docs").glob("*.md"))


def _first_command(text: str) -> int | None:
    """The offset of the first command line of a fenced block of ``text`` (None: none)."""
    inside = False
    offset = 0
    for line in text.splitlines(keepends=True):
        if line.startswith("```"):
            inside = not inside
        elif inside and _COMMAND.match(line):
            return offset
        offset += len(line)
    return None


@pytest.mark.parametrize("page", PAGES, ids=[p.name for p in PAGES])
def test_a_page_with_commands_says_how_canrls_gets_on_path(page: Path) -> None:
    text = page.read_text(encoding="utf-8")
    first = _first_command(text)
    if first is None:
        return
    assert _ON_PATH in text[:first], (
        f"{page.name}: a command at line {text.count(chr(10), 0, first) + 1} before the "
        f"page says how canrls gets on PATH ({_ON_PATH}, or write .venv/bin/canrls)")


def test_the_readme_says_it_as_the_pages_do() -> None:
    assert _ON_PATH in (ROOT / "README.md").read_text(encoding="utf-8")
