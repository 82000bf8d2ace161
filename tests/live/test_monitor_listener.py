"""The live monitor: decoding, units, trend, text and JSON views, the CLI."""

from __future__ import annotations

import itertools
import json
import os
import sys
from pathlib import Path

import can
import pytest
from cli_tool import cli_error

from canrls.can.estimator_frames import (
    CommandCode,
    CommandResult,
    ParameterReport,
    StatusReport,
    encode_ack,
    encode_param_info,
    encode_parameters,
    encode_status,
)
from canrls.cli.main import main
from canrls.core.effect_names import EffectId, EquationId
from canrls.core.errors import ConfigError
from canrls.live.daemon import Daemon
from canrls.live.daemon_settings import DaemonSettings
from canrls.live.monitor_listener import LibraryUnits, Monitor, parse_command_text
from canrls.processor.config import AppConfig

_ids = itertools.count()


def _reports() -> list[ParameterReport]:
    return [
        ParameterReport(0, effect_id=EffectId.INERTIA, fixed_value=2.01e-4, sigma=1e-7,
                        float_value=2e-4),
        ParameterReport(1, effect_id=EffectId.COGGING, component=1, order=6,
                        fixed_value=0.0015, sigma=2e-5, float_value=0.0016),
        ParameterReport(2, effect_id=EffectId.ELECTRICAL, component=0,
                        equation=EquationId.ELECTRICAL, fixed_value=None, valid=False,
                        sigma=None, float_value=0.5),
    ]


def test_library_units() -> None:
    u = LibraryUnits({"axis": "rotary"}, kt_known=True)
    assert u["inertia.J"] == "kg·m²" and u["cogging:24.sin"] == "N·m"
    assert u.get("nonsense.x") is None and "nonsense.x" not in u
    assert LibraryUnits({"axis": "rotary"}, kt_known=False)["coulomb.Tc"] == "A"
    assert LibraryUnits({"axis": "linear"})["viscous.B"] == "N·s/m"
    assert u.output_unit() == "N·m"


def test_snapshot_of_a_publication() -> None:
    mon = Monitor(units=LibraryUnits({"axis": "rotary"}), source="virtual:x")
    assert not mon.snapshot().complete
    reps = _reports()
    frames = encode_param_info(reps) + encode_parameters(reps, 1)
    for k, rms in enumerate([0.008, 0.006, 0.004, 0.002]):
        st = StatusReport(residual_rms=rms, update_count=100 * k, low_excitation=True,
                          active_effects=StatusReport.effect_mask([1, 7, 8]),
                          frames_lost=3, divergence=0.01)
        frames += encode_status(st, k)
    frames.append(encode_ack(4, CommandResult.OK, 1))
    frames.append(can.Message(arbitration_id=0x101, is_extended_id=False, data=bytes(8)))
    for m in frames:
        mon.on_message_received(m)
    v = mon.snapshot()
    assert v.complete and v.count == 3
    assert [p.name for p in v.parameters] == ["inertia.J", "cogging:6.cos", "electrical.R"]
    assert [p.unit for p in v.parameters] == ["kg·m²", "N·m", "Ω"] or \
        v.parameters[2].unit  # electrical unit from the library, whatever its spelling
    assert v.rms_trend == pytest.approx(0.002 / 0.008 - 1.0)
    assert v.totals["feedback"] == 1 and v.totals["estimator"] == len(frames) - 1
    text = v.format()
    for piece in ("inertia.J", "kg·m²", "cogging:6.cos", "residual RMS 0.002 N·m", "↓ -75 %",
                  "low_excitation", "lost 3", "inertia, cogging, electrical",
                  "last command: add_effect -> ok"):
        assert piece in text, piece
    assert "-0.5" not in text and "  -  " in text  # the invalid fixed value shows as '-'
    d = v.to_dict()
    assert d["parameters"]["inertia.J"]["fixed"] == pytest.approx(2.01e-4, rel=1e-6)
    assert d["flags"] == ["low_excitation"] and d["last_ack"]["result"] == "ok"
    json.dumps(d)


