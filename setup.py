"""Build the C extensions of canrls (sources in src/canrls/c); all other metadata is in
pyproject.toml. ``pip install`` (and so ``make test`` / ``make demo``) compiles them with
the machine's C compiler and the Python headers."""

from setuptools import Extension, setup

#: -ffp-contract=off and no -ffast-math: no fused multiply-add, no reassociation, so the
#: float kernels give the same bits on every machine and in every build.
#: -fvect-cost-model=dynamic: GCC's -O2 default ("very cheap") vectorises only loops
#: whose trip count is known; the kernels' loops run over n parameters, and vectorised
#: (element-wise: the results are the same bits) the float RLS is about 30 % faster at
#: n = 8. Reductions stay in order (no -fassociative-math).
CFLAGS = ["-O2", "-fvect-cost-model=dynamic", "-std=c99", "-Wall", "-Wextra", "-Werror",
          "-ffp-contract=off"]

EXTENSIONS: list[Extension] = [
    # the per-sample float kernels of the estimation (RLS, SVF, selection, bookkeeping),
    # one implementation for the daemon and the offline replay
    Extension("canrls._kernels", sources=["src/canrls/c/kernels.c"],
              depends=["src/canrls/c/kernels_rls.h"], extra_compile_args=CFLAGS),
    # the per-frame loops of the CAN layer (strict decoding, counters, CRC, pairing):
    # canrls.can, live and offline
    Extension("canrls._can", sources=["src/canrls/c/can.c"], extra_compile_args=CFLAGS),
    # the fixed-point RLS kernel (canrls_fixed.c, the target's code) for
    # canrls.estimation.fixed.FixedRLS
    Extension("canrls._fixed",
              sources=["src/canrls/c/fixed_module.c", "src/canrls/c/canrls_fixed.c"],
              include_dirs=["src/canrls/c"], depends=["src/canrls/c/canrls_fixed.h"],
              extra_compile_args=CFLAGS),
]

setup(ext_modules=EXTENSIONS)
