"""Faults against the daemon's command path and life cycle.

In one process on python-can's ``virtual`` bus: the regular publication schedule is a
fixed grid that forced publications never move, command floods (hundreds of
``add_effect``, random bytes) against a running daemon, the bounds on the model and the
command rate, and the exit status of a daemon whose estimator thread fails. Across
processes (python-can-remote on 127.0.0.1): ``canrls run`` killed with -9 at seeded
random moments resumes from its checkpoint every time; a second SIGTERM still stops it
cleanly with exit status 0.
"""

from __future__ import annotations

import collections
import itertools
import json
import logging
import os
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import can
import numpy as np
import pytest
from daemon_tool import DaemonTool, daemon_process, remote_sim_server

from canrls.can.estimator_frames import CommandCode, CommandResult, encode_command
from canrls.core.effect_names import EffectId
from canrls.core.errors import CheckpointError, ConfigError
from canrls.live.checkpoint import Checkpoint, fingerprint, load_checkpoint, save_checkpoint
from canrls.live.daemon import Daemon
from canrls.live.daemon_settings import DaemonSettings
from canrls.processor import FrameProcessor
from canrls.processor.config import AppConfig

ROOT = Path(__file__).resolve().parents[2]
BASE = ["inertia", "viscous", "coulomb"]
_ids = itertools.count()


def _chan(name: str) -> str:
    return f"test-fault-cmd-{name}-{os.getpid()}-{next(_ids)}"


def _setup(effects: list[str] = BASE) -> tuple[Any, Any, Any]:
    cfg = AppConfig()
    cfg.model = {"effects": list(effects), "kt": 0.1}
    protocol = cfg.protocol()
    return protocol, cfg.model_for(protocol), cfg.settings()


def _cmd(code: int, effect: int = 0, order: int = 0, lam: float = 0.0) -> can.Message:
    return encode_command(code, effect, order, lam)


# ------------------------------------------------------------------ the schedule
def test_forced_publications_do_not_move_the_regular_grid() -> None:
    """60 model changes within one interval force 60 publications; the next regular one
    stays where the grid has it (it moved one interval per forced publication: 6 s)."""
    protocol, model, settings = _setup()
    d = Daemon(protocol, model, settings, DaemonSettings(publish_interval=0.1),
               bus={"interface": "virtual", "channel": _chan("grid")})
    pub = d.publisher
    t0 = 1000.0
    pub.start(t0)
    assert pub.next_at == t0 + 0.1
    for k in range(60):  # a burst: each model change publishes at once
        pub.model_changed()
        now = t0 + 0.001 * k
        assert pub.due(now)
        pub.publish(now)
    assert pub.publications == 60
    assert pub.next_at == t0 + 0.1  # the grid did not move
    assert not pub.due(t0 + 0.099) and pub.due(t0 + 0.1)
    pub.publish(t0 + 0.1)
    assert abs(pub.next_at - (t0 + 0.2)) < 1e-9
    pub.publish(t0 + 0.4501)  # a long block missed slots: skipped, the grid kept
    assert abs(pub.next_at - (t0 + 0.5)) < 1e-9


# ------------------------------------------------------------------ floods in one process


def _sim(channel: str) -> dict[str, Any]:
    # feedback frames made as the daemon reads them (with backpressure): the estimator
    # is always busy while the commands flood in
    return dict(interface="canrls-sim", channel=channel, effects="inertia,viscous,coulomb",
                seed=3, excitation="slow", realtime=False, start_time=0.0)


def _random_frames(rng: np.random.Generator, n: int) -> list[can.Message]:
    """Random bytes on the command ID: random DLC 0..8, sometimes a remote frame."""
    out = []
    for _ in range(n):
        dlc = int(rng.integers(0, 9))
        if rng.random() < 0.05:
            out.append(can.Message(arbitration_id=0x320, is_extended_id=False,
                                   is_remote_frame=True, dlc=dlc))
        else:
            out.append(can.Message(arbitration_id=0x320, is_extended_id=False,
                                   data=rng.integers(0, 256, dlc, dtype=np.uint8).tobytes()))
    return out


