"""The target's C as an extension (``canrls._target``) against the Python specification.

:class:`canrls.firmware.native.TargetFeed` runs the C of ``canrls export-c`` on a model
given as data; the same loop with ``native=False`` runs the specification
(:class:`canrls.firmware.spec.TargetEstimator`). Both take a log's frames in blocks cut
at random places (seeded), and after every block their integer states (the test
vectors' record: filters, theta, P and their fractions, exponents, counters, shifts) are
the same word for word, as are every publication's frames and the final estimate: on
the simulated drive in canrls' DBC, through dropped, corrupted, duplicated and reordered
frames with both equations, on a user's Motorola DBC through rescales, on a CiA 402
drive, on an ODrive-style drive of float32 signals with NaN and infinities, and on an
HSM150 run in its own DBC (read from the shared data, where it is).
"""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from test_target_c import CIA_MAP, DRIVES, ODRIVE_MAP, _cia402, _motorola, _odrive, _quiet

from canrls.can.frameblock import FrameBlock
from canrls.can.logs import read_frames
from canrls.firmware.load import load, target_model
from canrls.firmware.native import NativeTarget, TargetFeed, pack
from canrls.firmware.target_model import TargetError, TargetModel
from canrls.firmware.vectors import block_frames, block_ticks, log_frames, record

ROOT = Path(__file__).resolve().parents[2]
HSM = ROOT.parent / "shared" / "data" / "hsm150"


def _model(d: Path, log: Path, fit_args: list[str]) -> TargetModel:
    saved = d / "m.json"
    _quiet(["fit", str(log), *fit_args, "--save-model", str(saved), "--quiet", "--json"])
    return target_model(load(saved))


def _blocks(log: Path, seed: int) -> list[FrameBlock]:
    """The log's frames in blocks of 1 to 600 frames, cut at random places."""
    frames = FrameBlock.concat(list(read_frames(log)))
    rng = np.random.default_rng(seed)
    cuts = np.cumsum(rng.integers(1, 600, size=len(frames)))
    cuts = cuts[cuts < len(frames)]
    edges = [0, *cuts.tolist(), len(frames)]
    return [frames.take(slice(a, b)) for a, b in zip(edges, edges[1:], strict=False)]


def _agree(tm: TargetModel, log: Path, seed: int = 0) -> TargetFeed:
    """The C and the specification over the log's blocks: the same state after every
    block, the same publications, the same estimate."""
    c, spec = TargetFeed(tm), TargetFeed(tm, native=False)
    for k, b in enumerate(_blocks(log, seed)):
        c.feed(b)
        spec.feed(b)
        assert c.state_record() == spec.state_record(), f"block {k}"
    assert c.theta_si() == spec.theta_si()
    assert c.run_info() == spec.run_info()
    assert c.saturations() == spec.saturations()
    # every publication, frame for frame, as the vectors of export-c hold them
    v = record(tm, log_frames([log]))
    est = NativeTarget(tm)
    pubs: list[Any] = []
    t0: list[float] = []
    for b in read_frames(log):
        est.run(block_ticks(b, t0, tm.tick_s), b, pubs)
    assert [frames for _, frames in pubs] == [frames for _, frames in v.publications]
    assert est.state_record() == v.checkpoints[-1][1]
    return c


@pytest.mark.parametrize("name", ["own", "faults", "no-frames"])
def test_the_c_agrees_with_the_specification_on_simulated_drives(tmp_path: Path,
                                                                  name: str) -> None:
    make, fit_args, _ = DRIVES[name]
    log = make(tmp_path)
    feed = _agree(_model(tmp_path, log, fit_args), log, seed=len(name))
    assert feed.run_info().samples > 4000
    if name == "faults":
        # both equations, and frames rejected or dropped on the way
        assert len(feed.run_info().updates) == 2 and feed.run_info().rejected


def test_the_c_agrees_through_rescales_in_a_users_motorola_dbc(tmp_path: Path) -> None:
    log, mapping = _motorola(tmp_path)
    tm = _model(tmp_path, log, [*mapping, "--kt", "0.1", "-e", "inertia,viscous,coulomb"])
    feed = _agree(tm, log, seed=3)
    assert feed.run_info().rescales["mechanical"] >= 1


def test_the_c_agrees_on_a_cia402_drive(tmp_path: Path) -> None:
    log = _cia402(tmp_path)
    _agree(_model(tmp_path, log, [*CIA_MAP, "-e", "inertia,viscous,coulomb,unbalance"]), log,
           seed=4)


def test_the_c_agrees_on_float32_signals_with_nan_and_infinities(tmp_path: Path) -> None:
    log = _odrive(tmp_path)
    tm = _model(tmp_path, log, [*ODRIVE_MAP, "--kt", "0.1", "-e",
                                "inertia,viscous,coulomb,unbalance"])
    assert any(f.is_float for f in tm.roles.values())
    feed = _agree(tm, log, seed=5)
    assert feed.run_info().rejected["range"] > 0


