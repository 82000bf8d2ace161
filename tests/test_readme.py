"""Every ```sh block of README.md, and of the pages of docs/ in ``PAGES``, runs as pasted
in a fresh clone.

The repository's tracked files as they stand (``git stash create``: the working tree,
nothing of it changed) are checked out in a clone under ``tmp_path``; the clone gets the
installed environment as its ``.venv`` (links to the one running this test, marked
installed, so ``make demo`` does not reinstall: the install is the one step not run
here, ``tests/test_build.py`` builds the extensions). Each block runs with bash from the
clone's folder, ``set -e``, with no ``canrls`` on ``PATH``. A block whose first line is
``# needs: WHAT, ...`` runs only where WHAT is a path that exists for the clone as for
the repository (``../shared/data/hsm150``: the clone's ``../shared`` links to the
repository's); otherwise it is skipped, and the skip says what it needs.

A page of docs/ calls ``canrls`` and ``python`` as on the ``PATH`` after ``source
.venv/bin/activate`` (each page says so), and its blocks build on each other (a ``cd``, a
variable, a file): each page runs in a clone of its own, its blocks in order in one
shell with the clone's ``.venv/bin`` first on ``PATH``, up to the first block whose
``# needs:`` the clone lacks (the blocks after it may use what it would have made).
"""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import pytest

from conftest import ROOT

pytestmark = pytest.mark.slow

#: a fenced shell block: its text, between ```sh and ```
_BLOCK = re.compile(r"^```sh\n(.*?)^```$", re.MULTILINE | re.DOTALL)
#: the first line of a block that needs more than a clone and ``make demo``
_NEEDS = re.compile(r"#\s*needs:\s*(.+)")


@dataclass(frozen=True)
class Block:
    """One shell block of the README: its first line number and its text."""

    line: int
    text: str

    @property
    def needs(self) -> str | None:
        """What the block's ``# needs:`` line names, or None."""
        m = _NEEDS.fullmatch(self.text.splitlines()[0].strip())
        return m.group(1) if m else None


def readme_blocks(text: str) -> list[Block]:
    """The ```sh blocks of a README, in order."""
    return [Block(text.count("\n", 0, m.start()) + 2, m.group(1)) for m in _BLOCK.finditer(text)]


BLOCKS = readme_blocks((ROOT / "README.md").read_text(encoding="utf-8"))

#: the pages of docs/ whose blocks run without hardware in seconds (the others need a CAN
#: interface, systemd or a drive's log, or take minutes)
PAGES = ("diagnose.md", "model_file.md", "tune.md", "hsm150.md")


def _git(*args: str, cwd: Path) -> str:
    return subprocess.run(["git", *args], cwd=cwd, check=True, capture_output=True,
                          text=True, timeout=120).stdout.strip()


