"""Checkpoints: atomic files, bit-exact resume, corruption and mismatch set aside, kill -9."""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from daemon_tool import daemon_process

from canrls.core.errors import CheckpointError
from canrls.estimation.model import Model
from canrls.live.checkpoint import (
    FORMAT,
    MAGIC,
    Checkpoint,
    fingerprint,
    load_checkpoint,
    save_checkpoint,
    set_aside,
)
from canrls.live.daemon import Daemon
from canrls.live.daemon_settings import DaemonSettings
from canrls.processor import FrameProcessor
from canrls.processor.config import AppConfig
from canrls.sim import scenario
from canrls.sim.scenario import Simulator

EFFECTS = ["inertia", "viscous", "coulomb"]


def _setup(effects: list[str] = EFFECTS) -> tuple:
    cfg = AppConfig()
    cfg.model = {"effects": list(effects), "kt": 0.1}
    protocol = cfg.protocol()
    return protocol, cfg.model_for(protocol), cfg.settings()


def _frames(seconds: float, seed: int = 1) -> list:
    sc = scenario("standard", seed=seed, duration=seconds, excitation="slow")
    return list(Simulator(sc, t0=0.0).frames(500))


def _checkpoint_of(proc: FrameProcessor, model, settings) -> Checkpoint:
    return Checkpoint(model=json.loads(json.dumps(proc.model.to_dict())),
                      config_model=json.loads(json.dumps(model.to_dict())),
                      fingerprint=fingerprint(settings, proc.dt), state=proc.state(),
                      counters={"frames": 7}, saved_at=123.5)


def test_roundtrip_continues_bit_for_bit(tmp_path: Path) -> None:
    protocol, model, settings = _setup()
    blocks = _frames(4.0)
    a = FrameProcessor(protocol, model, settings)
    for b in blocks[:4]:
        a.process(b)
    path = tmp_path / "cp.bin"
    n = save_checkpoint(path, _checkpoint_of(a, model, settings))
    assert path.stat().st_size == n
    assert path.read_bytes().startswith(MAGIC)
    assert [p.name for p in tmp_path.iterdir()] == ["cp.bin"]  # no temporary left
    cp = load_checkpoint(path)
    assert cp.counters == {"frames": 7} and cp.saved_at == 123.5
    b = FrameProcessor(protocol, model, settings)
    b.restore(cp.state, Model.from_dict(cp.model))
    assert b.calibration == a.calibration and b.model.exponents == a.model.exponents
    # the same continuation from the original and from the restored state
    a.restore(a.state(), a.model)  # both restart their filters alike
    for blk in blocks[4:]:
        a.process(blk)
        b.process(blk)
    ea, eb = a.pipeline.estimates(), b.pipeline.estimates()
    for pa, pb in zip(ea.parameters, eb.parameters, strict=True):
        assert pa.value == pb.value and pa.fixed == pb.fixed and pa.sigma == pb.sigma
    for x, y in zip(a.pipeline.estimators, b.pipeline.estimators, strict=True):
        assert np.array_equal(x.rls.state()["P"], y.rls.state()["P"])
        assert np.array_equal(x.frls.state()["P"], y.frls.state()["P"])


@pytest.mark.parametrize("damage", ["flip", "truncate", "magic", "format", "header"])
def test_corruption_is_detected(tmp_path: Path, damage: str) -> None:
    protocol, model, settings = _setup()
    pipe = FrameProcessor(protocol, model, settings)
    path = tmp_path / "cp.bin"
    save_checkpoint(path, _checkpoint_of(pipe, model, settings))
    raw = bytearray(path.read_bytes())
    if damage == "flip":
        raw[-40] ^= 0x01
    elif damage == "truncate":
        raw = raw[:-10]
    elif damage == "magic":
        raw[0:6] = b"XXXXXX"
    elif damage == "format":
        raw = raw.replace(FORMAT.encode(), b"canrls.checkpoint/9")
    else:
        raw = raw.replace(b'"sha256"', b'"sha256', 1)
    path.write_bytes(bytes(raw))
    with pytest.raises(CheckpointError):
        load_checkpoint(path)


def test_set_aside_keeps_the_file(tmp_path: Path) -> None:
    p = tmp_path / "cp.bin"
    p.write_bytes(b"junk")
    a = set_aside(p)
    p.write_bytes(b"junk2")
    b = set_aside(p)
    assert not p.exists() and a.read_bytes() == b"junk" and b.read_bytes() == b"junk2"
    assert a.name.startswith("cp.bin.bad-") and a != b


