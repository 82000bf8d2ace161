"""Write a candump log of a simulated CiA 402 drive in ``tests/data/cia402_drive.dbc``.

The simulated drive's measured run as a CANopen drive sends it: TPDO1 (statusword, torque
and current actual values in per mille of the rated torque and current) and TPDO2
(position and velocity actual values in encoder increments) on every SYNC, encoded by
cantools and written by python-can's candump writer. The README's CiA 402 example and
tests/test_torque_drive.py read such logs; docs/cia402.md describes the drive.

    python tools/cia402_log.py servo.log [--seed N] [--duration S] [--effects ...]
"""

from __future__ import annotations

import argparse
import math
import sys
from collections.abc import Sequence
from pathlib import Path

import can
import cantools
import numpy as np

from canrls.sim.scenario import SimResult, scenario, simulate

#: the drive's DBC (two TPDOs, the ‰ in Windows-1252)
DBC = Path(__file__).resolve().parents[1] / "tests" / "data" / "cia402_drive.dbc"
#: the drive's ratings: rated torque 0x6076 [N·m], rated current 0x6075 [A], encoder
#: increments per revolution (0x608F)
RATED_TORQUE, RATED_CURRENT, INCREMENTS = 0.32, 3.2, 131072


def write_log(res: SimResult, path: str | Path) -> None:
    """The measured run ``res`` as the CiA 402 drive sends it, into the log ``path``."""
    db = cantools.database.load_file(str(DBC))
    tpdo1, tpdo2 = db.get_message_by_name("TPDO1"), db.get_message_by_name("TPDO2")
    m = res.measured
    assert m.current is not None
    torque = res.truth.kt * m.current  # what the drive computes from its current
    turns = INCREMENTS / (2 * math.pi)
    position = np.unwrap(m.position)  # the position actual value is multi-turn
    with can.CanutilsLogWriter(str(path)) as w:
        for k in range(len(m)):
            d1 = tpdo1.encode({"Statusword": 0x0237,  # operation enabled
                               "TorqueActual": round(1000 * torque[k] / RATED_TORQUE),
                               "CurrentActual": round(1000 * m.current[k] / RATED_CURRENT)})
            d2 = tpdo2.encode({"PositionActual": round(position[k] * turns),
                               "VelocityActual": round(m.speed[k] * turns)})
            for dt, fid, data in ((0.0, 0x181, d1), (1e-4, 0x281, d2)):
                w.on_message_received(can.Message(timestamp=float(m.t[k]) + dt,
                                                  arbitration_id=fid, is_extended_id=False,
                                                  data=data))


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("out", help="the candump log to write")
    ap.add_argument("--seed", type=int, default=5, help="the simulation's seed")
    ap.add_argument("--duration", type=float, default=8.0, help="seconds of the run")
    ap.add_argument("--effects", default="inertia,viscous,coulomb",
                    help="the simulated drive's effects")
    args = ap.parse_args(argv)
    write_log(simulate(scenario("standard", effects=args.effects, seed=args.seed,
                                duration=args.duration)), args.out)
    print(args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
