"""Fault injection: spec parsing, counts, and the strict decoder's counters against the log."""

from __future__ import annotations

import numpy as np
import pytest

from canrls.can.decoder import Decoder
from canrls.can.frameblock import FrameBlock
from canrls.can.protocol import Protocol
from canrls.core.errors import ConfigError
from canrls.sim import FaultInjector, FaultSpec, inject, simulate
from canrls.sim.faults import Silence

DRIVE_CURRENT, DRIVE_SPEED = 0x101, 0x102


@pytest.fixture(scope="module")
def frames() -> FrameBlock:
    """20 s of clean drive frames (40000)."""
    return simulate("standard", duration=20.0, seed=7).frames


def _decode(block: FrameBlock):  # type: ignore[no-untyped-def]
    dec = Decoder(Protocol.load())
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
    # a swap (no reorderer here): the later frame arrives a period ahead of its time and
    # is rejected (``sequence``, a few ``stale`` where swaps meet), the earlier continues
    assert dec.rejected["sequence"] + dec.rejected["stale"] == log.reordered > 0
    assert dec.rejected.total == log.reordered


def test_simulate_applies_scenario_faults() -> None:
    r = simulate("standard", duration=5.0, seed=9, faults="drop=0.05,corrupt=0.01")
    log = r.fault_log
    assert log.frames_in == 10000 and len(r.frames) == log.frames_out
    dec = _decode(r.frames)
    assert dec.rejected["crc"] == log.corrupted
    # a frame rejected for its CRC was received: rejected, not lost
    # (tests/can/test_fault_counter.py)
    assert sum(dec.lost.values()) == log.dropped


# ----------------------------------------------------------------- the hostile rest of a bus


def test_parse_bus_faults() -> None:
    s = FaultSpec.parse("counter=0.01,dlc=0.002,tstep=1e-4,tstep_max=200ms,cmd=1e-3,"
                        "cmd_burst=8,errframe=1e-3")
    assert (s.counter, s.dlc, s.tstep, s.tstep_max, s.cmd, s.cmd_burst, s.errframe) == \
        (0.01, 0.002, 1e-4, 0.2, 1e-3, 8, 1e-3)
    assert s.active and FaultSpec.parse(str(s)) == s


@pytest.mark.parametrize(("spec", "field"), [
    ("counter=1.5", "counter"),
    ("dlc=x", "dlc"),
    ("tstep_max=0s", "tstep_max"),
    ("tstep_max=soon", "tstep_max"),
    ("cmd_burst=0", "cmd_burst"),
    ("cmd_burst=2.5", "cmd_burst"),
    ("errframe=-1", "errframe"),
    ("cmd=0.1,cmd=0.2", "cmd"),
])
def test_bad_bus_fault_spec_names_the_field(spec: str, field: str) -> None:
    with pytest.raises(ConfigError, match=field):
        FaultSpec.parse(spec)


def test_counter_fault_keeps_the_crc_valid(frames: FrameBlock) -> None:
    out, log = inject(frames, "counter=0.01", seed=11)
    assert log.miscounted > 0 and len(out) == len(frames)
    changed = np.flatnonzero(np.any(out.data != frames.data, axis=1))
    assert len(changed) == log.miscounted
    # only the CRC byte and the counter nibble change; the counter always moves
    assert np.array_equal(out.data[changed, 2:], frames.data[changed, 2:])
    assert np.array_equal(out.data[changed, 1] & 0xF0, frames.data[changed, 1] & 0xF0)
    assert np.all((out.data[changed, 1] & 0x0F) != (frames.data[changed, 1] & 0x0F))
    dec = _decode(out)
    assert dec.rejected["crc"] == 0  # the CRC holds: only the counter check can tell
    assert dec.rejected["stale"] + dec.rejected["repeated"] + sum(dec.lost.values()) > 0


def test_dlc_fault_is_rejected_for_its_length(frames: FrameBlock) -> None:
    out, log = inject(frames, "dlc=0.005", seed=12)
    assert log.resized > 0
    changed = np.flatnonzero(out.dlc != frames.dlc)
    assert len(changed) == log.resized and np.all(out.dlc <= 8)
    dec = _decode(out)
    assert dec.rejected["length"] == log.resized


def test_clock_steps_add_up_across_blocks(frames: FrameBlock) -> None:
    inj = FaultInjector("tstep=0.0005,tstep_max=0.3s", seed=13)
    halves = [frames.take(slice(0, 20000)), frames.take(slice(20000, None))]
    out = FrameBlock.concat([inj.apply(b) for b in halves])
    shift = out.t - frames.t
    jumps = np.flatnonzero(np.abs(np.diff(shift)) > 1e-9)
    steps = np.diff(shift)[jumps]
    assert inj.log.clock_steps == len(jumps) + int(abs(shift[0]) > 1e-9) > 2
    assert np.any(steps < 0) and np.any(steps > 0) and np.all(np.abs(steps) <= 0.3)
    assert shift[-1] == pytest.approx(inj.log.clock_offset)
    assert np.array_equal(out.data, frames.data)  # only the receive times move