@pytest.mark.skipif(not HSM.is_dir(), reason=f"HSM150 data not found at {HSM} (real "
                    "measurements kept outside the project; see docs/hsm150.md)")
def test_the_c_agrees_on_an_hsm150_run_in_its_own_dbc(tmp_path: Path) -> None:
    pytest.importorskip("scipy.io", reason="scipy (test extra) reads the .mat runs")
    sys.path.insert(0, str(ROOT / "tools"))
    import hsm150_to_can as tool

    log = tool.convert(HSM / "idf_pos_0.06_1.mat", tmp_path)
    mapping = ["--dbc", str(ROOT / "tests" / "data" / "hsm150_drive.dbc"),
               *[a for s in tool.SIGNALS for a in ("--signal", s)], "--kt", str(tool.KT)]
    tm = _model(tmp_path, log, [*mapping, "-e", "inertia,viscous,coulomb,offset"])
    feed = _agree(tm, log, seed=6)
    assert feed.run_info().samples > 1000


def test_a_frozen_kernel_keeps_its_estimate_in_the_c_and_the_specification(
        tmp_path: Path) -> None:
    make, fit_args, _ = DRIVES["own"]
    log = make(tmp_path)
    tm = _model(tmp_path, log, fit_args)
    blocks = _blocks(log, 7)
    c, spec = TargetFeed(tm), TargetFeed(tm, native=False)
    third = len(blocks) // 3
    for k, b in enumerate(blocks):
        if k in (third, 2 * third):  # frozen for the middle third, then running again
            for f in (c, spec):
                f.freeze(k == third)
            held = c.theta_si()
        c.feed(b)
        spec.feed(b)
        assert c.state_record() == spec.state_record(), f"block {k}"
        if third <= k < 2 * third:
            assert c.theta_si() == held
    assert c.theta_si() != held


def test_error_and_remote_frames_never_reach_the_target(tmp_path: Path) -> None:
    make, fit_args, _ = DRIVES["own"]
    log = make(tmp_path)
    tm = _model(tmp_path, log, fit_args)
    frames = FrameBlock.concat(list(read_frames(log)))
    # every tenth frame marked an error frame, every seventh a remote frame
    marked = frames.take(slice(None))
    marked.is_error[::10] = True
    marked.is_remote[::7] = True
    c, spec = TargetFeed(tm), TargetFeed(tm, native=False)
    c.feed(marked)
    spec.feed(marked)
    assert c.state_record() == spec.state_record()
    # ... and the frames the specification sees are those of block_frames
    t0: list[float] = []
    seen = list(block_frames(marked, t0, tm.tick_s))
    assert len(seen) == int(np.count_nonzero(~(marked.is_error | marked.is_remote)))


def test_a_vector_beyond_the_c_s_bounds_is_refused_by_name(tmp_path: Path) -> None:
    from canrls import _target

    make, fit_args, _ = DRIVES["own"]
    log = make(tmp_path)
    tm = _model(tmp_path, log, fit_args)
    v = pack(tm)
    _target.Target(v)  # as packed: taken
    bad = v.copy()
    bad[0] = 9  # nmsg beyond CANRLS_TARGET_MSG_MAX
    with pytest.raises(ValueError, match=r"model\.nmsg = 9 outside 1\.\.4"):
        _target.Target(bad)
    with pytest.raises(ValueError, match="the vector ends before"):
        _target.Target(v[:-1])
    with pytest.raises(ValueError, match="values beyond the model's end"):
        _target.Target(np.append(v, 0))
    # an object never given a model runs nothing
    with pytest.raises(ValueError, match="no model"):
        _target.Target.__new__(_target.Target).record()


def test_a_model_the_c_cannot_hold_is_a_target_error(tmp_path: Path,
                                                     monkeypatch: pytest.MonkeyPatch) -> None:
    import canrls.firmware.native as native

    make, fit_args, _ = DRIVES["own"]
    log = make(tmp_path)
    tm = _model(tmp_path, log, fit_args)

    def five_messages(model: TargetModel) -> np.ndarray:
        v = pack(model)
        v[0] = 5
        return v

    monkeypatch.setattr(native, "pack", five_messages)
    with pytest.raises(TargetError, match="the target's C does not take this model"):
        NativeTarget(tm)


def test_fit_json_says_the_path_of_its_fixed_column(tmp_path: Path) -> None:
    make, fit_args, _ = DRIVES["no-frames"]
    log = make(tmp_path)
    fit = json.loads(_quiet(["fit", str(log), *fit_args, "--json", "--quiet"]))
    assert fit["fixed"]["path"] == "target"
    kernel = json.loads(_quiet(["fit", str(log), *fit_args, "--json", "--quiet", "--fixed",
                                "kernel"]))
    assert "fixed" not in kernel
