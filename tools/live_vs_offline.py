#!/usr/bin/env python3
"""The same log offline and live, through real processes: `canrls fit` against `canrls run`.

1. ``canrls fit LOG --json`` (a simulated log is recorded first when no LOG is given);
2. a python-can-remote server on 127.0.0.1 (a virtual bus behind it: no CAN hardware);
3. ``canrls run -i remote`` listening on it, with the same model flags;
4. ``python -m can.player`` replaying LOG onto it at the log's own pace;
5. this tool, a python-can client of the same server, keeps the parameter frames the
   daemon publishes and decodes them (:class:`canrls.can.estimator_frames.FrameDecoder`).

Prints every parameter offline and as last published (float and fixed point) with the
relative difference, and the fixed-vs-float divergence offline and live, and exits 1 if
any is more than ``--tol`` (default 1 %) apart.
The player sends in real time: a 20 s log takes about 20 s. Frames arrive with the
server's clock, so the daemon pairs them on their arrival times, as on a real bus.

    python tools/live_vs_offline.py                 # a 20 s simulated log
    python tools/live_vs_offline.py drive.log --effects inertia,viscous,coulomb --kt 0.1
    python tools/live_vs_offline.py hsm/idf_pos_0.06_1.log --kt 0.0458 \
        --effects inertia,viscous,coulomb,offset --flags "--dbc hsm/hsm150_drive.dbc \
        --signal current=MC_Feedback1.PhaseCurrentIq ..."
"""

from __future__ import annotations

import argparse
import json
import shlex
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import can

from canrls.can.estimator_frames import FrameDecoder, frame_ids
from canrls.can.logs import read_frames, write_candump
from canrls.sim.scenario import scenario, simulate

PY = sys.executable


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def wait_port(port: int, timeout: float) -> None:
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        with socket.socket() as s:
            if s.connect_ex(("127.0.0.1", port)) == 0:
                return
        time.sleep(0.1)
    raise SystemExit(f"error: the remote server on 127.0.0.1:{port} did not start")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("log", nargs="?", help="CAN log (default: a simulated 20 s log)")
    ap.add_argument("--effects", default="inertia,viscous,coulomb,offset,cogging:6")
    ap.add_argument("--kt", default="0.1")
    ap.add_argument("--seed", type=int, default=5)
    ap.add_argument("--duration", type=float, default=20.0,
                    help="length of the simulated log [s]")
    ap.add_argument("--tol", type=float, default=0.01, help="relative tolerance (0.01)")
    ap.add_argument("--flags", default="",
                    help="more options of both canrls commands, one string (a DBC and "
                         "its signal map)")
    args = ap.parse_args()
    model_flags = ["--effects", args.effects, "--kt", args.kt, *shlex.split(args.flags)]
    with tempfile.TemporaryDirectory() as tmp:
        if args.log:
            log = Path(args.log)
            # the player sends at the log's pace: its length from its timestamps
            ts = [(float(b.t[0]), float(b.t[-1])) for b in read_frames(log) if len(b.t)]
            length = ts[-1][1] - ts[0][0]
        else:
            res = simulate(scenario("standard", effects=args.effects, seed=args.seed,
                                    duration=args.duration))
            log = Path(tmp) / "drive.log"
            write_candump(log, [res.frames])
            length = args.duration
        fit = subprocess.run([PY, "-m", "canrls", "fit", str(log), *model_flags, "--json",
                              "--quiet"], capture_output=True, text=True, check=True)
        offline = json.loads(fit.stdout)["parameters"]
        port = free_port()
        remote = f"127.0.0.1:{port}"
        procs: list[subprocess.Popen[str]] = []
        client: can.BusABC | None = None
        try:
            procs.append(subprocess.Popen(
                [PY, "-m", "can_remote", "-i", "virtual", "-c", "live-vs-offline",
                 "-H", "127.0.0.1", "-p", str(port)],
                stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, text=True))
            wait_port(port, 20)
            client = can.Bus(interface="remote", channel=remote)
            reader = can.BufferedReader()
            notifier = can.Notifier(client, [reader], timeout=0.1)
            daemon = subprocess.Popen(
                [PY, "-m", "canrls", "run", "-i", "remote", "-c", remote, *model_flags,
                 "--duration", f"{length + 15:.0f}", "--json"],
                stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
            procs.append(daemon)
            time.sleep(5.0)  # the daemon's start
            subprocess.run([PY, "-m", "can.player", "-i", "remote", "-c", remote, str(log)],
                           check=True, capture_output=True)
            out, err = daemon.communicate(timeout=length + 60)
            notifier.stop()
        finally:
            if client is not None:
                client.shutdown()
            for p in procs:
                if p.poll() is None:
                    p.terminate()
                    p.wait(10)
        if daemon.returncode != 0:
            sys.stderr.write(err)
            raise SystemExit(f"error: canrls run exited {daemon.returncode}")
        live = json.loads(out)
    ids = frame_ids()
    dec = FrameDecoder()
    while (m := reader.get_message(0.0)) is not None:
        if m.arbitration_id in ids.published:
            dec.feed(m)
    published = {p.name: p for p in dec.table()}
    print(f"{log.name}: {live.get('samples')} samples live, "
          f"{json.loads(fit.stdout)['samples']} offline")
    print(f"daemon's frames: {json.dumps(live.get('frames'))}")
    print(f"{'parameter':16s} {'offline':>13s} {'published':>13s} {'rel':>9s}   "
          f"{'fixed off':>13s} {'fixed pub':>13s} {'rel':>9s}")
    worst = 0.0
    for name, want in offline.items():
        got = published.get(name)
        if got is None or got.float_value is None or got.fixed_value is None:
            print(f"{name:16s} not published")
            worst = float("inf")
            continue
        r1 = abs(got.float_value - want["value"]) / abs(want["value"])
        r2 = abs(got.fixed_value - want["fixed"]) / abs(want["fixed"])
        worst = max(worst, r1, r2)
        print(f"{name:16s} {want['value']:13.6g} {got.float_value:13.6g} {r1:9.2e}   "
              f"{want['fixed']:13.6g} {got.fixed_value:13.6g} {r2:9.2e}")
    ok = worst <= args.tol
    print(f"largest relative difference {worst:.3g} ({'within' if ok else 'OUTSIDE'} "
          f"{args.tol:g})")
    for name, eq in json.loads(fit.stdout)["equations"].items():
        div = live.get("equations", {}).get(name, {}).get("divergence")
        print(f"fixed-vs-float divergence, {name}: offline {eq['divergence']:.3g}, live "
              + (f"{div:.3g}" if isinstance(div, float) else "not reported"))
    return 0 if ok else 1


if __name__ == "__main__":
    raise SystemExit(main())