def test_parse_command_text() -> None:
    assert parse_command_text("add cogging:6") == (CommandCode.ADD_EFFECT, EffectId.COGGING,
                                                   6, 0.0)
    assert parse_command_text("remove unbalance")[:2] == (CommandCode.REMOVE_EFFECT,
                                                          EffectId.UNBALANCE)
    assert parse_command_text("lambda 0.999")[3] == 0.999
    assert parse_command_text(" reset ")[0] is CommandCode.RESET
    for bad in ("", "jump", "add", "add cogging", "add nothing", "lambda 2", "reset now"):
        with pytest.raises(ConfigError):
            parse_command_text(bad)


@pytest.fixture
def running_daemon() -> tuple[Daemon, str]:
    cfg = AppConfig()
    cfg.model = {"effects": ["inertia", "viscous", "coulomb"], "kt": 0.1}
    protocol = cfg.protocol()
    ch = f"test-monitor-{os.getpid()}-{next(_ids)}"
    sim = dict(interface="canrls-sim", channel=ch, seed=5, excitation="slow", realtime=False,
               start_time=0.0, duration=20.0)
    d = Daemon(protocol, cfg.model_for(protocol), cfg.settings(),
               DaemonSettings(publish_interval=0.05, info_interval=0.2, commands=True),
               bus=sim,
               backpressure=True)
    d.start()
    try:
        yield d, ch
    finally:
        d.stop()


def test_cli_once_plain_and_json(running_daemon: tuple[Daemon, str],
                                 capsys: pytest.CaptureFixture[str]) -> None:
    d, ch = running_daemon
    assert main(["monitor", "-i", "virtual", "-c", ch, "--kt", "0.1", "--once",
                 "--timeout", "30"]) == 0
    out = capsys.readouterr().out
    for piece in ("canrls monitor  virtual:" + ch, "inertia.J", "kg·m²", "coulomb.Tc",
                  "residual RMS", "health:", "frames/s:", "feedback"):
        assert piece in out, piece
    assert "\x1b[" not in out  # not a terminal: plain text
    assert main(["monitor", "-i", "virtual", "-c", ch, "--kt", "0.1", "--once", "--json"]) == 0
    res = json.loads(capsys.readouterr().out)
    assert set(res["parameters"]) == {"inertia.J", "viscous.B", "coulomb.Tc"}
    assert res["parameters"]["coulomb.Tc"]["unit"] == "N·m"
    assert res["rates"]["estimator"] > 0


def test_cli_command_and_duration(running_daemon: tuple[Daemon, str],
                                  capsys: pytest.CaptureFixture[str]) -> None:
    d, ch = running_daemon
    assert main(["monitor", "-i", "virtual", "-c", ch, "--command", "add offset"]) == 0
    assert capsys.readouterr().out.strip() == "add_effect: ok"
    assert d.model.effect_names[-1] == "offset"
    assert main(["monitor", "-i", "virtual", "-c", ch, "--command", "add offset"]) == 1
    assert "not_applicable" in capsys.readouterr().out
    assert main(["monitor", "-i", "virtual", "-c", ch, "--duration", "0.5",
                 "--interval", "0.2"]) == 0
    out = capsys.readouterr().out
    assert out.count("canrls monitor") >= 2 and "offset.T0" in out


def test_cli_once_times_out_without_a_daemon(capsys: pytest.CaptureFixture[str]) -> None:
    ch = f"test-monitor-empty-{os.getpid()}"
    assert main(["monitor", "-i", "virtual", "-c", ch, "--once", "--timeout", "0.3"]) == 1
    assert "no complete publication" in capsys.readouterr().err


def test_cli_on_a_bus_of_its_own_says_so(capsys: pytest.CaptureFixture[str]) -> None:
    """``-i canrls-sim`` (or ``virtual``) is a bus inside the monitor's process: a daemon
    in another process is never on it, and the error says so and what works instead."""
    line = cli_error(capsys, ["monitor", "-i", "canrls-sim", "-c", "standard", "--once",
                              "--timeout", "0.3"])
    assert line.startswith("error: no complete publication from a canrls daemon within "
                           "0.3 s on canrls-sim:standard: each process gets its own "
                           "canrls-sim bus, so a daemon in another process is not on it; ")
    assert "-i remote -c ws://127.0.0.1:54701/" in line and "canrls demo" in line
    line = cli_error(capsys, ["monitor", "-i", "virtual", "-c", "nobody", "--command",
                              "freeze", "--timeout", "0.3"])
    assert line.startswith("error: no acknowledgement of 'freeze' within 0.3 s: each "
                           "process gets its own virtual bus")


