"""What both demos (``canrls demo``, ``canrls demo --axes N``) share: the model the story
starts from and the diagnosis of feedback recorded from the bus."""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from canrls.can.protocol import Protocol
    from canrls.estimation.model import Model
    from canrls.estimation.settings import EstimatorSettings

__all__ = ["BASE", "diagnosis"]

#: the effects the demos' models start with; the hidden effect is none of them
BASE = ("inertia", "viscous", "coulomb")


def diagnosis(frames: Any, protocol: Protocol, model: Model,
              settings: EstimatorSettings) -> Any:
    """The diagnosis of ``model`` on feedback ``frames`` (messages or a FrameBlock) recorded
    from the bus (None: ``canrls.diagnosis.analysis`` is not in this build)."""
    from canrls.can.frameblock import FrameBlock
    from canrls.processor import FrameProcessor

    try:
        diag = importlib.import_module("canrls.diagnosis.analysis")
    except ModuleNotFoundError:
        return None
    proc = FrameProcessor(protocol, model, settings)
    block = frames if isinstance(frames, FrameBlock) else FrameBlock.from_messages(frames)
    return diag.diagnose(proc.samples(block), model, settings, dt=proc.pipeline.dt,
                         source="the bus")
