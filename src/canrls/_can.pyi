"""Types of the C extension ``canrls._can`` (src/canrls/c/host/can.c): the decoding,
counter, CRC and pairing kernels of :mod:`canrls.can` and :mod:`canrls.processor`."""

import numpy as np
import numpy.typing as npt

_F64 = npt.NDArray[np.float64]
_I64 = npt.NDArray[np.int64]
_U8 = npt.NDArray[np.uint8]
_B = npt.NDArray[np.bool_]

def crc8(frame_id: int, data: _U8, width: int, length: int, powers: _U8, out: _U8, /
         ) -> None: ...
def gather_check(data: _U8, width: int, rows: _I64, length: int, is_remote: _B, dlc: _U8,
                 check_crc: bool, frame_id: int, powers: _U8, out: _U8, flags: _U8, /
                 ) -> int: ...
def counters(c: _I64, t: _F64, mod: int, window: int, period: float, state: _I64,
             state_t: _F64, status: _U8, lost: _I64, skip: _B | None = None, /) -> None: ...
def decode_fast(t: _F64, arbitration_id: npt.NDArray[np.uint32], is_extended: _B,
                is_remote: _B, is_error: _B, dlc: _U8, data: _U8, width: int, msg: _I64,
                period: _F64, sig: _I64, sig_f: _F64, powers: _U8, state: _I64,
                state_t: _F64, base: int, out_f: _F64, out_i: _I64, counts: _I64, /
                ) -> int: ...
def push(index: tuple[_I64, ...], t: tuple[_F64, ...], cnt: tuple[_I64, ...],
         vals: tuple[_F64, ...], use_counters: bool, role_msg: _I64, times: _F64,
         flush: bool, gf: _F64, gi: _I64, sf: _F64, si: _I64, counts: _I64, clock: _I64,
         iwork: _I64, fwork: _F64, vwork: _F64, /) -> int: ...
