"""``canrls fleet``: a simulated fleet ingested on a real Dask LocalCluster into a real
SQLite file and a real PostgreSQL server, wear found, every recording stored once.

One simulated fleet (50 drives x 10 recordings of 3 s, seed 1; ``canrls.sim.fleet_plan``)
and one LocalCluster of two worker processes serve the whole module: the fleet is
written and ingested on the cluster (the path ``canrls fleet ingest`` takes), the
smaller tests take a few of its drives.
"""

from __future__ import annotations

import csv
import dataclasses
import json
import math
import os
import re
import signal
import sqlite3
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

pytest.importorskip("distributed")
pytest.importorskip("sqlalchemy")
pytest.importorskip("alembic")

from fleet_records import pump_fleet  # noqa: E402
from postgres import postgres_server  # noqa: E402

from canrls.cli.fleet import rank_candidates  # noqa: E402
from canrls.cli.main import main  # noqa: E402
from canrls.core.errors import ConfigError  # noqa: E402
from canrls.fleet import detect  # noqa: E402
from canrls.fleet.cluster import dask_client  # noqa: E402
from canrls.fleet.detect import assess  # noqa: E402
from canrls.fleet.history import History, HistoryURL  # noqa: E402
from canrls.fleet.ingest import JobConfig, ingest, model_key  # noqa: E402
from canrls.fleet.records import (  # noqa: E402
    STATUS_ERROR,
    STATUS_OK,
    CandidateValue,
    ParameterValue,
    Recording,
)
from canrls.fleet.sources import LogSource, from_manifest, from_pattern  # noqa: E402
from canrls.sim.fleet_plan import FLEET_EFFECTS, FLEET_KT, make_fleet, write_recording  # noqa: E402

DRIVES, RECORDINGS, DURATION, SEED = 50, 10, 3.0, 1
CONFIG = JobConfig(effects=FLEET_EFFECTS, kt=FLEET_KT)
MODEL_ARGS = ["--effects", FLEET_EFFECTS, "--kt", str(FLEET_KT)]


@pytest.fixture(scope="module")
def client() -> Iterator[Any]:
    """A LocalCluster of two worker processes, one thread each (as ``canrls fleet
    ingest --workers 2``)."""
    with dask_client(None, 2) as c:
        yield c


