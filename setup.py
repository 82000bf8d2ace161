"""Build the C extensions of canrls (sources in src/canrls/c); all other metadata is in
pyproject.toml. ``pip install`` (and so ``make test`` / ``make demo``) compiles them with
the machine's C compiler and the Python headers."""

from setuptools import Extension, setup

EXTENSIONS: list[Extension] = []

setup(ext_modules=EXTENSIONS)
