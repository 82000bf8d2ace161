"""Shared fixtures: every test fails if it leaks a bus or a thread."""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
DATA = Path(__file__).resolve().parent / "data"


@pytest.fixture(autouse=True)
def no_leaked_threads() -> Iterator[None]:
    """Fail a test that leaves threads running (buses, notifiers, daemons)."""
    before = set(threading.enumerate())
    yield
    deadline = time.monotonic() + 2.0
    while True:
        leaked = [t for t in threading.enumerate() if t not in before and t.is_alive()]
        if not leaked or time.monotonic() > deadline:
            break
        time.sleep(0.02)
    assert not leaked, f"test leaked threads: {[t.name for t in leaked]}"


@pytest.fixture
def default_dbc() -> Path:
    return ROOT / "dbc" / "canrls.dbc"


@pytest.fixture
def bounded_writes() -> Iterator[int]:
    """Files this process writes stop at 64 MiB (RLIMIT_FSIZE, SIGXFSZ ignored: a larger
    write fails with EFBIG): a test of a bound on output cannot fill the disk when the
    bound is missing (the code before the fix), it fails instead."""
    import resource
    import signal

    limit = 64 << 20
    old = resource.getrlimit(resource.RLIMIT_FSIZE)
    old_handler = signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
    resource.setrlimit(resource.RLIMIT_FSIZE, (limit, old[1]))
    try:
        yield limit
    finally:
        resource.setrlimit(resource.RLIMIT_FSIZE, old)
        signal.signal(signal.SIGXFSZ, old_handler)
