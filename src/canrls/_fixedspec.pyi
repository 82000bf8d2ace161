"""Types of the C extension ``canrls._fixedspec`` (src/canrls/c/host/fixed_spec.c): the
compiled fixed-point specification of :mod:`canrls.estimation.fixed.kernels` and its Q
primitives. Each array's dtype and shape is checked by the C."""

from typing import SupportsIndex

import numpy as np
import numpy.typing as npt

_I64 = npt.NDArray[np.int64]

NPARAM: int
NSITES: int

def fixed_block(Phi: _I64, Y: _I64, theta: _I64, theta_frac: _I64, P: _I64, P_frac: _I64,
                scale: _I64, work: _I64, counts: _I64, prm: _I64, mode: SupportsIndex,
                frozen: bool, record: bool, eps_out: _I64, theta_out: _I64, trace_out: _I64,
                exp_out: _I64, flags_out: npt.NDArray[np.uint8], /) -> int: ...
def round_shift(x: SupportsIndex, s: SupportsIndex, /) -> int: ...
def saturate(x: SupportsIndex, lo: SupportsIndex, hi: SupportsIndex, /) -> tuple[int, int]: ...
def store(x: SupportsIndex, s: SupportsIndex, lo: SupportsIndex, hi: SupportsIndex, /
          ) -> tuple[int, int]: ...
def sat_mul(a: SupportsIndex, b: SupportsIndex, s: SupportsIndex, lo: SupportsIndex,
            hi: SupportsIndex, /) -> tuple[int, int]: ...
def sat_add(a: SupportsIndex, b: SupportsIndex, lo: SupportsIndex, hi: SupportsIndex, /
            ) -> tuple[int, int]: ...
def div_trunc(a: SupportsIndex, b: SupportsIndex, /) -> int: ...
