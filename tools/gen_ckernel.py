"""Generate what the C kernel (src/canrls/c/firmware/) is built and checked with, from the
Python spec.

The C text of a plan (:func:`canrls.firmware.kernel_export.plan_c`) is the package's, which
``canrls export-c`` writes for a user's model; this script adds the test vectors and
the sample streams of ``make target``.

The Python :class:`canrls.estimation.fixed.estimator.FixedRLS` is the specification; this script
only writes its integers in forms C reads:

* :func:`plan_c` -- the plan (``FixedRLS.constants``) as a ``canrls_plan_q31`` initialiser;
* :func:`write_vectors` -- a test-vector file for
  ``src/canrls/c/firmware/drivers/vector_driver.c`` (state taken from
  ``FixedRLS.state()``, the samples, a frozen flag per sample) and the lines the driver
  must print, computed by the Python estimator step by step;
* :func:`stream_header` -- a C header with a plan, an initial state, a sample stream and the
  final estimate Python reaches on it (the bare-metal example checks it);
* :func:`log_stream` -- the quantised ``(phi, y)`` rows the pipeline hands ``FixedRLS`` when it
  replays a recorded log (checked: the same rows give the pipeline's own final estimate).

Command line::

    python tools/gen_ckernel.py example OUT.h [--log drive.log] [--limit N]
    python tools/gen_ckernel.py synthetic OUT.h --n 6 [--samples 64] [--lam 0.99]
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import numpy.typing as npt

from canrls.core.c_escape import c_comment, c_float, c_identifier, c_int, c_uint
from canrls.estimation.fixed.estimator import FixedRLS
from canrls.estimation.fixed.formats import SITES, FixedConfig
from canrls.firmware.kernel_export import plan_c

IntArray = npt.NDArray[np.int64]


# ------------------------------------------------------------------ C text
def c_array(name: str, values: Sequence[int] | npt.ArrayLike, per_line: int = 8,
            ctype: str = "int32_t") -> str:
    """``static const CTYPE NAME[] = {...};``."""
    render = c_uint if ctype.startswith("uint") else c_int
    bits = 64 if ctype.endswith("64_t") else 32
    vals = [render(int(v), bits, f"{name}[]") for v in np.asarray(values).ravel()]
    lines = [", ".join(vals[i:i + per_line]) for i in range(0, len(vals), per_line)]
    inner = ",\n    ".join(lines) if lines else "0"
    return f"static const {ctype} {c_identifier(name, 'array name')}[] = {{\n    {inner},\n}};\n"


def upper(P: IntArray) -> IntArray:
    """The upper triangle of ``P`` packed by rows (the C kernel's layout of ``P~``)."""
    n = P.shape[0]
    return np.asarray(P[np.triu_indices(n)], dtype=np.int64)


# ------------------------------------------------------------------ vectors
def state_words(est: FixedRLS) -> list[int]:
    """``theta, theta_frac, P_up, P_frac_up, e, c, frozen, counts``: the state line of a
    vector file."""
    s = est.state()
    return [*s["theta"].tolist(), *s["theta_frac"].tolist(), *upper(est.P).tolist(),
            *upper(est.P_frac).tolist(), s["P_exp"], s["P_scale"], int(s["frozen"]),
            *s["counts"].tolist()]


def write_vectors(path: Path, est: FixedRLS, Phi: IntArray, Y: IntArray,
                  frozen: npt.ArrayLike | None = None) -> list[str]:
    """Write a vector file for ``vector_driver`` and return the lines it must print.

    The C state starts from ``est.state()`` (whatever set it up: the constructor's P0,
    a warm-up, a checkpoint); ``est`` then runs the samples one by one (``update``),
    frozen where ``frozen`` is true, and each expected line is read off it.
    """
    N, n = Phi.shape
    fz = np.zeros(N, bool) if frozen is None else np.asarray(frozen, bool)
    # the expected lines come from the specification (canrls._fixedspec), never the
    # target's kernel (canrls._fixed)
    est.backend = "spec"
    k = est.constants
    lines = [f"plan {len(k)}", *(f"{name} {v}" for name, v in k.items()),
             f"n {n}", "state " + " ".join(map(str, state_words(est))), f"steps {N}"]
    lines += [" ".join(map(str, [int(fz[i]), *Phi[i].tolist(), int(Y[i])])) for i in range(N)]
    path.write_text("\n".join(lines) + "\n")
    expected = []
    for i in range(N):
        if fz[i]:
            est.freeze()
        else:
            est.resume()
        st = est.update(Phi[i], int(Y[i]))
        s = est.saturations
        words = [0 if fz[i] else 1, st.eps, st.trace_P, st.P_exp, int(st.flags),
                 *est.theta.tolist(), *est.theta_frac.tolist(), *upper(est.P).tolist(),
                 *upper(est.P_frac).tolist(), est.P_scale,
                 *(s[site] for site in SITES)]
        expected.append(" ".join(map(str, words)))
    return expected


# ------------------------------------------------------------------ streams
@dataclass(frozen=True)
class Stream:
    """Quantised samples and the estimator (in its initial state) that takes them."""

    est: FixedRLS
    Phi: IntArray
    Y: IntArray
    source: str


def synthetic_stream(n: int, samples: int, lam: float = 0.99, alpha: float = 1e-2,
                     seed: int = 0, warm: int = 0) -> Stream:
    """A seeded, well-excited regression ``y = phi' theta + noise`` quantised for ``n``.

    ``warm`` samples run in Python first: the stream then starts from that state (the
    steady state of the recursion rather than its start-up).
    """
    rng = np.random.default_rng(seed)
    cfg = FixedConfig.auto(n, alpha, lam)
    est = FixedRLS(cfg, n, lam, alpha)
    Phi = rng.uniform(-1, 1, (warm + samples, n))
    theta = rng.uniform(-0.5, 0.5, n) / n
    Y = Phi @ theta + 1e-3 * rng.standard_normal(warm + samples)
    Pq, Yq, _ = cfg.quantize_inputs(Phi, Y)
    if warm:
        est.run(Pq[:warm], Yq[:warm], record=False)
    return Stream(est, Pq[warm:], Yq[warm:],
                  f"synthetic n={n} lam={lam} alpha={alpha} seed={seed} after {warm} samples")


def log_stream(log: Path | None = None, effects: str = "inertia,viscous,coulomb,offset",
               seed: int = 4, duration: float = 20.0) -> Stream:
    """The quantised rows the pipeline hands ``FixedRLS`` on a recorded log.

    ``log=None`` records one first: the simulated drive (``seed``, ``duration``)
    written as a candump log. The rows are the pipeline's used regressor rows and
    targets (``record=True``), quantised like the pipeline quantises them; a fresh
    estimator run over them must reach the pipeline's own final estimate (checked).
    """
    from canrls.can.logs import write_candump
    from canrls.processor import FrameProcessor
    from canrls.processor.config import AppConfig, prepare

    with tempfile.TemporaryDirectory() as tmp:
        if log is None:
            from canrls.sim.scenario import scenario, simulate

            res = simulate(scenario("standard", effects=effects, seed=seed,
                                    duration=duration))
            log = Path(tmp) / "drive.log"
            write_candump(log, [res.frames])
            source = (f"the simulated drive (standard scenario, {effects}, seed {seed}, "
                      f"{duration:g} s) recorded as a candump log")
        else:
            source = str(log)
        cfg = AppConfig()
        cfg.model = {"effects": effects.split(","), "kt": 0.1}
        prot, model, settings = prepare(cfg)
        from canrls.can.logs import read_frames

        proc = FrameProcessor(prot, model, settings)
        rows: list[npt.NDArray[np.float64]] = []
        ys: list[npt.NDArray[np.float64]] = []

        def keep(block: object) -> None:
            # the pipeline after the calibration window (its normalisation is frozen then)
            eq = proc.pipeline.estimators[0].equation
            b = block.equations[0]  # type: ignore[attr-defined]
            if b.phi is not None and len(b.used):
                rows.append(b.phi[b.used])
                ys.append(np.ldexp(b.y[b.used], -eq.scaling.output))

        for frames in read_frames(log):
            keep(proc.process(frames, True))
        keep(proc.flush(True))
    est0 = proc.pipeline.estimators[0]
    eq = est0.equation
    Phi = np.concatenate(rows) if rows else np.zeros((0, eq.n))
    Y = np.concatenate(ys) if ys else np.zeros(0)
    f = est0.frls
    est = FixedRLS(f.config, f.n, f.lam, f.alpha, trace_max=f.trace_max)
    Pq, Yq, _ = est.config.quantize_inputs(Phi, Y)
    check = FixedRLS.from_state(est.state())
    check.run(Pq, Yq, record=False)
    if not np.array_equal(check.theta, f.theta):
        raise RuntimeError("the captured rows do not reproduce the pipeline's fixed-point "
                           "estimate; the pipeline's input path changed")
    return Stream(est, Pq, Yq, f"{source} ({eq.name}: {eq.n} parameters)")


def stream_header(s: Stream, limit: int | None = None, guard: str = "CANRLS_STREAM_H") -> str:
    """A C header: plan, initial state, samples, and the state Python reaches on them.

    The initial state is ``s.est``'s (``theta``, ``theta_frac``, the packed upper triangle
    of ``P`` and of ``P_frac``, ``e``, ``c``: the C side restores it with
    ``canrls_restore_q31``); the final ``theta``, ``theta_frac``, ``P``, ``P_frac``,
    ``e``, ``c`` and counters are those of the Python estimator after the same samples
    (``FixedRLS.run``), counted from zero.
    """
    Phi, Y = (s.Phi, s.Y) if limit is None else (s.Phi[:limit], s.Y[:limit])
    st = s.est.state()
    st["counts"] = np.zeros_like(st["counts"])
    est = FixedRLS.from_state(st)
    theta0, tf0, P0, Pf0 = est.theta.copy(), est.theta_frac.copy(), upper(est.P), \
        upper(est.P_frac)
    e0, c0 = est.P_exp, est.P_scale
    est.backend = "spec"  # the final state of the specification, never the C extension
    est.run(Phi, Y, record=False)
    n = est.n
    cnt = est.saturations
    parts = [
        f"/* Generated by tools/gen_ckernel.py from the Python FixedRLS: do not edit.\n"
        f" * source: {c_comment(s.source, 'source')}\n"
        f" * {c_comment(est.config.label, 'label')}, n = {n}, lam = {c_float(est.lam)}, "
        f"alpha = [{', '.join(c_float(float(a)) for a in np.ravel(est.alpha))}], "
        f"{len(Y)} samples */\n",
        f"#ifndef {c_identifier(guard, 'guard')}\n#define {guard}\n\n"
        f"#include \"canrls_fixed.h\"\n\n",
        f"#define STREAM_N {c_uint(n)}\n#define STREAM_SAMPLES {c_uint(len(Y))}\n"
        f"#define STREAM_E0 {c_int(e0)}\n#define STREAM_C0 {c_int(c0)}\n"
        f"#define STREAM_E_FINAL {c_int(est.P_exp)}\n"
        f"#define STREAM_C_FINAL {c_int(est.P_scale)}\n\n",
        plan_c(est.constants, "stream_plan"),
        c_array("stream_theta0", theta0),
        c_array("stream_theta_frac0", tf0, ctype="uint32_t"),
        c_array("stream_P0", P0),
        c_array("stream_P_frac0", Pf0),
        c_array("stream_phi", Phi),
        c_array("stream_y", Y),
        c_array("stream_theta_final", est.theta),
        c_array("stream_theta_frac_final", est.theta_frac, ctype="uint32_t"),
        c_array("stream_P_final", upper(est.P)),
        c_array("stream_P_frac_final", upper(est.P_frac)),
        c_array("stream_counts_final", [cnt[k] for k in SITES], ctype="uint32_t"),
        f"\n#endif /* {guard} */\n",
    ]
    return "\n".join(parts)


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    ex = sub.add_parser("example", help="the bare-metal example's stream from a recorded log")
    ex.add_argument("out", type=Path)
    ex.add_argument("--log", type=Path, default=None, help="default: record the simulator's")
    ex.add_argument("--limit", type=int, default=2000, help="samples kept (default 2000)")
    sy = sub.add_parser("synthetic", help="a seeded synthetic stream (instruction counts)")
    sy.add_argument("out", type=Path)
    sy.add_argument("--n", type=int, required=True)
    sy.add_argument("--samples", type=int, default=64)
    sy.add_argument("--lam", type=float, default=0.99)
    sy.add_argument("--alpha", type=float, default=1e-2)
    sy.add_argument("--warm", type=int, default=0, help="samples run in Python first")
    a = ap.parse_args(argv)
    if a.cmd == "example":
        s = log_stream(a.log)
        a.out.write_text(stream_header(s, a.limit))
    else:
        s = synthetic_stream(a.n, a.samples, a.lam, a.alpha, warm=a.warm)
        a.out.write_text(stream_header(s))
    print(f"{a.out}: {s.source}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