def test_the_continuous_view_on_a_bus_of_its_own_says_so(
        capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch) -> None:
    """The continuous view on ``canrls-sim``: after --timeout without a publication it
    says, once on stderr beside the printed views or under each redrawn one, that the
    bus is the process's own and what works instead (it waited silently)."""
    args = ["monitor", "-i", "canrls-sim", "-c", "standard", "--duration", "0.9",
            "--interval", "0.2", "--timeout", "0.3"]
    assert main(args) == 0
    out, err = capsys.readouterr()
    assert out.startswith("canrls monitor  canrls-sim:standard")
    assert err.startswith("canrls monitor: no complete publication from a canrls daemon "
                          "within 0.3 s on canrls-sim:standard: each process gets its own "
                          "canrls-sim bus, so a daemon in another process is not on it; ")
    assert err.count("\n") == 1 and "canrls demo" in err
    monkeypatch.setattr(sys.stdout, "isatty", lambda: True)
    assert main(args) == 0
    out, err = capsys.readouterr()
    views = out.split("\x1b[H")[1:]
    assert err == "" and len(views) >= 3
    assert "each process gets its own canrls-sim bus" not in views[0]  # before --timeout
    assert "each process gets its own canrls-sim bus" in views[-1]


def test_cli_on_a_terminal_redraws_in_place(running_daemon: tuple[Daemon, str],
                                            capsys: pytest.CaptureFixture[str],
                                            monkeypatch: pytest.MonkeyPatch) -> None:
    d, ch = running_daemon
    monkeypatch.setattr(sys.stdout, "isatty", lambda: True)
    assert main(["monitor", "-i", "virtual", "-c", ch, "--kt", "0.1", "--duration", "0.5",
                 "--interval", "0.2"]) == 0
    out = capsys.readouterr().out
    views = out.split("\x1b[H")
    assert views[0] == "" and len(views) >= 3  # each view starts at the cursor's home
    for v in views[1:]:
        assert v.startswith("canrls monitor  virtual:" + ch) and v.endswith("\x1b[K\n\x1b[J")
        # every line clears what a longer line of the previous view left
        assert all(line.endswith("\x1b[K") for line in v.split("\n")[:-1])
    assert "\x1b[2J" not in out  # the screen is never blanked first: no flicker


def test_the_monitor_section_is_read_and_checked(tmp_path: Path) -> None:
    from canrls.core.errors import ConfigError
    from canrls.processor.config import AppConfig

    good = tmp_path / "good.toml"
    good.write_text("[monitor]\ninterval = 0.5\nplain = true\n")
    assert AppConfig.load(good).monitor == {"interval": 0.5, "plain": True}
    for body, what in (("interval = 0", "monitor.interval = 0: must be a positive"),
                       ("colour = true", "unknown key monitor.colour")):
        bad = tmp_path / "bad.toml"
        bad.write_text(f"[monitor]\n{body}\n")
        with pytest.raises(ConfigError, match=what):
            AppConfig.load(bad)


def test_an_axis_command_id_is_computed_in_one_place() -> None:
    """The daemon's command ID, its bulk receiver's and the demo's were each
    ``COMMAND_ID + own_offset`` written out; :func:`~canrls.live.bus_link.command_id` is
    the one sum, and moving a frame by the offset (``moved``) lands on it."""
    import re as _re
    from pathlib import Path as _Path

    from canrls.can.estimator_frames import CommandCode, encode_command
    from canrls.live import bus_link

    src = _Path(bus_link.__file__).resolve().parents[1]
    sums = [f"{p.relative_to(src)}:{s.count(chr(10), 0, m.start()) + 1}"
            for p in sorted(src.rglob("*.py")) for s in [p.read_text()]
            for m in _re.finditer(r"COMMAND_ID \+", s)]
    assert len(sums) == 1 and sums[0].startswith("live/bus_link.py:"), sums
    frame = bus_link.moved(encode_command(CommandCode.RESET), 0x40)
    assert frame.arbitration_id == bus_link.command_id(0x40) == bus_link.COMMAND_ID + 0x40
