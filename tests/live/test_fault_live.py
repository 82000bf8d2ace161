"""The live path under faults of its own making: receive times, the recorder, IDs,
signals at start, a lost remote bus, reloads and a second daemon (issue 22, part B).

Each test failed before its fix; everything stays inside the test's ``tmp_path`` and
127.0.0.1 (docs/reliability.md, *The live path, the model file and the configuration*).
"""

from __future__ import annotations

import dataclasses
import json
import os
import resource
import subprocess
import sys
import textwrap
import tracemalloc
from pathlib import Path

import numpy as np
import pytest
from daemon_tool import daemon_fed, daemon_process, reap, reloaded_daemon, remote_sim_server

from canrls.can.estimator_frames import FrameDecoder
from canrls.can.frameblock import FrameBlock
from canrls.core.checks import MAX_TIMESTAMP, is_time
from canrls.live.daemon import Daemon
from canrls.live.daemon_settings import DaemonSettings
from canrls.live.monitor_listener import Monitor
from canrls.processor import SEEN_IDS, FrameProcessor
from canrls.processor.config import AppConfig, prepare
from canrls.processor.replay import fit_frames
from canrls.processor.times import SPIKE_FRAMES, TimeJudge
from canrls.sim.scenario import scenario, simulate

EFFECTS = "inertia,viscous,coulomb"


def _setup() -> tuple:
    cfg = AppConfig()
    cfg.model = {"effects": EFFECTS.split(","), "kt": 0.1}
    return prepare(cfg)


@pytest.fixture(scope="module")
def sim() -> FrameBlock:
    """8 s of the simulated drive at 1 kHz (clean frames, two per period)."""
    return simulate(scenario("standard", effects=EFFECTS, seed=3, duration=8.0)).frames


def _stamped(block: FrameBlock, rows: list[int], value: float) -> FrameBlock:
    t = block.t.copy()
    t[rows] = value
    return dataclasses.replace(block, t=t)


# --------------------------------------------------------------------------- receive times
@pytest.mark.parametrize("stamp", [1e300, 1.7e15])
def test_an_absurd_receive_time_in_a_live_run_is_counted_and_estimation_goes_on(
        sim: FrameBlock, stamp: float) -> None:
    """The daemon on a virtual bus: one period's two frames stamped 1e300 s (or an
    epoch in microseconds, 1.7e15 s) 4 s into the run. Before, the sample count froze
    there (3,994 samples of 8,000), nothing counted, stale estimates published as
    healthy; now those two frames are rejected (``time``), the period is one sample
    lost, the rest estimated as the offline front end does, and the count and the
    ``ClockFault`` flag reach the bus and the monitor."""
    frames = _stamped(sim, [8000, 8001], stamp)
    messages = frames.to_messages()
    protocol, model, settings = _setup()
    with daemon_fed(protocol, model, settings, messages, "test-fault-live") as (d, reader):
        samples = d.stats().samples
        status = d.status()
        counts = d.frame_counts()
    offline = FrameProcessor(protocol, model, settings)
    offline.process(frames)
    assert samples == offline.pipeline.samples == len(sim) // 2 - 1
    assert status.rejects["time"] == 2 and status.rejects["clock_steps"] == 0
    assert counts["rejected"]["time"] == 2 and status.frames_rejected == 2

    dec, mon, flags = FrameDecoder(), Monitor(), []
    while (m := reader.get_message(0.0)) is not None:
        out = dec.feed(m)
        mon.on_message_received(m)
        if m.arbitration_id == 0x311 and out is not None:
            flags.append(out.clock_fault)
    assert any(flags) and not flags[-1]  # set after the frames, cleared after RlsRejects
    assert dec.status is not None and dec.status.rejects["time"] == 2
    view = mon.snapshot()
    assert view.to_dict()["rejects"]["time"] == 2
    assert "time 2" in view.format()


@pytest.mark.parametrize("stamp", [np.inf, -np.inf, np.nan, 2e10, -2e10])
def test_a_frame_without_a_time_costs_its_sample_and_nothing_more(
        sim: FrameBlock, stamp: float) -> None:
    """The front end the daemon and ``canrls fit`` share, fed one period's frames
    stamped with no time: before, a non-finite time was dropped as late but 2e10 s cost
    a clock step there and back; now both frames are rejected (``time``), one sample."""
    p = FrameProcessor(*_setup())
    p.process(_stamped(sim, [8000, 8001], stamp))
    assert p.reject_counts()["time"] == 2 and p.reject_counts()["clock_steps"] == 0
    assert p.pipeline.samples == len(sim) // 2 - 1
    assert "is not a time" in p.rejected.examples["time"]


