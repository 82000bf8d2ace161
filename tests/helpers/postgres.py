"""A throwaway PostgreSQL server for the tests (Debian's ``postgresql``).

:func:`postgres_server` finds ``initdb``/``pg_ctl`` (on the PATH or in
``/usr/lib/postgresql/*/bin``), installs Debian's ``postgresql`` with ``apt-get`` when
they are missing and the tests run as root (as CI does on a fresh machine), starts a
cluster in a temporary directory listening on a unix socket there only (no TCP port),
creates a database and yields its SQLAlchemy URL; at the end it stops the server and
removes the directory. PostgreSQL refuses to run as root: as root the server runs as
the ``postgres`` user (``runuser``). Without PostgreSQL and without root the test
skips with the reason.
"""

from __future__ import annotations

import glob
import os
import shutil
import subprocess
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import pytest
from debian import need_tool

__all__ = ["postgres_server", "pg_bin"]


def pg_bin() -> Path:
    """The directory of ``initdb`` and ``pg_ctl`` (installed when missing, as root)."""
    def find() -> Path | None:
        for cand in [shutil.which("initdb"), *sorted(
                glob.glob("/usr/lib/postgresql/*/bin/initdb"), reverse=True)]:
            if cand and os.access(cand, os.X_OK):
                return Path(cand).resolve().parent
        return None

    found = find()
    if found is None:
        need_tool("pg_ctlcluster", ["postgresql"])  # installs it as root, else skips
        found = find()
    if found is None or not (found / "pg_ctl").exists():
        pytest.skip("PostgreSQL's initdb/pg_ctl not found (Debian: postgresql)")
    return found


@contextmanager
def postgres_server(database: str = "canrls") -> Iterator[str]:
    """A running server with ``database``; yields its URL (``postgresql+psycopg://``)."""
    bindir = pg_bin()
    as_root = hasattr(os, "geteuid") and os.geteuid() == 0
    if as_root and shutil.which("runuser") is None:
        pytest.skip("running as root without runuser: cannot start PostgreSQL as postgres")
    if as_root:
        import pwd

        try:
            pwd.getpwnam("postgres")
        except KeyError:
            pytest.skip("running as root without a 'postgres' user to run PostgreSQL as")
    run_as = ["runuser", "-u", "postgres", "--"] if as_root else []
    base = Path(tempfile.mkdtemp(prefix="canrls-pg-"))
    data, sock = base / "data", base / "sock"
    sock.mkdir()
    if as_root:
        shutil.chown(base, "postgres")
        shutil.chown(sock, "postgres")
    base.chmod(0o755)

    def run(*cmd: str) -> None:
        res = subprocess.run([*run_as, *cmd], capture_output=True, text=True, timeout=120,
                             cwd=base)
        if res.returncode:
            raise RuntimeError(f"{' '.join(cmd)}: exit {res.returncode}: {res.stderr}")

    started = False
    try:
        run(str(bindir / "initdb"), "-D", str(data), "-U", "postgres", "-A", "trust",
            "--no-sync", "-E", "UTF8")
        run(str(bindir / "pg_ctl"), "-D", str(data), "-w", "-t", "60", "-l",
            str(base / "server.log"), "-o",
            f"-k {sock} -c listen_addresses='' -c fsync=off -p 5432", "start")
        started = True
        run(str(bindir / "createdb"), "-h", str(sock), "-U", "postgres", database) \
            if (bindir / "createdb").exists() else run(
            "psql", "-h", str(sock), "-U", "postgres", "-c", f"CREATE DATABASE {database}")
        yield f"postgresql+psycopg://postgres@/{database}?host={sock}"
    finally:
        if started:
            subprocess.run([*run_as, str(bindir / "pg_ctl"), "-D", str(data), "-m", "fast",
                            "-w", "stop"], capture_output=True, timeout=120, cwd=base)
        shutil.rmtree(base, ignore_errors=True)
