"""What ``canrls export-c`` exports: a saved model (or a configuration) as the service
runs it after its calibration.

A saved model (``canrls fit --save-model``, JSON) keeps the exponents its fit ended
with (``model.scaling``) and, in ``calibration``, the ones the calibration window
decided with the column energies measured in them, the columns still pending and the
control period. The target starts where the fit started after its window: from the
calibration's exponents, energies and pending columns (the ones the data later grew
into are the target's own rescales, as they were the fit's). A configuration (TOML)
has no calibration: the exponents of its ranges and the prior of an estimator that has
not calibrated.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from canrls.can.protocol import Protocol
from canrls.estimation.model import Model
from canrls.estimation.settings import EstimatorSettings
from canrls.firmware.target_model import TargetModel, build
from canrls.processor.config import AppConfig
from canrls.processor.period import control_period

if TYPE_CHECKING:
    from canrls.processor.modelfile import SavedModel

__all__ = ["Source", "load", "target_model"]


@dataclass
class Source:
    """A model to export: the configuration, the model with the calibration's exponents,
    its column energies and pending columns, the period and a label."""

    config: AppConfig
    protocol: Protocol
    model: Model
    settings: EstimatorSettings
    dt: float
    energy: dict[str, list[float]] | None
    pending: dict[str, list[str]] | None
    label: str
    #: where the period came from
    period_source: str
    #: the saved model read (None: a configuration)
    saved: SavedModel | None = None


def load(path: str | Path, dt: float | None = None, axis: str | None = None) -> Source:
    """A saved model (``.json``) or a configuration (TOML), of ``axis`` for a machine's;
    ``dt`` [s] overrides the control period (:func:`~canrls.processor.period.control_period`:
    else the saved model's, the DBC's cycle time, or
    :data:`~canrls.processor.period.DEFAULT_PERIOD`). The one loader of a model to export."""
    from canrls.processor.modelfile import SavedModel

    path = Path(path)
    cal: dict[str, Any] = {}
    saved = None
    if path.suffix.lower() == ".json":
        saved = SavedModel.load(path)
        cfg = saved.config()
        model = saved.build_model()
        cal = dict(saved.calibration or {})
        if cal.get("scaling"):
            # the exponents the calibration decided (the energies are in them)
            model = model.with_scaling(cal["scaling"])
        label = f"the saved model {path.name}"
    else:
        cfg = AppConfig.load(path)
        model = None
        label = f"the configuration {path.name}"
    cfg = cfg.axis(axis)
    protocol = cfg.protocol()
    if model is None:
        model = cfg.model_for(protocol)
    period = control_period(given=dt, measured=cal.get("period"), dbc=protocol.period)
    return Source(cfg, protocol, model, cfg.settings(), period.value, cal.get("energy"),
                  cal.get("pending"), label, period.source, saved)


def target_model(src: Source, *, frames: bool = True, tick_s: float = 1e-6) -> TargetModel:
    """The integers of ``src`` on the target (:func:`canrls.firmware.target_model.build`)."""
    return build(src.model, src.protocol, src.settings, src.dt, energy=src.energy,
                 pending=src.pending, tick_s=tick_s, frames=frames, source=src.label)
