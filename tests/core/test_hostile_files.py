"""Hostile files: every file canrls opens is opened one way (``canrls/core/files.py``).

FIFOs and directories where a file is expected, links planted where canrls writes, a
log of one huge line, IDs beyond 29 bits, empty and garbage binary logs, NUL bytes in
paths, DBCs whose numbers or layout cannot be, and the options of ``canrls sim`` and
``canrls run --record``: each is one ``error:`` line naming the file, flag or field and
exit status 1, within bounded time and memory, and nothing outside the test's own
``tmp_path`` is touched (the targets of planted links are files of that directory).
"""

from __future__ import annotations

import logging
import os
import signal
import subprocess
import sys
import time
import tracemalloc
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
from blocking import in_thread, unblock_fifo
from cli_tool import cli_error

from canrls.can.logs import LogReadStats, read_frames
from canrls.cli.main import main
from canrls.core.errors import ConfigError, LogFormatError
from canrls.core.files import (
    MAX_LINE,
    LineBound,
    atomic_writer,
    open_regular,
    read_bytes,
    staged_dir,
)
from canrls.processor.config import read_toml

ROOT = Path(__file__).resolve().parents[2]
DBC = ROOT / "dbc" / "canrls.dbc"
PRECIOUS = b"precious: must never change\n"
TOML = '[model]\neffects = ["inertia", "viscous", "coulomb"]\nkt = 0.1\n'


