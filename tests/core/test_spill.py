"""The record of samples in a temporary file (:class:`canrls.core.spill.SpilledSignals`) and
the masks at one bit a row (:class:`canrls.core.spill.PackedMask`): read back bit for bit,
the diagnosis on them the same, and the fallback to memory when the temporary directory
cannot take the file."""

from __future__ import annotations

import errno
import json
import logging
import os
import tempfile
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from canrls.cli.main import main
from canrls.core import spill as spill_mod
from canrls.core.samples import Signals
from canrls.core.spill import MaskPacker, PackedMask, SpilledSignals
from canrls.diagnosis.analysis import diagnose, diagnose_log
from canrls.estimation.model import Model
from canrls.processor import scan_ranges
from canrls.processor.config import DEFAULT_HELD, load_config, prepare
from canrls.processor.replay import read_logs
from canrls.sim.scenario import scenario, simulate


def _blocks(rng: np.random.Generator, sizes: list[int], position: bool = True,
            voltage: bool = False) -> list[Signals]:
    def col(n: int) -> np.ndarray:
        return rng.normal(size=n)

    return [Signals(col(n), col(n), col(n), col(n) if position else None,
                    col(n) if voltage else None) for n in sizes]


def _json(rep: Any) -> str:
    return json.dumps(rep.to_dict(), sort_keys=True, default=str)


