"""The saved model: ``canrls fit --save-model FILE`` writes it, ``canrls validate`` reads it.

A JSON document (format ``canrls-model``, version 1) with the physical parameters, the
model with the frozen ranges and power-of-two scaling that produced them, the
configuration and the calibration, so a prediction with the file builds exactly the
same filtered columns. Every key: docs/model_file.md.
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
from canrls.core.checks import json_safe, positive_period
from canrls.core.errors import ConfigError
from canrls.core.files import MAX_MODEL_BYTES, atomic_writer, read_text
from canrls.estimation.model import Model
from canrls.processor.config import AppConfig

if TYPE_CHECKING:
    from canrls.estimation.estimates import Estimates
    from canrls.processor.calibration import Calibration
    from canrls.processor.fit_result import FitResult

__all__ = ["FORMAT", "VERSION", "SavedModel"]

FORMAT = "canrls-model"
VERSION = 1



def _short(v: Any) -> str:
    """``repr(v)`` for an error message, cut to 60 characters."""
    if isinstance(v, int) and v.bit_length() > 100:  # repr() of 5,000 digits raises
        return f"an integer of about {int(v.bit_length() * 0.30103) + 1} digits"
    text = repr(v)
    return text if len(text) <= 60 else text[:57] + "..."


def _table(d: Mapping[str, Any], key: str, source: str, *, null: bool = False,
           where: str | None = None) -> dict[str, Any]:
    """``d[key]``, a table (``null``: also absent or null, then empty)."""
    v = d.get(key)
    if v is None and (null or key not in d):
        return {}
    if not isinstance(v, Mapping):
        raise ConfigError(f"{source}: {where or key} = {_short(v)}: must be a table")
    return dict(v)


def _strings(d: Mapping[str, Any], key: str, source: str, *, null: bool = False,
             where: str | None = None) -> list[str]:
    """``d[key]``, a list of strings (``null``: also absent or null, then empty)."""
    v = d.get(key)
    if v is None and null:
        return []
    if not isinstance(v, list) or not all(isinstance(x, str) for x in v):
        raise ConfigError(f"{source}: {where or key} = {_short(v)}: must be a list of "
                          f"strings")
    return list(v)


def _number(v: Any, where: str, source: str) -> float:
    """``v``, a finite number (an integer too large for a float is not one)."""
    if isinstance(v, bool) or not isinstance(v, int | float):
        raise ConfigError(f"{source}: {where} = {_short(v)}: must be a number")
    try:
        x = float(v)
    except OverflowError:
        x = math.inf
    if not math.isfinite(x):
        raise ConfigError(f"{source}: {where} = {_short(v)}: must be a finite number")
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
    #: the file (or ``from_dict``'s source) it was read from, which an error of its
    #: configuration names; empty for a model built in memory (not saved in the file)
    origin: str = field(default="", compare=False)

    # -- building ---------------------------------------------------------------------
    @classmethod
    def from_fit(cls, res: FitResult, cfg: AppConfig, sources: list[str]) -> SavedModel:
        """From a replay's result and the configuration that produced it (the control
        period it ran at kept with the calibration, ``calibration.period``: what
        ``canrls export-c`` builds the target's filter for)."""
        saved = cls.from_parts(res.model, res.estimates, res.calibration, cfg, sources)
        if saved.calibration is not None and res.period.value:
            saved.calibration["period"] = float(res.period.value)
        return saved

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
        return json_safe({"format": FORMAT, "version": VERSION, "created": self.created,
                       "canrls": self.canrls, "sources": self.sources, "model": self.model,
                       "effects": self.effects, "parameters": self.parameters,
                       "fit": self.fit, "configuration": self.configuration,
                       "calibration": self.calibration})

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
        """Validate a model file's document (every key its reader uses, with its type;
        parameters finite): a :class:`ConfigError` naming the file and the key."""
        if not isinstance(d, Mapping) or d.get("format") != FORMAT:
            raise ConfigError(f"{source}: not a canrls model file (no \"format\": \"{FORMAT}\")")
        if type(d.get("version")) is not int or d.get("version") != VERSION:
            raise ConfigError(f"{source}: model file version {_short(d.get('version'))} "
                              f"(this canrls reads version {VERSION})")
        for key in ("model", "parameters", "effects"):
            if key not in d:
                raise ConfigError(f"{source}: model file without {key!r}")
        model = _table(d, "model", source)
        params = _table(d, "parameters", source)
        for name, p in params.items():
            where = f"parameters.{name}"
            if not isinstance(p, Mapping):
                raise ConfigError(f"{source}: {where} = {_short(p)}: must be a table")
            _number(p.get("value"), f"{where}.value", source)
            for key in ("sigma", "fixed", "prior_share"):
                if p.get(key) is not None:
                    _number(p[key], f"{where}.{key}", source)
            if p.get("sigma") is not None and p["sigma"] < 0:  # a standard deviation
                raise ConfigError(f"{source}: {where}.sigma = {_short(p['sigma'])}: must be "
                                  f">= 0")
            for key in ("unit", "effect", "equation", "description"):
                if p.get(key) is not None and not isinstance(p[key], str):
                    raise ConfigError(f"{source}: {where}.{key} = {_short(p[key])}: must be "
                                      f"a string")
            if p.get("identifiable") is not None and not isinstance(p["identifiable"], bool):
                raise ConfigError(f"{source}: {where}.identifiable = "
                                  f"{_short(p['identifiable'])}: must be true or false")
        effects = _strings(d, "effects", source)
        fit = _table(d, "fit", source, null=True)
        for eq, f in fit.items():
            if not isinstance(f, Mapping):
                raise ConfigError(f"{source}: fit.{eq} = {_short(f)}: must be a table")
            for key in ("residual_rms", "fit_percent", "samples"):
                if f.get(key) is not None:
                    _number(f[key], f"fit.{eq}.{key}", source)
        configuration = _table(d, "configuration", source, null=True)
        for key in ("model", "estimator", "fixed", "can", "signals"):
            _table(configuration, key, source, null=True, where=f"configuration.{key}")
        _strings(configuration, "signal_overrides", source, null=True,
                 where="configuration.signal_overrides")
        calibration = d.get("calibration")
        if calibration is not None:
            calibration = _table(d, "calibration", source)
            energy = _table(calibration, "energy", source, null=True,
                            where="calibration.energy")
            for eq, e in energy.items():
                if not isinstance(e, list):
                    raise ConfigError(f"{source}: calibration.energy.{eq} = {_short(e)}: "
                                      f"must be a list of numbers")
                for k, x in enumerate(e):
                    _number(x, f"calibration.energy.{eq}[{k}]", source)
            if calibration.get("period") is not None:  # what export-c and tune run at
                positive_period(calibration["period"], f"{source}: calibration.period")
        saved = cls(model=model, parameters={k: dict(v) for k, v in params.items()},
                    effects=effects, fit={k: dict(v) for k, v in fit.items()},
                    configuration=configuration, calibration=calibration,
                    sources=_strings(d, "sources", source, null=True),
                    created=str(d.get("created", "")), canrls=str(d.get("canrls", "")),
                    origin=source)
        saved.config().check()  # the configuration's keys, as a TOML file's
        return saved

    @classmethod
    def load(cls, path: str | Path) -> SavedModel:
        p = Path(path)
        # a regular file of bounded size: a FIFO or a device is refused, never opened
        text = read_text(p, f"--model {p}", limit=MAX_MODEL_BYTES)
        try:
            d = json.loads(text)
        except json.JSONDecodeError as e:
            raise ConfigError(f"--model {p}: invalid JSON: {e}") from e
        except RecursionError as e:  # the JSON parser recurses once per nested level
            raise ConfigError(f"--model {p}: invalid JSON: nested too deep") from e
        except ValueError as e:  # an integer of more digits than Python converts
            raise ConfigError(f"--model {p}: invalid JSON: {e}") from e
        saved = cls.from_dict(d, source=str(p))
        try:  # the model checked where the file is read: names, units, expressions
            model = saved.build_model()
        except ConfigError as e:
            raise type(e)(f"--model {p}: {str(e).removeprefix('saved model: ')}") from e
        energy = (saved.calibration or {}).get("energy") or {}
        for eq in model.equations:  # one energy per column, as the ridge takes them
            got = energy.get(eq.name)
            if got is not None and len(got) != len(eq.parameters):
                raise ConfigError(f"--model {p}: calibration.energy.{eq.name} has "
                                  f"{len(got)} values, the {eq.name} equation "
                                  f"{len(eq.parameters)} parameters")
        return saved

    # -- use --------------------------------------------------------------------------
    def build_model(self, available_signals: list[str] | None = None) -> Model:
        """The model with the saved (frozen) ranges and scaling."""
        return Model.from_dict(self.model, source="saved model",
                               available_signals=available_signals)

    def config(self) -> AppConfig:
        """The configuration that produced the model (estimator settings, DBC, signals)."""
        c = self.configuration
        # an error of a read file's configuration names the file, not where the fit read it
        cfg = AppConfig(source=f"{self.origin}: configuration" if self.origin
                        else str(c.get("source", "<saved model>")))
        for key in ("model", "estimator", "fixed", "can", "signals"):
            setattr(cfg, key, dict(c.get(key) or {}))
        cfg.signal_overrides = list(c.get("signal_overrides") or [])
        return cfg

    def values(self) -> dict[str, float]:
        return {k: float(v["value"]) for k, v in self.parameters.items()}
