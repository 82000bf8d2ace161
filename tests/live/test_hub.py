"""A machine's one bus (:class:`canrls.live.hub.BusHub`): every frame reaches the queue of
the axis whose ID it carries, in stream order; error frames reach every axis; a frame of
no axis is counted and queued nowhere; the bus opens with the first axis and closes with
the last."""

from __future__ import annotations

import os
import threading

import can
import numpy as np
import pytest

from canrls.can.frameblock import FrameBlock
from canrls.live.bus_link import BusLink, FrameQueue, messages_to_block, open_bus
from canrls.live.daemon_settings import DaemonSettings
from canrls.live.hub import BusHub


def _link(hub: BusHub, ids: list[tuple[int, bool]], limit: int = 1000) -> BusLink:
    q = FrameQueue(limit, False, threading.Event(), on_error=lambda e: None)
    link = BusLink(q, lambda: None, DaemonSettings(), rx_ids=ids)  # type: ignore[arg-type]
    link.hub = hub
    return link


def _frames(mixed: bool) -> list[can.Message]:
    """Seeded frames of axes a (0x101, 0x102 extended) and b (0x111) and of unknown IDs
    (0x7FF, 0x101 extended), shuffled; ``mixed``: also of both axes (0x200) and an error
    frame (the hub's other path)."""
    rng = np.random.default_rng(5)
    ids = [(0x101, False), (0x102, True), (0x111, False), (0x7FF, False), (0x101, True)]
    if mixed:
        ids.append((0x200, False))
    out = [can.Message(timestamp=0.001 * k, arbitration_id=ids[i][0],
                       is_extended_id=ids[i][1], data=bytes([k % 256, *rng.bytes(7)]))
           for k, i in enumerate(rng.integers(0, len(ids), 300))]
    if mixed:
        out.insert(150, can.Message(timestamp=0.1495, arbitration_id=0x40, dlc=8,
                                    is_error_frame=True, data=bytes(8)))
    return out


def _block_of(msgs: list[can.Message]) -> FrameBlock:
    return messages_to_block(msgs) if msgs else FrameBlock.empty()


def _same(a: FrameBlock, b: FrameBlock) -> bool:
    return len(a) == len(b) and all(np.array_equal(getattr(a, f), getattr(b, f)) for f in
                                    ("t", "arbitration_id", "is_extended", "is_error", "data"))


@pytest.mark.parametrize("mixed", [False, True], ids=["own-ids", "shared-ids-and-errors"])
def test_each_axis_gets_its_frames_in_order_and_errors_others_are_counted(mixed: bool
                                                                          ) -> None:
    ch = f"hub-route-{os.getpid()}-{mixed}"
    hub = BusHub(lambda: open_bus({"interface": "virtual", "channel": ch}), DaemonSettings())
    a = _link(hub, [(0x101, False), (0x102, True), (0x200, False)])
    b = _link(hub, [(0x111, False), (0x200, False)])
    every = _link(hub, [])
    for link in (a, b, every):
        link.open()
    try:
        msgs = _frames(mixed)
        block = messages_to_block(msgs)
        for lo in range(0, len(block), 37):  # the reader's blocks, cut anywhere
            hub.on_block(block.take(slice(lo, lo + 37)))
        for link in (a, b, every):
            ids = set(link.rx_ids)
            want = [m for m in msgs if not ids or m.is_error_frame
                    or (m.arbitration_id, m.is_extended_id) in ids]
            assert _same(link.queue.take(10_000), _block_of(want))
        assert hub.foreign == 0  # the axis that takes every frame takes the unknown ones
        every.close()
        hub.on_block(block)
        unknown = sum(1 for m in msgs if not m.is_error_frame and (
            m.arbitration_id, m.is_extended_id) in ((0x7FF, False), (0x101, True)))
        assert hub.foreign == unknown > 0
    finally:
        for link in (a, b, every):
            link.close()
    assert a.bus is None


def _two_axes(tag: str, settings: DaemonSettings
              ) -> tuple[BusHub, BusLink, BusLink, list[can.BusABC]]:
    """A hub on a virtual channel, two axes' links on it, and every bus it opened."""
    ch = f"hub-{tag}-{os.getpid()}"
    opened: list[can.BusABC] = []

    def factory() -> can.BusABC:
        opened.append(open_bus({"interface": "virtual", "channel": ch}))
        return opened[-1]

    hub = BusHub(factory, settings)
    return hub, _link(hub, [(0x101, False)]), _link(hub, [(0x111, False)]), opened


def test_the_bus_opens_with_the_first_axis_and_closes_with_the_last() -> None:
    _, a, b, opened = _two_axes("life", DaemonSettings())
    a.open()
    b.open()
    assert len(opened) == 1 and a.bus is b.bus is opened[0]
    a.close()
    assert not opened[0]._is_shutdown  # b still on it
    b.close()
    assert opened[0]._is_shutdown


def test_a_failed_bus_is_reopened_once_for_every_axis() -> None:
    hub, a, b, opened = _two_axes("reopen", DaemonSettings(reopen_min_s=0.01))
    for link in (a, b):  # the daemon's callback: its link has failed
        link.queue._on_error = link.recv_failed
        link.open()
    try:
        hub.on_error(OSError("gone"))  # the reader's recv raised
        assert a.failed.is_set() and b.failed.is_set() and a.paused(0.0)
        stopping = threading.Event()
        a.reopen(stopping)
        b.reopen(stopping)
        assert len(opened) == 2 and opened[0]._is_shutdown
        assert a.bus is b.bus is opened[1] and not a.failed.is_set() and not b.failed.is_set()
        assert a.counts["bus_reopens"] == b.counts["bus_reopens"] == 1
    finally:
        a.close()
        b.close()
    assert opened[1]._is_shutdown
