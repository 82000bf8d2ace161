"""What the daemon tests share: a tool on a daemon's virtual bus (what a monitor or a
test bench sees: every frame the daemon sends in the ``0x3xx`` range, command frames
sent and their acknowledgements awaited), and a python-can-remote server hosting the
simulated drive for the tests across processes, a daemon fed a recorded stream on
a virtual bus, and ``canrls run`` in a process of its own, started and stopped in one
place (:func:`daemon_process`).
"""

from __future__ import annotations

import contextlib
import dataclasses
import itertools
import os
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

import can

from canrls.can.estimator_frames import CommandResult
from canrls.can.protocol import Protocol
from canrls.cli.run import daemon_for
from canrls.estimation.model import Model
from canrls.estimation.settings import EstimatorSettings
from canrls.live.daemon import Daemon
from canrls.live.daemon_settings import DaemonSettings
from canrls.processor.config import load_config

__all__ = ["DaemonProcess", "DaemonTool", "axis_daemons", "collect", "daemon_fed",
           "daemon_process", "datagrams", "notify_socket", "reloaded_daemon",
           "remote_sim_server"]

#: RlsCommandAck
ACK_ID = 0x321


def collect(reader: can.BufferedReader) -> list[can.Message]:
    """Every message ``reader`` holds now."""
    out = []
    while (m := reader.get_message(0.0)) is not None:
        out.append(m)
    return out


_channels = itertools.count()


def axis_daemons(config: Path, bus: dict[str, Any], *, backpressure: bool = False,
                 **settings: Any) -> dict[str, Daemon]:
    """Each axis's daemon of the machine ``config`` on ``bus`` (not started), by name:
    its ``[daemon]`` settings with ``settings`` over them."""
    out = {}
    for name, cfg in load_config(config).axis_configs().items():
        protocol = cfg.protocol()
        dset = dataclasses.replace(DaemonSettings.from_config(cfg), **settings)
        out[name] = daemon_for(protocol, cfg.model_for(protocol), cfg.settings(), dset,
                               bus=bus, backpressure=backpressure)
    return out


@contextlib.contextmanager
def daemon_fed(protocol: Protocol, model: Model, settings: EstimatorSettings,
               messages: Sequence[can.Message], name: str, *, publications: int = 6,
               daemon: DaemonSettings | None = None, **options: Any
               ) -> Iterator[tuple[Daemon, can.BufferedReader]]:
    """A daemon on a virtual bus, fed ``messages`` with their own timestamps (as a drive
    on a real bus would send them); yields it once it has taken every frame and published
    ``publications`` more times, with a reader holding every frame it sent (``0x3xx``).
    ``daemon`` replaces the settings, ``options`` go to the daemon. The daemon and the
    buses are stopped on leaving."""
    ch = f"{name}-{os.getpid()}-{next(_channels)}"
    sender = can.Bus(interface="virtual", channel=ch, preserve_timestamps=True,
                     ignore_config=True)
    tool = can.Bus(interface="virtual", channel=ch, ignore_config=True)
    tool.set_filters([{"can_id": 0x300, "can_mask": 0x700}])  # the daemon's frames
    reader = can.BufferedReader()
    notifier = can.Notifier(tool, [reader], timeout=0.05)
    d = Daemon(protocol, model, settings,
               daemon or DaemonSettings(publish_interval=0.05, info_interval=0.2),
               bus={"interface": "virtual", "channel": ch}, backpressure=True, **options)
    try:
        d.start()
        for m in messages:
            sender.send(m)
        assert d.wait_for(lambda x: x.stats().frames == len(messages), 120)
        n = d.stats().publications
        assert d.wait_for(lambda x: x.stats().publications >= n + publications, 20)
        yield d, reader
    finally:
        d.stop()
        notifier.stop()
        sender.shutdown()
        tool.shutdown()


class DaemonTool:
    """A virtual bus on the daemon's channel that keeps the daemon's frames."""

    def __init__(self, channel: str) -> None:
        self.bus = can.Bus(interface="virtual", channel=channel, ignore_config=True)
        self.bus.set_filters([{"can_id": 0x300, "can_mask": 0x700}])
        self.reader = can.BufferedReader()
        self.notifier = can.Notifier(self.bus, [self.reader], timeout=0.05)
        self.frames: list[can.Message] = []

    def take(self) -> list[can.Message]:
        """The frames received since the last call (also kept in :attr:`frames`)."""
        new = collect(self.reader)
        self.frames += new
        return new

    def command(self, msg: can.Message, timeout: float = 5.0) -> CommandResult | None:
        """Send a command frame and wait for its acknowledgement (None: none came)."""
        self.take()
        self.bus.send(msg)
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            for m in self.take():
                if m.arbitration_id == ACK_ID:
                    return CommandResult(m.data[1])
            time.sleep(0.01)
        return None

    def acks(self) -> list[can.Message]:
        """Every acknowledgement kept so far."""
        return [m for m in self.frames if m.arbitration_id == ACK_ID]

    def wait_acks(self, n: int, timeout: float = 60.0) -> list[can.Message]:
        """Until ``n`` acknowledgements have come (or ``timeout``): all of them."""
        end = time.monotonic() + timeout
        while len(self.acks()) < n and time.monotonic() < end:
            self.take()
            time.sleep(0.01)
        return self.acks()

    def close(self) -> None:
        self.notifier.stop()
        self.bus.shutdown()


