"""Clock faults and reordering: time is monotonic inside, and faults are visible.

Timestamps that step back (NTP, a merged log) or forward, gaps, absurd timestamps in a
log and frames swapped with their neighbour: each is detected, counted and published,
and none stops or biases the estimation (docs/protocol.md, ``RlsRejects``; the
``ClockFault`` health bit)."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from canrls.can.decoder import Decoder
from canrls.can.encoder import FeedbackEncoder
from canrls.can.frameblock import FrameBlock
from canrls.can.logs import LogReadStats, read_frames, write_candump
from canrls.can.protocol import Protocol
from canrls.core.errors import LogFormatError
from canrls.processor.config import AppConfig, prepare
from canrls.processor.pairing import Pairer
from canrls.processor.period import estimate_period
from canrls.processor.replay import fit_frames, fit_log
from canrls.sim.faults import inject
from canrls.sim.scenario import scenario, simulate

EFFECTS = "inertia,viscous,coulomb"


def _setup() -> tuple:
    cfg = AppConfig()
    cfg.model = {"effects": EFFECTS.split(","), "kt": 0.1}
    return prepare(cfg)


@pytest.fixture(scope="module")
def sim() -> FrameBlock:
    """8 s of the simulated drive at 1 kHz (clean frames)."""
    return simulate(scenario("standard", effects=EFFECTS, seed=3, duration=8.0)).frames


def _stepped(block: FrameBlock, at: float, by: float) -> FrameBlock:
    """The frames with every timestamp from the share ``at`` of the log on moved by ``by``."""
    t = block.t.copy()
    t[int(at * len(t)):] += by
    return dataclasses.replace(block, t=t)


# --------------------------------------------------------------------------- log lines
@pytest.mark.parametrize("stamp", ["inf", "-inf", "nan", "1e300", "99999999999.000000"])
def test_absurd_timestamp_is_a_bad_line_naming_file_and_line(tmp_path: Path,
                                                            stamp: str) -> None:
    lines = [f"({1.0 + k * 1e-3:.6f}) can0 101#00112233" for k in range(6)]
    lines.insert(3, f"({stamp}) can0 101#00112233")
    path = tmp_path / "bad.log"
    path.write_text("\n".join(lines) + "\n")
    with pytest.raises(LogFormatError, match=r"bad\.log:4: .*timestamp"):
        list(read_frames(path))
    stats = LogReadStats()
    got = FrameBlock.concat(read_frames(path, skip_bad_lines=True, stats=stats))
    assert stats.bad_lines == 1
    assert got.t.tolist() == [float(f"{1.0 + k * 1e-3:.6f}") for k in range(6)]


def test_inf_line_in_a_log_does_not_stop_the_fit(tmp_path: Path, sim: FrameBlock) -> None:
    """One ``(inf)`` line in the middle, skipped: every other frame is paired."""
    path = tmp_path / "inf.log"
    write_candump(path, [sim])
    lines = path.read_text().splitlines(keepends=True)
    half = len(lines) // 2
    lines.insert(half, "(inf) can0 101#0011223344556677\n")
    path.write_text("".join(lines))
    with pytest.raises(LogFormatError, match=rf"inf\.log:{half + 1}:"):
        fit_log(path, *_setup())
    fit = fit_log(path, *_setup(), skip_bad_lines=True)
    assert fit.frames.pairing["samples"] == len(sim) // 2
    assert fit.frames.pairing["late"] == 0


# --------------------------------------------------------------------------- steps
def test_step_back_is_counted_and_estimation_resumes(tmp_path: Path, sim: FrameBlock) -> None:
    """A 60 s step back in an 8 s log: before, every frame after it was late (half the
    samples lost); now it is one counted step, and the samples continue."""
    path = tmp_path / "step.log"
    write_candump(path, [_stepped(sim, 0.5, -60.0)])
    fit = fit_log(path, *_setup())
    clean = fit_frames([sim], *_setup())
    assert fit.frames.pairing["step_back"] == 1
    assert fit.frames.pairing["late"] == 0 and fit.frames.pairing["unpaired"] == 0
    assert fit.frames.pairing["samples"] == clean.frames.pairing["samples"]
    for a, b in zip(fit.parameters, clean.parameters, strict=True):
        assert abs(a.value - b.value) < 2 * b.sigma, (a, b)


def test_step_forward_is_a_step_not_lost_frames(sim: FrameBlock) -> None:
    fit = fit_frames([_stepped(sim, 0.5, 60.0)], *_setup())
    assert fit.frames.pairing["step_forward"] == 1
    assert fit.frames.pairing["lost"] == 0 and fit.frames.pairing["samples"] == len(sim) // 2
    # the alive counters neither: the time infers wraps only up to 1 s (before: 60 s of
    # frames, 120000, counted lost)
    assert sum(fit.frames.lost.values()) == 0


def test_sample_times_stay_monotonic_across_steps() -> None:
    """Steps back and forward, in blocks of any size: the pairer's sample times never go
    back, and the same samples come out whatever the cuts."""
    p = Protocol.load()
    n = 400
    k = np.arange(n, dtype=np.float64)
    block = FeedbackEncoder(p, stagger=1e-4).encode(k * p.period, k / 100, k / 50, k / 10,
                                                    k / 10)
    block = _stepped(_stepped(block, 0.25, -5.0), 0.75, 3.0)
    outs = []
    for cuts in ([], [1, 7, 200, 201, 599, 600, 601]):
        dec, pr = Decoder(p), Pairer(p)
        bounds = list(zip([0, *cuts], [*cuts, len(block)], strict=True))
        parts = [pr.push(dec.decode(block.take(slice(a, b)))) for a, b in bounds]
        parts.append(pr.flush())
        t = np.concatenate([s.t for s in parts])
        cur = np.concatenate([s.current for s in parts])
        assert np.all(np.diff(t) > 0)
        assert pr.counts.clock == {"step_back": 1, "step_forward": 1, "gap": 0}
        outs.append((t, cur))
    assert np.array_equal(outs[0][0], outs[1][0]) and np.array_equal(outs[0][1], outs[1][1])
    assert len(outs[0][0]) >= n - 4


def test_gap_is_counted_with_its_lost_frames() -> None:
    p = Protocol.load()
    k = np.arange(100, dtype=np.float64)
    k = k[(k < 40) | (k >= 50)]  # 10 periods silent
    block = FeedbackEncoder(p, stagger=1e-4).encode(k * p.period, k / 100, k / 50, k / 10,
                                                    k / 10)
    dec, pr = Decoder(Protocol.load(check_counter=False)), Pairer(p)
    pr.push(dec.decode(block))
    pr.flush()
    c = pr.counts
    assert c.clock == {"step_back": 0, "step_forward": 0, "gap": 1}
    assert c.lost == 2 * 10 and c.samples == 90


# --------------------------------------------------------------------------- period meter
@pytest.mark.parametrize("by", [-60.0, -0.05, 30.0])
@pytest.mark.parametrize("kind", ["jitter", "relayed"])
def test_period_meter_ignores_a_clock_step(by: float, kind: str) -> None:
    rng = np.random.default_rng(5)
    p = 2e-3
    t = 1.7e9 + p * np.arange(257)
    if kind == "jitter":
        t = t + rng.normal(0, 0.05 * p, len(t))
    else:  # groups of 4 frames delivered together, 2 µs apart
        i = np.arange(len(t))
        t = t[np.minimum((i // 4) * 4 + 3, len(t) - 1)] + 2e-6 * (i % 4)
    t[100:] += by
    est = estimate_period({"DriveCurrent": t, "DriveSpeed": t + 1e-4})
    assert est is not None
    assert est.period == pytest.approx(p, rel=0.02)


# --------------------------------------------------------------------------- reordering
@pytest.mark.parametrize("block", [None, 37])
def test_neighbour_swaps_do_not_bias_the_estimate(sim: FrameBlock, block: int | None) -> None:
    """20 % of the frames swapped with their neighbour of the same ID (contents move, the
    receive times stay): put back by their counters, inertia within 1 sigma of the clean
    log; before, -1.2 % (-59 sigma) with half the samples lost. In blocks of 37 frames
    (the daemon's blocks are whatever arrived) as in one."""
    swapped, log = inject(sim, "reorder=0.2", seed=1)
    assert log.reordered > 0.05 * len(sim)
    blocks = [swapped] if block is None else [swapped.take(slice(k, k + block))
                                              for k in range(0, len(swapped), block)]
    fit = fit_frames(blocks, *_setup())
    clean = fit_frames([sim], *_setup())
    assert fit.frames.rejected["stale"] == 0
    assert fit.frames.pairing["samples"] == clean.frames.pairing["samples"]
    for a, b in zip(fit.parameters, clean.parameters, strict=True):
        assert abs(a.value - b.value) <= b.sigma, (a, b)


def _counter_block(counters: list[int]) -> tuple[Protocol, FrameBlock]:
    """DriveCurrent frames (only) with these alive counters, one per period."""
    p = Protocol.load()
    k = np.arange(16, dtype=np.float64)
    b = FeedbackEncoder(p, stagger=1e-4).encode(k * p.period, k / 100, k / 50, k / 10, k / 10)
    cur = b.take(b.arbitration_id == p.messages[0].frame_id)  # counters 0..15
    out = cur.take(np.array(counters, np.intp))
    return p, dataclasses.replace(out, t=cur.t[:len(counters)].copy())


def test_reorderer_puts_swaps_back_and_leaves_losses_and_repeats() -> None:
    from canrls.processor.reorder import Reorderer

    p, b = _counter_block([0, 1, 3, 2, 4, 6, 7, 7, 9, 12, 10, 11, 13])
    r = Reorderer(p.messages)
    out = FrameBlock.concat([r.push(b.take(slice(0, 3))), r.push(b.take(slice(3, None))),
                             r.flush()])
    c = p.messages[0].counter.extract(out.data).astype(int).tolist()
    # 3,2 swapped back (across the cut); 5 lost; 7 repeated; 12 moved back by two
    assert c == [0, 1, 2, 3, 4, 6, 7, 7, 9, 10, 11, 12, 13]
    assert np.array_equal(out.t, b.t)  # the receive times stay where they were
    assert r.moved == 1 + 2  # frames moved up: 2; 10 and 11


# --------------------------------------------------------------------------- live
def test_daemon_on_a_bus_with_a_clock_step_keeps_estimating_and_says_so(
        sim: FrameBlock) -> None:
    """The daemon on a virtual bus fed frames whose timestamps step back 60 s half-way:
    every period still becomes a sample and updates the estimators (as the offline front
    end on the same frames), ClockFault and RlsRejects.ClockSteps go out on the bus, and
    the monitor shows them."""
    from daemon_tool import daemon_fed

    from canrls.can.estimator_frames import FrameDecoder
    from canrls.live.monitor_listener import Monitor
    from canrls.processor import FrameProcessor

    frames = _stepped(sim, 0.5, -60.0)
    messages = frames.to_messages()
    protocol, model, settings = _setup()
    with daemon_fed(protocol, model, settings, messages, "test-fault-clock") as (d, reader):
        live_updates = d.processor.pipeline.update_counts()
        live_samples = d.stats().samples
        status = d.status()
    offline = FrameProcessor(protocol, model, settings)
    offline.process(frames)
    assert live_samples == offline.pipeline.samples == len(sim) // 2
    assert live_updates == offline.pipeline.update_counts()
    clean = FrameProcessor(protocol, model, settings)
    clean.process(sim)
    # the step costs one warm-up of the filter, not the rest of the log
    lost = clean.pipeline.update_counts()[0][0] - live_updates[0][0]
    assert 0 < lost < 0.05 * clean.pipeline.update_counts()[0][0]
    assert status.rejects["clock_steps"] == 1

    dec, mon, flags = FrameDecoder(), Monitor(), []
    while (m := reader.get_message(0.0)) is not None:
        out = dec.feed(m)
        mon.on_message_received(m)
        if m.arbitration_id == 0x311 and out is not None:
            flags.append(out.clock_fault)
    assert any(flags) and not flags[-1]  # set after the step, cleared after RlsRejects
    assert dec.status is not None and dec.status.rejects["clock_steps"] == 1
    view = mon.snapshot()
    assert view.to_dict()["rejects"]["clock_steps"] == 1
    assert "clock steps 1" in view.format()


def test_a_frame_without_a_time_is_dropped_and_pairing_goes_on() -> None:
    """A non-finite timestamp (a FrameBlock built by hand, a reader without the log
    check): before, one +inf frame made every later frame late."""
    p = Protocol.load(check_counter=False)
    k = np.arange(40, dtype=np.float64)
    block = FeedbackEncoder(p, stagger=1e-4).encode(k * p.period, k / 100, k / 50, k / 10,
                                                    k / 10)
    t = block.t.copy()
    t[21] = np.inf
    t[31] = np.nan
    dec, pr = Decoder(p), Pairer(p)
    pr.push(dec.decode(dataclasses.replace(block, t=t)))
    pr.flush()
    c = pr.counts
    assert c.samples == 38 and c.late == 2 and c.clock["step_forward"] == 0


def test_the_published_totals_are_those_of_the_frame_counts(sim: FrameBlock) -> None:
    """:meth:`FrameProcessor.frames_rejected` and ``frames_lost`` (what every
    publication sends) are the sums of :meth:`frame_counts`, restarts included."""
    from canrls.processor import FrameProcessor

    faulty, _ = inject(sim, "drop=0.01,corrupt=0.01,counter=0.01,dlc=0.01", seed=7)
    proc = FrameProcessor(*_setup())
    half = len(faulty) // 2
    for part in (faulty.take(slice(0, half)), faulty.take(slice(half, None))):
        proc.process(part)
        counts = proc.frame_counts()
        assert sum(counts.rejected.values()) > 0 and sum(counts.lost.values()) > 0
        assert proc.frames_rejected() == sum(counts.rejected.values())
        assert proc.frames_lost() == sum(counts.lost.values())
        proc.restart()
