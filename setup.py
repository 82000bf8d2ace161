"""Build the C extensions of canrls (sources in src/canrls/c); all other metadata is in
pyproject.toml. ``pip install`` (and so ``make test`` / ``make demo``) compiles them with
the machine's C compiler and the Python headers."""

from setuptools import Extension, setup

#: compile flags of every extension: C99, warnings as errors, no floating-point contraction
#: (an FMA would round differently from the Python reference)
_CFLAGS = ["-O2", "-std=c99", "-Wall", "-Wextra", "-Werror", "-ffp-contract=off"]

EXTENSIONS: list[Extension] = [
    # the per-sample float loops of the estimation (RLS, SVF, selection, unwrapping,
    # pipeline sums), one implementation for the daemon and the offline replay.
    # -fvect-cost-model=dynamic: GCC's -O2 default vectorises only loops whose trip count
    # is known; these run over n parameters, and vectorised (element-wise, so the same
    # bits; reductions stay in order) the float RLS is about 30 % faster at n = 8
    Extension("canrls._kernels", sources=["src/canrls/c/kernels.c"],
              depends=["src/canrls/c/kernels_rls.h"],
              extra_compile_args=[*_CFLAGS, "-fvect-cost-model=dynamic"]),
]

setup(ext_modules=EXTENSIONS)
