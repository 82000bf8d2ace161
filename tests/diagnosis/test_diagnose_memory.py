"""Memory of ``canrls diagnose``: the peak traced memory (tracemalloc: numpy's arrays
included) on a simulated log and on one four times longer. A bound on memory, not on
time: the growth per extra sample must stay below :data:`BYTES_PER_SAMPLE`.

The pipeline's working arrays are one block long (:data:`canrls.diagnosis.analysis.
CHUNK`), not the record's, and so are the statistics' (:data:`canrls.diagnosis.record.
BLOCK`); what still grows with the record is listed in docs/diagnose.md ("Memory").
"""

from __future__ import annotations

import gc
import json
import tracemalloc
from pathlib import Path

import numpy as np
import pytest

from canrls.cli.main import main
from canrls.core.spill import MaskPacker, PackedMask, SpilledSignals
from canrls.diagnosis import analysis, record, residual, results
from canrls.diagnosis.analysis import diagnose_log
from canrls.processor.config import load_config, prepare

#: Bytes of peak memory per sample of the record that the diagnosis may grow by. Nothing
#: it keeps is a row long (the masks go to a temporary file past a chunk's bits; the
#: whiteness test's series, every 38th used row, and a few numbers per block and per
#: gap are all that grows): -1.1 and -1.0 measured here, the peaks of the two runs
#: falling on blocks of different lengths. (374 bytes per sample here before
#: the diagnosis ran the pipeline in blocks, fitted the residual left block by block and
#: re-ran the fixed-point estimator for its trace; 181 after; 103 with the statistics,
#: columns and traces built block by block; 73 with the filtered signals filtered again
#: block by block when read; 57 with the residuals too (108 with lost frames); 48, and
#: 51 with lost frames, with the gap-filled record and the unwrapped position not kept;
#: 8.4 and 10.8 with the samples in a temporary file; 4.9 and 5.4 with the masks of
#: the filled record and of the selection rules packed, one bit a row; the used masks
#: of the equations and of the candidates' samples were kept unpacked, a byte a row.)
BYTES_PER_SAMPLE = 0.5
SHORT_S = 20


def _one_thread(monkeypatch: pytest.MonkeyPatch) -> None:
    """The offline replay in one thread: its read-ahead (the next block parsed) and the
    fixed-point estimator's thread hold a block's arrays more at moments their timing
    decides, a constant that would show as growth in a difference of peaks now and then;
    these tests measure what grows with the log."""
    from canrls.can import logs
    from canrls.estimation import pipeline

    monkeypatch.setattr(logs, "READ_AHEAD", 1 << 62)
    monkeypatch.setattr(pipeline, "OVERLAP_ROWS", 1 << 62)


