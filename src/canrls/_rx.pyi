"""Types of the C extension ``canrls._rx`` (src/canrls/c/host/rx.c): the SocketCAN
receive of :mod:`canrls.live.socketcan`."""

import numpy as np
import numpy.typing as npt

AVAILABLE: int
DATA_WIDTH: int
AUX_FD: int
AUX_BRS: int
AUX_ESI: int
AUX_TX: int

def recv(fd: int, pause: float, timeout: float, offset: int, most: int, command_id: int,
         t: npt.NDArray[np.float64], arbitration_id: npt.NDArray[np.uint32],
         is_extended: npt.NDArray[np.bool_], is_remote: npt.NDArray[np.bool_],
         is_error: npt.NDArray[np.bool_], dlc: npt.NDArray[np.uint8],
         data: npt.NDArray[np.uint8], aux: npt.NDArray[np.uint8], /
         ) -> tuple[int, int, OSError | ValueError | None]: ...