_REMOTE_SERVER = """
from can_remote import RemoteServer
srv = RemoteServer("127.0.0.1", 0, channel=%r, bustype="canrls-sim", seed=7,
                   excitation="slow", effects="inertia,viscous,coulomb")
print(srv.server_port, flush=True)
srv.serve_forever()
"""


@contextlib.contextmanager
def remote_sim_server(directory: Path, channel: str) -> Iterator[str]:
    """A python-can-remote server on 127.0.0.1 (a free port) hosting the simulated
    drive in its own process; yields its ``ws://`` URL and stops it on exit (killed
    when SIGTERM has not ended it within 10 s: a loaded machine)."""
    script = directory / f"server-{channel}.py"
    script.write_text(_REMOTE_SERVER % channel)
    proc = subprocess.Popen([sys.executable, str(script)], stdout=subprocess.PIPE,
                            stderr=subprocess.DEVNULL, text=True)
    try:
        assert proc.stdout is not None
        yield f"ws://127.0.0.1:{int(proc.stdout.readline())}/"
    finally:
        reap(proc, terminate=True)


def reap(proc: subprocess.Popen[str], *, terminate: bool = False,
         timeout: float = 10.0) -> None:
    """End a test's subprocess if it still runs (SIGTERM first with ``terminate``,
    SIGKILL when it has not ended within ``timeout``), wait for it and close its stdout."""
    if proc.poll() is None and terminate:
        proc.terminate()
        try:
            proc.wait(timeout)
        except subprocess.TimeoutExpired:
            pass
    if proc.poll() is None:
        proc.kill()
    proc.wait(timeout)
    if proc.stdout is not None:
        proc.stdout.close()


def notify_socket(directory: Path, name: str) -> tuple[socket.socket, str]:
    """A datagram socket standing in for systemd's ``NOTIFY_SOCKET``: (socket, path)."""
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    addr = str(directory / f"{name}.sock")
    sock.bind(addr)
    sock.settimeout(0.2)
    return sock, addr


def datagrams(sock: socket.socket, want: str, timeout: float,
              proc: subprocess.Popen[str] | None = None) -> list[str]:
    """The notifications received until one holds ``want`` (or ``timeout``, or ``proc``
    has exited)."""
    got: list[str] = []
    end = time.monotonic() + timeout
    while time.monotonic() < end and (proc is None or proc.poll() is None):
        try:
            got.append(sock.recv(4096).decode())
        except TimeoutError:
            continue
        if want in got[-1]:
            break
    return got


class DaemonProcess:
    """``python -m canrls ...`` in a process of its own, told of systemd's
    ``NOTIFY_SOCKET`` in the test's directory (:func:`daemon_process` starts and stops it)."""

    def __init__(self, proc: subprocess.Popen[str], sock: socket.socket) -> None:
        self.proc = proc
        self.sock = sock

    def notifications(self, want: str, timeout: float = 60) -> list[str]:
        """The notifications until one holds ``want`` (or ``timeout``, or the exit)."""
        return datagrams(self.sock, want, timeout, self.proc)

    def wait_ready(self, timeout: float = 60) -> None:
        """Until the daemon says ``READY=1``; an AssertionError if it does not."""
        if not any("READY=1" in g for g in self.notifications("READY=1", timeout)):
            raise AssertionError(f"the daemon did not get ready (exit status "
                                 f"{self.proc.poll()})")

    def send(self, sig: int) -> None:
        self.proc.send_signal(sig)

    def stop(self, sig: int = signal.SIGTERM, timeout: float = 60) -> tuple[str, str]:
        """Send ``sig`` and wait for the exit: (stdout, stderr) as far as they were piped."""
        self.proc.send_signal(sig)
        out, err = self.proc.communicate(timeout=timeout)
        return out or "", err or ""


@contextlib.contextmanager
def daemon_process(args: Sequence[str], directory: Path, *, name: str = "notify",
                   env: dict[str, str] | None = None, stdout: Any = subprocess.PIPE,
                   stderr: Any = subprocess.PIPE) -> Iterator[DaemonProcess]:
    """``python -m canrls ARGS`` with a ``NOTIFY_SOCKET`` named ``name`` in ``directory``
    (and ``env`` over the environment); on exit killed if still running, its pipes and
    the socket closed, so no test leaves a daemon or a descriptor behind."""
    sock, addr = notify_socket(directory, name)
    proc = subprocess.Popen([sys.executable, "-m", "canrls", *args],
                            env=dict(os.environ, NOTIFY_SOCKET=addr, **(env or {})),
                            stdout=stdout, stderr=stderr, text=True)
    try:
        yield DaemonProcess(proc, sock)
    finally:
        if proc.poll() is None:
            proc.kill()
        proc.communicate()
        sock.close()


def reloaded_daemon(directory: Path, conf: Path, texts: Sequence[str]
                    ) -> tuple[int, str, str]:
    """``canrls run -C conf --json`` (:func:`daemon_process`): once it is ready, each of
    ``texts`` written to ``conf`` and a SIGHUP sent (the next waits for READY=1 again),
    then SIGTERM; returns (exit status, stdout, stderr)."""
    with daemon_process(["--log-level", "INFO", "run", "-C", str(conf), "--json"],
                        directory) as d:
        d.wait_ready()
        for text in texts:
            conf.write_text(text)
            d.send(signal.SIGHUP)
            assert "READY=1" in d.notifications("READY=1", 30)[-1]
        out, err = d.stop()
    return d.proc.returncode, out, err
