"""``canrls fleet`` under attack: schedulers that never answer or answer garbage, worker
counts beyond the machine, link loops under ``**``, one log under two drives, passwords
in URLs, damaged histories, concurrent creators of a new history, a read-only history,
a reader of the output that goes away (issue 30). Every case in its own temporary
directory, every wait bounded."""

from __future__ import annotations

import asyncio
import contextlib
import csv
import json
import multiprocessing
import os
import shutil
import signal
import socket
import sqlite3
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

pytest.importorskip("distributed")
pytest.importorskip("sqlalchemy")
pytest.importorskip("alembic")

from postgres import postgres_server  # noqa: E402

from canrls.cli.main import main  # noqa: E402
from canrls.core.errors import ConfigError, StallError  # noqa: E402
from canrls.fleet import cluster  # noqa: E402
from canrls.fleet import ingest as ingest_module  # noqa: E402
from canrls.fleet.cluster import dask_client, max_workers  # noqa: E402
from canrls.fleet.history import NOT_A_HISTORY, History, HistoryURL  # noqa: E402
from canrls.fleet.ingest import JobConfig, ingest  # noqa: E402
from canrls.fleet.records import ParameterValue, Recording  # noqa: E402
from canrls.fleet.sources import MAX_CELL, LogSource, from_manifest, from_pattern  # noqa: E402
from canrls.sim.fleet_plan import FLEET_EFFECTS, FLEET_KT, make_fleet, write_recording  # noqa: E402

_STORE_ADD = ingest_module._Store.add
CONFIG = JobConfig(effects=FLEET_EFFECTS, kt=FLEET_KT)
MODEL_ARGS = ["--effects", FLEET_EFFECTS, "--kt", str(FLEET_KT), "--quiet"]
#: the bound of every wait in these tests [s]: far beyond the 1 s timeouts they set
BOUND = 60.0


@pytest.fixture(scope="module")
def logs(tmp_path_factory: pytest.TempPathFactory) -> list[Path]:
    """Three simulated logs of one drive, 3 s each (seed 3)."""
    root = tmp_path_factory.mktemp("logs")
    plan = make_fleet(1, 3, 3.0, seed=3)
    d = plan.drives[0]
    out = []
    for k, r in enumerate(d.recordings):
        out.append(root / f"r{k + 1}.log")
        write_recording(out[-1], d, r, 3.0)
    return out


def _tree(root: Path, logs: list[Path], drives: list[str]) -> None:
    for name in drives:
        (root / name).mkdir(parents=True)
        for k, log in enumerate(logs):
            shutil.copy(log, root / name / f"r{k + 1}.log")


class _Server:
    """A TCP server on 127.0.0.1 that accepts and then says nothing (or ``reply``)."""

    def __init__(self, reply: bytes = b"") -> None:
        self.sock = socket.create_server(("127.0.0.1", 0))
        self.address = f"tcp://127.0.0.1:{self.sock.getsockname()[1]}"
        self.reply = reply
        self.conns: list[socket.socket] = []
        self.thread = threading.Thread(target=self._serve, daemon=True)
        self.thread.start()

    def _serve(self) -> None:
        while True:
            try:
                c, _ = self.sock.accept()
            except OSError:
                return
            self.conns.append(c)
            if self.reply:
                try:
                    c.sendall(self.reply)
                except OSError:
                    pass

    def close(self) -> None:
        self.sock.shutdown(socket.SHUT_RDWR)
        self.sock.close()
        for c in self.conns:
            c.close()
        self.thread.join(5)


@pytest.fixture
def silent_server() -> Iterator[_Server]:
    s = _Server()
    yield s
    s.close()


def _ingest_argv(logs: Path, db: Path, scheduler: str, *extra: str) -> list[str]:
    """``fleet ingest`` of ``logs/{drive}/*.log`` into ``db`` on ``scheduler``."""
    return ["fleet", "ingest", str(logs / "{drive}" / "*.log"), "--db", str(db),
            "--scheduler", scheduler, *extra, *MODEL_ARGS]


def _bounded_main(argv: list[str], bound: float = BOUND) -> int:
    """``main(argv)`` in a thread, failing the test if it has not returned in ``bound`` s."""
    out: list[int] = []
    t = threading.Thread(target=lambda: out.append(main(argv)), daemon=True)
    t.start()
    t.join(bound)
    assert not t.is_alive(), f"canrls {' '.join(argv)} still waiting after {bound:g} s"
    return out[0]


# ------------------------------------------------------------------ the scheduler
def test_a_scheduler_that_accepts_and_never_answers_is_named_within_the_timeout(
        tmp_path: Path, silent_server: _Server, monkeypatch: pytest.MonkeyPatch,
        capsys: pytest.CaptureFixture[str]) -> None:
    (tmp_path / "d1").mkdir()
    (tmp_path / "d1" / "a.log").write_text("")
    monkeypatch.setattr(cluster, "SCHEDULER_TIMEOUT", 1.0)
    t0 = time.monotonic()
    rc = _bounded_main(_ingest_argv(tmp_path, tmp_path / "h.db", silent_server.address))
    err = capsys.readouterr().err
    assert rc == 1 and time.monotonic() - t0 < 20
    assert err.startswith(f"error: --scheduler {silent_server.address}: no answer within 1 s")
    assert err.count("\n") == 1


