"""The saved model: ``canrls fit --save-model FILE`` writes it, ``canrls validate`` reads it.

A JSON document (``docs/model_file.md`` describes every key)::

    {
      "format": "canrls-model", "version": 1,
      "created": "2026-11-25T10:00:00Z", "canrls": "0.4.0",
      "sources": ["run1.log", "run2.log"],          # the logs it was identified on
      "model": {...},            # Model.to_dict() with the frozen ranges and scaling
      "effects": ["inertia", "viscous", "coulomb", "offset"],
      "parameters": {"inertia.J": {"value": 7.0e-05, "sigma": 4.9e-06, "unit": "kg·m²",
                                   "fixed": ..., "effect": "inertia",
                                   "equation": "mechanical", "description": "..."}, ...},
      "fit": {"mechanical": {"unit": "N·m", "residual_rms": ..., "fit_percent": ...,
                             "samples": ...}},
      "configuration": {"source": "drive.toml", "model": {...}, "estimator": {...},
                        "can": {...}, "signals": {...}, "signal_overrides": [...]},
      "calibration": {...}       # the frozen calibration (canrls.processor.Calibration)
    }

The parameters are physical (SI, the unit beside each); the model and the calibration
hold the ranges and power-of-two scaling that produced them, so a prediction with the
file (:func:`canrls.validate.validate_logs`) builds exactly the same filtered columns.
"""

from __future__ import annotations

import datetime as _dt
import json
import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from canrls import __version__
from canrls.config import AppConfig
from canrls.errors import ConfigError
from canrls.estimation.model import Model
from canrls.files import MAX_MODEL_BYTES, atomic_writer, read_text

if TYPE_CHECKING:
    from canrls.estimation.pipeline import Estimates
    from canrls.processor import Calibration, FitResult

__all__ = ["FORMAT", "VERSION", "SavedModel"]

FORMAT = "canrls-model"
VERSION = 1


def _clean(x: Any) -> Any:
    """JSON-safe: non-finite floats become null, tuples lists."""
    if isinstance(x, float):
        return x if math.isfinite(x) else None
    if isinstance(x, Mapping):
        return {str(k): _clean(v) for k, v in x.items()}
    if isinstance(x, list | tuple):
        return [_clean(v) for v in x]
    return x


