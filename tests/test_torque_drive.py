"""A drive that reports its torque, not its current (CiA 402): no ``--kt``.

The simulated drive (known J, B, Tc) is written frame by frame, through cantools, into
the two TPDOs of ``tests/data/cia402_drive.dbc`` (torque actual value 0x6077 in per mille
of the rated torque, current actual value 0x6078 in per mille of the rated current,
position actual value 0x6064 in encoder increments, velocity actual value 0x606C in
increments per second) and logged with python-can's candump writer. canrls must find
J, B and Tc in N·m units without Kt, as it finds them with Kt on the same run in its own
DBC, and carry the torque mapping and its ratings through ``fit``, ``diagnose``,
``validate``, ``run`` (the daemon on a virtual bus) and ``export-c``.
"""

from __future__ import annotations

import contextlib
import io
import itertools
import json
import math
import os
import shutil
import subprocess
from pathlib import Path
from typing import Any

import can
import cantools
import pytest
from user_drives import CIA402_DBC as DBC
from user_drives import INCREMENTS, RATED_CURRENT, RATED_TORQUE, cia402_log

from canrls.can.frameblock import FrameBlock
from canrls.can.logs import read_frames, write_candump
from canrls.can.protocol import Protocol
from canrls.cli._common import overrides
from canrls.cli.main import build_parser, main
from canrls.cli.run import build_daemon
from canrls.estimation.model import Model
from canrls.live.checkpoint import Checkpoint, fingerprint, load_checkpoint, save_checkpoint
from canrls.processor import FrameProcessor
from canrls.processor.config import load_config, prepare
from canrls.sim.scenario import scenario, simulate

TORQUE = ["torque=TPDO1.TorqueActual", "speed=TPDO2.VelocityActual",
          "position=TPDO2.PositionActual"]
RATINGS = ["--rated-torque", str(RATED_TORQUE), "--increments-per-rev", str(INCREMENTS)]
MAP = ["--dbc", str(DBC), *[a for s in TORQUE for a in ("--signal", s)], *RATINGS]
EFFECTS = "inertia,viscous,coulomb"
_ids = itertools.count()