def test_a_command_flood_is_bounded_answered_and_keeps_the_schedule(
        caplog: pytest.LogCaptureFixture) -> None:
    """300 add_effect and 300 random frames as fast as the bus takes them, against a
    daemon estimating a drive in real time: every frame is answered with its reason,
    the model never exceeds max_parameters, the parameter frames keep their grid and
    the daemon keeps running.

    The schedule is checked on what the daemon decides, not on the wall clock a loaded
    machine stretches: every publication leaves the next one on the grid (whole
    intervals from the first), and between two regular publications the estimator
    thread spends less than 10 intervals of its own CPU time (a flood that starved the
    publications would spend it on commands)."""
    protocol, model, settings = _setup()
    ch = _chan("flood")
    interval = 0.1
    cfg = DaemonSettings(publish_interval=interval, commands=True, max_parameters=16,
                         command_rate=2.0, command_burst=10)
    # after each publication: the grid's next slot and the estimator thread's CPU time
    marks: list[tuple[float, float]] = []
    d = Daemon(protocol, model, settings, cfg, bus=_sim(ch), backpressure=True,
               on_publish=lambda _f, _t: marks.append((d.publisher.next_at,
                                                       time.thread_time())))
    tool = DaemonTool(ch)
    rng = np.random.default_rng(20261127)
    adds = [_cmd(CommandCode.ADD_EFFECT, EffectId.COGGING, k) for k in range(1, 301)]
    junk = _random_frames(rng, 300)
    flood = [m for pair in zip(adds, junk, strict=True) for m in pair]
    sizes: list[int] = []
    caplog.set_level(logging.WARNING, logger="canrls.live.commands")
    try:
        d.start()
        assert d.wait_for(lambda x: x.pipeline.samples > 2000, 60)
        tool.take()
        t0 = time.time()
        m0 = len(marks)
        for k, m in enumerate(flood):
            tool.bus.send(m)
            if k % 50 == 0:
                sizes.append(len(d.model.parameters))
        acks = tool.wait_acks(len(flood))
        # and the schedule after the flood: still publishing (waiting on the count, not
        # on the clock: a loaded machine is slow)
        n = d.stats().publications
        assert d.wait_for(lambda x: x.stats().publications >= n + 5, 30)
        tool.take()
        t1 = time.time()
        m1 = len(marks)
        assert d.failure is None
    finally:
        d.stop()
        tool.close()
    assert len(acks) == len(flood)  # every frame answered
    results = collections.Counter(CommandResult(m.data[1]).name.lower() for m in acks)
    # the reasons: the model bound, the rate limit, and what is wrong with the bytes
    assert results["ok"] >= 6 and results["too_large"] >= 1 and results["rate_limited"] > 200
    assert results["malformed"] + results["unknown_command"] > 200, results
    assert d.stats().command_results == dict(results)
    # bounded: never more than max_parameters, and ended at the bound
    assert max(sizes) <= 16 and len(d.model.parameters) == 15
    assert d.model.effect_names[:3] == tuple(BASE)
    # the regular parameter frames went on during the flood, on their grid: forced
    # publications never moved it (the fault was seconds of silence)
    times = [m.timestamp for m in tool.frames if m.arbitration_id == 0x300
             and m.data[0] == 0 and t0 - interval <= m.timestamp <= t1]
    assert len(times) >= 3
    slots = np.array([at for at, _ in marks])
    steps = (slots - slots[0]) / interval
    assert np.all(np.diff(slots) >= 0) and np.allclose(steps, np.round(steps), atol=1e-6)
    # and no flood kept the estimator from them: its CPU time between two regular
    # publications (those that moved the grid on) stays under 10 intervals
    # (the flood may start before the first publication: m0 = 0, nothing before it)
    window = marks[max(m0 - 1, 0):m1]
    regular = [cpu for (at, cpu), (before, _) in zip(window[1:], window[:-1], strict=True)
               if at > before]
    assert len(regular) >= 3
    assert np.diff(regular).max() < 10 * interval, np.diff(regular).max()
    # nor does the journal get a line per frame: 10 a second at most
    logged = [r for r in caplog.records if "rejected (" in r.message]
    assert 10 <= len(logged) <= 10 * (t1 - t0 + 2) and len(logged) < len(flood) / 4


