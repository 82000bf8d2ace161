"""Types of the C extension ``canrls._fixed`` (src/canrls/c/host/fixed_module.c): the
firmware's fixed-point RLS kernel (src/canrls/c/firmware/canrls_fixed.c) on the host."""

from typing import SupportsFloat

import numpy as np
import numpy.typing as npt

_I64 = npt.NDArray[np.int64]

N_MAX: int
NSITES: int
PLAN_FIELDS: tuple[str, ...]

def run_block(Phi: _I64, Y: _I64, theta: _I64, theta_frac: _I64, P: _I64, P_frac: _I64,
              scale: _I64, K: _I64, counts: _I64, plan: _I64, frozen: bool, eps: _I64,
              theta_out: _I64 | None, trace: _I64, exp: _I64, flags: npt.NDArray[np.uint8], /
              ) -> int: ...
def round_saturate(x: npt.NDArray[np.float64], scale: SupportsFloat, lo: SupportsFloat,
                   hi: SupportsFloat, out: _I64, /) -> int: ...