@pytest.fixture(scope="module")
def drive(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    d = tmp_path_factory.mktemp("cia402")
    res = simulate(scenario("standard", effects=EFFECTS, seed=5, duration=8.0))
    out: dict[str, Any] = {"dir": d, "truth": res.truth.params, "kt": res.truth.kt,
                           "cia": d / "servo.log", "own": d / "own.log", "other": d / "other.log"}
    cia402_log(res, out["cia"])
    write_candump(out["own"], [res.frames])  # the same run in canrls's own DBC
    cia402_log(simulate(scenario("standard", effects=EFFECTS, seed=6, duration=4.0)),
                out["other"])
    return out


@pytest.fixture(scope="module")
def saved(drive: dict[str, Any]) -> Path:
    """``canrls fit --save-model`` of the CiA 402 log."""
    path = drive["dir"] / "servo.json"
    with contextlib.redirect_stdout(io.StringIO()):
        assert main(["fit", str(drive["cia"]), *MAP, "-e", EFFECTS, "--save-model",
                     str(path), "--quiet"]) == 0
    return path


def _json(capsys: pytest.CaptureFixture[str], args: list[str]) -> dict[str, Any]:
    assert main([*args, "--quiet", "--json"]) == 0
    out: dict[str, Any] = json.loads(capsys.readouterr().out)
    return out


def test_the_dbc_says_what_a_cia402_drive_sends() -> None:
    # the [signals] table of a configuration file, ratings included
    table = {"torque": "TPDO1.TorqueActual", "current": "TPDO1.CurrentActual",
             "speed": "TPDO2.VelocityActual", "position": "TPDO2.PositionActual",
             "rated_torque": RATED_TORQUE, "rated_current": RATED_CURRENT,
             "increments_per_rev": INCREMENTS}
    p = Protocol.load(DBC, table)
    assert [(m.name, m.frame_id) for m in p.messages] == [("TPDO1", 0x181), ("TPDO2", 0x281)]
    assert {r: i.unit for r, i in p.roles.items()} == {
        "current": "‰", "speed": "inc/s", "position": "inc", "torque": "‰"}
    assert p.roles["torque"].si_scale == pytest.approx(RATED_TORQUE / 1000)
    assert p.roles["current"].si_scale == pytest.approx(RATED_CURRENT / 1000)
    assert p.roles["speed"].si_scale == pytest.approx(2 * math.pi / INCREMENTS)
    assert p.roles["position"].si_scale == pytest.approx(2 * math.pi / INCREMENTS)
    assert p.period == 1e-3 and p.axis is None  # increments say no axis: rotary by default


def test_the_summary_says_the_speed_the_data_reach_not_the_dbc_limits(
        drive: dict[str, Any], capsys: pytest.CaptureFixture[str]) -> None:
    """The DBC declares ±10,000,000 inc/s (479.4 rad/s); the scaling comes from the
    calibration window, and so does the speed the summary prints."""
    got = _json(capsys, ["fit", str(drive["cia"]), *MAP, "-e", EFFECTS])
    cal = got["calibration"]
    db = cantools.database.load_file(str(DBC))
    tpdo2 = db.get_message_by_name("TPDO2")
    raw = [tpdo2.decode(m.data)["VelocityActual"] for m in can.LogReader(str(drive["cia"]))
           if m.arbitration_id == tpdo2.frame_id][:cal["window"]["samples"]]
    peak = max(abs(v) for v in raw) * 2 * math.pi / INCREMENTS
    assert cal["peaks"]["speed"] == pytest.approx(peak, rel=1e-12)
    assert main(["fit", str(drive["cia"]), *MAP, "-e", EFFECTS, "--quiet"]) == 0
    line = next(ln for ln in capsys.readouterr().out.splitlines()
                if ln.startswith("calibration:"))
    assert f"speed ±{peak:.4g} rad/s" in line
    assert "479.4" not in line and "dbc" not in line


def test_a_utf8_dbc_says_per_mille_as_written(
        drive: dict[str, Any], tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """The same DBC saved in UTF-8 (as some editors write it): '‰' is printed as '‰',
    not 'â€°', and the answer is the cp1252 file's."""
    utf8 = tmp_path / "cia402_utf8.dbc"
    utf8.write_bytes(DBC.read_bytes().decode("cp1252").encode("utf-8"))
    assert "‰".encode() in utf8.read_bytes()
    mapped = [a if a != str(DBC) else str(utf8) for a in MAP]
    assert main(["fit", str(drive["cia"]), *mapped, "-e", EFFECTS, "--quiet"]) == 0
    out = capsys.readouterr().out
    assert "axis rotary (DBC units: speed inc/s, position inc, torque ‰)" in out.splitlines()
    assert "â" not in out
    got = _json(capsys, ["fit", str(drive["cia"]), *mapped, "-e", EFFECTS])
    ref = _json(capsys, ["fit", str(drive["cia"]), *MAP, "-e", EFFECTS])
    assert got["parameters"] == ref["parameters"]


def test_fit_finds_the_drive_in_newton_metres_without_kt(
        drive: dict[str, Any], capsys: pytest.CaptureFixture[str]) -> None:
    got = _json(capsys, ["fit", str(drive["cia"]), *MAP, "-e", EFFECTS])
    own = _json(capsys, ["fit", str(drive["own"]), "--kt", str(drive["kt"]), "-e", EFFECTS])
    assert got["unit"] == "N·m" and got["equations"]["mechanical"]["unit"] == "N·m"
    assert got["axis"]["output"] == "the torque the drive reports, TPDO1.TorqueActual [N·m], " \
                                    "no Kt"
    assert got["axis"]["ratings"] == {"rated_torque": RATED_TORQUE,
                                      "increments_per_rev": INCREMENTS}
    units = {"inertia.J": "kg·m²", "viscous.B": "N·m·s/rad", "coulomb.Tc": "N·m"}
    for name, p in got["parameters"].items():
        assert p["unit"] == units[name]
        # the truth, within 3 sigma
        assert abs(p["value"] - drive["truth"][name]) <= 3 * p["sigma"], (name, p)
        # what canrls finds with Kt on the same run in its own DBC, within the two sigmas
        q = own["parameters"][name]
        assert abs(p["value"] - q["value"]) <= p["sigma"] + q["sigma"], (name, p, q)
        assert q["unit"] == p["unit"]
    assert got["fit_percent"] > 99


def test_the_text_names_the_output_and_the_ratings(
        drive: dict[str, Any], capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["fit", str(drive["cia"]), *MAP, "-e", EFFECTS, "--quiet"]) == 0
    out = capsys.readouterr().out
    assert "axis rotary (DBC units: speed inc/s, position inc, torque ‰)" in out
    assert "ratings: rated torque 0.32 N·m, 131072 increments per revolution" in out
    assert "mechanical output: the torque the drive reports, TPDO1.TorqueActual [N·m], " \
           "no Kt" in out


@pytest.mark.parametrize("drop, message", [
    ("--rated-torque", "TPDO1.TorqueActual: unit '‰' of the torque signal is per mille of "
                       "the rated torque: give --rated-torque VALUE (N·m; linear axis: N) "
                       "or rated_torque = VALUE in [signals]"),
    ("--increments-per-rev", "TPDO2.VelocityActual: unit 'inc/s' of the speed signal is in "
                             "encoder increments: give --increments-per-rev VALUE"),
])
def test_a_missing_rating_names_the_signal_and_the_flag(
        drive: dict[str, Any], drop: str, message: str,
        capsys: pytest.CaptureFixture[str]) -> None:
    i = MAP.index(drop)
    args = MAP[:i] + MAP[i + 2:]
    assert main(["fit", str(drive["cia"]), *args, "--quiet"]) == 1
    assert capsys.readouterr().err.startswith(f"error: {message}")


@pytest.mark.parametrize("args, message", [
    (["--kt", "0.1"], "--kt 0.1: the drive reports its torque (TPDO1.TorqueActual), the "
                      "mechanical output: the parameters come out in N·m (linear axis: N) "
                      "without Kt; leave Kt out"),
    (["--rated-torque", "-0.32"], "--rated-torque -0.32: must be a positive number "
                                  "(N·m; linear axis: N)"),
    (["--signal", "current=TPDO1.CurrentActual"],
     "TPDO1.CurrentActual: unit '‰' of the current signal is per mille of the rated "
     "current: give --rated-current VALUE (A)"),
])
def test_mistakes_with_a_torque_signal_name_the_flag(
        drive: dict[str, Any], args: list[str], message: str,
        capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["fit", str(drive["cia"]), *MAP, *args, "--quiet"]) == 1
    assert capsys.readouterr().err.startswith(f"error: {message}")


def test_the_configuration_file_gives_the_same_mapping_and_ratings(
        drive: dict[str, Any], tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    flags = _json(capsys, ["fit", str(drive["cia"]), *MAP, "-e", EFFECTS])
    # current and torque both mapped: the torque stays the mechanical output, so the
    # mechanical parameters are the same bit for bit
    toml = tmp_path / "servo.toml"
    toml.write_text(f"""\
[model]
effects = {EFFECTS.split(",")!r}
[can]
dbc = "{DBC}"
[signals]
torque = "TPDO1.TorqueActual"
current = "TPDO1.CurrentActual"
speed = "TPDO2.VelocityActual"
position = "TPDO2.PositionActual"
rated_torque = {RATED_TORQUE}
rated_current = {RATED_CURRENT}
increments_per_rev = {INCREMENTS}
""")
    both = _json(capsys, ["fit", str(drive["cia"]), "--config", str(toml)])
    assert both["parameters"] == flags["parameters"]
    assert both["axis"]["units"]["current"] == "‰"
    # ... unless the file says to identify on the current, with Kt
    text = toml.read_text().replace("[model]\n", f"[model]\noutput = \"current\"\n"
                                                 f"kt = {drive['kt']}\n")
    toml.write_text(text)
    on_current = _json(capsys, ["fit", str(drive["cia"]), "--config", str(toml)])
    assert "output" not in on_current["axis"]
    for name, p in on_current["parameters"].items():
        q = flags["parameters"][name]
        assert abs(p["value"] - q["value"]) <= p["sigma"] + q["sigma"], (name, p, q)
    toml.write_text(text.replace(f"rated_current = {RATED_CURRENT}", "rated_current = 0"))
    assert main(["fit", str(drive["cia"]), "--config", str(toml), "--quiet"]) == 1
    assert capsys.readouterr().err.startswith(
        f"error: {toml}: signals.rated_current = 0: must be a positive number (A)")


def test_diagnose_names_the_missing_friction_in_newton_metres(
        drive: dict[str, Any], capsys: pytest.CaptureFixture[str]) -> None:
    d = _json(capsys, ["diagnose", str(drive["cia"]), *MAP, "-e", "inertia,viscous"])
    assert d["unit"] == "N·m" and d["suggestion"]["add"] == ["coulomb"]
    c = d["candidates"][0]
    assert c["parameters"]["coulomb.Tc"]["unit"] == "N·m"
    assert c["parameters"]["coulomb.Tc"]["value"] == pytest.approx(
        drive["truth"]["coulomb.Tc"], rel=0.01)
    # where it fails is binned by the torque (the output's signal), not by a current
    quantities = {r["quantity"] for r in d["regions"]}
    assert "current" not in quantities and quantities <= {
        "speed", "position", "torque", "acceleration", "time"}


def test_validate_reuses_the_saved_torque_mapping_and_ratings(
        drive: dict[str, Any], saved: Path, capsys: pytest.CaptureFixture[str]) -> None:
    model = json.loads(saved.read_text())
    assert model["model"]["output"] == "torque" and "kt" not in model["model"]
    assert model["configuration"]["signals"] == {"rated_torque": RATED_TORQUE,
                                                 "increments_per_rev": INCREMENTS}
    assert model["configuration"]["signal_overrides"] == TORQUE
    assert model["fit"]["mechanical"]["unit"] == "N·m"
    # another run of the drive, no --dbc, --signal or ratings: the file's
    v = _json(capsys, ["validate", str(drive["other"]), "--model", str(saved)])
    eq = v["equations"]["mechanical"]
    assert eq["unit"] == "N·m" and eq["fit_percent"] > 99
    assert main(["validate", str(drive["other"]), "--model", str(saved), "--kt", "0.1",
                 "--quiet"]) == 1
    assert "--kt 0.1 (saved: None)" in capsys.readouterr().err


def test_the_daemon_reads_the_tpdos_from_a_bus(drive: dict[str, Any],
                                              capsys: pytest.CaptureFixture[str]) -> None:
    offline = _json(capsys, ["fit", str(drive["cia"]), *MAP, "-e", EFFECTS])["parameters"]
    ch = f"test-torque-{os.getpid()}-{next(_ids)}"
    args = build_parser("run").parse_args(["run", "-i", "virtual", "-c", ch, *MAP,
                                           "-e", EFFECTS, "--publish-interval", "0.05"])
    d = build_daemon(args)
    frames = FrameBlock.concat(read_frames(drive["cia"])).to_messages()
    sender = can.Bus(interface="virtual", channel=ch, preserve_timestamps=True,
                     ignore_config=True)
    try:
        d.start()
        for m in frames:
            sender.send(m)
        assert d.wait_for(lambda x: x.stats().frames == len(frames), 120)
    finally:
        d.stop()
        sender.shutdown()
    live = d.estimates()
    assert live.equations[0].unit == "N·m"
    for p in live.parameters:
        assert p.unit == offline[p.name]["unit"]
        assert p.value == pytest.approx(offline[p.name]["value"], rel=1e-9), p.name


def test_a_checkpoint_of_the_daemon_keeps_the_torque(drive: dict[str, Any],
                                                    tmp_path: Path) -> None:
    args = build_parser("run").parse_args(["run", *MAP, "-e", EFFECTS])
    cfg = load_config(None, overrides(args))
    protocol, model, settings = prepare(cfg)
    frames = FrameBlock.concat(read_frames(drive["cia"]))
    whole = FrameProcessor(protocol, model, settings)
    whole.process(frames)
    a = FrameProcessor(protocol, model, settings)
    a.process(frames.take(slice(0, 6000)))  # 3 s: past the calibration window
    cp = Checkpoint(model=json.loads(json.dumps(a.model.to_dict())),
                    config_model=json.loads(json.dumps(model.to_dict())),
                    fingerprint=fingerprint(settings, a.dt), state=a.state(), counters={},
                    saved_at=0.0)
    save_checkpoint(tmp_path / "cp.bin", cp)
    cp = load_checkpoint(tmp_path / "cp.bin")
    assert cp.model["output"] == "torque" and "torque" in cp.state["window"]
    assert "current" not in cp.state["window"]
    b = FrameProcessor(protocol, model, settings)
    b.restore(cp.state, Model.from_dict(cp.model))
    b.process(frames.take(slice(6000, None)))
    assert b.calibration == a.calibration
    for p, q in zip(b.pipeline.estimates().parameters, whole.pipeline.estimates().parameters,
                    strict=True):
        # the filter restarts at the restore: the same drive, within sigma
        assert p.unit == q.unit and abs(p.value - q.value) <= q.sigma, (p, q)


def test_export_c_states_the_torque_output_and_its_scaling(saved: Path, tmp_path: Path) -> None:
    out = tmp_path / "c"
    with contextlib.redirect_stdout(io.StringIO()):
        assert main(["export-c", "--model", str(saved), "--out", str(out)]) == 0
    h = (out / "canrls_config.h").read_text()
    assert "/* output y: motor torque T reported by the drive [N·m], no Kt" in h
    assert "#define CANRLS_MECHANICAL_OUTPUT_TORQUE 1" in h
    assert f"relative to rated_torque = {RATED_TORQUE!r} N·m" in h
    assert f"torque [N·m] = raw * {RATED_TORQUE / 1000!r};" in h
    c = (out / "canrls_config.c").read_text()
    assert 'canrls_mechanical_output_signal[] = "TPDO1.TorqueActual";' in c
    assert 'canrls_mechanical_output_unit[] = "\\342\\200\\260";' in c  # ‰ in UTF-8
    gcc = shutil.which("gcc")
    if gcc is None:
        pytest.skip("gcc not installed")
    f = out / "canrls_config.c"  # the kernel and the frame codecs: tests/firmware/test_c_export.py
    subprocess.run([gcc, "-std=c99", "-O2", "-Wall", "-Wextra", "-Werror", "-pedantic", "-c",
                    str(f), "-o", str(f.with_suffix(".o"))], check=True, capture_output=True)


def test_the_outputs_old_c_names_stay_one_release_as_aliases(saved: Path, tmp_path: Path) -> None:
    """The exported header called the output y "target"; firmware that uses those names
    still compiles (deprecated aliases of the new ones), to the same values."""
    gcc = shutil.which("gcc")
    if gcc is None:
        pytest.skip("gcc not installed")
    out = tmp_path / "c"
    with contextlib.redirect_stdout(io.StringIO()):
        assert main(["export-c", "--model", str(saved), "--out", str(out)]) == 0
    h = (out / "canrls_config.h").read_text()
    old = h.index("#define CANRLS_MECHANICAL_TARGET_EXP")
    assert h.index("Deprecated: the names of the output y") < old
    prog = tmp_path / "old.c"
    prog.write_text('#include <stdio.h>\n#include "canrls_config.h"\n'
                    "int main(void) {\n"
                    "    printf(\"%d %d %d %s %s\\n\", CANRLS_MECHANICAL_TARGET_EXP,\n"
                    "           CANRLS_MECHANICAL_TARGET_EXP == CANRLS_MECHANICAL_OUTPUT_EXP,\n"
                    "           CANRLS_MECHANICAL_TARGET_TORQUE, canrls_mechanical_target_signal,\n"
                    "           &canrls_mechanical_target_unit[0]\n"
                    "           == &canrls_mechanical_output_unit[0]\n"
                    "           ? \"same\" : \"other\");\n    return 0;\n}\n")
    exe = tmp_path / "old"
    subprocess.run([gcc, "-std=c99", "-Wall", "-Wextra", "-Werror", "-pedantic", "-I", str(out),
                    str(prog), str(out / "canrls_config.c"), str(out / "canrls_fixed.c"),
                    "-o", str(exe)], check=True, capture_output=True)
    s_y = h.split("#define CANRLS_MECHANICAL_OUTPUT_EXP ")[1].split()[0]
    run = subprocess.run([str(exe)], check=True, capture_output=True, text=True)
    assert run.stdout.split() == [s_y, "1", "1", "TPDO1.TorqueActual", "same"]
