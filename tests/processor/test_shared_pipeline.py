"""What a worker builds once per configuration (the fixed-point plans and formats, the
front end's start) and the short log read without a reader thread: fits of logs one
after another equal each log's fit alone, in a fresh configuration, bit for bit and
field by field."""

from __future__ import annotations

import dataclasses
import math
import struct
import threading
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from canrls.can.logs import read_frames
from canrls.estimation.fixed import plan
from canrls.estimation.model import Model
from canrls.estimation.pipeline import Pipeline
from canrls.processor.config import AppConfig, prepare
from canrls.processor.replay import fit_logs
from canrls.sim.fleet_plan import FLEET_EFFECTS, FLEET_KT, make_fleet, write_recording


@pytest.fixture(scope="module")
def short_logs(tmp_path_factory: pytest.TempPathFactory) -> list[Path]:
    """Three logs of 3 s (6,000 frames each) of drives of different types."""
    out = tmp_path_factory.mktemp("short")
    fleet = make_fleet(3, 1, 3.0, seed=33)
    paths = []
    for d in fleet.drives:
        p = out / f"{d.name}.log"
        write_recording(p, d, d.recordings[0], 3.0)
        paths.append(p)
    return paths


def _fresh() -> tuple[Any, Any, Any]:
    """Protocol, model and settings built anew, nothing shared with an earlier fit."""
    plan._plan.cache_clear()
    cfg = AppConfig()
    cfg.model = {"effects": FLEET_EFFECTS.split(","), "kt": FLEET_KT}
    return prepare(cfg)


def _same(a: Any, b: Any, where: str = "fit") -> None:
    """``a`` and ``b`` equal in every field, floats and arrays to the bit."""
    assert type(a) is type(b), where
    if isinstance(a, Model):
        _same(a.to_dict(), b.to_dict(), f"{where}.to_dict()")
    elif dataclasses.is_dataclass(a):
        for f in dataclasses.fields(a):
            _same(getattr(a, f.name), getattr(b, f.name), f"{where}.{f.name}")
    elif isinstance(a, np.ndarray):
        assert (a.dtype, a.shape, a.tobytes()) == (b.dtype, b.shape, b.tobytes()), where
    elif isinstance(a, float | np.floating):
        assert struct.pack("<d", a) == struct.pack("<d", b), f"{where}: {a!r} != {b!r}"
    elif isinstance(a, dict):
        assert list(a) == list(b), where
        for k in a:
            _same(a[k], b[k], f"{where}[{k!r}]")
    elif isinstance(a, list | tuple):
        assert len(a) == len(b), where
        for i, (x, y) in enumerate(zip(a, b, strict=True)):
            _same(x, y, f"{where}[{i}]")
    else:
        assert a == b, f"{where}: {a!r} != {b!r}"


def test_fits_in_turn_equal_each_fit_alone(short_logs: list[Path]) -> None:
    alone = []
    for p in short_logs:
        protocol, model, settings = _fresh()
        alone.append(fit_logs([p], protocol, model, settings))
    assert len({f.estimates.parameters[0].value for f in alone}) == len(short_logs)
    protocol, model, settings = _fresh()
    # one configuration for every log, as a worker holds it; each log twice, so that the
    # second fit of a log follows another log's
    order = [*range(len(short_logs)), *reversed(range(len(short_logs)))]
    for k in order:
        _same(fit_logs([short_logs[k]], protocol, model, settings), alone[k],
              f"fit of {short_logs[k].name}")


def test_fits_in_small_blocks_in_turn_equal_each_fit_alone(short_logs: list[Path]) -> None:
    # blocks shorter than the calibration window: each stream runs its own pipeline
    # from the shared start while the window fills
    alone = []
    for p in short_logs[:2]:
        protocol, model, settings = _fresh()
        alone.append(fit_logs([p], protocol, model, settings, chunk_size=500))
    protocol, model, settings = _fresh()
    for k in (0, 1, 0):
        _same(fit_logs([short_logs[k]], protocol, model, settings, chunk_size=500),
              alone[k], f"fit of {short_logs[k].name} in blocks of 500 frames")


def test_a_configuration_builds_its_start_once(short_logs: list[Path],
                                               monkeypatch: pytest.MonkeyPatch) -> None:
    protocol, model, settings = _fresh()
    fit_logs([short_logs[0]], protocol, model, settings)
    built: list[int] = []
    init = Pipeline.__init__

    def counted(self: Pipeline, *a: Any, **kw: Any) -> None:
        built.append(1)
        init(self, *a, **kw)

    monkeypatch.setattr(Pipeline, "__init__", counted)
    fit_logs([short_logs[1]], protocol, model, settings)
    # the calibration's probe and the calibrated pipeline; the start is the first log's
    assert len(built) == 2


def test_fit_result_is_the_same_whatever_the_plan_cache(short_logs: list[Path]) -> None:
    protocol, model, settings = _fresh()
    first = fit_logs([short_logs[0]], protocol, model, settings)
    again = fit_logs([short_logs[0]], protocol, model, settings)  # every plan from the cache
    _same(again, first)
    assert math.isfinite(first.residual_rms)


def test_an_uncalibrated_configuration_is_found_once() -> None:
    _, model, settings = _fresh()
    n = model.equations[0].n
    assert settings.fixed_config(n) is settings.fixed_config(n)
    # another configuration finds its own
    assert dataclasses.replace(settings, alpha=1.0).fixed_config(n) != settings.fixed_config(n)


def test_a_plan_is_made_once_and_shared_read_only() -> None:
    _, model, settings = _fresh()
    cfg = settings.fixed_config(model.equations[0].n)
    p1, named1 = plan.build_plan(cfg, 4, 0.999, 10.0)
    p2, named2 = plan.build_plan(cfg, 4, 0.999, 10.0)
    assert p1 is p2 and not p1.flags.writeable
    named1["phi_ps"] = -1  # each caller's named copy is its own
    assert named2["phi_ps"] != -1
    assert plan.build_plan(cfg, 4, 0.999, 20.0)[0] is not p1


def test_a_short_log_is_read_without_a_thread(short_logs: list[Path],
                                              monkeypatch: pytest.MonkeyPatch) -> None:
    started: list[str] = []
    start = threading.Thread.start

    def counted(self: threading.Thread) -> None:
        started.append(self.name)
        start(self)

    monkeypatch.setattr(threading.Thread, "start", counted)
    blocks = list(read_frames(short_logs[0]))
    assert sum(len(b) for b in blocks) > 5000
    assert started == []
    # a log of several blocks still reads the next block ahead in a thread
    assert len(list(read_frames(short_logs[0], chunk_size=4096))) == 2
    assert "canrls log reader" in started


def test_the_calibration_probe_runs_no_check_filter() -> None:
    _, model, settings = _fresh()
    probe = Pipeline(model, 1e-3, settings, adapt=False)
    assert all(e.check_builder is None for e in probe.estimators)
    assert all(e.check_builder is not None
               for e in Pipeline(model, 1e-3, settings).estimators)
