"""``canrls run`` of a machine with ``[history]``: each axis's snapshots stored under the
drive ``DRIVE.AXIS`` and the model key ``canrls fleet ingest`` gives that axis of a
machine's log; a real SIGHUP to the daemon's process adds and removes an axis, and a
``[history]`` a start would refuse is refused by the reload too."""

from __future__ import annotations

import dataclasses
import json
import os
import signal
import time
from pathlib import Path

import pytest
from daemon_tool import daemon_process

from canrls.fleet.history import History
from canrls.fleet.ingest import JobConfig, model_key, model_key_of
from canrls.processor.config import Overrides, load_config

pytest.importorskip("sqlalchemy")


def _machine(db: Path, axes: dict[str, int], history: str = "") -> str:
    text = (f'[model]\nkt = 0.1\n[daemon]\npublish_interval = 0.05\n'
            f'[history]\nurl = "{db}"\ndrive = "press"\ninterval = 0.3\n{history}')
    for name, k in axes.items():
        # own frames fixed per axis: an axis added later never meets a running one's
        text += (f'[[axes]]\nname = "{name}"\nids = "offset:{k * 0x10:#x}"\n'
                 f'own = "offset:{k * 0x40:#x}"\n')
    return text


def _drives(db: Path) -> dict[str, list]:
    h = History.open(str(db))
    try:
        out: dict[str, list] = {}
        for r in h.recordings():
            out.setdefault(r.drive, []).append(r)
        return out
    finally:
        h.close()


def _wait(check, timeout: float) -> bool:  # type: ignore[no-untyped-def]
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        try:
            if check():
                return True
        except Exception:  # noqa: BLE001 -- the database not made yet
            pass
        time.sleep(0.2)
    return False


@pytest.mark.slow
def test_a_machine_stores_each_axis_and_a_sighup_adds_and_removes_one(
        tmp_path: Path) -> None:
    db = tmp_path / "fleet.db"
    conf = tmp_path / "machine.toml"
    conf.write_text(_machine(db, {"a": 0, "b": 1}))
    args = ["--log-level", "INFO", "run", "-C", str(conf), "-i", "canrls-sim", "-c",
            f"hist-{os.getpid()}", "--bus-kwargs", "axes=3", "seed=2", "--json"]
    with daemon_process(args, tmp_path) as d:
        assert _wait(lambda: {"press.a", "press.b"} <= set(_drives(db)), 60), \
            d.proc.poll()
        # b removed, c added: the file read again on a real SIGHUP
        conf.write_text(_machine(db, {"a": 0, "c": 2}))
        d.send(signal.SIGHUP)
        assert _wait(lambda: "press.c" in _drives(db), 60)
        b_count = len(_drives(db)["press.b"])
        # a [history] a start would refuse: the reload refuses it, the axes stay
        conf.write_text(_machine(db, {"a": 0}, history='colour = "red"\n'))
        d.send(signal.SIGHUP)
        time.sleep(1.0)
        out, err = d.stop(timeout=60)
    assert d.proc.returncode == 0, err
    assert sorted(json.loads(out)["axes"]) == ["a", "c"]
    assert "reload: axis b removed" in err and "reload: axis c added" in err
    assert "history.colour = 'red': unknown key" in err
    drives = _drives(db)
    assert sorted(drives) == ["press.a", "press.b", "press.c"]
    assert len(drives["press.b"]) == b_count  # nothing of b after its removal
    assert len({r.session for r in drives["press.a"]}) == 1  # a ran on untouched
    # each axis's key: the one fleet ingest gives that axis of the machine's log
    for name in ("a", "b", "c"):
        full = _machine(db, {"a": 0, "b": 1, "c": 2})
        p = tmp_path / f"all-{name}.toml"
        p.write_text(full)
        job = dataclasses.replace(JobConfig.from_overrides(str(p), Overrides()),
                                  axis_name=name)
        key = model_key(job)[0]
        assert key == model_key_of(load_config(p).axis(name))[0]
        assert {r.model_key for r in drives[f"press.{name}"]} == {key}


def test_one_axis_of_a_machine_is_stored_as_fleet_ingest_stores_it(tmp_path: Path) -> None:
    """``canrls run --axis b`` of a machine (and a machine of one table) appends under
    ``DRIVE.AXIS``, the drive ``fleet ingest`` gives that axis's recordings."""
    from canrls.cli.main import build_parser
    from canrls.cli.run import build_daemon

    db = tmp_path / "fleet.db"
    for axes, pick, drive in (({"a": 0, "b": 1}, ["--axis", "b"], "press.b"),
                              ({"a": 0}, [], "press.a")):
        conf = tmp_path / "machine.toml"
        conf.write_text(_machine(db, axes))
        args = build_parser("run").parse_args(
            ["run", "-C", str(conf), "-i", "virtual", "-c", f"one-{os.getpid()}", *pick])
        d = build_daemon(args)
        try:
            assert d._history is not None
            appender = d._history.append.__self__
            assert appender.settings.drive == drive
        finally:
            d.stop()
            d._history.close()
