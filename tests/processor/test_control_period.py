"""The control period of an export and of a fit's target path: one decision
(:func:`canrls.processor.period.control_period`), taken by every place that needs it.

Before, four places decided it: ``export-c``'s loader let an infinite ``--dt`` through,
the kernel's export ignored the period a fit measured, and the fit's target path fell
back to 1 ms by itself.
"""

from __future__ import annotations

import math
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import pytest
from user_drives import SIGNALS, user_dbc

from canrls.core.errors import ConfigError
from canrls.firmware import kernel_export, target_fit
from canrls.firmware.load import load
from canrls.processor import period
from canrls.processor.config import AppConfig
from canrls.processor.period import DEFAULT_PERIOD, control_period


def test_the_period_given_then_measured_then_the_dbc_s_then_the_default() -> None:
    assert control_period(given=2e-3, measured=3e-3, dbc=4e-3) == (
        period.ControlPeriod(2e-3, "--dt"))
    assert control_period(measured=3e-3, dbc=4e-3) == period.ControlPeriod(3e-3, "the fit's")
    assert control_period(dbc=4e-3).source == "the DBC's cycle time"
    assert control_period() == period.ControlPeriod(DEFAULT_PERIOD, "the default")


@pytest.mark.parametrize("bad", [math.inf, math.nan, 0.0, -1e-3, True])
def test_a_period_that_is_not_one_is_refused_naming_who_gave_it(bad: Any) -> None:
    with pytest.raises(ConfigError, match="--dt: the control period must be a positive"):
        control_period(given=bad)
    with pytest.raises(ConfigError, match="the fit's: the control period"):
        control_period(measured=bad, dbc=1e-3)


def _config(tmp_path: Path, cycle_time: bool = True) -> Path:
    """A configuration; with the shipped DBC (a cycle time) or a user's without one."""
    p = tmp_path / "drive.toml"
    text = '[model]\neffects = ["inertia", "viscous", "coulomb"]\nkt = 0.1\n'
    if not cycle_time:
        dbc = tmp_path / "user.dbc"
        dbc.write_text(user_dbc(None))
        roles = "\n".join(f'{r} = "{s}"' for r, s in (x.split("=") for x in SIGNALS))
        text += f'[can]\ndbc = "{dbc}"\n[signals]\n{roles}\n'
    p.write_text(text)
    return p


def test_export_c_refuses_an_infinite_dt(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="--dt"):
        load(_config(tmp_path), math.inf)


def test_every_export_asks_the_one_decision(tmp_path: Path,
                                            monkeypatch: pytest.MonkeyPatch) -> None:
    """Move the default and the loader, the kernel's export and the fit's target path
    all move with it: none falls back to a period of its own."""
    monkeypatch.setattr(period, "DEFAULT_PERIOD", 2e-3)
    cfg_path = _config(tmp_path, cycle_time=False)
    src = load(cfg_path)
    assert (src.dt, src.period_source) == (2e-3, "the default")

    seen: dict[str, float] = {}
    real = kernel_export.Pipeline

    def pipeline(model: Any, dt: float, *a: Any, **k: Any) -> Any:
        seen["kernel"] = dt
        return real(model, dt, *a, **k)

    monkeypatch.setattr(kernel_export, "Pipeline", pipeline)
    kernel_export.export_c(AppConfig.load(cfg_path), tmp_path / "c")
    assert seen["kernel"] == 2e-3

    def build(model: Any, protocol: Any, settings: Any, dt: float, **k: Any) -> None:
        seen["fit"] = dt

    monkeypatch.setattr(target_fit, "build", build)
    cfg = AppConfig.load(cfg_path)
    protocol = cfg.protocol()
    assert protocol.period is None
    res = SimpleNamespace(model=cfg.model_for(protocol), calibration=None,
                          period=SimpleNamespace(value=None))
    target_fit.fit_model(res, protocol, cfg.settings())  # type: ignore[arg-type]
    assert seen["fit"] == 2e-3