def test_commands_are_off_by_default() -> None:
    protocol, model, settings = _setup()
    ch = _chan("off")
    d = Daemon(protocol, model, settings, DaemonSettings(publish_interval=1.0),
               bus={"interface": "virtual", "channel": ch})
    tool = DaemonTool(ch)
    try:
        d.start()
        for m in (_cmd(CommandCode.ADD_EFFECT, EffectId.OFFSET), _cmd(CommandCode.RESET),
                  can.Message(arbitration_id=0x320, is_extended_id=False, data=b"\x09")):
            tool.bus.send(m)
        acks = tool.wait_acks(3)
    finally:
        d.stop()
        tool.close()
    assert [CommandResult(m.data[1]) for m in acks] == [CommandResult.DISABLED] * 3
    assert [m.data[0] for m in acks] == [4, 1, 9]  # the raw command byte, as given
    assert d.model.effect_names == tuple(BASE)


def test_the_command_line_enables_commands(tmp_path: Path) -> None:
    from canrls.cli.main import build_parser
    from canrls.cli.run import build_daemon

    conf = tmp_path / "c.toml"
    conf.write_text('[model]\neffects = ["inertia", "viscous", "coulomb"]\nkt = 0.1\n'
                    '[daemon]\ncommands = true\n')
    parser = build_parser("run")
    base = ["run", "-i", "virtual", "-c", _chan("cli")]
    got = {}
    for extra in ([], ["--commands"], ["--no-commands"], ["-C", str(conf)],
                  ["-C", str(conf), "--no-commands"]):
        got[" ".join(extra)] = build_daemon(parser.parse_args(base + extra)).config.commands
    assert got == {"": False, "--commands": True, "--no-commands": False,
                   f"-C {conf}": True, f"-C {conf} --no-commands": False}
    with pytest.raises(SystemExit):  # not both
        parser.parse_args(base + ["--commands", "--no-commands"])


def test_a_model_the_frames_cannot_carry_is_refused_before_it_runs(tmp_path: Path) -> None:
    """The fault: ~127 add_effect grew the model past the 255 parameters the frames
    carry; encoding failed, the daemon stopped (exit status 0) and its checkpoint kept
    the model, so that every start stopped again. Now the add is answered too_large,
    the daemon goes on, and its checkpoint resumes. The model starts 2 adds short of the
    limit (cogging:1..124 configured): the growth before it proves nothing more and took
    17 s."""
    protocol, model, settings = _setup([*BASE, *(f"cogging:{k}" for k in range(1, 125))])
    ch = _chan("big")
    ckpt = tmp_path / "cp.bin"
    cfg = DaemonSettings(publish_interval=0.05, commands=True, max_parameters=255,
                         command_burst=1000, checkpoint=ckpt)
    d = Daemon(protocol, model, settings, cfg, bus={"interface": "virtual", "channel": ch})
    tool = DaemonTool(ch)
    n = 6
    try:
        d.start()
        for k in range(125, 125 + n):
            tool.bus.send(_cmd(CommandCode.ADD_EFFECT, EffectId.COGGING, k))
        acks = tool.wait_acks(n, timeout=120)
        time.sleep(0.2)
        assert d.failure is None
    finally:
        d.stop()
        tool.close()
    results = [CommandResult(m.data[1]) for m in acks]
    assert results == [CommandResult.OK] * 2 + [CommandResult.TOO_LARGE] * 4
    assert len(d.model.parameters) == 255
    assert len(load_checkpoint(ckpt).model["effects"]) == 3 + 126
    again = Daemon(protocol, model, settings, cfg, bus={"interface": "virtual", "channel": ch})
    assert again.resumed_from == str(ckpt) and len(again.model.parameters) == 255


