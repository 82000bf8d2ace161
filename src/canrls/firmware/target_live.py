"""The target's integer path in the daemon: the fixed column ``canrls run`` publishes.

:class:`LiveTarget` runs the target's C (:class:`~canrls.firmware.native.TargetFeed`) on
the frames the daemon's processor sees, from the first one on: held until the
processor's calibration froze (the integers need its exponents, energies and period),
then replayed and run block by block. The daemon's fixed column is then what ``canrls
fit`` prints and the C of ``canrls export-c`` computes from the same frames, bit for
bit. A checkpoint keeps its state (:meth:`LiveTarget.state`), from which a resumed daemon
continues (:meth:`LiveTarget.resume`). A path started again from its prior while the float
estimate kept its values is not compared with it until it has caught up
(:meth:`LiveTarget.settling`).
"""

from __future__ import annotations

import logging
import math
from typing import Any

import numpy as np

from canrls.can.frameblock import FrameBlock
from canrls.can.protocol import Protocol
from canrls.core.checks import is_real
from canrls.estimation.settings import EstimatorSettings
from canrls.firmware.native import STATE_BYTES, TargetFeed, TargetSnapshot, state_layout
from canrls.firmware.target_fit import fit_model
from canrls.firmware.target_model import TargetError
from canrls.processor import FrameProcessor

__all__ = ["LiveTarget", "HOLD_MAX", "SETTLE_MEMORIES", "settle_updates"]

log = logging.getLogger(__name__)

#: the most frames held while the calibration collects (beyond: the kernel's column)
HOLD_MAX = 1_000_000
#: a path that starts again while the float keeps its values catches up, at most, in this
#: many memories 1/(1 - lambda) of the forgetting factor
SETTLE_MEMORIES = 3
#: the fields of :meth:`LiveTarget.state`
_SAVED = frozenset({"layout", "model", "state", "t0", "frozen"})


def settle_updates(kept: dict[str, int], lam: float) -> dict[str, int]:
    """Per equation, the updates a path started again from its prior needs before it is
    compared with a float estimate that kept its values: as many as the float had then
    (``kept``: what its estimate rests on), at most :data:`SETTLE_MEMORIES` memories
    ``1/(1 - lambda)`` (what a forgetting float still remembers; none with lambda = 1)."""
    if lam >= 1.0:
        return dict(kept)
    cap = math.ceil(SETTLE_MEMORIES / (1.0 - lam))
    return {name: min(n, cap) for name, n in kept.items()}