@pytest.mark.parametrize("jump", [100.0, -100.0, 5e9, -1.7e9])
def test_a_lone_frame_off_the_time_base_is_an_outlier_not_a_clock_step(
        sim: FrameBlock, jump: float) -> None:
    """One frame more than 1 s off the stream, the frames after it back on it: before,
    it cost a clock step there and back (two re-anchorings, the filter restarted) and
    moved the time base by the jump for good; now it alone is rejected (``time``)."""
    t = sim.t.copy()
    t[8000] += jump
    p = FrameProcessor(*_setup())
    p.process(dataclasses.replace(sim, t=t))
    assert p.reject_counts()["time"] == 1
    assert p.reject_counts()["clock_steps"] == 0 and p.pairing.clock["gap"] == 0
    assert p.pipeline.samples == len(sim) // 2 - 1
    assert "out of line" in p.rejected.examples["time"]


def test_a_clock_step_is_still_a_step_and_any_split_gives_the_same(sim: FrameBlock) -> None:
    """A real step (every later frame 60 s on) is passed on whole to the pairer, which
    re-anchors and counts it; the judgment carries its state across blocks, so the
    frames, samples and counts do not depend on where the stream is cut, not even in
    the middle of a departure held for the frames after it."""
    t = sim.t.copy()
    t[8000:] += 60.0
    t[5000] = 1e300
    t[3000] += 2e9
    t[3001] += 2e9  # a departure of two frames that the stream leaves again
    frames = dataclasses.replace(sim, t=t)
    protocol, model, settings = _setup()
    whole = FrameProcessor(protocol, model, settings)
    whole.process(frames)
    rng = np.random.default_rng(22)
    for _ in range(3):
        cuts = np.sort(rng.choice(np.arange(1, len(frames)), 40, replace=False))
        cuts = np.unique(np.concatenate([cuts, [3000, 3001, 3002, 8000, 8001]]))
        part = FrameProcessor(protocol, model, settings)
        for a, b in zip(np.r_[0, cuts], np.r_[cuts, len(frames)], strict=True):
            part.process(frames.take(slice(int(a), int(b))))
        assert part.reject_counts() == whole.reject_counts()
        assert part.pipeline.update_counts() == whole.pipeline.update_counts()
    assert whole.reject_counts()["time"] == 3
    assert whole.reject_counts()["clock_steps"] == 1


def test_a_long_departure_is_a_step_and_a_slow_stream_is_kept() -> None:
    """The judge alone: a departure longer than SPIKE_FRAMES frames is a clock step
    (passed on), and frames more than 1 s apart one after another (a slow stream, a
    silence) are all kept: only a frame the stream comes back from is rejected."""
    def block(t: np.ndarray) -> FrameBlock:
        b = FrameBlock.allocate(len(t))
        b.t[:] = t
        return b

    j = TimeJudge()
    t = np.r_[np.arange(10) * 1e-3, 500.0 + np.arange(SPIKE_FRAMES + 1) * 1e-3]
    got = j.push(block(t))
    assert len(got) == len(t) and j.counts.total == 0
    slow = TimeJudge()
    t = np.arange(20) * 2.0  # one frame every 2 s
    kept = [slow.push(block(t[k:k + 1])) for k in range(len(t))] + [slow.flush()]
    assert sum(len(b) for b in kept) == len(t) and slow.counts.total == 0
    assert not is_time(MAX_TIMESTAMP * 1.0000001) and is_time(-MAX_TIMESTAMP)


def test_fit_json_counts_time_rejects_of_frames_fed_in_process(sim: FrameBlock) -> None:
    """``canrls fit``'s front end, fed frames without a log reader (which refuses such
    lines itself), counts them under the same reason."""
    res = fit_frames([_stamped(sim, [8000, 8001], np.inf)], *_setup())
    assert res.to_dict()["frames"]["rejected"]["time"] == 2


