"""Faults at the checkpoint path: links, FIFOs, directories, devices, huge or forged files,
NaN states, links at the temporary, stale temporaries, file modes, kill -9 in a write.

Every fault lives in the test's own ``tmp_path``: the FIFOs, links, sparse files and
device stand-ins are made there, and nothing points the code at a system path.
"""

from __future__ import annotations

import copy
import errno
import hashlib
import io
import json
import logging
import os
import secrets
import signal
import socket
import stat
import subprocess
import sys
import textwrap
import zipfile
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from blocking import in_thread, unblock_fifo
from daemon_tool import reap
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from canrls.cli.main import main
from canrls.core.errors import CheckpointError
from canrls.estimation.model import Model
from canrls.live.checkpoint import (
    FORMAT,
    MAGIC,
    MAX_BYTES,
    Checkpoint,
    Checkpointer,
    CheckpointPathError,
    fingerprint,
    load_checkpoint,
    save_checkpoint,
)
from canrls.live.daemon import Daemon
from canrls.live.daemon_settings import DaemonSettings
from canrls.processor import FrameProcessor, SampleProcessor
from canrls.processor.config import AppConfig
from canrls.sim import scenario
from canrls.sim.scenario import Simulator

ROOT = Path(__file__).resolve().parents[2]
EFFECTS = ["inertia", "viscous", "coulomb"]
PRECIOUS = b"precious: must never change\n"


# ------------------------------------------------------------------ helpers
def _setup(dbc: Path | None = None) -> tuple[Any, Model, Any]:
    cfg = AppConfig(can={"dbc": str(dbc)} if dbc is not None else {})
    cfg.model = {"effects": list(EFFECTS), "kt": 0.1}
    protocol = cfg.protocol()
    return protocol, cfg.model_for(protocol), cfg.settings()


def _frames(seconds: float, seed: int = 1) -> list:
    sc = scenario("standard", seed=seed, duration=seconds, excitation="slow")
    return list(Simulator(sc, t0=0.0).frames(500))


@pytest.fixture(scope="module")
def running() -> tuple[Any, Model, Any, FrameProcessor]:
    """A processor that has calibrated and estimated for a while (its state is real)."""
    protocol, model, settings = _setup()
    proc = FrameProcessor(protocol, model, settings)
    for b in _frames(2.5):
        proc.process(b)
    assert proc.pipeline.samples > 0
    return protocol, model, settings, proc


def _checkpoint(running: tuple, state: dict[str, Any] | None = None) -> Checkpoint:
    _, model, settings, proc = running
    return Checkpoint(model=json.loads(json.dumps(proc.model.to_dict())),
                      config_model=json.loads(json.dumps(model.to_dict())),
                      fingerprint=fingerprint(settings, proc.period),
                      state=proc.state() if state is None else state,
                      counters={"frames": 7}, saved_at=123.5)


def _checkpointer(running: tuple, path: Path, **kw: Any) -> Checkpointer:
    _, model, settings, proc = running
    return Checkpointer(path, model, settings, proc.period, 60.0, **kw)


def _restore(running: tuple) -> Callable[[Model, dict[str, Any]], FrameProcessor]:
    protocol, _, settings, _ = running

    def restore(model: Model, state: dict[str, Any]) -> FrameProcessor:
        p = FrameProcessor(protocol, model, settings)
        p.restore(state, model)
        return p
    return restore


def _daemon(running: tuple, path: Path) -> Daemon:
    protocol, model, settings, _ = running
    return Daemon(protocol, model, settings, DaemonSettings(checkpoint=path),
                  bus={"interface": "virtual", "channel": "unused-fault-ckpt"})


def _outside(tmp_path: Path) -> Path:
    """A file outside the checkpoint's directory that a link points to."""
    d = tmp_path / "outside"
    d.mkdir()
    f = d / "precious.txt"
    f.write_bytes(PRECIOUS)
    return f


def _forge(doc: Any, arrays: dict[str, np.ndarray] | None = None, *,
           meta: bytes | None = None) -> bytes:
    """A file in the documented format with a valid checksum around ``doc``."""
    text = meta if meta is not None else json.dumps(doc, allow_nan=True).encode()
    buf = io.BytesIO()
    np.savez(buf, __meta__=np.frombuffer(text, np.uint8), **(arrays or {}))
    return _envelope(buf.getvalue())


