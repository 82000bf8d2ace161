"""Drives in users' DBCs, shared by the tests: a Motorola DBC with 32-bit signals (the
processor's scaling tests and the firmware's), a CiA 402 drive's log written through
cantools (tools/cia402_log.py: the torque-drive tests, the firmware's and the README's)
and an ODrive-style CANSimple drive's float32 frames with NaN, infinity and values out
of range among them."""

from __future__ import annotations

import importlib.util
import math
import struct
from pathlib import Path
from typing import Any

import can
import numpy as np

from canrls.sim.scenario import SimResult


def _cia402_tool() -> Any:
    """tools/cia402_log.py, the simulated CiA 402 drive's log writer (the README's too)."""
    path = Path(__file__).resolve().parents[2] / "tools" / "cia402_log.py"
    spec = importlib.util.spec_from_file_location("cia402_log", path)
    assert spec is not None and spec.loader is not None
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


_CIA402 = _cia402_tool()
#: the CiA 402 drive's DBC (tests/data/cia402_drive.dbc)
CIA402_DBC: Path = _CIA402.DBC
#: the CiA 402 drive's ratings: rated torque 0x6076 [N·m], rated current 0x6075 [A], encoder
RATED_TORQUE, RATED_CURRENT, INCREMENTS = (_CIA402.RATED_TORQUE, _CIA402.RATED_CURRENT,
                                           _CIA402.INCREMENTS)
#: the measured run of a :class:`~canrls.sim.scenario.SimResult` as the CiA 402 drive
#: sends it: ``cia402_log(res, path)``
cia402_log = _CIA402.write_log

ODRIVE_DBC = Path(__file__).resolve().parents[1] / "data" / "odrive_cansimple.dbc"
ODRIVE_SIGNALS = ["speed=Get_Encoder_Estimates.Vel_Estimate",
                  "position=Get_Encoder_Estimates.Pos_Estimate", "current=Get_Iq.Iq_Measured"]
#: what the ODrive-style log sends instead of the velocity, every 397th sample: NaN,
#: infinities, beyond the DBC's 200 rev/s and beyond float32's integers; -0.0 and a
#: subnormal pass
ODRIVE_BAD = (math.nan, math.inf, -math.inf, 200.5, -3e38, 1e9, -0.0, 1e-40)

HEADER = 'VERSION ""\n\nNS_ :\n\nBS_:\n\n'
SIGNALS = ["current=Feedback.Current", "speed=Feedback.Speed", "position=Angle.Angle"]
#: (current A, speed rpm, angle deg) limits as the drive reaches them
TIGHT = (32.0, 2000.0, 360.0)


def user_dbc(scale: float | None) -> str:
    """32-bit signals in mA, 0.01 rpm and 0.01 deg; limits ``scale`` times the tight
    ones, or (None) the raw range of the 32-bit fields."""
    if scale is None:
        lim = ["[-2147483.648|2147483.647]", "[-21474836.48|21474836.47]", "[0|42949672.95]"]
    else:
        c, w, a = (x * scale for x in TIGHT)
        lim = [f"[{-c:g}|{c:g}]", f"[{-w:g}|{w:g}]", f"[0|{a:g}]"]
    return HEADER + f'''BU_: Drive

BO_ 2566914305 Feedback: 8 Drive
 SG_ Current : 7|32@0- (0.001,0) {lim[0]} "A" Vector__XXX
 SG_ Speed : 39|32@0- (0.01,0) {lim[1]} "rpm" Vector__XXX

BO_ 2566914306 Angle: 4 Drive
 SG_ Angle : 7|32@0+ (0.01,0) {lim[2]} "deg" Vector__XXX
'''


def odrive_log(res: SimResult, path: Path) -> None:
    """The measured run as an ODrive-style CANSimple drive sends it (node 1): the encoder
    estimates (turns, turns/s) and the q-axis current as little-endian float32, with
    :data:`ODRIVE_BAD` in place of the velocity now and then."""
    m = res.measured
    assert m.current is not None
    turns = np.unwrap(m.position) / (2 * math.pi)   # the position estimate is multi-turn
    vel = m.speed / (2 * math.pi)
    with can.CanutilsLogWriter(str(path)) as w:
        for k in range(len(m)):
            v = float(vel[k]) if k % 397 != 396 else ODRIVE_BAD[(k // 397) % len(ODRIVE_BAD)]
            frames = ((0.0, 0x034, struct.pack("<ff", 0.0, float(m.current[k]))),
                      (1e-4, 0x029, struct.pack("<ff", float(turns[k]), v)))
            for dt, fid, data in frames:
                w.on_message_received(can.Message(timestamp=float(m.t[k]) + dt,
                                                  arbitration_id=fid, is_extended_id=False,
                                                  data=data))