def test_a_scheduler_answering_garbage_is_named(tmp_path: Path,
                                                capsys: pytest.CaptureFixture[str]) -> None:
    server = _Server(b"HTTP/1.1 200 OK\r\n\r\n" + b"garbage" * 1000)
    try:
        with pytest.raises(ConfigError, match="does not answer as a Dask scheduler"):
            with dask_client(server.address, timeout=1.0):
                pass
    finally:
        server.close()


@pytest.mark.parametrize("address", ["garbage", "http://127.0.0.1:8786", "tcp://[::1",
                                     "tcp://127.0.0.1:0", "tcp://127.0.0.1:99999",
                                     "tcp://[zz]:8786", "tcp://a b:8786"])
def test_a_bad_scheduler_address_is_refused_before_anything(
        tmp_path: Path, capsys: pytest.CaptureFixture[str], address: str) -> None:
    (tmp_path / "d1").mkdir()
    (tmp_path / "d1" / "a.log").write_text("")
    rc = _bounded_main(["fleet", "ingest", str(tmp_path / "{drive}" / "*.log"), "--db",
                        str(tmp_path / "h.db"), "--scheduler", address, *MODEL_ARGS])
    err = capsys.readouterr().err
    assert rc == 1 and err.startswith(f"error: --scheduler {address!r}: ")
    assert err.count("\n") == 1
    assert not (tmp_path / "h.db").exists()  # refused before the history is made


@pytest.fixture(scope="module")
def idle_scheduler() -> Iterator[str]:
    """A Dask scheduler without a worker (in this process)."""
    import distributed

    with distributed.LocalCluster(n_workers=0, processes=False, protocol="tcp", host="127.0.0.1",
                                  dashboard_address="127.0.0.1:0") as c:
        yield c.scheduler_address


def test_a_scheduler_without_workers_is_named_within_the_timeout(idle_scheduler: str) -> None:
    t0 = time.monotonic()
    with pytest.raises(ConfigError, match=f"--scheduler {idle_scheduler}: no worker joined "
                                          f"its cluster within 1 s"):
        with dask_client(idle_scheduler, timeout=1.0):
            pass
    assert time.monotonic() - t0 < 20


class _RemoteCluster:
    """A Dask scheduler and one worker (without a nanny: the worker is the process) in
    subprocesses on 127.0.0.1, each of which a test may freeze (SIGSTOP)."""

    def __init__(self, root: Path) -> None:
        info = root / "scheduler.json"
        quiet = {"stdout": subprocess.DEVNULL, "stderr": subprocess.DEVNULL, "cwd": root}
        self.procs: list[subprocess.Popen[bytes]] = []
        self.scheduler = self._start([
            "distributed.cli.dask_scheduler", "--host", "127.0.0.1", "--port", "0",
            "--no-dashboard", "--scheduler-file", str(info)], quiet)
        end = time.monotonic() + BOUND
        while not info.is_file() or not info.read_text().strip().endswith("}"):
            assert time.monotonic() < end and self.scheduler.poll() is None, "no scheduler"
            time.sleep(0.1)
        self.address: str = json.loads(info.read_text())["address"]
        # the worker imports the ingest as it starts (not in the first task, which a
        # short stall limit would count), and has joined before a test begins
        self.worker = self._start([
            "distributed.cli.dask_worker", self.address, "--no-nanny", "--nthreads", "1",
            "--host", "127.0.0.1", "--no-dashboard", "--preload", "canrls.fleet.ingest"],
            quiet)
        while not asyncio.run(cluster._identity(self.address, BOUND)).get("workers"):
            assert time.monotonic() < end and self.worker.poll() is None, "no worker"
            time.sleep(0.1)

    def _start(self, argv: list[str], kw: dict[str, Any]) -> subprocess.Popen[bytes]:
        self.procs.append(subprocess.Popen([sys.executable, "-m", *argv], **kw))
        return self.procs[-1]

    def close(self) -> None:
        for p in self.procs:
            if p.poll() is None:
                os.kill(p.pid, signal.SIGCONT)
                p.kill()
            p.wait(BOUND)


@pytest.fixture
def remote_cluster(tmp_path: Path) -> Iterator[_RemoteCluster]:
    (tmp_path / "cluster").mkdir()
    c = _RemoteCluster(tmp_path / "cluster")
    try:
        yield c
    finally:
        c.close()