def test_a_checkpoint_whose_model_cannot_be_published_is_set_aside(tmp_path: Path) -> None:
    """A checkpoint left by the old daemon with an oversized model is not resumed."""
    protocol, model, settings = _setup()
    big = model.with_effects(add=[f"cogging:{k}" for k in range(1, 128)])
    assert len(big.parameters) == 257
    proc = FrameProcessor(protocol, big, settings)
    path = tmp_path / "cp.bin"
    save_checkpoint(path, Checkpoint(
        model=json.loads(json.dumps(big.to_dict())),
        config_model=json.loads(json.dumps(model.to_dict())),
        fingerprint=fingerprint(settings, proc.dt), state=proc.state(),
        counters={"frames": 7}, saved_at=123.5))
    d = Daemon(protocol, model, settings, DaemonSettings(checkpoint=path),
               bus={"interface": "virtual", "channel": _chan("bigckpt")})
    assert d.resumed_from is None and d.model.effect_names == tuple(BASE)
    assert not path.exists() and len(list(tmp_path.glob("cp.bin.bad-*"))) == 1
    # nor does a configured model beyond max_parameters start
    with pytest.raises(ConfigError, match="max_parameters = 32"):
        Daemon(protocol, big, settings, DaemonSettings(),
               bus={"interface": "virtual", "channel": _chan("bigcfg")})


def test_a_reload_beyond_max_parameters_keeps_the_running_model(
        caplog: pytest.LogCaptureFixture) -> None:
    protocol, model, settings = _setup()
    big = model.with_effects(add=["unbalance", "cogging:1", "cogging:2"])
    d = Daemon(protocol, model, settings, DaemonSettings(max_parameters=8),
               bus={"interface": "virtual", "channel": _chan("reload")}, reload=lambda: big)
    caplog.set_level(logging.ERROR, logger="canrls.live")
    try:
        d.start()
        d.request_reload()
        assert d.wait_for(lambda x: x.stats().reloads == 1, 10)
        time.sleep(0.1)
        assert d.failure is None
    finally:
        d.stop()
    assert d.model.effect_names == tuple(BASE)
    assert any("reload refused" in r.message and "max_parameters = 8" in r.message
               for r in caplog.records)


def test_the_rate_limit_refills() -> None:
    from canrls.live.commands import TokenBucket

    b = TokenBucket(rate=2.0, burst=3)
    assert [b.take(10.0) for _ in range(4)] == [True, True, True, False]
    assert not b.take(10.4)  # 0.8 token
    assert b.take(10.5) and not b.take(10.5)  # 1 token after 0.5 s
    assert [b.take(100.0) for _ in range(4)] == [True, True, True, False]  # never > burst


def test_freeze_and_resume_are_never_rate_limited() -> None:
    """A resume refused as rate_limited after its freeze left the estimator frozen until
    the tool asked again (the soak's command bursts, by accident of timing). Freeze and
    resume grow nothing: the bucket lets them through and they take no token."""
    from canrls.live.commands import CommandHandler, TokenBucket

    protocol, model, settings = _setup()
    proc = FrameProcessor(protocol, model, settings, period=1e-3)
    sent: list[can.Message] = []
    h = CommandHandler(proc, True, lambda msgs: sent.extend(msgs) or len(msgs),
                       lambda m, why: None, lambda: None,
                       bucket=TokenBucket(rate=1.0, burst=2), clock=lambda: 10.0)
    lam = _cmd(CommandCode.SET_LAMBDA, lam=0.999)
    assert [h.handle(lam) for _ in range(3)] == [CommandResult.OK, CommandResult.OK,
                                                 CommandResult.RATE_LIMITED]
    assert h.handle(_cmd(CommandCode.FREEZE)) is CommandResult.OK
    assert proc.pipeline.frozen
    assert h.handle(_cmd(CommandCode.RESUME)) is CommandResult.OK
    assert not proc.pipeline.frozen
    # a harmless resume while running is answered for what it is, not rate_limited
    assert h.handle(_cmd(CommandCode.RESUME)) is CommandResult.NOT_APPLICABLE
    assert h.handle(lam) is CommandResult.RATE_LIMITED  # the others still wait
    assert len(sent) == 7 and h.bucket is not None and h.bucket.tokens < 1.0


