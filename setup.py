"""Build the C extensions of canrls (sources in src/canrls/c); all other metadata is in
pyproject.toml. ``pip install`` (and so ``make test`` / ``make demo``) compiles them with
the machine's C compiler and the Python headers."""

from setuptools import Extension, setup

CFLAGS = ["-O2", "-std=c99", "-Wall", "-Wextra", "-Werror", "-ffp-contract=off"]

EXTENSIONS: list[Extension] = [
    # the fixed-point RLS kernel (canrls_fixed.c) for canrls.estimation.fixed.FixedRLS
    Extension(
        "canrls._fixed",
        sources=["src/canrls/c/fixed_module.c", "src/canrls/c/canrls_fixed.c"],
        include_dirs=["src/canrls/c"],
        depends=["src/canrls/c/canrls_fixed.h"],
        extra_compile_args=CFLAGS,
    ),
]

setup(ext_modules=EXTENSIONS)
