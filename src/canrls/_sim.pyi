"""Types of the C extension ``canrls._sim`` (src/canrls/c/host/sim.c): the simulated
drive's control loop of :mod:`canrls.sim.plant`."""

from typing import SupportsFloat, SupportsIndex

import numpy as np
import numpy.typing as npt

_F64 = npt.NDArray[np.float64]

def plant_run(dt: SupportsFloat, nsub: SupportsIndex, h_stiff: SupportsFloat, st: _F64,
              p: _F64, ck: _F64, cs: _F64, cc: _F64, gains: _F64, quant: _F64, ffv: _F64,
              ffmap: _F64, w_ref: _F64, a_ref: _F64, noise: _F64, out: _F64, /) -> None: ...
