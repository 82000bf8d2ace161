"""Alive-counter faults: a wrong counter costs its own frame, and lost means lost.

A frame with a valid CRC but a wrong alive counter between two good ones is rejected
and the next good frame continues the sequence of the last accepted one (the AUTOSAR
E2E receiver's idea; docs/protocol.md, *Decoding*): one bad counter costs one frame and
one sample, never a resynchronisation and a filter restart. ``lost`` (``FramesLost``)
counts the frames that never arrived, not the frames received and rejected."""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np
import pytest

from canrls.can.decoder import Decoder
from canrls.can.e2e import CRC8_TABLE
from canrls.can.encoder import FeedbackEncoder
from canrls.can.frameblock import FrameBlock
from canrls.can.protocol import Protocol
from canrls.estimation.estimates import PipelineBlock
from canrls.processor import FrameProcessor
from canrls.processor.config import AppConfig, prepare
from canrls.processor.replay import fit_frames
from canrls.sim.faults import inject
from canrls.sim.scenario import scenario, simulate

EFFECTS = "inertia,viscous,coulomb"


@pytest.fixture(scope="module")
def clean() -> FrameBlock:
    """3 s of the simulated drive at 1 kHz (6000 clean frames, current's message first)."""
    return simulate(scenario("standard", effects=EFFECTS, seed=5, duration=3.0)).frames


def _copy(b: FrameBlock) -> FrameBlock:
    return FrameBlock(*(getattr(b, f).copy() for f in
                        ("t", "arbitration_id", "is_extended", "is_remote", "is_error", "dlc",
                         "data")))


def _miscount(b: FrameBlock, row: int, move: int) -> FrameBlock:
    """A copy of ``b`` with the alive counter of ``row`` moved by ``move``, its CRC valid
    again (as the simulator's ``counter`` fault)."""
    out = _copy(b)
    d = out.data[row]
    d[1] = (d[1] & 0xF0) | ((int(d[1]) + move) & 0x0F)
    fid = int(out.arbitration_id[row])
    c = 0xFF
    # crc = CRC8_0x1D(id_lo, id_hi, d_1 .. d_{n-1}), init 0xFF, xorout 0xFF
    for x in (fid & 0xFF, (fid >> 8) & 0xFF, *d[1:int(out.dlc[row])].tolist()):
        c = int(CRC8_TABLE[c ^ x])
    d[0] = c ^ 0xFF
    return out


def _blocks(b: FrameBlock, cuts: tuple[int, ...]) -> Iterator[FrameBlock]:
    edges = (0, *cuts, len(b))
    for a, z in zip(edges[:-1], edges[1:], strict=True):
        yield b.take(slice(a, z))


def _samples(b: FrameBlock, cuts: tuple[int, ...] = ()) -> tuple[FrameProcessor, int]:
    cfg = AppConfig()
    cfg.model = {"effects": EFFECTS.split(","), "kt": 0.1}
    protocol = cfg.protocol()
    fp = FrameProcessor(protocol, cfg.model_for(protocol), cfg.settings())
    n = sum(len(fp.samples(blk)) for blk in _blocks(b, cuts))
    return fp, n + len(fp.flush_samples())


@pytest.mark.parametrize("move", range(1, 16))
@pytest.mark.parametrize("row", [3001, 3000])  # DriveSpeed, DriveCurrent of period 1500
def test_one_bad_counter_costs_one_frame_and_one_sample(clean: FrameBlock, row: int,
                                                        move: int) -> None:
    bad = _miscount(clean, row, move)
    _, n_clean = _samples(clean)
    for cuts in ((), (row,), (row + 1,), (row - 1, row + 2)):  # the fast and careful paths
        fp, n = _samples(bad, cuts)
        dec = fp.decoder
        assert dec.rejected.total == 1, (move, cuts, dict(dec.rejected))
        # what the counter says: a repeat (move 15), a jump backwards (8..14), or a jump
        # ahead of the time since the last frame (1..7: a wrong counter, not 1..7 lost)
        reason = "repeated" if move == 15 else "stale" if move >= 8 else "sequence"
        assert dec.rejected[reason] == 1
        assert sum(dec.lost.values()) == 0  # received, rejected: not lost
        assert n == n_clean - 1
        assert fp.pairing.unpaired == 1  # its partner


def test_one_bad_counter_leaves_the_filter_running(clean: FrameBlock) -> None:
    # before: a move of 2..7 was taken for 2..7 lost frames, the next good frames were
    # rejected as stale until three resynchronised, and the gap of 4 periods (> 3.5)
    # restarted the filter: 50 samples of warm-up lost per bad counter
    cfg = AppConfig()
    cfg.model = {"effects": EFFECTS.split(","), "kt": 0.1}
    protocol, model, settings = prepare(cfg)

    def used(b: FrameBlock) -> int:
        total = [0]

        def count(out: PipelineBlock) -> None:
            total[0] += sum(int(e.used.sum()) for e in out.equations)

        fit_frames([b], protocol, model, settings, on_block=count, record=True)
        return total[0]

    base = used(clean)
    for move in (2, 5, 7):
        assert base - used(_miscount(clean, 4001, move)) <= 1