class LiveTarget:
    """The target's estimator on a daemon's frames (``Daemon(fixed_path=...)``).

    :param protocol: the drive's DBC and mapping (the processor's).
    :param settings: the estimator settings (the processor's).
    """

    def __init__(self, protocol: Protocol, settings: EstimatorSettings) -> None:
        self.protocol = protocol
        self.settings = settings
        self._held: list[FrameBlock] = []
        self._n_held = 0
        #: the running path (None until the calibration froze)
        self.running: TargetFeed | None = None
        #: why the target does not run this model (None: it does)
        self.refused: str | None = None
        #: the forgetting factor the running path was built with
        self._lam = settings.lam
        #: a checkpoint's path, continued when the path is built (None: none)
        self._resume: TargetSnapshot | None = None
        #: the float's updates per equation at the last block (what it kept at a restart)
        self._float_updates: dict[str, int] = {}
        #: per equation, the float's updates when the path started again from its prior
        #: while the float kept its values (None: it did not: nothing to catch up)
        self._kept: dict[str, int] | None = None
        #: per equation, the path's updates before its divergence is judged
        self._settle: dict[str, int] = {}

    def feed(self, block: FrameBlock, proc: FrameProcessor) -> None:
        """The frames of a block the processor has processed."""
        self._seen(proc)
        if self.refused is not None:
            return
        if self.running is None:
            # a copy: the daemon's blocks may be views of its receive buffers
            self._held.append(block.take(np.arange(len(block))))
            self._n_held += len(block)
            if proc.calibration is None:
                if self._n_held > HOLD_MAX:
                    self._refuse(f"no calibration after {HOLD_MAX} frames")
                return
            running = self._build(proc)
            if running is None:
                return
            if self._resume is not None:
                try:
                    running.restore(self._resume)
                    self._settle = {}  # it continues: as far as the float
                except TargetError as e:
                    log.warning("fixed point: the target's integer path starts again from "
                                "its prior (the checkpoint's target state: %s)", e)
                self._resume = None
            held, self._held, self._n_held = self._held, [], 0
            for b in held:
                running.feed(b)
            return
        if proc.pipeline.settings.lam != self._lam:
            # a new forgetting factor (the command set_lambda) is a new kernel plan: the
            # path starts again from its prior with it, at these frames
            log.warning("fixed point: the target's integer path starts again from its prior "
                        "(lambda %r)", proc.pipeline.settings.lam)
            self.restart(float_kept=True)
            self.feed(block, proc)
            return
        if proc.pipeline.frozen != self.running.frozen:  # the commands freeze and resume
            self.running.freeze(proc.pipeline.frozen)
        self.running.feed(block)

    def _seen(self, proc: FrameProcessor) -> None:
        """Keep the float's updates per equation (what it rests on, should the path
        start again)."""
        pipe = proc.pipeline
        self._float_updates = {e.name: fl for e, (fl, _) in
                               zip(pipe.model.equations, pipe.update_counts(), strict=True)}

    def state(self) -> dict[str, Any] | None:
        """What a checkpoint keeps of the path, integers only (None: it does not run:
        a resume starts it again from its prior)."""
        if self.running is None:
            return None
        snap = self.running.snapshot()
        return {"layout": state_layout(), "model": snap.model,
                "state": np.frombuffer(snap.state, np.uint8).copy(),
                "t0": snap.t0, "frozen": snap.frozen}

    def resume(self, saved: Any, proc: FrameProcessor) -> str | None:
        """Continue from a checkpoint's :meth:`state` on ``proc``, the processor restored
        from it: at once where its calibration and period are known, else when the path
        is built at the next frames; why it starts again from its prior instead (None:
        it continues)."""
        self._seen(proc)
        self.restart(float_kept=True)
        if saved is None:
            return "the checkpoint holds no target state"
        try:
            if not isinstance(saved, dict) or set(saved) != _SAVED:
                raise TargetError(f"fields {sorted(saved) if isinstance(saved, dict) else []}")
            model, state, t0 = saved["model"], saved["state"], saved["t0"]
            if not (isinstance(saved["layout"], str) and isinstance(model, np.ndarray)
                    and model.dtype == np.int64 and model.ndim == 1
                    and isinstance(state, np.ndarray) and state.dtype == np.uint8
                    and state.shape == (STATE_BYTES,) and (t0 is None or is_real(t0))
                    and isinstance(saved["frozen"], bool)):
                raise TargetError("a field of the wrong type or size")
            if saved["layout"] != state_layout():
                raise TargetError("it was saved by a build with other C headers")
        except TargetError as e:
            return f"the checkpoint's target state does not fit ({e})"
        snap = TargetSnapshot(model=model, state=state.tobytes(),
                              t0=None if t0 is None else float(t0), frozen=saved["frozen"])
        if proc.calibration is None or proc.period is None:
            self._resume = snap
            return None
        running = self._build(proc)
        if running is None:
            return f"the target's integer path does not run this model: {self.refused}"
        try:
            running.restore(snap)
        except TargetError as e:
            self.restart(float_kept=True)
            return f"the checkpoint's target state does not fit ({e})"
        self._settle = {}  # it continues: as far as the float
        return None

    def _build(self, proc: FrameProcessor) -> TargetFeed | None:
        """The path built on the processor's calibration, model and settings, now
        :attr:`running` (None: the target does not run this model: :attr:`refused`)."""
        try:
            # the pipeline's settings: its forgetting factor, a command's included
            self._lam = proc.pipeline.settings.lam
            running = TargetFeed(fit_model(proc.result("canrls run"), self.protocol,
                                           proc.pipeline.settings))
        except TargetError as e:
            self._refuse(str(e))
            return None
        if proc.pipeline.frozen:  # a checkpoint's, or a command's during the window
            running.freeze(True)
        self.running = running
        self._settle = {} if self._kept is None else settle_updates(self._kept, self._lam)
        self._kept = None
        return running

    def _refuse(self, why: str) -> None:
        self.refused = why
        self._held, self._n_held = [], 0
        log.warning("fixed point: the kernel on the float front end (the target's integer "
                    "path does not run: %s)", why)

    def restart(self, float_kept: bool = False) -> None:
        """A new model runs, or the estimators were reset: the target's path starts again
        at the next frames (its calibration is the processor's then).

        :param float_kept: the float estimate keeps its values (a model change, a new
            forgetting factor, a resume): the path, from its prior, is compared with it
            only once it has caught up (:meth:`settling`); False: both start again.
        """
        self.running = None
        self.refused = None
        self._held, self._n_held = [], 0
        self._resume = None
        self._kept = dict(self._float_updates) if float_kept else None
        self._settle = {}

    def settling(self) -> frozenset[str]:
        """The equations whose path, started again from its prior while the float kept
        its values, has not caught up yet: their divergence from the float says nothing
        (:func:`settle_updates`)."""
        if self.running is None or not self._settle:
            return frozenset()
        updates = self.running.run_info().updates
        return frozenset(name for name, n in self._settle.items()
                         if updates.get(name, 0) < n)

    def fixed(self) -> dict[str, tuple[float, bool]] | None:
        """Every parameter's fixed value in SI and whether its equation has updated (None:
        not running, the kernel's column stands)."""
        if self.running is None:
            return None if self.refused is not None else {}
        return self.running.fixed()