# --------------------------------------------------------------------------- distinct IDs
def test_distinct_ids_before_a_mapped_frame_keep_memory_bounded() -> None:
    """Random 29-bit IDs while no mapped frame has come: before, each new ID stayed in a
    dict (1.3 GB an hour at 5,000 frames/s); now at most 2 x SEEN_IDS are kept, and the
    error still names the most frequent."""
    protocol, model, settings = _setup()
    p = FrameProcessor(protocol, model, settings, period=1e-3)
    rng = np.random.default_rng(4)
    n = 20_000

    def block(k: int) -> FrameBlock:
        b = FrameBlock.allocate(n)
        b.t[:] = k + np.arange(n) / n
        b.arbitration_id[:] = rng.integers(0x800, 1 << 29, n, dtype=np.uint32)
        b.arbitration_id[:50] = 0x7FF  # one frequent foreign ID
        b.is_extended[:] = True
        b.is_extended[:50] = False
        return b

    p.samples(block(0))
    tracemalloc.start()
    try:
        base = tracemalloc.get_traced_memory()[0]
        for k in range(1, 16):
            p.samples(block(k))
        grown = tracemalloc.get_traced_memory()[0] - base
    finally:
        tracemalloc.stop()
    assert grown < 2_000_000, grown  # 300,000 distinct IDs kept cost some 30 MB
    seen = p.seen_ids(SEEN_IDS * 4)
    assert len(seen) <= 2 * SEEN_IDS
    assert seen[0] == (0x7FF, 16 * 50)


# --------------------------------------------------------------------------- the recorder
@pytest.mark.slow
def test_a_full_disk_under_record_stops_the_recording_not_the_bus(tmp_path: Path) -> None:
    """``canrls run -i remote --record`` under a file-size limit (RLIMIT_FSIZE, EFBIG
    as a full disk): before, the error read as a bus failure (reopened ~40 times in 6 s,
    frames lost, publications paused) and closing the writer at the stop exited 3
    without the JSON. Now the error is logged once and counted, the recording stops,
    estimation and publication go on, and the stop is clean: exit 0 with its JSON."""
    limit = 4096  # python-can writes in 8 KiB: the first write fails

    def small_files() -> None:
        resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit))

    record = tmp_path / "rec.log"
    config = tmp_path / "short.toml"  # a short calibration: samples within the run
    config.write_text("[estimator]\ncalibration_s = 0.05\n")
    with remote_sim_server(tmp_path, "record") as url:
        r = subprocess.run(
            [sys.executable, "-m", "canrls", "--log-level", "INFO", "run", "-i", "remote",
             "-c", url, "--config", str(config), "--kt", "0.1", "--duration", "4",
             "--record", str(record), "--json"], capture_output=True, text=True,
            timeout=120, preexec_fn=small_files)
    assert r.returncode == 0, r.stderr[-2000:]
    out = json.loads(r.stdout)
    rec = out["daemon"]["record"]
    assert rec["errors"] >= 1 and "File too large" in rec["error"]
    assert rec["dropped"] > 0 and rec["frames"] > 0
    assert out["daemon"]["bus_reopens"] == 0 and out["daemon"]["rx_overflow"] == 0
    assert out["daemon"]["frames"] == rec["frames"] + rec["dropped"]  # every frame read on
    assert out["daemon"]["samples"] > 0 and out["daemon"]["publications"] > 0
    stopped = [line for line in r.stderr.splitlines() if "recording to" in line]
    assert len(stopped) == 1 and "stopped" in stopped[0]
    assert "failed" not in r.stderr and "Traceback" not in r.stderr
    assert 0 < record.stat().st_size <= limit


# --------------------------------------------------------------------------- signals at start
_SIGNAL_AT_IMPORT = textwrap.dedent("""
    import os, signal, sys

    class SignalAtImport:
        '''Sends the process SIGNAL when MODULE is first imported: the moment the
        heavy imports begin, before canrls run's own handlers can exist.'''

        def find_spec(self, name, path=None, target=None):
            if name == {module!r}:
                sys.meta_path.remove(self)
                os.kill(os.getpid(), signal.{signal})
            return None

    sys.meta_path.insert(0, SignalAtImport())
    from canrls.cli.main import main
    sys.exit(main())
""")


@pytest.mark.parametrize("signame, module", [("SIGTERM", "numpy"), ("SIGHUP", "numpy"),
                                             ("SIGTERM", "can")])
def test_a_signal_in_the_first_moments_of_canrls_run_does_not_kill_it(
        tmp_path: Path, signame: str, module: str) -> None:
    """The console script's ``main()`` with SIGTERM or SIGHUP arriving as numpy (or
    python-can) starts to load, some 0.1 s into ``canrls run``: before, the process died
    by the signal (-15, -1); now a SIGTERM makes the daemon start and stop at once
    (exit 0, its JSON, "signal 15: stopping"), a SIGHUP is ignored (nothing to reload
    yet) and the run goes on to its ``--duration``."""
    code = _SIGNAL_AT_IMPORT.format(module=module, signal=signame)
    r = subprocess.run(
        [sys.executable, "-c", code, "--log-level", "INFO", "run", "-i", "virtual", "-c",
         f"early-{signame}", "--duration", "1", "--json"],
        capture_output=True, text=True, timeout=120, cwd=tmp_path)
    assert r.returncode == 0, (r.returncode, r.stderr[-2000:])
    out = json.loads(r.stdout)
    assert "daemon" in out and "frames" in out
    stopping = "signal 15: stopping" in r.stderr
    assert stopping == (signame == "SIGTERM"), r.stderr[-2000:]


