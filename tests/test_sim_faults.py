"""Fault injection: spec parsing, counts, and the strict decoder's counters against the log."""

from __future__ import annotations

import numpy as np
import pytest

from canrls.can.frameblock import FrameBlock
from canrls.can.protocol import Protocol
from canrls.errors import ConfigError
from canrls.sim import FaultInjector, FaultSpec, inject, simulate
from canrls.sim.faults import Silence

DRIVE_CURRENT, DRIVE_SPEED = 0x101, 0x102


@pytest.fixture(scope="module")
def frames() -> FrameBlock:
    """20 s of clean drive frames (40000)."""
    return simulate("standard", duration=20.0, seed=7).frames


def _decode(block: FrameBlock):  # type: ignore[no-untyped-def]
    dec = Protocol.load().decoder()
    dec.decode(block)
    return dec


# --------------------------------------------------------------------------- parsing


def test_parse_full_spec() -> None:
    s = FaultSpec.parse("drop=0.01,dup=0.005,reorder=0.01,corrupt=0.001,silence=0.5s@10s")
    assert (s.drop, s.dup, s.reorder, s.corrupt) == (0.01, 0.005, 0.01, 0.001)
    assert s.silence == (Silence(0.5, 10.0),)
    assert str(s) == "drop=0.01,dup=0.005,reorder=0.01,corrupt=0.001,silence=0.5s@10s"
    assert FaultSpec.parse(str(s)) == s


def test_parse_silence_forms() -> None:
    s = FaultSpec.parse("silence=500ms@2,silence=1s@30s/60s+0.2@5s")
    assert s.silence == (Silence(0.5, 2.0), Silence(1.0, 30.0, 60.0), Silence(0.2, 5.0))
    for text in ("", "none", None):
        assert not FaultSpec.parse(text).active


@pytest.mark.parametrize(("spec", "field"), [
    ("drop=2", "drop"),
    ("dup=-0.1", "dup"),
    ("reorder=lots", "reorder"),
    ("corrupt", "corrupt"),
    ("silence=0.5s", "silence"),
    ("silence=0s@1s", "silence"),
    ("silence=1s@2s/0.5s", "silence"),
    ("silence=abc@1s", "silence"),
    ("jitter=0.1", "jitter"),
    ("drop=0.1,drop=0.2", "drop"),
])
def test_bad_spec_names_the_field(spec: str, field: str) -> None:
    with pytest.raises(ConfigError, match=field):
        FaultSpec.parse(spec)


# --------------------------------------------------------------------------- counts


def test_no_faults_is_identity(frames: FrameBlock) -> None:
    out, log = inject(frames, "none")
    assert out is frames and log.frames_in == log.frames_out == len(frames)


def test_counts_add_up(frames: FrameBlock) -> None:
    out, log = inject(frames, "drop=0.02,dup=0.01,reorder=0.01,corrupt=0.005,silence=0.5s@10s",
                      seed=3)
    assert log.frames_in == len(frames)
    assert log.frames_out == len(out) == len(frames) - log.lost + log.duplicated
    assert log.silenced == 1000  # 0.5 s of two 1 kHz messages
    n = len(frames)
    for kind, p in (("dropped", 0.02), ("duplicated", 0.01), ("corrupted", 0.005)):
        got = getattr(log, kind)
        assert abs(got - p * n) < 5 * np.sqrt(p * n), kind
    assert log.reordered > 0
    for kind in ("dropped", "duplicated", "corrupted", "reordered", "silenced"):
        assert sum(log.per_id[kind].values()) == getattr(log, kind)
    assert np.all(np.diff(out.t) >= 0)  # receive times stay in order


def test_seeded(frames: FrameBlock) -> None:
    a, la = inject(frames, "drop=0.05,corrupt=0.01", seed=1)
    b, lb = inject(frames, "drop=0.05,corrupt=0.01", seed=1)
    c, _ = inject(frames, "drop=0.05,corrupt=0.01", seed=2)
    assert np.array_equal(a.data, b.data) and la == lb
    assert len(a) != len(c) or not np.array_equal(a.data, c.data)


def test_silence_window_is_empty(frames: FrameBlock) -> None:
    out, log = inject(frames, "silence=1s@5s/8s")
    rel = out.t - frames.t[0]
    assert not np.any((rel >= 5) & (rel < 6)) and not np.any((rel >= 13) & (rel < 14))
    assert log.silenced == 4000


def test_injector_streams_blocks(frames: FrameBlock) -> None:
    inj = FaultInjector("drop=0.01,silence=1s@3s", seed=0)
    outs = [inj.apply(frames.take(slice(k, k + 7000))) for k in range(0, len(frames), 7000)]
    assert inj.log.frames_in == len(frames)
    assert inj.log.silenced == 2000
    assert sum(len(o) for o in outs) == inj.log.frames_out


# --------------------------------------------------------------------------- against the decoder


def test_decoder_counts_match_the_fault_log(frames: FrameBlock) -> None:
    # each fault alone, so that the decoder's counters map one to one
    out, log = inject(frames, "corrupt=0.01", seed=1)
    dec = _decode(out)
    assert dec.rejected["crc"] == log.corrupted > 0

    out, log = inject(frames, "dup=0.01", seed=2)
    dec = _decode(out)
    assert dec.rejected["repeated"] == log.duplicated > 0

    out, log = inject(frames, "drop=0.01", seed=3)
    dec = _decode(out)
    assert sum(dec.lost.values()) == log.dropped > 0
    assert dec.lost["DriveCurrent"] == log.per_id["dropped"].get(DRIVE_CURRENT, 0)

    out, log = inject(frames, "silence=0.5s@4s,silence=0.25s@12s", seed=4)
    dec = _decode(out)
    assert sum(dec.lost.values()) == log.silenced == 1500

    out, log = inject(frames, "reorder=0.005", seed=5)
    dec = _decode(out)
    # a swap: the later frame arrives first (one counted lost), the earlier one is stale
    assert dec.rejected["stale"] == log.reordered > 0
    assert dec.rejected.total == log.reordered


def test_simulate_applies_scenario_faults() -> None:
    r = simulate("standard", duration=5.0, seed=9, faults="drop=0.05,corrupt=0.01")
    log = r.fault_log
    assert log.frames_in == 10000 and len(r.frames) == log.frames_out
    dec = _decode(r.frames)
    assert dec.rejected["crc"] == log.corrupted
    # a frame rejected for its CRC leaves a gap in the alive counter, as a dropped one does
    assert sum(dec.lost.values()) == log.dropped + log.corrupted