def test_frames_lost_counts_frames_lost_not_frames_rejected(clean: FrameBlock) -> None:
    long = simulate(scenario("standard", effects=EFFECTS, seed=6, duration=20.0)).frames
    for spec, seed in (("corrupt=0.01", 1), ("counter=0.01", 2), ("dlc=0.01", 3),
                       ("dup=0.01", 4), ("corrupt=0.01,counter=0.01,dlc=0.01", 5)):
        out, log = inject(long, spec, seed=seed)
        dec = Decoder(Protocol.load())
        dec.decode(out)
        if log.duplicated:
            hit = log.duplicated
        else:  # frames hit (one may be hit by two faults: counted once)
            hit = int(np.sum(np.any(out.data != long.data, axis=1) | (out.dlc != long.dlc)))
        assert dec.rejected.total == hit > 0, spec
        assert sum(dec.lost.values()) == 0, spec
    # with drops among them: exactly the frames dropped
    out, log = inject(long, "drop=0.01,corrupt=0.01,counter=0.01,dlc=0.01", seed=7)
    dec = Decoder(Protocol.load())
    for blk in _blocks(out, (1234, 20000, 20001, 31000)):
        dec.decode(blk)
    assert log.dropped > 0 and sum(dec.lost.values()) == log.dropped


def test_a_loss_under_bunched_timestamps_costs_one_frame_more_not_a_cascade() -> None:
    # a receiver that stamps frames in bursts: three frames lost, then the next frames
    # all carry the same time. The first after the loss looks ahead of its time (rejected,
    # ``sequence``); the next continues its sequence, so the jump was a loss after all.
    proto = Protocol.load()
    enc = FeedbackEncoder(proto)
    b = enc.encode(np.arange(20) * 1e-3, np.zeros(20), np.zeros(20))
    cur = b.take(np.flatnonzero(b.arbitration_id == b.arbitration_id[0]))  # counters 0..15, 0..3
    keep = np.r_[0:6, 9:20]  # counters 6, 7, 8 lost
    s = cur.take(keep)
    s.t[6:] = s.t[5]  # bunched: the frames after the loss carry the time of the last one
    dec = Decoder(proto)
    d = dec.decode(s)
    assert d.rejected["sequence"] == 1  # counter 9, three periods ahead of its time
    assert d["DriveCurrent"].counter.tolist() == [*range(6), *range(10, 16), *range(4)]
    assert d.lost["DriveCurrent"] == 3  # 6, 7, 8 (9 was received and rejected)


def test_a_swap_without_the_reorderer_costs_one_frame(clean: FrameBlock) -> None:
    cur = clean.take(np.flatnonzero(clean.arbitration_id == clean.arbitration_id[0]))
    s = _copy(cur.take(np.arange(40)))
    # frames 10 and 11 swap their contents; the receive times stay in order
    s.data[[10, 11]] = s.data[[11, 10]]
    dec = Decoder(Protocol.load())
    d = dec.decode(s)
    assert dec.rejected.total == 1 and len(d["DriveCurrent"]) == 39
    # the later frame, which came first, is the one rejected (ahead of its time)
    assert dec.rejected["sequence"] == 1


def test_a_clock_step_forward_is_not_counted_as_lost_frames(clean: FrameBlock) -> None:
    # the time since the last frame implies whole counter wraps only when it agrees with
    # them (within half a period): a silence does, a receive clock stepping forward by
    # 0.3004 s does not (it used to count 300 frames lost per message)
    proto = Protocol.load()
    step = _copy(clean)
    step.t[3000:] += 0.3004
    dec = Decoder(proto)
    dec.decode(step)
    assert sum(dec.lost.values()) == 0 and dec.rejected.total == 0
    silent = clean.take(np.r_[0:3000, 3600:6000])  # 300 periods of both messages missing
    dec = Decoder(proto)
    dec.decode(silent)
    assert dec.lost == {"DriveCurrent": 300, "DriveSpeed": 300}
    # and with the receive times jittered by a tenth of a period
    rng = np.random.default_rng(11)
    jittered = _copy(silent)
    jittered.t[:] += rng.uniform(-1e-4, 1e-4, len(jittered))
    dec = Decoder(proto)
    dec.decode(jittered)
    assert dec.lost == {"DriveCurrent": 300, "DriveSpeed": 300} and dec.rejected.total == 0


def test_a_duplicate_takes_no_place_in_the_sequence(clean: FrameBlock) -> None:
    # a copy delivered with its frame, then the next frame lost: one lost (the copy is
    # no frame of its own); a frame repeating the last counter a period later took the
    # place of a genuine one (a wrong counter): nothing lost
    cur = clean.take(np.flatnonzero(clean.arbitration_id == clean.arbitration_id[0]))
    s = cur.take(np.r_[0:11, 10, 12:30])  # frame 10 twice, frame 11 lost
    dec = Decoder(Protocol.load())
    dec.decode(s)
    assert dec.rejected["repeated"] == 1 and dec.lost["DriveCurrent"] == 1
    late = _miscount(cur.take(np.arange(30)), 11, 15)  # frame 11 says 10
    dec = Decoder(Protocol.load())
    dec.decode(late)
    assert dec.rejected["repeated"] == 1 and dec.lost["DriveCurrent"] == 0
