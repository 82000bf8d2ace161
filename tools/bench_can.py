#!/usr/bin/env python3
"""The CAN layer's throughput on one million frames: encode, strict decode, pairing.

Prints figures; it is not a test (the goals stood in timed unit tests before, which a
loaded machine made fail). The frames are the default DBC's feedback messages at
1 kHz with random values (seeded); each figure is the best of ``--repeat`` warm runs.

Goals: encoding at least 1 M frames/s; decoding 1 M frames in under 0.6 s; pairing
1 M frames in under 1 s. Also printed (no goal): the reorderer (frames put back in
counter order before decoding) on the clean frames and on 20 % neighbour swaps, in
blocks of 65536 and of 64 frames (the daemon's blocks are whatever arrived).

Usage::

    python tools/bench_can.py [--frames 1000000] [--repeat 3]
"""

from __future__ import annotations

import argparse
import math
import time
from collections.abc import Callable

import numpy as np

from canrls.can.decoder import Decoder
from canrls.can.encoder import FeedbackEncoder
from canrls.can.protocol import Protocol
from canrls.processor.pairing import Pairer
from canrls.processor.reorder import Reorderer
from canrls.sim.faults import inject


def best(fn: Callable[[], object], repeat: int) -> float:
    """Shortest wall time [s] of ``repeat`` calls of ``fn`` (after one warm-up call)."""
    fn()
    out = math.inf
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        out = min(out, time.perf_counter() - t0)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=1_000_000)
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args()
    proto = Protocol.load()
    n = args.frames // len(proto.messages)  # one frame of each message per period
    rng = np.random.default_rng(4)
    t = np.arange(n) * 1e-3
    values = (rng.uniform(-800, 800, n), rng.uniform(-800, 800, n),
              rng.uniform(0, 2 * np.pi, n), rng.uniform(-320, 320, n))
    enc = FeedbackEncoder(proto)
    block = enc.encode(t, *values)
    decoded = Decoder(proto).decode(block)
    frames = len(block)
    t_enc = best(lambda: enc.encode(t, *values), args.repeat)
    t_dec = best(lambda: Decoder(proto).decode(block), args.repeat)
    t_pair = best(lambda: Pairer(proto).push(decoded), args.repeat)
    print(f"{frames} frames of {len(proto.messages)} messages, best of {args.repeat}:")
    for what, sec, ok in (("encode", t_enc, frames / t_enc >= 1e6),
                          ("strict decode", t_dec, t_dec * 1e6 / frames < 0.6),
                          ("pairing", t_pair, t_pair * 1e6 / frames < 1.0)):
        print(f"  {what:<14} {frames / sec / 1e6:6.2f} M frames/s  ({sec:.3f} s)  "
              f"goal {'met' if ok else 'NOT met'}")
    swapped = inject(block, "reorder=0.2", seed=1)[0]

    def reorder(b: object, size: int) -> None:
        r = Reorderer(proto.messages)
        for k in range(0, frames, size):
            r.push(b.take(slice(k, k + size)))  # type: ignore[attr-defined]
        r.flush()

    for what, b in (("clean", block), ("20 % swapped", swapped)):
        for size in (65536, 64):
            sec = best(lambda b=b, size=size: reorder(b, size), 1)
            print(f"  reorder {what:<12} blocks of {size:<5} {frames / sec / 1e6:6.2f} M "
                  f"frames/s  ({sec:.3f} s)")


if __name__ == "__main__":
    main()