# --------------------------------------------------------------------------- a lost remote bus
_REMOTE_ON_PORT = """
from can_remote import RemoteServer
srv = RemoteServer("127.0.0.1", %d, channel="lost", bustype="canrls-sim", seed=7,
                   excitation="slow", effects="inertia,viscous,coulomb")
print(srv.server_port, flush=True)
srv.serve_forever()
"""


def _free_port() -> int:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _server(port: int) -> subprocess.Popen[str]:
    proc = subprocess.Popen([sys.executable, "-c", _REMOTE_ON_PORT % port],
                            stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
    assert proc.stdout is not None and int(proc.stdout.readline()) == port
    return proc


@pytest.mark.slow
def test_a_remote_bus_lost_and_reconnected_leaves_no_traceback_at_exit(tmp_path: Path) -> None:
    """``canrls run -i remote``: the python-can-remote server goes away and comes back
    on its port. Before, the lost bus's shutdown failed (ENOTCONN), python-can's
    ``__del__`` tried again when it was collected and printed "Exception ignored in
    BusABC.__del__" with a traceback; now the old bus is shut down properly, whatever
    its connection did."""
    import queue
    import threading

    pytest.importorskip("can_remote")
    port = _free_port()
    server = _server(port)
    with daemon_process(["--log-level", "INFO", "run", "-i", "remote", "-c",
                         f"ws://127.0.0.1:{port}/", "--kt", "0.1", "--duration", "120",
                         "--json"], tmp_path) as d:
        daemon = d.proc
        lines: queue.Queue[str | None] = queue.Queue()
        seen: list[str] = []

        def pump() -> None:
            assert daemon.stderr is not None
            for line in daemon.stderr:
                lines.put(line)
            lines.put(None)

        reader = threading.Thread(target=pump, name="stderr pump")
        reader.start()

        def wait_for(text: str) -> None:
            while (line := lines.get(timeout=60)) is not None:
                seen.append(line)
                if text in line:
                    return
            raise AssertionError(f"no {text!r} in {''.join(seen)[-2000:]}")

        try:
            wait_for("daemon running")
            reap(server, terminate=True)
            wait_for("reopening")
            server = _server(port)
            wait_for("CAN bus reopened")
        finally:
            out, _ = d.stop()
            reader.join(10)
            reap(server, terminate=True)
    while (line := lines.get_nowait()) is not None:
        seen.append(line)
    err = "".join(seen)
    assert daemon.returncode == 0, err[-2000:]
    assert "Exception ignored" not in err and "Traceback" not in err, err[-3000:]
    assert "not properly shut down" not in err
    assert json.loads(out)["daemon"]["bus_reopens"] == 1


# --------------------------------------------------------------------------- reloads
def test_sighup_with_an_invalid_daemon_table_says_so_and_keeps_the_settings(
        tmp_path: Path) -> None:
    """SIGHUP after the configuration's ``[daemon]`` table went bad: before, the reload
    read only the model and said nothing (the next restart would then refuse the file);
    now the reload is refused with an error naming the key, and the daemon goes on with
    its settings and model. A valid change of the table is said to apply at the next
    start."""
    conf = tmp_path / "canrls.toml"
    good = ('[model]\neffects = ["inertia", "viscous", "coulomb"]\nkt = 0.1\n'
            '[can]\ninterface = "virtual"\nchannel = "reload-daemon"\n'
            '[daemon]\npublish_interval = 0.05\n')
    conf.write_text(good)
    rc, out, err = reloaded_daemon(tmp_path, conf, [good.replace("0.05", '"fast"'),
                                                    good.replace("0.05", "0.2")])
    assert rc == 0, err
    refused = [line for line in err.splitlines() if "reload failed" in line]
    assert len(refused) == 1, err
    assert "daemon.publish_interval = 'fast'" in refused[0]
    assert "keeps its configuration" in refused[0]
    assert "reload: [daemon] publish_interval changed: applied at the next start" in err
    assert json.loads(out)["daemon"]["reloads"] == 2


def test_sighup_with_another_dbc_refuses_what_a_start_refuses_and_says_what_waits(
        tmp_path: Path) -> None:
    """Issue 30, 10: SIGHUP after the configuration named another DBC and mapping logged
    only the model, kept decoding the old IDs without a word, and accepted a DBC that
    does not exist (a fresh start refuses it). Now a file a start would refuse is
    refused, the running configuration kept; a valid new DBC and mapping are said to
    apply at the next start."""
    conf = tmp_path / "canrls.toml"
    base = ('[model]\neffects = ["inertia", "viscous", "coulomb"]\nkt = 0.1\n'
            '[can]\ninterface = "virtual"\nchannel = "reload-dbc"\n{dbc}'
            '[daemon]\npublish_interval = 0.05\n{signals}')
    conf.write_text(base.format(dbc="", signals=""))
    text = (Path(__file__).resolve().parents[2] / "dbc" / "canrls.dbc").read_text()
    other = tmp_path / "other.dbc"
    other.write_text(text.replace("BO_ 257 DriveCurrent", "BO_ 300 MotorCurrent")
                     .replace("BO_ 258 DriveSpeed", "BO_ 301 MotorSpeed")
                     .replace(" 257 ", " 300 ").replace(" 258 ", " 301 "))
    other_map = ('[signals]\ncurrent = "MotorCurrent.Current"\n'
                 'speed = "MotorSpeed.Speed"\n')
    rc, out, err = reloaded_daemon(tmp_path, conf, [
        base.format(dbc=f'dbc = "{tmp_path / "missing.dbc"}"\n', signals=""),
        base.format(dbc=f'dbc = "{other}"\n', signals=other_map)])
    assert rc == 0, err
    refused = [line for line in err.splitlines() if "reload failed" in line]
    assert len(refused) == 1, err
    assert "missing.dbc" in refused[0] and "keeps its configuration" in refused[0]
    assert ("reload: can.dbc, signals changed: applied at the next start, not now"
            in err), err
    assert json.loads(out)["daemon"]["reloads"] == 2


# --------------------------------------------------------------------------- two daemons
def test_a_second_daemon_on_one_checkpoint_is_refused_naming_the_holder(
        tmp_path: Path) -> None:
    """Two ``canrls run`` on one checkpoint file: before, both ran and wrote it in turn
    (never torn, but each overwrote the other's state); now the second stops at start,
    exit 1, one error naming the checkpoint and the PID holding its lock (that the lock
    goes with the stop: the next test)."""
    ckpt = tmp_path / "cp.bin"
    cmd = ["run", "-i", "virtual", "-c", "lock-test", "--kt", "0.1", "--checkpoint",
           str(ckpt), "--json"]
    with daemon_process([*cmd, "--duration", "120"], tmp_path) as d:
        d.wait_ready()
        second = subprocess.run([sys.executable, "-m", "canrls", *cmd, "--duration", "1"],
                                capture_output=True, text=True, timeout=120)
        out, err = d.stop()
    first = d.proc
    assert first.returncode == 0, err
    assert second.returncode == 1 and second.stdout == ""
    lines = second.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: "), second.stderr
    assert f"{ckpt}: the checkpoint is in use" in lines[0]
    assert f"PID {first.pid}" in lines[0] and "cp.bin.lock" in lines[0]


def test_a_link_at_the_lock_path_runs_without_checkpoints_and_is_not_followed(
        tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    """A symbolic link planted at ``NAME.lock``: never followed (its target is not
    created nor written), the daemon runs without checkpoints and says so; and the lock
    goes with the daemon, so another one on the same file starts after it."""
    from canrls.core.errors import CheckpointError

    protocol, model, settings = _setup()
    target = tmp_path / "elsewhere.txt"
    (tmp_path / "cp.bin.lock").symlink_to(target)
    cfg = DaemonSettings(checkpoint=tmp_path / "cp.bin")
    d = Daemon(protocol, model, settings, cfg, bus={"interface": "virtual", "channel": "x"})
    assert not target.exists() and d.checkpoint() is None
    assert any("lock" in r.message and "without checkpoints" in r.message
               for r in caplog.records)
    (tmp_path / "cp.bin.lock").unlink()
    one = Daemon(protocol, model, settings, cfg, bus={"interface": "virtual", "channel": "x"})
    with pytest.raises(CheckpointError, match=rf"PID {os.getpid()}"):
        Daemon(protocol, model, settings, cfg, bus={"interface": "virtual", "channel": "x"})
    with one:
        pass  # started and stopped: the lock is released at the stop
    Daemon(protocol, model, settings, cfg, bus={"interface": "virtual", "channel": "x"})
