"""Build the C extensions of canrls (sources in src/canrls/c/host; the fixed-point kernel
they share with the target in src/canrls/c/firmware); all other metadata is in
pyproject.toml. ``pip install`` (and so ``make test`` / ``make demo``) compiles them with
the machine's C compiler (GCC or clang: ``CC`` chooses) and the Python headers; without
either the build stops with one ``error:`` line naming the Debian package to install."""

import os
import shutil
import subprocess
import sysconfig
import tempfile
from pathlib import Path

from setuptools import Extension, setup
from setuptools.command.build_ext import build_ext

try:  # setuptools' own copy of distutils (Python 3.12 has none in the standard library)
    from setuptools.errors import PlatformError
except ImportError:  # setuptools < 59
    from distutils.errors import DistutilsPlatformError as PlatformError

#: compile flags of every extension: C99, warnings as errors, no floating-point contraction
#: and no -ffast-math (an FMA or a reassociation would round differently from the
#: reference, so the float kernels give the same bits on every machine and in every build);
#: GCC and clang take them all
_CFLAGS = ["-O2", "-std=c99", "-Wall", "-Wextra", "-Werror", "-ffp-contract=off"]

#: -fvect-cost-model=dynamic (GCC only; clang refuses it, and vectorises these loops at
#: -O2 by itself): GCC's -O2 default vectorises only loops whose trip count is known; the
#: float kernels run over n parameters, and vectorised (element-wise, so the same bits;
#: reductions stay in order) the float RLS is about 30 % faster at n = 8
_VECTORISE = "-fvect-cost-model=dynamic"

#: what to install where the build finds no compiler or no Python headers (Debian names)
_COMPILER_HINT = ("canrls builds C extensions and needs a C compiler: {cc!r} was not found;"
                  " install one (Debian/Ubuntu: apt-get install build-essential; or clang)"
                  " or name it in CC")
_HEADERS_HINT = ("canrls builds C extensions and needs the Python headers: {h} is missing;"
                 " install them (Debian/Ubuntu: apt-get install python{v}-dev)")

EXTENSIONS: list[Extension] = [
    # the per-sample float loops of the estimation (RLS, SVF, selection, unwrapping,
    # pipeline sums; the diagnosis's harmonic columns), one implementation for the daemon
    # and the offline replay
    Extension("canrls._kernels", sources=["src/canrls/c/host/kernels.c"],
              depends=["src/canrls/c/host/kernels_rls.h", "src/canrls/c/host/pyargs.h"],
              extra_compile_args=[*_CFLAGS, _VECTORISE]),
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
              depends=["src/canrls/c/firmware/canrls_fixed.h",
                       "src/canrls/c/firmware/canrls_bounds.h"],
              extra_compile_args=_CFLAGS),
    # the target's whole integer path (canrls_target.c and canrls_fixed.c, the C that
    # export-c writes, its tables given at run time as data) for canrls.firmware.native:
    # canrls fit's and the daemon's fixed column
    Extension("canrls._target",
              sources=["src/canrls/c/host/target_module.c",
                       "src/canrls/c/firmware/canrls_target.c",
                       "src/canrls/c/firmware/canrls_target_check.c",
                       "src/canrls/c/firmware/canrls_fixed.c"],
              include_dirs=["src/canrls/c/firmware"],
              depends=["src/canrls/c/firmware/canrls_target.h",
                       "src/canrls/c/firmware/canrls_target_check.h",
                       "src/canrls/c/firmware/canrls_target_tables.h",
                       "src/canrls/c/firmware/canrls_fixed.h",
                       "src/canrls/c/firmware/canrls_bounds.h",
                       "src/canrls/c/host/pyargs.h"],
              extra_compile_args=_CFLAGS),
    # the fixed-point RLS as specified (every update form, any n) for
    # canrls.estimation.fixed.kernels: where the target's kernel does not apply
    Extension("canrls._fixedspec", sources=["src/canrls/c/host/fixed_spec.c"],
              depends=["src/canrls/c/host/pyargs.h"], extra_compile_args=_CFLAGS),
    # the simulated drive's loop (sensors, controllers, RK4): canrls.sim.plant
    Extension("canrls._sim", sources=["src/canrls/c/host/sim.c"],
              depends=["src/canrls/c/host/pyargs.h"], extra_compile_args=_CFLAGS),
]


class BuildExt(build_ext):
    """``build_ext`` that checks the compiler and the Python headers before building, and
    leaves out the flags the compiler refuses (GCC-only ones under clang)."""

    def build_extensions(self) -> None:
        cc = self.compiler.compiler_so[0] if getattr(self.compiler, "compiler_so", None) else None
        if cc is not None and shutil.which(cc) is None:
            raise PlatformError(_COMPILER_HINT.format(cc=cc))
        header = Path(sysconfig.get_path("include")) / "Python.h"
        if not header.is_file():
            raise PlatformError(_HEADERS_HINT.format(
                h=header, v=sysconfig.get_python_version()))
        for ext in self.extensions:
            ext.extra_compile_args = [f for f in ext.extra_compile_args
                                      if f in _CFLAGS or self._accepts(f)]
        super().build_extensions()

    def _accepts(self, flag: str) -> bool:
        """Whether the compiler compiles an empty C file with ``flag``, warnings as errors
        (clang only warns about some GCC flags it ignores); quietly, a refusal is no error."""
        with tempfile.TemporaryDirectory() as tmp:
            src = os.path.join(tmp, "flag.c")
            with open(src, "w", encoding="ascii") as f:
                f.write("int canrls_flag_probe;\n")
            probe = [*self.compiler.compiler_so, flag, "-Werror", "-c", src,
                     "-o", os.path.join(tmp, "flag.o")]
            return subprocess.run(probe, capture_output=True, check=False).returncode == 0


if __name__ == "__main__":
    setup(ext_modules=EXTENSIONS, cmdclass={"build_ext": BuildExt})
