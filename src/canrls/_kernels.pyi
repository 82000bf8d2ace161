"""Types of the C extension ``canrls._kernels`` (src/canrls/c/host/kernels.c): the float
RLS, state-variable filter, selection and bookkeeping kernels of
:mod:`canrls.estimation`. Each array's dtype and shape is checked by the C."""

from typing import Any, SupportsFloat, SupportsIndex

import numpy as np
import numpy.typing as npt

_F64 = npt.NDArray[np.float64]
_I64 = npt.NDArray[np.int64]
_U8 = npt.NDArray[np.uint8]
_B = npt.NDArray[np.bool_]
#: float64 or float32, every array of one call the same (theta's dtype)
_Real = npt.NDArray[np.floating[Any]]

FLAG_FROZEN: int
FLAG_NONFINITE: int
FLAG_WINDUP: int

def rls_block_symmetric(Phi: _Real, Y: _Real, theta: _Real, P: _Real, work: _Real, acc: _Real,
                        lam: SupportsFloat, trace_max: SupportsFloat, frozen: bool,
                        record: bool, eps_out: _Real, theta_out: _Real, trace_out: _Real,
                        flags_out: _U8, /) -> int: ...
def rls_block_literal(Phi: _Real, Y: _Real, theta: _Real, P: _Real, work: _Real, acc: _Real,
                      lam: SupportsFloat, trace_max: SupportsFloat, frozen: bool, record: bool,
                      eps_out: _Real, theta_out: _Real, trace_out: _Real, flags_out: _U8, /
                      ) -> int: ...
def trace_of(P: _Real, /) -> float: ...
def svf(u: _F64, Ad: _F64, G0: _F64, G1: _F64, x1: _F64, x2: _F64, up: _F64, primed: _I64,
        f: _F64, sf: _F64, /) -> None: ...
def svf_scaled(u: _F64, Ad: _F64, G0: _F64, G1: _F64, x1: _F64, x2: _F64, up: _F64,
               primed: _I64, deriv: _B, scale: _F64, y: _F64, phi: _F64, /) -> None: ...
def select(t: _F64, omega: _F64, gap: SupportsFloat, warm: SupportsIndex,
           min_speed: SupportsFloat, max_speed: SupportsFloat, state: _F64, restart: _B,
           use: _B, /) -> tuple[int, int]: ...
def nothing_to_fill(t: _F64, has_last: bool, last_t: SupportsFloat, dt: SupportsFloat,
                    max_gap: SupportsFloat, /) -> bool: ...
def unwrap(p: _F64, period: SupportsFloat, turns: SupportsIndex, last: SupportsFloat,
           out: _F64, /) -> int: ...
def accumulate(phi: _F64, y: _F64, use: _B, M: _F64, v: _F64, s: _F64, /) -> None: ...
def bookkeeping(phi: _F64, y: _F64, use: _B, eps_u: _F64, epsq_u: _I64, lsb: SupportsFloat,
                flags_u: _U8, flagsq_u: _U8, M: _F64, v: _F64, s: _F64, beta: SupportsFloat,
                rms_state: _F64, s_y: SupportsIndex, y_out: _F64, eps: _F64,
                eps_fixed: _F64, flags: _U8, rms: _F64, /) -> int: ...
def sincos(a: _F64, q: _F64, out: _F64, /) -> None: ...