def test_error_frames_and_command_bursts_are_inserted(frames: FrameBlock) -> None:
    from canrls.sim.faults import ERROR_CLASSES
    out, log = inject(frames, "errframe=0.001,cmd=0.0005,cmd_burst=5", seed=14)
    err = out.is_error
    cmd = out.arbitration_id == 0x320
    assert err.sum() == log.error_frames > 0 and cmd.sum() == log.commands > 0
    assert set(out.arbitration_id[err].tolist()) <= set(ERROR_CLASSES)
    assert log.command_bursts <= log.commands <= 2 * 5 * log.command_bursts
    assert len(out) == log.frames_out == len(frames) + log.inserted
    # the drive's frames are all there, in their order, and time never runs backwards
    assert np.array_equal(out.data[~err & ~cmd], frames.data)
    assert np.all(np.diff(out.t) >= 0)


def test_injected_commands_leave_the_estimates_as_they_were(frames: FrameBlock) -> None:
    """Every injected command is random (refused) or valid but harmless: a daemon that
    processes the stream with them ends with the estimates of the stream without them,
    bit for bit, and answers every one."""
    from canrls.can.estimator_frames import CommandCode, decode_command
    from canrls.core.errors import CommandError
    from canrls.live.daemon import Daemon
    from canrls.live.daemon_settings import DaemonSettings
    from canrls.processor.config import AppConfig

    out, log = inject(frames, "cmd=0.002,cmd_burst=6", seed=15)
    msgs = out.to_messages()
    codes = []
    for m in msgs:
        if m.arbitration_id == 0x320:
            try:
                codes.append(decode_command(m).code)
            except CommandError:
                codes.append(None)
    assert codes.count(None) > 0 and CommandCode.FREEZE in codes
    assert CommandCode.RESET not in codes and CommandCode.REMOVE_EFFECT not in codes

    def run(stream: list) -> tuple[np.ndarray, int]:  # type: ignore[type-arg]
        cfg = AppConfig()
        cfg.model = {"effects": ["inertia", "viscous", "coulomb"], "kt": 0.1}
        protocol = cfg.protocol()
        d = Daemon(protocol, cfg.model_for(protocol), cfg.settings(),
                   DaemonSettings(commands=True), bus={"interface": "virtual",
                                                       "channel": "never-opened"})
        for k in range(0, len(stream), 5000):
            d.process(stream[k:k + 5000])
        theta = np.array([p.value for eq in d.pipeline.parameters() for p in eq]
                         + [p.fixed for eq in d.pipeline.parameters() for p in eq])
        return theta, d.stats().commands

    with_cmds, answered = run(msgs)
    without, none = run(frames.to_messages())
    assert answered == log.commands > 0 and none == 0
    assert np.array_equal(with_cmds, without)


def test_a_moved_drive_gets_counter_faults_and_its_own_commands() -> None:
    """A drive on another axis's IDs (the default DBC's + 0x10): its alive-counter faults
    hit its own protected frames (not the default DBC's IDs, where it sends nothing), and
    its inserted commands go to the command ID it is given, as the soak of a machine
    needs (``tools/soak.py --axes``)."""
    from canrls.can.idrules import IdRule
    from canrls.sim.scenario import Simulator, scenario

    moved = Protocol.load().with_ids(IdRule("offset", 0x10))
    sc = scenario("standard", duration=5.0, seed=8, faults="counter=0.01,cmd=0.001,cmd_burst=3")
    sim = Simulator(sc, protocol=moved, command_id=0x360)
    out = FrameBlock.concat(list(sim.frames(1000)))
    log = sim.fault_log
    assert log.miscounted > 50  # ~1 % of 10000 frames
    assert set(log.per_id["miscounted"]) == {DRIVE_CURRENT + 0x10, DRIVE_SPEED + 0x10}
    assert 0 < log.commands == int(np.count_nonzero(out.arbitration_id == 0x360))
    assert not np.isin(out.arbitration_id, [0x320, DRIVE_CURRENT, DRIVE_SPEED]).any()
    dec = Decoder(moved)
    dec.decode(out)
    assert dec.rejected["crc"] == 0  # each CRC computed over the moved ID
    assert dec.rejected["stale"] + dec.rejected["repeated"] + sum(dec.lost.values()) > 0
