"""Faults against the daemon's command path and life cycle.

In one process on python-can's ``virtual`` bus: the regular publication schedule is a
fixed grid that forced publications never move, command floods (hundreds of
``add_effect``, random bytes) against a running daemon, the bounds on the model and the
command rate, and the exit status of a daemon whose estimator thread fails. Across
processes (python-can-remote on 127.0.0.1): ``canrls run`` killed with -9 at seeded
random moments resumes from its checkpoint every time; a second SIGTERM still stops it
cleanly with exit status 0.
"""

from __future__ import annotations

import itertools
import os
from pathlib import Path
from typing import Any

import can

from canrls.can.frames import CommandCode, encode_command
from canrls.config import AppConfig
from canrls.live.daemon import Daemon, DaemonSettings

ROOT = Path(__file__).resolve().parent.parent
BASE = ["inertia", "viscous", "coulomb"]
_ids = itertools.count()


def _chan(name: str) -> str:
    return f"test-fault-cmd-{name}-{os.getpid()}-{next(_ids)}"


def _setup(effects: list[str] = BASE) -> tuple[Any, Any, Any]:
    cfg = AppConfig()
    cfg.model = {"effects": list(effects), "kt": 0.1}
    protocol = cfg.protocol()
    return protocol, cfg.model_for(protocol), cfg.settings()


def _cmd(code: int, effect: int = 0, order: int = 0, lam: float = 0.0) -> can.Message:
    return encode_command(code, effect, order, lam)


# ------------------------------------------------------------------ the schedule
def test_forced_publications_do_not_move_the_regular_grid() -> None:
    """60 model changes within one interval force 60 publications; the next regular one
    stays where the grid has it (it moved one interval per forced publication: 6 s)."""
    protocol, model, settings = _setup()
    d = Daemon(protocol, model, settings, DaemonSettings(publish_interval=0.1),
               bus={"interface": "virtual", "channel": _chan("grid")})
    pub = d.publisher
    t0 = 1000.0
    pub.start(t0)
    assert pub.next_at == t0 + 0.1
    for k in range(60):  # a burst: each model change publishes at once
        pub.model_changed()
        now = t0 + 0.001 * k
        assert pub.due(now)
        pub.publish(now)
    assert pub.publications == 60
    assert pub.next_at == t0 + 0.1  # the grid did not move
    assert not pub.due(t0 + 0.099) and pub.due(t0 + 0.1)
    pub.publish(t0 + 0.1)
    assert abs(pub.next_at - (t0 + 0.2)) < 1e-9
    pub.publish(t0 + 0.4501)  # a long block missed slots: skipped, the grid kept
    assert abs(pub.next_at - (t0 + 0.5)) < 1e-9