def _envelope(payload: bytes) -> bytes:
    header = json.dumps({"format": FORMAT, "canrls": "0.1.0", "size": len(payload),
                         "sha256": hashlib.sha256(payload).hexdigest()}, sort_keys=True)
    return MAGIC + header.encode() + b"\n" + payload


def _flat(obj: Any, arrays: dict[str, np.ndarray]) -> Any:
    if isinstance(obj, np.ndarray):
        key = f"a{len(arrays)}"
        arrays[key] = obj
        return {"__array__": key}
    if isinstance(obj, dict):
        return {k: _flat(v, arrays) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [_flat(v, arrays) for v in obj]
    return obj


def _forge_checkpoint(cp: Checkpoint) -> bytes:
    """``cp`` in the documented format, written without any of the writer's checks."""
    arrays: dict[str, np.ndarray] = {}
    doc = _flat({"model": cp.model, "config_model": cp.config_model,
                 "fingerprint": cp.fingerprint, "state": cp.state, "counters": cp.counters,
                 "saved_at": cp.saved_at, "version": cp.version}, arrays)
    return _forge(doc, arrays)


@pytest.fixture
def umask022() -> Iterator[None]:
    old = os.umask(0o022)
    try:
        yield
    finally:
        os.umask(old)


# ------------------------------------------------------------------ links at the path
def test_a_link_at_the_path_never_touches_its_target(tmp_path: Path,
                                                      capsys: pytest.CaptureFixture[str],
                                                      caplog: pytest.LogCaptureFixture) -> None:
    """``canrls run --checkpoint LINK``: the link is neither resolved nor followed; the
    daemon runs without checkpoints and says why; the file it points to is untouched."""
    target = _outside(tmp_path)
    state = tmp_path / "state"
    state.mkdir()
    link = state / "cp.bin"
    link.symlink_to(target)
    with caplog.at_level(logging.ERROR, logger="canrls"):
        code = main(["run", "-i", "virtual", "-c", "fault-ckpt-link", "--kt", "0.1",
                     "--checkpoint", str(link), "--duration", "0.3", "--json"])
    assert code == 0
    res = json.loads(capsys.readouterr().out)
    assert res["daemon"]["checkpoints"] == 0
    assert target.read_bytes() == PRECIOUS
    assert sorted(p.name for p in target.parent.iterdir()) == ["precious.txt"]
    assert link.is_symlink() and os.readlink(link) == str(target)
    assert sorted(p.name for p in state.iterdir()) == ["cp.bin"]
    assert f"{link}: the checkpoint path is a symbolic link" in caplog.text
    assert "running without checkpoints" in caplog.text


def test_a_link_to_a_fifo_is_refused_without_reading(tmp_path: Path) -> None:
    fifo = tmp_path / "fifo"
    os.mkfifo(fifo)
    link = tmp_path / "cp.bin"
    link.symlink_to(fifo)
    running_stub = _setup()
    ck = Checkpointer(link, running_stub[1], running_stub[2], 1e-3, 60.0)
    assert in_thread(lambda: ck.resume(lambda m, s: pytest.fail("restored")),
                      unblock_fifo(fifo), "the checkpoint path") is None
    assert ck.disabled is not None and "symbolic link" in ck.disabled
    assert link.is_symlink() and stat.S_ISFIFO(fifo.lstat().st_mode)
    with pytest.raises(CheckpointPathError, match="symbolic link"):
        in_thread(lambda: load_checkpoint(link), unblock_fifo(fifo), "the checkpoint path")


def test_a_link_to_a_huge_file_is_not_read(tmp_path: Path) -> None:
    """The stand-in for a link to /dev/zero: a sparse file of 1 TiB (no disk used)."""
    big = tmp_path / "zeros"
    with open(big, "wb") as f:
        f.truncate(2**40)
    link = tmp_path / "cp.bin"
    link.symlink_to(big)
    _, model, settings = _setup()
    ck = Checkpointer(link, model, settings, 1e-3, 60.0)
    assert ck.resume(lambda m, s: pytest.fail("restored")) is None
    assert ck.disabled is not None
    assert big.stat().st_size == 2**40 and link.is_symlink()
    with pytest.raises(CheckpointPathError):
        load_checkpoint(link)


def test_a_link_to_a_character_device_is_left_alone(tmp_path: Path) -> None:
    """A character device made in tmp_path (the null device's numbers: harmless)."""
    dev = tmp_path / "null-device"
    try:
        os.mknod(dev, stat.S_IFCHR | 0o600, os.makedev(1, 3))
    except (PermissionError, OSError) as e:
        pytest.skip(f"cannot make a device node here: {e}")
    link = tmp_path / "cp.bin"
    link.symlink_to(dev)
    _, model, settings = _setup()
    ck = Checkpointer(link, model, settings, 1e-3, 60.0)
    assert ck.resume(lambda m, s: pytest.fail("restored")) is None
    assert link.is_symlink() and stat.S_ISCHR(dev.lstat().st_mode)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["cp.bin", "null-device"]
    # and a device directly at the path: refused, not renamed
    link.unlink()
    dev.rename(link)
    ck = Checkpointer(link, model, settings, 1e-3, 60.0)
    assert ck.resume(lambda m, s: pytest.fail("restored")) is None
    assert "character device" in str(ck.disabled)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["cp.bin"]


# ------------------------------------------------------------------ other non-regular files
def test_a_fifo_at_the_path_does_not_hang_the_start(tmp_path: Path,
                                                    running: tuple) -> None:
    path = tmp_path / "cp.bin"
    os.mkfifo(path)
    d = in_thread(lambda: _daemon(running, path), unblock_fifo(path), "the checkpoint path")
    assert d.resumed_from is None and d.pipeline.samples == 0
    assert d.checkpoint() is None  # checkpoints are off: nothing written over the FIFO
    assert stat.S_ISFIFO(path.lstat().st_mode)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["cp.bin"]


@pytest.mark.parametrize("kind", ["directory", "socket"])
def test_a_directory_or_socket_at_the_path_runs_without_checkpoints(
        tmp_path: Path, running: tuple, kind: str, caplog: pytest.LogCaptureFixture) -> None:
    """No crash loop: the daemon starts, logs one error naming the path, and runs
    without checkpoints. A socket stands for an unreadable file (we run as root, who
    reads any regular file)."""
    path = tmp_path / "cp.bin"
    if kind == "directory":
        path.mkdir()
        (path / "inside").write_bytes(PRECIOUS)
    else:
        sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        sock.bind(str(path))
        sock.close()
    with caplog.at_level(logging.ERROR, logger="canrls"):
        d = _daemon(running, path)
        assert d.checkpoint() is None
    assert d.resumed_from is None
    errors = [r.getMessage() for r in caplog.records if r.levelno >= logging.ERROR]
    assert errors == [f"{path}: the checkpoint path is a {kind}, not a regular file; it is "
                      f"left untouched; running without checkpoints"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["cp.bin"]
    if kind == "directory":
        assert (path / "inside").read_bytes() == PRECIOUS


def test_a_directory_that_is_a_file_runs_without_checkpoints(tmp_path: Path,
                                                             running: tuple) -> None:
    """An unusable location (here the 'directory' is a regular file: ENOTDIR, as a
    read-only or missing one would be): one error, no crash, nothing touched."""
    notdir = tmp_path / "notdir"
    notdir.write_bytes(PRECIOUS)
    d = _daemon(running, notdir / "cp.bin")
    assert d.resumed_from is None and d.checkpoint() is None
    assert notdir.read_bytes() == PRECIOUS


def test_a_huge_sparse_file_is_set_aside_unread(tmp_path: Path, running: tuple,
                                                caplog: pytest.LogCaptureFixture) -> None:
    path = tmp_path / "cp.bin"
    with open(path, "wb") as f:
        f.truncate(MAX_BYTES + 1)
    with caplog.at_level(logging.ERROR, logger="canrls"):
        d = _daemon(running, path)
    assert d.resumed_from is None
    assert f"more than the {MAX_BYTES}" in caplog.text  # refused by its size, not read
    bad = list(tmp_path.glob("cp.bin.bad-*"))
    assert len(bad) == 1 and bad[0].stat().st_size == MAX_BYTES + 1
    assert d.checkpoint() == path and load_checkpoint(path).state  # a fresh one written


# ------------------------------------------------------------------ forged contents
def _deep(levels: int) -> bytes:
    return b"[" * levels + b"]" * levels


def _nonsense(running: tuple) -> dict[str, bytes]:
    cp = _checkpoint(running)
    good_doc = json.loads(json.dumps({k: v for k, v in vars(cp).items() if k != "state"}))

    def with_state(state: Any) -> bytes:
        return _forge({**good_doc, "state": state})

    def mutated(fn: Callable[[dict[str, Any]], None]) -> bytes:
        state = copy.deepcopy(cp.state)
        fn(state)
        return _forge_checkpoint(Checkpoint(**{**vars(cp), "state": state}))

    def bad_npy(shape: tuple[int, ...]) -> bytes:
        # a .npy header that claims far more than the member holds
        raw = io.BytesIO()
        np.lib.format.write_array_header_1_0(raw, {"descr": "<f8", "fortran_order": False,
                                                   "shape": shape})
        meta = json.dumps({**good_doc, "state": {"__array__": "a0"}}).encode()
        buf = io.BytesIO()
        np.savez(buf, __meta__=np.frombuffer(meta, np.uint8))
        with zipfile.ZipFile(buf, "a") as zf:
            zf.writestr("a0.npy", raw.getvalue())
        return _envelope(buf.getvalue())

    def object_array() -> bytes:
        buf = io.BytesIO()
        meta = json.dumps({**good_doc, "state": {"__array__": "a0"}}).encode()
        np.savez(buf, __meta__=np.frombuffer(meta, np.uint8),
                 a0=np.array(["text"], dtype="U4"))
        return _envelope(buf.getvalue())

    return {
        "deep meta": _forge(None, meta=_deep(100_000)),
        "deep but within the JSON parser": _forge(None, meta=_deep(900)),
        "deep header": MAGIC + _deep(2000) + b"\n",
        "state is a list": with_state([1, 2, 3]),
        "document is a list": _forge([1, 2]),
        "counters are a list": _forge({**good_doc, "counters": [1], "state": {}}),
        "calibration is a list": mutated(lambda s: s.__setitem__("calibration", [1, 2])),
        "window is a number": mutated(lambda s: s.__setitem__("window", 5)),
        "estimators is a string": mutated(
            lambda s: s["pipeline"].__setitem__("estimators", "x")),
        "rls is a list": mutated(
            lambda s: s["pipeline"]["estimators"][0].__setitem__("rls", [])),
        "theta of another shape": mutated(
            lambda s: s["pipeline"]["estimators"][0]["rls"].__setitem__("theta", np.zeros(7))),
        "P of another shape": mutated(
            lambda s: s["pipeline"]["estimators"][0]["rls"].__setitem__("P", np.eye(2))),
        "array key unknown": with_state({"__array__": "a9"}),
        "array key a list": with_state({"__array__": [1]}),
        "npy header larger than its data": bad_npy((2**40,)),
        "string array": object_array(),
        "missing field": _forge({k: v for k, v in good_doc.items() if k != "saved_at"}),
        "saved_at NaN": _forge({**good_doc, "saved_at": float("nan"), "state": {}}),
        "samples a string": mutated(lambda s: s["pipeline"].__setitem__("samples", "many")),
    }


NONSENSE = ["deep meta", "deep but within the JSON parser", "deep header", "state is a list",
            "document is a list", "counters are a list", "calibration is a list",
            "window is a number", "estimators is a string", "rls is a list",
            "theta of another shape", "P of another shape", "array key unknown",
            "array key a list", "npy header larger than its data", "string array",
            "missing field", "saved_at NaN", "samples a string"]


@pytest.mark.parametrize("case", NONSENSE)
def test_a_valid_checksum_around_nonsense_is_set_aside(tmp_path: Path, running: tuple,
                                                       case: str,
                                                       caplog: pytest.LogCaptureFixture) -> None:
    path = tmp_path / "cp.bin"
    path.write_bytes(_nonsense(running)[case])
    with caplog.at_level(logging.ERROR, logger="canrls"):
        assert _checkpointer(running, path).resume(_restore(running)) is None
    assert not path.exists() and len(list(tmp_path.glob("cp.bin.bad-*"))) == 1
    assert "not loaded" in caplog.text
    # refused by the checks, not by the last resort around the restore
    assert "does not fit the model" not in caplog.text
    if case not in ("theta of another shape", "P of another shape", "samples a string",
                    "calibration is a list", "window is a number", "estimators is a string",
                    "rls is a list", "state is a list"):
        # the reader itself refuses these (the others: the restore does)
        path.write_bytes(_nonsense(running)[case])
        with pytest.raises(CheckpointError):
            load_checkpoint(path)


def test_a_nan_state_is_neither_loaded_nor_written(tmp_path: Path, running: tuple) -> None:
    path = tmp_path / "cp.bin"
    state = copy.deepcopy(running[3].state())
    state["pipeline"]["estimators"][0]["rls"]["theta"][1] = np.nan
    cp = _checkpoint(running, state)
    path.write_bytes(_forge_checkpoint(cp))
    with pytest.raises(CheckpointError, match="NaN"):
        load_checkpoint(path)
    d = _daemon(running, path)
    assert d.resumed_from is None and d.pipeline.samples == 0
    assert len(list(tmp_path.glob("cp.bin.bad-*"))) == 1
    # the writer refuses it too, and keeps the last good checkpoint
    good = _checkpoint(running)
    save_checkpoint(path, good)
    before = path.read_bytes()
    with pytest.raises(CheckpointError, match="NaN"):
        save_checkpoint(path, cp)
    assert path.read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir() if ".tmp." in p.name) == []


def test_a_model_larger_than_the_bound_is_refused(tmp_path: Path, running: tuple) -> None:
    path = tmp_path / "cp.bin"
    save_checkpoint(path, _checkpoint(running))
    ck = _checkpointer(running, path, max_parameters=2)  # the model has 3
    assert ck.resume(_restore(running)) is None
    ck.close()  # its lock: the next checkpointer of the file takes it
    assert len(list(tmp_path.glob("cp.bin.bad-*"))) == 1
    save_checkpoint(path, _checkpoint(running))
    restored = _checkpointer(running, path).resume(_restore(running))  # 256: fits
    assert restored is not None and restored[0].pipeline.samples == running[3].pipeline.samples


# ------------------------------------------------------------------ writing
def test_a_link_at_the_temporary_path_is_not_written_through(
        tmp_path: Path, running: tuple, monkeypatch: pytest.MonkeyPatch) -> None:
    target = _outside(tmp_path)
    path = tmp_path / "cp.bin"
    pid = os.getpid()
    tokens = iter(["00000000", "11111111"])
    monkeypatch.setattr(secrets, "token_hex", lambda n=None: next(tokens))
    for name in (f".cp.bin.tmp.{pid}", f".cp.bin.tmp.{pid}.00000000"):
        (tmp_path / name).symlink_to(target)
    save_checkpoint(path, _checkpoint(running))
    assert target.read_bytes() == PRECIOUS
    assert load_checkpoint(path).counters == {"frames": 7}
    assert not path.is_symlink()
    assert (tmp_path / f".cp.bin.tmp.{pid}.00000000").is_symlink()


def test_checkpoints_are_private(tmp_path: Path, running: tuple, umask022: None) -> None:
    path = tmp_path / "cp.bin"
    save_checkpoint(path, _checkpoint(running))
    assert stat.S_IMODE(path.stat().st_mode) == 0o600
    save_checkpoint(path, _checkpoint(running))  # replaced: still private
    assert stat.S_IMODE(path.stat().st_mode) == 0o600


def test_stale_temporaries_are_cleaned_and_nothing_else(tmp_path: Path,
                                                        running: tuple) -> None:
    target = _outside(tmp_path)
    path = tmp_path / "cp.bin"
    save_checkpoint(path, _checkpoint(running))
    ours = [".cp.bin.tmp.123", ".cp.bin.tmp.456.abcdef01"]
    for name in ours:
        (tmp_path / name).write_bytes(b"half a checkpoint")
    (tmp_path / ".cp.bin.tmp.789").symlink_to(target)  # a link: not ours, left alone
    (tmp_path / ".cp.bin.tmp.99.dir").mkdir()
    keep = [".cp.bin.tmp.notours", "other.bin.tmp.1", ".cp.bin.tmp.12x"]
    for name in keep:
        (tmp_path / name).write_bytes(PRECIOUS)
    restored = _checkpointer(running, path).resume(_restore(running))
    assert restored is not None
    names = {p.name for p in tmp_path.iterdir()}
    assert not names & set(ours)
    assert {".cp.bin.tmp.789", ".cp.bin.tmp.99.dir", *keep} <= names
    assert target.read_bytes() == PRECIOUS


_KILL_SCRIPT = textwrap.dedent("""
    import os, sys, time
    from canrls.live import checkpoint
    from canrls.live.checkpoint import Checkpoint, save_checkpoint
    import numpy as np
    path = sys.argv[1]
    def cp(v):
        return Checkpoint(model={}, config_model={}, fingerprint={},
                          state={"theta": np.full(100_000, v)}, counters={"n": int(v)})
    save_checkpoint(path, cp(1.0))
    real_fsync = os.fsync
    def stuck(fd):  # the second save is killed after its bytes, before its fsync
        sys.stdout.write("writing\\n")
        sys.stdout.flush()
        time.sleep(600)
    os.fsync = stuck
    save_checkpoint(path, cp(2.0))
""")


def test_kill_9_during_a_write_leaves_no_usable_damage(tmp_path: Path,
                                                       running: tuple) -> None:
    path = tmp_path / "cp.bin"
    env = dict(os.environ, PYTHONPATH=str(ROOT / "src"))
    proc = subprocess.Popen([sys.executable, "-c", _KILL_SCRIPT, str(path)], env=env,
                            stdout=subprocess.PIPE, text=True)
    try:
        assert proc.stdout is not None
        assert proc.stdout.readline() == "writing\n"
        proc.send_signal(signal.SIGKILL)
        proc.wait(30)
    finally:
        reap(proc)
    assert proc.returncode == -signal.SIGKILL
    temps = [p for p in tmp_path.iterdir() if p.name.startswith(".cp.bin.tmp.")]
    assert len(temps) == 1  # the write cut short
    assert load_checkpoint(path).counters == {"n": 1}  # the old one, intact
    # the next start removes the temporary and goes on with what is there
    ck = _checkpointer(running, path)
    assert ck.resume(lambda m, s: pytest.fail("another model: not restored")) is None
    assert sorted(p.name for p in tmp_path.iterdir()) == \
        [*(p.name for p in tmp_path.glob("cp.bin.bad-*")), "cp.bin.lock"]  # set aside
    assert not any(p.name.startswith(".cp.bin.tmp.") for p in tmp_path.iterdir())


# ------------------------------------------------------------------ the control period
def _unstated_dbc(tmp_path: Path) -> Path:
    """The shipped DBC without the feedback messages' GenMsgCycleTime: measured."""
    text = (ROOT / "dbc" / "canrls.dbc").read_text()
    lines = [ln for ln in text.splitlines()
             if not ln.startswith(('BA_ "GenMsgCycleTime" BO_ 257 ',
                                   'BA_ "GenMsgCycleTime" BO_ 258 '))]
    p = tmp_path / "unstated.dbc"
    p.write_text("\n".join(lines) + "\n")
    return p


def test_the_fingerprint_holds_no_placeholder_period(tmp_path: Path) -> None:
    protocol, model, settings = _setup(_unstated_dbc(tmp_path))
    assert protocol.period is None
    d = Daemon(protocol, model, settings, DaemonSettings(),
               bus={"interface": "virtual", "channel": "unused-fault-ckpt"})
    assert d.dt is None
    stated = _setup()
    d2 = Daemon(*stated, DaemonSettings(),
                bus={"interface": "virtual", "channel": "unused-fault-ckpt"})
    assert d2.dt == stated[0].period == pytest.approx(1e-3)


def test_the_state_records_its_period() -> None:
    _, model, settings = _setup()
    state = SampleProcessor(model, 1e-3, settings).state()
    assert state["dt"] == 1e-3
    SampleProcessor(model, 1.004e-3, settings).restore(state, model)  # within 1 %
    with pytest.raises(CheckpointError, match="control period of 0.001 s, the frames give 2 ms"):
        SampleProcessor(model, 2e-3, settings).restore(state, model)


@pytest.mark.parametrize(("period", "kept"), [(1e-3, True), (2e-3, False)])
def test_a_deferred_restore_checks_the_measured_period(
        tmp_path: Path, period: float, kept: bool, caplog: pytest.LogCaptureFixture) -> None:
    """The period is measured after the checkpoint is restored: a state that ran at
    another period is then dropped with a warning, and estimation starts afresh."""
    protocol, model, settings = _setup(_unstated_dbc(tmp_path))
    blocks = _frames(3.5)
    a = FrameProcessor(protocol, model, settings, period=1e-3)
    for b in blocks[:5]:
        a.process(b)
    assert a.calibration is not None
    state = a.state()
    assert state["dt"] == 1e-3
    state["dt"] = period  # as a run at that period would have recorded it
    b2 = FrameProcessor(protocol, model, settings)
    assert b2.period is None
    running_model = Model.from_dict(json.loads(json.dumps(a.model.to_dict())))
    assert running_model != model  # calibrated: its ranges and scaling frozen
    b2.restore(state, running_model)  # as the daemon does
    assert b2.dt == period  # restored at its own period while the frames' is measured
    with caplog.at_level(logging.WARNING, logger="canrls"):
        for b in blocks[5:]:
            b2.process(b)
    assert b2.period == pytest.approx(1e-3)
    fresh = FrameProcessor(protocol, model, settings)
    for b in blocks[5:]:
        fresh.process(b)
    if kept:
        assert b2.restore_refused is None and b2.calibration == a.calibration
        assert b2.pipeline.samples > fresh.pipeline.samples
    else:
        assert b2.restore_refused is not None and "control period" in b2.restore_refused
        assert "starts afresh" in caplog.text
        assert b2.model == fresh.model  # the configured model, calibrated afresh
        assert b2.calibration == fresh.calibration != a.calibration
        assert b2.pipeline.samples == fresh.pipeline.samples
        assert [(e.value, e.fixed) for e in b2.pipeline.estimates().parameters] == \
            [(e.value, e.fixed) for e in fresh.pipeline.estimates().parameters]


# ------------------------------------------------------------------ the reader, at random
@pytest.fixture(scope="module")
def valid_bytes(running: tuple) -> bytes:
    return _forge_checkpoint(_checkpoint(running))


_json_values = st.recursive(
    st.none() | st.booleans() | st.integers() | st.floats() | st.text(max_size=8),
    lambda inner: st.lists(inner, max_size=4)
    | st.dictionaries(st.sampled_from(["model", "state", "counters", "saved_at", "version",
                                       "fingerprint", "config_model", "__array__", "x"]),
                      inner, max_size=5),
    max_leaves=30)


def _read(tmp: Path, raw: bytes) -> None:
    p = tmp / "cp.bin"
    p.write_bytes(raw)
    try:
        cp = load_checkpoint(p)
    except CheckpointError:
        return
    assert isinstance(cp, Checkpoint)


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(data=st.data())
def test_the_reader_raises_nothing_but_checkpoint_errors(
        tmp_path_factory: pytest.TempPathFactory, valid_bytes: bytes, data: st.DataObject) -> None:
    tmp = tmp_path_factory.mktemp("prop", numbered=True)
    how = data.draw(st.sampled_from(["random", "flip", "flip payload, checksum fixed",
                                     "truncate", "random document"]))
    if how == "random":
        raw = data.draw(st.binary(max_size=512))
        if data.draw(st.booleans()):
            raw = MAGIC + raw
    elif how == "random document":
        doc = data.draw(_json_values)
        raw = _forge(doc)
    else:
        end = valid_bytes.index(b"\n", len(MAGIC)) + 1
        payload = bytearray(valid_bytes[end:])
        whole = bytearray(valid_bytes)
        if how == "truncate":
            raw = bytes(whole[:data.draw(st.integers(0, len(whole)))])
        else:
            buf = whole if how == "flip" else payload
            flips = data.draw(st.lists(st.tuples(st.integers(0, len(buf) - 1),
                                                 st.integers(0, 255)), min_size=1, max_size=8))
            for i, byte in flips:
                buf[i] = byte
            raw = bytes(whole) if how == "flip" else _envelope(bytes(payload))
    _read(tmp, raw)


def test_an_array_header_that_does_not_parse_is_a_checkpoint_error(tmp_path: Path) -> None:
    """A .npy header with an open bracket makes numpy's parser raise tokenize's own
    error (found by the property above): still a CheckpointError."""
    meta = json.dumps({"x": {"__array__": "a0"}}).encode()
    header = b"{'descr': '<f8', 'fortran_order': False, 'shape': ((3,), }"
    header += b" " * (117 - len(header)) + b"\n"
    npy = b"\x93NUMPY\x01\x00" + len(header).to_bytes(2, "little") + header + bytes(24)
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as z:
        z.writestr("__meta__.npy", _npy_bytes(np.frombuffer(meta, np.uint8)))
        z.writestr("a0.npy", npy)
    p = tmp_path / "cp.bin"
    p.write_bytes(_envelope(buf.getvalue()))
    with pytest.raises(CheckpointError, match="payload unreadable"):
        load_checkpoint(p)


def _npy_bytes(a: np.ndarray) -> bytes:
    out = io.BytesIO()
    np.save(out, a)
    return out.getvalue()


def _paths(obj: Any, path: tuple = ()) -> Iterator[tuple]:
    yield path
    if isinstance(obj, dict):
        for k, v in obj.items():
            yield from _paths(v, (*path, k))
    elif isinstance(obj, list):
        for i, v in enumerate(obj):
            yield from _paths(v, (*path, i))


_arrays = st.builds(lambda shape, kind, fill: np.full(shape, fill, dtype=kind),
                    st.sampled_from([(0,), (1,), (3,), (7,), (3, 3), (2, 2), (3, 1)]),
                    st.sampled_from(["f8", "i8", "u1", "?"]),
                    st.sampled_from([0, 1, 3]))


@settings(max_examples=120, deadline=None,
          suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture])