def _daemon(protocol, model, settings, path: Path, **kw) -> Daemon:
    return Daemon(protocol, model, settings, DaemonSettings(checkpoint=path, **kw),
                  bus={"interface": "virtual", "channel": "unused-ckpt"})


def test_daemon_resumes_and_sets_aside_mismatches(tmp_path: Path,
                                                  caplog: pytest.LogCaptureFixture) -> None:
    protocol, model, settings = _setup()
    path = tmp_path / "cp.bin"
    proc = FrameProcessor(protocol, model, settings)
    for b in _frames(2.0):
        proc.process(b)
    save_checkpoint(path, _checkpoint_of(proc, model, settings))
    d = _daemon(protocol, model, settings, path)
    assert d.resumed_from == str(path)
    assert d.pipeline.samples == proc.pipeline.samples > 0
    assert d.stats().frames == 7
    d.stop()  # never started: the checkpoint's lock is released for the next
    # another configured model: set aside, never loaded
    _, model2, _ = _setup(EFFECTS + ["offset"])
    with caplog.at_level("ERROR", logger="canrls.live"):
        d2 = _daemon(protocol, model2, settings, path)
    assert d2.resumed_from is None and d2.pipeline.samples == 0
    assert not path.exists() and len(list(tmp_path.glob("cp.bin.bad-*"))) == 1
    assert "another configured model" in caplog.text
    d2.stop()
    # other estimator settings: also a mismatch
    save_checkpoint(path, _checkpoint_of(proc, model, settings))
    cfg = AppConfig()
    cfg.estimator = {"alpha": 0.5}
    d3 = _daemon(protocol, model, cfg.settings(), path)
    assert d3.resumed_from is None and len(list(tmp_path.glob("cp.bin.bad-*"))) == 2
    d3.stop()
    # a corrupted file
    save_checkpoint(path, _checkpoint_of(proc, model, settings))
    raw = bytearray(path.read_bytes())
    raw[-5] ^= 0xFF
    path.write_bytes(bytes(raw))
    d4 = _daemon(protocol, model, settings, path)
    assert d4.resumed_from is None and len(list(tmp_path.glob("cp.bin.bad-*"))) == 3


def test_effect_added_by_command_survives_a_restart(tmp_path: Path) -> None:
    protocol, model, settings = _setup()
    path = tmp_path / "cp.bin"
    pipe = FrameProcessor(protocol, model.with_effects(add=["unbalance"]), settings)
    cp = _checkpoint_of(pipe, model.with_effects(add=["unbalance"]), settings)
    cp.config_model = json.loads(json.dumps(model.to_dict()))
    save_checkpoint(path, cp)
    d = _daemon(protocol, model, settings, path)
    assert d.model.effect_names == (*EFFECTS, "unbalance")
    assert d.config_model.effect_names == tuple(EFFECTS)


@pytest.mark.slow
def test_kill_9_loses_at_most_one_interval(tmp_path: Path) -> None:
    path = tmp_path / "cp.bin"
    interval = 0.5
    cmd = ["run", "-i", "canrls-sim", "-c", "kill9", "--bus-kwargs", "seed=4",
           "excitation=slow", "--kt", "0.1", "--checkpoint", str(path),
           "--checkpoint-interval", str(interval)]
    with daemon_process(cmd, tmp_path, stdout=subprocess.DEVNULL) as d:
        d.wait_ready()
        time.sleep(2.5)
        d.send(signal.SIGKILL)
        killed = time.time()
        d.proc.wait(10)
    assert d.proc.returncode == -signal.SIGKILL
    cp = load_checkpoint(path)  # intact despite the kill
    assert killed - cp.saved_at <= interval + 0.5  # at most one interval (+ scheduling slack)
    assert cp.state["pipeline"]["samples"] > 500
    leftovers = [p.name for p in tmp_path.iterdir() if p.name.startswith(".cp.bin.tmp")]
    assert len(leftovers) <= 1  # a write cut short leaves at most its temporary file
    # resume from it
    out = subprocess.run([sys.executable, "-m", "canrls", *cmd[:-4], "--checkpoint", str(path),
                          "--duration", "1", "--json"],
                         capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    res = json.loads(out.stdout)
    assert res["daemon"]["resumed_from"] == str(path)
    # the pipeline goes on counting from the checkpoint (res["samples"] counts the samples
    # the equation used, fewer by the filter's warm-ups)
    assert res["daemon"]["samples"] >= cp.state["pipeline"]["samples"]
