"""Cost of the target's integer path (the C of ``canrls export-c`` as ``canrls._target``)
in ``canrls fit`` and in the daemon, against the kernel's fixed column on the float front end.

Prints figures; it is not a test. On a simulated log (``--seconds``, 1 kHz, seed 3):

* **fit**: the whole command ``canrls fit LOG --kt 0.1 --quiet`` in a fresh process, with
  ``--fixed kernel`` and with the default (the target's path), ``--runs`` times each,
  alternating; the best and the median wall time of each, and their ratio. Then, in one
  process, the parts the target's path adds: the model's integers
  (:func:`canrls.firmware.target_fit.fit_model`) and the log read again and run through the C.
* **daemon**: a daemon built as ``canrls run`` builds it (``[daemon] fixed = "kernel"``
  and the default), fed the log's frames in blocks of ``--block`` frames through
  ``Daemon.process`` (what its estimator thread does with a block); the thread CPU time
  per frame, the best of ``--runs`` runs.

Usage::

    python tools/bench_target_path.py [--seconds 20] [--runs 5] [--block 256]
"""

from __future__ import annotations

import argparse
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

EFFECTS = "inertia,viscous,coulomb,offset,unbalance"


def _canrls(*args: str) -> tuple[float, float]:
    """Wall time and CPU time (user + system) of one ``canrls`` command in a fresh
    interpreter [s]."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t = time.perf_counter()
    subprocess.run([sys.executable, "-m", "canrls", *args], check=True,
                   stdout=subprocess.DEVNULL)
    wall = time.perf_counter() - t
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    return wall, (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)


def bench_fit(log: Path, runs: int) -> None:
    times: dict[str, list[tuple[float, float]]] = {"kernel": [], "target": []}
    for _ in range(runs):
        for path in times:
            how = ["--fixed", "kernel"] if path == "kernel" else []
            times[path].append(_canrls("fit", str(log), "--kt", "0.1", "-e", EFFECTS,
                                       "--quiet", *how))
    for i, what in enumerate(("wall", "CPU")):
        best = {k: min(x[i] for x in v) for k, v in times.items()}
        med = {k: statistics.median(x[i] for x in v) for k, v in times.items()}
        print(f"canrls fit, {what} time, {runs} runs each: --fixed kernel best "
              f"{best['kernel']:.2f} s, median {med['kernel']:.2f} s; the target's path "
              f"(default) best {best['target']:.2f} s, median {med['target']:.2f} s; ratio "
              f"{best['target'] / best['kernel']:.2f} (best), "
              f"{med['target'] / med['kernel']:.2f} (median)")
    _fit_parts(log, runs)


def _fit_parts(log: Path, runs: int) -> None:
    from canrls.cli._common import setup
    from canrls.cli.main import build_parser
    from canrls.firmware.native import TargetFeed
    from canrls.firmware.target_fit import fit_model
    from canrls.firmware.vectors import log_blocks
    from canrls.processor.config import prepare
    from canrls.processor.replay import fit_logs

    args = build_parser("fit").parse_args(["fit", str(log), "--kt", "0.1", "-e", EFFECTS])
    protocol, model, settings = prepare(setup(args, every_axis=True).one_axis())

    def best(f: object) -> float:
        out = []
        for _ in range(runs):
            t = time.perf_counter()
            f()  # type: ignore[operator]
            out.append(time.perf_counter() - t)
        return min(out)

    res = fit_logs([log], protocol, model, settings)
    t_fit = best(lambda: fit_logs([log], protocol, model, settings))
    t_model = best(lambda: fit_model(res, protocol, settings))
    tm = fit_model(res, protocol, settings)

    def run() -> None:
        feed = TargetFeed(tm)
        for b in log_blocks([log]):
            feed.feed(b)

    t_run = best(run)
    frames = sum(len(b) for b in log_blocks([log]))
    print(f"  in one process: the replay {t_fit * 1e3:.0f} ms; the target's path adds its "
          f"model {t_model * 1e3:.1f} ms and the log read again and run through the C "
          f"{t_run * 1e3:.1f} ms ({t_run / frames * 1e9:.0f} ns a frame, {frames} frames)")


def bench_daemon(log: Path, runs: int, block: int) -> None:
    from canrls.can.frameblock import FrameBlock
    from canrls.can.logs import read_frames
    from canrls.cli.main import build_parser
    from canrls.cli.run import build_daemon

    frames = FrameBlock.concat(list(read_frames(log)))
    blocks = [frames.take(slice(k, k + block)) for k in range(0, len(frames), block)]
    cpu: dict[str, float] = {}
    for path in ("kernel", "target"):
        with tempfile.TemporaryDirectory() as tmp:
            cfg = Path(tmp) / "daemon.toml"
            cfg.write_text(f'[daemon]\nfixed = "{path}"\n')
            best = float("inf")
            for _ in range(runs):
                d = build_daemon(build_parser("run").parse_args(
                    ["run", "-i", "virtual", "-c", "bench-target-path", "--kt", "0.1", "-e",
                     EFFECTS, "--config", str(cfg)]))
                try:
                    t = time.thread_time()
                    for b in blocks:
                        d.process(b)
                    best = min(best, time.thread_time() - t)
                finally:
                    d.stop()
            cpu[path] = best / len(frames)
    print(f"daemon, {len(frames)} frames in blocks of {block}: CPU a frame with fixed = "
          f"\"kernel\" {cpu['kernel'] * 1e6:.2f} us, \"target\" (default) "
          f"{cpu['target'] * 1e6:.2f} us: {(cpu['target'] - cpu['kernel']) * 1e6:+.2f} us "
          f"(best of {runs})")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seconds", type=float, default=20.0)
    ap.add_argument("--runs", type=int, default=5)
    ap.add_argument("--block", type=int, default=256)
    a = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        log = Path(tmp) / "drive.log"
        subprocess.run([sys.executable, "-m", "canrls", "sim", "--out", str(log), "--duration",
                        str(a.seconds), "--effects", EFFECTS, "--seed", "3"], check=True,
                       stdout=subprocess.DEVNULL)
        print(f"{a.seconds:g} s simulated log at 1 kHz, model {EFFECTS}")
        bench_fit(log, a.runs)
        bench_daemon(log, a.runs, a.block)


if __name__ == "__main__":
    main()