@pytest.fixture(scope="module")
def fleet(client: Any, tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    """The fleet written (on the cluster) and ingested into SQLite (on the cluster,
    candidates ranked around residual changes)."""
    root = tmp_path_factory.mktemp("fleet")
    plan = make_fleet(DRIVES, RECORDINGS, DURATION, seed=SEED)
    jobs = [(d, r) for d in plan.drives for r in d.recordings]
    for d in plan.drives:
        (root / d.type / d.name).mkdir(parents=True)
    t0 = time.monotonic()
    futs = client.map(lambda dr: write_recording(root / dr[1].file, dr[0], dr[1], DURATION),
                      jobs, pure=False)
    client.gather(futs)
    t1 = time.monotonic()
    with open(root / "manifest.csv", "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["path", "drive", "type"])
        w.writerows((r.file, d.name, d.type) for d, r in jobs)
    truth = plan.truth()["drives"]
    db = root / "fleet.db"
    with History.open(db) as h:
        summary = ingest(from_manifest(root / "manifest.csv"), CONFIG, h, client=client,
                         rank="auto", ranker=rank_candidates, max_order=16)
        recs = h.recordings()
    print(f"\nthe fleet: {len(jobs)} logs written in {t1 - t0:.1f} s, ingested in "
          f"{summary.elapsed_s:.1f} s ({summary.ranked} ranked)")
    return {"root": root, "db": db, "truth": truth, "summary": summary, "recordings": recs,
            "plan": plan}


def _subset(fleet: dict[str, Any], drives: list[str]) -> list[LogSource]:
    return [s for s in from_manifest(fleet["root"] / "manifest.csv") if s.drive in drives]


# ------------------------------------------------------------------ detection
def _right(alert: detect.Alert, truth: dict[str, Any]) -> bool:
    if truth["class"] == "harmonic":
        return alert.kind == "new effect" and alert.effect == truth["effect"]
    return alert.series == truth["parameter"]


def test_wear_is_found_with_the_right_parameter_and_no_false_alerts(
        fleet: dict[str, Any]) -> None:
    s = fleet["summary"]
    assert (s.total, s.stored, s.errors, s.failed) == (500, 500, 0, ())
    assert s.workers == 2 and len(s.worker_peak_rss) == 2 and s.ranked > 0
    truth = fleet["truth"]
    fa = assess(fleet["recordings"])
    faulty = [d for d, t in truth.items() if t["class"] != "healthy"]
    healthy = [d for d, t in truth.items() if t["class"] == "healthy"]
    assert len(faulty) >= 10 and len(healthy) >= 35
    found = [d for d in faulty if fa.drive(d).headline is not None]
    right = [d for d in found if _right(fa.drive(d).headline, truth[d])]
    false = [d for d in healthy if fa.drive(d).alerts]
    print(f"\nfleet seed {SEED}: {len(found)}/{len(faulty)} faulty drives alerted, "
          f"{len(right)} with the right parameter or effect; {len(false)}/{len(healthy)} "
          f"healthy drives alerted")
    assert len(found) >= 0.95 * len(faulty), [d for d in faulty if d not in found]
    assert right == found, {d: fa.drive(d).headline.message for d in found if d not in right}
    assert len(false) <= 0.01 * len(healthy), {d: fa.drive(d).alerts[0].message for d in false}
    # the drives that need a look come first, with their evidence
    top = [d.drive for d in fa.drives[:len(found)]]
    assert set(top) == set(found)
    a = fa.drive(found[0]).headline
    assert a.evidence and all(math.isfinite(e.value) and e.sigma >= 0 for e in a.evidence)
    # every class is in the fleet and named: a drift of friction, a load change, a new
    # harmonic with its effect, an outlier
    kinds = {truth[d]["class"]: fa.drive(d).headline.kind for d in found}
    assert kinds["load"] == "change" and kinds["harmonic"] == "new effect"
    assert kinds["outlier"] == "outlier" and kinds["friction"] in ("drift", "change")


def test_sigma_alone_understates_the_scatter(fleet: dict[str, Any],
                                            monkeypatch: pytest.MonkeyPatch) -> None:
    """The between-recording scatter is what keeps healthy drives quiet: with each
    recording's sigma alone (tau = 0) and no size that matters, most healthy drives
    would alert."""
    truth = fleet["truth"]
    healthy = [d for d, t in truth.items() if t["class"] == "healthy"]
    monkeypatch.setattr(detect, "estimate_tau", lambda pairs, quantile=0.5: 0.0)
    monkeypatch.setattr(detect, "_own_tau", lambda pairs: 0.0)
    fa = assess(fleet["recordings"], settings=detect.DetectionSettings(
        min_times_usual=1e-9, min_change={k: 0.0 for k in detect.MIN_CHANGE}))
    false = [d for d in healthy if fa.drive(d).alerts]
    assert len(false) > 0.5 * len(healthy)


def test_tau_is_the_scatter_of_normal_differences() -> None:

    rng = np.random.default_rng(3)
    s = rng.uniform(0.005, 0.02, 2001)
    y = rng.normal(0, np.sqrt(s ** 2 + 0.03 ** 2))
    pairs = [(float((y[k + 1] - y[k]) ** 2), float(s[k] ** 2 + s[k + 1] ** 2))
             for k in range(2000)]
    assert detect.estimate_tau(pairs) == pytest.approx(0.03, rel=0.1)
    assert detect.estimate_tau([(1e-6, 1.0)] * 10) == 0.0  # sigma explains it all


# ------------------------------------------------------------------ idempotence
def test_rerun_skips_everything_by_hash(fleet: dict[str, Any], tmp_path: Path) -> None:
    with History.open(fleet["db"]) as h:
        before = h.count()
        s = ingest(_subset(fleet, ["d001", "d002"]), CONFIG, h)
        assert (s.stored, s.skipped, s.errors) == (0, 20, 0)
        assert h.count() == before
        # another model is another recording of the same log
        other = JobConfig(effects="inertia,viscous,coulomb", kt=FLEET_KT)
        s2 = ingest(_subset(fleet, ["d001"]), other, h)
        assert s2.stored == 10 and h.count() == before + 10
        assert len(h.models()) == 2


def test_a_log_listed_twice_is_fitted_once_on_the_cluster(fleet: dict[str, Any],
                                                          client: Any, tmp_path: Path) -> None:
    """On Dask as in this process (tests/test_fault_fleet.py): the same log under a
    second drive is not sent to be fitted, the first listed drive owns it."""
    import dataclasses

    srcs = _subset(fleet, ["d003"])[:3]
    again = dataclasses.replace(srcs[0], drive="d003-again")
    with History.open(tmp_path / "twice.db") as h:
        s = ingest([*srcs, again], CONFIG, h, client=client)
        assert (s.total, s.stored, s.already, len(s.duplicates)) == (4, 3, 0, 1)
        assert (s.duplicates[0].drive, s.duplicates[0].owner) == ("d003-again", "d003")
        assert {r.drive for r in h.recordings()} == {"d003"}


def test_short_logs_go_several_to_a_task_with_the_same_answers(
        fleet: dict[str, Any], client: Any, tmp_path: Path) -> None:
    """On the cluster, short logs (0.3 MB) go several to a task: fewer tasks than logs,
    the progress counting every log once, and every recording as an ingest in this
    process stores it."""
    from distributed import get_task_stream

    sources = _subset(fleet, ["d006", "d007", "d008"])
    seen: list[tuple[int, int]] = []
    with History.open(tmp_path / "c.db") as h, get_task_stream(client) as ts:
        s = ingest(sources, CONFIG, h, client=client,
                   progress=lambda done, total: seen.append((done, total)))
        on_cluster = _rows(h)
    tasks = [t for t in ts.data if t["key"].startswith("ingest_")]
    assert (s.stored, s.errors, s.failed) == (30, 0, ())
    assert 2 <= len(tasks) < len(sources)
    assert [d for d, _ in seen] == sorted(d for d, _ in seen) and seen[-1] == (30, 30)
    with History.open(tmp_path / "p.db") as h:
        ingest(sources, CONFIG, h)
        assert _rows(h) == on_cluster


def test_a_killed_worker_leaves_every_recording_once(fleet: dict[str, Any],
                                                     tmp_path: Path) -> None:
    """A LocalCluster of its own (one worker: its nanny starts it again) whose worker is
    killed mid-ingest; the run goes on, a rerun adds nothing."""
    sources = _subset(fleet, ["d003", "d004", "d005"])
    killed: list[int] = []
    with dask_client(None, 1) as c, History.open(tmp_path / "k.db") as h:
        pids = c.run(os.getpid)

        def kill_one(done: int, total: int) -> None:
            if done >= 5 and not killed:  # a task may take several logs
                pid = sorted(pids.values())[0]
                os.kill(pid, signal.SIGKILL)  # the worker process this test's cluster started
                killed.append(pid)

        s = ingest(sources, CONFIG, h, client=c, progress=kill_one)
        assert killed and set(c.run(os.getpid).values()) != set(pids.values())
        # the task the worker died in ran again on the new worker (or waits for the rerun)
        assert s.stored + len(s.failed) == len(sources) and s.errors == 0
        s2 = ingest(sources, CONFIG, h, client=c)
        assert s2.stored == len(s.failed) and s2.skipped == s.stored
        assert h.count() == len(sources)
    con = sqlite3.connect(tmp_path / "k.db")
    try:
        rows = con.execute("SELECT content_hash, COUNT(*) FROM recordings "
                           "GROUP BY content_hash, model_id").fetchall()
        assert len(rows) == len(sources) and all(n == 1 for _, n in rows)
        paths = {p for (p,) in con.execute("SELECT path FROM recordings")}
        assert paths == {s.path for s in sources}
    finally:
        con.close()


def test_an_interrupted_run_on_an_existing_scheduler_is_finished_by_a_rerun(
        fleet: dict[str, Any], client: Any, tmp_path: Path) -> None:
    """``canrls fleet ingest --scheduler`` (the cluster's address, as with ``dask
    scheduler`` and ``dask worker``) killed mid-run, then run again."""
    manifest = tmp_path / "m.csv"
    drives = ["d007", "d008"]
    with open(manifest, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["path", "drive", "type"])
        w.writerows((s.path, s.drive, s.drive_type) for s in _subset(fleet, drives))
    db = tmp_path / "i.db"
    cmd = [sys.executable, "-m", "canrls", "fleet", "ingest", "--manifest", str(manifest),
           "--db", str(db), "--scheduler", client.scheduler.address, *MODEL_ARGS]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            start_new_session=True)
    try:
        end = time.monotonic() + 120
        n = 0
        while time.monotonic() < end and proc.poll() is None:
            if db.exists():
                try:
                    con = sqlite3.connect(db, timeout=5)
                    n = con.execute("SELECT COUNT(*) FROM recordings").fetchone()[0]
                    con.close()
                except sqlite3.OperationalError:
                    n = 0  # the schema not there yet
                if n >= 3:
                    break
            time.sleep(0.05)
        killed = proc.poll() is None
        if killed:
            os.killpg(proc.pid, signal.SIGKILL)  # the process group this test started
    finally:
        proc.communicate(timeout=60)
    out = subprocess.run(cmd + ["--json", "--quiet"], capture_output=True, text=True,
                         timeout=300)
    assert out.returncode == 0, out.stderr
    res = json.loads(out.stdout)
    total = 10 * len(drives)
    assert res["stored"] + res["skipped"] == total and res["errors"] == 0
    if killed:
        assert res["skipped"] >= 3
    con = sqlite3.connect(db)
    try:
        assert con.execute("SELECT COUNT(*), COUNT(DISTINCT content_hash) FROM recordings"
                           ).fetchone() == (total, total)
    finally:
        con.close()


def test_two_runs_at_once_store_each_recording_once(fleet: dict[str, Any],
                                                    tmp_path: Path) -> None:
    sources = _subset(fleet, ["d011"])
    url = tmp_path / "twice.db"
    History.open(url).close()
    results: list[Any] = []

    def run() -> None:
        with History.open(url) as h:
            results.append(ingest(sources, CONFIG, h))

    threads = [threading.Thread(target=run) for _ in range(2)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(300)
    assert len(results) == 2
    assert sum(r.stored for r in results) == len(sources)
    assert sum(r.stored + r.already + r.skipped for r in results) == 2 * len(sources)
    with History.open(url) as h:
        assert h.count() == len(sources)


# ------------------------------------------------------------------ both databases
def _rows(h: History) -> list[tuple[Any, ...]]:
    return [(r.drive, r.drive_type, r.content_hash, r.status, r.t_start, r.samples,
             r.residual_rms, tuple((p.name, p.value, p.sigma, p.identifiable)
                                   for p in r.parameters)) for r in h.recordings()]


def test_sqlite_and_postgresql_hold_the_same_schema_and_results(
        fleet: dict[str, Any], tmp_path: Path) -> None:
    import sqlalchemy as sa

    sources = _subset(fleet, ["d012", "d013", "d014"])
    bad = tmp_path / "bad.log"
    bad.write_text("this is not a CAN log\n")
    sources.append(LogSource(path=str(bad), drive="d012", drive_type=sources[0].drive_type))
    with postgres_server() as pg:
        out = {}
        for name, url in (("sqlite", str(tmp_path / "s.db")), ("postgresql", pg)):
            with History.open(url) as h:
                assert h.revision() == "0001"
                s = ingest(sources, CONFIG, h)
                assert (s.stored, s.errors) == (30, 1)
                insp = sa.inspect(h.engine)
                schema = {t: sorted((c["name"], type(c["type"]).__name__.lower()
                                     .replace("double_precision", "float")
                                     .replace("double", "float"))
                                    for c in insp.get_columns(t))
                          for t in insp.get_table_names() if t != "alembic_version"}
                uniques = {t: sorted(tuple(u["column_names"])
                                     for u in insp.get_unique_constraints(t))
                           for t in schema}
                out[name] = (schema, uniques, _rows(h),
                             assess(h.recordings()).to_dict()["drives"])
            with History.open(url) as h:  # opened again: at head, nothing migrated
                assert ingest(sources, CONFIG, h).skipped == len(sources)
                err = h.recordings(status=STATUS_ERROR)
                assert len(err) == 1 and str(bad) in (err[0].error or "")
    s_schema, s_uniq, s_rows, s_drives = out["sqlite"]
    p_schema, p_uniq, p_rows, p_drives = out["postgresql"]
    assert {t: [c for c, _ in cols] for t, cols in s_schema.items()} == \
        {t: [c for c, _ in cols] for t, cols in p_schema.items()}
    assert s_uniq["recordings"] == p_uniq["recordings"] == [("content_hash", "model_id")]
    assert s_rows == p_rows
    assert s_drives == p_drives


def _batch_recording(k: int, drive: str) -> Recording:
    """A recording whose every value says which one it is (``k``)."""
    return Recording(drive=drive, drive_type="servo", content_hash=f"{k:064x}",
                     model_key="m" * 64, model="inertia", path=f"r{k}.log",
                     t_start=1e9 + 3600.0 * k, t_end=1e9 + 3600.0 * k + 3, samples=k,
                     parameters=(ParameterValue("inertia.J", float(k), 0.1, "kg*m^2"),
                                 ParameterValue("viscous.B", -float(k), 0.2, "N*m*s")),
                     candidates=(CandidateValue(1, f"cogging{k}", 0.5, -3.0, 0.1, True,
                                                False),))


def test_a_batch_is_stored_in_one_statement_per_table(tmp_path: Path) -> None:
    """``History.store`` sends a batch's recordings, parameters and candidates in one
    statement per table (not three per recording), each row with its own recording's
    values; a content stored before, or listed twice in the batch, is stored once."""
    import sqlalchemy as sa

    drives = [f"d{k}" for k in range(5)]
    with postgres_server() as pg:
        for url in (str(tmp_path / "s.db"), pg):
            with History.open(url) as h:
                assert h.store([_batch_recording(k, d) for k, d in enumerate(drives)]) == [
                    1, 2, 3, 4, 5]  # every drive and the model known from here on
                batch = [_batch_recording(k, drives[k % 5]) for k in range(3, 70)]
                batch.append(_batch_recording(40, "d0"))  # listed twice in the batch
                sent: list[str] = []
                sa.event.listen(h.engine, "before_cursor_execute",
                                lambda *a, sent=sent, **kw: sent.append(a[2].split()[2]))
                ids = h.store(batch)
                assert sorted(sent) == ["candidates", "parameters", "recordings"]
                assert ids[:2] == [None, None] and ids[-1] is None  # 3, 4 stored before
                new = [i for i in ids if i is not None]
                assert len(set(new)) == len(new) == 65  # 5 to 69
                got = {r.id: r for r in h.recordings()}
                assert len(got) == 70
                for rec, rid in zip(batch, ids, strict=True):
                    if rid is not None:
                        k = rec.samples
                        r = got[rid]
                        assert (r.content_hash, r.drive, r.samples) == (f"{k:064x}",
                                                                        drives[k % 5], k)
                        assert [(p.name, p.value) for p in r.parameters] == [
                            ("inertia.J", k), ("viscous.B", -k)]
                        assert r.candidates is not None
                        assert [c.effect for c in r.candidates] == [f"cogging{k}"]


def test_a_batch_that_rolls_back_leaves_no_id_of_a_row_it_did_not_keep(
        tmp_path: Path) -> None:
    """A batch that fails (two candidates of one rank) stores nothing, and the ids of
    the drive and model it had inserted are not kept: the next batch of that drive is
    stored, not refused for a drive row that was rolled back."""
    bad = dataclasses.replace(_batch_recording(1, "new"), candidates=(
        CandidateValue(1, "a", 0.5, -3.0, 0.1, True, False),
        CandidateValue(1, "b", 0.5, -3.0, 0.1, True, False)))
    with History.open(str(tmp_path / "s.db")) as h:
        with pytest.raises(ConfigError):
            h.store([bad])
        assert h.recordings() == []
        assert h.store([_batch_recording(2, "new")]) == [1]
        assert [r.drive for r in h.recordings()] == ["new"]


def test_the_migrations_build_the_schema_the_code_uses(tmp_path: Path) -> None:
    from alembic.autogenerate import compare_metadata
    from alembic.migration import MigrationContext

    from canrls.fleet.history import METADATA

    with History.open(tmp_path / "m.db") as h, h.engine.connect() as conn:
        diff = compare_metadata(MigrationContext.configure(conn), METADATA())
    assert diff == []


#: a migration after 0001 as SQLite runs most of them: Alembic's batch mode copies the
#: table into a new one and drops the old (SQLite alters little in place)
_RECREATE_0002 = '''"""A test's migration: a column added to recordings by copying the table."""
import sqlalchemy as sa
from alembic import op

revision = "0002"
down_revision = "0001"
branch_labels = None
depends_on = None


def upgrade() -> None:
    with op.batch_alter_table("recordings", recreate="always") as b:
        b.add_column(sa.Column("note", sa.Text, nullable=True))
'''


def _migrations_to_0002(tmp_path: Path, monkeypatch: pytest.MonkeyPatch, body: str
                        ) -> None:
    """canrls's migration scripts copied, with a 0002 of ``body`` after them."""
    import shutil

    from canrls.fleet import history as history_mod

    mig = tmp_path / "migrations"
    shutil.copytree(history_mod.MIGRATIONS, mig, ignore=shutil.ignore_patterns("__pycache__"))
    (mig / "versions" / "0002_test.py").write_text(body)
    monkeypatch.setattr(history_mod, "MIGRATIONS", mig)


def test_a_history_of_an_older_schema_is_migrated_with_nothing_lost(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A history at revision 0001 with data, opened by a canrls whose migrations go one
    further (the scripts copied, a 0002 that copies the recordings table): ``fleet
    report`` (no upgrade) refuses it naming both revisions; ``History.open`` upgrades it
    and every drive, recording, parameter and candidate is kept, the new column null."""
    from canrls.fleet.records import CandidateValue

    logs = tmp_path / "logs"
    logs.mkdir()
    cand = (CandidateValue(rank=1, effect="cogging[6]", explained=0.4, delta_bic=-30.0,
                           rms_after=1e-3, identifiable=True, suggested=True),)
    recs = [dataclasses.replace(r, id=None, candidates=cand if r.drive == "d5" else None)
            for r in pump_fleet(logs, drift=True)]
    db = tmp_path / "old.db"
    with History.open(db) as h:
        assert h.revision() == "0001"
        h.store(recs)
        before = _rows(h), [r.candidates for r in h.recordings()]
        assessed = assess(h.recordings()).to_dict()["drives"]
    _migrations_to_0002(tmp_path, monkeypatch, _RECREATE_0002)
    with pytest.raises(ConfigError, match="schema revision '0001', this canrls needs '0002'"):
        History.open(db, upgrade=False)
    with History.open(db) as h:
        assert h.revision() == "0002"
        assert (_rows(h), [r.candidates for r in h.recordings()]) == before
        assert assess(h.recordings()).to_dict()["drives"] == assessed
    con = sqlite3.connect(db)
    try:
        assert con.execute("SELECT COUNT(*), COUNT(note) FROM recordings").fetchone() == (36, 0)
        assert con.execute("SELECT COUNT(*) FROM parameters").fetchone() == (72,)
        assert con.execute("SELECT COUNT(*) FROM candidates").fetchone() == (6,)
        assert con.execute("PRAGMA foreign_key_check").fetchall() == []
    finally:
        con.close()


def test_a_migration_that_orphans_rows_is_rolled_back(tmp_path: Path,
                                                      monkeypatch: pytest.MonkeyPatch
                                                      ) -> None:
    """A 0002 that leaves parameters of a recording it deleted: refused, the history
    left at 0001 with every row."""
    logs = tmp_path / "logs"
    logs.mkdir()
    db = tmp_path / "old.db"
    with History.open(db) as h:
        h.store([dataclasses.replace(r, id=None) for r in pump_fleet(logs)])
    _migrations_to_0002(tmp_path, monkeypatch, _RECREATE_0002.replace(
        '    with op.batch_alter_table("recordings", recreate="always") as b:\n'
        '        b.add_column(sa.Column("note", sa.Text, nullable=True))\n',
        '    op.execute("DELETE FROM recordings WHERE id = 1")\n'))
    with pytest.raises(ConfigError, match=r"the migration left rows of parameters "
                                          r"pointing at rows that are not there \(1\); "):
        History.open(db)
    con = sqlite3.connect(db)
    try:
        assert con.execute("SELECT version_num FROM alembic_version").fetchone() == ("0001",)
        assert con.execute("SELECT COUNT(*) FROM recordings").fetchone() == (36,)
        assert con.execute("SELECT COUNT(*) FROM parameters").fetchone() == (36,)
    finally:
        con.close()


def test_a_newer_history_is_refused(tmp_path: Path, capsys: pytest.CaptureFixture[str]
                                    ) -> None:
    db = tmp_path / "new.db"
    History.open(db).close()
    con = sqlite3.connect(db)
    con.execute("UPDATE alembic_version SET version_num = '9999'")
    con.commit()
    con.close()
    assert main(["fleet", "report", "--db", str(db), "--json"]) == 1
    err = capsys.readouterr().err
    assert err.startswith(f"error: history {db}: ") and "'9999' is newer" in err
    assert err.count("\n") == 1


# ------------------------------------------------------------------ the command line
def test_report_html_and_json(fleet: dict[str, Any], tmp_path: Path,
                              capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "report"
    assert main(["fleet", "report", "--db", str(fleet["db"]), "--out", str(out), "--json",
                 "--figures", "2"]) == 0
    d = json.loads(capsys.readouterr().out)
    truth = fleet["truth"]
    alerted = [x["drive"] for x in d["drives"] if x["alerts"]]
    assert alerted and all(truth[a]["class"] != "healthy" for a in alerted)
    assert d["drives"][0]["score"] >= d["drives"][-1]["score"]
    page = (out / "index.html").read_text()
    assert page.count("<img src='drive-") == 2 and "spread-01.svg" in page
    assert alerted[0] in page and "τ" in page
    assert (out / "drive-0001.svg").read_bytes().startswith(b"<?xml")
    # the healthy drives: one row each in a compact table, no section of their own
    healthy = [x["drive"] for x in d["drives"] if not x["alerts"]]
    assert healthy and f"<h2>Healthy drives ({len(healthy)}, no alert)</h2>" in page
    assert page.count("<section") == 2 and all(f"id='{h}'" not in page for h in healthy)


def test_report_escapes_the_history_strings(tmp_path: Path) -> None:
    """A path with markup in it reaches the page as text."""
    from canrls.fleet.fleet_report import write_html
    from canrls.fleet.records import ParameterValue, Recording

    recs = [Recording(drive="d1", content_hash=f"{k:064x}", model_key="m" * 64,
                      model="inertia", path=f"<script>alert({k})</script>.log",
                      t_start=1.7e9 + 86400 * k, residual_rms=1e-3,
                      parameters=(ParameterValue("inertia.J", 1e-3 * (1 + (k > 4)), 1e-6),),
                      id=k) for k in range(10)]
    page = write_html(assess(recs), tmp_path / "r").read_text()
    assert "<script>alert(" not in page and "&lt;script&gt;alert(" in page


def test_report_shows_an_outlier_against_its_siblings(tmp_path: Path) -> None:
    """Six drives of one type, one with twice the inertia: its section draws the
    siblings' level, its table names the parameter and links the recordings; the
    healthy drives are rows of one table."""
    from canrls.fleet.fleet_report import _siblings, write_html

    logs = tmp_path / "logs"
    logs.mkdir()
    recs = pump_fleet(logs)
    fleet = assess(recs)
    out = fleet.drive("d5")
    assert [a.kind for a in out.alerts] == ["outlier"]
    assert sorted(_siblings(fleet, out, "inertia.J")) == sorted(
        v for d, (_, v) in fleet.spread["m" * 64]["inertia.J"].items() if d != "d5")
    page = write_html(fleet, tmp_path / "r").read_text()
    assert page.count("<section") == 1 and "id='d5'" in page
    assert "<h2>Healthy drives (5, no alert)</h2>" in page
    assert "<th>inertia.J [kg·m²]</th>" in page
    assert "<a href='../logs/d5%20%235.log'>" in page  # relative, quoted
    figure = re.search(r"<img src='(drive-\d+\.svg)' alt='([^']+)'", page)
    assert figure is not None and figure.group(2).startswith("Trends of d5: inertia.J")
    assert b"siblings" in (tmp_path / "r" / figure.group(1)).read_bytes()


def test_report_figures_draw_the_history_strings_as_text(tmp_path: Path) -> None:
    """Issue 30, 4: a unit `$a^$` (a user term's) ended `fleet report` with exit 3
    (matplotlib's mathtext parser): a drive, type, parameter and unit with `$` are now
    drawn as the characters they hold (canrls.figtext.plain)."""
    pytest.importorskip("matplotlib")
    from canrls.fleet.fleet_report import write_html
    from canrls.fleet.records import ParameterValue, Recording

    recs = [Recording(drive=f"$d{d}^$", drive_type="$t^$", content_hash=f"{d}{k:063x}",
                      model_key="m" * 64, model="user:drag", path=f"{d}-{k}.log",
                      t_start=1.7e9 + 86400 * k, residual_rms=1e-3,
                      parameters=(ParameterValue("user:drag.c", 1e-3 * (1 + (d == 0 and k > 4))
                                                 * (1 + 0.01 * d), 1e-6, unit="$a^$"),),
                      id=10 * d + k) for d in range(4) for k in range(10)]
    fleet = assess(recs)
    assert fleet.alerts  # a trend figure with the alert's message, a spread figure
    out = tmp_path / "r"
    write_html(fleet, out)
    assert sorted(p.name for p in out.glob("*.svg"))


def test_ingest_cli_in_process_with_a_pattern_and_errors(fleet: dict[str, Any], tmp_path: Path,
                                                        capsys: pytest.CaptureFixture[str]
                                                        ) -> None:
    logs = tmp_path / "logs"
    for s in _subset(fleet, ["d015"])[:3]:
        (logs / "pumps" / s.drive).mkdir(parents=True, exist_ok=True)
        (logs / "pumps" / s.drive / Path(s.path).name).write_bytes(Path(s.path).read_bytes())
    (logs / "pumps" / "d099").mkdir(parents=True)
    (logs / "pumps" / "d099" / "empty.log").write_text("")
    db = tmp_path / "p.db"
    argv = ["fleet", "ingest", str(logs / "{type}" / "{drive}" / "*.log"), "--db", str(db),
            "--workers", "0", "--quiet", *MODEL_ARGS]
    assert main(argv) == 0
    out = capsys.readouterr().out
    assert out.startswith("4 logs: 3 stored, 0 already in the history, 1 errors")
    assert "empty.log" in out
    with History.open(db) as h:
        recs = h.recordings()
    assert {r.drive_type for r in recs} == {"pumps"}
    ok = [r for r in recs if r.status == STATUS_OK]
    assert len(ok) == 3 and all(r.t_end > r.t_start > 1.7e9 for r in ok)
    assert all(r.canrls_version and r.model.startswith(FLEET_EFFECTS) for r in ok)
    key, _ = model_key(CONFIG)
    assert {r.model_key for r in recs} == {key}
    # a rerun skips them all, --retry-errors tries the error again
    assert main(argv) == 0
    assert capsys.readouterr().out.startswith("4 logs: 0 stored, 4 already")
    assert main([*argv, "--retry-errors"]) == 0
    assert capsys.readouterr().out.startswith(
        "4 logs: 0 stored, 3 already in the history, 1 errors")


def _residual_rise(logs: Path, key: str, desc: str) -> list[Any]:
    """Six pumps recorded weekly, ``d2``'s residual 30 % higher from the sixth week:
    below the default size that matters for the residual (50 %), above 20 %. Each
    recording's log is a small file whose hash it carries (a rerun holds them all)."""
    import hashlib

    from canrls.fleet.records import ParameterValue, Recording

    rng = np.random.default_rng(33)
    recs = []
    for i in range(6):
        for k in range(10):
            p = logs / f"d{i}-{k}.log"
            p.write_bytes(f"pump {i} week {k}\n".encode())
            rise = 1.3 if i == 2 and k >= 5 else 1.0
            recs.append(Recording(
                drive=f"d{i}", drive_type="pump",
                content_hash=hashlib.sha256(p.read_bytes()).hexdigest(), model_key=key,
                model=desc, path=str(p), t_start=1.7e9 + 7 * 86400 * k,
                residual_rms=1e-3 * (1 + 0.01 * rng.standard_normal()) * rise,
                parameters=(ParameterValue("inertia.J", 1e-3 * (
                    1 + 0.01 * rng.standard_normal()), 1e-6, unit="kg·m²"),)))
    return recs


def test_rank_auto_takes_the_detection_of_fleet_in_config(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
        capsys: pytest.CaptureFixture[str]) -> None:
    """``fleet ingest --rank auto --config FILE`` ranks around the residual changes that
    FILE's ``[fleet]`` table finds (as ``fleet report --config FILE`` alerts on them), not
    those of the default settings; a bad ``[fleet]`` key stops it before any log."""
    from canrls.cli import fleet as cli_fleet
    from canrls.fleet.records import CandidateValue

    logs = tmp_path / "logs"
    logs.mkdir()
    cfg = tmp_path / "plant.toml"
    cfg.write_text("[fleet]\nmin_change = { residual_rms = 0.2 }\n")
    key, desc = model_key(JobConfig(config=str(cfg), effects=FLEET_EFFECTS, kt=FLEET_KT))
    assert key == model_key(CONFIG)[0]  # [fleet] is not part of the model
    db = tmp_path / "h.db"
    with History.open(db) as h:
        h.store(_residual_rise(logs, key, desc))
    ranked: list[str] = []

    def ranker(path: str, *_: Any) -> list[Any]:  # the logs are not CAN logs
        ranked.append(Path(path).name)
        return [CandidateValue(rank=1, effect="cogging[6]", explained=0.5, delta_bic=-40.0,
                               rms_after=1e-3, identifiable=True, suggested=True)]

    monkeypatch.setattr(cli_fleet, "rank_candidates", ranker)
    argv = ["fleet", "ingest", str(logs / "{drive}-*.log"), "--db", str(db), "--workers",
            "0", "--quiet", "--rank", "auto", *MODEL_ARGS]
    assert main(argv) == 0  # the defaults: a rise of 30 % is no change that matters
    assert capsys.readouterr().out.startswith("60 logs: 0 stored, 60 already")
    assert ranked == []
    assert main([*argv, "--config", str(cfg)]) == 0
    out = capsys.readouterr().out
    assert "candidate effects ranked on 4 recordings" in out
    assert sorted(ranked) == ["d2-3.log", "d2-4.log", "d2-8.log", "d2-9.log"]
    with History.open(db) as h:
        assert sum(1 for r in h.recordings() if r.candidates) == 4
    bad = tmp_path / "bad.toml"
    bad.write_text("[fleet]\nmin_chnage = 0.2\n")
    assert main([*argv, "--config", str(bad)]) == 1
    err = capsys.readouterr().err
    assert err.startswith(f"error: {bad}: unknown key fleet.min_chnage") and \
        err.count("\n") == 1


@pytest.mark.parametrize(("argv", "message"), [
    (["fleet", "ingest", "logs/*.log"], "error: pattern 'logs/*.log': needs a {drive} field"),
    (["fleet", "ingest", "nowhere/{drive}/*.log"], "error: pattern 'nowhere/{drive}/*.log': "
                                                   "no file matches"),
    (["fleet", "ingest"], "error: fleet ingest: give a PATTERN"),
    (["fleet", "report", "--db", "x.db"], "error: fleet report: give --out DIR"),
    (["fleet", "report", "--db", "x.db", "--json"], "error: --db x.db: no such history"),
    (["fleet", "ingest", "--manifest", "m.csv", "--db", "mysql://x/y"],
     "error: history: mysql:// databases are not supported"),
])
def test_errors_are_one_line(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                             capsys: pytest.CaptureFixture[str], argv: list[str],
                             message: str) -> None:
    monkeypatch.chdir(tmp_path)
    (tmp_path / "m.csv").write_text("path,drive\n")
    assert main(argv) == 1
    err = capsys.readouterr().err
    assert err.startswith(message) and err.count("\n") == 1


@pytest.mark.parametrize(("text", "message"), [
    ("path,drive,colour\n", "line 1: unknown column 'colour'"),
    ("path\n", "line 1: no 'drive' column"),
    ("path,drive\nmissing.log,d1\n", "line 2: field 'path': 'missing.log': no such file"),
    ("path,drive,kt\nx.log,d1,-1\n", "line 2: field 'kt': '-1' must be a positive number"),
    ("path,drive\nx.log,<b>\n", "line 2: drive '<b>': must be 1 to 128 letters"),
    ("path,drive\n", "the manifest lists no log"),
])
def test_manifest_errors_name_the_line_and_field(tmp_path: Path, text: str,
                                                 message: str) -> None:
    (tmp_path / "x.log").write_text("")
    m = tmp_path / "m.csv"
    m.write_text(text)
    with pytest.raises(ConfigError) as e:
        from_manifest(m)
    assert str(e.value).startswith(f"{m}: {message}")


@pytest.mark.parametrize(("column", "cell", "message"), [
    ("effects", "warp", "--effects warp: unknown effect 'warp'"),
    ("signals", "warp", "--signal warp: expected ROLE=MESSAGE.SIGNAL"),
    ("signals", "current=Nope.Nope", "has no message 'Nope' (mapped to current"),
])
def test_a_manifest_rows_bad_override_names_the_row(
        tmp_path: Path, capsys: pytest.CaptureFixture[str], column: str, cell: str,
        message: str) -> None:
    """A manifest row's effects or signals that cannot be: the error named "--effects
    warp", a flag nobody typed, and not the manifest nor its line."""
    (tmp_path / "x.log").write_text("")
    m = tmp_path / "m.csv"
    m.write_text(f"path,drive,{column}\nx.log,d1,\nx.log,d2,{cell}\n")
    assert main(["fleet", "ingest", "--manifest", str(m), "--db", str(tmp_path / "h.db"),
                 "--workers", "0", "--quiet"]) == 1
    err = capsys.readouterr().err
    assert err.startswith(f"error: {m}: line 3: ") and message in err, err
    assert err.count("\n") == 1


def test_a_missing_dependency_disables_only_its_command(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
        capsys: pytest.CaptureFixture[str]) -> None:
    (tmp_path / "a" / "d1").mkdir(parents=True)
    (tmp_path / "a" / "d1" / "x.log").write_text("")
    monkeypatch.setitem(sys.modules, "distributed", None)
    assert main(["fleet", "ingest", str(tmp_path / "a" / "{drive}" / "*.log"), "--db",
                 str(tmp_path / "h.db")]) == 1
    err = capsys.readouterr().err
    assert err.startswith("error: ingesting on Dask needs dask[distributed]") and \
        "pip install 'canrls[fleet]'" in err and "--workers 0" in err
    assert main(["sim", "--out", str(tmp_path / "s.log"), "--duration", "0.1"]) == 0


def test_pattern_takes_drive_and_type(tmp_path: Path) -> None:
    for ty, d in (("servo", "a1"), ("servo", "a2"), ("pump", "b1")):
        (tmp_path / ty / d).mkdir(parents=True)
        (tmp_path / ty / d / "r1.log").write_text("x")
        (tmp_path / ty / d / "notes.txt").write_text("x")
    got = from_pattern(str(tmp_path / "{type}" / "{drive}" / "*.log"))
    assert [(s.drive_type, s.drive, Path(s.path).name) for s in got] == [
        ("pump", "b1", "r1.log"), ("servo", "a1", "r1.log"), ("servo", "a2", "r1.log")]


def test_sim_fleet_writes_logs_manifest_and_truth(tmp_path: Path,
                                                  capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "f"
    assert main(["sim", "fleet", "--drives", "3", "--recordings", "2", "--duration", "3",
                 "--out", str(out), "--seed", "5"]) == 0
    out_err = capsys.readouterr()
    # the summary on stdout, as plain canrls sim's: its first line the answer
    assert out_err.out.startswith(f"canrls sim fleet: wrote 6 logs of 3 drives (3 s each, "
                                  f"seed 5) to {out}") and out_err.err == ""
    truth = json.loads((out / "truth.json").read_text())
    srcs = from_manifest(out / "manifest.csv")
    assert len(srcs) == 6 and {s.drive for s in srcs} == set(truth["drives"])
    for s in srcs:
        t = truth["drives"][s.drive]
        assert s.drive_type == t["type"] and Path(s.path).parent.parent.name == t["type"]
    assert [Path(s.path).name for s in srcs[:2]] == ["d001-01.log", "d001-02.log"]
    # the same seed, the same bytes
    again = tmp_path / "g"
    assert main(["sim", "fleet", "--drives", "3", "--recordings", "2", "--duration", "3",
                 "--out", str(again), "--seed", "5"]) == 0
    assert (again / srcs[0].path.split("/f/", 1)[1]).read_bytes() == \
        Path(srcs[0].path).read_bytes()
    assert main(["sim", "fleet", "--out", str(tmp_path / "h"), "--effects", "inertia"]) == 1
    assert "--effects: not an option of 'canrls sim fleet'" in capsys.readouterr().err


# ------------------------------------------------------------------ the daemon's history
def test_the_daemon_appends_to_the_history_it_shares_with_ingest(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    db = tmp_path / "live.db"
    conf = tmp_path / "canrls.toml"
    conf.write_text(f'[model]\neffects = ["inertia", "viscous", "coulomb", "offset"]\n'
                    f'kt = {FLEET_KT}\n'
                    f'[history]\nurl = "{db}"\ndrive = "axis-7"\ntype = "servo-s"\n'
                    f'interval = 0.3\n')
    assert main(["run", "-C", str(conf), "-i", "canrls-sim", "-c", "fleet-live",
                 "--bus-kwargs", "effects=inertia,viscous,coulomb,offset", "seed=2",
                 "realtime=False", "start_time=0", "--duration", "2",
                 "--publish-interval", "0.05"]) == 0
    capsys.readouterr()
    with History.open(db) as h:
        recs = h.recordings()
    assert len(recs) >= 3 and {r.source for r in recs} == {"live"}
    assert len({r.session for r in recs}) == 1 and {r.drive for r in recs} == {"axis-7"}
    last = max(recs, key=lambda r: r.t_end)
    assert last.samples > 1000 and last.parameter("inertia.J").value == pytest.approx(
        2e-4, rel=0.05)
    # the same model key as an offline ingest with the same configuration
    key, _ = model_key(JobConfig(config=str(conf)))
    assert {r.model_key for r in recs} == {key}
    fa = assess(recs)
    assert fa.drive("axis-7").recordings == 1  # one session counts once


def test_history_settings_errors() -> None:
    from canrls.core.errors import ConfigError
    from canrls.fleet.live_appender import HistorySettings

    with pytest.raises(ConfigError, match=r"c.toml: history.drive = None: must be"):
        HistorySettings.from_table({"url": "x.db"}, "c.toml")
    with pytest.raises(ConfigError, match=r"c.toml: history.interval = 0: must be"):
        HistorySettings.from_table({"url": "x.db", "drive": "a", "interval": 0}, "c.toml")
    with pytest.raises(ConfigError, match=r"c.toml: history.colour = 1: unknown key"):
        HistorySettings.from_table({"url": "x.db", "drive": "a", "colour": 1}, "c.toml")


# -- the history's URL: one parse -------------------------------------------------------
@pytest.mark.parametrize("text, url, path", [
    ("k.db", None, "k.db"),
    ("sqlite:///k.db", "sqlite:///k.db", "k.db"),
    ("sqlite:////var/h/k.db", "sqlite:////var/h/k.db", "/var/h/k.db"),
    ("sqlite:///k.db?timeout=5", "sqlite:///k.db?timeout=5", "k.db"),
    ("postgresql://u:secret@db/plant", "postgresql+psycopg://u:secret@db/plant", None),
    ("postgres://u@db/plant", "postgresql+psycopg://u@db/plant", None),
])
def test_a_history_url_is_parsed_once_into_its_parts(text: str, url: str | None,
                                                      path: str | None) -> None:
    where = HistoryURL.parse(text)
    if url is None:  # a plain path: SQLite, made absolute
        assert where.sqlite_path == Path(text).absolute()
        assert where.url == f"sqlite:///{Path(text).absolute()}"
    else:
        assert where.url == url
        assert where.sqlite_path == (None if path is None else Path(path))
    assert "secret" not in where.shown


@pytest.mark.parametrize("text", ["", "mysql://u@db/x"])
def test_a_history_url_of_another_kind_is_refused(text: str) -> None:
    with pytest.raises(ConfigError, match="history: "):
        HistoryURL.parse(text)


@pytest.mark.parametrize("text", ["sqlite://", "sqlite:///:memory:",
                                  "sqlite:///file:x?mode=memory&uri=true"])
def test_the_parse_refuses_an_in_memory_history(text: str) -> None:
    with pytest.raises(ConfigError, match=r"an in-memory database keeps nothing"):
        HistoryURL.parse(text)


def test_messages_name_the_history_as_given_without_its_secrets() -> None:
    where = HistoryURL.parse("postgresql://alice:s3cret@db/plant?sslpassword=x2")
    assert where.url == "postgresql+psycopg://alice:s3cret@db/plant?sslpassword=x2"
    assert where.shown == "postgresql://alice:***@db/plant?sslpassword=***"
    assert HistoryURL.parse("k.db").shown == "k.db"  # as typed, not made absolute


def test_every_reader_of_a_history_url_asks_the_one_parser(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
        capsys: pytest.CaptureFixture[str]) -> None:
    """History.open (the daemon's [history], fleet ingest) and fleet report's "no such
    history" take the database file from HistoryURL.parse, not from the text again: a
    query after the file (``?timeout=5``, the driver's) is no part of the file."""
    asked: list[str] = []
    parse = HistoryURL.parse.__func__  # type: ignore[attr-defined]

    def spy(cls: type[HistoryURL], text: Any) -> HistoryURL:
        asked.append(str(text))
        return parse(cls, text)

    monkeypatch.setattr(HistoryURL, "parse", classmethod(spy))
    db = tmp_path / "k.db"
    History.open(f"sqlite:///{db}?timeout=5").close()
    assert asked == [f"sqlite:///{db}?timeout=5"] and db.is_file()
    assert main(["fleet", "report", "--db", f"sqlite:///{db}?timeout=5", "--json"]) == 0
    assert "no such history" not in capsys.readouterr().err
    assert asked[1:] and set(asked[1:]) == {f"sqlite:///{db}?timeout=5"}
    with pytest.raises(ConfigError, match="directory .* does not exist"):
        History.open(f"sqlite:///{tmp_path}/no/k.db?timeout=5")


def test_ingest_of_a_machine_stores_one_recording_per_axis(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """Logs of a two-axis machine with --axes: each log gives one recording per axis,
    under the drive MACHINE.AXIS, with the parameters canrls fit --axis finds."""
    logs = tmp_path / "logs" / "robot1"
    logs.mkdir(parents=True)
    for seed in (1, 2):
        assert main(["sim", "--out", str(logs / f"r{seed}.log"), "--duration", "2",
                     "--axes", "2", "--seed", str(seed)]) == 0
    axes = ["--axes", "offset:0,0x10", "--kt", "0.1", "-e", "inertia,viscous,coulomb"]
    db = tmp_path / "m.db"
    argv = ["fleet", "ingest", str(tmp_path / "logs" / "{drive}" / "*.log"), "--db", str(db),
            "--workers", "0", "--quiet", *axes]
    capsys.readouterr()
    assert main(argv) == 0
    assert capsys.readouterr().out.startswith(
        "2 logs (4 recordings, one per axis): 4 stored, 0 already in the history, 0 errors")
    with History.open(db) as h:
        recs = h.recordings()
    assert sorted((r.drive, Path(r.path).name) for r in recs) == [
        ("robot1.axis1", "r1.log"), ("robot1.axis1", "r2.log"),
        ("robot1.axis2", "r1.log"), ("robot1.axis2", "r2.log")]
    assert all(r.status == STATUS_OK for r in recs)
    assert len({r.model_key for r in recs}) == 2  # each axis its own IDs: its own model
    for r in recs:
        axis = r.drive.split(".")[1]
        capsys.readouterr()
        assert main(["fit", r.path, *axes, "--axis", axis, "--json"]) == 0
        fit = json.loads(capsys.readouterr().out)["parameters"]
        assert {p.name: p.value for p in r.parameters} == {
            n: v["value"] for n, v in fit.items()}
        assert r.frames == 8000  # the whole log read, the other axis's frames foreign
    # --axis NAME: that axis only; a rerun finds every recording there
    assert main([*argv, "--axis", "axis2"]) == 0
    assert capsys.readouterr().out.startswith("2 logs: 0 stored, 2 already in the history")
    assert main(argv) == 0
    assert capsys.readouterr().out.startswith(
        "2 logs (4 recordings, one per axis): 0 stored, 4 already in the history")


def test_one_axes_table_of_the_dbcs_own_ids_keeps_the_model_key(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """A drive's configuration given one [[axes]] table whose rule moves no ID (or the
    short form --axes offset:0) fits the same model: its logs are not fitted again under
    another key."""
    logs = tmp_path / "logs" / "press1"
    logs.mkdir(parents=True)
    assert main(["sim", "--out", str(logs / "r1.log"), "--duration", "2", "--seed", "1"]) == 0
    plain = tmp_path / "plain.toml"
    plain.write_text('[model]\nkt = 0.1\n')
    table = tmp_path / "table.toml"
    table.write_text('[model]\nkt = 0.1\n[[axes]]\nname = "a"\nids = "offset:0"\n')
    db = tmp_path / "k.db"
    base = ["fleet", "ingest", str(tmp_path / "logs" / "{drive}" / "*.log"), "--db", str(db),
            "--workers", "0", "--quiet"]
    capsys.readouterr()
    assert main([*base, "--config", str(plain)]) == 0
    assert capsys.readouterr().out.startswith("1 logs: 1 stored")
    for extra in (["--config", str(table)], ["--config", str(plain), "--axes", "offset:0"]):
        assert main([*base, *extra]) == 0
        out = capsys.readouterr().out
        assert "0 stored, 1 already in the history" in out, (extra, out)
    with History.open(db) as h:
        assert len(h.models()) == 1
    # a rule that moves the IDs is another model (another drive's frames)
    assert main([*base, "--config", str(plain), "--axes", "offset:0x20"]) == 0
    capsys.readouterr()
    with History.open(db) as h:
        assert len(h.models()) == 2
