"""Build the C extensions of canrls (sources in src/canrls/c); all other metadata is in
pyproject.toml. ``pip install`` (and so ``make test`` / ``make demo``) compiles them with
the machine's C compiler and the Python headers."""

from setuptools import Extension, setup

#: -ffp-contract=off and no -ffast-math: no fused multiply-add, no reassociation, so the
#: float kernels give the same bits on every machine and in every build.
CFLAGS = ["-O2", "-std=c99", "-Wall", "-Wextra", "-Werror", "-ffp-contract=off"]

EXTENSIONS: list[Extension] = [
    # the per-sample float kernels of the estimation (RLS, SVF, selection, bookkeeping),
    # one implementation for the daemon and the offline replay
    Extension("canrls._kernels", sources=["src/canrls/c/kernels.c"],
              depends=["src/canrls/c/kernels_rls.h"], extra_compile_args=CFLAGS),
]

setup(ext_modules=EXTENSIONS)