def _peak(path: Path, chunk: int, monkeypatch: pytest.MonkeyPatch) -> tuple[int, int]:
    """(samples, peak traced bytes above the start) of diagnosing ``path``."""
    # every block shorter than the short log, so that only what grows with the record
    # differs between the two runs (in use the blocks are 32768 and 65536 samples long)
    monkeypatch.setattr(analysis, "CHUNK", chunk, raising=False)
    monkeypatch.setattr(record, "BLOCK", chunk)
    monkeypatch.setattr(residual, "BLOCK", chunk)
    # the figures' points too (in use up to 20000 per trace, a fixed amount)
    monkeypatch.setattr(results, "FIGURE_POINTS", chunk // 4, raising=False)
    # the chunks of the temporary file of the samples (its write buffer is one chunk)
    monkeypatch.setattr(SpilledSignals, "ROWS", chunk)
    # the bits a mask keeps in memory before they go to a temporary file (a chunk's)
    monkeypatch.setattr(MaskPacker, "MEMORY", chunk // 8, raising=False)
    _one_thread(monkeypatch)
    cfg = load_config(None)
    cfg.model["kt"] = 0.1
    protocol, model, settings = prepare(cfg)
    gc.collect()
    tracemalloc.start()
    try:
        start, _ = tracemalloc.get_traced_memory()
        # the log read in blocks of frames shorter than the short log too (the
        # reader's scratch space is one block)
        rep = diagnose_log(path, protocol, model, settings, max_order=8,
                           chunk_size=chunk)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    return rep.samples, peak - start


CHUNK = 4096


@pytest.fixture(scope="module")
def warm(tmp_path_factory: pytest.TempPathFactory) -> None:
    """One diagnosis of a short log first: it loads and compiles the kernels."""
    p = tmp_path_factory.mktemp("warm") / "warm.log"
    assert main(["sim", "--out", str(p), "--duration", "4", "--seed", "4",
                 "--effects", "inertia,viscous,coulomb,offset"]) == 0
    with pytest.MonkeyPatch.context() as mp:
        _peak(p, CHUNK, mp)


@pytest.mark.parametrize("faults", ["", "drop=0.01"], ids=["complete", "dropped_frames"])
def test_diagnose_memory_grows_little_with_the_log(tmp_path: Path,
                                                  monkeypatch: pytest.MonkeyPatch,
                                                  faults: str, warm: None) -> None:
    """Also with lost frames: the gap-filled record is not kept but filled again
    where read (:class:`canrls.estimation.selection.FilledRecord`)."""
    logs = []
    for k, seconds in enumerate((SHORT_S, 4 * SHORT_S)):
        p = tmp_path / f"drive{k}.log"
        assert main(["sim", "--out", str(p), "--duration", str(seconds), "--seed", "4",
                     "--effects", "inertia,viscous,coulomb,offset"]
                    + (["--faults", faults] if faults else [])) == 0
        logs.append(p)
    chunk = CHUNK
    n1, p1 = _peak(logs[0], chunk, monkeypatch)
    n4, p4 = _peak(logs[1], chunk, monkeypatch)
    assert n4 > 3 * n1
    growth = (p4 - p1) / (n4 - n1)
    print(f"{faults or 'complete'}: {growth:.1f} bytes per extra sample")
    assert growth < BYTES_PER_SAMPLE, (
        f"peak {p1 / 1e6:.1f} MB for {n1} samples, {p4 / 1e6:.1f} MB for {n4}: "
        f"{growth:.0f} bytes per extra sample")


def test_blocks_give_the_answer_of_one_run(tmp_path: Path,
                                           monkeypatch: pytest.MonkeyPatch) -> None:
    """The record run in blocks (with lost frames and a silence: gaps and filter
    restarts across block boundaries) gives the report of a single run, bit for bit."""
    p = tmp_path / "gaps.log"
    assert main(["sim", "--out", str(p), "--duration", "12", "--seed", "6",
                 "--effects", "inertia,viscous,coulomb,offset",
                 "--faults", "drop=0.01,dup=0.005,silence=0.3s@5s"]) == 0
    cfg = load_config(None)
    cfg.model["kt"] = 0.1
    protocol, model, settings = prepare(cfg)
    reports = []
    for chunk in (1 << 30, 3000):
        monkeypatch.setattr(analysis, "CHUNK", chunk, raising=False)
        rep = diagnose_log(p, protocol, model, settings, max_order=8, add=["offset"])
        reports.append(json.dumps(rep.to_dict(), sort_keys=True, default=str))
    assert reports[0] == reports[1]


@pytest.mark.parametrize("kind", ["normal", "quantised", "heavy", "constant"])
def test_order_statistics_without_a_copy_are_numpys(kind: str,
                                                    monkeypatch: pytest.MonkeyPatch) -> None:
    """The bin edges and the noise estimate read exact percentiles and medians block by
    block (a grid count, then the bin that holds the value): numpy's, bit for bit, also
    with many equal values and across block boundaries."""
    rng = np.random.default_rng(11)
    monkeypatch.setattr(residual, "BLOCK", 1000)
    for n in (1, 2, 7, 4000, 150_001):
        x = {"normal": rng.normal(size=n), "quantised": np.round(rng.normal(size=n) * 8) / 8,
             "heavy": rng.standard_cauchy(size=n), "constant": np.full(n, 2.5)}[kind]
        for rows in (None, rng.random(n) < 0.7):
            if rows is not None and not rows.any():
                continue
            xs = x if rows is None else x[rows]
            qs = [0.0, 0.5, 50.0, 99.0, 99.5, 100.0]
            assert residual.percentiles(x, rows, qs) == [float(v) for v in
                                                         np.percentile(xs, qs)]
            assert residual.median(x, rows) == float(np.median(xs))


def test_filtered_signals_read_in_blocks_are_one_pass(tmp_path: Path,
                                                     monkeypatch: pytest.MonkeyPatch) -> None:
    """The filtered speed, acceleration, current and position are not kept: read in
    slices or at sorted rows they are filtered again block by block from saved filter
    states, and equal one pass of the filter over the gap-filled record, bit for bit
    (gaps and filter restarts inside and across blocks)."""
    from canrls.diagnosis.record import RecordSamples
    from canrls.estimation.svf import SVF
    from canrls.processor.replay import read_logs

    p = tmp_path / "gaps.log"
    assert main(["sim", "--out", str(p), "--duration", "6", "--seed", "8",
                 "--faults", "drop=0.02,silence=0.2s@2s"]) == 0
    cfg = load_config(None)
    cfg.model["kt"] = 0.1
    protocol, model, settings = prepare(cfg)
    log = read_logs([p], protocol, model, settings)
    monkeypatch.setattr(record, "BLOCK", 777)
    ctx = RecordSamples(log.model, log.signals, log.dt, settings, 8)
    assert ctx.selected.real is not None and len(ctx.segments()) > 1
    filled = ctx.selected.signals
    held = log.model.held
    hold = {r: ("zoh" if r in held else "foh") for r in ("speed", "current", "position")}
    svf = SVF(log.model.cutoff_hz, log.dt, log.model.zeta, (hold["speed"], hold["current"]))
    ref = {"speed": np.empty(len(filled)), "acceleration": np.empty(len(filled)),
           "current": np.empty(len(filled))}
    for a, b in ctx.segments():
        svf.reset()
        fb = filled.slice(a, b)
        f, sf = svf.process(np.column_stack([fb.speed, fb.current]))
        ref["speed"][a:b], ref["acceleration"][a:b], ref["current"][a:b] = \
            f[:, 0], sf[:, 0], f[:, 1]
    rng = np.random.default_rng(3)
    n = len(log.signals)
    for name, full in ref.items():
        want = ctx.selected.measured(full)
        got = getattr(ctx, name)
        assert np.array_equal(np.asarray(got), want)
        for _ in range(20):
            a, b = sorted(int(x) for x in rng.integers(0, n + 1, 2))
            assert np.array_equal(got[a:b], want[a:b])
        idx = np.sort(rng.choice(n, 300, replace=False))
        assert np.array_equal(got[idx], want[idx])
    assert ctx.position is not None
    assert np.array_equal(ctx.position[::1], np.asarray(ctx.position))


def test_residual_read_in_blocks_is_one_pass(tmp_path: Path,
                                            monkeypatch: pytest.MonkeyPatch) -> None:
    """The residual is not kept either: read in slices (forward, backward, across
    restarts) or at sorted rows, the regressor builder runs again from the block last
    computed or the segment's start; the values are those of one pass, bit for bit."""
    from canrls.diagnosis.record import RecordSamples
    from canrls.processor.replay import read_logs

    p = tmp_path / "gaps.log"
    assert main(["sim", "--out", str(p), "--duration", "6", "--seed", "9",
                 "--faults", "drop=0.02,silence=0.2s@2s"]) == 0
    cfg = load_config(None)
    cfg.model["kt"] = 0.1
    protocol, model, settings = prepare(cfg)
    log = read_logs([p], protocol, model, settings)
    monkeypatch.setattr(record, "BLOCK", 613)
    ctx = RecordSamples(log.model, log.signals, log.dt, settings, 8)
    eq = log.model.equations[0]
    theta = np.linspace(0.1, 0.4, eq.n)
    want = np.concatenate([eq.output_to_physical(y - phi @ theta)
                           for _, phi, y in ctx.measured_blocks(eq)])
    r = ctx.residual(eq, theta)
    assert np.array_equal(np.asarray(r), want)
    rng = np.random.default_rng(5)
    n = len(want)
    for _ in range(30):
        a, b = sorted(int(x) for x in rng.integers(0, n + 1, 2))
        assert np.array_equal(r[a:b], want[a:b])
    idx = np.sort(rng.choice(n, 400, replace=False))
    assert np.array_equal(r[idx], want[idx])


def test_filled_record_read_in_slices_is_the_whole_fill(tmp_path: Path) -> None:
    """The gap-filled record is not kept: any slice of it, filled again from the
    measured rows around it, equals filling the whole record in one block, bit for bit
    (gaps cut by the slice's ends, a silence, duplicates); the used and restart masks
    selected block by block are those of one block."""
    from canrls.estimation.selection import SamplePolicy, SampleSelector
    from canrls.processor.replay import read_logs

    p = tmp_path / "gaps.log"
    assert main(["sim", "--out", str(p), "--duration", "4", "--seed", "12",
                 "--faults", "drop=0.05,dup=0.005,silence=0.2s@2s"]) == 0
    cfg = load_config(None)
    cfg.model["kt"] = 0.1
    protocol, model, settings = prepare(cfg)
    log = read_logs([p], protocol, model, settings)
    policy = SamplePolicy.for_equation(log.model.equations[0], log.dt, settings)
    filler = policy.filler()
    whole, real = filler.fill(log.signals)
    assert real is not None
    # the rows in the filter's memory of a doubtful fill are not used either
    settling = filler.settling(whole, real)
    usable = real if settling is None else real & ~settling
    sel = SampleSelector(policy).select(whole.t, whole.speed)
    got = policy.apply(log.signals, block=777)
    assert got.real is not None and np.array_equal(got.real, real)
    assert np.array_equal(got.restart, sel.restart)
    assert np.array_equal(got.use, sel.use & usable)
    # kept packed, one bit a row
    for m in (got.real, got.restart, got.use):
        assert isinstance(m, PackedMask) and m.nbytes == -(-len(whole) // 8)
    assert got.segments() == [(int(a), int(b)) for a, b in zip(
        np.flatnonzero(sel.restart), [*np.flatnonzero(sel.restart)[1:], len(whole)],
        strict=True)]
    assert np.array_equal(got.measured(whole.speed), log.signals.speed)
    spread = got.filled(np.ones(len(log.signals), np.bool_))
    assert isinstance(spread, PackedMask) and np.array_equal(spread, real)
    filled = got.signals
    assert len(filled) == len(whole)
    rng = np.random.default_rng(7)
    cuts = [(0, len(whole)), (0, 1), (len(whole) - 1, len(whole))]
    cuts += [tuple(sorted(int(x) for x in rng.integers(0, len(whole) + 1, 2)))
             for _ in range(200)]
    for a, b in cuts:
        part = filled.slice(a, b)
        for r in ("t", "current", "speed", "position"):
            assert np.array_equal(getattr(part, r), getattr(whole, r)[a:b]), (r, a, b)


@pytest.mark.parametrize(("spill", "bound"), [(False, 50), (True, 1)],
                         ids=["memory", "spilled"])
def test_read_logs_keeps_the_samples_once(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                          spill: bool, bound: float) -> None:
    """``read_logs`` keeps the samples (five float64 a sample) and, while joining its
    blocks, one channel more: not the larger arrays the blocks' columns are views of,
    nor the samples twice (74 bytes per extra sample here before, 39 now). Spilled to
    a temporary file, nothing grows in memory (the write buffer is one chunk)."""
    monkeypatch.setattr(SpilledSignals, "ROWS", 4096)
    _one_thread(monkeypatch)
    from canrls.processor.replay import read_logs

    cfg = load_config(None)
    cfg.model["kt"] = 0.1
    protocol, model, settings = prepare(cfg)
    peaks = []
    for k, seconds in enumerate((10, 40)):
        p = tmp_path / f"drive{k}.log"
        assert main(["sim", "--out", str(p), "--duration", str(seconds), "--seed", "5"]) == 0
        read_logs([p], protocol, model, settings, chunk_size=4096)  # warm up
        gc.collect()
        tracemalloc.start()
        try:
            start, _ = tracemalloc.get_traced_memory()
            log = read_logs([p], protocol, model, settings, chunk_size=4096, spill=spill)
            _, peak = tracemalloc.get_traced_memory()
        finally:
            tracemalloc.stop()
        assert isinstance(log.signals, SpilledSignals) == spill
        peaks.append((len(log.signals), peak - start))
        log.close()
        del log
    (n1, p1), (n4, p4) = peaks
    growth = (p4 - p1) / (n4 - n1)
    print(f"read_logs: {growth:.1f} bytes per extra sample")
    assert growth < bound, f"{growth:.1f} bytes per extra sample"
