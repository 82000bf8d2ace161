"""A restored target state is checked before the C runs on it (canrls_target_check.c).

``canrls._target.Target.set_state`` takes a checkpoint's bytes only where
``canrls_target_check_state`` finds every field where the estimator can bring it: every
state a run reaches is taken (and continues bit for bit), each field set outside its
invariant is refused with its name, and a few thousand states with random bytes flipped
(seeded) are each refused or run a block of frames under AddressSanitizer and
UndefinedBehaviorSanitizer (src/canrls/c/firmware/drivers/state_driver.c on the C of
``canrls export-c``).
"""

from __future__ import annotations

import re
import shutil
import struct
import subprocess
from pathlib import Path
from typing import Any

import pytest
from test_target_c import DRIVES, _motorola, _quiet
from test_target_native import _blocks, _model

from canrls.can.logs import read_frames
from canrls.firmware.native import NativeTarget
from canrls.firmware.target_model import TargetError, TargetModel
from canrls.firmware.vectors import block_ticks

ROOT = Path(__file__).resolve().parents[2]
KERNEL = ROOT / "src" / "canrls" / "c" / "firmware"
DRIVER = KERNEL / "drivers" / "state_driver.c"


_CACHE: dict[str, tuple[Path, Path, TargetModel]] = {}


def _drive(name: str, tmp: pytest.TempPathFactory) -> tuple[Path, Path, TargetModel]:
    """A drive of test_target_c (its log, saved model and target model), made once."""
    if name not in _CACHE:
        d = tmp.mktemp(name)
        make, fit_args, _ = DRIVES[name]
        log = make(d)
        if fit_args is None:
            fit_args = [*_motorola(d, noise=name != "pending")[1], "--kt", "0.1",
                        "-e", "inertia,viscous,coulomb"]
        saved = d / "m.json"
        _quiet(["fit", str(log), *fit_args, "--save-model", str(saved), "--quiet", "--json"])
        _CACHE[name] = (log, saved, _model(d, log, fit_args))
    return _CACHE[name]


@pytest.fixture(scope="module")
def faults(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path, TargetModel]:
    """Both equations, Stribeck and cogging at lambda < 1, through faulty frames."""
    return _drive("faults", tmp_path_factory)


def _states(tm: TargetModel, log: Path, seed: int) -> tuple[NativeTarget, list[bytes]]:
    """The C over the log's blocks, its state after each."""
    est, t0, out = NativeTarget(tm), [], []
    for b in _blocks(log, seed):
        est.run(block_ticks(b, t0, tm.tick_s), b)
        out.append(est.state())
    return est, out


@pytest.mark.parametrize("name", ["faults", "motorola", "pending"])
def test_every_state_of_a_run_is_taken(tmp_path_factory: pytest.TempPathFactory,
                                       name: str) -> None:
    """Through rescales, pending columns' first values, windup and restarts."""
    log, _, tm = _drive(name, tmp_path_factory)
    _, states = _states(tm, log, 1)
    for s in states:
        NativeTarget(tm).set_state(s)  # refused: TargetError
    assert len(states) > 20
    # the middle state restored goes on bit for bit
    blocks, half = _blocks(log, 1), len(states) // 2
    est, t0 = NativeTarget(tm), []
    for b in blocks[:half + 1]:
        block_ticks(b, t0, tm.tick_s)  # the stream's first time, as the checkpoint keeps it
    est.set_state(states[half])
    for b in blocks[half + 1:]:
        est.run(block_ticks(b, t0, tm.tick_s), b)
    assert est.state() == states[-1]
    if name != "faults":
        assert est.counts()[3][0] >= 1  # rescales


def _gcc() -> str:
    gcc = shutil.which("gcc")
    if gcc is None:
        pytest.skip("gcc not installed")
    return gcc


_DRIVERS: dict[str, tuple[Path, Path, int]] = {}


