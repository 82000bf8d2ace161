#!/usr/bin/env python3
"""Turn HSM150 runs (MATLAB ``.mat``, 1 kHz) into candump logs of a drive-like DBC.

The HSM150 rig (``../shared/data/hsm150``, see its README) records position, speed
and motor current at 1 kHz. This tool writes what a real servo drive would have put on
its bus, in a DBC that is deliberately *not* canrls's own (``tests/data/hsm150_drive.dbc``,
also written by ``--write-dbc``):

* 29-bit identifiers, J1939-like (``0x0CF00401``, ``0x0CF00402``)
* ``MC_Feedback1.PhaseCurrentIq``: 16-bit signed, 1 mA; ``TorqueEst`` 0.1 mN·m;
  ``AliveCounter`` 4-bit
* ``MC_Feedback2.RotorSpeed``: 24-bit signed, 0.01 rpm; ``RotorAngle``: 16-bit
  unsigned, 0.001 rad, wraps at one turn; ``AliveCounter`` 4-bit
* ``GenMsgCycleTime`` 1 ms

Usage::

    python tools/hsm150_to_can.py OUT_DIR [RUN.mat ...]   # default: every run of the folder
    python tools/hsm150_to_can.py --raw-limits OUT_DIR    # 32-bit signals, raw limits

writes ``OUT_DIR/<run>.log`` (candump ``-l`` format, ``(t) can0 ID#DATA``) and
``OUT_DIR/hsm150_drive.dbc``. With ``--raw-limits`` the current and the speed are 32-bit
signals whose DBC declares the full raw range of their 32 bits (±2.1e6 A, ±21e6 rpm), as
vendors' tools often write them; the signal names, units and resolutions stay the same,
so the same map reads either directory. The map for canrls::

    canrls fit OUT_DIR/idf_pos_0.06_1.log --dbc OUT_DIR/hsm150_drive.dbc \\
      --signal current=MC_Feedback1.PhaseCurrentIq --signal speed=MC_Feedback2.RotorSpeed \\
      --signal position=MC_Feedback2.RotorAngle \\
      --signal counter=MC_Feedback1.AliveCounter --signal counter=MC_Feedback2.AliveCounter \\
      --kt 0.0458

Timestamps are epoch seconds (``--t0``, default 2024-05-01 12:00:00 UTC), as candump
writes them.
"""

from __future__ import annotations

import argparse
import math
import sys
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import numpy.typing as npt

#: Where the runs are, relative to the repository root (never copied into the project).
DATA_DIR = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "hsm150"
#: The DBC shipped with the tests (the same text as :data:`DBC_TEXT`).
DBC_FILE = Path(__file__).resolve().parents[1] / "tests" / "data" / "hsm150_drive.dbc"

ID_FB1 = 0x0CF00401  # current (29-bit)
ID_FB2 = 0x0CF00402  # speed and angle (29-bit)
KT = 0.0458          # N·m/A, the rig's torque constant (README: torque = current x Cu)

#: The command-line mapping of the roles to this DBC's signals.
SIGNALS: tuple[str, ...] = (
    "current=MC_Feedback1.PhaseCurrentIq",
    "speed=MC_Feedback2.RotorSpeed",
    "position=MC_Feedback2.RotorAngle",
    "counter=MC_Feedback1.AliveCounter",
    "counter=MC_Feedback2.AliveCounter",
)

DBC_TEXT = f"""VERSION "HSM150 servo drive (example: 29-bit ids, scaled integer units)"

NS_ :
\tCM_
\tBA_DEF_
\tBA_
\tBA_DEF_DEF_

BS_:

BU_: ServoDrive Logger

BO_ {0x80000000 | ID_FB1} MC_Feedback1: 8 ServoDrive
 SG_ PhaseCurrentIq : 0|16@1- (1,0) [-32000|32000] "mA" Logger
 SG_ TorqueEst : 16|16@1- (0.0001,0) [-3|3] "N.m" Logger
 SG_ DcLinkVoltage : 32|16@1+ (0.01,0) [0|100] "V" Logger
 SG_ AliveCounter : 60|4@1+ (1,0) [0|15] "" Logger

BO_ {0x80000000 | ID_FB2} MC_Feedback2: 8 ServoDrive
 SG_ RotorSpeed : 0|24@1- (0.01,0) [-60000|60000] "rpm" Logger
 SG_ RotorAngle : 24|16@1+ (0.001,0) [0|6.283] "rad" Logger
 SG_ AliveCounter : 60|4@1+ (1,0) [0|15] "" Logger

CM_ BO_ {0x80000000 | ID_FB1} "q-axis current in mA, torque estimate (Kt x Iq), 1 ms.";
CM_ BO_ {0x80000000 | ID_FB2} "Rotor speed in 0.01 rpm and angle in mrad (one turn), 1 ms.";
BA_DEF_ BO_ "GenMsgCycleTime" INT 0 65535;
BA_DEF_ BO_ "VFrameFormat" ENUM "StandardCAN","ExtendedCAN";
BA_DEF_DEF_ "GenMsgCycleTime" 0;
BA_DEF_DEF_ "VFrameFormat" "StandardCAN";
BA_ "GenMsgCycleTime" BO_ {0x80000000 | ID_FB1} 1;
BA_ "GenMsgCycleTime" BO_ {0x80000000 | ID_FB2} 1;
BA_ "VFrameFormat" BO_ {0x80000000 | ID_FB1} 1;
BA_ "VFrameFormat" BO_ {0x80000000 | ID_FB2} 1;
"""


