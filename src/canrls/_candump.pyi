"""Types of the C extension ``canrls._candump`` (src/canrls/c/host/candump.c): the
candump parser and writer of :mod:`canrls.can.candump`."""

import numpy as np
import numpy.typing as npt

CAN_ERR_FLAG: int
EFF_MASK: int
MAX_TIMESTAMP: float

def parse(buf: npt.NDArray[np.uint8], stop: int, final: bool, t: npt.NDArray[np.float64],
          aid: npt.NDArray[np.uint32], ext: npt.NDArray[np.bool_],
          err: npt.NDArray[np.bool_], dlc: npt.NDArray[np.uint8],
          data: npt.NDArray[np.uint8], slow: npt.NDArray[np.int64], /
          ) -> tuple[int, int, int, int]: ...
def format_lines(sec: npt.NDArray[np.int64], usec: npt.NDArray[np.int64],
                 aid: npt.NDArray[np.uint32], ext: npt.NDArray[np.bool_],
                 rtr: npt.NDArray[np.bool_], err: npt.NDArray[np.bool_],
                 dlc: npt.NDArray[np.uint8], data: npt.NDArray[np.uint8],
                 channel: npt.NDArray[np.uint8], out: npt.NDArray[np.uint8], /) -> int: ...
