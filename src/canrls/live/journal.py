"""The daemon's journal: the few lines a person, or systemd's journal, reads while it runs.

One line when it starts publishing (the bus, the axis, the model), one on each model
change, and one when a fault begins or ends (the bus failed or reopened, transmission
paused or resumed, the fixed point diverged from the float reference, an estimate became
physically implausible, a thread failed). They go to the logger :data:`JOURNAL`:
``canrls run`` in text mode writes them to stdout, one flushed line each
(:func:`to_stream`); elsewhere they reach the log like any other (its warnings shown,
the rest at ``--log-level INFO``).
"""

from __future__ import annotations

import logging
from collections.abc import Iterator
from contextlib import contextmanager
from typing import IO

from canrls.can.estimator_frames import StatusReport
from canrls.estimation.model import Model

__all__ = ["JOURNAL", "Journal", "to_stream"]

#: the logger of the journal's lines
JOURNAL = logging.getLogger(__name__)

#: status flags that are states (a fault that lasts until it ends), and their words;
#: the counters' flags (frames lost, saturations, clock) are the monitor's to show, a
#: freeze is commanded, the bus's faults are journaled by the bus link
_STATE_FLAGS = {
    "diverged": "the fixed-point estimate diverged from the float reference",
    "implausible": "an estimate that physics rules out",
}


def model_line(model: Model) -> str:
    """The model in one phrase: its effects and the number of parameters."""
    return f"{','.join(model.effect_names)} ({len(model.parameters)} parameters)"


class Journal:
    """What the daemon says on each publication: that it publishes (once), and the
    status's lasting faults as they begin and end."""

    def __init__(self) -> None:
        self._publishing = False
        self._faults: set[str] = set()

    def published(self, bus: str, model: Model, status: StatusReport | None) -> None:
        """After a publication on ``bus`` of ``model``'s estimates with ``status``."""
        if not self._publishing:
            self._publishing = True
            JOURNAL.info("publishing on %s: %s axis, model %s", bus, model.axis,
                         model_line(model))
        flags = set(status.flags) & _STATE_FLAGS.keys() if status is not None else set()
        for name in sorted(flags - self._faults):
            JOURNAL.warning("fault: %s", _STATE_FLAGS[name])
        for name in sorted(self._faults - flags):
            JOURNAL.info("fault ended: %s", _STATE_FLAGS[name])
        self._faults = flags

    @staticmethod
    def model_changed(model: Model, why: str) -> None:
        """The running model changed (a command, a reload)."""
        JOURNAL.info("%s: model is now %s; estimation restarts", why, model_line(model))

    @staticmethod
    def fixed_restarted(why: str) -> None:
        """The target's integer path (the fixed column) starts again from its prior."""
        JOURNAL.info("%s: the fixed point's integer path starts again from its prior", why)

    @staticmethod
    def fixed_resumed(path: str, restarts: str | None) -> None:
        """After a resume from the checkpoint ``path``: the target's integer path continues
        from it, or starts again from its prior because of ``restarts``."""
        if restarts is None:
            JOURNAL.info("resumed from %s: the fixed point's integer path continues from "
                         "the checkpoint", path)
        else:
            JOURNAL.info("resumed from %s: the fixed point's integer path starts again from "
                         "its prior (%s)", path, restarts)


@contextmanager
def to_stream(stream: IO[str]) -> Iterator[None]:
    """While in the block, the journal's lines, information included, go to ``stream``
    alone: one line each, flushed, no time stamp (the journal adds its own)."""
    handler = logging.StreamHandler(stream)
    handler.setFormatter(logging.Formatter("canrls: %(message)s"))
    level, propagate = JOURNAL.level, JOURNAL.propagate
    JOURNAL.addHandler(handler)
    JOURNAL.setLevel(logging.INFO)
    JOURNAL.propagate = False
    try:
        yield
    finally:
        JOURNAL.removeHandler(handler)
        JOURNAL.setLevel(level)
        JOURNAL.propagate = propagate
