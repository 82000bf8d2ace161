"""Build the C extensions of canrls (sources in src/canrls/c); all other metadata is in
pyproject.toml. ``pip install`` (and so ``make test`` / ``make demo``) compiles them with
the machine's C compiler and the Python headers."""

from setuptools import Extension, setup

#: compile flags of every extension: C99, warnings as errors, no floating-point contraction
#: (an FMA would round differently from the Python reference)
_CFLAGS = ["-O2", "-std=c99", "-Wall", "-Wextra", "-Werror", "-ffp-contract=off"]

EXTENSIONS: list[Extension] = [
    # the per-frame loops of the CAN layer (strict decoding, pairing): canrls.can
    Extension("canrls._can", sources=["src/canrls/c/can.c"], extra_compile_args=_CFLAGS),
]

setup(ext_modules=EXTENSIONS)
