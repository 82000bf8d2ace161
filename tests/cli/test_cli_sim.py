"""``canrls sim``: writes a log of the simulated drive."""

from __future__ import annotations

import re
import signal
import subprocess
import time
from pathlib import Path

import can
import numpy as np
import pytest
from cli_tool import python_module

from canrls.can.decoder import Decoder
from canrls.can.frameblock import FrameBlock
from canrls.can.protocol import Protocol
from canrls.cli.main import main
from canrls.sim import simulate


def test_writes_a_candump_log_python_can_reads(tmp_path: Path,
                                               capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "drive.log"
    rc = main(["sim", "--out", str(out), "--duration", "2", "--seed", "3",
               "--effects", "inertia,viscous,coulomb,cogging:24"])
    assert rc == 0
    out_err = capsys.readouterr()
    assert out_err.err == ""  # the truth on stdout: `canrls sim ... > truth.txt` keeps it
    assert out_err.out == (f"canrls sim: wrote 4000 frames to {out} (2 s, scenario standard, "
                           "seed 3); truth: inertia.J=0.0002 viscous.B=0.0001 coulomb.Tc=0.02 "
                           "cogging:24.sin=0.003 cogging:24.cos=0.0015 Kt=0.1\n")
    msgs = list(can.LogReader(str(out)))
    assert len(msgs) == 4000
    assert msgs[0].timestamp == 0.0 and msgs[-1].timestamp == pytest.approx(1.9991)
    block = FrameBlock.from_messages(msgs)
    dec = Decoder(Protocol.load())
    d = dec.decode(block)
    assert dec.rejected.total == 0 and d.accepted == 4000
    # the same frames as simulate() with the same settings
    ref = simulate("standard", seed=3, duration=2.0,
                   effects="inertia,viscous,coulomb,cogging:24").frames
    assert np.array_equal(block.data, ref.data)


def test_faults_and_linear_axis(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "lin.log"
    rc = main(["sim", "--out", str(out), "--duration", "3", "--axis", "linear",
               "--effects", "inertia,viscous,coulomb,electrical", "--param", "coulomb.Tc=4",
               "--faults", "drop=0.01,silence=0.5s@1s"])
    assert rc == 0
    err = capsys.readouterr().out
    assert "scenario standard-linear" in err and "coulomb.Tc=4 " in err and "Kf=20" in err
    assert "faults drop=0.01,silence=0.5s@1s: 6000 frames in" in err
    assert "1000 silenced" in err
    msgs = list(can.LogReader(str(out)))
    t = np.array([m.timestamp for m in msgs])
    assert not np.any((t >= 1.0) & (t < 1.5))


def test_a_machine_says_what_it_wrote_on_stdout(tmp_path: Path,
                                               capsys: pytest.CaptureFixture[str]) -> None:
    """canrls sim --axes N as plain canrls sim: the summary, then each axis's truth, on
    stdout (the first line the answer), nothing on stderr."""
    out = tmp_path / "machine.log"
    assert main(["sim", "--out", str(out), "--duration", "0.2", "--axes", "2",
                 "--seed", "4"]) == 0
    out_err = capsys.readouterr()
    assert out_err.err == ""
    lines = out_err.out.splitlines()
    n = len(list(can.LogReader(str(out))))
    assert lines[0].startswith(f"canrls sim: wrote {n} frames of 2 axes to {out} (0.2 s, "
                               f"scenario standard, seed 4; canrls fit --axes offset:")
    assert len(lines) == 3 and all(" truth: inertia.J=" in x for x in lines[1:])
    # one axis is an axis, not "1 axes"
    assert main(["sim", "--out", str(out), "--duration", "0.2", "--axes", "1"]) == 0
    assert " frames of 1 axis to " in capsys.readouterr().out


def test_other_log_formats(tmp_path: Path) -> None:
    out = tmp_path / "drive.asc"
    assert main(["sim", "--out", str(out), "--duration", "0.1", "--scenario", "poor"]) == 0
    assert len(list(can.LogReader(str(out)))) == 200


@pytest.mark.parametrize(("argv", "message"), [
    (["--faults", "drop=2"], "error: fault spec 'drop=2': drop: probability 2 is not in [0, 1]"),
    (["--effects", "inertia,cogging"], "error: effect 'cogging' needs its order"),
    (["--param", "stribeck.Ts=0.1"], "error: params: 'stribeck.Ts' belongs to effect 'stribeck'"),
    (["--duration", "0"], "error: --duration: 0.0 must be a positive number of seconds"),
])
def test_errors_are_one_line(tmp_path: Path, capsys: pytest.CaptureFixture[str],
                             argv: list[str], message: str) -> None:
    args = ["sim", "--out", str(tmp_path / "x.log"), "--duration", "1", *argv]
    assert main(args) == 1
    err = capsys.readouterr().err
    assert err.startswith(message) and err.count("\n") == 1
    assert not (tmp_path / "x.log").exists()


def test_an_inertia_the_integrator_cannot_afford_is_refused_naming_the_limit(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """Issue 30, 11: -p inertia.J=1e-8 needed 11 minutes for 5 s of drive (a million
    sub-steps per period at standstill). Refused at once, naming the sub-step bound and
    the smallest J, which is then accepted."""
    from cli_tool import cli_error

    from canrls.sim.plant import MAX_SUBSTEPS

    out = tmp_path / "drive.log"
    line = cli_error(capsys, ["sim", "--out", str(out), "--duration", "5", "-p",
                              "inertia.J=1e-8"])
    m = re.search(rf"more than the simulator's {MAX_SUBSTEPS}: give inertia\.J >= (\S+) with",
                  line)
    assert line.startswith("error: inertia.J = 1e-08: ") and m, line
    assert not out.exists()
    assert main(["sim", "--out", str(out), "--duration", "0.5", "-p",
                 f"inertia.J={m.group(1)}"]) == 0


@pytest.mark.parametrize(("sig", "status"), [(signal.SIGTERM, 143), (signal.SIGINT, 130)])
def test_a_signal_inside_the_c_loop_stops_sim_within_a_second(
        tmp_path: Path, sig: signal.Signals, status: int) -> None:
    """Issue 30, 11: SIGTERM was not acted on inside the C loop (a call simulates 65,536
    periods: about a minute at the smallest J). The loop looks at the signals every
    100,000 sub-steps now."""
    out = tmp_path / "long.log"
    # Ctrl-C restored in the child: a background job's SIGINT is ignored, and inherited
    proc = subprocess.Popen(python_module("canrls") + [
        "sim", "--out", str(out), "--duration", "3600", "-p", "inertia.J=5e-7"],
        stderr=subprocess.PIPE, text=True)
    err = ""
    try:
        deadline = time.monotonic() + 120
        while not any(p.name.endswith(".part") for p in tmp_path.iterdir()):
            assert proc.poll() is None and time.monotonic() < deadline, "no temporary seen"
            time.sleep(0.02)
        time.sleep(0.5)  # inside the first call of the C loop
        sent = time.monotonic()
        proc.send_signal(sig)
        try:
            _, err = proc.communicate(timeout=30)
        except subprocess.TimeoutExpired:
            err = f"still running 30 s after {sig.name}, killed; its stderr:\n"
        took = time.monotonic() - sent
    finally:
        if proc.poll() is None:
            proc.kill()
            err += proc.communicate()[1]  # where the signal went, if it went missing
    assert proc.returncode == status, err
    assert took < 1.0, f"{took:.1f} s"
    assert list(tmp_path.iterdir()) == []