@given(data=st.data())
def test_a_mutated_state_is_resumed_or_set_aside_never_fatal(
        tmp_path_factory: pytest.TempPathFactory, running: tuple, data: st.DataObject,
        caplog: pytest.LogCaptureFixture) -> None:
    """Any one value of a real state replaced by any JSON value or array: the daemon's
    resume either restores it or sets the file aside; nothing escapes."""
    cp = _checkpoint(running)
    state = copy.deepcopy(cp.state)
    where = data.draw(st.sampled_from([p for p in _paths(state) if p]))
    parent = state
    for k in where[:-1]:
        parent = parent[k]
    parent[where[-1]] = data.draw(_json_values | _arrays)
    tmp = tmp_path_factory.mktemp("mut", numbered=True)
    path = tmp / "cp.bin"
    path.write_bytes(_forge_checkpoint(Checkpoint(**{**vars(cp), "state": state})))
    caplog.clear()
    with caplog.at_level(logging.ERROR, logger="canrls"):
        out = _checkpointer(running, path).resume(_restore(running))
    if out is None:
        assert not path.exists() and "not loaded" in caplog.text
    else:
        assert path.exists()


def test_a_link_placed_while_running_is_not_written_through(tmp_path: Path,
                                                            running: tuple) -> None:
    """A link put at the path after the start: that save fails with a logged error, the
    link and its target stay as they are, and saves resume once the link is gone."""
    target = _outside(tmp_path)
    path = tmp_path / "cp.bin"
    d = _daemon(running, path)
    assert d.checkpoint() == path
    path.unlink()
    path.symlink_to(target)
    assert d.checkpoint() is None
    assert path.is_symlink() and target.read_bytes() == PRECIOUS
    path.unlink()
    assert d.checkpoint() == path and load_checkpoint(path).state
    assert stat.S_IMODE(path.stat().st_mode) == 0o600