# ------------------------------------------------------------------ exit status
def test_an_exception_in_the_estimator_thread_exits_non_zero(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
        caplog: pytest.LogCaptureFixture) -> None:
    """The daemon used to log the exception and return 0: systemd's
    Restart=on-failure then left it stopped. Now run() returns 1, and the state that
    failed is not checkpointed."""
    protocol, model, settings = _setup()
    ckpt = tmp_path / "cp.bin"
    d = Daemon(protocol, model, settings,
               DaemonSettings(publish_interval=0.05, checkpoint=ckpt),
               bus={"interface": "virtual", "channel": _chan("boom")})

    def boom(now: float) -> None:
        raise RuntimeError("injected publisher fault")

    monkeypatch.setattr(d.publisher, "publish", boom)
    caplog.set_level(logging.CRITICAL, logger="canrls.live")
    assert d.run(duration=30.0) == 1
    assert isinstance(d.failure, RuntimeError)
    assert not ckpt.exists()
    assert any("estimator thread failed" in r.message and r.exc_info for r in caplog.records)


# ------------------------------------------------------------------ across processes
@pytest.mark.slow
def test_sigterm_after_sigterm_is_still_a_clean_stop(tmp_path: Path) -> None:
    """SIGTERM every 10 ms until the daemon has exited: it stops gracefully, exit 0
    (a SIGTERM after the daemon had restored the default handlers killed it: -15)."""
    ckpt = tmp_path / "cp.bin"
    with daemon_process(["run", "-i", "canrls-sim", "-c", "standard", "--bus-kwargs",
                         "seed=1", "--kt", "0.1", "--effects", "inertia,viscous,coulomb",
                         "--checkpoint", str(ckpt), "--json"], tmp_path, name="term") as d:
        d.wait_ready()
        time.sleep(1.0)
        end = time.monotonic() + 60
        while d.proc.poll() is None and time.monotonic() < end:
            d.send(signal.SIGTERM)
            time.sleep(0.01)
        out, err = d.proc.communicate(timeout=30)
    proc = d.proc
    assert proc.returncode == 0, err
    assert json.loads(out)["daemon"]["frames"] > 0 and ckpt.exists()




