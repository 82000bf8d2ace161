"""The daemon's journal: in text mode ``canrls run`` says, while it runs, that it
publishes (bus, axis, model), and each model change and fault, one flushed line each."""

from __future__ import annotations

import io
import os
import queue
import threading
from pathlib import Path

import pytest
from daemon_tool import DaemonTool, daemon_process

from canrls.can.estimator_frames import CommandCode, EffectId, StatusReport, encode_command
from canrls.live.daemon import Daemon, DaemonSettings
from canrls.live.journal import Journal, to_stream
from canrls.processor.config import AppConfig


def _model() -> tuple:
    cfg = AppConfig()
    cfg.model = {"effects": ["inertia", "viscous", "coulomb"], "kt": 0.1}
    protocol = cfg.protocol()
    return protocol, cfg.model_for(protocol), cfg.settings()


def test_run_says_it_publishes_while_it_runs(tmp_path: Path) -> None:
    """The first line comes while the daemon runs (not at its exit): it is flushed."""
    lines: queue.Queue[str] = queue.Queue()
    with daemon_process(["run", "-i", "canrls-sim", "-c", "standard", "--bus-kwargs",
                         "seed=1", "--kt", "0.1", "--duration", "120"], tmp_path) as d:

        def first_line() -> None:
            assert d.proc.stdout is not None
            lines.put(d.proc.stdout.readline())

        reader = threading.Thread(target=first_line, name="stdout reader")
        reader.start()
        try:
            line = lines.get(timeout=60)
            assert d.proc.poll() is None, "the line came only at the exit"
        finally:
            out, err = d.stop()
            reader.join()
    assert d.proc.returncode == 0, err
    assert line == ("canrls: publishing on canrls simulated drive, channel standard: rotary "
                    "axis, model inertia,viscous,coulomb (3 parameters)\n")
    assert "publishing" not in out  # once
    assert out.splitlines()[0].startswith("parameter ")  # then the estimates at the exit


def test_model_changes_are_journaled() -> None:
    protocol, model, settings = _model()
    ch = f"test-journal-{os.getpid()}"
    tool = DaemonTool(ch)
    d = Daemon(protocol, model, settings,
               DaemonSettings(publish_interval=0.05, commands=True),
               bus={"interface": "virtual", "channel": ch})
    text = io.StringIO()
    try:
        with to_stream(text):
            d.start()
            assert tool.command(encode_command(CommandCode.ADD_EFFECT, EffectId.COGGING,
                                               6)) is not None
            assert d.wait_for(lambda dd: dd.publisher.publications > 1, 10)
            d.stop()
    finally:
        d.stop()
        tool.close()
    lines = text.getvalue().splitlines()
    assert ("canrls: command add_effect cogging:6: model is now "
            "inertia,viscous,coulomb,cogging:6 (5 parameters); estimation restarts") in lines
    assert sum(ln.startswith("canrls: publishing on ") for ln in lines) == 1


def test_faults_begin_and_end_once(caplog: pytest.LogCaptureFixture) -> None:
    _, model, _ = _model()
    j = Journal()
    caplog.set_level("INFO", logger="canrls.live.journal")
    for status in (StatusReport(), StatusReport(diverged=True), StatusReport(diverged=True),
                   StatusReport(diverged=True, implausible=True, saturation=True),
                   StatusReport(implausible=True), StatusReport()):
        j.published("virtual channel x", model, status)
    assert [r.getMessage() for r in caplog.records] == [
        "publishing on virtual channel x: rotary axis, model inertia,viscous,coulomb "
        "(3 parameters)",
        "fault: the fixed-point estimate diverged from the float reference",
        "fault: an estimate that physics rules out",
        "fault ended: the fixed-point estimate diverged from the float reference",
        "fault ended: an estimate that physics rules out",
    ]
    assert [r.levelname for r in caplog.records] == ["INFO", "WARNING", "WARNING", "INFO",
                                                     "INFO"]
