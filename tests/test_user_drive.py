"""A user's own drive: their DBC and logs, no configuration file, from the command line.

The user DBCs are written here (DBC text, as a user's tool writes it): no
``GenMsgCycleTime``, 29-bit IDs, Motorola byte order, scaled integer units (mA,
0.01 rpm, 0.01 deg, mm, 0.01 mm/s). The same simulated data is encoded once in the
user's DBC and once in canrls's own, and both fits must give the same parameters
within their sigma.
"""

from __future__ import annotations

import json
import math
import re
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from canrls.can.encoder import FeedbackEncoder
from canrls.can.logs import LogReadStats, read_frames, write_log
from canrls.can.protocol import Protocol
from canrls.cli.main import main
from canrls.processor.period import estimate_period
from canrls.sim.scenario import Simulator, scenario

#: what every DBC begins with
HEADER = 'VERSION ""\n\nNS_ :\n\nBS_:\n\n'

ROTARY_DBC = HEADER + '''BU_: Drive

BO_ 2566914305 MotorFeedback: 8 Drive
 SG_ PhaseCurrent : 7|16@0- (1,0) [-32000|32000] "mA" Vector__XXX
 SG_ MotorSpeed : 23|32@0- (0.01,0) [-2000000|2000000] "rpm" Vector__XXX

BO_ 2566914306 MotorAngle: 2 Drive
 SG_ Angle : 7|16@0+ (0.01,0) [0|360] "deg" Vector__XXX
'''
ROTARY_SIGNALS = ["current=MotorFeedback.PhaseCurrent", "speed=MotorFeedback.MotorSpeed",
                  "position=MotorAngle.Angle"]

LINEAR_DBC = HEADER + '''BU_: Axis

BO_ 2566914561 AxisCurrent: 2 Axis
 SG_ Iq : 7|16@0- (1,0) [-32000|32000] "mA" Vector__XXX

BO_ 2566914562 AxisMotion: 8 Axis
 SG_ Velocity : 7|32@0- (0.01,0) [-2000000|2000000] "mm/s" Vector__XXX
 SG_ Pos : 39|32@0- (0.001,0) [-2000000|2000000] "mm" Vector__XXX
'''
LINEAR_SIGNALS = ["current=AxisCurrent.Iq", "speed=AxisMotion.Velocity",
                  "position=AxisMotion.Pos"]

EPOCH = 1_700_000_000.25
DURATION = 8.0


def _flags(dbc: Path, signals: list[str]) -> list[str]:
    return ["--dbc", str(dbc), *[a for s in signals for a in ("--signal", s)]]


def _fit(capsys: pytest.CaptureFixture[str], args: list[str]) -> dict[str, Any]:
    assert main(["fit", *args, "--quiet", "--json"]) == 0
    out: dict[str, Any] = json.loads(capsys.readouterr().out)
    return out


def _same(a: dict[str, Any], b: dict[str, Any]) -> None:
    """The same parameters within their sigma (the two sigmas added)."""
    assert a["parameters"].keys() == b["parameters"].keys()
    for name, pa in a["parameters"].items():
        pb = b["parameters"][name]
        assert abs(pa["value"] - pb["value"]) <= pa["sigma"] + pb["sigma"], (name, pa, pb)
        assert pa["unit"] == pb["unit"]


def _logs(d: Path, dbc_text: str, signals: list[str], name: str, seed: int,
          logs: dict[str, tuple[str, float]]) -> dict[str, Path]:
    """The user's DBC and, of one simulated run, a log in canrls's own DBC (``own``) and
    logs ``{key: (file name, t0)}`` in the user's."""
    dbc = d / "user.dbc"
    dbc.write_text(dbc_text)
    user = Protocol.load(dbc, signals)
    sc = scenario(name, seed=seed, duration=DURATION)
    out = {"dbc": dbc, "own": d / "own.log"}
    write_log(out["own"], Simulator(sc).frames())
    for key, (fname, t0) in logs.items():
        out[key] = d / fname
        write_log(out[key], Simulator(sc, t0=t0, protocol=user).frames())
    return out