def test_a_read_only_location_runs_without_checkpoints(
        tmp_path: Path, running: tuple, monkeypatch: pytest.MonkeyPatch,
        caplog: pytest.LogCaptureFixture) -> None:
    """A read-only file system at the checkpoint's directory (root writes anywhere else,
    so creating files there is made to fail as EROFS would): one error at start, no
    crash, no retry at every interval, the existing file untouched."""
    path = tmp_path / "cp.bin"
    save_checkpoint(path, _checkpoint(running))
    before = path.read_bytes()
    real_open = os.open

    def read_only(file: Any, flags: int, *args: Any, **kw: Any) -> int:
        if flags & os.O_CREAT:
            raise OSError(errno.EROFS, os.strerror(errno.EROFS), str(file))
        return real_open(file, flags, *args, **kw)
    monkeypatch.setattr(os, "open", read_only)
    with caplog.at_level(logging.ERROR, logger="canrls"):
        d = _daemon(running, path)
        assert d.checkpoint() is None and d.checkpoint() is None
    errors = [r.getMessage() for r in caplog.records if r.levelno >= logging.ERROR]
    assert errors == [f"{path}: cannot write in the checkpoint's directory: Read-only file "
                      f"system; running without checkpoints"]
    assert d.resumed_from is None and path.read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["cp.bin"]
