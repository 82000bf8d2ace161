"""Build the C extensions of canrls (sources in src/canrls/c/host; the
fixed-point kernel they share with the target in src/canrls/c/firmware); all other metadata is in
pyproject.toml. ``pip install`` (and so ``make test`` / ``make demo``) compiles them with
the machine's C compiler (GCC) and the Python headers."""

from setuptools import Extension, setup

#: compile flags of every extension: C99, warnings as errors, no floating-point contraction
#: and no -ffast-math (an FMA or a reassociation would round differently from the
#: reference, so the float kernels give the same bits on every machine and in every build)
_CFLAGS = ["-O2", "-std=c99", "-Wall", "-Wextra", "-Werror", "-ffp-contract=off"]

EXTENSIONS: list[Extension] = [
    # the per-sample float loops of the estimation (RLS, SVF, selection, unwrapping,
    # pipeline sums; the diagnosis's harmonic columns), one implementation for the daemon
    # and the offline replay.
    # -fvect-cost-model=dynamic: GCC's -O2 default vectorises only loops whose trip count
    # is known; these run over n parameters, and vectorised (element-wise, so the same
    # bits; reductions stay in order) the float RLS is about 30 % faster at n = 8
    Extension("canrls._kernels", sources=["src/canrls/c/host/kernels.c"],
              depends=["src/canrls/c/host/kernels_rls.h", "src/canrls/c/host/pyargs.h"],
              extra_compile_args=[*_CFLAGS, "-fvect-cost-model=dynamic"]),
    # the per-frame loops of the CAN layer (strict decoding, counters, CRC, pairing):
    # canrls.can, live and offline
    Extension("canrls._can", sources=["src/canrls/c/host/can.c"], extra_compile_args=_CFLAGS),
    # the candump reader and writer (text <-> frame arrays): canrls.can.candump
    Extension("canrls._candump", sources=["src/canrls/c/host/candump.c"],
              depends=["src/canrls/c/host/pyargs.h"], extra_compile_args=_CFLAGS),
    # the bulk receive of SocketCAN frames (recvmmsg into a FrameBlock's arrays):
    # canrls.live.socketcan, the daemon's reader of a python-can SocketcanBus. Linux only;
    # it builds everywhere (recv raises NotImplementedError where recvmmsg is missing)
    Extension("canrls._rx", sources=["src/canrls/c/host/rx.c"], extra_compile_args=_CFLAGS),
    # the fixed-point RLS kernel (canrls_fixed.c, the target's code) for
    # canrls.estimation.fixed.estimator.FixedRLS
    Extension("canrls._fixed",
              sources=["src/canrls/c/host/fixed_module.c",
                       "src/canrls/c/firmware/canrls_fixed.c"],
              include_dirs=["src/canrls/c/firmware"],
              depends=["src/canrls/c/firmware/canrls_fixed.h"],
              extra_compile_args=_CFLAGS),
    # the fixed-point RLS as specified (every update form, any n) for
    # canrls.estimation.fixed.kernels: where the target's kernel does not apply
    Extension("canrls._fixedspec", sources=["src/canrls/c/host/fixed_spec.c"],
              depends=["src/canrls/c/host/pyargs.h"], extra_compile_args=_CFLAGS),
    # the simulated drive's loop (sensors, controllers, RK4): canrls.sim.plant
    Extension("canrls._sim", sources=["src/canrls/c/host/sim.c"],
              depends=["src/canrls/c/host/pyargs.h"], extra_compile_args=_CFLAGS),
]

setup(ext_modules=EXTENSIONS)
