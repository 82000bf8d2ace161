"""The target's integer path in the daemon: the fixed column ``canrls run`` publishes.

:class:`LiveTarget` runs :class:`~canrls.firmware.spec.TargetEstimator` on the frames
the daemon's processor sees, from the first one on: held until the processor's
calibration froze (the integers need its exponents, energies and period), then replayed
and run frame by frame. The daemon's fixed column is then what ``canrls fit`` prints
and the C of ``canrls export-c`` computes from the same frames, bit for bit.
"""

from __future__ import annotations

import logging

from canrls.can.frameblock import FrameBlock
from canrls.can.protocol import Protocol
from canrls.estimation.settings import EstimatorSettings
from canrls.firmware.spec import PUBLISH, TargetEstimator
from canrls.firmware.target_fit import fit_model
from canrls.firmware.target_model import TargetError
from canrls.firmware.vectors import Frame, block_frames
from canrls.processor import FrameProcessor

__all__ = ["LiveTarget", "HOLD_MAX"]

log = logging.getLogger(__name__)

#: the most frames held while the calibration collects (beyond: the kernel's column)
HOLD_MAX = 1_000_000


class LiveTarget:
    """The target's estimator on a daemon's frames (``Daemon(fixed_path=...)``).

    :param protocol: the drive's DBC and mapping (the processor's).
    :param settings: the estimator settings (the processor's).
    :param tick_s: the unit of the target's timestamps [s] (as ``canrls export-c``).
    """

    def __init__(self, protocol: Protocol, settings: EstimatorSettings,
                 tick_s: float = 1e-6) -> None:
        self.protocol = protocol
        self.settings = settings
        self.tick_s = tick_s
        self._t0: list[float] = []
        self._held: list[Frame] = []
        #: the running estimator (None until the calibration froze)
        self.estimator: TargetEstimator | None = None
        #: why the target does not run this model (None: it does)
        self.refused: str | None = None

    def feed(self, block: FrameBlock, proc: FrameProcessor) -> None:
        """The frames of a block the processor has processed."""
        if self.refused is not None:
            return
        frames = list(block_frames(block, self._t0, self.tick_s))
        if self.estimator is None:
            self._held += frames
            if proc.calibration is None:
                if len(self._held) > HOLD_MAX:
                    self._refuse(f"no calibration after {HOLD_MAX} frames")
                return
            try:
                tm = fit_model(proc.result("canrls run"), self.protocol, self.settings)
            except TargetError as e:
                self._refuse(str(e))
                return
            self.estimator = TargetEstimator(tm)
            frames, self._held = self._held, []
        est = self.estimator
        for t, fid, ext, data in frames:
            if est.frame(fid, ext, data, t) & PUBLISH:
                est.publish()

    def _refuse(self, why: str) -> None:
        self.refused = why
        self._held = []
        log.warning("fixed point: the kernel on the float front end (the target's integer "
                    "path does not run: %s)", why)

    def restart(self) -> None:
        """A new model runs: the estimator starts again at the next frames."""
        self.estimator = None
        self.refused = None
        self._held = []

    def fixed(self) -> dict[str, tuple[float, bool]] | None:
        """Every parameter's fixed value in SI and whether its equation has updated (None:
        not running, the kernel's column stands)."""
        est = self.estimator
        if est is None:
            return None if self.refused is not None else {}
        theta = iter(est.theta_si())
        return {p.name: (next(theta), es.updates > 0) for es in est.eqs
                for p in es.spec.parameters}