@dataclass
class SavedModel:
    """An identified model: effects, parameters with sigma and unit, and what made them."""

    model: dict[str, Any]
    parameters: dict[str, dict[str, Any]]
    effects: list[str]
    fit: dict[str, dict[str, Any]] = field(default_factory=dict)
    configuration: dict[str, Any] = field(default_factory=dict)
    calibration: dict[str, Any] | None = None
    sources: list[str] = field(default_factory=list)
    created: str = ""
    canrls: str = __version__

    # -- building ---------------------------------------------------------------------
    @classmethod
    def from_fit(cls, res: FitResult, cfg: AppConfig, sources: list[str]) -> SavedModel:
        """From a replay's result and the configuration that produced it."""
        return cls.from_parts(res.model, res.estimates, res.calibration, cfg, sources)

    @classmethod
    def from_parts(cls, model: Model, est: Estimates, calibration: Calibration | None,
                   cfg: AppConfig, sources: list[str]) -> SavedModel:
        """From a model (with its frozen ranges and scaling), its estimates, the
        calibration (None: the model's ranges and scaling say it all) and the
        configuration."""
        can = dict(cfg.can)
        dbc = cfg.dbc_path()
        if dbc is not None:
            can["dbc"] = str(dbc.resolve())  # the file, wherever validate runs from
        return cls(
            model=model.to_dict(),
            parameters={p.name: p.to_dict() for p in est.parameters},
            effects=list(est.effects),
            fit={e.equation: {"unit": e.unit, "residual_rms": e.residual_rms,
                              "fit_percent": e.fit_percent, "samples": e.samples}
                 for e in est.equations},
            configuration={"source": cfg.source, "model": dict(cfg.model),
                           "estimator": dict(cfg.estimator), "fixed": dict(cfg.fixed),
                           "can": can, "signals": dict(cfg.signals),
                           "signal_overrides": list(cfg.signal_overrides)},
            calibration=None if calibration is None else calibration.to_dict(),
            sources=[str(s) for s in sources],
            created=_dt.datetime.now(_dt.UTC).strftime("%Y-%m-%dT%H:%M:%SZ"))

    def to_dict(self) -> dict[str, Any]:
        return _clean({"format": FORMAT, "version": VERSION, "created": self.created,
                       "canrls": self.canrls, "sources": self.sources, "model": self.model,
                       "effects": self.effects, "parameters": self.parameters,
                       "fit": self.fit, "configuration": self.configuration,
                       "calibration": self.calibration})  # type: ignore[no-any-return]

    def save(self, path: str | Path) -> Path:
        p = Path(path)
        text = json.dumps(self.to_dict(), indent=2, ensure_ascii=False) + "\n"
        # a temporary beside it, renamed: never written through a link, never half-written
        with atomic_writer(p, f"--save-model {p}") as f:
            f.write(text.encode("utf-8"))
        return p

    # -- reading ----------------------------------------------------------------------
    @classmethod
    def from_dict(cls, d: Mapping[str, Any], source: str = "<dict>") -> SavedModel:
        if not isinstance(d, Mapping) or d.get("format") != FORMAT:
            raise ConfigError(f"{source}: not a canrls model file (no \"format\": \"{FORMAT}\")")
        if d.get("version") != VERSION:
            raise ConfigError(f"{source}: model file version {d.get('version')!r} "
                              f"(this canrls reads version {VERSION})")
        for key in ("model", "parameters", "effects"):
            if key not in d:
                raise ConfigError(f"{source}: model file without {key!r}")
        params = d["parameters"]
        for name, p in params.items():
            if not isinstance(p, Mapping) or not isinstance(p.get("value"), int | float):
                raise ConfigError(f"{source}: parameters.{name}: needs a numeric 'value'")
        return cls(model=dict(d["model"]), parameters={k: dict(v) for k, v in params.items()},
                   effects=list(d["effects"]), fit=dict(d.get("fit") or {}),
                   configuration=dict(d.get("configuration") or {}),
                   calibration=d.get("calibration"), sources=list(d.get("sources") or []),
                   created=str(d.get("created", "")), canrls=str(d.get("canrls", "")))

    @classmethod
    def load(cls, path: str | Path) -> SavedModel:
        p = Path(path)
        # a regular file of bounded size: a FIFO or a device is refused, never opened
        text = read_text(p, f"--model {p}", limit=MAX_MODEL_BYTES)
        try:
            d = json.loads(text)
        except json.JSONDecodeError as e:
            raise ConfigError(f"--model {p}: invalid JSON: {e}") from e
        saved = cls.from_dict(d, source=str(p))
        try:  # the model checked where the file is read: names, units, expressions
            saved.build_model()
        except ConfigError as e:
            raise type(e)(f"--model {p}: {str(e).removeprefix('saved model: ')}") from e
        return saved

    # -- use --------------------------------------------------------------------------
    def build_model(self, available_signals: list[str] | None = None) -> Model:
        """The model with the saved (frozen) ranges and scaling."""
        return Model.from_dict(self.model, source="saved model",
                               available_signals=available_signals)

    def config(self) -> AppConfig:
        """The configuration that produced the model (estimator settings, DBC, signals)."""
        c = self.configuration
        cfg = AppConfig(source=str(c.get("source", "<saved model>")))
        for key in ("model", "estimator", "fixed", "can", "signals"):
            setattr(cfg, key, dict(c.get(key) or {}))
        cfg.signal_overrides = list(c.get("signal_overrides") or [])
        return cfg

    def values(self) -> dict[str, float]:
        return {k: float(v["value"]) for k, v in self.parameters.items()}
