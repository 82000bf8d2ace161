"""A tool on a daemon's virtual bus: what a monitor or a test bench sees of it.

Shared by the daemon tests: it keeps every frame the daemon sends (the ``0x3xx``
range), sends command frames and waits for their acknowledgements.
"""

from __future__ import annotations

import time

import can

from canrls.can.frames import CommandResult

__all__ = ["DaemonTool", "collect"]

#: RlsCommandAck
ACK_ID = 0x321


def collect(reader: can.BufferedReader) -> list[can.Message]:
    """Every message ``reader`` holds now."""
    out = []
    while (m := reader.get_message(0.0)) is not None:
        out.append(m)
    return out


class DaemonTool:
    """A virtual bus on the daemon's channel that keeps the daemon's frames."""

    def __init__(self, channel: str) -> None:
        self.bus = can.Bus(interface="virtual", channel=channel, ignore_config=True)
        self.bus.set_filters([{"can_id": 0x300, "can_mask": 0x700}])
        self.reader = can.BufferedReader()
        self.notifier = can.Notifier(self.bus, [self.reader], timeout=0.05)
        self.frames: list[can.Message] = []

    def take(self) -> list[can.Message]:
        """The frames received since the last call (also kept in :attr:`frames`)."""
        new = collect(self.reader)
        self.frames += new
        return new

    def command(self, msg: can.Message, timeout: float = 5.0) -> CommandResult | None:
        """Send a command frame and wait for its acknowledgement (None: none came)."""
        self.take()
        self.bus.send(msg)
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            for m in self.take():
                if m.arbitration_id == ACK_ID:
                    return CommandResult(m.data[1])
            time.sleep(0.01)
        return None

    def acks(self) -> list[can.Message]:
        """Every acknowledgement kept so far."""
        return [m for m in self.frames if m.arbitration_id == ACK_ID]

    def wait_acks(self, n: int, timeout: float = 60.0) -> list[can.Message]:
        """Until ``n`` acknowledgements have come (or ``timeout``): all of them."""
        end = time.monotonic() + timeout
        while len(self.acks()) < n and time.monotonic() < end:
            self.take()
            time.sleep(0.01)
        return self.acks()

    def close(self) -> None:
        self.notifier.stop()
        self.bus.shutdown()
