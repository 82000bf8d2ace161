"""Reading a candump log with epoch timestamps (``candump -l``) against a zero-based one.

Prints figures; it is not a test. Writes two candump logs of the same frames (the
default DBC's feedback frames of a ``--duration`` second run at 1 kHz, two frames per
period: 10 minutes are 1.2 M frames), one with times from 0 and one from an epoch time
(``--epoch``, 1.7e9 s, as ``candump -l`` writes), then reads each with
:func:`canrls.can.logs.read_frames` warm (after one untimed read: the first read of the
file is not timed) and prints frames/s, best of ``--repeat``;
then the whole replay, ``fit_log`` (read, decode, measure and check the period, pair,
estimate), the same way. Both logs should take the compiled fast path and replay at the
same speed; the goal is at least 1 M frames/s each.

Usage::

    python tools/bench_epoch.py [--duration 600] [--epoch 1.7e9] [--repeat 3] [--dir DIR]
                                [--no-fit]
"""

from __future__ import annotations

import argparse
import math
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from canrls.can.encoder import FeedbackEncoder
from canrls.can.frameblock import FrameBlock
from canrls.can.logs import LogReadStats, read_frames, write_candump
from canrls.can.protocol import Protocol


def frames(duration: float, t0: float, dt: float = 1e-3, chunk: int = 65536
           ) -> Iterator[FrameBlock]:
    """Feedback frames of a sine speed profile, ``chunk`` periods at a time."""
    enc = FeedbackEncoder(Protocol.load(), clip=True, stagger=1e-4)
    n = int(round(duration / dt))
    for k0 in range(0, n, chunk):
        k = np.arange(k0, min(n, k0 + chunk), dtype=np.float64)
        t = k * dt
        w = 50.0 * np.sin(2 * math.pi * 0.5 * t)
        yield enc.encode(t0 + t, current=0.5 * np.cos(2 * math.pi * 0.5 * t), speed=w,
                         position=np.mod(100.0 * t, 2 * math.pi), voltage=0.1 * w)


def read_rate(path: Path, repeat: int) -> tuple[float, int, int]:
    """(best frames/s, frames, lines the slow path took)."""
    best = math.inf
    n = 0
    slow = 0
    for _ in range(repeat + 1):  # the first, untimed, warms up
        st = LogReadStats()
        t = time.perf_counter()
        n = sum(len(b) for b in read_frames(path, stats=st))
        el = time.perf_counter() - t
        best = min(best, el) if _ else best
        slow = int(getattr(st, "slow_lines", 0) or 0)
    return n / best, n, slow


def fit_rate(path: Path, repeat: int) -> tuple[float, int]:
    """(best frames/s of ``fit_log``, samples used)."""
    from canrls.processor.config import AppConfig, prepare
    from canrls.processor.replay import fit_log

    protocol, model, settings = prepare(AppConfig())
    best = math.inf
    used = 0
    for i in range(repeat + 1):
        t = time.perf_counter()
        res = fit_log(path, protocol, model, settings)
        el = time.perf_counter() - t
        best = min(best, el) if i else best
        used = res.estimates.samples
    return res.frames.total / best, used


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--duration", type=float, default=600.0)
    ap.add_argument("--epoch", type=float, default=1.7e9)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--dir", type=Path, default=None)
    ap.add_argument("--no-fit", action="store_true", help="time the reader only")
    a = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        d = a.dir or Path(tmp)
        for name, t0 in (("zero-based", 0.0), ("epoch", a.epoch)):
            path = d / f"bench_{name}.log"
            write_candump(path, frames(a.duration, t0))
            with open(path, "rb") as f:
                first = f.readline().decode().strip()
            rate, n, slow = read_rate(path, a.repeat)
            print(f"{name:>10}: {n} frames ({path.stat().st_size / 2**20:.0f} MiB), "
                  f"{rate / 1e6:.2f} M frames/s warm, first line {first!r}"
                  + (f", {slow} lines on the slow path" if slow else ""))
            if not a.no_fit:
                frate, used = fit_rate(path, a.repeat)
                print(f"{'':>10}  fit_log: {frate / 1e6:.2f} M frames/s warm ({used} samples "
                      f"used)")


if __name__ == "__main__":
    main()