@pytest.fixture(scope="module")
def clone(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A clone of the repository's tracked files as they stand, with the test's
    environment as its ``.venv``."""
    return make_clone(tmp_path_factory.mktemp("readme"))


def make_clone(base: Path) -> Path:
    """A clone in ``base`` of the repository's tracked files as they stand, with the
    test's environment as its ``.venv`` (skips where there is no git checkout or venv)."""
    if shutil.which("git") is None or not (ROOT / ".git").exists():
        pytest.skip("not a git checkout: no clone to make")
    venv = Path(sys.prefix)
    if not (venv / "pyvenv.cfg").is_file() or not (venv / "bin" / "canrls").exists():
        pytest.skip(f"the tests do not run in an installed venv ({venv}): make test does")
    commit = _git("stash", "create", cwd=ROOT) or _git("rev-parse", "HEAD", cwd=ROOT)
    dest = base / "canrls"
    _git("clone", "--quiet", "--shared", "--no-checkout", str(ROOT), str(dest), cwd=base)
    _git("checkout", "--quiet", "--detach", commit, cwd=dest)
    if (ROOT.parent / "shared").is_dir():
        (base / "shared").symlink_to(ROOT.parent / "shared")
    own = dest / ".venv"
    (own / "bin").mkdir(parents=True)
    shutil.copy2(venv / "pyvenv.cfg", own / "pyvenv.cfg")
    for entry in venv.iterdir():
        if entry.name not in ("bin", "pyvenv.cfg"):
            (own / entry.name).symlink_to(entry)
    for entry in (venv / "bin").iterdir():
        if entry.name != ".installed":
            (own / "bin" / entry.name).symlink_to(entry)
    (own / "bin" / ".installed").touch()  # newer than every file of the clone
    return dest


def _env() -> dict[str, str]:
    """The environment of a block: no ``canrls`` on PATH, no active venv."""
    path = [d for d in os.environ.get("PATH", "").split(os.pathsep)
            if d and not (Path(d) / "canrls").exists()]
    env = {k: v for k, v in os.environ.items() if k not in ("VIRTUAL_ENV", "PYTHONPATH")}
    return {**env, "PATH": os.pathsep.join(path), "MPLBACKEND": "Agg"}


def _activated(clone: Path) -> dict[str, str]:
    """The environment of a page's blocks: as after ``source .venv/bin/activate``."""
    env = _env()
    return {**env, "PATH": os.pathsep.join([str(clone / ".venv" / "bin"), env["PATH"]]),
            "VIRTUAL_ENV": str(clone / ".venv")}


def test_readme_has_blocks_to_run() -> None:
    assert [b for b in BLOCKS if b.needs is None], "no ```sh block of the README runs"


@pytest.mark.parametrize("block", BLOCKS, ids=[f"line{b.line}" for b in BLOCKS])
def test_readme_block_runs_as_pasted(block: Block, clone: Path) -> None:
    if block.needs is not None:
        what = block.needs.split(",")[0].strip()
        if not (clone / what).exists():
            pytest.skip(f"README line {block.line} needs {block.needs}")
    assert not re.search(r"^\s*make test\b", block.text, re.MULTILINE), (
        f"README line {block.line}: 'make test' in a shell block would run the whole suite "
        f"from here, this test among it: name it in the prose")
    r = subprocess.run(["bash", "-e", "-o", "pipefail", "-c", block.text], cwd=clone,
                       env=_env(), capture_output=True, text=True, timeout=600, check=False)
    assert r.returncode == 0, (f"README line {block.line}: exit {r.returncode}\n{block.text}\n"
                               f"--- stdout\n{r.stdout[-3000:]}\n--- stderr\n{r.stderr[-3000:]}")


@pytest.mark.parametrize("page", PAGES)
def test_docs_page_blocks_run_as_pasted(page: str, tmp_path: Path) -> None:
    blocks = readme_blocks((ROOT / "docs" / page).read_text(encoding="utf-8"))
    assert blocks, f"docs/{page} has no ```sh block to run"
    where = make_clone(tmp_path)
    run, left = [], []
    for b in blocks:
        if left or (b.needs is not None
                    and not (where / b.needs.split(",")[0].strip()).exists()):
            left.append(b)
        else:
            run.append(b)
    if not run:
        pytest.skip(f"docs/{page} line {left[0].line} needs {left[0].needs}")
    for b in run:
        assert not re.search(r"^\s*make test\b", b.text, re.MULTILINE), (
            f"docs/{page} line {b.line}: 'make test' in a shell block: name it in the prose")
    script = "".join(f"echo '--- docs/{page} line {b.line}'\n{b.text}" for b in run)
    r = subprocess.run(["bash", "-e", "-o", "pipefail", "-c", script], cwd=where,
                       env=_activated(where), capture_output=True, text=True, timeout=600,
                       check=False)
    assert r.returncode == 0, (f"docs/{page}: exit {r.returncode}\n"
                               f"--- stdout\n{r.stdout[-3000:]}\n--- stderr\n{r.stderr[-3000:]}")