def _wait_for_checkpoint_beyond(path: Path, frames: int, proc: subprocess.Popen[str],
                                timeout: float) -> None:
    """Until the checkpoint at ``path`` counts more than ``frames`` frames."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        assert proc.poll() is None, "the daemon stopped"
        try:
            if int(load_checkpoint(path).counters["frames"]) > frames:
                return
        except (OSError, CheckpointError):
            pass  # not written yet
        time.sleep(0.05)
    raise AssertionError(f"no checkpoint beyond {frames} frames within {timeout} s")


@pytest.mark.slow
def test_kill_9_at_random_moments_resumes_from_the_checkpoint(tmp_path: Path) -> None:
    """``canrls run -i remote`` (python-can-remote on 127.0.0.1) killed with -9 at seeded
    random moments and started again: every start resumes from the checkpoint, whose
    frame count only grows, and nothing is set aside."""
    pytest.importorskip("can_remote")
    rng = np.random.default_rng(9)
    ckpt = tmp_path / "cp.bin"
    frames: list[int] = []
    with remote_sim_server(tmp_path, "remote-kill9") as url:
        cmd = ["--log-level", "INFO", "run", "-i", "remote", "-c", url, "--kt", "0.1",
               "--effects", "inertia,viscous,coulomb", "--checkpoint", str(ckpt),
               "--checkpoint-interval", "0.3", "--publish-interval", "0.05", "--json"]
        for k in range(4):
            log = tmp_path / f"daemon{k}.log"
            with log.open("w") as err, daemon_process(cmd, tmp_path, name=f"n{k}",
                                                      stderr=err) as d:
                d.wait_ready()
                if k < 3:
                    # a checkpoint newer than the last start's, then a random moment
                    # (waiting on the file, not the clock: a loaded machine is slow)
                    _wait_for_checkpoint_beyond(ckpt, frames[-1] if frames else -1,
                                                d.proc, 60)
                    time.sleep(float(rng.uniform(0.0, 1.5)))
                    d.stop(signal.SIGKILL, timeout=30)
                    assert d.proc.returncode == -signal.SIGKILL
                else:  # the last one stops gracefully
                    time.sleep(1.0)
                    out, _ = d.stop()
            proc = d.proc
            text = log.read_text()
            if k > 0:
                assert f"resumed from checkpoint {ckpt}" in text, text
            assert "not loaded" not in text, text
            frames.append(int(load_checkpoint(ckpt).counters["frames"]))
    assert proc.returncode == 0
    final = json.loads(out)
    assert final["daemon"]["resumed_from"] == str(ckpt)
    assert all(b > a for a, b in itertools.pairwise(frames)), frames
    assert not list(tmp_path.glob("cp.bin.bad-*"))


def test_canrls_run_leaves_late_stop_signals_ignored_as_it_exits(tmp_path: Path) -> None:
    """The process's own canrls run, once its daemon has stopped: SIGTERM, SIGINT and
    SIGHUP are ignored until it exits. A SIGINT storm killed it at its exit (-2 in 3 of
    4 runs): SIGINT went back to Python's handler, which Python resets to the default
    action while it finalises."""
    code = ("import signal, sys; from canrls.cli.main import main; "
            "sys.argv = ['canrls', 'run', '-i', 'virtual', '-c', sys.argv[1], '--kt', '0.1', "
            "'--effects', 'inertia,viscous,coulomb', '--duration', '0.2', '--json']; "
            "rc = main(); print(rc, *(signal.getsignal(s) is signal.SIG_IGN for s in "
            "(signal.SIGTERM, signal.SIGINT, signal.SIGHUP)), file=sys.stderr)")
    done = subprocess.run([sys.executable, "-c", code, _chan("exit-signals")],
                          capture_output=True, text=True, timeout=120, cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    assert done.stderr.splitlines()[-1] == "0 True True True", done.stderr


def test_canrls_run_exits_1_on_an_internal_error(
        monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]) -> None:
    from canrls.cli.main import main
    from canrls.live.publisher import Publisher

    def boom(self: Publisher, now: float) -> None:
        raise RuntimeError("injected publisher fault")

    monkeypatch.setattr(Publisher, "publish", boom)
    saved = {s: signal.getsignal(s) for s in (signal.SIGTERM, signal.SIGINT, signal.SIGHUP)}
    try:
        status = main(["run", "-i", "virtual", "-c", _chan("cli-boom"), "--kt", "0.1",
                       "--effects", "inertia,viscous,coulomb", "--duration", "30"])
        # main() called from another program restores its handlers: an ignored SIGTERM
        # would pass to every process it starts afterwards (the test's servers ignored
        # terminate() after such a call)
        assert {s: signal.getsignal(s) for s in saved} == saved
        child = subprocess.run(
            [sys.executable, "-c",
             "import signal; print(signal.getsignal(signal.SIGTERM) == signal.SIG_DFL)"],
            capture_output=True, text=True, check=True)
        assert child.stdout.strip() == "True", child.stdout
    finally:
        for s, h in saved.items():
            signal.signal(s, h)
    assert status == 1
    err = capsys.readouterr().err
    assert "error: the daemon stopped on an internal error: RuntimeError: injected" in err