#: The DBC of ``--raw-limits``: the current and the speed in 32 bits, declaring the raw
#: range of their fields; the torque estimate, the angle and the counters as above (no
#: DC-link voltage: no room left).
DBC_TEXT_RAW = DBC_TEXT.replace(
    """ SG_ PhaseCurrentIq : 0|16@1- (1,0) [-32000|32000] "mA" Logger
 SG_ TorqueEst : 16|16@1- (0.0001,0) [-3|3] "N.m" Logger
 SG_ DcLinkVoltage : 32|16@1+ (0.01,0) [0|100] "V" Logger
""", """ SG_ PhaseCurrentIq : 0|32@1- (1,0) [-2147483648|2147483647] "mA" Logger
 SG_ TorqueEst : 32|16@1- (0.0001,0) [-3|3] "N.m" Logger
""").replace(
    """ SG_ RotorSpeed : 0|24@1- (0.01,0) [-60000|60000] "rpm" Logger
 SG_ RotorAngle : 24|16@1+ (0.001,0) [0|6.283] "rad" Logger
""", """ SG_ RotorSpeed : 0|32@1- (0.01,0) [-21474836.48|21474836.47] "rpm" Logger
 SG_ RotorAngle : 32|16@1+ (0.001,0) [0|6.283] "rad" Logger
""").replace("scaled integer units)", "scaled integer units, raw limits)")


def load_run(path: str | Path) -> npt.NDArray[np.float64]:
    """The ``data`` matrix of a run (20000 x 7: t, ref, position, speed, input, torque,
    current), see the folder's README."""
    from scipy.io import loadmat  # test extra

    return np.asarray(loadmat(str(path))["data"], dtype=np.float64)


def _le(values: npt.NDArray[np.int64], bits: int, start: int) -> npt.NDArray[np.uint64]:
    """Two's complement ``values`` in ``bits`` bits at little-endian bit ``start``."""
    v = values.astype(np.int64) & ((1 << bits) - 1)
    return v.astype(np.uint64) << np.uint64(start)


def encode(data: npt.NDArray[np.float64], t0: float = 1714564800.0, raw_limits: bool = False
           ) -> list[tuple[float, int, bytes]]:
    """Frames ``(t, id, payload)`` of one run, in time order (FB1 then FB2 each period);
    ``raw_limits``: the layout of :data:`DBC_TEXT_RAW`."""
    t = data[:, 0] + t0
    n = len(t)
    cur = np.rint(data[:, 6] * 1000.0).astype(np.int64)                      # mA
    tq = np.rint(data[:, 6] * KT / 0.0001).astype(np.int64)                   # 0.1 mN·m
    volt = np.full(n, 2400, np.int64)                                         # 24 V, 0.01 V
    rpm = np.rint(data[:, 3] * 60.0 / (2.0 * math.pi) / 0.01).astype(np.int64)  # 0.01 rpm
    ang = np.rint(np.mod(data[:, 2], 2.0 * math.pi) / 0.001).astype(np.int64)
    ang = np.where(ang > 6283, ang - 6284, ang)                               # one turn
    cnt = np.arange(n, dtype=np.int64) % 16
    if raw_limits:
        w1 = _le(cur, 32, 0) | _le(tq, 16, 32) | _le(cnt, 4, 60)
        w2 = _le(rpm, 32, 0) | _le(ang, 16, 32) | _le(cnt, 4, 60)
    else:
        w1 = _le(cur, 16, 0) | _le(tq, 16, 16) | _le(volt, 16, 32) | _le(cnt, 4, 60)
        w2 = _le(rpm, 24, 0) | _le(ang, 16, 24) | _le(cnt, 4, 60)
    out: list[tuple[float, int, bytes]] = []
    for k in range(n):
        out.append((float(t[k]), ID_FB1, int(w1[k]).to_bytes(8, "little")))
        out.append((float(t[k]) + 0.0001, ID_FB2, int(w2[k]).to_bytes(8, "little")))
    return out


def write_log(path: str | Path, frames: Sequence[tuple[float, int, bytes]],
              channel: str = "can0") -> None:
    """A candump ``-l`` log."""
    with open(path, "w", encoding="ascii") as f:
        for t, cid, data in frames:
            f.write(f"({t:.6f}) {channel} {cid:08X}#{data.hex().upper()}\n")


def convert(run: str | Path, out_dir: str | Path, t0: float = 1714564800.0,
            raw_limits: bool = False) -> Path:
    """Write ``out_dir/<run stem>.log``; return its path."""
    out = Path(out_dir) / (Path(run).stem + ".log")
    write_log(out, encode(load_run(run), t0, raw_limits))
    return out


def write_dbc(out_dir: str | Path, raw_limits: bool = False) -> Path:
    p = Path(out_dir) / "hsm150_drive.dbc"
    p.write_text(DBC_TEXT_RAW if raw_limits else DBC_TEXT, encoding="ascii")
    return p


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("out_dir", help="directory for the .log files and the DBC")
    ap.add_argument("runs", nargs="*", help=f".mat runs (default: every run of {DATA_DIR})")
    ap.add_argument("--t0", type=float, default=1714564800.0,
                    help="epoch time of the first sample [s]")
    ap.add_argument("--raw-limits", action="store_true",
                    help="current and speed as 32-bit signals whose DBC declares the full "
                         "raw range of their fields")
    args = ap.parse_args(argv)
    runs = [Path(r) for r in args.runs] or sorted(DATA_DIR.glob("idf_*.mat"))
    if not runs:
        print(f"no runs given and none in {DATA_DIR}", file=sys.stderr)
        return 1
    out = Path(args.out_dir)
    out.mkdir(parents=True, exist_ok=True)
    print(write_dbc(out, args.raw_limits))
    for r in runs:
        print(convert(r, out, args.t0, args.raw_limits))
    return 0


if __name__ == "__main__":
    sys.exit(main())