@pytest.fixture(scope="module")
def eight_logs(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Eight simulated logs of one drive, 3 s each (seed 8), under ``DIR/d1/``."""
    root = tmp_path_factory.mktemp("eight")
    plan = make_fleet(1, 8, 3.0, seed=8)
    d = plan.drives[0]
    (root / "d1").mkdir()
    for k, r in enumerate(d.recordings):
        write_recording(root / "d1" / f"r{k + 1}.log", d, r, 3.0)
    return root


def test_a_scheduler_that_freezes_after_its_identity_is_named_within_the_timeout(
        tmp_path: Path, remote_cluster: _RemoteCluster, eight_logs: Path,
        monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]) -> None:
    probe = cluster._probe

    def probe_then_freeze(address: str, timeout: float) -> None:
        probe(address, timeout)
        os.kill(remote_cluster.scheduler.pid, signal.SIGSTOP)

    monkeypatch.setattr(cluster, "_probe", probe_then_freeze)
    monkeypatch.setattr(cluster, "SCHEDULER_TIMEOUT", 1.0)
    t0 = time.monotonic()
    rc = _bounded_main(_ingest_argv(eight_logs, tmp_path / "h.db", remote_cluster.address),
                       bound=30.0)
    err = capsys.readouterr().err
    assert rc == 1 and time.monotonic() - t0 < 20
    assert err == (f"error: --scheduler {remote_cluster.address}: no handshake within 1 s "
                   f"(a scheduler that answered, then stopped)\n")


def test_a_scheduler_that_freezes_before_the_first_log_is_named_within_the_timeout(
        tmp_path: Path, remote_cluster: _RemoteCluster, eight_logs: Path,
        monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]) -> None:
    """Connected, then frozen before any log is sent: the question of how many tasks its
    workers run at once is bounded too."""
    real = ingest_module.ingest

    def freeze_then_ingest(*args: Any, **kw: Any) -> Any:
        os.kill(remote_cluster.scheduler.pid, signal.SIGSTOP)
        return real(*args, **kw)

    monkeypatch.setattr(ingest_module, "ingest", freeze_then_ingest)
    monkeypatch.setattr(cluster, "SCHEDULER_TIMEOUT", 2.0)
    monkeypatch.setattr(cluster, "STALL_TIMEOUT", 2.0)
    try:
        t0 = time.monotonic()
        rc = _bounded_main(_ingest_argv(eight_logs, tmp_path / "h.db",
                                        remote_cluster.address), bound=30.0)
        err = capsys.readouterr().err
        assert rc == 1 and time.monotonic() - t0 < 20, err
        assert err.startswith(f"error: the Dask scheduler at {remote_cluster.address}: no "
                              f"answer within 2 s when asked for its workers (")
        assert err.endswith("0 of the 8 logs to fit stored, each kept: run again for the "
                            "rest\n") and err.count("\n") == 1
    finally:
        os.kill(remote_cluster.scheduler.pid, signal.SIGCONT)


def _freeze_after_first_store(monkeypatch: pytest.MonkeyPatch, pid: int) -> None:
    """SIGSTOP process ``pid`` as the ingest stores its first result."""
    add = ingest_module._Store.add

    def add_then_freeze(self: Any, rec: Recording) -> None:
        add(self, rec)
        os.kill(pid, signal.SIGSTOP)  # again for a result that was on its way: harmless

    monkeypatch.setattr(ingest_module._Store, "add", add_then_freeze)


def _stored(db: Path) -> int:
    with History.open(str(db)) as h:
        return len(h.recordings())


@pytest.mark.parametrize("frozen", ["worker", "scheduler"])
def test_a_cluster_that_freezes_mid_ingest_ends_naming_it_and_keeps_each_stored_log(
        tmp_path: Path, remote_cluster: _RemoteCluster, eight_logs: Path, frozen: str,
        monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]) -> None:
    proc = getattr(remote_cluster, frozen)
    _freeze_after_first_store(monkeypatch, proc.pid)
    monkeypatch.setattr(cluster, "SCHEDULER_TIMEOUT", 2.0)
    monkeypatch.setattr(cluster, "STALL_TIMEOUT", 4.0)
    db = tmp_path / "h.db"
    argv = _ingest_argv(eight_logs, db, remote_cluster.address)
    t0 = time.monotonic()
    rc = _bounded_main(argv, bound=60.0)
    err = capsys.readouterr().err
    assert rc == 1 and time.monotonic() - t0 < 45, err
    n = _stored(db)
    assert 1 <= n < 8
    assert err == (f"error: the Dask scheduler at {remote_cluster.address}: no result within "
                   f"4 s (it or its workers stopped answering); {n} of the 8 logs to fit "
                   f"stored, each kept: run again for the rest\n")
    # thawed, a rerun stores the rest, each once
    os.kill(proc.pid, signal.SIGCONT)
    monkeypatch.setattr(ingest_module._Store, "add", _STORE_ADD)
    assert _bounded_main([*argv, "--json"], bound=60.0) == 0
    got = json.loads(capsys.readouterr().out)
    assert (got["stored"], got["skipped"]) == (8 - n, n)
    assert _stored(db) == 8


def test_the_stall_limit_is_a_flag(tmp_path: Path, remote_cluster: _RemoteCluster,
                                   eight_logs: Path, monkeypatch: pytest.MonkeyPatch,
                                   capsys: pytest.CaptureFixture[str]) -> None:
    _freeze_after_first_store(monkeypatch, remote_cluster.worker.pid)
    rc = _bounded_main(_ingest_argv(eight_logs, tmp_path / "h.db", remote_cluster.address,
                                    "--stall-timeout", "3.5"), bound=60.0)
    err = capsys.readouterr().err
    assert rc == 1 and ": no result within 3.5 s (" in err and err.count("\n") == 1


@pytest.fixture(scope="module")
def dask_offload_thread() -> None:
    """Dask's one process-wide offload thread, started before the test that first uses it
    (closing a cluster whose worker is frozen does): it never ends, and is no leak."""
    from distributed.utils import _offload_executor

    _offload_executor.submit(int).result()


def test_a_local_worker_that_freezes_ends_the_ingest_and_its_cluster(
        tmp_path: Path, eight_logs: Path, monkeypatch: pytest.MonkeyPatch,
        dask_offload_thread: None) -> None:
    raised: list[BaseException] = []
    pids: list[int] = []

    def run() -> None:
        try:
            with dask_client(None, 1) as client, History.open(str(tmp_path / "h.db")) as h:
                pids.extend(client.run(os.getpid).values())
                _freeze_after_first_store(monkeypatch, pids[0])
                ingest(from_pattern(str(eight_logs / "{drive}" / "*.log")), CONFIG, h,
                       client=client, stall_timeout=4.0)
        except BaseException as e:
            raised.append(e)

    t = threading.Thread(target=run, daemon=True)
    t.start()
    t.join(BOUND)
    try:
        assert not t.is_alive(), f"the ingest on a local cluster still waiting after {BOUND:g} s"
        assert len(raised) == 1 and isinstance(raised[0], StallError), raised
        n = _stored(tmp_path / "h.db")
        assert 1 <= n < 8 and f"; {n} of the 8 logs to fit stored" in str(raised[0])
    finally:
        for pid in pids:
            with contextlib.suppress(ProcessLookupError):
                os.kill(pid, signal.SIGCONT)


# ------------------------------------------------------------------ workers
def test_workers_beyond_the_cores_and_open_files_are_refused(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
        capsys: pytest.CaptureFixture[str]) -> None:
    import distributed

    def refuse(*args: Any, **kw: Any) -> None:
        raise AssertionError(f"a LocalCluster of {kw.get('n_workers')} workers started")

    monkeypatch.setattr(distributed, "LocalCluster", refuse)  # the code before: 10,000
    (tmp_path / "d1").mkdir()
    (tmp_path / "d1" / "a.log").write_text("")
    rc = main(["fleet", "ingest", str(tmp_path / "{drive}" / "*.log"), "--db",
               str(tmp_path / "h.db"), "--workers", "10000", *MODEL_ARGS])
    err = capsys.readouterr().err
    top = max_workers()
    assert rc == 1 and err == (f"error: --workers 10000: at most {top} here "
                               f"({cluster.WORKERS_PER_CORE} per core of {os.cpu_count()}, "
                               f"within the open-file limit)\n")
    assert not (tmp_path / "h.db").exists()
    # the open-file limit bounds it too: 1024 files leave room for 60 workers
    assert max_workers(cores=64, open_files=1024) == 60
    assert max_workers(cores=2, open_files=1 << 20) == 2 * cluster.WORKERS_PER_CORE
    assert max_workers(cores=2, open_files=10) == 1


def test_max_order_is_checked_up_front(tmp_path: Path,
                                       capsys: pytest.CaptureFixture[str]) -> None:
    (tmp_path / "d1").mkdir()
    (tmp_path / "d1" / "a.log").write_text("")
    for k in ("1000000000", "0", "-3"):
        with pytest.raises(SystemExit) as e:
            main(["fleet", "ingest", str(tmp_path / "{drive}" / "*.log"), "--db",
                  str(tmp_path / "h.db"), "--workers", "0", "--rank", "all",
                  "--max-order", k, *MODEL_ARGS])
        assert e.value.code == 2
        assert f"argument --max-order: '{k}' must be in 1..256" in capsys.readouterr().err
    assert not (tmp_path / "h.db").exists()


# ------------------------------------------------------------------ which logs
def test_double_star_over_link_loops_ends_and_finds_each_log_once(tmp_path: Path) -> None:
    root = tmp_path / "plant"
    for d in ("d1", "d2"):
        (root / "a" / d).mkdir(parents=True)
        (root / "a" / d / "x.log").write_text("")
    (root / "a" / "d1" / "up").symlink_to("..")        # a loop
    (root / "a" / "d2" / "top").symlink_to("../..")    # another
    (root / "b").symlink_to("a")                        # two ways to one directory
    code = ("import json, sys; from canrls.fleet.sources import from_pattern; "
            "print(json.dumps([(s.path, s.drive) for s in from_pattern(sys.argv[1])]))")
    try:
        got = subprocess.run([sys.executable, "-c", code, str(root / "**" / "{drive}" /
                                                              "*.log")],
                             capture_output=True, text=True, timeout=BOUND, check=True)
    except subprocess.TimeoutExpired:
        pytest.fail(f"'**' over two link loops still walking after {BOUND:g} s")
    found = json.loads(got.stdout)
    assert found == [[str(root / "a" / "d1" / "x.log"), "d1"],
                     [str(root / "a" / "d2" / "x.log"), "d2"]]


def test_a_class_in_a_pattern_matches_as_the_shell_does(tmp_path: Path) -> None:
    for d in ("d1", "d2"):
        (tmp_path / d).mkdir()
        for k in range(1, 7):
            (tmp_path / d / f"r{k}.log").write_text("")
    (tmp_path / "d1" / ".r1.log").write_text("")
    got = from_pattern(str(tmp_path / "{drive}" / "r[1-4].log"))
    assert [(Path(s.path).name, s.drive) for s in got] == [
        (f"r{k}.log", d) for d in ("d1", "d2") for k in range(1, 5)]
    got = from_pattern(str(tmp_path / "{drive}" / "r[!1-4].log"))
    assert [Path(s.path).name for s in got] == ["r5.log", "r6.log"] * 2
    # a name starting with a dot only where the pattern says so, as the shell's glob
    assert [Path(s.path).name for s in from_pattern(str(tmp_path / "{drive}" / "*"))
            ].count(".r1.log") == 0
    assert [Path(s.path).name for s in from_pattern(str(tmp_path / "{drive}" / ".*"))
            ] == [".r1.log"]


def test_a_directory_with_a_bad_name_is_an_error_row_the_rest_is_ingested(
        tmp_path: Path, logs: list[Path], capsys: pytest.CaptureFixture[str]) -> None:
    _tree(tmp_path / "plant", logs[:1], ["d1", "bad name"])
    db = tmp_path / "h.db"
    argv = ["fleet", "ingest", str(tmp_path / "plant" / "{drive}" / "*.log"), "--db",
            str(db), "--workers", "0", *MODEL_ARGS]
    assert main(argv) == 0
    out = capsys.readouterr().out
    assert out.startswith("2 logs: 1 stored, 0 already in the history, 1 errors")
    assert (f"  error: {tmp_path / 'plant' / 'bad name' / 'r1.log'}: drive 'bad name': must "
            f"be 1 to 128 letters") in out
    with History.open(db) as h:
        assert [r.drive for r in h.recordings()] == ["d1"]


def test_a_manifest_with_a_byte_order_mark_reads(tmp_path: Path) -> None:
    (tmp_path / "x.log").write_text("")
    m = tmp_path / "m.csv"
    m.write_bytes("\ufeffpath,drive,type\r\nx.log,d1,servo\r\n".encode())
    got = from_manifest(m)
    assert [(s.path, s.drive, s.drive_type) for s in got] == [
        (str(tmp_path / "x.log"), "d1", "servo")]


@pytest.mark.parametrize("column", ["path", "drive", "type", "dbc", "effects", "kt",
                                    "signals"])
def test_a_huge_manifest_field_gives_a_short_error_line(
        tmp_path: Path, column: str, capsys: pytest.CaptureFixture[str]) -> None:
    (tmp_path / "x.log").write_text("")
    cells = {"path": "x.log", "drive": "d1", column: "y" * 100_000}
    m = tmp_path / "m.csv"
    with open(m, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(cells))
        w.writeheader()
        w.writerow(cells)
    assert main(["fleet", "ingest", "--manifest", str(m), "--db", str(tmp_path / "h.db"),
                 "--workers", "0", *MODEL_ARGS]) == 1
    err = capsys.readouterr().err
    assert err == (f"error: {m}: line 2: field {column!r}: 100000 characters (at most "
                   f"{MAX_CELL})\n")


def test_one_log_under_two_drives_is_stored_once_under_the_first_listed(
        tmp_path: Path, logs: list[Path]) -> None:
    shutil.copy(logs[0], tmp_path / "a.log")
    shutil.copy(logs[0], tmp_path / "copy.log")
    shutil.copy(logs[1], tmp_path / "b.log")

    def manifest(name: str, rows: list[tuple[str, str]]) -> Path:
        m = tmp_path / name
        m.write_text("path,drive\n" + "".join(f"{p},{d}\n" for p, d in rows))
        return m

    rows = [("a.log", "d2"), ("b.log", "d2"), ("a.log", "d1"), ("copy.log", "d3")]
    m = manifest("m.csv", rows)
    for run in range(2):  # the owner stays the same on a rerun
        with History.open(tmp_path / "h.db") as h:
            s = ingest(from_manifest(m), CONFIG, h)
            recs = h.recordings()
        assert (s.total, s.already) == (4, 0)
        assert [(d.path, d.drive, d.owner_path, d.owner) for d in s.duplicates] == ([
            (str(tmp_path / "a.log"), "d1", str(tmp_path / "a.log"), "d2"),
            (str(tmp_path / "copy.log"), "d3", str(tmp_path / "a.log"), "d2")]
            if run == 0 else [])
        assert (s.stored, s.skipped) == ((2, 0) if run == 0 else (0, 4))
        assert sorted((r.drive, Path(r.path).name) for r in recs) == [
            ("d2", "a.log"), ("d2", "b.log")]
    with History.open(tmp_path / "h3.db") as h:
        lines = ingest(from_manifest(m), CONFIG, h).format().splitlines()
    assert "2 duplicates" in lines[0] and "stored meanwhile" not in lines[0]
    assert lines[1:3] == [
        f"  duplicate: {tmp_path / 'a.log'} (listed for drive d1) is the same log as "
        f"{tmp_path / 'a.log'}: stored once, under drive d2",
        f"  duplicate: {tmp_path / 'copy.log'} (listed for drive d3) is the same log as "
        f"{tmp_path / 'a.log'}: stored once, under drive d2"]
    # the first listed owns it, whichever it is
    with History.open(tmp_path / "h2.db") as h:
        s = ingest(from_manifest(manifest("m2.csv", rows[::-1])), CONFIG, h)
        assert sorted((r.drive, Path(r.path).name) for r in h.recordings()) == [
            ("d2", "b.log"), ("d3", "copy.log")]
    assert {d.owner for d in s.duplicates} == {"d3"}


@pytest.fixture(scope="module")
def thread_cluster() -> Iterator[Any]:
    """A Dask client of a cluster of one worker thread in this process (a test can patch
    what its tasks call); Dask's own threads started before any test."""
    import distributed

    with distributed.LocalCluster(n_workers=1, processes=False, threads_per_worker=1,
                                  protocol="tcp", host="127.0.0.1",
                                  dashboard_address="127.0.0.1:0") as lc, \
            distributed.Client(lc) as c:
        known = c.scatter([frozenset({"x"})], broadcast=True, hash=False)[0]
        assert c.submit(len, known, pure=False).result() == 1
        yield c


def test_on_a_cluster_each_log_is_read_once_and_the_first_listed_owns_it(
        tmp_path: Path, logs: list[Path], monkeypatch: pytest.MonkeyPatch,
        thread_cluster: Any) -> None:
    """On Dask each log is opened once, by the task that fits it: its hash is taken as
    the fit reads it (a rerun, whose history holds hashes, hashes first and fits
    nothing); duplicates, a path listed twice and a rerun are decided by the hashes
    the tasks return, the first listed owning each content (a cluster of threads in
    this process, so the reads can be counted)."""
    import canrls.can.logs as logs_module

    shutil.copy(logs[0], tmp_path / "a.log")
    shutil.copy(logs[0], tmp_path / "copy.log")
    shutil.copy(logs[1], tmp_path / "b.log")
    reads: list[str] = []
    hash_file = ingest_module.content_hash
    open_log = logs_module.open_regular

    def counted(path: str | Path) -> str:
        reads.append(Path(path).name)
        return hash_file(path)

    def opened(path: Any, *args: Any, **kw: Any) -> Any:
        reads.append(Path(path).name)
        return open_log(path, *args, **kw)

    monkeypatch.setattr(ingest_module, "content_hash", counted)
    monkeypatch.setattr(logs_module, "open_regular", opened)
    m = tmp_path / "m.csv"
    m.write_text("path,drive\ncopy.log,d3\nb.log,d2\na.log,d2\ncopy.log,d3\n")
    for run in range(2):
        reads.clear()
        with History.open(tmp_path / "h.db") as h:
            s = ingest(from_manifest(m), CONFIG, h, client=thread_cluster, stall_timeout=BOUND)
            recs = h.recordings()
        assert sorted(reads) == ["a.log", "b.log", "copy.log"]  # once each
        assert sorted((r.drive, Path(r.path).name) for r in recs) == [
            ("d2", "b.log"), ("d3", "copy.log")]
        assert {r.content_hash for r in recs} == {hash_file(tmp_path / "copy.log"),
                                                  hash_file(tmp_path / "b.log")}
        assert (s.stored, s.skipped, s.failed) == ((2, 0, ()) if run == 0 else
                                                   (0, 4, ()))
        assert [(Path(d.path).name, d.drive, Path(d.owner_path).name, d.owner)
                for d in s.duplicates] == ([("a.log", "d2", "copy.log", "d3"),
                                            ("copy.log", "d3", "copy.log", "d3")]
                                           if run == 0 else [])


def test_results_out_of_listed_order_keep_the_first_listed_as_owner() -> None:
    """A later listed log's fit finishing first neither owns the content nor is stored
    before those listed earlier have arrived."""
    stored: list[str] = []

    class Store:
        def add(self, rec: Recording) -> None:
            stored.append(rec.drive)

    jobs = [ingest_module.IngestJob(source=LogSource(
        f"/x/{d}.log", d), config=CONFIG, key="k", model="m") for d in ("d1", "d2", "d3")]
    recs = [Recording(drive=j.source.drive, content_hash="same" if j.source.drive != "d2"
                      else "other", model_key="k", model="m", path=j.source.path)
            for j in jobs]
    order = ingest_module._InOrder(jobs, Store())  # type: ignore[arg-type]
    order.arrive(2, recs[2])
    assert stored == [] and order.duplicates == []
    order.arrive(1, recs[1])
    assert stored == []
    order.arrive(0, recs[0])
    assert stored == ["d1", "d2"]
    assert [(d.drive, d.owner) for d in order.duplicates] == [("d3", "d1")]


def test_a_task_takes_short_logs_up_to_its_bytes_in_the_listed_order() -> None:
    """Consecutive logs until a task holds TASK_BYTES; a log of that size alone; never
    so many a task that a worker is left without TASKS_PER_WORKER tasks."""
    mb = 1 << 20
    groups = ingest_module.task_groups
    assert ingest_module.TASK_BYTES == 2 * mb and ingest_module.TASKS_PER_WORKER == 4
    # 0.3 MB logs: six to a task (1.8 MB, a seventh would pass 2 MB)
    assert groups([300_000] * 800, 2) == [range(k, min(k + 6, 800))
                                          for k in range(0, 800, 6)]
    assert groups([3 * mb, 100, 100, 3 * mb] + [100] * 36, 1) == [
        range(0, 1), range(1, 3), range(3, 4), range(4, 14), range(14, 24), range(24, 34),
        range(34, 40)]
    # few logs: at most len / (4 x workers) to a task, at least one
    assert groups([100] * 30, 2) == [range(k, min(k + 3, 30)) for k in range(0, 30, 3)]
    assert groups([100] * 5, 2) == [range(k, k + 1) for k in range(5)]
    assert groups([], 2) == []
    assert groups([0] * 64, 0) == [range(k, k + 16) for k in range(0, 64, 16)]  # as one


# ------------------------------------------------------------------ the history
def _recording(k: int) -> Recording:
    return Recording(drive=f"d{k % 7}", drive_type="servo", content_hash=f"{k:064x}",
                     model_key="m" * 64, model="inertia", path=f"r{k}.log",
                     t_start=1e9 + 3600.0 * k, t_end=1e9 + 3600.0 * k + 3, samples=100,
                     residual_rms=0.01, fit_percent=95.0,
                     parameters=(ParameterValue("inertia.J", 2e-4, 1e-7, "kg*m^2"),))


def _history(path: Path, n: int) -> Path:
    with History.open(path) as h:
        h.store([_recording(k) for k in range(n)])
    return path


def _damaged(path: Path, how: str) -> None:
    import random

    if how == "random bytes":
        path.write_bytes(random.Random(30).randbytes(16384))
    elif how in ("truncated", "header only"):
        _history(path, 2000)
        size = path.stat().st_size
        with open(path, "r+b") as f:
            f.truncate(size // 2 if how == "truncated" else 100)
    else:
        with sqlite3.connect(path) as c:
            if how == "no tables":  # versioned, its tables gone
                c.execute("CREATE TABLE alembic_version (version_num VARCHAR(32) NOT NULL)")
                c.execute("INSERT INTO alembic_version VALUES ('0001')")
            else:  # another program's database
                c.execute("CREATE TABLE notes (id INTEGER PRIMARY KEY, text TEXT)")
        c.close()


DAMAGES = ["random bytes", "truncated", "header only", "no tables", "another program's"]


@pytest.mark.parametrize("how", DAMAGES)
@pytest.mark.parametrize("command", ["ingest", "report", "run"])
def test_a_damaged_or_foreign_history_is_one_error_and_left_as_it_was(
        tmp_path: Path, logs: list[Path], capsys: pytest.CaptureFixture[str], how: str,
        command: str) -> None:
    db = tmp_path / "h.db"
    _damaged(db, how)
    before = db.read_bytes()
    if command == "ingest":
        (tmp_path / "d1").mkdir()
        shutil.copy(logs[0], tmp_path / "d1" / "a.log")
        argv = ["fleet", "ingest", str(tmp_path / "{drive}" / "*.log"), "--db", str(db),
                "--workers", "0", *MODEL_ARGS]
    elif command == "report":
        argv = ["fleet", "report", "--db", str(db), "--json"]
    else:
        conf = tmp_path / "canrls.toml"
        conf.write_text(f'[model]\neffects = ["inertia", "viscous", "coulomb"]\n'
                        f'kt = {FLEET_KT}\n[history]\nurl = "{db}"\ndrive = "axis-7"\n')
        argv = ["run", "-C", str(conf), "-i", "canrls-sim", "-c", "fleet-damaged",
                "--bus-kwargs", "seed=2", "realtime=False", "start_time=0",
                "--duration", "1"]
    assert main(argv) == 1
    err = capsys.readouterr().err
    assert err.startswith(f"error: history {db}: {NOT_A_HISTORY} (")
    assert err.count("\n") == 1
    assert db.read_bytes() == before


@pytest.mark.parametrize(("url", "secret"), [
    ("postgresql://alice@127.0.0.1:1/db?password=s3cret&sslmode=disable", "s3cret"),
    ("postgresql://alice:s3cret@127.0.0.1:1/db", "s3cret"),
    ("postgresql://alice:s3cret@127.0.0.1:notaport/db", "s3cret"),
    ("sqlite+pysqlcipher://alice:s3cret@/x.db", "s3cret"),
    ("sqlite+pysqlcipher://:s3cret@/x.db?cipher=aes-256-cfb&kdf_iter=64000", "s3cret"),
])
@pytest.mark.parametrize("command", ["ingest", "report"])
def test_a_password_in_the_url_is_never_echoed(
        tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch,
        url: str, secret: str, command: str) -> None:
    monkeypatch.chdir(tmp_path)
    (tmp_path / "d1").mkdir()
    (tmp_path / "d1" / "a.log").write_text("")
    argv = (["fleet", "ingest", "{drive}/*.log", "--db", url, "--workers", "0", *MODEL_ARGS]
            if command == "ingest" else ["fleet", "report", "--db", url, "--json"])
    assert _bounded_main(argv) == 1
    err = capsys.readouterr().err
    shown = HistoryURL.redact(url)
    assert err.startswith((f"error: history {shown}: ", f"error: --db {shown}: "))
    assert err.count("\n") == 1
    assert secret not in err and "***" in err


def test_redact_hides_every_password_form() -> None:
    redact = HistoryURL.redact
    assert redact("postgresql://alice:pw@h:5/db?sslmode=require&password=x&sslpassword=y"
                  ) == "postgresql://alice:***@h:5/db?sslmode=require&password=***&sslpassword=***"
    assert redact("sqlite+pysqlcipher://:pw@/x.db") == "sqlite+pysqlcipher://:***@/x.db"
    assert redact("postgresql://alice@h/db") == "postgresql://alice@h/db"
    assert redact("/var/lib/fleet.db") == "/var/lib/fleet.db"


@pytest.mark.parametrize("url", ["sqlite://", "sqlite:///:memory:",
                                 "sqlite:///file:x?mode=memory&uri=true"])
def test_an_in_memory_history_is_refused(tmp_path: Path, logs: list[Path], url: str,
                                         capsys: pytest.CaptureFixture[str]) -> None:
    (tmp_path / "d1").mkdir()
    shutil.copy(logs[0], tmp_path / "d1" / "a.log")
    assert main(["fleet", "ingest", str(tmp_path / "{drive}" / "*.log"), "--db", url,
                 "--workers", "0", *MODEL_ARGS]) == 1
    out, err = capsys.readouterr()
    assert out == "" and err == (f"error: history {url}: an in-memory database keeps "
                                 f"nothing (give a file: a path or sqlite:///FILE)\n")


def _ingest_at_once(db: str, sources: list[Any], barrier: Any, q: Any) -> None:
    try:
        barrier.wait(BOUND)
        with History.open(db) as h:
            s = ingest(sources, CONFIG, h)
        q.put((s.stored, s.skipped, s.already, s.errors, ""))
    except BaseException as e:  # the parent reports it
        q.put((0, 0, 0, 0, f"{type(e).__name__}: {e}"))


def test_concurrent_ingests_on_a_new_history_all_succeed(tmp_path: Path,
                                                         logs: list[Path]) -> None:
    """Three to five ``fleet ingest`` at once on a history none has made yet, 20 rounds:
    every run succeeds and each log is stored once (the schema's creation raced: one run
    in six exited 1 with 'table drives already exists')."""
    sources = [s for s in from_pattern(str(logs[0].parent / "{drive}.log"))][:2]
    CONFIG.prepared()  # built once, before the fork
    ctx = multiprocessing.get_context("fork")
    failures = []
    for rnd in range(20):
        n = 3 + rnd % 3
        db = str(tmp_path / f"h{rnd}.db")
        barrier, q = ctx.Barrier(n), ctx.Queue()
        procs = [ctx.Process(target=_ingest_at_once, args=(db, sources, barrier, q))
                 for _ in range(n)]
        for p in procs:
            p.start()
        got = [q.get(timeout=BOUND) for _ in procs]
        for p in procs:
            p.join(BOUND)
        failures += [f"round {rnd}: {g[4]}" for g in got if g[4]]
        if not any(g[4] for g in got):  # each log stored by one run, found by the others
            assert sum(g[0] for g in got) == len(sources)
            assert sum(g[0] + g[1] + g[2] for g in got) == n * len(sources)
        with History.open(db) as h:
            assert sorted(r.path for r in h.recordings()) == sorted(s.path for s in sources)
    assert not failures, failures


def test_a_read_only_history_is_reported(tmp_path: Path) -> None:
    """A history in a directory and a file this user cannot write (root without its
    override of file permissions) is read for the report as it is."""
    setpriv = shutil.which("setpriv")
    if setpriv is None or os.geteuid() != 0:
        pytest.skip("needs root and setpriv to drop the override of file permissions")
    ro = tmp_path / "ro"
    ro.mkdir()
    _history(ro / "h.db", 30)
    (ro / "h.db").chmod(0o444)
    ro.chmod(0o555)
    try:
        got = subprocess.run(
            [setpriv, "--bounding-set=-dac_override,-dac_read_search,-fowner",
             "--inh-caps=-all", sys.executable, "-m", "canrls", "fleet", "report", "--db",
             str(ro / "h.db"), "--json"], capture_output=True, text=True, timeout=BOUND)
    finally:
        ro.chmod(0o755)
    assert got.returncode == 0, got.stderr
    rep = json.loads(got.stdout)
    assert sorted(d["drive"] for d in rep["drives"]) == [f"d{k}" for k in range(7)]
    assert sorted(p.name for p in ro.iterdir()) == ["h.db"]


def test_a_reader_that_goes_away_ends_the_command_quietly(tmp_path: Path) -> None:
    """``canrls fleet report --json | head -1``: the reader closes the pipe before the
    command writes; the command exits as Unix tools do, without a word."""
    db = _history(tmp_path / "h.db", 30)
    r, w = os.pipe()
    os.close(r)  # the reader is gone before the first byte
    try:
        got = subprocess.run([sys.executable, "-m", "canrls", "fleet", "report", "--db",
                              str(db), "--json"], stdout=w, stderr=subprocess.PIPE,
                             text=True, timeout=BOUND)
    finally:
        os.close(w)
    assert got.stderr == "" and got.returncode == 141


def _open_at_once(url: str, barrier: Any, q: Any) -> None:
    try:
        barrier.wait(BOUND)
        with History.open(url) as h:
            h.store([_recording(k) for k in range(3)])
        q.put("")
    except BaseException as e:  # the parent reports it
        q.put(f"{type(e).__name__}: {e}")


def test_concurrent_creators_of_a_postgresql_history_all_succeed() -> None:
    """The PostgreSQL side of the schema's lock (an advisory lock): four processes
    opening a new database at once, 5 rounds, each storing the same three recordings:
    all succeed, each recording once. (The code before passed this too, by a retry
    after the failed creation; this holds the lock that replaced the retry.)"""
    import sqlalchemy as sa

    ctx = multiprocessing.get_context("fork")
    with postgres_server() as pg:
        admin = sa.create_engine(pg, isolation_level="AUTOCOMMIT")
        try:
            failures = []
            for rnd in range(5):
                with admin.connect() as c:
                    c.exec_driver_sql(f"CREATE DATABASE round{rnd}")
                url = pg.replace("/canrls?", f"/round{rnd}?")
                barrier, q = ctx.Barrier(4), ctx.Queue()
                procs = [ctx.Process(target=_open_at_once, args=(url, barrier, q))
                         for _ in range(4)]
                for p in procs:
                    p.start()
                failures += [f"round {rnd}: {m}" for m in
                             (q.get(timeout=BOUND) for _ in procs) if m]
                for p in procs:
                    p.join(BOUND)
                with History.open(url) as h:
                    assert h.count() == 3
        finally:
            admin.dispose()
    assert not failures, failures
