"""Physics that cannot be is named with its likely cause; a message that never comes too.

A drive whose current is read with the wrong sign fits as well as one read right, with
every parameter negated: ``fit``, ``diagnose``, ``validate`` and the daemon's health
frame say so and name the sign. A mapped message the log never carries is named with
its ID instead of ending in "too few usable samples".
"""

from __future__ import annotations

import itertools
import json
import os
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import can
import pytest
from daemon_tool import DaemonTool

from canrls.can.estimator_frames import FrameDecoder
from canrls.can.frameblock import FrameBlock
from canrls.can.logs import read_frames, write_log
from canrls.can.protocol import Protocol
from canrls.cli.main import build_parser, main
from canrls.cli.run import build_daemon
from canrls.estimation.physics import check_physics
from canrls.sim.scenario import Simulator, scenario

HEADER = 'VERSION ""\n\nNS_ :\n\nBS_:\n\n'
DBC = HEADER + '''BU_: Drive

BO_ 641 Feedback: 8 Drive
 SG_ Current : 0|32@1- (0.001,0) [-100|100] "A" Vector__XXX
 SG_ Speed : 32|32@1- (0.01,0) [-20000|20000] "rpm" Vector__XXX

BO_ 642 Angle: 4 Drive
 SG_ Angle : 0|32@1+ (0.01,0) [0|360] "deg" Vector__XXX
'''
SIGNALS = ["speed=Feedback.Speed", "position=Angle.Angle"]
EFFECTS = "inertia,viscous,coulomb"
_ids = itertools.count()