@pytest.fixture(scope="module")
def log(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("hostile") / "drive.log"
    assert main(["sim", "--out", str(path), "--duration", "2", "--seed", "1"]) == 0
    return path


def _precious(tmp_path: Path) -> Path:
    target = tmp_path / "precious.txt"
    target.write_bytes(PRECIOUS)
    return target


# ------------------------------------------------------------------ not a regular file
@pytest.mark.parametrize("where", ["--dbc", "--config", "log", "validate --model",
                                   "export-c --model"])
def test_a_fifo_where_a_file_is_read_is_refused_without_blocking(
        tmp_path: Path, log: Path, capsys: pytest.CaptureFixture[str], where: str) -> None:
    """Item 15: a FIFO as --dbc, --config, --model or a log hung the command."""
    fifo = tmp_path / {"--dbc": "d.dbc", "--config": "c.toml", "log": "x.log",
                       "validate --model": "m.json", "export-c --model": "m.toml"}[where]
    os.mkfifo(fifo)
    argv = {"--dbc": ["fit", str(log), "--dbc", str(fifo)],
            "--config": ["fit", str(log), "--config", str(fifo)],
            "log": ["fit", str(fifo)],
            "validate --model": ["validate", str(log), "--model", str(fifo)],
            "export-c --model": ["export-c", "--model", str(fifo), "--out",
                                 str(tmp_path / "c")]}[where]
    line = in_thread(lambda: cli_error(capsys, argv), unblock_fifo(fifo), "a FIFO")
    assert f"{fifo.name}: is a FIFO, not a regular file" in line


@pytest.mark.parametrize("where", ["--dbc", "--config", "log"])
def test_a_directory_where_a_file_is_read_is_one_error_line(
        tmp_path: Path, log: Path, capsys: pytest.CaptureFixture[str], where: str) -> None:
    d = tmp_path / {"--dbc": "d.dbc", "--config": "c.toml", "log": "x.log"}[where]
    d.mkdir()
    argv = {"--dbc": ["fit", str(log), "--dbc", str(d)],
            "--config": ["fit", str(log), "--config", str(d)],
            "log": ["fit", str(d)]}[where]
    assert "is a directory, not a regular file" in cli_error(capsys, argv)


def test_sighup_with_the_model_file_a_fifo_keeps_the_daemon_running(
        tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    """Item 7: a SIGHUP while ``[daemon] model_file`` was a FIFO blocked the estimator
    thread for good (checkpoints stopped, SIGTERM no longer stopped the daemon). The
    reload now fails at once, naming the key and the FIFO; the running model stays."""
    from canrls.cli.main import build_parser
    from canrls.cli.run import build_daemon

    model = tmp_path / "model.toml"
    model.write_text(TOML)
    conf = tmp_path / "canrls.toml"
    conf.write_text(f'[daemon]\nmodel_file = "{model.name}"\n')
    args = build_parser("run").parse_args(
        ["run", "-C", str(conf), "-i", "virtual", "-c", f"hostile-{os.getpid()}"])
    d = build_daemon(args)
    model.unlink()
    os.mkfifo(model)
    caplog.set_level(logging.ERROR, logger="canrls")
    d.start()
    try:
        d.request_reload()

        def failed() -> None:
            while not any("reload failed" in r.getMessage() for r in caplog.records):
                time.sleep(0.01)
        in_thread(failed, unblock_fifo(model), "a FIFO")
    finally:
        d.stop()
    msg = next(r.getMessage() for r in caplog.records if "reload failed" in r.getMessage())
    assert f"daemon.model_file = {model}: is a FIFO, not a regular file" in msg
    assert d.stats().reloads == 1 and d.failure is None


def test_the_helpers_refuse_a_fifo_and_bound_the_size(tmp_path: Path) -> None:
    fifo = tmp_path / "f"
    os.mkfifo(fifo)
    with pytest.raises(ConfigError, match="f: is a FIFO"):
        in_thread(lambda: open_regular(fifo, str(fifo)), unblock_fifo(fifo), "a FIFO")
    big = tmp_path / "big.toml"
    big.write_bytes(b"#" * 5000)
    with pytest.raises(ConfigError, match="5000 bytes, more than the 4096"):
        read_bytes(big, str(big), limit=4096)
    with pytest.raises(ConfigError, match="NUL byte"):
        read_toml("a\0b.toml")


# ------------------------------------------------------------------ one huge line
def _peak(fn: Callable[[], Any]) -> int:
    tracemalloc.start()
    try:
        fn()
    finally:
        peak = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
    return peak


@pytest.mark.parametrize("suffix", [".log", ".asc", ".csv"])
def test_one_huge_line_is_refused_in_bounded_memory(tmp_path: Path, suffix: str) -> None:
    """Item 5: a log of one huge line was read with a buffer that doubled without a cap
    (a 256 MB line: 1.06 GB for .log, 2.2 GB through python-can's readers). Now a line
    over MAX_LINE is an error naming the file and the line, read no further."""
    path = tmp_path / f"huge{suffix}"
    head = {".log": b"(1.000000) can0 101#01\n",
            ".asc": b"date Mon Jan 1 00:00:00.000 am 2024\nbase hex  timestamps absolute\n",
            ".csv": b"timestamp,arbitration_id,extended,remote,error,dlc,data\n"}[suffix]
    warm = tmp_path / f"warm{suffix}"  # the reader's code loaded before measuring
    warm.write_bytes(head)
    list(read_frames(warm))
    with path.open("wb") as f:
        f.write(head)
        f.write(b"7" * (32 << 20))
        f.write(b"\n")
    errors: list[str] = []

    def read() -> None:
        try:
            for _ in read_frames(path):
                pass
        except LogFormatError as e:
            errors.append(str(e))

    peak = _peak(read)
    line = head.count(b"\n") + 1
    assert errors and str(path) in errors[0] and f"{line}" in errors[0]
    assert "longer than" in errors[0] and str(MAX_LINE) in errors[0]
    assert peak < 16 << 20, f"{peak / 2**20:.0f} MB for a 32 MB line"


def test_a_long_line_is_skipped_with_skip_bad_lines(tmp_path: Path) -> None:
    path = tmp_path / "long.log"
    path.write_bytes(b"(1.0) can0 101#01\n(" + b"9" * 300_000 + b"\n(2.0) can0 102#02\n")
    st = LogReadStats()
    frames = [b for b in read_frames(path, chunk_size=2, skip_bad_lines=True, stats=st)]
    assert [t for b in frames for t in b.t.tolist()] == [1.0, 2.0]
    assert st.bad_lines == 1 and st.lines == 3
    with pytest.raises(LogFormatError, match=r"long\.log:2: line longer than"):
        list(read_frames(path, chunk_size=2))


def test_line_bound_counts_lines_across_reads(tmp_path: Path) -> None:
    path = tmp_path / "x.txt"
    path.write_bytes(b"a\r\nb\n" + b"c" * 40 + b"\n" + b"d" * 100)
    with open_regular(path, str(path)) as f:
        bound = LineBound(f, "x.txt", max_line=64)
        with pytest.raises(ConfigError, match="x.txt: line 4 is longer than 64 bytes"):
            while bound.read(7):
                pass


# ------------------------------------------------------------------ links where canrls writes
def test_sim_never_writes_through_a_link_at_its_temporary(tmp_path: Path) -> None:
    """Item 6: ``canrls sim`` wrote ``OUT.part`` with ``open(tmp, "wb")``, through a link
    planted there; its temporary is now a fresh name created with O_EXCL|O_NOFOLLOW."""
    target = _precious(tmp_path)
    out = tmp_path / "drive.log"
    (tmp_path / "drive.log.part").symlink_to(target)
    assert main(["sim", "--out", str(out), "--duration", "0.2"]) == 0
    assert target.read_bytes() == PRECIOUS
    assert out.read_bytes().startswith(b"(0.")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["drive.log", "drive.log.part",
                                                           "precious.txt"]


def test_sim_replaces_a_link_at_its_name(tmp_path: Path) -> None:
    target = _precious(tmp_path)
    out = tmp_path / "drive.asc"
    out.symlink_to(target)
    assert main(["sim", "--out", str(out), "--duration", "0.2"]) == 0
    assert target.read_bytes() == PRECIOUS and not out.is_symlink()


def test_save_model_never_writes_through_a_link(tmp_path: Path, log: Path) -> None:
    target = _precious(tmp_path)
    link = tmp_path / "m.json"
    link.symlink_to(target)
    assert main(["fit", str(log), "--save-model", str(link)]) == 0
    assert target.read_bytes() == PRECIOUS and not link.is_symlink()
    assert b'"format": "canrls-model"' in link.read_bytes()


def test_record_never_writes_through_a_link(tmp_path: Path,
                                            capsys: pytest.CaptureFixture[str]) -> None:
    """Item 6: ``canrls run --record LINK`` wrote through the link (python-can opens
    by name); now the link is refused before the daemon starts."""
    target = _precious(tmp_path)
    link = tmp_path / "rec.log"
    link.symlink_to(target)
    line = cli_error(capsys, ["run", "-i", "virtual", "-c", f"rec-{os.getpid()}",
                           "--record", str(link), "--duration", "0.2"])
    assert f"--record {link}: is a symbolic link, not a file canrls may write" in line
    assert target.read_bytes() == PRECIOUS


@pytest.mark.parametrize("case", ["suffix", "no directory", "directory"])
def test_record_is_checked_before_the_daemon_starts(
        tmp_path: Path, capsys: pytest.CaptureFixture[str], case: str) -> None:
    """Item 8: ``run --record`` with an unknown suffix, a missing directory or a
    directory exited 3 (or failed once running); now one error line, exit 1."""
    path = {"suffix": tmp_path / "rec.xyz", "no directory": tmp_path / "no" / "rec.log",
            "directory": tmp_path / "rec.log"}[case]
    if case == "directory":
        path.mkdir()
    line = cli_error(capsys, ["run", "-i", "virtual", "-c", f"rec-{os.getpid()}",
                           "--record", str(path), "--duration", "0.2"])
    assert line.startswith(f"error: --record {path}: ")
    assert {"suffix": "unknown log format '.xyz'",
            "no directory": "No such file or directory",
            "directory": "is a directory"}[case] in line


def test_record_writes_a_log_canrls_reads_back(tmp_path: Path) -> None:
    rec = tmp_path / "rec.asc"
    conf = tmp_path / "c.toml"
    conf.write_text(f'[daemon]\nrecord = "{rec.name}"\n')
    assert main(["run", "-C", str(conf), "-i", "canrls-sim", "-c", "standard",
                 "--duration", "1"]) == 0
    assert sum(len(b) for b in read_frames(rec)) > 0


def test_export_c_out_an_existing_file_is_refused(tmp_path: Path,
                                                  capsys: pytest.CaptureFixture[str]) -> None:
    """Item 8: ``export-c --out FILE`` exited 3 (FileExistsError)."""
    cfg = tmp_path / "drive.toml"
    cfg.write_text(TOML)
    out = _precious(tmp_path)
    line = cli_error(capsys, ["export-c", "--model", str(cfg), "--out", str(out)])
    assert f"--out {out}: exists and is a regular file, not a directory" in line
    assert out.read_bytes() == PRECIOUS


def test_export_c_never_writes_through_a_link_inside_out(tmp_path: Path) -> None:
    """Item 6: a link planted at ``OUT/canrls_config.h`` was written through."""
    cfg = tmp_path / "drive.toml"
    cfg.write_text(TOML)
    target = _precious(tmp_path)
    out = tmp_path / "c"
    out.mkdir()
    (out / "canrls_config.h").symlink_to(target)
    (out / "canrls_fixed.c").mkdir()  # a directory at a name: refused, left alone
    with pytest.raises(ConfigError, match="canrls_fixed.c: is a directory"):
        from canrls.firmware.kernel_export import export_c
        from canrls.firmware.load import load

        src = load(cfg)
        export_c(src.config, out, model=src.model, energy=src.energy, source=src.label)
    (out / "canrls_fixed.c").rmdir()
    assert main(["export-c", "--model", str(cfg), "--out", str(out)]) == 0
    assert target.read_bytes() == PRECIOUS
    assert not (out / "canrls_config.h").is_symlink()
    assert b"CANRLS_MECHANICAL_N" in (out / "canrls_config.h").read_bytes()


def test_atomic_writer_leaves_nothing_on_an_exception(tmp_path: Path) -> None:
    path = tmp_path / "x.bin"
    with pytest.raises(KeyboardInterrupt), atomic_writer(path, "x") as f:
        f.write(b"half")
        raise KeyboardInterrupt
    assert list(tmp_path.iterdir()) == []


def test_a_staged_directory_is_renamed_in_whole_or_not_at_all(tmp_path: Path) -> None:
    """A report's directory: its files appear when the block ends, the page last, a link
    at a name replaced, never written through; an exception leaves it as it was."""
    out = tmp_path / "report"
    with pytest.raises(KeyboardInterrupt), staged_dir(out, "--report") as stage:
        (stage / "a.svg").write_text("figure")
        raise KeyboardInterrupt
    assert list(tmp_path.iterdir()) == []
    outside = tmp_path / "outside"
    outside.write_bytes(PRECIOUS)
    out.mkdir()
    (out / "index.html").symlink_to(outside)
    (out / "old.svg").write_text("kept")
    with staged_dir(out, "--report", last="index.html") as stage:
        assert stage.parent == out  # an existing directory: on its own file system
        for name in ("index.html", "a.svg"):
            (stage / name).write_text(name)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["outside", "report"]
    assert sorted(p.name for p in out.iterdir()) == ["a.svg", "index.html", "old.svg"]
    assert not (out / "index.html").is_symlink() and outside.read_bytes() == PRECIOUS
    assert (out / "index.html").read_text() == "index.html"


def test_sigterm_during_sim_leaves_no_temporary(tmp_path: Path) -> None:
    """Item 14: SIGTERM during ``canrls sim`` left ``OUT.part`` behind."""
    out = tmp_path / "long.log"
    proc = subprocess.Popen([sys.executable, "-m", "canrls", "sim", "--out", str(out),
                             "--duration", "3600"], stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 120
        while not any(p.name.endswith(".part") and p.stat().st_size > 0
                      for p in tmp_path.iterdir()):
            assert proc.poll() is None and time.monotonic() < deadline, "no temporary seen"
            time.sleep(0.05)
        proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    assert proc.returncode == 128 + signal.SIGTERM, err
    assert list(tmp_path.iterdir()) == []


# ------------------------------------------------------------------ canrls sim's options
@pytest.mark.parametrize(("argv", "message"), [
    (["--duration", "1e300"], "--duration: 1e+300 must be a positive number of seconds, "
                              "at most 86400"),
    (["--duration", "nan"], "--duration: nan must be"),
    (["--seed", "-1"], "--seed -1: must be a non-negative integer"),
    (["--channel", "a b"], "--channel 'a b': a channel name in a CAN log is 1 to 64 "
                           "printable ASCII characters without spaces"),
    (["--channel", "ä"], "--channel 'ä': a channel name"),
    (["--start-time", "1e300"], "--start-time 1e+300: the log's times must stay within"),
    (["--out", "x.xyz"], "unknown log format '.xyz'"),
])
def test_sim_options_are_checked_before_anything_is_written(
        tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch,
        bounded_writes: int, argv: list[str], message: str) -> None:
    """Items 14, 18, 8: ``--duration 1e300`` filled the disk, ``--seed -1`` and
    ``--channel ä`` exited 3, ``--channel "a b"`` wrote a log canrls cannot read."""
    monkeypatch.chdir(tmp_path)
    line = cli_error(capsys, ["sim", "--out", str(tmp_path / "x.log"), "--duration", "1",
                           *argv])
    assert message in line
    assert list(tmp_path.iterdir()) == []


def test_a_channel_sim_accepts_is_read_back(tmp_path: Path) -> None:
    out = tmp_path / "x.log"
    assert main(["sim", "--out", str(out), "--duration", "0.2", "--channel", "vcan0/#1"]) == 0
    assert sum(len(b) for b in read_frames(out)) == 400


# ------------------------------------------------------------------ log formats
@pytest.mark.parametrize("suffix", [".asc", ".csv"])
def test_an_id_beyond_29_bits_is_refused_naming_the_frame(
        tmp_path: Path, capsys: pytest.CaptureFixture[str], suffix: str) -> None:
    """Item 8: an ``.asc``/``.csv`` frame with an ID above 32 bits exited 3."""
    path = tmp_path / f"x{suffix}"
    if suffix == ".asc":
        path.write_text("date Sat Nov 28 17:00:11.938 2026\nbase hex  timestamps absolute\n"
                        "internal events logged\n"
                        "Begin Triggerblock Thu Jan 01 00:00:00.0 1970\n"
                        " 0.001000 1  101             Rx   d 1 01\n"
                        " 0.002000 1  123456789x      Rx   d 1 02\n")
    else:
        path.write_text("timestamp,arbitration_id,extended,remote,error,dlc,data\n"
                        "0.001,0x101,0,0,0,1,AQ==\n0.002,0x123456789,1,0,0,1,Ag==\n")
    line = cli_error(capsys, ["fit", str(path)])
    assert f"{path}: frame 2 has the ID 0x123456789, not a CAN ID (at most 29 bits" in line


@pytest.mark.parametrize("content", [b"", bytes(200), b"LOGG\x04\x00\x00\x00"],
                         ids=["empty", "zeros", "short-header"])
def test_an_empty_or_garbage_blf_is_one_error_line(
        tmp_path: Path, capsys: pytest.CaptureFixture[str], content: bytes) -> None:
    """Item 8: an empty or garbage ``.blf`` exited 3."""
    path = tmp_path / "x.blf"
    path.write_bytes(content)
    assert str(path) in cli_error(capsys, ["fit", str(path)])


@pytest.mark.parametrize("key", ["can.dbc", "daemon.record", "daemon.checkpoint",
                                 "daemon.model_file"])
def test_a_nul_byte_in_a_path_of_the_configuration(
        tmp_path: Path, log: Path, capsys: pytest.CaptureFixture[str], key: str) -> None:
    """Item 8: a NUL byte in a path in TOML exited 3 (ValueError: embedded null byte)."""
    table, name = key.split(".")
    conf = tmp_path / "c.toml"
    conf.write_text(f'[{table}]\n{name} = "a\\u0000b"\n')
    argv = (["fit", str(log), "--config", str(conf)] if table == "can" else
            ["run", "-C", str(conf), "-i", "virtual", "-c", "nul", "--duration", "0.2"])
    line = cli_error(capsys, argv)
    assert key in line and "NUL byte" in line


# ------------------------------------------------------------------ DBC numbers and layout
def _dbc(tmp_path: Path, old: str, new: str) -> Path:
    text = DBC.read_text()
    assert old in text
    path = tmp_path / "drive.dbc"
    path.write_text(text.replace(old, new, 1))
    return path


@pytest.mark.parametrize(("old", "new", "message"), [
    ("SG_ Current : 16|24@1- (0.0001,0)", "SG_ Current : 16|24@1- (0,0)",
     "message DriveCurrent: signal Current: scale 0"),
    ("SG_ Current : 16|24@1- (0.0001,0) [-800|800]",
     "SG_ Current : 16|24@1- (1e308,0) [-800|800]",
     "message DriveCurrent: signal Current: scale 1e+308 and offset 0 put the raw values "
     "-8388608..8388607 beyond"),
    ("SG_ Speed : 16|24@1- (0.0001,0)", "SG_ Speed : 16|24@1- (0.0001,1e999)",
     "message DriveSpeed: signal Speed: offset inf is not a finite number"),
    ("SG_ Current : 16|24@1-", "SG_ Current : 999999|24@1-",
     "message DriveCurrent: signal Current: start bit 999999 and length 24 do not fit"),
    ("SG_ Current : 16|24@1-", "SG_ Current : 16|999999999@1-",
     "message DriveCurrent: signal Current: start bit 16 and length 999999999 do not fit"),
    ("BO_ 257 DriveCurrent: 8 Drive", "BO_ 257 DriveCurrent: 99999999 Drive",
     "message DriveCurrent: 99999999 bytes long, a CAN frame carries at most 64"),
    # issue 30: reported as "message never occurs" although it occurs 5,000 times
    ("SG_ Current : 16|24@1- (0.0001,0) [-800|800]",
     "SG_ Current : 16|24@1- (0.0001,0) [800|-800]",
     "DriveCurrent.Current (mapped to current): minimum 800 > maximum -800"),
], ids=["scale-0", "scale-1e308", "offset-inf", "start-bit", "length", "message-length",
        "minimum-above-maximum"])
def test_a_dbc_whose_numbers_cannot_be_is_refused_naming_message_and_signal(
        tmp_path: Path, log: Path, capsys: pytest.CaptureFixture[str], old: str, new: str,
        message: str) -> None:
    """Items 16, 8, 9: a current scale of 0 gave every parameter 0 +- 0 and exit 0; a
    scale of 1e308 exited 3; a start bit of 999999 cost 106 s of CPU in cantools'
    strict check, a length of 1e9 74 s and 3.2 GB in its codec. Now each is refused
    (the layout on cantools' tokens, before cantools builds anything)."""
    dbc = _dbc(tmp_path, old, new)
    line = cli_error(capsys, ["fit", str(log), "--dbc", str(dbc)])
    assert str(dbc) in line and message in line
