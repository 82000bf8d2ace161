"""The public API: what docs/architecture.md lists imports without a warning, and the old
module paths of the move into the layers' folders still import, with a warning."""

from __future__ import annotations

import importlib
import re
import sys
import warnings
from pathlib import Path

import pytest

import canrls

ROOT = Path(__file__).resolve().parents[1]


def public_imports() -> list[str]:
    """The ``from canrls... import ...`` lines of docs/architecture.md's public API table."""
    text = (ROOT / "docs" / "architecture.md").read_text()
    section = text.split("## The public API", 1)[1].split("\n## ", 1)[0]
    return re.findall(r"^\| `(from canrls[\w.]* import [\w, ]+)` \|", section, re.M)


def test_the_docs_list_the_public_api() -> None:
    assert len(public_imports()) >= 8


@pytest.mark.parametrize("line", public_imports())
def test_every_public_import_works_without_a_warning(line: str) -> None:
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        exec(line, {})  # the docs' own import line


@pytest.mark.parametrize("old", sorted(canrls.MOVED))
def test_an_old_path_imports_the_new_module_with_a_warning(old: str) -> None:
    new = canrls.MOVED[old]
    for name in [m for m in sys.modules if m == old or m.startswith(old + ".")]:
        del sys.modules[name]  # imported by an earlier test: import it afresh
    with pytest.warns(DeprecationWarning, match=re.escape(f"{old} is now {new}")):
        mod = importlib.import_module(old)
    assert mod is importlib.import_module(new)


def test_the_old_paths_are_gone_from_the_tree() -> None:
    """The table holds moved modules only: no old path is still a file of the package."""
    src = ROOT / "src"
    for old in canrls.MOVED:
        rel = Path(*old.split("."))
        assert not (src / rel.with_suffix(".py")).exists(), old
        assert not (src / rel / "__init__.py").exists(), old
