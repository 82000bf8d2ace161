"""Types of the C extension ``canrls._target`` (src/canrls/c/host/target_module.c): the
C of ``canrls export-c`` on the host, for :mod:`canrls.firmware.native`."""

from typing import final

import numpy as np
import numpy.typing as npt

#: LAYOUT[section] = ((name, count), ...): the integer vector :class:`Target` reads
LAYOUT: dict[str, tuple[tuple[str, int], ...]]
N_MAX: int
#: sizeof(canrls_target): the bytes of Target.state()
STATE_BYTES: int

@final
class Target:
    def __init__(self, vector: npt.NDArray[np.int64]) -> None: ...
    def run(self, ticks: npt.NDArray[np.uint32], arbitration_id: npt.NDArray[np.uint32],
            is_extended: npt.NDArray[np.bool_], skip: npt.NDArray[np.bool_],
            dlc: npt.NDArray[np.uint8], data: npt.NDArray[np.uint8],
            publications: list[tuple[int, list[tuple[int, bytes]]]] | None, /) -> int: ...
    def record(self) -> list[int]: ...
    def theta(self) -> list[float]: ...
    def counts(self) -> tuple[int, tuple[int, ...], tuple[int, ...], tuple[int, ...],
                              tuple[tuple[int, ...], ...]]: ...
    def freeze(self, on: bool, /) -> None: ...
    def state(self) -> bytes: ...
    def set_state(self, state: bytes, /) -> None: ...