@pytest.mark.parametrize("voltage", [False, True])
def test_spilled_record_reads_back_bit_for_bit(monkeypatch: pytest.MonkeyPatch,
                                               tmp_path: Path, voltage: bool) -> None:
    """Slices, sorted rows and single rows, across the file's chunks and the chunk
    still in the write buffer, are the rows appended; the file has no name in its
    directory and is gone once closed."""
    monkeypatch.setattr(SpilledSignals, "ROWS", 1000)
    rng = np.random.default_rng(1)
    blocks = _blocks(rng, [5, 999, 1, 2500, 0, 3000, 7], voltage=voltage)
    whole = Signals.concat(blocks)
    rec = SpilledSignals.from_blocks(blocks, dir=str(tmp_path))
    assert os.listdir(tmp_path) == []  # anonymous: unlinked at once
    n = len(whole)
    assert len(rec) == n and rec.has("position") and rec.has("voltage") == voltage
    assert (rec.voltage is None) != voltage
    roles = ["t", "current", "speed", "position"] + (["voltage"] if voltage else [])
    cuts = [(0, n), (0, 0), (n, n), (999, 1001), (6000, n), (n - 1, n + 5)]
    cuts += [tuple(sorted(int(x) for x in rng.integers(0, n + 1, 2))) for _ in range(200)]
    for a, b in cuts:
        part = rec.slice(a, b)
        for r in roles:
            want = getattr(whole, r)[a:b]
            assert np.array_equal(getattr(part, r), want), (r, a, b)
            assert np.array_equal(getattr(rec, r)[a:b], want), (r, a, b)
    for _ in range(20):
        idx = np.sort(rng.choice(n, 60, replace=False))
        for r in roles:
            assert np.array_equal(getattr(rec, r)[idx], getattr(whole, r)[idx])
    assert rec.t[0] == whole.t[0] and rec.t[-1] == whole.t[-1]
    assert rec.speed[4321] == whole.speed[4321]
    with pytest.raises(IndexError):
        rec.t[n]
    assert np.array_equal(np.asarray(rec.current), whole.current)
    # file: whole chunks of 8 bytes per row and channel
    assert rec.nbytes == -(-n // 1000) * 1000 * 8 * len(roles)
    rec.close()
    with pytest.raises(ValueError):
        rec.slice(0, 10)


def test_a_channel_one_block_lacks_is_absent_as_concat_has_it() -> None:
    rng = np.random.default_rng(2)
    blocks = _blocks(rng, [10, 20]) + _blocks(rng, [5], position=False)
    with SpilledSignals.from_blocks(blocks) as rec:
        assert rec.position is None and not rec.has("position")
        got = rec.slice(0, len(rec))
        want = Signals.concat(blocks)
        assert want.position is None and got.position is None
        assert np.array_equal(got.t, want.t) and np.array_equal(got.speed, want.speed)


def test_packed_mask_reads_like_the_mask() -> None:
    rng = np.random.default_rng(3)
    for n in (0, 1, 7, 8, 9, 100, 1001):
        m = rng.random(n) < 0.3
        cuts = sorted(int(x) for x in rng.integers(0, n + 1, 4))
        for pm in (PackedMask.pack(m), PackedMask.from_blocks(np.split(m, cuts))):
            assert len(pm) == n and np.array_equal(np.asarray(pm), m)
            assert pm.nbytes == -(-n // 8) and pm.any() == bool(m.any())
            for _ in range(100):
                a, b = sorted(int(x) for x in rng.integers(0, n + 1, 2))
                assert np.array_equal(pm[a:b], m[a:b]), (n, a, b)
                assert pm.count(a, b) == int(m[a:b].sum())
            assert [pm[k] for k in range(n)] == list(m)
            assert pm.count() == int(m.sum())


def test_packed_mask_in_a_temporary_file_reads_like_the_mask(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """Past MaskPacker.MEMORY bytes the bits go to a temporary file: read back in
    slices, at sorted rows, counted, intersected and hashed as the mask in memory,
    with only a page of it in memory."""
    monkeypatch.setattr(MaskPacker, "MEMORY", 64)
    monkeypatch.setattr(PackedMask, "CHUNK", 100)  # many chunks of bits per pass
    rng = np.random.default_rng(4)
    for n in (1000, 4099, 20001):
        m = rng.random(n) < 0.4
        other = rng.random(n) < 0.5
        cuts = sorted(int(x) for x in rng.integers(0, n + 1, 6))
        pm = PackedMask.from_blocks(np.split(m, cuts))
        mem = PackedMask.pack(m)
        assert pm.spilled and not mem.spilled and pm.nbytes <= 4096
        assert len(pm) == n and np.array_equal(np.asarray(pm), m)
        assert pm.any() and pm.count() == pm.sum() == int(m.sum())
        for _ in range(50):
            a, b = sorted(int(x) for x in rng.integers(0, n + 1, 2))
            assert np.array_equal(pm[a:b], m[a:b]) and pm.count(a, b) == int(m[a:b].sum())
        assert [pm[k] for k in range(0, n, 7)] == list(m[::7])
        idx = np.sort(rng.choice(n, 300, replace=False))
        assert np.array_equal(pm[idx], m[idx])
        both = pm.intersect(other)
        assert both.spilled and np.array_equal(np.asarray(both), m & other)
        assert np.array_equal(np.asarray(pm.intersect(PackedMask.pack(other))), m & other)
        assert pm.digest() == mem.digest() != both.digest()
        assert not PackedMask.from_blocks([np.zeros(n, np.bool_)]).any()
    pk = MaskPacker()
    pk.append(m)
    pk.mask()
    with pytest.raises(ValueError, match="taken with its file"):
        pk.append(m)


def test_a_mask_file_that_cannot_be_written_keeps_the_mask_in_memory(
        monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture) -> None:
    """The temporary directory fills up while a mask is written: one warning line, the
    bytes written so far read back, the mask whole in memory (and later masks too,
    without another warning)."""
    monkeypatch.setattr(MaskPacker, "MEMORY", 16)
    monkeypatch.setattr(spill_mod, "_mask_warned", False)
    writes = []
    pwrite = os.pwrite

    def full(fd: int, data: Any, offset: int) -> int:
        if len(writes) >= 3:
            raise OSError(errno.ENOSPC, "No space left on device")
        writes.append(offset)
        return pwrite(fd, data, offset)

    monkeypatch.setattr(spill_mod.os, "pwrite", full)
    rng = np.random.default_rng(5)
    m = rng.random(5000) < 0.3
    with caplog.at_level(logging.WARNING, logger="canrls.core.samples"):
        pms = [PackedMask.from_blocks(np.array_split(m, 40)) for _ in range(2)]
    assert len(writes) == 3
    warnings = [r for r in caplog.records if r.levelno == logging.WARNING]
    assert len(warnings) == 1 and "No space left" in warnings[0].getMessage()
    assert "\n" not in warnings[0].getMessage()
    for pm in pms:
        assert not pm.spilled and np.array_equal(np.asarray(pm), m)


@pytest.fixture
def drive_log(tmp_path: Path) -> Path:
    p = tmp_path / "drive.log"
    assert main(["sim", "--out", str(p), "--duration", "20", "--seed", "6",
                 "--effects", "inertia,viscous,coulomb,offset,unbalance",
                 "--faults", "drop=0.01,dup=0.005,silence=0.3s@5s"]) == 0
    return p


def test_diagnose_log_on_spilled_samples_is_the_in_memory_report(
        drive_log: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """``diagnose_log`` keeps the samples in a temporary file (lost and duplicated frames,
    a silence, position): its report is the one of the samples in memory, bit for bit,
    with ``--add`` (the refit reads the record again)."""
    cfg = load_config(None)
    cfg.model["kt"] = 0.1
    protocol, model, settings = prepare(cfg)
    log = read_logs([drive_log], protocol, model, settings)
    assert isinstance(log.signals, Signals)
    want = diagnose(log.signals, log.model, settings, dt=log.dt, add=["offset"],
                    max_order=16, source=str(drive_log), frames=log.frames,
                    period=log.period, start=log.start)
    made: list[SpilledSignals] = []
    init = SpilledSignals.__init__

    def spy(self: SpilledSignals, *a: Any, **k: Any) -> None:
        init(self, *a, **k)
        made.append(self)

    monkeypatch.setattr(SpilledSignals, "__init__", spy)
    monkeypatch.setattr(SpilledSignals, "ROWS", 5000)  # several chunks
    got = diagnose_log(drive_log, protocol, model, settings, add=["offset"], max_order=16)
    assert len(made) == 1 and len(made[0]) == len(log.signals)
    assert made[0]._file.closed  # freed on return
    assert _json(got) == _json(want)


@pytest.mark.parametrize("axis", ["rotary", "linear"])
def test_diagnose_on_spilled_samples_is_the_in_memory_report(axis: str) -> None:
    """Simulated drives, rotary and linear, rows dropped (gaps filled): the same report
    from a :class:`SpilledSignals` as from the arrays."""
    res = simulate(scenario("standard" if axis == "rotary" else "linear",
                            effects="inertia,viscous,coulomb,unbalance", seed=3,
                            duration=15))
    m = res.measured
    rng = np.random.default_rng(4)
    keep = rng.random(len(m)) > 0.01
    cols = {r: (None if getattr(m, r) is None else np.asarray(getattr(m, r))[keep])
            for r in ("t", "current", "speed", "position", "voltage")}
    sig = Signals(**cols)  # type: ignore[arg-type]
    tr = res.truth
    kw: dict[str, Any] = {}
    if tr.axis == "linear":
        kw = {"coulomb_band": tr.coulomb_band, "stribeck_speed": tr.stribeck_speed}
    ranges = scan_ranges([sig], res.scenario.dt, 25.0, 0.7071)
    model = Model(["inertia", "viscous", "coulomb"], kt=tr.kt, axis=tr.axis, pitch=tr.pitch,
                  held=DEFAULT_HELD, ranges=ranges, **kw)
    want = diagnose(sig, model, dt=res.scenario.dt, add=["unbalance"], max_order=8)
    blocks = [sig.slice(a, a + 3000) for a in range(0, len(sig), 3000)]
    with SpilledSignals.from_blocks(blocks) as rec:
        got = diagnose(rec, model, dt=res.scenario.dt, add=["unbalance"], max_order=8)
    assert got.to_dict()["axis"] == axis
    assert _json(got) == _json(want)


def test_no_temporary_file_keeps_the_samples_in_memory(
        drive_log: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
        caplog: pytest.LogCaptureFixture) -> None:
    """A temporary directory that cannot take the file (here a stand-in regular file in
    its place): one warning line naming it, the samples in memory, the same report."""
    cfg = load_config(None)
    cfg.model["kt"] = 0.1
    protocol, model, settings = prepare(cfg)
    want = _json(diagnose_log(drive_log, protocol, model, settings, max_order=8))
    stand_in = tmp_path / "not-a-directory"
    stand_in.write_text("")
    monkeypatch.setattr(tempfile, "tempdir", str(stand_in))
    with caplog.at_level(logging.WARNING, logger="canrls.processor.replay"):
        log = read_logs([drive_log], protocol, model, settings, spill=True)
        assert isinstance(log.signals, Signals)
        got = _json(diagnose_log(drive_log, protocol, model, settings, max_order=8))
    warnings = [r for r in caplog.records if r.levelno == logging.WARNING]
    assert len(warnings) == 2  # one per read
    msg = warnings[0].getMessage()
    assert "\n" not in msg and str(stand_in) in msg and "kept in memory" in msg
    assert got == want


def test_a_write_that_fails_keeps_every_sample_in_memory(
        drive_log: Path, monkeypatch: pytest.MonkeyPatch,
        caplog: pytest.LogCaptureFixture) -> None:
    """The temporary directory fills up while the log is read: one warning line, the
    rows written so far read back, none lost (the samples of the in-memory read)."""
    cfg = load_config(None)
    cfg.model["kt"] = 0.1
    protocol, model, settings = prepare(cfg)
    want = read_logs([drive_log], protocol, model, settings)
    monkeypatch.setattr(SpilledSignals, "ROWS", 3000)
    writes = []
    pwrite = os.pwrite

    def full(fd: int, data: Any, offset: int) -> int:
        if len(writes) >= 2:
            raise OSError(errno.ENOSPC, "No space left on device")
        writes.append(offset)
        return pwrite(fd, data, offset)

    monkeypatch.setattr(spill_mod.os, "pwrite", full)
    with caplog.at_level(logging.WARNING, logger="canrls.processor.replay"):
        got = read_logs([drive_log], protocol, model, settings, chunk_size=2000, spill=True)
    assert len(writes) == 2
    warnings = [r for r in caplog.records if r.levelno == logging.WARNING]
    assert len(warnings) == 1 and "No space left" in warnings[0].getMessage()
    assert isinstance(got.signals, Signals)
    for r in ("t", "current", "speed", "position"):
        assert np.array_equal(getattr(got.signals, r), getattr(want.signals, r)), r