@pytest.fixture(scope="module")
def drive(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    d = tmp_path_factory.mktemp("physics")
    dbc = d / "drive.dbc"
    dbc.write_text(DBC)
    proto = Protocol.load(dbc, ["current=Feedback.Current", *SIGNALS])
    log = d / "drive.log"
    write_log(log, Simulator(scenario("standard", seed=8, duration=8.0),
                             protocol=proto).frames())
    return {"dbc": dbc, "log": log, "dir": d}


def _flags(drive: dict[str, Path], sign: str) -> list[str]:
    return ["--dbc", str(drive["dbc"]), "--signal", f"current=Feedback.Current{sign}",
            *[a for s in SIGNALS for a in ("--signal", s)], "--kt", "0.1", "-e", EFFECTS]


def _json(capsys: pytest.CaptureFixture[str], argv: list[str]) -> dict[str, Any]:
    capsys.readouterr()
    assert main([*argv, "--quiet", "--json"]) == 0
    out: dict[str, Any] = json.loads(capsys.readouterr().out)
    return out


def test_a_flipped_current_is_named_in_fit_diagnose_and_validate(
        drive: dict[str, Path], capsys: pytest.CaptureFixture[str]) -> None:
    right = _json(capsys, ["fit", str(drive["log"]), *_flags(drive, "")])
    assert right["implausible"] == []
    saved = drive["dir"] / "flipped.json"
    fit = _json(capsys, ["fit", str(drive["log"]), *_flags(drive, ":-1"),
                         "--save-model", str(saved)])
    assert fit["fit_percent"] > 90  # it fits as well as the right one
    named = {i["parameter"]: i for i in fit["implausible"]}
    assert set(named) == {"inertia.J", "viscous.B", "coulomb.Tc"}
    assert all("sign" in i["cause"] and ":-1" in i["cause"] for i in named.values())
    # the text says it once, with the cause
    capsys.readouterr()
    assert main(["fit", str(drive["log"]), *_flags(drive, ":-1"), "--quiet"]) == 0
    lines = [ln for ln in capsys.readouterr().out.splitlines()
             if ln.startswith("PHYSICS THAT CANNOT BE")]
    assert len(lines) == 1 and "inertia.J" in lines[0] and "sign" in lines[0]
    diag = _json(capsys, ["diagnose", str(drive["log"]), *_flags(drive, ":-1")])
    assert {i["parameter"] for i in diag["implausible"]} == set(named)
    val = _json(capsys, ["validate", str(drive["log"]), "--model", str(saved)])
    assert {i["parameter"] for i in val["implausible"]} == set(named)


@dataclass
class _P:
    name: str
    value: float
    sigma: float
    identifiable: bool = True


def test_the_rules_and_their_causes() -> None:
    # friction a little negative within 3 sigma is noise, not a finding
    assert check_physics([_P("viscous.B", -1e-6, 1e-6), _P("inertia.J", 1e-4, 1e-6)]) == ()
    # an inertia alone not positive: not the sign (the others are fine), a delay or unit
    (j,) = check_physics([_P("inertia.J", -1e-5, 1e-6), _P("viscous.B", 1e-4, 1e-6),
                          _P("coulomb.Tc", 0.02, 1e-4)])
    assert j.parameter == "inertia.J" and "delay" in j.cause and "sign" not in j.cause
    # a parameter the data cannot identify says nothing
    assert check_physics([_P("inertia.J", -1e-5, 1e-6, identifiable=False)]) == ()
    # a torque constant far from the back-EMF constant the voltage shows
    (kt,) = check_physics([_P("electrical.Ke", 0.1, 1e-4)], kt=0.001)
    assert kt.parameter == "kt" and "--kt" in kt.cause
    assert check_physics([_P("electrical.Ke", 0.1, 1e-4)], kt=0.12) == ()


def test_the_health_frame_flags_it(drive: dict[str, Path]) -> None:
    ch = f"test-physics-{os.getpid()}-{next(_ids)}"
    args = build_parser("run").parse_args(["run", "-i", "virtual", "-c", ch,
                                           *_flags(drive, ":-1"),
                                           "--publish-interval", "0.05"])
    d = build_daemon(args)
    frames = FrameBlock.concat(read_frames(drive["log"])).to_messages()
    sender = can.Bus(interface="virtual", channel=ch, preserve_timestamps=True,
                     ignore_config=True)
    tool = DaemonTool(ch)
    try:
        d.start()
        for m in frames:
            sender.send(m)
        assert d.wait_for(lambda x: x.stats().frames == len(frames), 120)
        dec = FrameDecoder()
        end = time.monotonic() + 30
        while time.monotonic() < end and not (dec.status and dec.status.implausible):
            dec.feed_all(tool.take())
            time.sleep(0.05)
        assert dec.status is not None and dec.status.implausible
        assert "implausible" in dec.status.flags
    finally:
        d.stop()
        sender.shutdown()
        tool.close()


def test_a_mapped_message_that_never_occurs_is_named(
        drive: dict[str, Path], capsys: pytest.CaptureFixture[str]) -> None:
    log = drive["dir"] / "no_angle.log"
    log.write_text("".join(ln for ln in drive["log"].read_text().splitlines(True)
                           if "282#" not in ln))
    capsys.readouterr()
    assert main(["fit", str(log), *_flags(drive, ""), "--quiet"]) == 1
    err = capsys.readouterr().err
    assert "Angle (0x282: position) never occurs" in err
    assert "Feedback" in err and "frames" in err and "too few usable samples" not in err


def test_a_message_whose_frames_all_decode_out_of_range_is_not_said_to_never_occur(
        drive: dict[str, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """A huge scale factor on the current: its frames arrive, every one outside the
    signal's range; the error says so, with their number and the signal, not "never
    occurs"."""
    dbc = tmp_path / "huge.dbc"
    dbc.write_text(DBC.replace("(0.001,0) [-100|100]", "(1e+30,0) [-100|100]"))
    n = drive["log"].read_text().count("281#")
    assert n > 0
    capsys.readouterr()
    flags = ["--dbc", str(dbc), *_flags(drive, "")[2:]]
    assert main(["fit", str(drive["log"]), *flags, "--quiet"]) == 1
    err = capsys.readouterr().err
    assert err.startswith("error: ") and err.count("\n") == 1, err
    assert (f"mapped message Feedback (0x281: current, speed) arrives but decodes no frame: "
            f"every one of its {n} frames is rejected (range {n}; e.g. Feedback.Current = "
            in err), err
    assert "A outside [-100, 100]" in err and "never occur" not in err