@pytest.fixture(scope="module")
def rotary(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    return _logs(tmp_path_factory.mktemp("rotary"), ROTARY_DBC, ROTARY_SIGNALS, "standard", 5,
                 {"epoch": ("candump-2023.log", EPOCH), "blf": ("servo.blf", 0.0)})


@pytest.fixture(scope="module")
def linear(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    return _logs(tmp_path_factory.mktemp("linear"), LINEAR_DBC, LINEAR_SIGNALS, "linear", 6,
                 {"asc": ("axis.asc", 0.0)})


def test_the_user_dbc_has_what_a_user_dbc_has(rotary: dict[str, Path]) -> None:
    p = Protocol.load(rotary["dbc"], ROTARY_SIGNALS)
    assert p.period is None and p.period_source is None  # no GenMsgCycleTime
    assert all(m.is_extended for m in p.messages)
    assert p.messages[0].frame_id == 0x19000101
    assert p.db.get_message_by_name("MotorFeedback").signals[0].byte_order == "big_endian"
    assert p.axis == "rotary"


def test_rotary_epoch_candump_log_fits_as_with_the_own_dbc(
        rotary: dict[str, Path], capsys: pytest.CaptureFixture[str]) -> None:
    own = _fit(capsys, [str(rotary["own"])])
    user = _fit(capsys, [str(rotary["epoch"]), *_flags(rotary["dbc"], ROTARY_SIGNALS)])
    _same(own, user)
    assert user["period"]["source"] == "measured"
    assert user["period"]["value"] == pytest.approx(1e-3, rel=1e-6)
    assert user["start"]["t0"] == pytest.approx(EPOCH)
    assert user["start"]["date"].startswith("2023-11-14 22:13:20.25")
    # times relative to the start of the log
    assert user["calibration"]["window"]["t_start"] < 1.0
    assert user["axis"]["axis"] == "rotary"
    assert user["parameters"]["inertia.J"]["unit"] == "A·s²/rad"


def test_rotary_text_names_date_period_axis_and_defaults(
        rotary: dict[str, Path], capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["fit", str(rotary["epoch"]), *_flags(rotary["dbc"], ROTARY_SIGNALS),
                 "--kt", "0.1", "--quiet"]) == 0
    out = capsys.readouterr().out
    assert "log starts 2023-11-14 22:13:20.250000 UTC" in out
    assert "1.7e+09" not in out
    assert "control period 1 ms (measured on the timestamps)" in out
    assert "axis rotary (DBC units: current mA, speed rpm, position deg)" in out
    assert "defaults from the data: Coulomb band" in out
    assert "kg·m²" in out and "N·m" in out


def test_diagnosis_page_of_an_epoch_log_names_its_start_date(
        rotary: dict[str, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    pytest.importorskip("matplotlib")
    assert main(["diagnose", str(rotary["epoch"]), *_flags(rotary["dbc"], ROTARY_SIGNALS),
                 "--report", str(tmp_path / "page"), "--quiet"]) == 0
    capsys.readouterr()
    html = (tmp_path / "page" / "index.html").read_text(encoding="utf-8")
    assert "The log starts 2023-11-14 22:13:20.250000 UTC" in html
    assert "1.7e+09" not in html and "1.70e+09" not in html


def test_blf_log_of_the_user_dbc(rotary: dict[str, Path],
                                 capsys: pytest.CaptureFixture[str]) -> None:
    own = _fit(capsys, [str(rotary["own"])])
    user = _fit(capsys, [str(rotary["blf"]), *_flags(rotary["dbc"], ROTARY_SIGNALS)])
    _same(own, user)


def test_linear_asc_log_in_mm_fits_as_with_the_own_dbc(
        linear: dict[str, Path], capsys: pytest.CaptureFixture[str]) -> None:
    own = _fit(capsys, [str(linear["own"]), "--axis", "linear", "--kt", "20"])
    user = _fit(capsys, [str(linear["asc"]), *_flags(linear["dbc"], LINEAR_SIGNALS),
                         "--kt", "20"])
    _same(own, user)
    assert user["axis"]["axis"] == "linear"  # from the DBC's mm and mm/s
    units = {k: v["unit"] for k, v in user["parameters"].items()}
    assert units == {"inertia.J": "kg", "viscous.B": "N·s/m", "coulomb.Tc": "N"}
    # the truth: m = 2 kg, B = 5 N·s/m, Fc = 3 N
    p = user["parameters"]
    assert p["inertia.J"]["value"] == pytest.approx(2.0, rel=0.01)
    assert p["coulomb.Tc"]["value"] == pytest.approx(3.0, rel=0.01)
    # defaults scaled from the data (speed noise 1e-4 m/s), not 0.01 "rad/s or m/s"
    band = user["calibration"]["defaults"]["coulomb_band"]
    assert 1e-4 < band < 1e-3
    assert user["calibration"]["defaults"]["pitch"] == 1.0  # 0.9 m of travel rounded up


def test_diagnose_a_user_log_without_configuration(
        linear: dict[str, Path], capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["diagnose", str(linear["asc"]), *_flags(linear["dbc"], LINEAR_SIGNALS),
                 "--kt", "20", "--quiet", "--json"]) == 0
    d = json.loads(capsys.readouterr().out)
    assert d["frames"]["period"]["source"] == "measured"
    assert d["before"]["parameters"]["coulomb.Tc"]["unit"] == "N"


# ------------------------------------------------------------------ clear errors


def test_a_wrong_period_is_refused_naming_both(rotary: dict[str, Path],
                                               capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["fit", str(rotary["epoch"]), *_flags(rotary["dbc"], ROTARY_SIGNALS),
                 "--period", "0.0018", "--quiet"]) == 1
    err = capsys.readouterr().err
    assert "--period 0.0018 gives a control period of 1.8 ms" in err
    assert "timestamps say 1 ms" in err
    # within 10 %: accepted, and used
    d = _fit(capsys, [str(rotary["epoch"]), *_flags(rotary["dbc"], ROTARY_SIGNALS),
                      "--period", "0.00102"])
    assert d["period"]["value"] == 0.00102 and d["period"]["source"] == "--period 0.00102"


@pytest.mark.parametrize(("args", "message"), [
    (["--kt", "-0.1"], "--kt -0.1: the torque constant must be positive"),
    (["--kt", "0"], "--kt 0: the torque constant must be positive"),
    (["--period", "0"], "--period 0: the control period must be a positive number"),
    (["--period=-1e-3"], "--period -1e-3: the control period must be a positive number"),
    (["--effects", "inertia,viscous,colomb"], "--effects inertia,viscous,colomb: unknown "
                                              "effect 'colomb'"),
    (["--lambda", "2"], "--lambda 2: must be in (0.5, 1]"),
    (["--signal", "current"], "--signal current: expected ROLE=MESSAGE.SIGNAL"),
])
def test_command_line_mistakes_name_the_flag(rotary: dict[str, Path], args: list[str],
                                             message: str,
                                             capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["fit", str(rotary["own"]), *args, "--quiet"]) == 1
    err = capsys.readouterr().err
    assert err.startswith(f"error: {message}"), err
    assert "<defaults>" not in err


def test_a_foreign_log_names_expected_and_seen_ids(
        rotary: dict[str, Path], capsys: pytest.CaptureFixture[str]) -> None:
    # the user's log read with canrls's own DBC
    assert main(["fit", str(rotary["epoch"]), "--quiet"]) == 1
    err = capsys.readouterr().err
    assert "none of the mapped messages occurs" in err
    assert "expected 0x101 (DriveCurrent), 0x102 (DriveSpeed)" in err
    assert "0x19000101 (8000)" in err and "0x19000102 (8000)" in err
    assert main(["diagnose", str(rotary["epoch"]), "--quiet"]) == 1
    assert "0x19000101 (8000)" in capsys.readouterr().err


def test_too_few_usable_samples_says_how_many_and_why(
        tmp_path: Path, rotary: dict[str, Path], capsys: pytest.CaptureFixture[str]) -> None:
    short = tmp_path / "short.log"
    blocks = list(read_frames(rotary["own"]))
    write_log(short, [blocks[0].take(slice(0, 120))])
    assert main(["fit", str(short), "--quiet"]) == 1
    err = capsys.readouterr().err
    assert re.search(r"too few usable samples: the mechanical equation used \d+, its 3 "
                     r"parameters need at least 30; 120 frames gave 60 samples", err), err
    assert "warm-up" in err
    assert main(["diagnose", str(short), "--quiet"]) == 1
    assert "too few usable samples" in capsys.readouterr().err


def test_an_empty_log_is_an_error(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    empty = tmp_path / "empty.log"
    empty.write_text("")
    assert main(["fit", str(empty), "--quiet"]) == 1
    assert "no CAN frames" in capsys.readouterr().err


# ------------------------------------------------------------------ timestamps


def test_epoch_candump_takes_the_fast_path(rotary: dict[str, Path]) -> None:
    st = LogReadStats()
    blocks = list(read_frames(rotary["epoch"], stats=st))
    assert st.slow_lines == 0 and st.frames == 2 * int(DURATION / 1e-3)
    t = np.concatenate([b.t for b in blocks])
    # exactly float() of the text
    with open(rotary["epoch"]) as f:
        ref = [float(line[1:line.index(")")]) for line in f]
    assert t.tolist() == ref


@pytest.mark.parametrize("kind", ["jitter", "drops", "bursts", "relayed"])
def test_period_from_timestamps_is_robust(kind: str) -> None:
    rng = np.random.default_rng(3)
    p = 2e-3
    t = EPOCH + p * np.arange(2000)
    if kind == "jitter":
        t = t + rng.normal(0, 0.1 * p, len(t))
    elif kind == "drops":
        t = t[rng.random(len(t)) > 0.3]
    elif kind == "bursts":  # groups of 8 frames queued and sent within 10 µs
        t = t[(np.arange(len(t)) // 8) * 8] + 1e-6 * (np.arange(len(t)) % 8)
    else:  # relayed (a websocket, a gateway): groups of 3 to 24 frames, each delivered
        # after its last frame plus a latency of up to 1.5 periods, 2 µs apart
        out, i = [], 0
        while i < len(t):
            j = min(i + int(rng.integers(3, 25)), len(t))
            out += [t[j - 1] + rng.uniform(0, 1.5 * p) + 2e-6 * k for k in range(j - i)]
            i = j
        t = np.array(out)
    est = estimate_period({"m": np.sort(t)[:257]})  # what the meter measures on
    assert est is not None
    assert est.period == pytest.approx(p, rel=0.02)


def test_the_period_is_the_same_live_and_offline(rotary: dict[str, Path]) -> None:
    """The daemon's front end measures the period on the first frames as they come, in
    blocks of any size: the same period and parameters as one block."""
    from canrls.processor.config import AppConfig
    from canrls.processor.replay import fit_frames

    cfg = AppConfig(can={"dbc": str(rotary["dbc"])}, signal_overrides=ROTARY_SIGNALS)
    protocol = cfg.protocol()
    model, settings = cfg.model_for(protocol), cfg.settings()
    whole = list(read_frames(rotary["epoch"]))
    small = [b.take(slice(i, i + 37)) for b in whole for i in range(0, len(b), 37)]
    a = fit_frames(whole, protocol, model, settings)
    b = fit_frames(small, protocol, model, settings)
    assert a.period == b.period
    for pa, pb in zip(a.parameters, b.parameters, strict=True):
        assert pa.value == pb.value or (math.isnan(pa.value) and math.isnan(pb.value))


def test_bench_epoch_runs(tmp_path: Path) -> None:
    """tools/bench_epoch.py on a short log: both logs read, neither on the slow path."""
    import subprocess
    import sys

    tool = Path(__file__).resolve().parents[1] / "tools" / "bench_epoch.py"
    out = subprocess.run([sys.executable, str(tool), "--duration", "2", "--repeat", "1",
                          "--dir", str(tmp_path)], capture_output=True, text=True, check=True,
                         timeout=300).stdout
    lines = out.splitlines()
    assert [ln.split(":")[0].strip() for ln in lines if "first line" in ln] == \
        ["zero-based", "epoch"]
    assert "(1700000000.000000) can0" in out
    assert "slow path" not in out
    assert out.count("fit_log:") == 2


def test_a_checkpoint_restored_before_the_period_is_measured(rotary: dict[str, Path]) -> None:
    """The daemon restores a checkpoint at start, before the first frames have told the
    period: the restored calibration holds once the period is measured."""
    from canrls.processor import FrameProcessor
    from canrls.processor.config import AppConfig

    cfg = AppConfig(can={"dbc": str(rotary["dbc"])}, signal_overrides=ROTARY_SIGNALS)
    protocol = cfg.protocol()
    model, settings = cfg.model_for(protocol), cfg.settings()
    blocks = [b.take(slice(i, i + 1000)) for b in read_frames(rotary["epoch"])
              for i in range(0, len(b), 1000)]
    a = FrameProcessor(protocol, model, settings)
    for b in blocks[:8]:
        a.process(b)
    assert a.calibration is not None and a.period == pytest.approx(1e-3)
    b2 = FrameProcessor(protocol, model, settings)
    assert b2.period is None
    b2.restore(a.state(), a.model)
    for b in blocks[8:]:
        b2.process(b)
    assert b2.period == pytest.approx(1e-3)
    assert b2.calibration == a.calibration
    assert b2.pipeline.estimates().samples > 0


def test_a_refused_model_switch_before_the_period_keeps_the_model_to_start_with(
        rotary: dict[str, Path], monkeypatch: pytest.MonkeyPatch) -> None:
    """A command's model switch that fails while the period is being measured leaves
    the model the processor will start with as it was (it was replaced first)."""
    from canrls.core.errors import ConfigError
    from canrls.processor import FrameProcessor, SampleProcessor
    from canrls.processor.config import AppConfig

    cfg = AppConfig(can={"dbc": str(rotary["dbc"])}, signal_overrides=ROTARY_SIGNALS)
    protocol = cfg.protocol()
    model, settings = cfg.model_for(protocol), cfg.settings()
    proc = FrameProcessor(protocol, model, settings)
    assert proc.period is None

    def refuse(self: SampleProcessor, m: Any) -> Any:
        raise ConfigError("refused")

    with monkeypatch.context() as mp:
        mp.setattr(SampleProcessor, "with_model", refuse)
        with pytest.raises(ConfigError):
            proc.with_model(model.with_effects(add=["offset"]))
    for b in read_frames(rotary["epoch"]):
        proc.process(b)
    assert proc.period == pytest.approx(1e-3)
    assert [p.name for p in proc.model.parameters] == [p.name for p in model.parameters]


@pytest.mark.parametrize(("cycle_ms", "ok"), [(1, True), (2, False)])
def test_the_dbc_cycle_time_is_checked_against_the_timestamps(
        tmp_path: Path, rotary: dict[str, Path], cycle_ms: int, ok: bool,
        capsys: pytest.CaptureFixture[str]) -> None:
    dbc = tmp_path / "cycle.dbc"
    dbc.write_text(ROTARY_DBC + '\nBA_DEF_ BO_ "GenMsgCycleTime" INT 0 65535;\n'
                   'BA_DEF_DEF_ "GenMsgCycleTime" 0;\n'
                   f'BA_ "GenMsgCycleTime" BO_ 2566914305 {cycle_ms};\n'
                   f'BA_ "GenMsgCycleTime" BO_ 2566914306 {cycle_ms};\n')
    code = main(["fit", str(rotary["epoch"]), *_flags(dbc, ROTARY_SIGNALS), "--quiet",
                 "--json"])
    out, err = capsys.readouterr()
    if ok:
        assert code == 0
        assert json.loads(out)["period"]["source"] == "the GenMsgCycleTime of DBC cycle.dbc"
    else:
        assert code == 1
        assert err.startswith(f"error: {rotary['epoch']}: the GenMsgCycleTime of DBC "
                              f"cycle.dbc gives a control period of 2 ms but the log's "
                              f"timestamps say 1 ms"), err


@pytest.mark.parametrize(("unit", "axis", "factor"), [
    ("rpm", "rotary", 2 * math.pi / 60), ("deg", "rotary", math.pi / 180),
    ("rad/s", "rotary", 1.0), ("rev", "rotary", 2 * math.pi), ("mrad", "rotary", 1e-3),
    ("m", "linear", 1.0), ("mm", "linear", 1e-3), ("mm/s", "linear", 1e-3),
    ("m/min", "linear", 1 / 60), ("µm", "linear", 1e-6), ("cm/s", "linear", 1e-2),
])
def test_every_motion_unit_names_its_axis(unit: str, axis: str, factor: float) -> None:
    from canrls.core.units import axis_of, si_factor

    assert axis_of(unit) == axis
    role = "speed" if "/" in unit or unit == "rpm" else "position"
    assert si_factor(role, unit) == pytest.approx(factor)


# ------------------------------------------------------------------ real measurements

HSM150 = Path(__file__).resolve().parents[2] / "shared" / "data" / "hsm150"


def _loadmat(path: Path) -> dict[str, np.ndarray]:
    """The numeric matrices of a MATLAB v5 file (compressed or not): enough of the format
    for the HSM150 runs, without scipy."""
    import struct
    import zlib

    kinds = {1: np.int8, 2: np.uint8, 3: np.int16, 4: np.uint16, 5: np.int32, 6: np.uint32,
             7: np.float32, 9: np.float64, 12: np.int64, 13: np.uint64}

    def elements(buf: bytes, p: int = 0) -> list[tuple[int, bytes]]:
        out = []
        while p + 8 <= len(buf):
            ty, n = struct.unpack("<II", buf[p:p + 8])
            if ty >> 16:  # small element: size and type in 4 bytes, data in the next 4
                out.append((ty & 0xFFFF, buf[p + 4:p + 4 + (ty >> 16)]))
                p += 8
            else:  # data padded to 8 bytes, except a compressed element's
                out.append((ty, buf[p + 8:p + 8 + n]))
                p += 8 + (n if ty == 15 else (n + 7) // 8 * 8)
        return out

    found: dict[str, np.ndarray] = {}
    todo = elements(path.read_bytes(), 128)
    while todo:
        ty, data = todo.pop(0)
        if ty == 15:  # miCOMPRESSED
            todo[:0] = elements(zlib.decompress(data))
        elif ty == 14:  # miMATRIX: flags, dims, name, real part
            parts = elements(data)
            if parts[0][1][0] >= 6 and len(parts) >= 4:  # numeric classes
                dims = struct.unpack(f"<{len(parts[1][1]) // 4}i", parts[1][1])
                kind, raw = parts[3]
                found[parts[2][1].decode()] = np.frombuffer(raw, kinds[kind]).reshape(
                    dims, order="F").astype(np.float64)
    return found


@pytest.mark.skipif(not HSM150.is_dir(), reason=f"real measurements not found at {HSM150}")
def test_real_measurements_in_a_user_dbc_fit_as_in_the_own(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """An HSM150 run (1 kHz, 20 s) sent as a user's drive would send it (mA, 0.01 rpm,
    0.01 deg, 29-bit Motorola frames, candump -l epoch times) and in canrls's own DBC:
    the same parameters within their sigma, with no configuration."""
    d = _loadmat(HSM150 / "idf_neg_0.045_1.mat")["data"]
    t, position, speed, current = d[:, 0], d[:, 2], d[:, 3], d[:, 6]
    angle = np.mod(position, 2 * np.pi)
    dbc = tmp_path / "servo.dbc"
    dbc.write_text(ROTARY_DBC)
    user = FeedbackEncoder(Protocol.load(dbc, ROTARY_SIGNALS), stagger=1e-4)
    write_log(tmp_path / "user.log", [user.encode(EPOCH + t, current, speed, angle)])
    own = FeedbackEncoder(Protocol.load(), stagger=1e-4)
    write_log(tmp_path / "own.log", [own.encode(t, current, speed, angle, np.zeros_like(t))])
    flags = ["--kt", "0.0458", "--effects", "inertia,viscous,offset"]
    a = _fit(capsys, [str(tmp_path / "own.log"), *flags])
    b = _fit(capsys, [str(tmp_path / "user.log"), *_flags(dbc, ROTARY_SIGNALS), *flags])
    _same(a, b)
    assert b["period"]["value"] == pytest.approx(1e-3, rel=1e-6)
    assert b["parameters"]["inertia.J"]["unit"] == "kg·m²"


def test_messages_at_different_periods_are_named() -> None:
    from canrls.core.errors import ConfigError

    t = np.arange(500) * 1e-3
    with pytest.raises(ConfigError, match=r"MotorFeedback every 1 ms, MotorAngle every 10 ms"):
        estimate_period({"MotorFeedback": t, "MotorAngle": t[::10]})
    est = estimate_period({"MotorFeedback": t, "MotorAngle": t + 1e-4})
    assert est is not None and est.period == pytest.approx(1e-3)


def test_the_daemon_measures_the_period_as_the_replay_does(tmp_path: Path) -> None:
    """``canrls run`` with a DBC without cycle times: the daemon's front end measures the
    period on the first frames; replaying what it saw gives the same period and the same
    parameters bit for bit."""
    import os

    from canrls.can.mapping import SignalMapping
    from canrls.can.protocol import DEFAULT_DBC
    from canrls.live.daemon import Daemon
    from canrls.live.daemon_settings import DaemonSettings
    from canrls.processor import FrameProcessor
    from canrls.processor.config import AppConfig

    dbc = tmp_path / "no_cycle.dbc"
    dbc.write_text("".join(ln for ln in DEFAULT_DBC.read_text().splitlines(keepends=True)
                           if not ln.startswith('BA_ "GenMsgCycleTime" BO_ 25')))
    protocol = Protocol.load(dbc, SignalMapping.default())
    assert protocol.period is None
    cfg = AppConfig(model={"effects": ["inertia", "viscous", "coulomb"], "kt": 0.1})
    model, settings = cfg.model_for(protocol), cfg.settings()
    log = tmp_path / "seen.log"
    d = Daemon(protocol, model, settings, DaemonSettings(record=log, block_interval=0.002),
               bus=dict(interface="canrls-sim", channel=f"user-period-{os.getpid()}",
                        effects="inertia,viscous,coulomb", seed=3, excitation="slow",
                        realtime=False, start_time=0.0), backpressure=True)
    try:
        d.start()
        assert d.wait_for(lambda x: x.pipeline.samples > 4000, 60)
    finally:
        d.stop()
    assert d.processor.period == pytest.approx(1e-3, rel=1e-6)
    live = d.estimates()
    proc = FrameProcessor(protocol, model, settings)
    for block in read_frames(log, 997):
        proc.process(block)
    assert proc.period == d.processor.period
    off = proc.pipeline.estimates()
    for a, b in zip(live.parameters, off.parameters, strict=True):
        assert (a.name, a.value, a.sigma) == (b.name, b.value, b.sigma)