def _driver(name: str, tmp: pytest.TempPathFactory) -> tuple[Path, Path, int]:
    """The state driver on the exported C of a drive, under AddressSanitizer and
    UndefinedBehaviorSanitizer; its frames file and the frame after which it saves."""
    if name in _DRIVERS:
        return _DRIVERS[name]
    log, saved, tm = _drive(name, tmp)
    d = tmp.mktemp("driver")
    out = d / "c"
    _quiet(["export-c", "--model", str(saved), "--out", str(out)])
    rec = bytearray()
    t0: list[float] = []
    for b in read_frames(log):
        ticks = block_ticks(b, t0, tm.tick_s)
        for k in range(len(b)):
            if b.is_error[k] or b.is_remote[k]:
                continue
            data = bytes(b.data[k][: b.dlc[k]]).ljust(8, b"\0")
            rec += struct.pack("<IIBB8s2x", int(ticks[k]), int(b.arbitration_id[k]),
                               int(b.is_extended[k]), int(b.dlc[k]), data)
    frames = d / "frames.bin"
    frames.write_bytes(bytes(rec))
    exe = d / "state_driver"
    subprocess.run([_gcc(), "-std=c99", "-O1", "-g", "-Wall", "-Wextra", "-Werror",
                    "-fsanitize=address,undefined", "-fno-sanitize-recover=all", "-I", str(out),
                    str(DRIVER), *(str(out / f) for f in ("canrls_model.c", "canrls_target.c",
                                                          "canrls_fixed.c",
                                                          "canrls_target_check.c")),
                    "-o", str(exe)], check=True)
    _DRIVERS[name] = (exe, frames, len(rec) // 20 // 2)
    return _DRIVERS[name]


@pytest.fixture(scope="module")
def driver(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path, int]:
    """The state driver of the faults drive."""
    return _driver("faults", tmp_path_factory)


def test_the_drivers_state_is_the_extensions(driver: Any, faults: Any, tmp_path: Path) -> None:
    """The exported C's state after half the frames is taken by canrls._target and goes on
    as the extension's (the driver checks that it continues bit for bit in C)."""
    exe, frames, k = driver
    subprocess.run([str(exe), str(frames), str(k), "save", str(tmp_path / "s")], check=True)
    NativeTarget(faults[2]).set_state((tmp_path / "s").read_bytes())


#: each field set outside its invariant (state_driver.c, spoil) and the name the check gives
SPOILED = {
    "last_counter": "last_counter", "open_mask": "open_mask/open_counter",
    "open_counter": "open_mask/open_counter", "raw": "raw", "has_t": "a flag",
    "frame_loss": "a flag", "primed": "a filter's state", "since_publish": "since_publish",
    "x1": "a filter's state", "x2": "a filter's state", "uph": "a filter's state",
    "upl": "a filter's state", "plan.e_max": "an equation's plan",
    "plan.phi_ps": "an equation's plan", "plan.trace_max_lam": "an equation's plan",
    "rls.frozen": "an equation's kernel", "rls.e": "an equation's kernel",
    "rls.e.negative": "an equation's kernel", "rls.c.half": "an equation's kernel",
    "rls.c.above": "an equation's kernel", "rls.theta": "an equation's kernel",
    "rls.P": "an equation's kernel", "rls.trw": "an equation's kernel",
    "rls.wu_lo": "an equation's kernel", "rls.wide": "an equation's kernel",
    "rls.theta.unused": "an equation's kernel", "sh": "a shift or exponent",
    "sh.low": "a shift or exponent", "exponents": "a shift or exponent",
    "sh_y": "a shift or exponent", "exponents.y": "a shift or exponent",
    "pending": "a flag", "ridge.m": "a ridge or trace term", "ridge.e": "a ridge or trace term",
    "terms": "a ridge or trace term", "left": "left or w_last",
    "left.negative": "left or w_last", "w_last": "left or w_last", "flags": "ms or flags",
    "ms": "ms or flags", "last_counter.unused": "beyond the model",
    "x1.unused": "beyond the model", "sh.unused": "beyond the model",
    "x1.narrow": "a filter's state",
}
#: fields a restore sets itself (the pointers) or checks first (n): the driver's check only
C_ONLY = {"model": "model", "rls.plan": "an equation's kernel", "rls.n": "an equation's kernel"}


@pytest.mark.parametrize("field", sorted(SPOILED) + sorted(C_ONLY))
def test_a_field_outside_its_invariant_is_refused_by_name(driver: Any, faults: Any,
                                                          tmp_path: Path, field: str) -> None:
    exe, frames, k = driver
    r = subprocess.run([str(exe), str(frames), str(k), "bad", field, str(tmp_path / "s")],
                       capture_output=True, text=True, check=True)
    name = SPOILED.get(field) or C_ONLY[field]
    assert name in r.stdout, r.stdout
    if field in SPOILED:
        with pytest.raises(TargetError, match=re.escape(name)):
            NativeTarget(faults[2]).set_state((tmp_path / "s").read_bytes())


@pytest.mark.parametrize("name", ["faults", "motorola"])
def test_random_bytes_flipped_are_refused_or_run_without_undefined_behaviour(
        tmp_path_factory: pytest.TempPathFactory, name: str) -> None:
    """4000 copies of a state with 1..8 random bytes flipped (seeded): each refused by the
    check or run over 2000 frames, under the sanitizers (any finding stops the driver
    with a nonzero status). Both equations through faulty frames; a Motorola DBC through
    rescales."""
    exe, frames, k = _driver(name, tmp_path_factory)
    r = subprocess.run([str(exe), str(frames), str(k), "fuzz", "4000", "7"],
                       capture_output=True, text=True)
    assert r.returncode == 0, r.stderr[-3000:]
    accepted, refused = map(int, r.stdout.split())
    assert accepted + refused == 4000 and refused > 0 and accepted > 0
