"""One pipeline, live and offline: the daemon fed a log over a bus gives `canrls fit`'s answer.

The log's frames go onto a python-can virtual bus with their own timestamps
(``preserve_timestamps``), the daemon listens on that bus as on a real one, and a tool on
the same bus keeps the parameter frames the daemon publishes. The daemon's estimates are
those of the front end fed the same frames, bit for bit; the published parameters (float
and fixed point) are within 1 % of what ``canrls fit LOG --json`` prints for the log.
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import pytest
from daemon_tool import daemon_fed

from canrls.can.estimator_frames import FrameDecoder
from canrls.can.frameblock import FrameBlock
from canrls.can.logs import read_frames, write_candump
from canrls.cli.main import main
from canrls.processor import FrameProcessor
from canrls.processor.config import AppConfig
from canrls.sim.scenario import scenario, simulate

EFFECTS = "inertia,viscous,coulomb,offset,cogging:6"


@pytest.fixture(scope="module")
def log(tmp_path_factory: pytest.TempPathFactory) -> Path:
    res = simulate(scenario("standard", effects=EFFECTS, seed=5, duration=20.0))
    path = tmp_path_factory.mktemp("one") / "drive.log"
    write_candump(path, [res.frames])
    return path


def _setup() -> tuple:
    cfg = AppConfig()
    cfg.model = {"effects": EFFECTS.split(","), "kt": 0.1}
    protocol = cfg.protocol()
    return protocol, cfg.model_for(protocol), cfg.settings()


def test_daemon_fed_the_log_over_a_bus_gives_the_offline_answer(
        log: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["fit", str(log), "--kt", "0.1", "--effects", EFFECTS, "--json",
                 "--quiet"]) == 0
    offline = json.loads(capsys.readouterr().out)["parameters"]

    protocol, model, settings = _setup()
    frames = FrameBlock.concat(read_frames(log)).to_messages()
    # a publication after the last frame carries the final estimates
    with daemon_fed(protocol, model, settings, frames, "test-one-pipeline",
                    publications=2) as (d, reader):
        pass
    dec = FrameDecoder(units={p.name: p.unit for p in model.parameters})
    while (m := reader.get_message(0.0)) is not None:
        dec.feed(m)
    published = {p.name: p for p in dec.table()}

    # in process, the same timestamped frames: bit for bit
    proc = FrameProcessor(protocol, model, settings)
    proc.process(FrameBlock.from_messages(frames))
    live = d.estimates()
    assert d.processor.calibration == proc.calibration
    for a, b in zip(live.parameters, proc.pipeline.estimates().parameters, strict=True):
        assert (a.name, a.value, a.sigma, a.fixed) == (b.name, b.value, b.sigma, b.fixed)

    # over the bus: every published parameter within 1 % of canrls fit's (float, fixed)
    assert set(published) == set(offline)
    for name, want in offline.items():
        got = published[name]
        assert got.float_value == pytest.approx(want["value"], rel=0.01), name
        assert got.fixed_value == pytest.approx(want["fixed"], rel=0.01), name


def test_calibration_is_the_same_whatever_the_blocks(log: Path) -> None:
    """The calibration window is counted in samples: any cut of the stream into blocks
    (a live bus delivers them as they come) freezes the same decision."""
    protocol, model, settings = _setup()
    whole = FrameBlock.concat(read_frames(log))
    cals = []
    for size in (1, 7, 1000, len(whole)):
        proc = FrameProcessor(protocol, model, settings)
        for k in range(0, min(len(whole), 6000 if size < 100 else len(whole)), size):
            proc.process(whole.take(slice(k, k + size)))
        if size < 100:
            proc.process(whole.take(slice(6000, len(whole))))
        cals.append((proc.calibration, proc.model.exponents))
    assert all(c == cals[0] for c in cals[1:])
    assert cals[0][0] is not None


def test_an_effect_added_live_keeps_the_frozen_normalisation(log: Path) -> None:
    protocol, model, settings = _setup()
    base = model.with_effects(remove=["cogging:6"])
    proc = FrameProcessor(protocol, base, settings)
    blocks = list(read_frames(log, 4000))
    for b in blocks[:3]:
        proc.process(b)
    before = dict(proc.model.exponents["mechanical"])
    t0 = time.monotonic()
    proc.with_model(proc.model.with_effects(add=["cogging:6"]))
    assert time.monotonic() - t0 < 30
    after = proc.model.exponents["mechanical"]
    assert {k: after[k] for k in before} == before  # shared columns keep theirs
    assert "cogging:6.sin" in after and "cogging:6.cos" in after
    for b in blocks[3:]:
        proc.process(b)
    est = proc.pipeline.estimates()
    assert est["cogging:6.sin"].value == pytest.approx(0.003, rel=0.05)
